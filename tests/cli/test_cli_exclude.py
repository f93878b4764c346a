"""``--exclude FILE:ROWS``: rows left out of a fit, recorded in the model file."""

from __future__ import annotations

import csv
import json
import re
import shlex

import pytest
from cli_helpers import device_folder, run_cascal

from cascal.io.data import read_stage
from cascal.io.modelfile import load_model
from cascal.workflow import fit_model


def _without(src, dst, rows: set[int]) -> None:
    """Copy a file without some of its rows (the header is row 1)."""
    lines = src.read_text().splitlines()
    dst.write_text("\n".join(t for r, t in enumerate(lines, start=1) if r not in rows) + "\n")


def test_excluded_rows_fit_as_the_files_without_them(spoiled):
    tmp, bad_ref, bad_dev = spoiled
    res = run_cascal("fit", bad_ref, bad_dev, "-o", tmp / "ex.json",
                     "--exclude", f"{bad_ref.name}:41", "--exclude", f"{bad_dev}:101")  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""  # nothing suspect is left
    assert f"Stage 0 ({bad_ref}: 128 rows, row 41 left out, 43 points)" in res.stdout
    assert f"Stage 1 ({bad_dev}: 199 rows, row 101 left out, 199 points)" in res.stdout
    # The same fit as of the files with those rows deleted.
    cut_ref, cut_dev = tmp / "cut_ref.csv", tmp / "cut_dev.csv"
    _without(bad_ref, cut_ref, {41})
    _without(bad_dev, cut_dev, {101})
    expected = fit_model([read_stage(cut_ref), read_stage(cut_dev)])
    model = load_model(tmp / "ex.json")
    for a, b in zip(model.fitted.models, expected.fitted.models, strict=True):
        assert a.hyperparameters == b.hyperparameters
        assert a.log_marginal_likelihood == b.log_marginal_likelihood
    assert [s.excluded for s in model.sources] == [(41,), (101,)]
    doc = json.loads((tmp / "ex.json").read_text())
    assert doc["schema_version"] == 2
    # info and the report show them; info still knows the file, whose checksum is unchanged.
    info = run_cascal("info", tmp / "ex.json")
    assert info.returncode == 0 and "schema 2" in info.stdout
    assert (
        "row 41 left out" in info.stdout
        and f"input {bad_ref} (columns testbed, reference): unchanged" in info.stdout
    )
    rep = run_cascal("report", tmp / "ex.json", "-o", tmp / "ex.html")
    assert rep.returncode == 0, rep.stderr
    html = (tmp / "ex.html").read_text()
    assert "<th>rows left out</th>" in html and "<td>41</td>" in html and "<td>101</td>" in html


def test_the_warnings_say_how_to_leave_the_suspects_out(spoiled):
    tmp, bad_ref, bad_dev = spoiled
    res = run_cascal("fit", bad_ref, bad_dev, "-o", tmp / "m0.json")
    hints = re.findall(r"--exclude (\S+?)(?: leaves|,)", res.stderr)
    assert hints == [shlex.quote(f"{bad_ref}:41"), shlex.quote(f"{bad_dev}:101")]
    args = [a for h in hints for a in ("--exclude", *shlex.split(h))]
    again = run_cascal("fit", bad_ref, bad_dev, "-o", tmp / "m1.json", *args)
    assert again.returncode == 0 and again.stderr == ""
    assert "Outlier screening (1 % false-alarm level per stage and check): none found" in (
        again.stdout
    )


def test_fit_devices_leaves_rows_of_the_test_bed_and_of_a_device_out(spoiled, linear_files):
    tmp, bad_ref, bad_dev = spoiled
    (_, good_dev), _ = linear_files
    folder = device_folder(tmp / "devices_ex", good_dev, bad_dev)
    res = run_cascal("fit-devices", bad_ref, "--devices", folder, "-o", tmp / "fleet_ex",
                     "--exclude", f"{bad_ref.name}:41", "--exclude", "b.csv:101,102-103",
                     "--jobs", "2")  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""
    tb = load_model(tmp / "fleet_ex" / "testbed.json")
    a = load_model(tmp / "fleet_ex" / "devices" / "a.json")
    b = load_model(tmp / "fleet_ex" / "devices" / "b.json")
    assert tb.sources[0].excluded == (41,) and a.sources[0].excluded == (41,)
    assert a.sources[1].excluded == () and b.sources[1].excluded == (101, 102, 103)
    with open(tmp / "fleet_ex" / "fleet_summary.csv", newline="") as fh:
        rows = {r["device"]: r for r in csv.DictReader(fh)}
    assert rows["b"]["points"] == "197" and rows["b"]["suspect_rows"] == ""


@pytest.mark.parametrize(
    ("spec", "words"),
    [
        ("reference_testbed.csv", "expected FILE:ROWS"),
        ("other.csv:5", "other.csv is none of the stage files"),
        ("reference_testbed.csv:1", "row 1 is no data row (row 1 is the header"),
        ("reference_testbed.csv:9-5", "9-5 is an empty range"),
        ("reference_testbed.csv:4,x", "expected row numbers such as 41,57 or 50-52, got 'x'"),
        (
            "reference_testbed.csv:999",
            "row 999 lies past the end of the file (its last row is 130)",
        ),
    ],
)
def test_a_bad_exclusion_is_refused(spec, words, linear_files, tmp_path):
    files, _ = linear_files
    res = run_cascal("fit", *files, "-o", tmp_path / "m.json", "--exclude", spec)
    assert res.returncode == 2 and words in res.stderr, res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "m.json").exists()


def test_a_name_two_stage_files_share_must_be_a_path(linear_files, tmp_path):
    files, _ = linear_files
    other = tmp_path / "sub"
    other.mkdir()
    twin = other / files[1].name
    twin.write_text(files[1].read_text())
    res = run_cascal("fit-devices", files[0], "--devices", other, "-o", tmp_path / "f",
                     "--exclude", f"{files[1].name}:5")  # fmt: skip
    assert res.returncode == 0, res.stderr  # only the device file has that name
    device = load_model(tmp_path / "f" / "devices" / f"{twin.stem}.json")
    assert device.sources[1].excluded == (5,)
    res = run_cascal("fit", files[1], twin, "-o", tmp_path / "m.json",
                     "--exclude", f"{files[1].name}:5")  # fmt: skip
    assert res.returncode == 2 and "names several of the stage files" in res.stderr


def test_a_row_range_is_checked_against_the_file_before_it_is_counted(linear_files, tmp_path):
    files, _ = linear_files
    ref = files[0]
    res = run_cascal("fit", *files, "-o", tmp_path / "m.json",
                     "--exclude", f"{ref.name}:2-100000000000")  # fmt: skip
    assert res.returncode == 2 and "Traceback" not in res.stderr
    last = len(ref.read_text().splitlines())
    assert f"row 100000000000 lies past the end of the file (its last row is {last})" in (
        res.stderr
    )


def test_fit_devices_refuses_a_device_row_past_the_end_before_any_fit(spoiled, linear_files):
    tmp, bad_ref, bad_dev = spoiled
    folder = tmp / "devices_past"
    folder.mkdir()
    (folder / "b.csv").write_text(bad_dev.read_text())
    out = tmp / "fleet_past"
    res = run_cascal("fit-devices", bad_ref, "--devices", folder, "-o", out,
                     "--exclude", "b.csv:999")  # fmt: skip
    assert res.returncode == 2 and "row 999 lies past the end of the file" in res.stderr
    assert not (out / "testbed.json").exists()


def test_an_existing_file_that_is_no_stage_file_is_refused(linear_files, tmp_path, monkeypatch):
    files, _ = linear_files
    monkeypatch.chdir(tmp_path)
    (tmp_path / files[0].name).write_text(files[0].read_text())  # same name, not an input
    res = run_cascal("fit", *files, "-o", "m.json", "--exclude", f"{files[0].name}:41")
    assert res.returncode == 2
    assert f"--exclude {files[0].name}:41: {files[0].name} is none of the stage files" in (
        res.stderr
    )  # and the message says which stage file has that name
    assert f"is another file here: write --exclude {files[0]}:41" in res.stderr


def test_fit_devices_library_matches_exclusions_by_path(spoiled, tmp_path):
    from pathlib import Path

    from cascal.errors import InputError
    from cascal.io.modelfile import save_model
    from cascal.workflow import fit_devices

    _, bad_ref, bad_dev = spoiled
    testbed = save_model(tmp_path / "tb.json", fit_model([read_stage(bad_ref)]))
    device = tmp_path / "b.csv"
    device.write_text(bad_dev.read_text())
    key = Path(f"{tmp_path}/./b.csv")  # another spelling of the same path
    (r,) = fit_devices(testbed, [str(device)], tmp_path / "out", options={"exclude": {key: [101]}})
    assert r.error is None and r.points == 199
    assert load_model(r.model).sources[1].excluded == (101,)
    with pytest.raises(InputError, match=r"c\.csv is none of the device files"):
        fit_devices(testbed, [device], tmp_path / "out", options={"exclude": {"c.csv": [5]}})
