"""Speed of correcting 10^6 device readings with uncertainty (``cascal correct``).

Fits the linear demo cascade (200 device points, method bayes), saves the model, then times
(1) the library: ``load_model`` + ``workflow.correct`` on 10^6 readings (mean and u), best of
three, against exact GP prediction on a subset; and (2) the whole command,
``cascal correct MODEL READINGS.csv -o OUT.csv``, from process start to exit, which adds the
interpreter start and imports, CSV parsing and writing five columns.

Run: ``python benchmarks/bench_correct.py [--n 1000000]``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cascal.demo import linear_demo
from cascal.io.csvout import write_columns
from cascal.io.data import read_stage
from cascal.io.modelfile import load_model, save_model
from cascal.workflow import correct, fit_model


def _model(folder: Path) -> Path:
    case = linear_demo(0)
    data = []
    for st in case.stages:
        write_columns(
            folder / st.file, dict(zip(st.columns, (st.x, st.y), strict=True)), decimals=12
        )
        data.append(read_stage(folder / st.file))
    return save_model(folder / "model.json", fit_model(data, unit="m"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="readings (default 10^6)")
    n = ap.parse_args().n
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path = _model(folder)
        model = load_model(path)
        lo, hi = model.calibrated_range
        readings = np.random.default_rng(1).uniform(lo, hi, n)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            c = correct(load_model(path), readings)
            times.append(time.perf_counter() - t0)
        sub = readings[:20000]
        mean, std = model.fitted.device.predict(sub, return_std=True)
        err_m = float(np.max(np.abs(c.corrected[:20000] - mean)))
        err_u = float(np.max(np.abs(c.u[:20000] - std)))
        print(f"library: load + correct {n} readings (mean and u): {min(times):.3f} s (best of 3)")
        print(
            f"  vs exact GP prediction on 20000 readings: max |diff| mean {err_m:.2e} m, "
            f"u {err_u:.2e} m (smallest u {float(std.min()):.2e} m)"
        )
        csv_in = folder / "readings.csv"
        write_columns(csv_in, {"reading": readings}, decimals=12)
        exe = Path(sys.executable).with_name("cascal")
        cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "cascal.cli"]
        cmd += ["correct", str(path), str(csv_in), "-o", str(folder / "out.csv")]
        walls = []
        for _ in range(3):
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, capture_output=True)
            walls.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        subprocess.run([*cmd[:-5], "--version"], check=True, capture_output=True)
        start = time.perf_counter() - t0
        print(
            f"command: cascal correct on {n} readings, CSV in and out: {min(walls):.3f} s wall "
            f"(best of 3; of which {start:.3f} s is starting Python and importing cascal)"
        )


if __name__ == "__main__":
    main()
