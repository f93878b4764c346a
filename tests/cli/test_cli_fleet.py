"""``cascal fit-devices``: one test-bed fit, devices in parallel, a bad file skipped."""

from __future__ import annotations

import csv
import io
import json
import re
import sys

import pytest
from cli_helpers import interrupted, run_cascal

from cascal.demo import fleet_demo
from cascal.io.csvout import write_columns


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fleet")
    testbed, devices = fleet_demo(0, n_devices=3)
    tb = tmp / "testbed.csv"
    write_columns(tb, dict(zip(testbed.columns, (testbed.x, testbed.y), strict=True)), decimals=14)
    folder = tmp / "devices"
    for d in devices:
        write_columns(folder / d.file, dict(zip(d.columns, (d.x, d.y), strict=True)), decimals=14)
    (folder / "device99.csv").write_text("device,testbed\n0.1,0.1\n0.2,oops\n0.3,0.3\n")
    (folder / "notes.txt").write_text("not a device file")
    out = tmp / "out"
    res = run_cascal("fit-devices", tb, "--devices", folder, "-o", out, "--jobs", "2",
                     "--restarts", "2")  # fmt: skip
    return tmp, tb, folder, out, res


def test_bad_device_is_reported_and_skipped(fleet):
    *_, out, res = fleet
    assert res.returncode == 1, res.stderr  # some devices were skipped
    assert "Traceback" not in res.stderr
    assert "skipped device device99: " in res.stderr and "row 3" in res.stderr
    assert "3 of 4 devices calibrated" in res.stdout
    counts = sorted(
        int(m)
        for m in re.findall(r"\[(\d)/4, [0-9.e+-]+ devices/s, ETA \d+ s\]", res.stdout + res.stderr)
    )
    assert counts == [1, 2, 3, 4]  # each device's line says how far the fleet is
    assert sorted(p.name for p in (out / "devices").iterdir()) == [
        "device01.json", "device02.json", "device03.json",
    ]  # fmt: skip
    assert (out / "testbed.json").exists()


def test_fleet_summary(fleet):
    *_, out, _ = fleet
    with open(out / "fleet_summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["device"] for r in rows] == ["device01", "device02", "device03", "device99"]
    assert [r["status"] for r in rows] == ["ok", "ok", "ok", "error"]
    for r in rows[:3]:
        assert float(r["length_scale"]) > 0 and float(r["noise_variance"]) >= 0
        assert float(r["rms_correction"]) > 1e-4  # the paper's errors: centimetres
        assert 0 < float(r["max_u"]) < 1e-3
        assert r["points"] == "100"
    assert "oops" in rows[3]["error"] and rows[3]["model"] == ""
    assert [r["warnings"] for r in rows] == ["", "", "", ""]  # (the error is not repeated)
    assert [r["unit"] for r in rows] == ["m", "m", "m", ""]  # (a review: no unit column)
    assert [r["arc_left_out"] for r in rows] == ["", "", "", ""]


def test_a_rotary_device_row_names_the_arc_its_readings_leave_out():
    """A report review's case: a rotary device measured from 300 over 0 to 60 deg read
    range 0.02 to 357.29 in the summary, as if measured over almost the whole turn; the
    arc its readings leave out is a column now (rounded outward), beside the unit."""
    from cascal.cli import _fleet_csv
    from cascal.workflow import DeviceResult

    turn = DeviceResult(
        "enc7", "enc7.csv", model="enc7.json", rms_correction=1e-3, max_u=1e-5,
        calibrated_range=(0.02, 357.292636711), points=40, arc=(59.9912345678, 299.99),
    )  # fmt: skip
    (row,) = list(csv.DictReader(io.StringIO(_fleet_csv([turn], {}, "deg"))))
    assert row["unit"] == "deg" and row["arc_left_out"] == "59.9912345 to 299.99"
    assert row["range_lo"] == "0.02" and row["status"] == "ok"


def test_device_model_equals_a_plain_fit_of_both_stages(fleet):
    """The test bed is fitted once and reused; with the same seed the device's model is
    the one ``cascal fit TESTBED DEVICE`` gives, whatever the number of workers."""
    tmp, tb, folder, out, _ = fleet
    single = tmp / "single.json"
    res = run_cascal("fit", tb, folder / "device02.csv", "-o", single, "--restarts", "2")
    assert res.returncode == 0, res.stderr
    a = json.loads(single.read_text())
    b = json.loads((out / "devices" / "device02.json").read_text())
    assert a["stages"] == b["stages"]
    assert a["calibrated_range"] == b["calibrated_range"]
    tb_model = json.loads((out / "testbed.json").read_text())
    assert tb_model["stages"][0] == b["stages"][0]


def _blas_threads() -> int:
    from threadpoolctl import threadpool_info

    return max(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")


def test_fleet_workers_run_blas_on_one_thread():
    """A review's case: devices of 150 points fitted by two workers, each on two BLAS
    threads, differed from ``cascal fit``'s models in their last digits (length scale
    0.04423546118965255 against 0.04423546118961811); workers now pin BLAS to one thread,
    with which they equal the plain fit's."""
    import multiprocessing

    from cascal import workflow

    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(1, initializer=workflow._init_worker, initargs=(None,)) as p:
        assert p.apply(_blas_threads) == 1


def test_parser_refuses_negative_seeds_too_many_trials_and_odd_units(tmp_path):
    for argv in (
        ["fit", tmp_path / "a.csv", "-o", tmp_path / "m.json", "--seed", "-1"],
        ["fit", tmp_path / "a.csv", "-o", tmp_path / "m.json", "--unit", "m\nx"],
        ["study", "--trials", "2", "--seed", "-3", "--out", tmp_path / "s"],
        ["study", "--trials", str(10**9), "--out", tmp_path / "s"],
    ):
        res = run_cascal(*argv)
        assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
        words = ("seed >= 0", "at most 100000000 trials", "printable characters")
        assert any(w in res.stderr for w in words), res.stderr
    assert not (tmp_path / "s").exists()


def test_unexpected_failure_skips_one_device_and_removes_its_old_model(fleet, monkeypatch):
    """Any exception in one device's fit is that device's error, with its type; the others
    complete, and a model an earlier run wrote for the failed device is removed."""
    from cascal import workflow

    tmp, _, folder, out, _ = fleet
    devices = sorted(folder.glob("device0*.csv"))[:2]
    again = tmp / "again"
    stale = again / f"{devices[0].stem}.json"
    stale.parent.mkdir()
    stale.write_text("a model of an earlier run")
    real = workflow.fit_model

    def flaky(stages, **kw):
        if stages[0].source.file == str(devices[0]):
            raise ZeroDivisionError("boom")
        return real(stages, **kw)

    monkeypatch.setattr(workflow, "fit_model", flaky)
    options = {"n_restarts": 2, "seed": 0}
    results = workflow.fit_devices(out / "testbed.json", devices, again, options=options)
    assert results[0].error == "unexpected ZeroDivisionError: boom" and not stale.exists()
    assert results[1].error is None and (again / f"{devices[1].stem}.json").exists()


def test_a_device_with_another_zero_is_named_and_fits_with_mean_offset(fleet, tmp_path):
    """A device whose readings are 100 m off its test bed's: the fleet warns of that device
    (its corrections are one offset) and --mean offset fits it."""
    _, tb, folder, _, _ = fleet
    devices = tmp_path / "devices"
    devices.mkdir()
    head, *rows = (folder / "device01.csv").read_text().splitlines()
    moved = [f"{float(a) + 100.0!r},{b}" for a, b in (r.split(",") for r in rows)]
    (devices / "far.CSV").write_text("\n".join([head, *moved]) + "\n")  # any case of .csv
    runs = {}
    for mean in ("identity", "offset"):
        runs[mean] = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / mean,
                                "--jobs", "1", "--restarts", "2", "--mean", mean)  # fmt: skip
        assert runs[mean].returncode == 0, runs[mean].stderr
    stuck = runs["identity"].stderr
    assert "swapped" not in stuck  # (device, testbed) after the test bed's (testbed, reference)
    assert "far.CSV: the corrections average -99.9" in stuck, stuck
    assert "--mean offset" in stuck
    assert "--mean offset" not in runs["offset"].stderr, runs["offset"].stderr


def test_a_copy_of_the_test_bed_file_among_the_devices_is_named_as_such(fleet, tmp_path):
    """A review's case: the test bed's file left in the devices folder was fitted as a
    device against itself and reported as a device the reference never confirmed."""
    import shutil

    _, tb, folder, _, _ = fleet
    devices = tmp_path / "devices"
    devices.mkdir()
    shutil.copy(folder / "device01.csv", devices)
    shutil.copy(tb, devices / "old_testbed.csv")
    res = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / "out",
                     "--jobs", "1", "--restarts", "2")  # fmt: skip
    assert res.returncode == 1, res.stderr
    assert "skipped device old_testbed: " in res.stderr
    assert f"the test bed's own stage file ({tb}, the same SHA-256), not a device" in res.stderr
    assert sorted(p.name for p in (tmp_path / "out" / "devices").iterdir()) == ["device01.json"]


def test_a_device_file_with_its_columns_swapped_is_named(fleet, tmp_path):
    _, tb, folder, _, _ = fleet
    devices = tmp_path / "devices"
    devices.mkdir()
    head, *rows = (folder / "device02.csv").read_text().splitlines()
    x, y = head.split(",")
    (devices / "swapped.csv").write_text("\n".join([f"{y},{x}", *rows]) + "\n")
    res = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / "out",
                     "--jobs", "1", "--restarts", "2")  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert f"swapped.csv: its columns ({y}, {x}) follow " in res.stderr
    assert "are one file's columns swapped?" in res.stderr
    with open(tmp_path / "out" / "fleet_summary.csv", newline="") as fh:
        (row,) = csv.DictReader(fh)  # a user review's case: the warning was on stderr only
    assert row["status"] == "ok" and "are one file's columns swapped?" in row["warnings"]


def test_models_of_devices_gone_from_the_folder_are_named(fleet, tmp_path):
    """A second run after a device file was removed: its model of the first run stays in
    devices/ but is no longer in the summary, which the run says (a review's case)."""
    _, tb, folder, *_ = fleet
    mine = tmp_path / "devices"
    mine.mkdir()
    for name in ("device01.csv", "device02.csv"):
        (mine / name).write_text((folder / name).read_text())
    out = tmp_path / "out"
    argv = ("fit-devices", tb, "--devices", mine, "-o", out, "--restarts", "2")
    assert run_cascal(*argv).returncode == 0
    (mine / "device02.csv").unlink()
    res = run_cascal(*argv)
    assert res.returncode == 0, res.stderr
    assert "1 model(s) of devices with no file in" in res.stderr
    assert "(device02.json): left as they were, not in the summary" in res.stderr
    assert (out / "devices" / "device02.json").exists()


def test_outputs_never_overwrite_the_test_bed_or_a_device_file(fleet, tmp_path):
    """A review's case: a test-bed file kept in the -o folder as fleet_summary.csv was
    replaced by the summary (exit 0). Now refused before any fit, the file unchanged; and
    one column named for both readings is refused (a fit of a column against itself)."""
    _, tb, folder, _, _ = fleet
    out = tmp_path / "out"
    out.mkdir()
    kept = out / "fleet_summary.csv"
    kept.write_bytes(tb.read_bytes())
    res = run_cascal("fit-devices", kept, "--devices", folder, "-o", out)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert f"would overwrite {kept}, an input of this command" in res.stderr
    assert kept.read_bytes() == tb.read_bytes() and sorted(out.iterdir()) == [kept]
    name = tb.read_text().splitlines()[0].split(",")[0]
    res = run_cascal("fit-devices", tb, "--devices", folder, "-o", tmp_path / "o2",
                     "--x-column", name, "--y-column", name)  # fmt: skip
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert f"{tb}, row 1: column {name!r} is named twice" in res.stderr


def test_a_record_spanning_lines_is_warned_of_by_fit_and_fit_devices(fleet, tmp_path):
    """A quoted cell that spans lines (a stray quote could make one) is named in one
    warning line by ``fit`` and, from its worker process, by ``fit-devices``; no Python
    warning text."""
    _, tb, folder, _, _ = fleet
    devices = tmp_path / "devices"
    devices.mkdir()
    head, *rows = (folder / "device02.csv").read_text().splitlines()
    a, b = rows[3].split(",")
    rows[3] = f'{a},"{b}\n"'  # file rows 5 and 6: one record
    (devices / "noted.csv").write_text("\n".join([head, *rows]) + "\n")
    (devices / "plain.csv").write_text((folder / "device01.csv").read_text())  # two: a pool
    for args in (
        ("fit-devices", tb, "--devices", devices, "-o", tmp_path / "out", "--jobs", "2"),
        ("fit", tb, devices / "noted.csv", "-o", tmp_path / "m.json"),
    ):
        res = run_cascal(*args, "--restarts", "2")
        assert res.returncode == 0, res.stderr
        assert f"cascal {args[0]}: warning: " in res.stderr
        assert "noted.csv, rows 5 to 6: read as one record" in res.stderr
        assert "DataWarning" not in res.stderr and "warnings.warn" not in res.stderr
    # a device skipped for too few rows: the warning says why (a review's case)
    (devices / "short.csv").write_text(f'{head}\n0.1,0.1\n0.2,"0.2\n"\n')
    res = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / "o2",
                     "--jobs", "2", "--restarts", "2")  # fmt: skip
    assert res.returncode == 1, res.stderr
    assert "short.csv, rows 3 to 4: read as one record" in res.stderr
    assert "skipped device short: " in res.stderr and "at least 3 data rows" in res.stderr


def test_an_interrupt_cancels_the_devices_not_started(fleet, tmp_path):
    """A user review's case: Ctrl-C printed "interrupted" only after the whole fleet (36 of
    40 models written after it). An interrupt while the results come in now cancels the
    devices not yet handed to a worker: only those under way finish."""
    from cascal.workflow import fit_devices

    _, _, folder, out, _ = fleet
    devices = []
    for k in range(16):
        devices.append(tmp_path / f"d{k:02d}.csv")
        devices[-1].write_text((folder / "device01.csv").read_text())

    def stop(result) -> None:
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        fit_devices(out / "testbed.json", devices, tmp_path / "models", options={"n_restarts": 2},
                    jobs=2, on_result=stop)  # fmt: skip
    written = list((tmp_path / "models").glob("*.json"))
    # the first, the two under way, and the one the executor had queued for them (its call
    # queue holds one task more than there are workers: seen on a loaded machine); none
    # handed out after
    assert 1 <= len(written) <= 4


def _interrupted_fleet(fleet, tmp_path, gaps: tuple[float, ...], after: str = "[1/16", wait=None):
    """Run ``fit-devices`` on 16 devices and send SIGINT to its process group once a line
    of its output holds ``after`` (by default: the first device is done), then again after
    each of ``gaps`` (s); ``wait(pid)`` before the first. Returns (returncode, stderr,
    output folder)."""
    _, tb, folder, _, _ = fleet
    devices = tmp_path / "devices"
    devices.mkdir()
    for k in range(16):
        (devices / f"d{k:02d}.csv").write_text((folder / "device01.csv").read_text())
    out = tmp_path / "out"
    (out / "devices").mkdir(parents=True)  # an earlier run's model of the last device (a
    (out / "devices" / "d15.json").write_text("{}")  # review: it stayed, unsummarised)

    def ready(proc) -> None:
        for line in proc.stdout:
            if after in line:
                break
        if wait is not None:
            wait(proc.pid)

    args = ["fit-devices", tb, "--devices", devices, "-o", out, "--jobs", "2"]
    code, err = interrupted(args, ready, gaps)
    return code, err, out


def _check_interrupted(out, err) -> None:
    """The summary lists every device once, the models written as ok and the others as
    not fitted, which keep no model (an earlier run's neither); no temporaries."""
    assert "Traceback" not in err and "interrupted after " in err
    with open(out / "fleet_summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    # in file order, as a finished fleet's (a review: in the order they completed)
    assert [r["device"] for r in rows] == [f"d{k:02d}" for k in range(16)]
    ok = [r["device"] for r in rows if r["status"] == "ok"]
    done = sum(r["error"] != "not fitted: the fleet was interrupted" for r in rows)
    (said,) = re.findall(r"interrupted after (\d+) of 16 devices", err)
    assert int(said) == done  # (a review: it said 16 of 16, those not fitted counted)
    models = sorted(p.stem for p in (out / "devices").glob("*.json"))
    assert 1 <= len(models) < 16 and models == sorted(ok)  # those under way finished too
    assert len({r["device"] for r in rows}) == len(rows)
    left = [r["error"] for r in rows if r["status"] != "ok"]
    assert all(e == "not fitted: the fleet was interrupted" for e in left)
    assert not [p for p in out.rglob("*") if p.name.startswith(".")]  # no temporaries


def test_ctrl_c_in_a_fleet_fits_no_further_device_and_summarises_those_done(fleet, tmp_path):
    """A review's case: Ctrl-C reached the workers too, which went on with the devices
    queued for them, and the folder kept the last run's summary. Now the workers leave
    the signal to the command, which writes the summary of the devices reported so far."""
    code, err, out = _interrupted_fleet(fleet, tmp_path, ())
    assert code == 130, err
    _check_interrupted(out, err)


@pytest.mark.parametrize("gap", [0.02, 0.1])
def test_a_second_ctrl_c_in_a_fleet_stops_it_at_once(fleet, tmp_path, gap):
    """A review's case: a second Ctrl-C while the devices under way finished interrupted
    the wait for them, and the process hung at exit. Now it stops their workers; the
    summary names the devices left unfitted, and no temporary file stays."""
    code, err, out = _interrupted_fleet(fleet, tmp_path, (gap,))
    assert code in (130, -2), err  # -2: the second signal came as the process ended
    _check_interrupted(out, err)


def _children(pid: int) -> list[str]:
    """The child processes of ``pid`` (Linux)."""
    from pathlib import Path

    return (Path(f"/proc/{pid}/task/{pid}/children").read_text()).split()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
@pytest.mark.parametrize("delay", [0.0, 0.1, 0.3])
def test_ctrl_c_as_the_workers_start_gives_no_traceback(fleet, tmp_path, delay):
    """A review's case: Ctrl-C while the workers imported NumPy (they had not yet set
    SIGINT aside) printed their tracebacks. Now they start with SIGINT blocked. The
    signal comes ``delay`` s after the second child process (the first worker; the
    first is multiprocessing's resource tracker) appears."""
    import time

    def wait(pid: int) -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and len(_children(pid)) < 2:
            time.sleep(0.005)
        time.sleep(delay)

    code, err, out = _interrupted_fleet(
        fleet, tmp_path, (), after="Test bed fitted once", wait=wait
    )
    assert code == 130, err
    assert "Traceback" not in err and "interrupted" in err, err
    assert not [p for p in out.rglob("*") if p.name.startswith(".")]  # no temporaries


def test_a_partly_measured_rotary_device_is_named_in_the_summary(tmp_path):
    """A review's case: a rotary device measured from 5 to 200 degrees only was reported
    "ok" with no word of it (``cascal fit`` names the arc its readings leave out); the
    fleet now warns of it, and the summary's warnings column carries it."""
    from cascal.demo import rotary_demo
    from cascal.text import measured_ends

    testbed, device = rotary_demo(0).stages
    tb = tmp_path / "testbed.csv"
    write_columns(tb, dict(zip(testbed.columns, (testbed.x, testbed.y), strict=True)), decimals=12)
    folder = tmp_path / "devices"
    keep = (device.x > 5.0) & (device.x < 200.0)
    for name, sel in (("full", slice(None)), ("part", keep)):
        cols = dict(zip(device.columns, (device.x[sel], device.y[sel]), strict=True))
        write_columns(folder / f"{name}.csv", cols, decimals=12)
    out = tmp_path / "out"
    res = run_cascal("fit-devices", tb, "--devices", folder, "-o", out, "--kernel", "periodic",
                     "--period", "360", "--unit", "deg", "--restarts", "1")  # fmt: skip
    assert res.returncode == 0, res.stderr
    start, end = measured_ends((float(device.x[keep].max()), float(device.x[keep].min())))
    assert float(start) >= device.x[keep].min() and float(end) <= device.x[keep].max()
    left = f"{end} to {start} deg"  # the arc left out, rounded outward
    assert "warning: part: calibrated over " in res.stderr and f"leave out {left}" in res.stderr
    assert "full: calibrated over" not in res.stderr
    with open(out / "fleet_summary.csv", newline="") as fh:
        rows = {r["device"]: r for r in csv.DictReader(fh)}
    assert f"leave out {left}" in rows["part"]["warnings"] and not rows["full"]["warnings"]


def test_the_test_bed_and_the_devices_name_their_columns_apart(tmp_path):
    """A user review's case: a test-bed log with its own column names (and time and
    temperature columns) beside device files of another station could not be fitted:
    ``--x-column`` was taken once, for every file. Given twice, it names the test bed's
    column, then the devices'; three times is refused."""
    testbed, devices = fleet_demo(0, n_devices=2)
    tb = tmp_path / "testbed_log.csv"
    cols = {"time_s": testbed.x * 0.0, "stage_mm": testbed.x, "interferometer_mm": testbed.y}
    write_columns(tb, cols, decimals=14)
    folder = tmp_path / "devices"
    for d in devices:
        write_columns(folder / d.file, dict(zip(d.columns, (d.x, d.y), strict=True)), decimals=14)
    xd, yd = devices[0].columns
    out = tmp_path / "out"
    args = ["--x-column", "stage_mm", "--x-column", xd, "--y-column", "interferometer_mm",
            "--y-column", yd, "--restarts", "1"]  # fmt: skip
    res = run_cascal("fit-devices", tb, "--devices", folder, "-o", out, *args)
    assert res.returncode == 0, res.stderr
    assert "2 of 2 devices calibrated" in res.stdout
    model = json.loads((out / "devices" / f"{devices[0].file.rsplit('.', 1)[0]}.json").read_text())
    assert "stage_mm" in json.dumps(model) and xd in json.dumps(model)
    res = run_cascal("fit-devices", tb, "--devices", folder, "-o", tmp_path / "o2",
                     *args, "--x-column", "third")  # fmt: skip
    assert res.returncode == 2 and "give it once (the test bed and every device)" in res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "o2").exists()


def test_a_device_file_that_is_a_dangling_link_is_reported(fleet, tmp_path):
    """A review's case: a device file linked to a share not mounted was left out without a
    word ("1 of 1 devices calibrated", exit 0); it is a device that could not be read."""
    _, tb, folder, _, _ = fleet
    devices = tmp_path / "devices"
    devices.mkdir()
    (devices / "a.csv").write_text((folder / "device01.csv").read_text())
    (devices / "b.csv").symlink_to(tmp_path / "unmounted" / "b.csv")
    res = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / "out",
                     "--jobs", "1", "--restarts", "1")  # fmt: skip
    assert res.returncode == 1, res.stderr
    assert "1 of 2 devices calibrated" in res.stdout
    assert "skipped device b: " in res.stderr and "cannot read the file" in res.stderr
    rows = (tmp_path / "out" / "fleet_summary.csv").read_text().splitlines()
    assert rows[2].startswith("b,error,")


def test_an_interrupt_before_the_first_device_keeps_no_model_of_the_old_test_bed(
    fleet, tmp_path, monkeypatch, capsys
):
    """A review's case: Ctrl-C after the new testbed.json was written (the test bed's
    screening) but before the first device left the earlier run's device models and its
    summary, all "ok", beside it. Every device is listed as not fitted now, and keeps no
    model of the earlier run."""
    import shutil

    from cascal import workflow
    from cascal.cli import main

    _, tb, folder, out, _ = fleet
    again = tmp_path / "again"
    shutil.copytree(out, again)
    assert len(list((again / "devices").glob("*.json"))) == 3

    def stop(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(workflow, "screen_stages", stop)
    code = main(["fit-devices", str(tb), "--devices", str(folder), "-o", str(again),
                 "--restarts", "2"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 130 and "interrupted after 0 of 4 devices" in err
    assert list((again / "devices").glob("*.json")) == []
    with open(again / "fleet_summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["status"] for r in rows] == ["error"] * 4
    assert {r["error"] for r in rows} == {"not fitted: the fleet was interrupted"}


def test_cautions_of_every_device_are_in_each_row_and_a_renamed_file_s_old_model_named(
    fleet, tmp_path
):
    """A review's cases: a test bed's caution (u in doubt) and the homoscedastic method's
    were printed once or not at all, and no row of the summary carried them; a device file
    renamed by case only left its old model (dev01.json beside DEV01.json) unnamed."""
    _, _, folder, _, _ = fleet
    devices = tmp_path / "devices"
    devices.mkdir()
    (devices / "DEVICE01.csv").write_text((folder / "device01.csv").read_text())
    weak = tmp_path / "weak.csv"  # three reference positions: the fit warns u is in doubt
    weak.write_text("testbed,reference\n-0.2,-0.199\n0.5,0.502\n1.2,1.199\n")
    out = tmp_path / "out"
    (out / "devices").mkdir(parents=True)
    (out / "devices" / "device01.json").write_text("{}")  # the file's earlier name's model
    res = run_cascal("fit-devices", weak, "--devices", devices, "-o", out, "--restarts", "2",
                     "--method", "homoscedastic", "--no-screening")  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "covered 66 % of the errors" in res.stderr
    with open(out / "fleet_summary.csv", newline="") as fh:
        (row,) = list(csv.DictReader(fh))
    assert "test bed: " in row["warnings"] and "covered 66 % of the errors" in row["warnings"]
    assert "1 model(s) of devices with no file" in res.stderr and "(device01.json)" in res.stderr


def test_a_folder_or_a_pipe_named_like_a_device_file_is_reported(fleet, tmp_path):
    """A review's case: a folder or a named pipe called ``*.csv`` among the device files was
    left out without a word (and alone, "no .csv device files" for a folder that visibly
    held x.csv). Each is a device skipped now, named in the summary, and never read."""
    import os

    _, tb, folder, _, _ = fleet
    devices = tmp_path / "devices"
    (devices / "folder.csv").mkdir(parents=True)
    os.mkfifo(devices / "pipe.csv")
    res = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / "o")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "no .csv device files in folder" in res.stderr
    assert "folder.csv is a folder, not a file; pipe.csv is not a regular file" in res.stderr
    (devices / "device01.csv").write_text((folder / "device01.csv").read_text())
    res = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / "o",
                     "--restarts", "2", "--no-screening", timeout=120)  # fmt: skip
    assert res.returncode == 1, res.stderr
    assert "skipped device folder: " in res.stderr and "skipped device pipe: " in res.stderr
    assert "1 of 3 devices calibrated" in res.stdout
    with open(tmp_path / "o" / "fleet_summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["device"], r["status"]) for r in rows] == [
        ("device01", "ok"), ("folder", "error"), ("pipe", "error"),
    ]  # fmt: skip
    assert rows[1]["error"].endswith("folder.csv is a folder, not a file")


def test_a_lookup_table_fleet_says_it_has_no_u_and_hidden_files_are_left_out(fleet, tmp_path):
    """A review's cases: each device's line of a lut fleet read "largest u nan m", and a
    macOS ``._device01.csv`` beside the device files was fitted as a device (and failed)."""
    _, tb, folder, _, _ = fleet
    devices = tmp_path / "devices"
    devices.mkdir()
    (devices / "device01.csv").write_text((folder / "device01.csv").read_text())
    (devices / "._device01.csv").write_bytes(b"\x00\x05\x16\x07 AppleDouble")
    res = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / "o",
                     "--method", "lut", "--no-screening")  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "no u (lut)" in res.stdout and "nan" not in res.stdout
    assert "1 hidden file(s) left out (._device01.csv)" in res.stderr
    assert "1 of 1 devices calibrated" in res.stdout
    (devices / "device01.csv").unlink()  # hidden files alone: named (a diff review)
    res = run_cascal("fit-devices", tb, "--devices", devices, "-o", tmp_path / "o")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "no .csv device files in folder" in res.stderr
    assert "; 1 hidden file(s) left out (._device01.csv)" in res.stderr


def test_a_write_protected_fleet_output_or_study_output_is_not_replaced(fleet, tmp_path):
    """A diff review's case: -o files were refused where write-protected, but a fleet's
    testbed.json, device models and summary, and a study's outputs, were replaced."""
    import shutil
    import subprocess
    import sys

    _, tb, folder, out, _ = fleet
    again = tmp_path / "again"
    shutil.copytree(out, again)
    (again / "devices" / "device02.json").chmod(0o444)
    res = run_cascal("fit-devices", tb, "--devices", folder, "-o", again)
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "device02.json: the file is write-protected; not replaced" in res.stderr
    study = tmp_path / "study"
    study.mkdir()
    (study / "summary.json").write_text("{}")
    (study / "summary.json").chmod(0o444)
    cmd = [sys.executable, "-m", "cascal.cli", "study", "--trials", "1", "--out", str(study)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "summary.json: the file is write-protected" in done.stderr
    assert not (study / "study.sqlite").exists()
