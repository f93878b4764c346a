"""Outlier screening in ``cascal fit`` and ``fit-devices``: the rows named, the numbers."""

from __future__ import annotations

import csv
import re

import numpy as np
import pytest
from cli_helpers import device_folder, run_cascal, spoil

from cascal.io.data import read_stage
from cascal.io.modelfile import load_model
from cascal.screening import screen, screen_repeats
from cascal.workflow import fit_model, screen_stages


def test_clean_files_have_nothing_suspect(linear_files, tmp_path):
    files, _ = linear_files
    res = run_cascal("fit", *files, "-o", tmp_path / "m.json")
    assert res.returncode == 0, res.stderr
    assert "Outlier screening (1 % false-alarm level per stage and check): none found" in (
        res.stdout
    )
    assert "warning" not in res.stderr


def test_fit_names_the_rows_and_the_numbers_are_the_library_s(spoiled):
    tmp, bad_ref, bad_dev = spoiled
    res = run_cascal("fit", bad_ref, bad_dev, "-o", tmp / "m.json")
    assert res.returncode == 0, res.stderr
    assert "2 suspect rows, see the warnings" in res.stdout
    warnings = res.stderr.strip().splitlines()
    assert len(warnings) == 3, res.stderr
    assert warnings[0].startswith(f"cascal fit: warning: {bad_ref} row 41: reference ")
    assert "is the farthest of the 3 readings at testbed" in warnings[0]
    assert "(rows 41, 42 and 43)" in warnings[0]
    assert warnings[1].startswith(f"cascal fit: warning: {bad_dev} row 101: testbed ")
    assert warnings[2].startswith(f"cascal fit: warning: {bad_dev}: without the suspect point")
    # The printed figures are the library's, on the model the command wrote.
    model = load_model(tmp / "m.json")
    ref_data = read_stage(bad_ref)
    (spread,) = screen_repeats(ref_data.raw_x, ref_data.raw_y)
    assert ref_data.raw_rows[spread.farthest] == 41
    assert f"scatter {spread.ratio:.1f} times" in warnings[0]
    assert f"(p = {spread.p:.2g})" in warnings[0]
    device = screen(model.fitted.models[1])
    (q,) = device.suspects
    z = float(re.search(r"lies ([0-9.]+) standard deviations above", warnings[1]).group(1))
    assert z == round(q.z, 1) and z > device.threshold
    assert f"({q.target - q.predicted:+.3g} m)" in warnings[1]
    assert (
        f"would be {device.noise_std_without:.3g} m instead of {device.noise_std:.3g}"
        in (warnings[2])
    )


def test_screen_stages_maps_points_to_file_rows(spoiled):
    _, bad_ref, bad_dev = spoiled
    data = [read_stage(bad_ref), read_stage(bad_dev)]
    model = fit_model(data)
    checks = screen_stages(model, data)
    assert [c.rows for c in checks] == [[41], [101]]
    assert [c.stage for c in checks] == [0, 1]
    # A suspect averaged point names all of its rows.
    ref = data[0]
    i = int(np.flatnonzero(ref.counts == 3)[5])
    rows = ref.point_rows(i)
    assert rows.size == 3 and rows[0] == ref.rows[i]
    assert np.all(ref.raw_x[np.isin(ref.raw_rows, rows)] == ref.x[i])
    # A device fitted on a test-bed prefix: its file alone, as the model's stage 1.
    prefix = fit_model(data[:1])
    device = fit_model(data[1:], prefix=prefix)
    (check,) = screen_stages(device, data[1:])
    assert check.stage == 1 and check.rows == [101]
    with pytest.raises(ValueError, match="at most 1 stage files"):
        screen_stages(prefix, data)


def test_lookup_tables_are_not_fitted_but_their_repeats_are_screened(spoiled):
    _, bad_ref, bad_dev = spoiled
    data = [read_stage(bad_ref), read_stage(bad_dev)]
    checks = screen_stages(fit_model(data, method="lut"), data)
    assert [c.fit for c in checks] == [None, None]
    assert [c.rows for c in checks] == [[41], []]


def test_fleet_summary_lists_suspect_rows(spoiled, linear_files):
    tmp, bad_ref, bad_dev = spoiled
    (_, good_dev), _ = linear_files
    folder = device_folder(tmp / "devices", good_dev, bad_dev)
    res = run_cascal("fit-devices", bad_ref, "--devices", folder, "-o", tmp / "fleet")
    assert res.returncode == 0, res.stderr
    assert re.search(r"\] b: rms correction .*, 1 suspect row\n", res.stdout)
    assert re.search(r"\] a: rms correction [^,]* m, largest u [0-9.e+-]+ m\n", res.stdout)
    assert f"fit-devices: warning: {bad_ref} row 41:" in res.stderr
    assert f"fit-devices: warning: {folder / 'b.csv'} row 101:" in res.stderr
    assert "Outlier screening of the test bed (1 % " in res.stdout
    assert "Outlier screening of the devices: 1 of 2 with suspect rows" in res.stdout
    with open(tmp / "fleet" / "fleet_summary.csv", newline="") as fh:
        rows = {r["device"]: r for r in csv.DictReader(fh)}
    assert rows["a"]["suspect_rows"] == "" and rows["b"]["suspect_rows"] == "101"


def test_report_lists_the_suspects_and_circles_them(spoiled, linear_model):
    from cascal.report import build_report
    from cascal.reportdata import stage_views

    _, bad_ref, bad_dev = spoiled
    model = fit_model([read_stage(bad_ref), read_stage(bad_dev)])
    views = stage_views(model)
    (q,) = views[1].screening.suspects
    assert views[0].screening.suspects == ()  # the bad repeat hides in its own point
    text = build_report(model)
    assert text.count("Outlier screening: every point agrees with the others' prediction") == 1
    assert "Outlier screening: 1 point the others do not support" in text
    assert f"<td>{q.z:+.1f}</td>" in text and f"<td>{q.reading:.10g}</td>" in text
    clean = build_report(load_model(linear_model))
    assert clean.count("Outlier screening: every point agrees with the others' prediction") == 2
    # The figure circles the suspect at its residual.
    from cascal.report import stage_figure

    fig = stage_figure(views[1], unit="m")
    ring = [ln for ln in fig.axes[1].lines if ln.get_label() == "suspect (outlier screening)"]
    assert len(ring) == 1 and list(ring[0].get_xdata()) == [q.reading]


def test_fit_says_when_more_points_disagree_than_it_takes_out(tmp_path):
    rng = np.random.default_rng(5)
    x = np.linspace(0.0, 1.0, 60)
    y = x + 0.01 * np.sin(5 * x) + rng.normal(0.0, 1e-4, 60)
    y[3::5] += 1e-2 * 0.7 ** np.arange(12)  # 100 down to 2 noise standard deviations
    stage = tmp_path / "stage.csv"
    cells = "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(x, y, strict=True))
    stage.write_text("reading,reference\n" + cells)
    res = run_cascal("fit", stage, "-o", tmp_path / "m.json")
    assert res.returncode == 0, res.stderr
    lines = res.stderr.strip().splitlines()
    rows = [int(m) for m in re.findall(r"stage\.csv row (\d+): reference", res.stderr)]
    assert rows == [5, 10, 15, 20, 25, 30]  # file rows of the six largest, worst first
    assert "without the 6 suspect points its learned noise" in lines[-2]
    assert lines[-1].endswith(
        "more points disagree with the others than the screening takes out (at most 6 of "
        "its 60): its noise may not be Gaussian, or the map may be rougher than the kernel "
        "allows (see the residuals in cascal report)"
    )
    assert "6 suspect rows" in res.stdout


def test_too_few_points_to_find_an_outlier_is_said(tmp_path):
    x = np.linspace(0.0, 1.0, 8)
    y = x + 0.01 * np.sin(5 * x)
    y[4] += 0.05  # gross, yet the learned noise covers it: |z| <= sqrt(8) < 3.23
    stage = tmp_path / "stage.csv"
    cells = "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(x, y, strict=True))
    stage.write_text("reading,reference\n" + cells)
    res = run_cascal("fit", stage, "-o", tmp_path / "m.json")
    assert res.returncode == 0, res.stderr
    assert res.stderr.strip() == (
        f"cascal fit: warning: {stage}: 8 points are too few for the leave-one-out check to "
        "find an outlier (the noise it learns covers any single point; it needs 12 or more)"
    )
    assert "no single suspect row, but see the warnings" in res.stdout
    assert (tmp_path / "m.json").exists()


def test_a_small_stage_is_said_to_be_weakly_screened(tmp_path):
    """A review's case: 13 points with one reading 100 times the noise off passed the
    check with "none found" and no caveat (the learned noise grew 29 times to cover it)."""
    rng = np.random.default_rng(8)
    x = np.sort(rng.uniform(0.0, 1.0, 13))
    y = x + 0.01 * np.sin(5 * x) + 1e-4 * rng.standard_normal(13)
    y[6] += 1e-2
    stage = tmp_path / "small.csv"
    cells = "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(x, y, strict=True))
    stage.write_text("reading,reference\n" + cells)
    res = run_cascal("fit", stage, "-o", tmp_path / "m.json")
    assert res.returncode == 0, res.stderr
    assert f"{stage}: with 13 points the leave-one-out check finds only outliers" in res.stderr
    assert "no single suspect row, but see the warnings" in res.stdout


def test_a_failed_screening_is_a_warning_and_the_model_is_kept(spoiled, monkeypatch):
    from cascal import workflow
    from cascal.cli_screening import screening_lines, screening_summary
    from cascal.errors import NumericalError

    _, bad_ref, bad_dev = spoiled
    data = [read_stage(bad_ref), read_stage(bad_dev)]
    model = fit_model(data)

    def broken(gp, level):
        raise NumericalError("target covariance is not positive definite")

    monkeypatch.setattr(workflow, "screen", broken)
    checks = screen_stages(model, data)
    assert [c.problem for c in checks] == ["target covariance is not positive definite"] * 2
    assert [c.rows for c in checks] == [[41], []]  # the repeats are still screened
    assert screening_lines(checks[1], "m") == [
        f"{bad_dev}: the leave-one-out check stopped: target covariance is not positive definite"
    ]
    assert screening_summary(checks).endswith(
        "1 suspect row, see the warnings; one check failed, see the warnings"
    )


def test_rotary_outlier_next_to_the_seam_is_named_by_its_row(tmp_path):
    from cli_helpers import write_case

    from cascal.demo import rotary_demo

    (ref, dev), _ = write_case(rotary_demo(0), tmp_path / "rotary")
    first = float(dev.read_text().splitlines()[1].split(",")[0])
    assert first < 2.0  # the first device reading, a degree past the seam
    bad = tmp_path / "device.csv"
    spoil(dev, bad, {2: 3e-3})  # 30 noise standard deviations
    res = run_cascal("fit", ref, bad, "-o", tmp_path / "m.json", "--kernel", "periodic",
                     "--period", "360", "--unit", "deg")  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert f"warning: {bad} row 2: " in res.stderr and " deg); check that measurement" in res.stderr
    assert "1 suspect row, see the warnings" in res.stdout


def test_screening_level_is_passed_on_and_can_be_turned_off(spoiled):
    from cascal.cli_screening import SKIPPED
    from cascal.screening import LEVEL

    tmp, bad_ref, bad_dev = spoiled
    data = [read_stage(bad_ref), read_stage(bad_dev)]
    strict = run_cascal("fit", bad_ref, bad_dev, "-o", tmp / "strict.json",
                        "--screening-level", "1e-6")  # fmt: skip
    assert strict.returncode == 0, strict.stderr
    model = load_model(tmp / "strict.json")
    checks = screen_stages(model, data, level=1e-6)
    # Row 101 (4.4 sd) is below the threshold at 1e-6 (5.3 sd for 200 points), row 41 not.
    assert [c.rows for c in checks] == [[41], []]
    assert checks[1].fit.threshold > 5.0 > abs(checks[1].fit.z).max()
    assert "(0.0001 % false-alarm level per stage and check): 1 suspect row" in strict.stdout
    assert f"{bad_ref} row 41: " in strict.stderr and "row 101" not in strict.stderr
    off = run_cascal("fit", bad_ref, bad_dev, "-o", tmp / "off.json", "--no-screening")
    assert off.returncode == 0, off.stderr
    assert off.stderr == "" and SKIPPED in off.stdout and "suspect" not in off.stdout
    # Screening never changes the model.
    a, b = load_model(tmp / "off.json"), load_model(tmp / "strict.json")
    for ga, gb in zip(a.fitted.models, b.fitted.models, strict=True):
        assert ga.hyperparameters == gb.hyperparameters
    # The help states the library's default.
    assert f"(default {LEVEL:g})" in run_cascal("fit", "--help").stdout.replace("\n", " ")


def test_fit_devices_screens_at_the_level_given_or_not_at_all(spoiled, linear_files):
    from cascal.cli_screening import SKIPPED

    tmp, bad_ref, bad_dev = spoiled
    (_, good_dev), _ = linear_files
    folder = device_folder(tmp / "devices2", good_dev, bad_dev)
    strict = run_cascal("fit-devices", bad_ref, "--devices", folder, "-o", tmp / "fleet2",
                        "--screening-level", "1e-6", "--jobs", "1")  # fmt: skip
    assert strict.returncode == 0, strict.stderr
    assert "Outlier screening of the test bed (0.0001 % " in strict.stdout
    assert "Outlier screening of the devices: 0 of 2 with suspect rows" in strict.stdout
    assert "row 101" not in strict.stderr and f"{bad_ref} row 41:" in strict.stderr
    off = run_cascal("fit-devices", bad_ref, "--devices", folder, "-o", tmp / "fleet3",
                     "--no-screening", "--jobs", "1")  # fmt: skip
    assert off.returncode == 0, off.stderr
    assert off.stderr == "" and SKIPPED in off.stdout
    assert "Outlier screening of the devices" not in off.stdout
    assert "suspect row" not in off.stdout
    with open(tmp / "fleet3" / "fleet_summary.csv", newline="") as fh:
        assert [r["suspect_rows"] for r in csv.DictReader(fh)] == ["", ""]


@pytest.mark.parametrize(
    ("value", "words"),
    [
        ("0", "from 1e-12 to below 1, got 0 (--no-screening turns the screening off)"),
        ("1", "from 1e-12 to below 1, got 1"),
        ("nan", "from 1e-12 to below 1, got nan"),
        ("1e-322", "from 1e-12 to below 1, got 1e-322"),  # its tail probabilities underflow
        ("often", "expected a number, got 'often'"),
    ],
)
def test_a_bad_screening_level_is_refused(value, words, tmp_path, linear_files):
    files, _ = linear_files
    res = run_cascal("fit", *files, "-o", tmp_path / "m.json", "--screening-level", value)
    assert res.returncode == 2 and words in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "m.json").exists()


def test_screening_level_and_no_screening_exclude_each_other(tmp_path, linear_files):
    files, _ = linear_files
    res = run_cascal("fit", *files, "-o", tmp_path / "m.json", "--screening-level", "0.05",
                     "--no-screening")  # fmt: skip
    assert res.returncode == 2 and "not allowed with argument" in res.stderr
