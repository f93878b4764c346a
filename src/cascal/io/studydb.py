"""SQLite storage of a Monte Carlo study: one row per finished trial, committed as it lands.

A folder holds one study. Its configuration is stamped into the database on creation and
compared on every reopen, so a folder is never silently reused for other settings.
"""

from __future__ import annotations

import errno
import json
import math
import os
import sqlite3
from collections.abc import Iterable
from pathlib import Path

from .._version import __version__
from ..errors import InputError
from ..montecarlo import TrialResult

__all__ = ["DB_NAME", "StudyDB"]

DB_NAME = "study.sqlite"
_SCHEMA = 1


class StudyDB:
    """The trials of one study in ``folder/study.sqlite``.

    Args:
        folder: Output folder (created if missing).
        config: The study's configuration as a JSON-able dict. Every trial depends on it and
            on its index alone, so the trial count is not part of it: a study can grow.

    Raises:
        InputError: The folder holds a study with another configuration, or its
            ``study.sqlite`` is not a readable study of this schema (nothing is written
            to it then), or is in use by another process: a folder takes one open
            StudyDB at a time (an advisory lock on the folder, held until :meth:`close`
            or the process ends), so two runs do not compute the same pending trials.
    """

    def __init__(self, folder: str | Path, config: dict) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.path = self.folder / DB_NAME
        self.methods = list(config["methods"])
        if self.path.is_dir():
            raise self._refuse("is a folder, not a study database")
        if self.path.exists() and not self.path.is_file():  # (through links)
            raise self._refuse("is not a regular file (a device or a pipe), not a study database")
        self._lock = _lock_folder(self.folder)
        try:
            self.con = sqlite3.connect(self.path)
        except sqlite3.Error as exc:
            self._unlock()
            raise self._unreadable(exc) from None
        try:
            self._open(config)
        except sqlite3.DatabaseError as exc:
            self.close()
            raise self._unreadable(exc) from None
        except BaseException:
            self.close()
            raise

    def _open(self, config: dict) -> None:
        """Check what the file holds before writing to it; create the tables if it is new:
        one transaction holding the write lock, so that two runs starting together on a
        new folder do not both create it, and a run killed meanwhile leaves no half."""
        self.con.execute("BEGIN IMMEDIATE")
        try:
            self._check_or_create(config)
            self.con.commit()
        except BaseException:
            self.con.rollback()
            raise
        self.con.execute("PRAGMA journal_mode=WAL")
        self.con.execute("PRAGMA synchronous=NORMAL")

    def _check_or_create(self, config: dict) -> None:
        tables = {
            r[0] for r in self.con.execute("SELECT name FROM sqlite_master WHERE type='table'")
        }
        if tables and tables != {"meta", "trials"}:
            raise self._refuse(f"holds the tables {sorted(tables)}, not a cascal study")
        wanted = json.dumps(config, sort_keys=True)
        if tables:
            meta = dict(self.con.execute("SELECT key, value FROM meta").fetchall())
            if meta.get("schema") != str(_SCHEMA):
                raise self._refuse(
                    f"has study schema {meta.get('schema')!r}; this cascal reads schema {_SCHEMA}"
                )
            if "config" not in meta:
                raise self._refuse("has no configuration")
            try:
                stored = _identity(meta["config"])
            except (ValueError, TypeError, AttributeError):
                raise self._refuse(f"has an unreadable configuration {meta['config']!r}") from None
            if stored != _identity(wanted):
                raise self._refuse(
                    f"holds a study with configuration {meta['config']}, not {wanted}",
                    "rerun with the same options to resume it, or choose another --out folder",
                )
            names = [r[1] for r in self.con.execute("PRAGMA table_info(trials)")]
            expected = ["idx", *(f"j_{m}" for m in self.methods), "redraws", "fits", "seconds"]
            if names != expected:
                raise self._refuse(f"has trial columns {names}, expected {expected}")
            return
        cols = ", ".join(f"j_{m} REAL NOT NULL" for m in self.methods)
        self.con.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
        self.con.execute(
            f"CREATE TABLE trials (idx INTEGER PRIMARY KEY, {cols}, "
            "redraws INTEGER NOT NULL, fits TEXT NOT NULL, seconds TEXT NOT NULL)"
        )
        self.con.execute("INSERT INTO meta VALUES ('config', ?)", (wanted,))
        self.con.execute("INSERT INTO meta VALUES ('schema', ?)", (str(_SCHEMA),))
        self.con.execute("INSERT INTO meta VALUES ('cascal', ?)", (__version__,))

    def _refuse(self, problem: str, hint: str = "choose another --out folder") -> InputError:
        return InputError(f"{self.path} {problem}; {hint}")

    def _unreadable(self, exc: sqlite3.Error) -> Exception:
        if "disk is full" in str(exc) or "disk I/O error" in str(exc):  # not the file's fault
            code = errno.ENOSPC if "full" in str(exc) else errno.EIO
            return OSError(code, f"cannot write {self.path}: {exc}")
        if "locked" in str(exc):
            return InputError(f"{self.path} is in use by another study process ({exc})")
        if "readonly" in str(exc) or "unable to open" in str(exc):
            return InputError(f"{self.path} cannot be opened for writing ({exc})")
        return self._refuse(f"is not a readable cascal study database ({exc})")

    def done(self) -> set[int]:
        """Indices of the trials already stored."""
        try:
            done = [r[0] for r in self.con.execute("SELECT idx FROM trials")]
        except sqlite3.DatabaseError as exc:
            raise self._unreadable(exc) from None
        for i in done:
            if not (type(i) is int and i >= 0):
                raise self._refuse(
                    f"has an unreadable record of trial {i!r} (an index must be a whole "
                    "number >= 0)"
                )
        return set(done)

    def add(self, results: Iterable[TrialResult]) -> None:
        """Store finished trials in one transaction (all or none); a stored index is kept."""
        q = ", ".join("?" * (len(self.methods) + 4))
        rows = [
            (
                r.index,
                *(r.cost[m] for m in self.methods),
                r.redraws,
                json.dumps(r.fits, sort_keys=True),
                json.dumps(r.seconds, sort_keys=True),
            )
            for r in results
        ]
        try:
            with self.con:
                self.con.executemany(f"INSERT OR IGNORE INTO trials VALUES ({q})", rows)
        except sqlite3.DatabaseError as exc:
            raise self._unreadable(exc) from None

    def results(self) -> list[TrialResult]:
        """Every stored trial, ordered by index."""
        cols = ", ".join(f"j_{m}" for m in self.methods)
        query = f"SELECT idx, {cols}, redraws, fits, seconds FROM trials ORDER BY idx"
        out = []
        try:
            rows = self.con.execute(query).fetchall()
        except sqlite3.DatabaseError as exc:
            raise self._unreadable(exc) from None
        for row in rows:
            try:
                out.append(self._record(row))
            except (ValueError, TypeError) as exc:
                raise self._refuse(f"has an unreadable record of trial {row[0]} ({exc})") from None
        return out

    def _record(self, row: tuple) -> TrialResult:
        """A stored row as a trial; ValueError where a field is not what a trial holds."""
        k = len(self.methods)
        index, redraws = row[0], row[1 + k]
        if not (type(index) is int and index >= 0 and type(redraws) is int and redraws >= 0):
            raise ValueError("expected whole numbers >= 0 for the index and the redraws")
        cost = {m: float(v) for m, v in zip(self.methods, row[1 : 1 + k], strict=True)}
        fits, seconds = json.loads(row[2 + k]), json.loads(row[3 + k])
        numbers = list(cost.values()) + list(_values(seconds))
        for stage in _values(fits):
            numbers += _values(stage)
        if not all(type(v) in (int, float) and math.isfinite(v) for v in numbers):
            raise ValueError("expected finite numbers for J, the fits and the timings")
        return TrialResult(index, cost, redraws, fits, seconds)

    def close(self) -> None:
        self.con.close()
        self._unlock()

    def _unlock(self) -> None:
        if self._lock is not None:
            os.close(self._lock)  # (closing the descriptor releases its lock)
            self._lock = None


def _lock_folder(folder: Path) -> int | None:
    """A descriptor of ``folder`` holding an exclusive advisory lock (``flock``), or None
    where the system has none (Windows). InputError if another process holds it."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on POSIX
        return None
    fd = os.open(folder, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise InputError(
            f"{folder} is in use by another cascal study run; a study folder takes one run "
            "at a time: wait for that run to end (it stores every trial, so rerunning then "
            "resumes), or choose another --out folder"
        ) from None
    except OSError:  # a file system without locks: run unlocked, as before
        os.close(fd)
        return None
    return fd


def _values(obj: object) -> list:
    """The values of a JSON object; ValueError for anything else."""
    if not isinstance(obj, dict):
        raise ValueError(f"expected a JSON object, got {type(obj).__name__}")
    return list(obj.values())


def _identity(config_json: str) -> dict:
    """The part of a stored configuration that fixes every trial's numbers."""
    config = json.loads(config_json)
    config.pop("trials", None)  # stamped by cascal 0.1.0 development versions
    return config
