"""SQLite storage of a Monte Carlo study: one row per finished trial, committed as it lands.

A folder holds one study. Its configuration is stamped into the database on creation and
compared on every reopen, so a folder is never silently reused for other settings.
"""

from __future__ import annotations

import json
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
        InputError: The folder holds a study with another configuration.
    """

    def __init__(self, folder: str | Path, config: dict) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.path = self.folder / DB_NAME
        self.methods = list(config["methods"])
        self.con = sqlite3.connect(self.path)
        self.con.execute("PRAGMA journal_mode=WAL")
        self.con.execute("PRAGMA synchronous=NORMAL")
        cols = ", ".join(f"j_{m} REAL NOT NULL" for m in self.methods)
        with self.con:
            self.con.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT)")
            self.con.execute(
                f"CREATE TABLE IF NOT EXISTS trials (idx INTEGER PRIMARY KEY, {cols}, "
                "redraws INTEGER NOT NULL, fits TEXT NOT NULL, seconds TEXT NOT NULL)"
            )
            row = self.con.execute("SELECT value FROM meta WHERE key='config'").fetchone()
            wanted = json.dumps(config, sort_keys=True)
            if row is None:
                self.con.execute("INSERT INTO meta VALUES ('config', ?)", (wanted,))
                self.con.execute("INSERT INTO meta VALUES ('schema', ?)", (str(_SCHEMA),))
                self.con.execute("INSERT INTO meta VALUES ('cascal', ?)", (__version__,))
        if row is not None and _identity(row[0]) != _identity(wanted):
            self.con.close()
            raise InputError(
                f"{self.path} holds a study with configuration {row[0]}, not {wanted}; "
                "rerun with the same options to resume it, or choose another --out folder"
            )

    def done(self) -> set[int]:
        """Indices of the trials already stored."""
        return {r[0] for r in self.con.execute("SELECT idx FROM trials")}

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
        with self.con:
            self.con.executemany(f"INSERT OR IGNORE INTO trials VALUES ({q})", rows)

    def results(self) -> list[TrialResult]:
        """Every stored trial, ordered by index."""
        cols = ", ".join(f"j_{m}" for m in self.methods)
        out = []
        for row in self.con.execute(
            f"SELECT idx, {cols}, redraws, fits, seconds FROM trials ORDER BY idx"
        ):
            k = len(self.methods)
            cost = dict(zip(self.methods, row[1 : 1 + k], strict=True))
            out.append(
                TrialResult(
                    row[0], cost, row[1 + k], json.loads(row[2 + k]), json.loads(row[3 + k])
                )
            )
        return out

    def close(self) -> None:
        self.con.close()


def _identity(config_json: str) -> dict:
    """The part of a stored configuration that fixes every trial's numbers."""
    config = json.loads(config_json)
    config.pop("trials", None)  # stamped by cascal 0.1.0 development versions
    return config
