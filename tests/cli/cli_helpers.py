"""Helpers of the workflow tests: run the installed ``cascal`` command, write demo files."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from cascal.demo import DemoCase
from cascal.io.csvout import auto_decimals, write_columns

__all__ = [
    "assert_refused",
    "device_folder",
    "interrupted",
    "run_bad_cases",
    "run_cascal",
    "spoil",
    "write_case",
]

_SCRIPT = Path(sys.executable).with_name("cascal")


def run_cascal(
    *args: object, timeout: float = 300, stdin: str | None = None
) -> subprocess.CompletedProcess:
    """Run the installed ``cascal`` script (or ``python -m cascal.cli``) and capture it;
    ``stdin``: text for its standard input."""
    cmd = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "cascal.cli"]
    return subprocess.run(
        [*cmd, *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
        input=stdin,
    )


def interrupted(
    args: list, ready: Callable[[subprocess.Popen], None], gaps: tuple[float, ...] = ()
) -> tuple[int, str]:
    """Start ``cascal *args`` in a process group of its own with SIGINT at its default (as
    a terminal does), wait for ``ready(proc)`` to return, send SIGINT to the group, then
    again after each of ``gaps`` (s). Returns (returncode, stderr); fails the test where
    the command has not ended 120 s after the last signal."""
    import contextlib
    import os
    import signal
    import time

    import pytest

    proc = subprocess.Popen(
        [str(_SCRIPT), *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    ready(proc)
    os.killpg(proc.pid, signal.SIGINT)
    for gap in gaps:
        time.sleep(gap)
        with contextlib.suppress(ProcessLookupError):  # (it may have ended already)
            os.killpg(proc.pid, signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail(f"cascal {args[0]} hung after the interrupts")
    return proc.returncode, err


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
