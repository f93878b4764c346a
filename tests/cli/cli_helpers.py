"""Helpers of the workflow tests: run the installed ``cascal`` command, write demo files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from cascal.demo import DemoCase
from cascal.io.csvout import auto_decimals, write_columns

__all__ = ["run_cascal", "write_case"]

_SCRIPT = Path(sys.executable).with_name("cascal")


def run_cascal(*args: object, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run the installed ``cascal`` script (or ``python -m cascal.cli``) and capture it."""
    cmd = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "cascal.cli"]
    return subprocess.run(
        [*cmd, *map(str, args)], capture_output=True, text=True, timeout=timeout, check=False
    )


def write_case(case: DemoCase, folder: Path) -> tuple[list[Path], Path]:
    """Write a demo case's stage files and readings (column ``reading``) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for st in case.stages:
        path = folder / st.file
        cols = dict(zip(st.columns, (st.x, st.y), strict=True))
        write_columns(path, cols, decimals=auto_decimals([st.x, st.y]))
        files.append(path)
    readings = folder / "readings.csv"
    write_columns(readings, {"reading": case.readings}, decimals=14)
    return files, readings
