"""Atomic file writes: a temporary file in the target folder, then a rename."""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path

__all__ = ["atomic_write", "save_figure", "write_text"]


def _read_umask() -> int:
    mask = os.umask(0)  # the only portable way to read it: read once, at import
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Call ``write(tmp_path)`` and rename the result onto ``path``; nothing half-written.

    A symbolic link stays and its target is replaced; a device or FIFO (``/dev/stdout``, a
    named pipe) is written in place, since renaming a file onto it would replace it.

    Args:
        path: Destination file; its folder is created if missing.
        write: Writes the whole content to the temporary path it is given.
    """
    dest = Path(path)
    try:
        mode = os.stat(dest).st_mode  # through links
    except OSError:
        mode = None
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        write(str(dest))  # a device or a FIFO (/dev/stdout, a pipe): written in place
        return dest
    if dest.is_symlink():  # replace the file the link points at, and keep the link
        dest = Path(os.path.realpath(dest))
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot write {dest}: {exc.strerror}") from None
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the usual permissions
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())  # the content is on disk before the name points at it
        os.replace(tmp, dest)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and exc.filename in (tmp, str(dest)):
            raise OSError(exc.errno, f"cannot write {dest}: {exc.strerror}") from None
        raise
    return dest


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""

    def _write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(text)

    return atomic_write(path, _write)


def save_figure(fig, path: str | os.PathLike, **kwargs) -> Path:
    """Save a matplotlib figure atomically; the format follows the file suffix."""
    fmt = Path(path).suffix.lstrip(".") or "png"
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format=fmt, **kwargs))
