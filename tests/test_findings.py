"""What makes a fitted stage's u doubtful (workflow.fit_findings), on files with a known
cause: an offset between the sensors' zeros, too few points, clean data."""

from __future__ import annotations

import numpy as np
import pytest

from cascal.io.data import read_stage
from cascal.workflow import BoundHit, StageOffset, fit_findings, fit_model


def _stage(path, x, y, names=("testbed", "reference")):
    rows = zip(np.asarray(x).tolist(), np.asarray(y).tolist(), strict=True)
    path.write_text(",".join(names) + "\n" + "".join(f"{a!r},{b!r}\n" for a, b in rows))
    return read_stage(path)


@pytest.fixture
def smooth():
    rng = np.random.default_rng(3)
    x = np.linspace(0.0, 1.0, 40)
    return x, x + 1e-3 * np.sin(6 * x) + 2e-5 * rng.standard_normal(40)


def test_an_offset_between_the_zeros_is_named_and_mean_offset_removes_it(tmp_path, smooth):
    """A reference 100 m off (corrections 1e5 times their spread): with the identity mean
    the variance is profiled, so no bound is hit, yet the offset is named; with the offset
    mean nothing is, and the corrections are those of the unshifted fit."""
    x, y = smooth
    data = _stage(tmp_path / "far.csv", x, y + 100.0)
    (finding,) = fit_findings(fit_model([data], n_restarts=2))
    assert isinstance(finding, StageOffset) and finding.stage == 0
    assert finding.offset == pytest.approx(np.mean(y + 100.0 - x), rel=1e-12)
    assert finding.spread == pytest.approx(np.std(y - x), rel=1e-9)
    offset = fit_model([data], n_restarts=2, mean="offset")
    assert fit_findings(offset) == []
    plain = fit_model([_stage(tmp_path / "near.csv", x, y)], n_restarts=2, mean="offset")
    xs = np.linspace(0.05, 0.95, 50)
    np.testing.assert_allclose(
        offset.fitted.correct(xs) - 100.0, plain.fitted.correct(xs), rtol=0, atol=1e-9
    )


def test_three_points_hit_their_bounds_and_clean_data_none(tmp_path, smooth):
    few = _stage(tmp_path / "few.csv", [0.0, 0.5, 1.0], [0.0001, 0.4990, 1.0002])
    hits = fit_findings(fit_model([few], n_restarts=2))
    assert hits == [
        BoundHit(0, "length_scale", "lower", 3),
        BoundHit(0, "noise_ratio", "upper", 3),
    ]
    x, y = smooth
    assert fit_findings(fit_model([_stage(tmp_path / "ok.csv", x, y)], n_restarts=2)) == []


def test_three_points_that_interpolate_at_any_noise_are_named(tmp_path):
    """Three reference points of a review (from the demo's file): the fit passes through
    them at any noise below 1e-10 of the variance (the run below that floor gains 6e-10
    nats), so the noise is not estimated and u is far too small (17.7 % of check points
    inside U). The noise stays at its first floor and is named, as at a bound."""
    x = [-0.045103644571, 0.343952608537, 0.978728600451]
    y = [-0.000043643525, 0.402522016101, 1.000138897997]
    model = fit_model([_stage(tmp_path / "ref3.csv", x, y)])
    assert fit_findings(model) == [BoundHit(0, "noise_ratio", "lower", 3)]
    hp = model.fitted.models[0].hyperparameters
    assert hp["noise_variance"] / hp["variance"] == pytest.approx(1e-10, rel=1e-3)


def test_few_points_read_as_a_straight_line_are_named_and_many_are_not(tmp_path):
    """A review's case: the first, middle and last of the demo's reference points end with
    the length scale at its upper bound (a straight correction plus 16 mm of noise; 59 % of
    the device's check points inside U), which was not named. Below 12 points it is; 40
    noisy points along a straight correction that end there too are not."""
    from cascal.text import finding_line

    x = [-0.045103644571, 0.548719057542, 0.978728600451]
    y = [-0.000043643525, 0.601419670694, 1.000035145508]
    model = fit_model([_stage(tmp_path / "ref3.csv", x, y)])
    assert fit_findings(model) == [BoundHit(0, "length_scale", "upper", 3)]
    line = finding_line(fit_findings(model)[0], "ref3.csv", "m")
    assert "straight correction plus noise" in line and "3 points" in line
    rng = np.random.default_rng(2)
    xs = np.linspace(0.0, 1.0, 40)  # a scale error of 1e-4 and an offset, with noise
    ys = xs * (1 + 1e-4) + 2e-3 + rng.normal(0.0, 1e-3, 40)
    straight = fit_model([_stage(tmp_path / "line.csv", xs, ys)], n_restarts=2)
    assert straight.fitted.models[0].optimization.at_bounds() == [("length_scale", "upper")]
    assert fit_findings(straight) == []


def test_a_loaded_model_shows_the_findings_of_its_fit(tmp_path, smooth):
    """A review's case: the report and ``info`` of a model from three reference points
    said nothing of what ``fit`` had warned, since a model file stores no search bounds.
    Loading puts them back (``gp.restore_bounds``): the same bounds, to the last bit, and
    the same findings as the fresh fit's, for bounds hit at either end, the noise floor
    searched again (and kept, or moved), and none."""
    from cascal.io.modelfile import load_model, save_model

    x, y = smooth
    rng = np.random.default_rng(5)
    xf = np.linspace(0.0, 1.0, 30)
    cases = {
        "few": ([0.0, 0.5, 1.0], [0.0001, 0.4990, 1.0002]),
        "ref3": (
            [-0.045103644571, 0.343952608537, 0.978728600451],
            [-0.000043643525, 0.402522016101, 1.000138897997],
        ),
        "ok": (x, y),
        "fine": (xf, xf + 1e-3 * np.sin(3 * xf) + 1e-12 * rng.standard_normal(30)),
        "far": (x, y + 100.0),
    }
    xd = np.linspace(0.05, 0.9, 30)
    device = (xd + 2e-4 * np.cos(4 * xd), xd)  # (device readings, test-bed readings)
    floors = set()
    for name, (a, b) in cases.items():
        for method in ("bayes", "homoscedastic"):
            stages = [_stage(tmp_path / f"{name}.csv", a, b), _stage(tmp_path / "dev.csv", *device)]
            fresh = fit_model(stages, method=method, n_restarts=2)
            path = save_model(tmp_path / f"{name}_{method}.json", fresh)
            loaded = load_model(path)
            assert fit_findings(loaded) == fit_findings(fresh), (name, method)
            for k, gp in enumerate(fresh.fitted.models):
                want, got = gp.optimization, loaded.fitted.models[k].optimization
                assert got.names == want.names
                assert np.array_equal(got.bounds, want.bounds), (name, method, k)
                floors.add(bool(want.bounds[-1, 0] < np.log(1e-10) - 1.0))
    assert floors == {True, False}  # both kinds of noise floor were restored
    assert fit_findings(load_model(tmp_path / "few_bayes.json"))[0].points == 3


def test_older_model_files_keep_no_bounds(tmp_path):
    """A diff review's case: cascal before 0.4.2 capped the profiled noise ratio at 10, so
    today's bounds would misstate what its fits hit (a "noise at its upper end" warning
    went missing). Files of those versions get no bounds back: their findings are the
    offsets alone, as before."""
    import json

    from cascal.io import modelfile

    x = [-0.045103644571, 0.343952608537, 0.978728600451]
    y = [-0.000043643525, 0.402522016101, 1.000138897997]
    path = modelfile.save_model(
        tmp_path / "m.json", fit_model([_stage(tmp_path / "ref3.csv", x, y)])
    )
    assert fit_findings(modelfile.load_model(path)) == [BoundHit(0, "noise_ratio", "lower", 3)]
    doc = json.loads(path.read_text())
    doc["provenance"]["cascal_version"] = "0.4.1"
    body = {k: v for k, v in doc.items() if k != "checksum"}
    doc["checksum"]["value"] = modelfile._checksum(body)
    old = tmp_path / "old.json"
    old.write_text(json.dumps(doc))
    loaded = modelfile.load_model(old)
    assert loaded.fitted.models[0].optimization.bounds is None and fit_findings(loaded) == []


def test_files_before_044_with_a_product_kernel_keep_no_bounds():
    """cascal 0.4.4 bounds a product's second factor's variance as a number, no longer by
    the data's variance: a product's bounds are today's only in files of 0.4.4 and later,
    other kernels' since 0.4.2."""
    from cascal.io.modelfile import _same_bounds
    from cascal.kernels import Periodic, SquaredExp

    se, per = SquaredExp(1.0, 1.0), Periodic(1.0, 1.0, period=360.0)
    for kernel, since in ((se, "0.4.2"), (se + per, "0.4.2"), (se * per, "0.4.4")):
        assert _same_bounds(since, kernel) and _same_bounds("1.0.0", kernel)
        assert not _same_bounds("0.4.1", kernel) and not _same_bounds("0.4.4rc1", kernel)
    assert not _same_bounds("0.4.3", se + se * per) and _same_bounds("0.4.3", se + per)


def test_a_stage_outside_the_range_above_names_units_and_turns(tmp_path):
    """A user review's cases: a device file whose test-bed column is in mm where the
    reference file's is in m, and rotary readings that wrap at 360 degrees fitted without
    the periodic kernel, were both told to measure the stage above over a wider range."""
    from cascal.errors import InputError

    x = np.linspace(0.05, 0.95, 12)
    ref = _stage(tmp_path / "ref.csv", x, x + 1e-4 * np.sin(3 * x))
    mm = _stage(tmp_path / "mm.csv", x * 1000, x * 1000 + 0.1, names=("device", "testbed"))
    with pytest.raises(InputError, match=r"12 of 12 points lie outside, up to 949.*different un"):
        fit_model([ref, mm], n_restarts=1)
    deg = np.linspace(25.0, 335.0, 12)  # the reference cannot reach 0 degrees
    table = _stage(tmp_path / "table.csv", deg, deg + 0.01)
    turn = np.linspace(1.0, 359.0, 30)  # the device turns all the way round
    enc = _stage(tmp_path / "enc.csv", turn, turn + 0.02, names=("encoder", "testbed"))
    leave = r"range too, or leave them out \(--exclude enc.csv:2,3,30,31\)"
    with pytest.raises(InputError, match=leave + r"; or, for a rotary axis .* --period 360, a GP"):
        fit_model([table, enc], n_restarts=1, unit="deg")
    with pytest.raises(InputError, match=leave + "$"):  # a linear axis in mm
        fit_model([table, enc], n_restarts=1, unit="mm")
    with pytest.raises(InputError, match=r"--period 6.28318530717959, a GP"):
        fit_model([table, enc], n_restarts=1, unit="rad")  # (the numbers do not matter)


def test_the_exclude_advice_names_a_file_whose_name_the_stage_above_shares_by_its_path(tmp_path):
    """A user review's case: two stage files named s.csv in two folders; fit advised
    ``--exclude s.csv:...``, which it then refused as naming several stage files."""
    from cascal.errors import InputError

    x = np.linspace(0.05, 0.95, 12)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    ref = _stage(tmp_path / "a" / "s.csv", x, x + 1e-4 * np.sin(3 * x))
    dev = _stage(tmp_path / "b" / "s.csv", x, np.r_[x[:-1], 0.99], names=("device", "testbed"))
    with pytest.raises(InputError) as exc:
        fit_model([ref, dev], n_restarts=1)
    assert f"(--exclude {tmp_path / 'b' / 's.csv'}:13)" in str(exc.value)
