"""``cascal plan``: proposed reference measurements through the installed command."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from cli_helpers import run_cascal

from cascal.io.modelfile import load_model, save_model
from cascal.reportdata import find_gaps
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
        "reach_reversed": ([linear_model, "--reach", "0.5:0.1"], ["LO <= HI"]),
        "reach_nan": ([linear_model, "--reach", "nan"], ["finite"]),
        "reach_three": ([linear_model, "--reach", "1:2:3"], ["LO:HI"]),
        "where_two_stages": ([linear_model, "--where", "0:1"], ["one-stage model"]),
        "noise_negative": ([linear_model, "--noise-std", "-1"], ["noise std", ">= 0"]),
        "too_many": ([linear_model, "-n", "1001"], ["1 to 1000"]),
        "plot_suffix": ([linear_model, "--plot", tmp / "p.txt"], [".png"]),
        "output_folder": ([linear_model, "-o", tmp / "folder.csv"], ["existing folder"]),
        "lut": ([lut], ["lut", "no uncertainty"]),
        "corrupt": ([corrupt], ["corrupt.json"]),
    }
    with ThreadPoolExecutor(4) as pool:
        futures = {
            name: pool.submit(
                run_cascal, "plan", *args, "-o" if "-o" not in args else "--plot", tmp / f"{name}.x"
            )
            for name, (args, _) in cases.items()
        }
        return {
            name: (f.result(), cases[name][1], tmp / f"{name}.x") for name, f in futures.items()
        }


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
        "plot_suffix",
        "output_folder",
        "lut",
        "corrupt",
    ],
)
def test_bad_input_exits_2_and_writes_nothing(bad_runs, name):
    res, words, out = bad_runs[name]
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert "Traceback" not in res.stderr
    for w in words:
        assert w in res.stderr, (w, res.stderr)
    assert not out.exists()
