"""``cascal fit`` and ``cascal correct`` end to end, against the simulated truth and
against the library in memory."""

from __future__ import annotations

import numpy as np
import pytest
from cli_helpers import run_cascal

from cascal.io.csvout import auto_decimals
from cascal.io.data import read_readings, read_stage, read_table
from cascal.io.modelfile import load_model, save_model
from cascal.workflow import correct, fit_model


@pytest.fixture(scope="module")
def corrected(linear_model, linear_files, tmp_path_factory):
    _, readings = linear_files
    out = tmp_path_factory.mktemp("corrected") / "out.csv"
    res = run_cascal("correct", linear_model, readings, "-o", out)
    assert res.returncode == 0, res.stderr
    return res, read_table(out, ("reading", "corrected", "u", "U", "out_of_range"))


def test_correction_beats_raw_readings_tenfold_and_U_covers(corrected, linear_case):
    _, table = corrected
    reading, fixed, u, U, out = table.columns
    assert table.source.columns == ("reading", "corrected", "u", "U", "out_of_range")
    truth = linear_case.truth  # the true map at each reading: device reading -> position
    inside = out == 0
    raw = np.sqrt(np.mean((reading - truth)[inside] ** 2))
    err = (fixed - truth)[inside]
    assert np.sqrt(np.mean(err**2)) * 10 <= raw
    assert np.mean(np.abs(err) <= U[inside]) >= 0.90
    np.testing.assert_allclose(U, 2 * u, atol=2e-12)


def test_out_of_range_readings_are_flagged_and_warned(corrected, linear_case, linear_model):
    res, table = corrected
    reading, *_, out = table.columns
    lo, hi = load_model(linear_model).calibrated_range
    np.testing.assert_array_equal(out == 1, (reading < lo) | (reading > hi))
    n_out = int(np.sum(out))
    assert n_out == 1  # the demo puts one reading beyond the device's calibrated range
    assert f"warning: {n_out} of {reading.size} readings lie outside" in res.stderr
    assert f"row {reading.size + 1}" in res.stderr


def test_command_output_equals_library_in_memory(corrected, linear_files, linear_case):
    """The command's numbers are the in-memory fit's, up to the decimals written."""
    files, readings = linear_files
    res, table = corrected
    model = fit_model([read_stage(f) for f in files])
    c = correct(model, read_readings(readings).columns[0])
    inside = ~c.out_of_range  # the decimals come from the readings inside the range
    decimals = auto_decimals([c.reading[inside], c.corrected[inside]], c.u[inside])
    assert f"({decimals} decimals" in res.stdout
    tol = 0.5 * 10.0**-decimals + 1e-15
    np.testing.assert_allclose(table.columns[1], c.corrected, rtol=0, atol=tol)
    np.testing.assert_allclose(table.columns[2], c.u, rtol=0, atol=tol)


@pytest.mark.filterwarnings("ignore:the u of method 'homoscedastic'")
@pytest.mark.parametrize("method", ["bayes", "homoscedastic", "lut"])
def test_fit_save_load_correct_is_bit_identical(method, linear_files, linear_case, tmp_path):
    files, _ = linear_files
    model = fit_model([read_stage(f) for f in files], method=method, n_restarts=2)
    loaded = load_model(save_model(tmp_path / "m.json", model))
    r = linear_case.readings
    a, b = correct(model, r), correct(loaded, r)
    np.testing.assert_array_equal(a.corrected, b.corrected)
    np.testing.assert_array_equal(a.u, b.u)
    np.testing.assert_array_equal(a.out_of_range, b.out_of_range)
    big = np.resize(r, 50_000)  # enough readings for the interpolation table
    np.testing.assert_array_equal(correct(model, big).corrected, correct(loaded, big).corrected)
    exact = model.fitted.correct(r, return_std=method != "lut")
    again = loaded.fitted.correct(r, return_std=method != "lut")
    np.testing.assert_array_equal(np.asarray(exact), np.asarray(again))
    assert loaded.method == method


def test_lut_leaves_u_empty_and_says_so(linear_files, tmp_path):
    files, readings = linear_files
    model, out = tmp_path / "lut.json", tmp_path / "lut.csv"
    assert run_cascal("fit", *files, "-o", model, "--method", "lut").returncode == 0
    res = run_cascal("correct", model, readings, "-o", out)
    assert res.returncode == 0, res.stderr
    assert "method lut gives no uncertainty" in res.stderr
    rows = out.read_text().splitlines()
    assert rows[0] == "reading,corrected,u,U,out_of_range"
    assert all(r.split(",")[2:4] == ["", ""] for r in rows[1:])
    # a review's case: export's errors about the model did not name it
    res = run_cascal("export", model, "-o", tmp_path / "lut.h")
    assert res.returncode == 2 and f"error: {model}: a lookup-table (lut) model" in res.stderr
    assert not (tmp_path / "lut.h").exists()


def test_homoscedastic_u_is_named_as_too_small(linear_files, tmp_path):
    """A review's simulations: U = 2u of a homoscedastic cascade covered 66 % of the errors;
    fit and correct say so (a bayes model does not warn)."""
    files, readings = linear_files
    for method in ("homoscedastic", "bayes"):
        model, out = tmp_path / f"{method}.json", tmp_path / f"{method}.csv"
        fit = run_cascal("fit", *files, "-o", model, "--method", method, "--restarts", "2")
        cor = run_cascal("correct", model, readings, "-o", out)
        assert fit.returncode == 0 and cor.returncode == 0, (fit.stderr, cor.stderr)
        # export writes the same u to a CSV table's u column (a review's case: in silence)
        exp = run_cascal("export", model, "-o", tmp_path / f"{method}_table.csv")
        assert exp.returncode == 0, exp.stderr
        for res, cmd in ((fit, "fit"), (cor, "correct"), (exp, "export")):
            named = f"cascal {cmd}: warning: u of --method homoscedastic leaves" in res.stderr
            assert named == (method == "homoscedastic"), res.stderr


def test_columns_picked_by_name_and_empty_out_of_range(linear_case, tmp_path):
    st0, st1 = linear_case.stages
    a = tmp_path / "tb.csv"
    a.write_text(
        "time,reference,testbed,temp\n"
        + "".join(
            f"{i},{y!r},{x!r},20.0\n"
            for i, (x, y) in enumerate(zip(st0.x.tolist(), st0.y.tolist(), strict=True))
        )
    )
    b = tmp_path / "dev.csv"
    b.write_text(
        "device,testbed\n"
        + "".join(f"{x!r},{y!r}\n" for x, y in zip(st1.x.tolist(), st1.y.tolist(), strict=True))
    )
    model = tmp_path / "m.json"
    res = run_cascal(
        "fit", a, b, "-o", model, "--x-column", "testbed", "--x-column", "device",
        "--y-column", "reference", "--y-column", "testbed", "--restarts", "2",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "Stage 0 (" in res.stdout and "129 rows, 43 points" in res.stdout
    readings = tmp_path / "r.csv"
    readings.write_text("id,reading\n1,0.5\n2,-3.0\n")
    out = tmp_path / "o.csv"
    res = run_cascal("correct", model, readings, "-o", out, "--column", "reading",
                     "--out-of-range", "empty")  # fmt: skip
    assert res.returncode == 0, res.stderr
    rows = out.read_text().splitlines()
    assert rows[2].split(",")[1:] == ["", "", "", "1"]
    assert rows[1].split(",")[-1] == "0" and rows[1].split(",")[1] != ""


def test_a_far_outlier_keeps_the_other_rows_digits(linear_files, tmp_path):
    """A reading far outside the range (here 1e9) does not cut the decimals of the rows
    inside it: they are written as precisely as without it."""
    files, _ = linear_files
    model = tmp_path / "lut.json"
    assert run_cascal("fit", *files, "-o", model, "--method", "lut").returncode == 0
    readings = tmp_path / "r.csv"
    readings.write_text("reading\n0.5\n0.6\n1e9\n")
    out = tmp_path / "c.csv"
    assert run_cascal("correct", model, readings, "-o", out).returncode == 0
    rows = out.read_text().splitlines()[1:]
    want = correct(load_model(model), np.array([0.5, 0.6])).corrected
    got = np.array([float(r.split(",")[1]) for r in rows[:2]])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert rows[2].endswith(",1")


def test_a_zero_offset_is_named_and_fitted_with_mean_offset(linear_files, linear_case, tmp_path):
    """The device's zero 100 m off its test bed's (the corrections 1900 times their
    spread): the fit names the offset and points to --mean offset, with which the model is
    the unshifted one, moved by 100 m."""
    (ref, dev), _ = linear_files
    shifted = tmp_path / "device_offset.csv"
    head, *rows = dev.read_text().splitlines()
    moved = [f"{float(a) + 100.0!r},{b}" for a, b in (r.split(",") for r in rows)]
    shifted.write_text("\n".join([head, *moved]) + "\n")
    stuck = run_cascal("fit", ref, shifted, "-o", tmp_path / "stuck.json", "--no-screening")
    assert stuck.returncode == 0, stuck.stderr
    assert "device_offset.csv: the corrections average -100" in stuck.stderr
    assert "--mean offset" in stuck.stderr and "stuck" not in stuck.stderr
    fits = {}
    for name, stage in (("plain", dev), ("offset", shifted)):
        out = tmp_path / f"{name}.json"
        res = run_cascal("fit", ref, stage, "-o", out, "--mean", "offset", "--no-screening")
        assert res.returncode == 0 and "--mean offset" not in res.stderr, res.stderr
        fits[name] = load_model(out)
    assert "prior mean offset -100" in res.stdout
    r = linear_case.readings
    a, b = correct(fits["plain"], r), correct(fits["offset"], r + 100.0)
    inside = ~a.out_of_range
    np.testing.assert_allclose(b.corrected[inside], a.corrected[inside], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.u[inside], a.u[inside], rtol=1e-4)
    err = a.corrected[inside] - linear_case.truth[inside]
    assert np.sqrt(np.mean(err**2)) < 0.1 * np.sqrt(np.mean((r - linear_case.truth)[inside] ** 2))


def test_too_few_reference_points_are_named(tmp_path):
    """Three reference points: the fit takes them for noise about the identity (its length
    scale at its bound, its noise over 1e4 times its variance), and says that u cannot be
    trusted."""
    ref, dev = tmp_path / "ref.csv", tmp_path / "dev.csv"
    ref.write_text("testbed,reference\n0,0.0001\n0.5,0.4990\n1.0,1.0002\n")
    dev.write_text("device,testbed\n0.1,0.1003\n0.5,0.5002\n0.9,0.8995\n")
    res = run_cascal("fit", ref, dev, "-o", tmp_path / "m.json")
    assert res.returncode == 0, res.stderr
    assert "ref.csv: the learned noise sits at the upper end of its range" in res.stderr
    assert "ref.csv: the fitted length scale sits at the lower end of its range" in res.stderr
    assert "dev.csv: the fitted length scale sits at the lower end of its range" in res.stderr


@pytest.mark.parametrize("dest", ["-", "/dev/stdout"])
def test_a_table_written_to_stdout_keeps_it_to_itself(linear_model, linear_files, dest):
    """``-o -`` (or /dev/stdout) writes the CSV to standard output and the command's own
    lines to standard error, so the output can be piped on."""
    _, readings = linear_files
    res = run_cascal("correct", linear_model, readings, "-o", dest)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0] == "reading,corrected,u,U,out_of_range"
    assert len(lines) == len(readings.read_text().splitlines())
    assert "Corrected " in res.stderr and "Corrected" not in res.stdout


def test_a_table_appended_to_a_file_through_stdout_keeps_the_file(
    linear_model, linear_files, tmp_path
):
    """``-o - >> log.csv``: standard output is a file opened for appending; the table is
    added after what it held (a rename onto it would have replaced it)."""
    import shlex
    import subprocess
    import sys
    from pathlib import Path

    _, readings = linear_files
    log = tmp_path / "log.csv"
    log.write_text("# earlier line\n")
    script = shlex.quote(str(Path(sys.executable).with_name("cascal")))
    q = shlex.quote
    cmd = f"{script} correct {q(str(linear_model))} {q(str(readings))} -o - >> {q(str(log))}"
    res = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    lines = log.read_text().splitlines()
    assert lines[:2] == ["# earlier line", "reading,corrected,u,U,out_of_range"]
    assert len(lines) == len(readings.read_text().splitlines()) + 1
    closed = subprocess.run(["bash", "-c", cmd.replace(f">> {q(str(log))}", ">&-")],
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert closed.returncode == 1 and "no standard output to write to" in closed.stderr
    assert "Traceback" not in closed.stderr


def test_a_reader_that_leaves_early_ends_the_command_quietly(linear_model):
    """``cascal info MODEL | true``: the reader is gone before anything is written; the
    command stops without a message, with the status a shell gives a process SIGPIPE ended."""
    import shlex
    import subprocess
    import sys
    from pathlib import Path

    script = Path(sys.executable).with_name("cascal")
    cmd = f"{shlex.quote(str(script))} info {shlex.quote(str(linear_model))} | true"
    res = subprocess.run(
        ["bash", "-c", cmd + "; echo ${PIPESTATUS[0]}"], capture_output=True, text=True, timeout=60
    )
    assert res.stdout.strip() == "141", (res.stdout, res.stderr)
    assert res.stderr == ""


def test_a_stage_file_with_its_columns_swapped_is_named(tmp_path):
    """The device file's header says (testbed, device): the chain reference -> testbed ->
    device then reads backwards, which the names show; generic names say nothing."""
    t = np.linspace(0.0, 1.0, 30)
    testbed = t + 1e-3 * np.sin(5 * t)
    ref = tmp_path / "ref.csv"
    pairs = zip(testbed.tolist(), t.tolist(), strict=True)
    ref.write_text("testbed,reference\n" + "".join(f"{a!r},{b!r}\n" for a, b in pairs))
    d = np.linspace(0.1, 0.9, 25)
    swapped = tmp_path / "dev.csv"
    rows = zip((d + 2e-3 * np.cos(3 * d)).tolist(), d.tolist(), strict=True)
    swapped.write_text("testbed,device\n" + "".join(f"{a!r},{b!r}\n" for a, b in rows))
    res = run_cascal("fit", ref, swapped, "-o", tmp_path / "m.json", "--no-screening")
    assert res.returncode == 0, res.stderr
    assert "dev.csv: its columns (testbed, device) follow " in res.stderr
    assert "ref.csv's (testbed, reference), sharing a name in the same place" in res.stderr
    assert "are one file's columns swapped?" in res.stderr
    for f in (ref, swapped):  # the same files with generic headers: no warning
        f.write_text("x,y\n" + f.read_text().split("\n", 1)[1])
    res = run_cascal("fit", ref, swapped, "-o", tmp_path / "g.json", "--no-screening")
    assert res.returncode == 0 and "swapped" not in res.stderr, res.stderr


def test_readings_all_outside_the_range_suggest_a_unit(linear_model, tmp_path):
    """A user review's case: readings in mm against a model in m were all flagged, one by
    one, with no word of the likely cause; the message now asks about the unit."""
    mm = tmp_path / "mm.csv"
    mm.write_text("reading\n300.0\n450.5\n600.25\n")
    res = run_cascal("correct", linear_model, mm, "-o", tmp_path / "c.csv")
    assert res.returncode == 0, res.stderr
    assert "3 of 3 readings lie outside" in res.stderr
    assert "all far off: readings in another unit than the model's (m)?" in res.stderr
    res = run_cascal("correct", linear_model, mm, "-o", tmp_path / "e.csv", "--out-of-range",
                     "error")  # fmt: skip
    assert res.returncode == 2 and "another unit than the model's (m)?" in res.stderr
    near = tmp_path / "near.csv"  # just beyond the range (a review's case): no such hint
    near.write_text("reading\n0.945\n0.96\n")
    res = run_cascal("correct", linear_model, near, "-o", tmp_path / "n.csv")
    assert "2 of 2 readings lie outside" in res.stderr and "unit" not in res.stderr


def test_correct_echoes_readings_as_read(linear_model, linear_files, tmp_path):
    """A review's case: readings kept with more decimals than the corrections need were
    written back rounded to the corrections' decimals (up to 5e-10 deg off the input), so
    an output row did not always match its input row. They are now echoed exactly."""
    _, readings = linear_files
    r = read_readings(readings).columns[0]
    lo, hi = load_model(linear_model).calibrated_range
    fine = np.round(np.linspace(lo, hi, 2001) + 1e-9 * np.sin(np.arange(2001)), 14)
    fine[-1] = round(hi + 0.01234567890123, 14)  # out of range: echoed as read too (a review)
    src = tmp_path / "fine.csv"
    src.write_text("reading\n" + "".join(f"{x!r}\n" for x in fine.tolist()))
    out = tmp_path / "out.csv"
    res = run_cascal("correct", linear_model, src, "-o", out)
    assert res.returncode == 0 and "1 of 2001 readings lie outside" in res.stderr, res.stderr
    decimals = int(res.stdout.split("(")[1].split(" decimals")[0])
    assert decimals < 14 and "; readings as read, 14)" in res.stdout
    table = read_table(out, ("reading", "corrected"))
    np.testing.assert_array_equal(table.columns[0], fine)  # every bit
    cells = [line.split(",")[1] for line in out.read_text().splitlines()[1:]]
    assert {len(c.split(".")[1]) for c in cells} == {decimals}  # corrections as before
    plain = tmp_path / "plain.csv"  # readings with few decimals: the message as before
    plain.write_text("reading\n" + "".join(f"{x:.3f}\n" for x in r[:50].tolist()))
    res = run_cascal("correct", linear_model, plain, "-o", tmp_path / "p.csv")
    assert res.returncode == 0 and "readings as read" not in res.stdout, res.stderr


def test_columns_that_name_another_unit_are_warned_of(tmp_path):
    """A user review's case: columns named encoder_mm and laser_mm fitted with --unit left
    at its default (m), every label then 1000 times off, without a word."""
    stage = tmp_path / "s.csv"
    stage.write_text("encoder_mm,laser_mm\n0,0.01\n10,10.02\n20,20.01\n30,30.0\n40,40.03\n")
    res = run_cascal("fit", stage, "-o", tmp_path / "m.json")
    assert res.returncode == 0, res.stderr
    assert "name the unit mm, and the readings are taken as m (--unit)" in res.stderr
    res = run_cascal("fit", stage, "-o", tmp_path / "m.json", "--unit", "mm")
    assert res.returncode == 0 and "name the unit" not in res.stderr
    plain = tmp_path / "p.csv"  # no unit named, or a word that only looks like one
    plain.write_text("m_encoder,reference\n0,0.01\n10,10.02\n20,20.01\n30,30.0\n40,40.03\n")
    assert "name the unit" not in run_cascal("fit", plain, "-o", tmp_path / "p.json").stderr
