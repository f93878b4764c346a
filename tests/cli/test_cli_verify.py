"""``cascal verify``: a model against check points, through the installed command."""

from __future__ import annotations

import numpy as np
import pytest
from cli_helpers import assert_refused, run_bad_cases, run_cascal

from cascal.io.csvout import write_columns
from cascal.io.modelfile import load_model
from cascal.workflow import verify_model
from utils import assert_allclose


@pytest.fixture(scope="module")
def check_file(tmp_path_factory, linear_case):
    """The linear case's readings with their true positions (one beyond the range)."""
    path = tmp_path_factory.mktemp("verify") / "check.csv"
    write_columns(path, {"device": linear_case.readings, "ref": linear_case.truth}, decimals=15)
    return path


def test_csv_and_summary_hold_the_library_numbers(linear_model, check_file, tmp_path):
    out, fig = tmp_path / "v.csv", tmp_path / "v.png"
    res = run_cascal("verify", linear_model, check_file, "--reference-u", "1e-6",
                     "-o", out, "--plot", fig)  # fmt: skip
    assert res.returncode == 0, res.stderr
    table = np.genfromtxt(out, delimiter=",", names=True)
    names = table.dtype.names
    assert names == ("reading", "reference", "corrected", "error", "u_calibration", "u", "U",
                     "En", "out_of_range")  # fmt: skip
    src = np.loadtxt(check_file, delimiter=",", skiprows=1)
    lib = verify_model(load_model(linear_model), src[:, 0], src[:, 1], u_reference=1e-6)
    for name, want in (("corrected", lib.corrected), ("error", lib.error), ("u", lib.u),
                       ("En", lib.en), ("out_of_range", ~lib.inside)):  # fmt: skip
        assert_allclose(table[name], want, rtol=1e-9, atol=1e-12, err_msg=name)
    s = lib.summary()
    assert f"at {s['points']} check points" in res.stdout
    assert f"at {s['within_U']} of {s['points']} points" in res.stdout
    assert "(the model's learned noise)" in res.stdout and "not judged" in res.stdout
    assert "1 of 2001 check points lie outside the calibrated range" in res.stderr
    assert "row 2002" in res.stderr
    assert fig.stat().st_size > 10_000


def test_mpe_decides_the_exit_status(linear_model, check_file, tmp_path):
    """A point conforms when |error| + 2 u_reference <= MPE; any that does not: exit 1."""
    src = np.loadtxt(check_file, delimiter=",", skiprows=1)
    lib = verify_model(load_model(linear_model), src[:, 0], src[:, 1])
    largest = lib.summary()["max_after"]
    ok = run_cascal("verify", linear_model, check_file, "--mpe", f"{1.01 * largest:.17g}")
    assert ok.returncode == 0, ok.stderr
    assert "Verification passed." in ok.stdout
    out = tmp_path / "v.csv"
    tight = run_cascal("verify", linear_model, check_file, "--mpe", f"{0.5 * largest:.17g}",
                       "--reference-u", "1e-6", "-o", out)  # fmt: skip
    assert tight.returncode == 1, tight.stderr
    strict = verify_model(load_model(linear_model), src[:, 0], src[:, 1], u_reference=1e-6,
                          mpe=0.5 * largest)  # fmt: skip
    n_ok = strict.summary()["conforming"]
    assert 0 < n_ok < 2000 and f"{n_ok} of 2000 points conform" in tight.stdout
    assert f"{2000 - n_ok} check point(s) not shown to conform" in tight.stdout
    written = np.genfromtxt(out, delimiter=",", names=True)
    assert np.array_equal(written["conforms"].astype(bool), strict.conforms)


def test_lookup_table_model(linear_files, check_file, tmp_path):
    files, _ = linear_files
    model = tmp_path / "lut.json"
    assert run_cascal("fit", *files, "--method", "lut", "-o", model).returncode == 0
    out = tmp_path / "v.csv"
    res = run_cascal("verify", model, check_file, "--mpe", "1", "-o", out)
    assert res.returncode == 0, res.stderr
    assert "no uncertainty" in res.stderr and "Verification passed." in res.stdout
    table = np.genfromtxt(out, delimiter=",", names=True)
    assert np.all(np.isnan(table["En"])) and np.all(table["conforms"] == 1)


@pytest.fixture(scope="module")
def bad_runs(linear_model, check_file, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("verify_bad")
    nan = tmp / "nan.csv"
    nan.write_text("device,ref\n0.5,0.5\n0.6,nan\n")
    one = tmp / "one.csv"
    one.write_text("device\n0.5\n")
    far = tmp / "far.csv"
    far.write_text("device,ref\n5,5\n6,6\n")
    corrupt = tmp / "corrupt.json"
    corrupt.write_text(linear_model.read_text()[:-40])
    cases = {
        "nan": ([linear_model, nan], ["nan.csv", "row 3"]),
        "one_column": ([linear_model, one], ["one.csv", "--x-column"]),
        "no_column": ([linear_model, check_file, "--y-column", "truth"], ["truth"]),
        "all_outside": ([linear_model, far], ["far.csv", "no check point lies inside"]),
        "reading_u": ([linear_model, check_file, "--reading-u", "-1"], ["--reading-u"]),
        "reference_u": ([linear_model, check_file, "--reference-u", "inf"], ["--reference-u"]),
        "mpe": ([linear_model, check_file, "--mpe", "0"], ["--mpe"]),
        "plot_suffix": ([linear_model, check_file, "--plot", tmp / "v.txt"], [".png"]),
        "output_is_check": ([linear_model, check_file, "-o", check_file], ["is an input"]),
        "corrupt": ([corrupt, check_file], ["corrupt.json"]),
    }
    return run_bad_cases("verify", cases, tmp)


@pytest.mark.parametrize(
    "name",
    ["nan", "one_column", "no_column", "all_outside", "reading_u", "reference_u", "mpe",
     "plot_suffix", "output_is_check", "corrupt"],
)  # fmt: skip
def test_bad_input_exits_2_and_writes_nothing(bad_runs, name, check_file):
    assert_refused(*bad_runs[name])
    assert check_file.read_text().startswith("device,ref\n")
