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
    """The linear case's model, and recalibrations after the device drifted by up to
    80 µm and 600 µm (its test-bed column moved by 80 µm or 600 µm times (2 x - 1))."""
    (ref, dev), _ = linear_files
    tmp = tmp_path_factory.mktemp("compare")
    lines = dev.read_text().splitlines()
    for size, drifted in ((8e-5, tmp / "testbed_device_2.csv"), (6e-4, tmp / "far.csv")):
        moved = [lines[0]]
        for line in lines[1:]:
            x, y = map(float, line.split(","))
            moved.append(f"{x!r},{y + size * (2 * x - 1)!r}")
        drifted.write_text("\n".join(moved) + "\n")
    drifted = tmp / "testbed_device_2.csv"
    out = {}
    for name, files, extra in (
        ("old", (ref, dev), ()),
        ("new", (ref, drifted), ()),
        ("far", (ref, tmp / "far.csv"), ()),
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


def test_max_change_counts_the_change_s_uncertainty(models):
    """--max-change T passes (status 0) where |change| + k_band u <= T everywhere, fails
    where |change| - k_band u > T somewhere, and is not shown within otherwise (status 3,
    with a warning where the band alone reaches T). A review: an unchanged device failed a
    T below the band in 22 of 40 recalibrations, by the change's noise alone."""
    _, m = models
    c = compare_models(load_model(m["old"]), load_model(m["far"]))
    a, margin = np.abs(c.change), c.k_band * c.u
    assert np.max(a - margin) > 0  # (the drift is beyond the band somewhere)

    def run(t):
        return run_cascal("compare", m["old"], m["far"], "--max-change", f"{t:.6g}"), float(
            f"{t:.6g}"
        )

    res, t = run(0.5 * float(np.max(a - margin)))
    assert res.returncode == 3, res.stderr
    share = np.mean(a - margin > t)
    assert f"Changed by more than --max-change {t:g} m, beyond its uncertainty" in res.stdout
    assert f"over {100 * share:.1f} % of the range (largest change" in res.stdout
    assert "is within the band" in res.stderr  # (t is below the band's reach too)
    res, t = run(1.01 * float(np.max(a + margin)))
    assert res.returncode == 0, res.stderr
    assert f"Within --max-change {t:g} m everywhere, the change's uncertainty counted" in res.stdout
    assert "within the band" not in res.stderr
    res, t = run(0.5 * float(np.max(a - margin) + np.max(a + margin)))  # between the two
    assert np.max(a - margin) <= t < np.max(a + margin)
    assert res.returncode == 3, res.stderr
    share = np.mean(a + margin > t)
    assert (
        f"Not shown within --max-change {t:g} m: |change| + {c.k_band:.2f} u exceeds it over "
        in (res.stdout)
    )
    assert f"{100 * share:.1f} % of the range, and nowhere" in res.stdout
    unresolved = np.mean(margin >= t)
    if unresolved > 0:
        assert f"over {100 * unresolved:.1f} % of the range: there the two calibrations" in (
            res.stderr
        )


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
    assert (
        "the stages above it changed, not the device: stage 0 (the test bed's calibration)\n"
        in res.stdout
    )
    assert "the device (or its mounting) has changed" not in res.stdout


def test_a_change_of_a_middle_stage_is_named(tmp_path):
    """A chain review's case: of three stages, only stage 1's file changed (the device file
    the same), and compare blamed the test bed's calibration; it names stage 1 now."""
    import dataclasses

    from cascal.io.modelfile import save_model
    from cascal.workflow import fit_model
    from utils import three_stages

    ref, mid, dev = three_stages()
    bump = dataclasses.replace(mid, y=mid.y + 8e-4 * np.exp(-(((mid.x - 0.6) / 0.05) ** 2)))
    old = save_model(tmp_path / "old.json", fit_model([ref, mid, dev], n_restarts=1))
    new = save_model(tmp_path / "new.json", fit_model([ref, bump, dev], n_restarts=1))
    res = run_cascal("compare", old, new)
    assert res.returncode == 0, res.stderr
    assert "beyond that band" in res.stdout
    want = "so the stages above it changed, not the device: stage 1 (testbed_device.csv)\n"
    assert want in res.stdout
    both = dataclasses.replace(ref, y=ref.y + 1e-4 * ref.x)
    new = save_model(tmp_path / "both.json", fit_model([both, bump, dev], n_restarts=1))
    res = run_cascal("compare", old, new)
    assert "changed, not the device: stage 0 (the test bed's calibration) and stage 1 (" in (
        res.stdout
    )
