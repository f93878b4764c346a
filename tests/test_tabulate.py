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
