"""``cascal demo``: simulated example files, then ``fit``, ``correct``, ``report``,
``export``, ``plan`` and ``verify`` on them, and for the linear case a recalibration after
a drift (``fit``, ``compare``, ``info``).

Two cases (:mod:`cascal.demo`): a linear axis in metres whose reference cannot reach a
stretch in the middle, and a rotary table in degrees whose reference cannot reach a sector
across 0/360, fitted with a periodic kernel. Each command is printed as a user would type
it and run through the same entry point; ``verify`` checks the corrections against the
simulated truth.
"""

from __future__ import annotations

import shlex
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from .demo import DemoCase, linear_demo, linear_recalibration, rotary_demo
from .io.atomic import save_figure
from .io.csvout import auto_decimals, write_columns
from .io.modelfile import load_model
from .report import correction_figure
from .reportdata import correction_curve

__all__ = ["run_demo"]


def run_demo(out: Path, *, seed: int, main: Callable[[Sequence[str]], int]) -> int:
    """Write, fit, correct, report, export, plan and verify both demo cases under ``out``,
    and recalibrate the linear one after a drift (fit, compare, info); returns the status."""
    for case in (linear_demo(seed), rotary_demo(seed)):
        folder = out / "demo" / case.name
        status = _run_case(case, folder, main, seed)
        if status:
            return status
    linear, rotary = out / "demo" / "linear", out / "demo" / "rotary"
    model = load_model(rotary / "model.json")
    curve = correction_curve(model)
    fig = correction_figure(curve, unit=model.unit, period=model.period)
    fig.suptitle("Rotary table: periodic kernel, continuous across 0/360 deg", fontsize=10)
    figure = save_figure(fig, out / "rotary_periodic.png", dpi=120)
    ends = model.fitted.correct(np.array([0.0, 360.0])) - np.array([0.0, 360.0])
    print(
        f"\nRotary correction at 0 deg and at 360 deg: {ends[0] * 3600:.6f} and "
        f"{ends[1] * 3600:.6f} arcsec (continuous across the seam); figure: {figure}"
    )
    print("\nWhere to look:")
    print(f"  {linear / 'report.html'}   linear axis: fits, bands, gaps, final correction")
    print(f"  {rotary / 'report.html'}   rotary table (periodic kernel over 360 deg)")
    print(f"  {linear / 'corrected.csv'}   reading, corrected, u, U, out_of_range")
    print(
        f"  {linear / 'linear_compensation.h'}   compensation table and function for a controller"
    )
    print(f"  {linear / 'plan.png'}   where the next reference measurements help most")
    print(f"  {linear / 'verify.png'}   errors against the simulated truth, with U")
    print(f"  {linear / 'change.png'}   a recalibration after a drift: the change, in its band")
    print(f"  {figure}   the rotary correction across 0/360 deg")
    return 0


def _run_case(case: DemoCase, folder: Path, main: Callable[[Sequence[str]], int], seed: int) -> int:
    print(f"== {case.name} demo ({case.unit}) in {folder}/")
    files = []
    for st in case.stages:
        path = folder / st.file
        decimals = auto_decimals([st.x, st.y])
        write_columns(path, {st.columns[0]: st.x, st.columns[1]: st.y}, decimals=decimals)
        files.append(str(path))
    readings = folder / "readings.csv"
    decimals = auto_decimals([case.readings])
    write_columns(readings, {"reading": case.readings}, decimals=decimals)
    truth = folder / "readings_truth.csv"
    write_columns(truth, {"reading": case.readings, "true": case.truth}, decimals=decimals)
    print(f"Wrote {', '.join(Path(f).name for f in files)}, {readings.name}, {truth.name}")
    model, corrected, report = (
        folder / "model.json",
        folder / "corrected.csv",
        folder / "report.html",
    )
    extra = ["--unit", case.unit, "--kernel", case.kernel]
    if case.period is not None:
        extra += ["--period", f"{case.period:g}"]
    commands = [
        ["fit", *files, "-o", str(model), *extra],
        ["correct", str(model), str(readings), "-o", str(corrected)],
        ["report", str(model), "-o", str(report)],
        ["export", str(model), "-o", str(folder / f"{case.name}_compensation.h")],
        [
            "plan",
            str(model),
            "-n",
            "5",
            "-o",
            str(folder / "plan.csv"),
            "--plot",
            str(folder / "plan.png"),
        ],
        # The truth is the map's exact value at each noisy reading: its noise is no part of
        # the error, so --reading-u stays 0.
        [
            "verify",
            str(model),
            str(truth),
            "-o",
            str(folder / "verify.csv"),
            "--plot",
            str(folder / "verify.png"),
        ],
    ]
    status = _run_commands(commands, main)
    if status:
        return status
    if case.name == "linear":
        status = _recalibrate(folder, files[0], model, extra, main, seed)
        if status:
            return status
        status = _zero_offset(folder, files, extra, main)
        if status:
            return status
    print()
    return 0


def _recalibrate(
    folder: Path, reference: str, model: Path, extra: list[str], main: Callable, seed: int
) -> int:
    """The linear device measured again after a drift of up to 0.25 mm: fit, compare (with
    a go/no-go limit of 1 mm on the change, which it passes)."""
    st = linear_recalibration(seed, drift=2.5e-4)
    path = folder / st.file
    decimals = auto_decimals([st.x, st.y])
    write_columns(path, {st.columns[0]: st.x, st.columns[1]: st.y}, decimals=decimals)
    print(f"\nWrote {path.name}: the device measured again after it drifted (up to 0.25 mm)")
    recal = folder / "model_recalibrated.json"
    commands = [
        ["fit", reference, str(path), "-o", str(recal), *extra],
        # a go/no-go of 1 mm, the change's uncertainty counted: passed
        [
            "compare",
            str(model),
            str(recal),
            "--max-change",
            "1e-3",
            "--plot",
            str(folder / "change.png"),
        ],
        ["info", str(recal)],
    ]
    return _run_commands(commands, main)


def _zero_offset(folder: Path, files: list[str], extra: list[str], main: Callable) -> int:
    """The device file with its readings 100 m off (a sensor zeroed elsewhere): the fit
    names the offset, and --mean offset fits it."""
    head, *rows = Path(files[1]).read_text().splitlines()
    moved = folder / "testbed_device_zero_offset.csv"
    shifted = [f"{float(a) + 100.0!r},{b}" for a, b in (r.split(",") for r in rows)]
    moved.write_text("\n".join([head, *shifted]) + "\n")
    print(f"\nWrote {moved.name}: the same device, its readings' zero 100 m away")
    commands = [
        ["fit", files[0], str(moved), "-o", str(folder / "model_zero_offset.json"), *extra,
         "--no-screening"],
        ["fit", files[0], str(moved), "-o", str(folder / "model_zero_offset.json"), *extra,
         "--mean", "offset"],
    ]  # fmt: skip
    return _run_commands(commands, main)


def _run_commands(commands: list[list[str]], main: Callable) -> int:
    """Print each command as a user would type it and run it; the first failure's status."""
    for argv in commands:
        print(f"\n$ cascal {shlex.join(argv)}", flush=True)
        status = main(argv)
        if status:
            return status
    return 0
