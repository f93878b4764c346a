"""``cascal verify``: a model against check points, through the installed command."""

from __future__ import annotations

import numpy as np
import pytest
from cli_helpers import assert_refused, run_bad_cases, run_cascal

from cascal.demo import rotary_demo
from cascal.io.csvout import write_columns
from cascal.io.modelfile import load_model, save_model
from cascal.workflow import fit_model, verify_model
from utils import assert_allclose, demo_stages


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
    assert "(taken as exact" not in res.stdout
    assert res.returncode == 0, res.stderr
    table = np.genfromtxt(out, delimiter=",", names=True)
    names = table.dtype.names
    assert names == ("reading", "reference", "corrected", "error", "u_calibration", "u", "U",
                     "En", "out_of_range")  # fmt: skip
    src = np.loadtxt(check_file, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(table["reading"], src[:, 0])  # as read, not rounded to the
    np.testing.assert_array_equal(table["reference"], src[:, 1])  # corrections' decimals
    lib = verify_model(load_model(linear_model), src[:, 0], src[:, 1], u_reference=1e-6)
    en = np.where(lib.inside, lib.en, np.nan)  # points outside the range are not judged
    for name, want in (("corrected", lib.corrected), ("error", lib.error), ("u", lib.u),
                       ("En", en), ("out_of_range", ~lib.inside)):  # fmt: skip
        assert_allclose(table[name], want, rtol=1e-9, atol=1e-12, err_msg=name)
    s = lib.summary()
    assert f"at {s['points']} check points" in res.stdout
    assert f"at {s['within_U']} of {s['points']} (" in res.stdout
    assert "(not given: --reading-u)" in res.stdout and "not judged" in res.stdout
    assert "Warning" not in res.stderr  # no Python warnings leak
    assert "1 of 2001 check points lie outside the calibrated range" in res.stderr
    assert "row 2002" in res.stderr
    assert fig.stat().st_size > 10_000


def test_mpe_decides_the_exit_status(linear_model, check_file, tmp_path):
    """A point conforms when |error| + 2 u_reference <= MPE; any that does not: exit 1."""
    src = np.loadtxt(check_file, delimiter=",", skiprows=1)
    lib = verify_model(load_model(linear_model), src[:, 0], src[:, 1])
    largest = lib.summary()["max_after"]
    inside = tmp_path / "inside.csv"  # the check points inside the range
    write_columns(inside, {"device": src[lib.inside, 0], "ref": src[lib.inside, 1]}, decimals=15)
    ok = run_cascal("verify", linear_model, inside, "--mpe", f"{1.01 * largest:.17g}")
    assert ok.returncode == 0, ok.stderr
    assert "Verification passed: all 2000 check points conform." in ok.stdout
    # a review's case: the point outside the range, not judged, passed with the others
    cut = run_cascal("verify", linear_model, check_file, "--mpe", f"{1.01 * largest:.17g}")
    assert cut.returncode == 3, cut.stderr
    row = 2 + int(np.flatnonzero(~lib.inside)[0])
    assert (
        "Verification failed: 1 check point outside the range, not judged, so not shown to "
        f"conform to the MPE (first: row {row}); the 2000 check points inside conform."
    ) in cut.stdout
    out = tmp_path / "v.csv"
    assert "no guard band" in ok.stderr  # the reference taken as exact
    tight = run_cascal("verify", linear_model, check_file, "--mpe", f"{0.5 * largest:.17g}",
                       "--reference-u", "1e-6", "-o", out)  # fmt: skip
    assert tight.returncode == 3, tight.stderr
    assert "no guard band" not in tight.stderr
    strict = verify_model(load_model(linear_model), src[:, 0], src[:, 1], u_reference=1e-6,
                          mpe=0.5 * largest)  # fmt: skip
    n_ok = strict.summary()["conforming"]
    assert 0 < n_ok < 2000 and f"{n_ok} of 2000 conform" in tight.stdout
    assert f"{2000 - n_ok} check points not shown to conform" in tight.stdout
    written = np.genfromtxt(out, delimiter=",", names=True)
    inside = strict.inside
    assert np.array_equal(written["conforms"][inside].astype(bool), strict.conforms[inside])
    assert np.all(np.isnan(written["conforms"][~inside]))  # not judged: empty
    assert np.all(np.isnan(written["En"][~inside]))
    assert "1 outside the range not judged" in tight.stdout


def test_points_outside_the_range_are_not_judged(linear_model, tmp_path):
    """A far-off point outside the range is neither the largest error nor a failure; one
    check point is enough; columns by name; warnings when error / u is far from 1."""
    check = tmp_path / "c.csv"
    check.write_text("note,ref,device\n1,0.47423,0.5\n2,5.0,0.99\n")
    res = run_cascal("verify", linear_model, check, "--x-column", "device", "--y-column", "ref",
                     "--mpe", "1e-3", "--reference-u", "1e-7")  # fmt: skip
    assert res.returncode == 3, res.stderr  # not shown to conform: the go/no-go fails
    assert "at 1 check point of" in res.stdout and "(row 2, reading 0.5)" in res.stdout
    assert "1 check point outside the range, not judged, so not shown to conform" in res.stdout
    assert "the 1 check point inside conform" in res.stdout
    assert "row 3); they are not judged" in res.stderr
    big = run_cascal("verify", linear_model, check, "--x-column", "device", "--y-column", "ref",
                     "--reading-u", "1")  # fmt: skip
    assert big.returncode == 0 and "test little of the model's uncertainty" in big.stderr
    far = tmp_path / "far.csv"
    far.write_text("device,ref\n0.5,0.5\n0.6,0.6\n")
    res = run_cascal("verify", linear_model, far)
    assert res.returncode == 0 and "uncertainty is too small" in res.stderr
    assert "no smaller than before" in res.stdout


def test_rotary_references_a_turn_away(tmp_path):
    """References given a turn away give the same errors; readings on other turns too."""
    case = rotary_demo(0)
    model = tmp_path / "rotary.json"
    save_model(model, fit_model(demo_stages(case), kernel="periodic", period=360.0, unit="deg",
                                n_restarts=2))  # fmt: skip
    k = 50
    shift = np.where(np.arange(k) % 2 == 0, 360.0, -360.0)
    turned = (case.readings[:k] + shift, case.truth[:k] - shift)
    for name, (reading, ref) in (("a.csv", (case.readings[:k], case.truth[:k])),
                                 ("b.csv", turned)):  # fmt: skip
        write_columns(tmp_path / name, {"device": reading, "ref": ref}, decimals=12)
        res = run_cascal("verify", model, tmp_path / name, "-o", tmp_path / f"{name}.out",
                         "--plot", tmp_path / f"{name}.png")  # fmt: skip
        assert res.returncode == 0, res.stderr
    a = np.genfromtxt(tmp_path / "a.csv.out", delimiter=",", names=True)
    b = np.genfromtxt(tmp_path / "b.csv.out", delimiter=",", names=True)
    assert_allclose(b["error"], a["error"], rtol=0, atol=1e-9)
    assert np.max(np.abs(a["error"])) < 1e-3 and not np.any(a["out_of_range"])


def test_lookup_table_model(linear_files, check_file, tmp_path):
    files, _ = linear_files
    model = tmp_path / "lut.json"
    assert run_cascal("fit", *files, "--method", "lut", "-o", model).returncode == 0
    out = tmp_path / "v.csv"
    res = run_cascal("verify", model, check_file, "--mpe", "1", "-o", out)
    assert res.returncode == 3, res.stderr  # (the point outside the range)
    assert "no uncertainty" in res.stderr and "the 2000 check points inside conform" in res.stdout
    table = np.genfromtxt(out, delimiter=",", names=True)
    assert np.all(np.isnan(table["En"]))
    assert np.all(table["conforms"][:-1] == 1) and np.isnan(table["conforms"][-1])


@pytest.fixture(scope="module")
def bad_runs(linear_model, check_file, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("verify_bad")
    nan = tmp / "nan.csv"
    nan.write_text("device,ref\n0.5,0.5\n0.6,nan\n")
    one = tmp / "one.csv"
    one.write_text("device\n0.5\n")
    far = tmp / "far.csv"
    far.write_text("device,ref\n5,5\n6,6\n")
    huge = tmp / "huge.csv"
    huge.write_text("device,ref\n0.5,0.5\n0.6,1e300\n")
    corrupt = tmp / "corrupt.json"
    corrupt.write_text(linear_model.read_text()[:-40])
    cases = {
        "nan": ([linear_model, nan], ["nan.csv", "row 3"]),
        "one_column": ([linear_model, one], ["one.csv", "--x-column"]),
        "no_column": ([linear_model, check_file, "--y-column", "truth"], ["truth"]),
        "all_outside": (
            [linear_model, far],
            ["far.csv", "no check point lies inside", "in another unit than the model's (m)?"],
        ),
        "reading_u": ([linear_model, check_file, "--reading-u", "-1"], ["--reading-u"]),
        "reference_u": ([linear_model, check_file, "--reference-u", "inf"], ["--reference-u"]),
        "mpe": ([linear_model, check_file, "--mpe", "0"], ["--mpe"]),
        "negative_exponent": (
            [linear_model, check_file, "--reference-u", "-1e-9"],
            ["--reference-u: expected a number >= 0"],
        ),
        "same_column": (
            [linear_model, check_file, "--x-column", "ref", "--y-column", "ref"],
            ["both name 'ref'"],
        ),
        "huge": ([linear_model, huge], ["huge.csv", "row 3", "too large"]),
        "plot_suffix": ([linear_model, check_file, "--plot", tmp / "v.txt"], [".png"]),
        "output_is_check": ([linear_model, check_file, "-o", check_file], ["is an input"]),
        "corrupt": ([corrupt, check_file], ["corrupt.json"]),
    }
    return run_bad_cases("verify", cases, tmp)


@pytest.mark.parametrize(
    "name",
    ["nan", "one_column", "no_column", "all_outside", "reading_u", "reference_u", "mpe",
     "negative_exponent", "same_column", "huge", "plot_suffix", "output_is_check", "corrupt"],
)  # fmt: skip
def test_bad_input_exits_2_and_writes_nothing(bad_runs, name, check_file):
    assert_refused(*bad_runs[name])
    assert check_file.read_text().startswith("device,ref\n")


def test_check_points_with_the_reference_in_another_unit_are_warned_of(
    linear_model, check_file, tmp_path
):
    """A review's case: check points with the device readings in m and the reference in
    mm (as an interferometer exports) were judged as drift ("has the device or the test
    bed changed since the fit?"); the columns' spans are compared as for a stage file."""
    src = np.loadtxt(check_file, delimiter=",", skiprows=1)
    mm = tmp_path / "check_mm.csv"
    np.savetxt(mm, np.c_[src[:, 0], 1e3 * src[:, 1]], delimiter=",", header="device,reference",
               comments="", fmt="%.15g")  # fmt: skip
    res = run_cascal("verify", linear_model, mm)
    assert res.returncode == 0, res.stderr
    assert "check_mm.csv: the readings of column 'reference' span" in res.stderr
    assert "different units (mm and m)?" in res.stderr
    plain = run_cascal("verify", linear_model, check_file)
    assert plain.returncode == 0 and "different units" not in plain.stderr
