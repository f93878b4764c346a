"""``cascal plan``: proposed reference measurements through the installed command."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import assert_refused, run_bad_cases, run_cascal

from cascal.cli import check_output, join_negative, same_file
from cascal.demo import rotary_demo
from cascal.errors import InputError
from cascal.io.modelfile import load_model, save_model
from cascal.planning import covered, find_gaps
from cascal.plots import _wrapped
from cascal.text import measured_ends
from cascal.workflow import fit_model, plan_measurements
from utils import assert_allclose, demo_stages


def test_plan_csv_and_figure_hold_the_library_plan(linear_model, tmp_path):
    """The CSV holds the library's plan; by default no proposal falls into the stretch the
    reference could not reach; the device stage is the target of a bayes model."""
    model = load_model(linear_model)
    lib = plan_measurements(model, 4)
    res = run_cascal(
        "plan", linear_model, "-n", "4", "-o", tmp_path / "p.csv", "--plot", tmp_path / "p.png"
    )
    assert res.returncode == 0, res.stderr
    assert "Lowered: stage 1" in res.stdout and "now" in res.stdout
    rows = np.loadtxt(tmp_path / "p.csv", delimiter=",", skiprows=1)
    assert rows.shape == (4, 4) and np.array_equal(rows[:, 0], [1, 2, 3, 4])
    assert_allclose(rows[:, 1], lib.plan.positions, atol=1e-12, rtol=0)
    assert_allclose(rows[:, 2], lib.plan.u_rms[1:], rtol=1e-6)
    assert (tmp_path / "p.png").stat().st_size > 10_000
    (gap,) = find_gaps(model.data[0].x)
    assert not np.any((lib.plan.positions > gap[0]) & (lib.plan.positions < gap[1]))
    assert lib.lower_name == model.data[1].name
    assert lib.plan.u_rms[-1] < lib.plan.u_rms[0]


def test_reach_limits_the_proposals(linear_model, tmp_path):
    out = tmp_path / "p.csv"
    res = run_cascal(
        "plan", linear_model, "-n", "3", "--reach", "0.1:0.2", "--reach", "0.9", "-o", out
    )
    assert res.returncode == 0, res.stderr
    assert "[0.1, 0.2], [0.9, 0.9] m" in res.stdout
    positions = np.loadtxt(out, delimiter=",", skiprows=1)[:, 1]
    assert positions.size == 3
    assert np.all(((positions >= 0.1) & (positions <= 0.2)) | (positions == 0.9))
    assert "warning" not in res.stderr
    far = run_cascal("plan", linear_model, "-n", "2", "--reach", "5:6")
    assert far.returncode == 0, far.stderr
    assert "lower the RMS u by less than 0.1 %" in far.stderr
    # a review's case: 5:6 on a 1 m axis (a unit mixed up?) is named as such
    assert "--reach 5:6 lies more than their span away from the test-bed readings" in far.stderr
    assert "(readings in another unit?)" in far.stderr
    near = run_cascal("plan", linear_model, "-n", "2", "--reach", "1.1:1.2")
    assert near.returncode == 0 and "away from the test-bed readings" not in near.stderr
    assert "--reach 1.1:1.2 lies wholly outside the test-bed readings" in near.stderr
    inside = run_cascal("plan", linear_model, "-n", "2", "--reach", "0.95:1.2")
    assert inside.returncode == 0 and "outside the test-bed readings" not in inside.stderr


def test_negative_readings_and_covered_stretches(linear_model, tmp_path):
    """``--reach -0.04:0.3`` works as typed; the default reach leaves out gaps wider than
    3 median spacings, and a tenth of the span or 3 times the spacings beside them, and runs
    across a periodic seam."""
    assert join_negative(["plan", "m", "--reach", "-1:2", "--where", "-3:-1", "-n", "2"]) == [
        "plan", "m", "--reach=-1:2", "--where=-3:-1", "-n", "2",
    ]  # fmt: skip
    assert join_negative(["--reach", "-4e-2", "--where", "-x", "--", "--reach", "-1:2"]) == [
        "--reach=-4e-2", "--where", "-x", "--", "--reach", "-1:2",
    ]  # fmt: skip
    out = tmp_path / "p.csv"
    res = run_cascal("plan", linear_model, "-n", "2", "--reach", "-0.04:0.3", "-o", out)
    assert res.returncode == 0, res.stderr
    positions = np.loadtxt(out, delimiter=",", skiprows=1)[:, 1]
    assert np.all((positions >= -0.04) & (positions <= 0.3))
    paper = np.delete(np.linspace(0.0, 1.0, 100)[10:90], np.s_[32:48])
    assert covered(paper, None) == [(paper[0], paper[31]), (paper[32], paper[-1])]
    clustered = np.concatenate([np.linspace(0.0, 0.1, 21), np.linspace(0.19, 1.0, 10)])
    assert covered(clustered, None) == [(0.0, 1.0)]  # sparse, not a gap
    full = np.arange(0.0, 360.0, 5.0)
    assert covered(full, 360.0) == [(0.0, 360.0)]
    seam = np.arange(25.0, 340.0, 5.0)
    assert covered(seam, 360.0) == [(25.0, 335.0)]
    # a review's case: set points every 5 mm with 25 mm the interferometer could not reach
    # (under a tenth of the span): the report hatched it, and the plan proposed points there
    travel = np.r_[np.arange(20.0, 141.0, 5.0), np.arange(165.0, 286.0, 5.0)]
    assert covered(travel, None) == [(20.0, 140.0), (165.0, 285.0)]
    assert covered(np.r_[travel, 152.0], None) == [(20.0, 285.0)]  # one point: two gaps


def test_periodic_proposals_lie_on_one_turn(tmp_path):
    """A rotary model whose reference could not reach the seam: the default reach keeps
    off it; given a reach across it, the proposals lie there, on one turn."""
    stages = demo_stages(rotary_demo(0))
    model = fit_model(stages, kernel="periodic", period=360.0, unit="deg", n_restarts=2)
    mp = plan_measurements(model, 3)
    lo, hi = float(model.data[0].x.min()), float(model.data[0].x.max())
    assert np.all((mp.plan.positions >= lo) & (mp.plan.positions <= hi))
    mp = plan_measurements(model, 3, reach=[(340.0, 380.0)])
    p = mp.plan.positions
    assert np.all((p >= 0.0) & (p < 360.0) & ((p >= 340.0) | (p <= 20.0)))
    assert mp.plan.u_rms[-1] < 0.9 * mp.plan.u_rms[0]  # the seam is where u is largest
    assert _wrapped([(340.0, 380.0)], 360.0) == [(340.0, 360.0), (0.0, 20.0)]
    assert _wrapped([(-20.0, 10.0), (400.0, 410.0)], 360.0) == [
        (340.0, 360.0), (0.0, 10.0), (40.0, 50.0),
    ]  # fmt: skip
    assert _wrapped([(0.0, 400.0), (5.0, 6.0)], 360.0) == [(0.0, 360.0)]
    path = save_model(tmp_path / "rotary.json", model)  # a reach turns away: no unit warning
    res = run_cascal("plan", path, "-n", "1", "--reach=720:740")
    assert res.returncode == 0 and "another unit" not in res.stderr, res.stderr
    assert mp.target.endswith("over its calibrated full turn (period 360)")


def test_a_partly_measured_rotary_device_is_planned_for_over_its_measured_arc(monkeypatch):
    """A user review's case: the plan of a rotary device whose readings leave part of the
    turn out lowered u over the readings' smallest to largest angle, which holds the arc
    left out (u large there, and flagged) and leaves out the stretch across 0. It now
    plans over the measured arc and names it as fit and info do."""
    from dataclasses import replace

    from cascal import workflow

    case = rotary_demo(0)
    dev = case.stages[1]
    keep = (dev.x < 150.0) | (dev.x > 250.0)  # a swivel that never turns through 200
    part = replace(case, stages=(case.stages[0], replace(dev, x=dev.x[keep], y=dev.y[keep])))
    model = fit_model(demo_stages(part), kernel="periodic", period=360.0, unit="deg",
                      n_restarts=1)  # fmt: skip
    targets = []
    real = workflow.LowerStage
    monkeypatch.setattr(workflow, "LowerStage", lambda *a: targets.append(real(*a)) or targets[-1])
    mp = plan_measurements(model, 2)
    start = float(dev.x[keep & (dev.x < 150.0)].max())  # the arc left out: start to end
    end = float(dev.x[keep & (dev.x > 250.0)].min())
    a, b = measured_ends((start, end))  # the measured arc, from end round to start
    assert float(a) >= end and float(b) <= start  # rounded inward
    assert f"{a} to {b} deg of the turn" in mp.target and f"leave out {b} to {a}" in mp.target
    (target,) = targets
    w = target.where
    assert not np.any((w > start + 1e-9) & (w < end - 1e-9))  # none in the arc left out
    assert np.any(w < 10.0) and np.any(w > 350.0)  # and the stretch across 0 is planned for


def test_outputs_never_overwrite_inputs(linear_files, linear_model, tmp_path):
    """Not the same regular file (``..`` and links resolved); devices are never the same."""
    files, readings = linear_files
    (tmp_path / "sub").mkdir()
    assert same_file(tmp_path / "sub" / ".." / "p.png", tmp_path / "p.png")
    (tmp_path / "link.json").symlink_to(linear_model)
    assert same_file(tmp_path / "link.json", linear_model)
    assert not same_file(os.devnull, os.devnull)
    check_output(os.devnull, inputs=[os.devnull])  # e.g. -o /dev/stdout with /dev/stdin
    res = run_cascal("plan", linear_model, "-o", tmp_path / "sub" / ".." / "p.x",
                     "--plot", tmp_path / "p.x.png")  # fmt: skip
    assert res.returncode == 0, res.stderr
    res = run_cascal("plan", linear_model, "-o", tmp_path / "sub" / ".." / "q.png",
                     "--plot", tmp_path / "q.png")  # fmt: skip
    assert res.returncode == 2 and "same file as -o" in res.stderr
    for args in (
        ("correct", linear_model, readings, "-o", readings),
        ("export", linear_model, "-o", linear_model),
        ("report", linear_model, "-o", linear_model),
        ("fit", *files, "-o", files[0]),
    ):
        before = Path(args[-1]).read_bytes()
        res = run_cascal(*args)
        assert res.returncode == 2 and "is an input of this command" in res.stderr, args
        assert Path(args[-1]).read_bytes() == before
    # a review's case: through a folder not made yet, then "..", the input had been replaced
    # (the writer makes the folder, then renames onto the input)
    for args in (
        ("correct", linear_model, readings, "-o", f"{readings.parent}/nosuch/../{readings.name}"),
        ("fit", *files, "-o", f"{files[0].parent}/nosuch/../{files[0].name}"),
    ):
        before = Path(args[1 if args[0] == "fit" else 2]).read_bytes()
        res = run_cascal(*args)
        assert res.returncode == 2 and "is an input of this command" in res.stderr, args
        assert Path(args[1 if args[0] == "fit" else 2]).read_bytes() == before
        assert not Path(args[-1]).parent.exists()
    # and "-o odir/" or "odir/." for a folder not there wrote a file "odir"
    for end in ("/", "/."):
        res = run_cascal("correct", linear_model, readings, "-o", f"{tmp_path}/odir{end}")
        assert res.returncode == 2 and "expected a file name, got a folder's" in res.stderr
        assert not (tmp_path / "odir").exists()
    # through a linked folder: resolved as the writer will (a second review: the input was
    # replaced, and a file of the same name beside the link refused)
    data, work = tmp_path / "data", tmp_path / "work"
    (data / "sub").mkdir(parents=True)
    work.mkdir()
    (work / "linkdir").symlink_to(data / "sub")
    rd = data / "rd.csv"
    rd.write_text(readings.read_text())
    res = run_cascal("correct", linear_model, rd, "-o", f"{work}/linkdir/nosuch/../../rd.csv")
    assert res.returncode == 2 and "is an input of this command" in res.stderr
    assert rd.read_text() == readings.read_text()
    (work / "loop").symlink_to(work / "loop")  # (resolve() raised RuntimeError: a traceback)
    res = run_cascal("correct", linear_model, rd, "-o", work / "loop")
    assert "Traceback" not in res.stderr
    local = work / "rd.csv"
    local.write_text(readings.read_text())
    res = run_cascal("correct", linear_model, local, "-o", f"{work}/linkdir/../rd.csv")
    assert res.returncode == 0, res.stderr
    assert local.read_text() == readings.read_text() and rd.read_text() != readings.read_text()


def test_targets_of_other_models(tmp_path):
    """A one-stage model lowers stage 0's u over ``where``; a homoscedastic one at stage
    1's test-bed readings; a lut model is refused."""
    stages = demo_stages()
    one = fit_model(stages[:1])
    mp = plan_measurements(one, 2, where=(0.0, 1.0))
    assert mp.lower_name is None and mp.plan.where.size == 201
    assert mp.plan.where[0] == 0.0 and mp.plan.where[-1] == 1.0
    hom = fit_model(stages, method="homoscedastic")
    mp = plan_measurements(hom, 2)
    assert np.array_equal(mp.plan.where, stages[1].y)
    save_model(tmp_path / "one.json", one)
    save_model(tmp_path / "lut.json", fit_model(stages, method="lut"))
    res = run_cascal("plan", tmp_path / "one.json", "--where", "0:1", "-n", "2")
    assert res.returncode == 0, res.stderr
    assert "test-bed readings [0, 1]" in res.stdout


@pytest.fixture(scope="module")
def bad_runs(linear_model, tmp_path_factory):
    """Every bad invocation run concurrently: name -> (result, output paths)."""
    tmp = tmp_path_factory.mktemp("plan_bad")
    stages = demo_stages()
    lut = save_model(tmp / "lut.json", fit_model(stages, method="lut"))
    corrupt = tmp / "corrupt.json"
    corrupt.write_text('{"schema_version": 1, "stages": [')
    (tmp / "folder.csv").mkdir()
    cases = {
        "reach_words": ([linear_model, "--reach", "a:b"], ["--reach", "LO:HI"]),
        "reach_reversed": ([linear_model, "--reach", "0.5:0.1"], ["--reach '0.5:0.1'", "lo <= hi"]),
        "reach_nan": ([linear_model, "--reach", "nan"], ["finite"]),
        "reach_three": ([linear_model, "--reach", "1:2:3"], ["LO:HI"]),
        "where_two_stages": ([linear_model, "--where", "0:1"], ["one-stage model"]),
        "noise_negative": ([linear_model, "--noise-std", "-1"], ["--noise-std", ">= 0"]),
        "too_many": ([linear_model, "-n", "1001"], ["-n", "at most 1000"]),
        "noise_huge": ([linear_model, "--noise-std", "1e200"], ["--noise-std", "below 1e150"]),
        "reach_overflow": (
            [linear_model, "--reach=-1e308:1e308"],
            ["--reach '-1e308:1e308'", "finite"],
        ),
        "plot_is_output": (
            [linear_model, "--plot", tmp / "same.png", "-o", tmp / "same.png"],
            ["same file as -o"],
        ),
        "plot_folder": (
            [linear_model, "--plot", tmp / "folder.csv"],
            ["--plot", "existing folder"],
        ),
        "output_is_model": ([linear_model, "-o", linear_model], ["is an input"]),
        "plot_suffix": ([linear_model, "--plot", tmp / "p.txt"], [".png"]),
        "output_folder": ([linear_model, "-o", tmp / "folder.csv"], ["existing folder"]),
        "lut": ([lut], ["lut", "no uncertainty"]),
        "corrupt": ([corrupt], ["corrupt.json"]),
    }
    return run_bad_cases("plan", cases, tmp)


@pytest.mark.parametrize(
    "name",
    [
        "reach_words",
        "reach_reversed",
        "reach_nan",
        "reach_three",
        "where_two_stages",
        "noise_negative",
        "too_many",
        "noise_huge",
        "reach_overflow",
        "plot_is_output",
        "plot_folder",
        "output_is_model",
        "plot_suffix",
        "output_folder",
        "lut",
        "corrupt",
    ],
)
def test_bad_input_exits_2_and_writes_nothing(bad_runs, name):
    assert_refused(*bad_runs[name])


@pytest.mark.skipif(not os.path.isfile("/proc/version"), reason="needs Linux's /proc")
def test_an_output_where_no_file_can_be_made_is_refused_before_work(tmp_path):
    """A leftover of an earlier review: ``-o /proc/version`` passed the permission check
    (root may write anywhere, by os.access) and failed only when written, after the fit,
    with "No such file" and status 1. The check now makes (and removes) a file where the
    write will make its temporary one: through a link too, to the link's target."""
    refused = r"(cannot create a file|no permission to write) in /proc"  # (root: the first)
    for dest in ("/proc/version", "/proc/no/such.json"):
        with pytest.raises(InputError, match=refused):
            check_output(dest)
    (tmp_path / "link.json").symlink_to("/proc/version")
    with pytest.raises(InputError, match=r"-o .*link.json: " + refused):
        check_output(tmp_path / "link.json")
    check_output(tmp_path / "new" / "m.json")
    check_output(tmp_path, folder=True)
    assert [p.name for p in tmp_path.iterdir()] == ["link.json"]  # no probe left behind


def test_an_input_from_a_pipe_is_named_as_such_in_titles(tmp_path):
    """A review: figure titles and headers named a piped file by its pipe (/dev/fd/63 as
    "63 against m.json")."""
    from cascal.cli import file_label

    (tmp_path / "m.json").write_text("{}")
    os.mkfifo(tmp_path / "fifo")
    assert file_label(tmp_path / "m.json") == "m.json"
    assert file_label(tmp_path / "fifo", "check points") == "check points read from a pipe"


def test_a_write_protected_output_file_is_not_replaced(tmp_path, linear_model, linear_files):
    """A leftover of a review: ``-o`` naming a read-only file replaced it (the atomic
    write's rename needs only the folder's permission). It is refused before any work, as
    a link to one is; a writable file is replaced as before."""
    out = tmp_path / "corrected.csv"
    out.write_text("old\n")
    out.chmod(0o444)
    (tmp_path / "link.csv").symlink_to(out)
    for dest in (out, tmp_path / "link.csv"):
        with pytest.raises(InputError, match=r"write-protected; not replaced"):
            check_output(dest)
    res = run_cascal("correct", linear_model, linear_files[1], "-o", out)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "write-protected; not replaced" in res.stderr and out.read_text() == "old\n"
    out.chmod(0o644)
    check_output(out)
