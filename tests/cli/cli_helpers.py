"""Helpers of the workflow tests: run the installed ``cascal`` command, write demo files."""

from __future__ import annotations

import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from cascal.demo import DemoCase
from cascal.io.csvout import auto_decimals, write_columns

__all__ = [
    "assert_refused",
    "device_folder",
    "run_bad_cases",
    "run_cascal",
    "spoil",
    "write_case",
]

_SCRIPT = Path(sys.executable).with_name("cascal")


def run_cascal(*args: object, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run the installed ``cascal`` script (or ``python -m cascal.cli``) and capture it."""
    cmd = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "cascal.cli"]
    return subprocess.run(
        [*cmd, *map(str, args)], capture_output=True, text=True, timeout=timeout, check=False
    )


def run_bad_cases(command: str, cases: dict, tmp: Path) -> dict:
    """Run ``cascal command *args`` for every ``name: (args, words)`` of ``cases``, four at
    a time, each with ``-o tmp/<name>.x`` unless its args hold ``-o``; returns ``name:
    (result, words, that output path)``."""
    with ThreadPoolExecutor(4) as pool:
        futures = {
            name: pool.submit(
                run_cascal, command, *args, *([] if "-o" in args else ["-o", tmp / f"{name}.x"])
            )
            for name, (args, _) in cases.items()
        }
        return {
            name: (f.result(), cases[name][1], tmp / f"{name}.x") for name, f in futures.items()
        }


def assert_refused(res: subprocess.CompletedProcess, words: list, out: Path) -> None:
    """Exit status 2, no traceback, every one of ``words`` in stderr, ``out`` not written."""
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    for w in words:
        assert w in res.stderr, (w, res.stderr)
    assert not out.exists()


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


def spoil(src, dst, changes: dict[int, float]) -> None:
    """Copy a stage file, adding ``changes[row]`` to the second column of those file rows."""
    lines = src.read_text().splitlines()
    for row, delta in changes.items():
        x, y = lines[row - 1].split(",")
        lines[row - 1] = f"{x},{float(y) + delta!r}"
    dst.write_text("\n".join(lines) + "\n")


def device_folder(folder: Path, good: Path, bad: Path) -> Path:
    """A new folder of two device files for ``fit-devices``: ``a.csv`` a copy of ``good``,
    ``b.csv`` of ``bad``."""
    folder.mkdir()
    (folder / "a.csv").write_text(good.read_text())
    (folder / "b.csv").write_text(bad.read_text())
    return folder
