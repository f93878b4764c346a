"""``cascal compare``: a recalibration against the calibration before it."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from cli_helpers import run_cascal

from cascal.io.modelfile import load_model
from cascal.workflow import compare_models


@pytest.fixture(scope="module")
def models(linear_files, tmp_path_factory):
    """The linear case's model, and a recalibration after the device drifted by up to
    80 µm (its test-bed column moved by 80 µm times (2 x - 1))."""
    (ref, dev), _ = linear_files
    tmp = tmp_path_factory.mktemp("compare")
    lines = dev.read_text().splitlines()
    moved = [lines[0]]
    for line in lines[1:]:
        x, y = map(float, line.split(","))
        moved.append(f"{x!r},{y + 8e-5 * (2 * x - 1)!r}")
    drifted = tmp / "testbed_device_2.csv"
    drifted.write_text("\n".join(moved) + "\n")
    out = {}
    for name, files, extra in (
        ("old", (ref, dev), ()),
        ("new", (ref, drifted), ()),
        ("lut", (ref, drifted), ("--method", "lut")),
        ("mm", (ref, drifted), ("--unit", "mm")),
    ):
        res = run_cascal("fit", *files, "-o", tmp / f"{name}.json", "--no-screening", *extra)
        assert res.returncode == 0, res.stderr
        out[name] = tmp / f"{name}.json"
    return tmp, out


def test_compare_prints_and_writes_the_library_s_numbers(models):
    tmp, m = models
    res = run_cascal("compare", m["old"], m["new"], "-o", tmp / "c.csv", "--plot", tmp / "c.png")
    assert res.returncode == 0, res.stderr
    c = compare_models(load_model(m["old"]), load_model(m["new"]))
    s = c.summary()
    assert c.shared  # one reference file, one seed: the same fitted test bed
    assert f"RMS {s['rms_change']:.4g} m, largest {s['max_change']:.4g} m" in res.stdout
    assert "(the test bed's calibration both share counted once)" in res.stdout
    assert f"{c.u.min():.3g} to {c.u.max():.3g} m" in res.stdout
    assert f"largest |change| / u {s['max_z']:.3g}, at reading {s['max_z_at']:.9g}" in res.stdout
    assert f"stays below {c.k_band:.2f} over the whole range with 95 % probability" in res.stdout
    verdict = "the device (or its mounting) has changed" if c.changed else "no change shown"
    assert verdict in res.stdout
    assert (tmp / "c.png").stat().st_size > 10_000
    with open(tmp / "c.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 1001
    assert list(rows[0]) == ["reading", "old", "new", "change", "u_old", "u_new", "u", "En"]
    for name, col in (("change", c.change), ("u", c.u), ("En", c.en)):
        got = np.array([float(r[name]) for r in rows])
        scale = np.max(np.abs(col))
        np.testing.assert_allclose(got, col, rtol=0, atol=1e-6 * scale)


def test_max_change_sets_the_exit_status(models):
    _, m = models
    c = compare_models(load_model(m["old"]), load_model(m["new"]))
    largest = c.summary()["max_change"]
    bad = run_cascal("compare", m["old"], m["new"], "--max-change", f"{largest / 2:.6g}")
    assert bad.returncode == 3, bad.stderr
    share = np.mean(np.abs(c.change) > float(f"{largest / 2:.6g}"))
    assert f"over {100 * share:.1f} % of the range" in bad.stdout
    good = run_cascal("compare", m["old"], m["new"], "--max-change", f"{largest * 2:.6g}")
    assert good.returncode == 0 and "Within --max-change" in good.stdout


def test_lookup_tables_give_the_change_alone(models):
    tmp, m = models
    res = run_cascal("compare", m["old"], m["lut"], "-o", tmp / "l.csv")
    assert res.returncode == 0, res.stderr
    assert "method lut gives no uncertainty: only the change is reported" in res.stderr
    assert "standard uncertainty" not in res.stdout
    with open(tmp / "l.csv", newline="") as fh:
        assert {r["En"] for r in csv.DictReader(fh)} == {""}


@pytest.mark.parametrize(
    ("which", "extra", "words"),
    [
        ("mm", (), "different units ('m' and 'mm')"),
        ("new", ("--max-change", "-1"), "--max-change: expected a number > 0"),
        ("broken", (), "not a valid model file"),
    ],
)
def test_bad_comparisons_are_refused(models, which, extra, words):
    tmp, m = models
    (tmp / "broken.json").write_text(m["new"].read_text()[:100])
    other = m.get(which, tmp / "broken.json")
    res = run_cascal("compare", m["old"], other, "-o", tmp / f"bad_{which}.csv", *extra)
    assert res.returncode == 2 and words in res.stderr and "Traceback" not in res.stderr
    assert not (tmp / f"bad_{which}.csv").exists()


def test_a_model_compared_with_itself_is_named(linear_model):
    """A review's case: comparing a model file with itself reported a non-zero u and a band
    with no word that both hold the same readings."""
    res = run_cascal("compare", linear_model, linear_model)
    assert res.returncode == 0, res.stderr
    assert "both models were fitted on the same readings" in res.stderr
    assert "largest 0 m" in res.stdout


def test_a_three_stage_comparison_names_the_shared_stages_as_upstream(tmp_path):
    """A numerical review's nit: comparing two three-stage models that share their upper
    stages said "the test bed's calibration both share", where they share two stages."""
    from cascal.io.modelfile import save_model
    from cascal.workflow import fit_model
    from utils import three_stages

    model = save_model(tmp_path / "three.json", fit_model(three_stages(), n_restarts=1))
    res = run_cascal("compare", model, model)
    assert res.returncode == 0, res.stderr
    assert "(the upstream calibrations both share counted once)" in res.stdout


def test_a_change_of_the_test_bed_alone_is_not_called_a_change_of_the_device(tmp_path):
    """A user review's case: a recalibrated test bed, the device file byte-identical, and
    compare concluded that "the device (or its mounting) has changed"; it names the stages
    above now, the device's readings being the same in both models."""
    from dataclasses import replace

    from cascal.io.modelfile import save_model
    from cascal.workflow import fit_model
    from utils import demo_stages

    ref, dev = demo_stages()
    bump = replace(ref, y=ref.y + 5e-4 * np.exp(-(((ref.x - 0.75) / 0.05) ** 2)))
    old = save_model(tmp_path / "old.json", fit_model([ref, dev], n_restarts=1))
    new = save_model(tmp_path / "new.json", fit_model([bump, dev], n_restarts=1))
    res = run_cascal("compare", old, new)
    assert res.returncode == 0, res.stderr
    assert "beyond that band" in res.stdout
    assert "the stages above it changed (the test bed's calibration), not the device" in res.stdout
    assert "the device (or its mounting) has changed" not in res.stdout
