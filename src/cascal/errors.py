"""Exception types raised by cascal: one root, typed leaves that say what went wrong."""

from __future__ import annotations

__all__ = [
    "CascalError",
    "CascalWarning",
    "DataWarning",
    "InputError",
    "JitterWarning",
    "ModelFileError",
    "NumericalError",
    "WorkerError",
]


class CascalError(Exception):
    """Root of every error cascal raises on purpose."""


class InputError(CascalError, ValueError):
    """Bad input data: names the source (file), row and column where known.

    Args:
        message: What was expected and what was got.
        file: Path of the file the data came from, if any.
        row: 1-based row number in that file (header is row 1), if known.
        column: Column name, if known.
    """

    def __init__(
        self,
        message: str,
        *,
        file: str | None = None,
        row: int | None = None,
        column: str | None = None,
    ) -> None:
        self.file = file
        self.row = row
        self.column = column
        self.detail = message
        where = []
        if file is not None:
            where.append(str(file))
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column {column!r}")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {message}" if prefix else message)


class NumericalError(CascalError, ArithmeticError):
    """A computation could not be carried out stably, with a remedy in the message."""


class ModelFileError(CascalError):
    """A model file is missing, corrupt, edited, or of an unsupported schema version."""


class WorkerError(CascalError):
    """The executor lost its workers or its scheduler; work finished before is kept."""


class CascalWarning(Warning):
    """Root of every warning cascal gives on purpose (the CLI prints them as one line)."""


class JitterWarning(CascalWarning, RuntimeWarning):
    """A matrix needed jitter on its diagonal to factorise: the result is the jittered one's."""


class DataWarning(CascalWarning, UserWarning):
    """Input data read, but in a way the user should check (names the file and rows)."""
