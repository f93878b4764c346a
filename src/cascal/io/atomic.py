"""Atomic file writes: a temporary file in the target folder, then a rename; standard
output (``-``, or a path to it) gets the finished content where it stands."""

from __future__ import annotations

import os
import shutil
import stat
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

__all__ = ["STDOUT", "atomic_write", "is_stdout", "save_figure", "write_text"]

#: The output name of standard output.
STDOUT = "-"


def _read_umask() -> int:
    mask = os.umask(0)  # the only portable way to read it: read once, at import
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def is_stdout(path: object) -> bool:
    """Whether an output ``path`` is this process's standard output: ``-``, or a path to
    the file, pipe or terminal it is (``/dev/stdout``)."""
    if path is None:
        return False
    if str(path) == STDOUT:
        return True
    out = sys.__stdout__
    try:
        a, b = os.stat(path), os.fstat(out.fileno())  # type: ignore[arg-type, union-attr]
    except (OSError, ValueError, AttributeError, TypeError):
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Call ``write(tmp_path)`` and rename the result onto ``path``; nothing half-written.

    A symbolic link stays and its target is replaced; a replaced file keeps its permission
    bits (a new one gets the usual ones); a device or FIFO (a named pipe) is written in
    place, since renaming a file onto it would replace it. An OSError names ``path``
    (a full disk's error names no file). Standard output
    (:func:`is_stdout`) gets the finished content copied to it where it stands, so a file
    it appends to keeps what it held.

    Args:
        path: Destination file; its folder is created if missing.
        write: Writes the whole content to the temporary path it is given.
    """
    if is_stdout(path):
        return _to_stdout(path, write)
    dest = Path(path)
    try:
        mode = os.stat(dest).st_mode  # through links
    except OSError:
        mode = None
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        try:  # a device or a FIFO (/dev/stdout, a pipe): written in place
            write(str(dest))
        except OSError as exc:
            raise _naming(exc, dest, (str(dest), None)) from None
        return dest
    keep = stat.S_IMODE(mode) if mode is not None and stat.S_ISREG(mode) else None
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
        os.chmod(tmp, 0o666 & ~_UMASK if keep is None else keep)  # mkstemp makes 0600
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())  # the content is on disk before the name points at it
        os.replace(tmp, dest)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise _naming(exc, dest, (tmp, str(dest), None)) from None
        raise
    return dest


def _naming(exc: OSError, dest: Path, names: tuple) -> OSError:
    """``exc`` as "cannot write DEST: reason" where it concerns ``dest`` (its file name is
    one of ``names``, or none) and has an errno; else ``exc`` itself (a message-only
    error keeps its text)."""
    if exc.errno is not None and exc.filename in names:
        return OSError(exc.errno, f"cannot write {dest}: {exc.strerror}")
    return exc


def _to_stdout(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    out = sys.__stdout__
    if out is None:
        raise OSError(9, "there is no standard output to write to")
    with tempfile.TemporaryDirectory() as folder:
        tmp = os.path.join(folder, "output")
        write(tmp)
        out.flush()
        with open(tmp, "rb") as fh:
            shutil.copyfileobj(fh, out.buffer)
        out.buffer.flush()
    return Path("/dev/stdout" if str(path) == STDOUT else path)  # as messages name it


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
