"""The verified interpolation table behind fast corrections, against exact GP prediction."""

from __future__ import annotations

import numpy as np
import pytest

from cascal import tabulate as tab_mod
from cascal.gp import fit_gp
from cascal.tabulate import predict_many, tabulate


def _gp(kernel, rng, period=None, n=80):
    lo, hi = (0.0, 360.0) if period else (0.0, 1.0)
    x = np.sort(rng.uniform(lo, hi, n))
    w = 2 * np.pi / (hi - lo)
    y = x + 0.01 * (hi - lo) * (np.sin(3 * w * x) + 0.5 * np.cos(7 * w * x))
    y = y + rng.normal(0, 1e-4 * (hi - lo), n)
    return fit_gp(x, y, kernel=kernel, period=period, n_restarts=2)


@pytest.mark.parametrize("kernel", ["se", "matern32", "matern52", "periodic"])
def test_table_matches_exact_prediction(kernel, rng):
    period = 360.0 if kernel == "periodic" else None
    gp = _gp(kernel, rng, period)
    lo, hi = float(gp.x.min()), float(gp.x.max())
    table = tabulate(gp, lo, hi, rtol=1e-6)
    assert table is not None
    r = rng.uniform(lo, hi, 20000)
    if period:
        r = np.r_[r, r[:100] + 360.0, r[:100] - 720.0]  # other turns
    mean, std = table(r, return_std=True)
    em, es = gp.predict(r, return_std=True)
    # The recorded bound comes from the coarser grid checked at its midpoints; the table's
    # own error is far below it. Check against the tolerance with a factor 2 to spare.
    tol = 1e-6 * float(es.min())
    assert np.max(np.abs(mean - em)) <= 2 * tol
    assert np.max(np.abs(std - es)) <= 2 * tol
    assert table.error_mean <= tol and table.error_std <= tol


def test_predict_many_uses_exact_prediction_for_few_and_outside(rng, monkeypatch):
    gp = _gp("se", rng)
    r = np.r_[np.linspace(0.1, 0.9, 50), -0.5, 1.7]
    mean, std = predict_many(gp, r, return_std=True)
    em, es = gp.predict(r, return_std=True)
    np.testing.assert_array_equal(mean, em)  # few readings: exact
    np.testing.assert_array_equal(std, es)
    monkeypatch.setattr(tab_mod, "MIN_READINGS_FOR_TABLE", 10)
    mean, std = predict_many(gp, r, return_std=True)
    np.testing.assert_array_equal(mean[-2:], em[-2:])  # outside the data: exact
    np.testing.assert_allclose(mean[:-2], em[:-2], rtol=0, atol=2e-6 * es.min())
    only_mean = predict_many(gp, r)
    np.testing.assert_array_equal(only_mean, mean)


def test_no_table_without_uncertainty_to_compare_with(rng):
    """A noise-free GP has std 0 at its data: no relative tolerance can be met."""
    x = np.linspace(0, 1, 12)
    gp = fit_gp(x, x + 0.01 * np.sin(5 * x), hyperparameters={"length_scale": 0.3,
                "variance": 1e-4, "noise_variance": 0.0})  # fmt: skip
    assert tabulate(gp, 0.0, 1.0, max_nodes=4097) is None
    r = np.linspace(0, 1, 25000)
    np.testing.assert_array_equal(predict_many(gp, r), gp.predict(r))


def _study_gps(n_trials):
    """The stage-B GPs (bayes and homoscedastic) of the study's first trials, with J's nodes."""
    from cascal.cascade import Cascade
    from cascal.montecarlo import trial_rng
    from cascal.simulation import j_reference, simulate_trial

    for i in range(n_trials):
        trial = simulate_trial(trial_rng(0, i))
        grid, _ = j_reference(trial)
        bayes = Cascade([trial.d2, trial.d1], "bayes", seed=i).fit()
        homo = Cascade([trial.d2, trial.d1], "homoscedastic", seed=i).fit(first=bayes.models[0])
        yield trial, grid, bayes.device
        yield trial, grid, homo.device


def test_chebyshev_mean_agrees_with_exact_prediction_to_its_rounding():
    """On the study's stage-B GPs the interpolant takes the place of the exact mean at J's
    2001 nodes: it differs from it by no more than the exact sum's own rounding (eps times
    sum |alpha_i k_i|, which dominates where alpha is large) or 1e-12 of the correction,
    and J moves by less than 1e-8 of itself."""
    from cascal.simulation import cost_j

    for trial, grid, gp in _study_gps(6):
        K = gp.kernel(grid, gp.x)
        exact = gp.mean(grid) + K @ gp.alpha
        rounding = np.finfo(float).eps * np.abs(K) @ np.abs(gp.alpha)
        cheb = tab_mod.chebyshev_mean(gp, grid)
        scale = np.max(np.abs(exact - gp.mean(grid)))
        assert np.all(np.abs(cheb - exact) <= 8 * np.maximum(rounding, 1e-12 * scale))
        ref = cost_j(trial, corrected=exact)
        assert abs(cost_j(trial, corrected=cheb) - ref) <= 1e-8 * ref
        assert not np.array_equal(cheb, exact)  # the interpolant, not the fallback


def test_chebyshev_mean_is_exact_where_a_polynomial_cannot_follow(rng):
    """A length scale short against the range (coefficients decay slowly), a kernel of
    limited smoothness or a periodic kernel: the exact mean, bit for bit."""
    x = np.linspace(0.0, 1.0, 200)
    y = x + 1e-3 * np.sin(150 * x) + rng.normal(0, 1e-6, 200)
    short = fit_gp(x, y, n_restarts=2)
    assert short.hyperparameters["length_scale"] < 0.03
    grid = np.linspace(0.0, 1.0, 2001)
    assert np.array_equal(tab_mod.chebyshev_mean(short, grid), short.predict(grid))
    for kernel in ("matern32", "periodic"):
        gp = _gp(kernel, rng, 360.0 if kernel == "periodic" else None)
        g = np.linspace(float(gp.x.min()), float(gp.x.max()), 2001)
        assert np.array_equal(tab_mod.chebyshev_mean(gp, g), gp.predict(g))
