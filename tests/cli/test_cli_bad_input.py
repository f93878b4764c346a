"""Bad input through the installed command: exit status 2, one line naming the file, the
row and the problem, no traceback and no output file.

The commands run concurrently in a session fixture (each test then checks its own case),
which keeps the interpreter start-ups from adding up.
"""

from __future__ import annotations

import json
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import interrupted, run_cascal

GOOD = "a,b\n1.0,1.1\n2.0,2.05\n3.0,3.2\n4.0,4.1\n"

#: name -> (stage file content, extra arguments of fit, words the message must contain)
FIT_CASES = {
    "missing_column": ("a\n1\n2\n3\n", [], ["row 1", "missing columns", "expected 2"]),
    "extra_columns": ("a,b,c\n1,1,1\n2,2,2\n3,3,3\n", [], ["row 1", "extra columns", "'c'"]),
    "unknown_column": (GOOD, ["--x-column", "nope", "--y-column", "b"], ["row 1", "'nope'"]),
    "non_numeric": (
        "a,b\n1,1\n2,2\n3,abc\n4,4\n",
        [],
        ["row 4", "column 'b'", "expected a number", "'abc'"],
    ),
    "empty_cell": ("a,b\n1,1\n2,\n3,3\n", [], ["row 3", "column 'b'", "empty cell"]),
    "nan": ("a,b\n1,1\nnan,2\n3,3\n", [], ["row 3", "column 'a'", "finite", "'nan'"]),
    "inf": ("a,b\n1,1\n2,2\n3,-inf\n", [], ["row 4", "column 'b'", "finite"]),
    "too_few_rows": ("a,b\n1,1\n2,2\n", [], ["row 3", "at least 3 data rows", "got 2"]),
    "huge_cell": (GOOD + "5," + "6" * 200_000 + "\n", [], ["row 6", "not readable CSV"]),
    "stray_cr": ("a,b\n1,1\n2\r,2\n3,3\n", [], ["row 3", "missing cells"]),
    "period_without_periodic": (
        GOOD,
        ["--period", "360"],
        ["--period is the period of --kernel periodic, not of se"],
    ),
    "mean_for_lookup_tables": (
        GOOD,
        ["--method", "lut", "--mean", "offset"],
        ["--mean offset", "no prior mean"],
    ),
    "kernel_for_lookup_tables": (
        GOOD,
        ["--method", "lut", "--kernel", "matern32"],
        ["--kernel matern32", "have no kernel"],
    ),
    "rotary_lookup_tables": (  # a review: accepted, and the model was not rotary
        GOOD,
        ["--method", "lut", "--kernel", "periodic", "--period", "360"],
        ["--kernel periodic", "do not wrap at the turn", "--method bayes"],
    ),
    "period_too_short": (
        GOOD,
        ["--kernel", "periodic", "--period", "2"],
        ["row 5", "span 3", "--period (2)", "one turn"],
    ),
    "rotary_closure": (  # a turn's readings and the start read again at its end
        "enc,ref\n0.0012,0\n90.0009,90\n180.0012,180\n270.0015,270\n360.0012,360\n",
        ["--kernel", "periodic", "--period", "360"],
        ["row 6", "rows 2 and 6 read 0.0012 and 360.0012", "a closure reading", "--exclude"],
    ),
    "rotary_closure_twice": (  # (a diff review: the advice named one row of two)
        "enc,ref\n0.0012,0\n90.0009,90\n180.0012,180\n270.0015,270\n360.0012,360\n"
        "360.0014,360.0001\n",
        ["--kernel", "periodic", "--period", "360"],
        ["row 7", "leave the readings a turn past the first out (--exclude", ":6,7)"],
    ),
    "too_few_positions": ("a,b\n1,1\n1,1.1\n2,2\n", [], ["3 or more distinct positions"]),
    "extra_cell": ("a,b\n1,1\n2,2,7\n3,3\n", [], ["row 3", "extra cells"]),
    "missing_cell": ("a,b\n1,1\n2\n3,3\n", [], ["row 3", "missing cells"]),
    "no_header": ("1,1\n2,2\n3,3\n4,4\n", [], ["row 1", "header"]),
    "empty_file": ("", [], ["row 1", "header"]),
    "not_increasing": (
        "a,b\n1,1\n2,2.5\n3,2.4\n4,4\n",
        [],
        ["row 4", "(of b or of a)", "not above", "(row 3)", "one-to-one", "a mistyped cell"],
    ),
    "reversed_direction": (
        "a,b\n1,-1\n2,-2\n3,-3\n4,-4\n",
        [],
        ["row 3", "3 of its 3 steps go back", "direction reversed"],
    ),
    "noisier_than_the_steps": (
        "a,b\n1,1\n2,2.5\n3,2.4\n4,4\n5,5.2\n6,5.1\n7,7\n",
        [],
        ["row 4", "not above", "2 of its 6 steps go back", "closer together than"],
    ),
    "stuck_reference": (  # a review: flat steps had been said to "go back"
        "a,b\n1,0.5\n2,0.5\n3,0.5\n4,0.5\n",
        [],
        ["3 of its 3 steps are flat (b the same at other a)", "did not move, or a constant"],
    ),
    "flat_steps_among_rising_ones": (
        "a,b\n1,1\n2,2\n3,2\n4,4\n5,5\n6,5\n7,7\n",
        [],
        ["not above", "2 of its 6 steps are flat", "closer together than the readings' resolution"],
    ),
    "back_and_flat_steps": (
        "a,b\n1,1\n2,2.5\n3,2.4\n4,4\n5,5\n6,5\n7,7\n",
        [],
        ["1 of its 6 steps go back and 1 are flat", "closer together than the readings' noise"],
    ),
    "periodic_without_period": (GOOD, ["--kernel", "periodic"], ["--period"]),
    "negative_period": (GOOD, ["--kernel", "periodic", "--period", "-3"], ["--period", "positive"]),
}
NO_FILE_NAMED = {
    "periodic_without_period",
    "period_without_periodic",
    "mean_for_lookup_tables",
    "kernel_for_lookup_tables",
    "rotary_lookup_tables",
    "negative_period",
    "export_bad_name",
    "export_bad_tolerance",
}


def _cases(tmp: Path, model: Path, files: list[Path], readings: Path) -> dict[str, tuple]:
    """Every case: name -> (argv, output path that must not appear, words, file name)."""
    out: dict[str, tuple] = {}
    for name, (text, extra, words) in FIT_CASES.items():
        path = tmp / f"{name}.csv"
        path.write_text(text)
        dest = tmp / f"{name}.json"
        out[name] = (["fit", path, "-o", dest, *extra], dest, words, path.name)
    # A device stage whose test-bed readings leave the test bed's calibrated range.
    lines = files[1].read_text().splitlines()
    top = max(float(r.split(",")[1]) for r in lines[1:])
    last = float(lines[-1].split(",")[0])
    outside = tmp / "outside.csv"
    beyond = [f"{last + 0.01!r},{top + 0.5!r}", f"{last + 0.02!r},{top + 0.6!r}"]
    outside.write_text("\n".join([*lines, *beyond]) + "\n")
    dest = tmp / "outside.json"
    row = f"row {len(lines) + 1}"
    words = [row, "column 'testbed'", "outside the range", "calibrated by the stage above"]
    # every such row, ready to leave out (a user review: found one run at a time)
    words.append(f"or leave them out (--exclude outside.csv:{len(lines) + 1},{len(lines) + 2})")
    out["device_outside_testbed"] = (
        ["fit", files[0], outside, "-o", dest],
        dest,
        words,
        "outside.csv",
    )
    # Model files: truncated, edited, newer and older schema, not JSON, missing.
    text = model.read_text()
    doc = json.loads(text)
    variants = {
        "model_truncated": (text[: len(text) // 2], ["(the file ends early: truncated?)"]),
        "model_edited": (text.replace('"unit": "m"', '"unit": "mm"'), ["checksum", "edited"]),
        "model_newer": (
            text.replace('"schema_version": 1', '"schema_version": 3'),
            ["schema version 3", "newer", "upgrade cascal"],
        ),
        "model_older": (
            text.replace('"schema_version": 1', '"schema_version": 0'),
            ["schema version 0", "not supported"],
        ),
        "model_not_json": (
            "stage,x\n1,2\n",
            ["not a valid model file: it starts with 'stage,x'", "reads like a CSV file"],
        ),
        "model_other_json": (json.dumps({"stages": doc["stages"][:1]}), ["not a cascal model"]),
    }
    for name, (content, words) in variants.items():
        path = tmp / f"{name}.json"
        path.write_text(content)
        dest = tmp / f"{name}.csv"
        out[name] = (["correct", path, readings, "-o", dest], dest, words, path.name)
    dest = tmp / "missing_model.csv"
    argv = ["correct", tmp / "nowhere.json", readings, "-o", dest]
    out["model_missing"] = (argv, dest, ["cannot read"], "nowhere.json")
    # Readings: non-numeric, and out of range when asked to refuse.
    bad = tmp / "bad_readings.csv"
    bad.write_text("reading\n0.5\n0.6\nzero\n")
    dest = tmp / "bad_readings_out.csv"
    out["readings_non_numeric"] = (
        ["correct", model, bad, "-o", dest], dest, ["row 4", "column 'reading'", "'zero'"],
        bad.name,
    )  # fmt: skip
    dest = tmp / "refused.csv"
    n_rows = len(readings.read_text().splitlines())
    out["readings_out_of_range_refused"] = (
        ["correct", model, readings, "-o", dest, "--out-of-range", "error"], dest,
        [f"row {n_rows}", "outside the calibrated range"], readings.name,
    )  # fmt: skip
    dest = tmp / "edited_report.html"
    out["report_edited_model"] = (
        ["report", tmp / "model_edited.json", "-o", dest], dest, ["checksum"], "model_edited.json"
    )  # fmt: skip
    plain_out = tmp / "plain_out.csv"
    plain_out.write_text("x")
    bad_tb = tmp / "non_numeric.csv"
    dest = tmp / "fleet_bad_testbed"
    out["fleet_bad_testbed"] = (
        ["fit-devices", bad_tb, "--devices", files[0].parent, "-o", dest], dest, ["row 4"],
        bad_tb.name,
    )  # fmt: skip
    twins = tmp / "twins"
    twins.mkdir()
    for name in ("a.csv", "a.CSV"):
        (twins / name).write_text(GOOD)
    dest = tmp / "fleet_twins"
    out["fleet_twin_devices"] = (
        ["fit-devices", files[0], "--devices", twins, "-o", dest], dest,
        ["a.CSV and a.csv would both be device a"], "twins",
    )  # fmt: skip
    dest = tmp / "fleet_no_folder"
    out["fleet_no_folder"] = (
        ["fit-devices", files[0], "--devices", tmp / "nowhere", "-o", dest], dest,
        ["--devices", "no such folder"], "nowhere",
    )  # fmt: skip
    fleet = tmp / "fleet_in_place"
    fleet.mkdir()
    (fleet / "a.csv").write_text(GOOD)
    out["fleet_output_is_the_devices_folder"] = (
        ["fit-devices", files[0], "--devices", fleet, "-o", fleet], fleet / "testbed.json",
        ["the same folder as --devices"], "fleet_in_place",
    )  # fmt: skip
    # Commands writing a folder of outputs check it before any work.
    for name, cmd in [
        ("study_out_is_a_file", ["study", "--trials", "2", "--workers", "1"]),
        ("example_out_is_a_file", ["example"]),
        ("demo_out_is_a_file", ["demo"]),
    ]:
        out[name] = (
            [*cmd, "--out", plain_out], plain_out / "x",
            ["--out", "expected a folder, got an existing file"], plain_out.name,
        )  # fmt: skip
    # Compensation tables: a file type that is neither, a name C cannot take, a tolerance
    # that is no positive number, an edited model.
    for name, dest, extra, words in [
        ("export_bad_suffix", tmp / "table.txt", [], ["table.txt", ".h (C header) or .csv"]),
        ("export_bad_name", tmp / "t1.h", ["--name", "9lives"], ["C identifier", "'9lives'"]),
        ("export_bad_tolerance", tmp / "t2.h", ["--tolerance=-1e-6"], ["positive number"]),
        ("export_name_for_csv", tmp / "t4.csv", ["--name", "axis"], ["--name", "C header"]),
    ]:
        out[name] = (["export", model, "-o", dest, *extra], dest, words, dest.name)
    dest = tmp / "t3.h"
    out["export_edited_model"] = (
        ["export", tmp / "model_edited.json", "-o", dest], dest, ["checksum"], "model_edited.json"
    )  # fmt: skip
    # Outputs that cannot be written, refused before any fitting.
    taken = tmp / "taken_folder"
    taken.mkdir()
    plain = tmp / "plain_file"
    plain.write_text("x")
    out["output_is_a_folder"] = (
        ["fit", files[0], "-o", taken], tmp / "never.json", ["expected a file name", "folder"],
        taken.name,
    )  # fmt: skip
    out["output_under_a_file"] = (
        ["correct", model, readings, "-o", plain / "c.csv"], plain / "c.csv",
        ["is a file, not a folder"], plain.name,
    )  # fmt: skip
    # A study folder whose database is not one.
    folder = tmp / "study_corrupt"
    folder.mkdir()
    (folder / "study.sqlite").write_bytes(b"not a database, just bytes\n" * 40)
    out["study_corrupt_database"] = (
        ["study", "--trials", "2", "--workers", "1", "--out", folder], folder / "trials.csv",
        ["not a readable cascal study database", "choose another --out folder"], "study.sqlite",
    )  # fmt: skip
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory, linear_model, linear_files):
    tmp = tmp_path_factory.mktemp("bad")
    cases = _cases(tmp, linear_model, *linear_files)
    with ThreadPoolExecutor(4) as pool:
        done = pool.map(lambda c: run_cascal(*c[0]), cases.values())
        results = dict(zip(cases, done, strict=True))
    return cases, results


ALL = [
    *FIT_CASES,
    "device_outside_testbed",
    "model_truncated",
    "model_edited",
    "model_newer",
    "model_older",
    "model_not_json",
    "model_other_json",
    "model_missing",
    "readings_non_numeric",
    "readings_out_of_range_refused",
    "report_edited_model",
    "fleet_bad_testbed",
    "fleet_no_folder",
    "fleet_twin_devices",
    "fleet_output_is_the_devices_folder",
    "study_out_is_a_file",
    "example_out_is_a_file",
    "demo_out_is_a_file",
    "study_corrupt_database",
    "output_is_a_folder",
    "output_under_a_file",
    "export_bad_suffix",
    "export_bad_name",
    "export_bad_tolerance",
    "export_edited_model",
    "export_name_for_csv",
]


@pytest.mark.parametrize("name", ALL)
def test_bad_input_exits_2_with_one_line(runs, name):
    cases, results = runs
    argv, dest, words, file_name = cases[name]
    res = results[name]
    assert res.returncode == 2, (res.stdout, res.stderr)
    err = res.stderr.strip()
    assert "Traceback" not in res.stderr
    assert "\n" not in err, err
    assert err.startswith(f"cascal {argv[0]}: error: "), err
    if name not in NO_FILE_NAMED:
        assert file_name in err, err
    for w in words:
        assert w in err, (w, err)
    assert not Path(dest).exists(), f"{dest} was written"


def test_every_case_is_checked(runs):
    cases, _ = runs
    assert sorted(cases) == sorted(ALL)


def test_restarts_beyond_the_cap_are_refused(tmp_path):
    """Optimiser starts have a cap (a mistyped 100000 ran for hours, with no progress)."""
    stage = tmp_path / "s.csv"
    stage.write_text(GOOD)
    res = run_cascal("fit", stage, "-o", tmp_path / "m.json", "--restarts", "101")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "argument --restarts: expected at most 100, got 101" in res.stderr
    assert not (tmp_path / "m.json").exists()


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("--restarts", "\uff15"), "argument --restarts: expected a whole number, got '\uff15'"),
        (("--seed", "1_000"), "argument --seed: expected a whole number, got '1_000'"),
        (("--period", "3_60", "--kernel", "periodic"), "argument --period: expected a number"),
        (("--exclude", "s.csv:1_0"), "--exclude s.csv:1_0: expected row numbers"),
        (("--restarts", "abc"), "argument --restarts: expected a whole number, got 'abc'"),
    ],
)
def test_options_take_numbers_as_csv_cells_write_them_in_one_line(tmp_path, args, words):
    """A fuzz review: options took full-width digits and digit-group underscores, which
    the CSV reader refuses, and argparse's errors came under a usage block of 3 to 6
    lines; they are refused in one line now."""
    stage = tmp_path / "s.csv"
    stage.write_text(GOOD)
    res = run_cascal("fit", stage, "-o", tmp_path / "m.json", *args)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert words in res.stderr and "\n" not in res.stderr.strip(), res.stderr
    assert res.stderr.startswith("cascal fit: error: ")
    assert not (tmp_path / "m.json").exists()


def test_an_output_name_too_long_is_refused_before_the_work(tmp_path):
    """A fuzz review: a name of 300 bytes failed as the file was written, after the fit,
    with exit 1; it is refused first, in one line, with the length the file system takes."""
    stage = tmp_path / "s.csv"
    stage.write_text(GOOD)
    res = run_cascal("fit", stage, "-o", tmp_path / ("x" * 300 + ".json"))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "characters): a name of 305 bytes in the path, longer than the file system " \
        "takes (" in res.stderr and "\n" not in res.stderr.strip()  # fmt: skip
    assert "Model written" not in res.stdout
    # (a second review: a name of 242 to 255 bytes passed, and its temporary file, 14 bytes
    # longer, failed after the work)
    long = tmp_path / ("y" * 250 + ".json")
    res = run_cascal("fit", stage, "-o", long)
    assert res.returncode == 0, res.stderr
    assert long.exists()


@pytest.mark.parametrize("option", ["--unit=--", "-o=--", "--restarts=--", "--seed=--"])
def test_an_option_given_as_equals_dashdash_is_refused(tmp_path, option):
    """A fuzzing review's case: ``--unit=--`` reached the command as an empty list
    (Python 3.11's argparse), a traceback and exit 1; ``fit --screening-level=--`` wrote
    the model first."""
    stage = tmp_path / "s.csv"
    stage.write_text(GOOD)
    res = run_cascal("fit", stage, "-o", tmp_path / "m.json", option)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert f"argument {option[:-3]}: expected a value, got '--'" in res.stderr
    assert not (tmp_path / "m.json").exists()


def test_ctrl_c_while_the_command_starts_ends_without_a_traceback(tmp_path):
    """A review's case: Ctrl-C in the first 0.3 s, while the package imported NumPy and
    SciPy, printed a traceback. The package now loads its modules on first use, so the
    console script reaches ``main`` at once, and ``main`` catches the interrupt wherever
    it comes while the subcommands load. Here SIGINT arrives as the parser is built."""
    import signal
    import subprocess
    import sys

    code = (
        "import os, signal, sys, cascal.cli as c\n"
        "assert 'numpy' not in sys.modules, 'the package imported NumPy'\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"  # (a background parent
        # may have started this process with SIGINT ignored, as a terminal never does)
        "build = c._parser\n"
        "def parser():\n"
        "    os.kill(os.getpid(), signal.SIGINT)\n"
        "    return build()\n"
        "c._parser = parser\n"
        "sys.exit(c.main(['info', 'm.json']))\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert p.returncode == 128 + signal.SIGINT, p.stderr
    assert p.stderr == "cascal: interrupted\n"


def test_a_stage_too_large_for_a_gp_is_named_and_memory_ends_without_traceback(
    tmp_path, monkeypatch, capsys
):
    """A review's case: 100 000 readings in a stage file ended in a traceback (74.5 GiB
    asked for). A GP stage of over MAX_GP_POINTS positions is refused, naming the file;
    and a MemoryError anywhere ends with one line, exit 1, no traceback."""
    import numpy as np

    from cascal import cli, workflow
    from cascal.errors import InputError
    from cascal.io.data import read_stage

    x = np.linspace(0.0, 1.0, workflow.MAX_GP_POINTS + 1)
    path = tmp_path / "huge.csv"
    path.write_text("testbed,reference\n" + "".join(f"{v!r},{v!r}\n" for v in x.tolist()))
    stage = read_stage(path)
    with pytest.raises(InputError, match=rf"huge.csv: {x.size} distinct positions; a GP"):
        workflow.fit_model([stage])
    assert workflow.fit_model([stage], method="lut").fitted.models[0] is not None

    def boom(*args, **kwargs):
        raise MemoryError

    monkeypatch.setattr(workflow, "fit_model", boom)
    assert cli.main(["fit", str(path), "-o", str(tmp_path / "m.json")]) == 1
    err = capsys.readouterr().err
    assert "cascal fit: error: out of memory" in err and "Traceback" not in err
    assert not (tmp_path / "m.json").exists()


@pytest.mark.parametrize("gap", [0.02, 0.2])
def test_ctrl_c_twice_in_a_study_ends_it_and_the_same_command_resumes(tmp_path, gap):
    """A review's case: a second Ctrl-C while the study waited for its workers hung it
    (they kept running, and so did the command). Now the workers leave Ctrl-C to the
    command, which stops them; the stored trials stay, and the command resumes."""
    import time

    from utils import stored_trials

    out = tmp_path / "study"
    args = ["study", "--trials", "300", "--workers", "2", "--out", out]

    def stored() -> int:
        return stored_trials(out / "study.sqlite")

    def ready(proc) -> None:
        deadline = time.monotonic() + 120
        while stored() == 0 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)

    code, err = interrupted(args, ready, (gap,))
    assert code in (130, -2), err  # -2: the second came as the process ended
    assert "Traceback" not in err and "interrupted" in err
    before = stored()
    assert 0 < before < 300
    res = run_cascal(*args)
    assert res.returncode == 0, res.stderr
    assert f"({300 - before} run now" in res.stdout and stored() == 300


def test_stage_files_in_reverse_order_are_named_as_such(tmp_path):
    """A review's case: `fit tb_dev.csv ref_tb.csv` (the device's file first) advised
    measuring the stage above over the range; the column names show the files reversed."""
    x = np.linspace(0.0, 1.0, 21)
    ref = tmp_path / "ref_tb.csv"
    ref.write_text(
        "testbed,reference\n" + "".join(f"{v!r},{v + 1e-4 * v * v!r}\n" for v in x.tolist())
    )
    dev = tmp_path / "tb_dev.csv"
    d = np.linspace(0.1, 0.9, 30)
    dev.write_text("device,testbed\n" + "".join(f"{v!r},{v + 1e-4 * v!r}\n" for v in d.tolist()))
    res = run_cascal("fit", dev, ref, "-o", tmp_path / "m.json")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "the stage files look to be in reverse order (ref_tb.csv's first column, testbed, " \
        "is the second of tb_dev.csv)" in res.stderr  # fmt: skip
    assert not (tmp_path / "m.json").exists()
    assert run_cascal("fit", ref, dev, "-o", tmp_path / "m.json").returncode == 0
    # (a diff review: where the device file spans the reference's range, the range check
    wide = tmp_path / "tb_dev_wide.csv"
    d = np.linspace(-0.05, 1.25, 30)
    wide.write_text("device,testbed\n" + "".join(f"{v!r},{0.1 + 0.7 * v!r}\n" for v in d.tolist()))
    # passed, and the files were fitted in reverse order with no word: names are labels
    # only (a second review: a logger's ch1,ch2 above ch2,ch3), so they are warned of)
    res = run_cascal("fit", wide, ref, "-o", tmp_path / "w.json")
    assert res.returncode == 0, res.stderr
    assert "warning: " + str(ref) + ": the stage files look to be in reverse order" in res.stderr


def test_a_stage_file_whose_names_do_not_link_is_warned_of(tmp_path):
    """A chain review: `fit ref_tb.csv int_dev.csv`, the middle stage left out (headed
    `device,intermediate` under `testbed,reference`), was fitted with no word."""
    x = np.linspace(0.0, 1.0, 21)
    ref = tmp_path / "ref_tb.csv"
    ref.write_text("testbed,reference\n" + "".join(f"{v!r},{v + 1e-4 * v!r}\n" for v in x.tolist()))
    dev = tmp_path / "int_dev.csv"
    d = np.linspace(0.1, 0.9, 30)
    dev.write_text(
        "device,intermediate\n" + "".join(f"{v!r},{v + 1e-4 * v!r}\n" for v in d.tolist())
    )
    res = run_cascal("fit", ref, dev, "-o", tmp_path / "m.json")
    assert res.returncode == 0, res.stderr
    assert "its columns (device, intermediate) share no name with" in res.stderr
    assert "is a stage missing between them, or is the file of another chain?" in res.stderr
    good = tmp_path / "tb_dev.csv"
    good.write_text(dev.read_text().replace("device,intermediate", "device,testbed"))
    res = run_cascal("fit", ref, good, "-o", tmp_path / "m.json")
    assert res.returncode == 0 and "share no name" not in res.stderr


def test_rotary_stage_files_in_reverse_order_are_warned_of_and_a_file_twice_refused(tmp_path):
    """A chain review's cases: a periodic fit has no range check, so rotary stage files in
    reverse order were fitted with no word (the reference file taken for the device): the
    names show it, and as they are labels only, a warning says so; and a stage file given
    twice was fitted as one more stage (the device's error applied twice): refused."""
    deg = np.linspace(0.0, 350.0, 36)
    ref = tmp_path / "ref_tb.csv"
    ref.write_text(
        "testbed,reference\n"
        + "".join(f"{v + 0.01 * float(np.sin(np.radians(v)))!r},{v!r}\n" for v in deg.tolist())
    )
    dev = tmp_path / "tb_dev.csv"
    d = np.linspace(2.0, 357.0, 72)
    dev.write_text(
        "device,testbed\n"
        + "".join(f"{v!r},{v + 0.02 * float(np.cos(np.radians(2 * v)))!r}\n" for v in d.tolist())
    )
    rotary = ("--kernel", "periodic", "--period", "360", "--unit", "deg")
    res = run_cascal("fit", dev, ref, "-o", tmp_path / "r.json", *rotary)
    assert res.returncode == 0 and "Traceback" not in res.stderr
    want = f"warning: {ref}: the stage files look to be in reverse order (ref_tb.csv's first"
    assert want + " column, testbed, is the second of tb_dev.csv)" in res.stderr
    for extra in (rotary, ()):
        res = run_cascal("fit", ref, dev, dev, "-o", tmp_path / "m.json", *extra)
        assert res.returncode == 2 and "Traceback" not in res.stderr
        assert f"stages 1 and 2 hold the same readings ({dev} and {dev}): one stage file " \
            "given twice?" in res.stderr  # fmt: skip
    assert not (tmp_path / "m.json").exists()
    assert run_cascal("fit", ref, dev, "-o", tmp_path / "m.json", *rotary).returncode == 0


def test_a_reading_outside_the_range_above_says_when_it_is_a_mean(tmp_path):
    """A review's case: the message named row 2 and quoted 9.966666666666667e-08, the
    mean of rows 2 to 4, where row 2 holds 0.000000069."""
    ref = tmp_path / "ref.csv"
    x = np.linspace(0.1, 1.0, 10)
    ref.write_text("testbed,reference\n" + "".join(f"{v!r},{v!r}\n" for v in x.tolist()))
    dev = tmp_path / "dev.csv"
    rows = [(0.0, 0.069e-6), (0.0, 0.11e-6), (0.0, 0.12e-6)]
    rows += [(v, v) for v in np.linspace(0.2, 0.9, 8).tolist()]
    dev.write_text("device,testbed\n" + "".join(f"{a!r},{b!r}\n" for a, b in rows))
    res = run_cascal("fit", ref, dev, "-o", tmp_path / "m.json")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "row 2" in res.stderr
    assert "(the mean of this position's 3 rows) lies outside the range" in res.stderr


def test_a_program_s_own_sigterm_handler_survives_an_interrupted_command():
    """A diff review's case: a command ending on Ctrl-C set SIGTERM to be ignored even
    where the program embedding ``cascal.cli.main`` had its own handler: that program
    could no longer be stopped with ``kill``. Only the command's own handler is replaced."""
    import signal

    from cascal.pool import raise_terminated, stop_listening

    def own(signum, frame):  # pragma: no cover - never called
        pass

    previous = signal.signal(signal.SIGTERM, own)
    ctrl_c = signal.getsignal(signal.SIGINT)
    try:
        stop_listening()
        assert signal.getsignal(signal.SIGTERM) is own
        signal.signal(signal.SIGTERM, raise_terminated)
        stop_listening()
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, previous)
        signal.signal(signal.SIGINT, ctrl_c)  # (stop_listening ignores Ctrl-C too)
