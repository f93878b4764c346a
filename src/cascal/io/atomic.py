"""Atomic file writes: a temporary file in the target folder, then a rename; standard
output (``-``, or a path to it) gets the finished content where it stands. Inside
:func:`together`, the renames wait until every write of the block has succeeded."""

from __future__ import annotations

import os
import shutil
import stat
import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any, NoReturn

__all__ = ["STDOUT", "atomic_write", "is_stdout", "save_figure", "together", "write_text"]

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


#: The pending (to a stream?, commit, discard) of this thread's :func:`together` block, or
#: None outside one.
_PENDING: ContextVar[list[tuple[bool, Callable[[], None], Callable[[], None]]] | None] = ContextVar(
    "cascal_pending_writes", default=None
)


@contextmanager
def together() -> Iterator[None]:
    """Make the writes of the block (:func:`atomic_write`) one: each is finished in a
    temporary file as the block runs; when it ends without an error, the contents for
    standard output or a device are copied there first (they can still fail), then the
    files are renamed onto their names. After an error in the block, or in a copy, no file
    is replaced: each keeps its old content. A block inside another joins the outer one
    (its writes are dropped if it fails, and committed with the outer block's otherwise)."""
    outer = _PENDING.get()
    if outer is not None:  # nested: the outer block commits, unless this one fails
        mark = len(outer)
        try:
            yield
        except BaseException:
            for _, _, discard in outer[mark:]:
                discard()
            del outer[mark:]
            raise
        return
    staged: list[tuple[bool, Callable[[], None], Callable[[], None]]] = []
    token = _PENDING.set(staged)
    try:
        yield
    except BaseException:
        for _, _, discard in staged:
            discard()
        raise
    finally:
        _PENDING.reset(token)
    ordered = [e for e in staged if e[0]] + [e for e in staged if not e[0]]  # streams first
    for i, (_, commit, _) in enumerate(ordered):
        try:
            commit()
        except BaseException:
            for _, _, discard in ordered[i + 1 :]:
                discard()
            raise


def _stage_stream(write: Callable[[str], None], deliver: Callable[[Any], None]) -> None:
    """Inside :func:`together`: ``write`` the content to a private temporary file now, and
    ``deliver(file)`` it (to standard output or a device) at the commit."""
    fd, tmp = tempfile.mkstemp(prefix=".cascal-", suffix=".tmp")
    os.close(fd)
    try:
        write(tmp)
    except BaseException:
        _discard(tmp)
        raise

    def commit() -> None:
        try:
            with open(tmp, "rb") as fh:
                deliver(fh)
        finally:
            _discard(tmp)

    _PENDING.get().append((True, commit, lambda: _discard(tmp)))  # type: ignore[union-attr]


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
    pending = _PENDING.get()
    if is_stdout(path):
        if pending is not None:
            _stage_stream(write, lambda fh: _to_stdout(path, lambda tmp: _copy_to(fh, tmp)))
            return Path("/dev/stdout" if str(path) == STDOUT else path)
        return _to_stdout(path, write)
    dest = Path(path)
    try:
        mode = os.stat(dest).st_mode  # through links
    except OSError:
        mode = None
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):

        def in_place(target: Callable[[str], None]) -> None:  # a device or a FIFO
            try:
                target(str(dest))
            except OSError as exc:
                raise _naming(exc, dest, (str(dest), None)) from None

        if pending is not None:
            _stage_stream(write, lambda fh: in_place(lambda d: _copy_to(fh, d)))
        else:
            in_place(write)
        return dest
    keep = stat.S_IMODE(mode) if mode is not None and stat.S_ISREG(mode) else None
    if dest.is_symlink():  # replace the file the link points at, and keep the link
        dest = Path(os.path.realpath(dest))
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
        # (a review: a name of 242 to 255 bytes made the temporary's too long, after the
        # work; such a name's temporary is named after its first 100 characters)
        prefix = f".{dest.name[:100]}." if len(os.fsencode(dest.name)) > 200 else f".{dest.name}."
        fd, tmp = tempfile.mkstemp(prefix=prefix, suffix=".tmp", dir=dest.parent)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot write {dest}: {exc.strerror}") from None
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK if keep is None else keep)  # mkstemp makes 0600
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())  # the content is on disk before the name points at it
    except BaseException as exc:
        _fail(exc, tmp, dest)
    if pending is not None:
        pending.append((False, lambda: _replace(tmp, dest), lambda: _discard(tmp)))
    else:
        _replace(tmp, dest)
    return dest


def _replace(tmp: str, dest: Path) -> None:
    try:
        os.replace(tmp, dest)
    except BaseException as exc:
        _fail(exc, tmp, dest)


def _fail(exc: BaseException, tmp: str, dest: Path) -> NoReturn:
    """Remove the temporary ``tmp`` and raise ``exc``, an OSError naming ``dest``."""
    _discard(tmp)
    if isinstance(exc, OSError):
        raise _naming(exc, dest, (tmp, str(dest), None)) from None
    raise exc


def _copy_to(fh: Any, path: str) -> None:
    """Copy the open file ``fh`` to ``path`` (written from its start)."""
    with open(path, "wb") as out:
        shutil.copyfileobj(fh, out)


def _discard(tmp: str) -> None:
    if os.path.exists(tmp):
        os.unlink(tmp)


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
    """Save a matplotlib figure atomically; the format follows the file suffix. SVG and PDF
    files carry no date and fixed ids: the same figure gives the same bytes."""
    import matplotlib

    fmt = Path(path).suffix.lstrip(".").lower() or "png"
    if fmt in ("svg", "pdf"):
        kwargs.setdefault("metadata", {"Date" if fmt == "svg" else "CreationDate": None})

    def _write(tmp: str) -> None:
        with matplotlib.rc_context({"svg.hashsalt": "cascal"}):
            fig.savefig(tmp, format=fmt, **kwargs)

    return atomic_write(path, _write)
