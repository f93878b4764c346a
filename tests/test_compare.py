"""Comparing a recalibration with the calibration before: the change, the covariance it
would have were the device unchanged (against dense textbook formulas), and the
simultaneous band's false-alarm rate (against sampling)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cascal.errors import InputError
from cascal.verification import band_factor, compare
from cascal.workflow import (
    change_covariance,
    compare_models,
    correct,
    fit_model,
    shares_upstream,
)
from utils import demo_stages


@pytest.fixture(scope="module")
def pair():
    """A device's calibration and its recalibration against the same test bed, after a
    drift of the device of 50 µm across the axis (more accurate readings moved)."""
    ref, dev = demo_stages()
    drifted = dataclasses.replace(dev, y=dev.y + 5e-5 * (dev.x - 0.5) * 2)
    testbed = fit_model([ref], n_restarts=1)
    old = fit_model([dev], prefix=testbed, n_restarts=1)
    new = fit_model([drifted], prefix=testbed, n_restarts=1)
    return old, new


def _dense_posterior_cov(gp, a, b):
    """The textbook latent posterior covariance between positions a and b."""
    C = gp.L @ gp.L.T  # the target covariance the fit factorised
    return gp.kernel(a, b) - gp.kernel(a, gp.x) @ np.linalg.solve(C, gp.kernel(gp.x, b))


def _targets_covariance(old, new, shared, same_file=False):
    """Covariance of the two device fits' targets were the device unchanged, written out:
    one device map (the old fit's prior), each file's white noise, the test bed's posterior
    covariance at each file's test-bed readings, and between them where it is shared; with
    ``same_file`` (one device file, the test bed refitted), the file's white noise (one
    draw) between them too."""
    go, gn = old.fitted.device, new.fitted.device
    x = np.concatenate([go.x, gn.x])
    no = go.x.size
    ya, yb = old.data[-1].y, new.data[-1].y
    C = go.kernel(x, x)
    C[:no, :no] += go.noise_variance * np.eye(no)
    C[no:, no:] += gn.noise_variance * np.eye(gn.x.size)
    C[:no, :no] += _dense_posterior_cov(old.fitted.models[0], ya, ya)
    C[no:, no:] += _dense_posterior_cov(new.fitted.models[0], yb, yb)
    if shared:
        S = _dense_posterior_cov(old.fitted.models[0], ya, yb)
        C[:no, no:] += S
        C[no:, :no] += S.T
    if same_file:
        both = np.sqrt(go.noise_variance * gn.noise_variance) * np.eye(no)
        C[:no, no:] += both
        C[no:, :no] += both
    return C


def _weights(gp, r):
    return np.linalg.solve(gp.L @ gp.L.T, gp.kernel(gp.x, r))


def _homoscedastic_pair():
    """Two homoscedastic calibrations against test beds fitted on different reference
    data (their errors independent; the fits themselves ignore them)."""
    ref, dev = demo_stages()
    other = dataclasses.replace(ref, y=ref.y + 2e-7)
    kw = dict(method="homoscedastic", n_restarts=1)
    return fit_model([ref, dev], **kw), fit_model([other, dev], **kw)


@pytest.mark.parametrize("which", ["bayes, one test bed", "homoscedastic, two test beds"])
def test_change_covariance_against_dense_formulas(pair, which):
    old, new = pair if which.startswith("bayes") else _homoscedastic_pair()
    shared = shares_upstream(old, new)
    assert shared == which.startswith("bayes")
    r = np.linspace(*old.calibrated_range, 37)
    # (the homoscedastic pair: one device file, its noise one draw in both)
    C = _targets_covariance(old, new, shared, same_file=not shared)
    v = np.concatenate([-_weights(old.fitted.device, r), _weights(new.fitted.device, r)])
    expected = v.T @ C @ v
    got = change_covariance(old, new, r, shared=shared)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-7 * np.abs(expected).max())
    if shared:  # the shared test bed counted once: less than were it not shared
        alone = change_covariance(old, new, r, shared=False)
        assert np.all(np.diag(got) < np.diag(alone))
    # For bayes, the test bed's posterior at the device file's readings is the known
    # noise the fit was given (up to the pivoted factor's dropped pivots).
    up = old.fitted.models[0].cross_covariance(old.data[-1].y, old.data[-1].y)
    if old.method == "bayes":
        Sigma = old.fitted.device.noise.dense(old.fitted.device.x.size)
        np.testing.assert_allclose(up, Sigma, rtol=0, atol=1e-6 * np.abs(Sigma).max())


def test_an_unchanged_device_leaves_the_band_in_5_percent_of_recalibrations(pair):
    old, new = pair
    c = compare_models(old, new)
    cov = change_covariance(old, new, c.reading, shared=True)
    np.testing.assert_allclose(c.u, np.sqrt(np.diag(cov)), rtol=1e-12)
    w, V = np.linalg.eigh(cov)
    big = w > w[-1] * 1e-12
    rng = np.random.default_rng(7)  # not the band's own draws
    z = (
        np.abs((V[:, big] * np.sqrt(w[big])) @ rng.standard_normal((big.sum(), 8000)))
        / c.u[:, None]
    )
    top = z.max(axis=0)
    assert 0.04 < np.mean(top > c.k_band) < 0.06
    # Judged by k = 2 at every reading, an unchanged device would look changed far more often.
    assert np.mean(top > 2.0) > 0.2


def test_band_factor_against_known_cases():
    from scipy.stats import norm

    one = band_factor(np.array([[4.0]]))
    assert one == pytest.approx(norm.ppf(0.975), abs=0.03)
    ones = band_factor(np.full((50, 50), 2.0))  # fully correlated: one value
    assert ones == pytest.approx(norm.ppf(0.975), abs=0.03)
    sidak = norm.ppf(1 - (1 - 0.95 ** (1 / 100)) / 2)
    assert band_factor(np.diag(np.linspace(1, 9, 100))) == pytest.approx(sidak, abs=0.03)
    assert band_factor(np.eye(3)) == band_factor(np.eye(3))  # a fixed seed: the same factor


def test_compare_models_reports_the_change_and_its_uncertainty(pair):
    old, new = pair
    c = compare_models(old, new)
    lo, hi = old.calibrated_range
    np.testing.assert_array_equal(c.reading, np.linspace(lo, hi, 1001))
    a, b = correct(old, c.reading), correct(new, c.reading)
    np.testing.assert_array_equal(c.change, b.corrected - a.corrected)
    np.testing.assert_array_equal(c.u_old, a.u)
    assert c.shared
    np.testing.assert_allclose(c.en, np.abs(c.change) / (2 * c.u), rtol=1e-12)
    # The drift is found: the change follows it where the data are dense.
    mid = (c.reading > 0.3) & (c.reading < 0.7)
    drift = 5e-5 * (c.reading - 0.5) * 2
    assert np.max(np.abs(c.change - drift)[mid]) < 2e-5
    s = c.summary()
    i = int(np.argmax(np.abs(c.change)))
    assert s["max_change"] == abs(c.change[i]) and s["at"] == c.reading[i]
    assert s["rms_change"] == pytest.approx(np.sqrt(np.mean(c.change**2)), rel=1e-12)
    assert s["share_beyond_U"] == np.count_nonzero(np.abs(c.change) > 2 * c.u) / 1001
    assert s["share_beyond_band"] == np.count_nonzero(np.abs(c.change) > c.k_band * c.u) / 1001
    assert c.changed == (s["max_z"] > c.k_band)
    # A model against itself: no change.
    same = compare_models(old, old)
    assert np.all(same.change == 0.0) and np.all(same.en == 0.0)


def test_upstream_is_shared_by_data_and_hyperparameters(pair):
    old, new = pair
    ref, dev = demo_stages()
    # The same test bed fitted again (another cascal version): hyperparameters a few
    # 1e-11 apart still count as the same calibration.
    up = old.fitted.models[0]
    kernel = dataclasses.replace(up.kernel, length_scale=up.kernel.length_scale * (1 + 3e-11))
    refit = dataclasses.replace(
        new,
        fitted=dataclasses.replace(
            new.fitted, models=(dataclasses.replace(up, kernel=kernel), new.fitted.device)
        ),
    )
    assert shares_upstream(old, refit)
    other_ref = dataclasses.replace(ref, y=ref.y + 1e-7)  # a test bed fitted on other data
    other = fit_model([other_ref, dev], n_restarts=1)
    assert not shares_upstream(old, other)
    c = compare_models(old, other)
    assert not c.shared
    cov = change_covariance(old, other, c.reading)
    np.testing.assert_allclose(c.u, np.sqrt(np.diag(cov)), rtol=1e-12)
    homo = fit_model([ref, dev], method="homoscedastic", n_restarts=1)
    assert shares_upstream(old, homo)  # one test bed: stage 0 is fitted alike by both methods
    assert not shares_upstream(old, fit_model([ref, dev], method="lut"))


def test_rotary_changes_go_the_short_way_round():
    reading = np.array([0.0, 90.0, 180.0])
    c = compare(reading, np.array([359.9, 90.0, 10.0]), np.ones(3), np.array([0.1, 90.2, 9.0]),
                np.ones(3), period=360.0)  # fmt: skip
    np.testing.assert_allclose(c.change, [0.2, 0.2, -1.0], atol=1e-12)
    np.testing.assert_allclose(c.en, np.abs(c.change) / (2 * np.sqrt(2.0)))
    with pytest.raises(
        InputError,
        match=r"u_new of one non-empty shape \(n,\), got \(3,\), \(3,\), \(3,\), \(2,\)",
    ):
        compare(reading, reading, reading, reading[:2], reading)


def test_models_that_cannot_be_compared_are_refused(pair):
    old, _ = pair
    ref, dev = demo_stages()
    with pytest.raises(InputError, match="different units"):
        compare_models(old, dataclasses.replace(old, unit="mm"))
    with pytest.raises(InputError, match="differ in their period"):
        compare_models(old, dataclasses.replace(old, period=360.0))
    with pytest.raises(InputError, match="the models have 2 and 1 stages"):
        compare_models(old, fit_model([ref], n_restarts=1))
    part = dataclasses.replace(dev, x=dev.x[:40], y=dev.y[:40], counts=dev.counts[:40],
                               rows=dev.rows[:40])  # fmt: skip
    late = dataclasses.replace(dev, x=dev.x[-40:], y=dev.y[-40:], counts=dev.counts[-40:],
                               rows=dev.rows[-40:])  # fmt: skip
    a, b = fit_model([ref, part], n_restarts=1), fit_model([ref, late], n_restarts=1)
    with pytest.raises(InputError, match="do not overlap"):
        compare_models(a, b)


def test_rotary_models_are_compared_over_one_turn():
    from cascal.demo import rotary_demo

    ref, dev = demo_stages(rotary_demo(0))
    kw = dict(kernel="periodic", period=360.0, unit="deg", n_restarts=1)
    testbed = fit_model([ref], **kw)
    old = fit_model([dev], prefix=testbed, **kw)
    new = fit_model([dataclasses.replace(dev, y=dev.y + 1e-3)], prefix=testbed, **kw)
    c = compare_models(old, new, n=360)
    np.testing.assert_array_equal(c.reading, np.arange(360.0))
    assert c.shared and c.period == 360.0
    a, b = correct(old, c.reading), correct(new, c.reading)
    d = b.corrected - a.corrected
    np.testing.assert_allclose(c.change, d - 360.0 * np.round(d / 360.0), rtol=0, atol=1e-12)
    assert np.all(np.abs(c.change - 1e-3) < 3e-4)  # the offset, all the way round


def test_rotary_models_are_compared_over_the_arc_both_devices_cover(monkeypatch):
    """A review's case: a swivel's device readings covering 7 to 199 deg were compared over
    the whole turn, where both models only extrapolate: a change of 0.0074 deg there failed
    a --max-change that the measured arc passed (0.00032). The readings now span the part
    both cover; two arcs that overlap at both ends give two stretches, and arcs that do not
    overlap are refused."""
    from cascal import workflow
    from cascal.demo import rotary_demo

    ref, dev = demo_stages(rotary_demo(0))
    kw = dict(kernel="periodic", period=360.0, unit="deg", n_restarts=1)
    testbed = fit_model([ref], **kw)
    part = dev.x < 200.0
    old = fit_model([dataclasses.replace(dev, x=dev.x[part], y=dev.y[part])], prefix=testbed, **kw)
    late = (dev.x > 50.0) & (dev.x < 300.0)
    new = fit_model([dataclasses.replace(dev, x=dev.x[late], y=dev.y[late])], prefix=testbed, **kw)
    c = compare_models(old, new, n=101)
    lo, hi = dev.x[late].min(), dev.x[part].max()
    np.testing.assert_allclose(c.reading, np.linspace(lo, hi, 101), rtol=0, atol=1e-12)
    assert not correct(old, c.reading).out_of_range.any()
    assert not correct(new, c.reading).out_of_range.any()
    full = fit_model([dev], prefix=testbed, **kw)  # the whole turn: the other's arc alone
    arc = np.array(workflow.measured_arc(old))  # from the first turn on
    arc -= 360.0 * np.floor(arc[0] / 360.0)
    np.testing.assert_allclose(compare_models(full, old, n=11).reading, np.linspace(*arc, 11))
    arcs = {id(old): (300.0, 460.0), id(new): (50.0, 330.0)}  # 300-330 and 410-460 (50-100)
    monkeypatch.setattr(workflow, "measured_arc", lambda m: arcs[id(m)])
    r = compare_models(old, new, n=80).reading
    np.testing.assert_allclose(r, np.r_[np.linspace(300, 330, 30), np.linspace(410, 460, 50)])
    arcs[id(new)] = (190.0, 370.0)  # 190-200 and 360-370: 500.5 each of 1001, rounded
    assert compare_models(old, new, n=1001).reading.size == 1001
    arcs[id(new)] = (120.0, 250.0)
    with pytest.raises(InputError, match=r"cover \(300 to 460 and 120 to 250 deg\) do not overlap"):
        compare_models(old, new)


def test_a_drifted_device_leaves_the_band_and_an_unchanged_one_does_not():
    from cascal.demo import linear_recalibration
    from cascal.io.data import StageData

    ref, dev = demo_stages()
    testbed = fit_model([ref], n_restarts=1)
    old = fit_model([dev], prefix=testbed, n_restarts=1)
    found = {}
    for drift in (0.0, 2.5e-4):
        st = linear_recalibration(0, drift=drift)
        data = StageData(st.x, st.y, None, np.ones(st.x.size, int), np.arange(2, 202), dev.source)
        c = compare_models(old, fit_model([data], prefix=testbed, n_restarts=1))
        found[drift] = (c.changed, c.summary()["max_z"], c.k_band)
    assert found[0.0][0] is False and found[2.5e-4][0] is True, found


def test_a_limit_is_judged_with_the_change_s_uncertainty():
    """``against(T)``: shown beyond T where |change| - k_band u > T, shown within where
    |change| + k_band u <= T everywhere, else undecided; five independent points of u = 1
    mm (k_band about 2.57, Sidak's factor)."""
    r = np.linspace(0.0, 1.0, 5)
    change = np.array([0.0, 1.0, 2.0, 5.0, -6.0]) * 1e-3
    c = compare(r, r, np.full(5, 1e-3), r + change, np.zeros(5), change_cov=np.eye(5) * 1e-6)
    k = c.k_band
    assert 2.5 < k < 2.65
    v = c.against(2e-3)  # 6 - k and 5 - k mm exceed 2 mm; k u alone reaches 2 mm everywhere
    assert (v.verdict, v.share_beyond, v.share_unresolved) == ("beyond", 0.4, 1.0)
    v = c.against(4e-3)  # 6 - k < 4 < 6 + k: not shown either way; 2, 5 and 6 mm not within
    assert (v.verdict, v.share_beyond, v.share_not_within, v.share_unresolved) == (
        "undecided", 0.0, 0.6, 0.0,
    )  # fmt: skip
    v = c.against(9e-3)  # 6 + k < 9
    assert (v.verdict, v.share_not_within) == ("within", 0.0)
    lut = compare(r, r, np.full(5, np.nan), r + change, np.full(5, np.nan))
    assert lut.against(5.5e-3).verdict == "beyond" and lut.against(6.01e-3).verdict == "within"
    with pytest.raises(InputError, match="limit: expected a finite number > 0"):
        c.against(0.0)
    # (a diff review: u 0 everywhere, no band: a NaN margin had passed any change)
    exact = compare(r, r, np.zeros(5), r + change, np.zeros(5))
    assert exact.against(5.5e-3).verdict == "beyond" and exact.against(6.01e-3).verdict == "within"


def test_a_limit_s_wrong_verdicts_are_rare():
    """Over 4000 draws of the change of a correlated 60-point comparison: an unchanged
    device is shown beyond even a tiny limit only as often as it leaves the band (about 5
    %: pointwise at k = 2 it would be far more often), and a change at a limit of 3 u
    everywhere is shown within it in under 2.5 % (its estimate must fall k_band u below it
    at every reading; judged by the change alone, in about a third of the draws, the
    change's correlation reaching over half the range)."""
    r = np.linspace(0.0, 1.0, 60)
    sd = 1e-4 * (1.0 + r)
    cov = np.exp(-0.5 * ((r[:, None] - r[None, :]) / 0.1) ** 2) * np.outer(sd, sd)
    cov += np.diag(1e-3 * sd**2)
    c = compare(r, r, sd, r, np.zeros(60), change_cov=cov)
    t = 1e-6 * float(np.max(c.u))
    draws = np.random.default_rng(1).multivariate_normal(np.zeros(60), cov, size=4000)
    beyond = [dataclasses.replace(c, change=e).against(t).verdict == "beyond" for e in draws]
    band = [dataclasses.replace(c, change=e).changed for e in draws]
    assert np.mean(beyond) <= np.mean(band) < 0.065 and np.mean(beyond) > 0.035
    wide = np.exp(-0.5 * ((r[:, None] - r[None, :]) / 0.5) ** 2) * np.outer(sd, sd)
    wide += np.diag(1e-3 * sd**2)
    c = compare(r, r, sd, r, np.zeros(60), change_cov=wide)
    t = 3.0 * float(np.max(c.u))
    draws = np.random.default_rng(2).multivariate_normal(np.zeros(60), wide, size=4000)
    within = [dataclasses.replace(c, change=t + e).against(t).verdict == "within" for e in draws]
    alone = [np.all(np.abs(t + e) <= t) for e in draws]  # (no margin)
    assert np.mean(within) < 0.025 < 0.2 < np.mean(alone)


def test_one_device_file_under_a_recalibrated_test_bed_shares_its_noise():
    """A user review's leftover: the device file reused under a test bed fitted on other
    reference data counted the file's noise as two independent draws. It is one: the
    change's covariance against the dense formulas with that noise shared, and narrower
    than with it independent; every file the same keeps them independent (compare says
    so)."""
    ref, dev = demo_stages()
    bump = dataclasses.replace(ref, y=ref.y + 3e-5 * np.exp(-(((ref.x - 0.75) / 0.1) ** 2)))
    old, new = (fit_model([t, dev], n_restarts=1) for t in (ref, bump))
    assert not shares_upstream(old, new)
    r = np.linspace(*old.calibrated_range, 37)
    v = np.concatenate([-_weights(old.fitted.device, r), _weights(new.fitted.device, r)])
    expected = v.T @ _targets_covariance(old, new, False, same_file=True) @ v
    got = change_covariance(old, new, r)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-7 * np.abs(expected).max())
    apart = v.T @ _targets_covariance(old, new, False) @ v
    assert np.all(np.diag(got) < np.diag(apart))
    same = change_covariance(old, old, r, shared=True)
    v = np.concatenate([-_weights(old.fitted.device, r), _weights(old.fitted.device, r)])
    expected = v.T @ _targets_covariance(old, old, True) @ v
    np.testing.assert_allclose(same, expected, rtol=0, atol=1e-7 * np.abs(expected).max())
