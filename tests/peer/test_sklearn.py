"""cascal against scikit-learn's GaussianProcessRegressor at the same hyperparameters.

sklearn's noise ``alpha`` is diagonal only, so the peer covers learned-scalar and per-point
noise. cascal's identity prior mean is matched by giving sklearn the residuals ``y - x``.
"""

from __future__ import annotations

import numpy as np
import pytest

from utils import assert_allclose

pytest.importorskip("sklearn")
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import (
    RBF,
    ConstantKernel,
    ExpSineSquared,
    Matern,
    WhiteKernel,
)

from cascal import fit_gp, log_marginal_likelihood
from cascal.kernels import Matern32, Matern52, Periodic, SquaredExp

N = 25


def _data(periodic: bool):
    g = np.random.default_rng(31)
    if periodic:
        x = np.sort(g.uniform(0.0, 720.0, N))  # degrees, two turns
        y = x + 0.05 * np.sin(np.deg2rad(x)) + 0.02 * np.cos(np.deg2rad(3 * x))
        y = y + 1e-3 * g.normal(size=N)
        xs = np.linspace(-30.0, 750.0, 61)
    else:
        x = np.sort(g.random(N))
        y = x + 0.01 * np.sin(6 * x) + 1e-3 * g.normal(size=N)
        xs = np.linspace(-0.2, 1.2, 61)
    return x, y, xs


# name: (cascal kernel, sklearn kernel without the constant factor, variance, periodic?)
L, V = 0.25, 2e-4
KERNELS = {
    "se": (SquaredExp(L, V), RBF(L), False),
    "matern32": (Matern32(L, V), Matern(L, nu=1.5), False),
    "matern52": (Matern52(L, V), Matern(L, nu=2.5), False),
    "periodic": (
        Periodic(0.8, V, period=360.0),
        ExpSineSquared(length_scale=0.8, periodicity=360.0, periodicity_bounds="fixed"),
        True,
    ),
}


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_kernel_matrices_agree(name):
    # includes the mapping ExpSineSquared(l, p) == Periodic(l, variance=1, period=p)
    ck, sk, periodic = KERNELS[name]
    x, _, xs = _data(periodic)
    skk = ConstantKernel(V) * sk
    assert_allclose(ck(x), skk(x[:, None]), rtol=1e-13, atol=1e-300)
    assert_allclose(ck(xs, x), skk(xs[:, None], x[:, None]), rtol=1e-13, atol=1e-300)


def test_exp_sine_squared_formula():
    # sklearn: exp(-2 sin^2(pi d / p) / l^2); cascal's Periodic with variance 1 is the same
    d = np.array([0.0, 30.0, 90.0, 200.0])
    sk = ExpSineSquared(length_scale=0.7, periodicity=360.0)
    expected = np.exp(-2 * np.sin(np.pi * d / 360.0) ** 2 / 0.7**2)
    assert_allclose(sk(np.zeros((1, 1)), d[:, None])[0], expected, rtol=1e-14)
    assert_allclose(Periodic(0.7, 1.0, period=360.0)(np.zeros(1), d)[0], expected, rtol=1e-14)


@pytest.mark.parametrize("name", sorted(KERNELS))
@pytest.mark.parametrize("form", ["scalar", "vector"])
def test_prediction_and_lml_agree(name, form):
    ck, sk, periodic = KERNELS[name]
    x, y, xs = _data(periodic)
    if form == "scalar":
        noise = 1e-6
        fit = fit_gp(x, y, kernel=ck, hyperparameters={**ck.params, "noise_variance": noise})
    else:
        noise = np.linspace(5e-7, 4e-6, N)
        fit = fit_gp(x, y, kernel=ck, noise=noise, hyperparameters=ck.params)
    gpr = GaussianProcessRegressor(
        ConstantKernel(V) * sk, alpha=noise, optimizer=None, normalize_y=False
    ).fit(x[:, None], y - x)
    m_sk, s_sk = gpr.predict(xs[:, None], return_std=True)
    m, s = fit.predict(xs, return_std=True)
    assert_allclose(m - xs, m_sk, rtol=1e-9, atol=1e-9 * np.max(np.abs(m_sk)))
    assert_allclose(s, s_sk, rtol=1e-9, atol=1e-12)
    _, cov_sk = gpr.predict(xs[:, None], return_cov=True)
    assert_allclose(fit.predict(xs, return_cov=True)[1], cov_sk, rtol=0, atol=1e-11 * V)
    assert fit.log_marginal_likelihood == pytest.approx(
        gpr.log_marginal_likelihood_value_, rel=1e-10
    )
    # gradient: sklearn's theta is [log constant, log length_scale]; cascal's is reversed
    lml_sk, g_sk = gpr.log_marginal_likelihood(gpr.kernel_.theta, eval_gradient=True)
    known = noise if form == "vector" else None
    sn2 = 0.0 if form == "vector" else noise
    v, g = log_marginal_likelihood(
        x, y, kernel=ck, noise=known, noise_variance=sn2, eval_gradient=True
    )
    assert v == pytest.approx(lml_sk, rel=1e-10)
    assert_allclose(g[[1, 0]], g_sk, rtol=1e-7, atol=1e-7 * np.max(np.abs(g_sk)))


@pytest.mark.parametrize("name", ["se", "matern52"])
def test_white_kernel_as_learned_noise(name):
    ck, sk, periodic = KERNELS[name]
    x, y, xs = _data(periodic)
    sn2 = 2e-6
    fit = fit_gp(x, y, kernel=ck, hyperparameters={**ck.params, "noise_variance": sn2})
    gpr = GaussianProcessRegressor(
        ConstantKernel(V) * sk + WhiteKernel(sn2), alpha=0.0, optimizer=None
    ).fit(x[:, None], y - x)
    m_sk, s_sk = gpr.predict(xs[:, None], return_std=True)
    m, s = fit.predict(xs, return_std=True)
    assert_allclose(m - xs, m_sk, rtol=1e-9, atol=1e-9 * np.max(np.abs(m_sk)))
    # sklearn's std includes the white noise at the test points; cascal's is of the latent map
    assert_allclose(s**2 + sn2, s_sk**2, rtol=1e-9)
    assert fit.log_marginal_likelihood == pytest.approx(
        gpr.log_marginal_likelihood_value_, rel=1e-10
    )
    # gradient with respect to [log c, log l, log noise] against cascal's [log l, log v, log sn2]
    _, g_sk = gpr.log_marginal_likelihood(gpr.kernel_.theta, eval_gradient=True)
    _, g = log_marginal_likelihood(x, y, kernel=ck, noise_variance=sn2, eval_gradient=True)
    assert_allclose(g[[1, 0, 2]], g_sk, rtol=1e-7, atol=1e-7 * np.max(np.abs(g_sk)))
