"""cascal against tinygp with dense (correlated) target noise at the same hyperparameters.

tinygp's ``noise.Dense`` is the peer for stage B of the cascade, which sklearn cannot
express. jax runs in float64 here.
"""

from __future__ import annotations

import numpy as np
import pytest

from utils import assert_allclose

tinygp = pytest.importorskip("tinygp")
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

from cascal import Cascade, fit_gp  # noqa: E402
from cascal.kernels import Matern32, Matern52, Periodic, SquaredExp  # noqa: E402
from cascal.simulation import simulate_trial  # noqa: E402

N = 30


@pytest.fixture
def data():
    g = np.random.default_rng(5)
    x = np.sort(g.random(N))
    y = x + 0.01 * np.sin(5 * x) - 0.004 * np.cos(11 * x) + 1e-3 * g.normal(size=N)
    C = 3e-6 * np.exp(-np.abs(x[:, None] - x[None, :]) / 0.2)  # correlated, positive definite
    return x, y, C, np.linspace(-0.1, 1.1, 41)


L, V, SN2 = 0.2, 1e-4, 5e-7
KERNELS = {
    "se": (SquaredExp(L, V), V * tinygp.kernels.ExpSquared(scale=L)),
    "matern32": (Matern32(L, V), V * tinygp.kernels.Matern32(scale=L)),
    "matern52": (Matern52(L, V), V * tinygp.kernels.Matern52(scale=L)),
    # tinygp: exp(-gamma sin^2(pi d / scale)); cascal: exp(-2 sin^2(pi d / period) / l^2)
    "periodic": (
        Periodic(0.9, V, period=0.6),
        V * tinygp.kernels.ExpSineSquared(scale=0.6, gamma=2.0 / 0.9**2),
    ),
}


def _tinygp(kernel, x, noise_matrix):
    return tinygp.GaussianProcess(
        kernel,
        jnp.asarray(x),
        noise=tinygp.noise.Dense(jnp.asarray(noise_matrix)),
        mean=lambda t: t,
    )


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_dense_noise_lml_and_posterior(name, data):
    x, y, C, xs = data
    ck, tk = KERNELS[name]
    assert_allclose(ck(x), np.asarray(tk(jnp.asarray(x), jnp.asarray(x))), rtol=1e-12, atol=1e-300)
    fit = fit_gp(x, y, kernel=ck, noise=C, hyperparameters={**ck.params, "noise_variance": SN2})
    assert fit.noise.n_clipped == 0
    gp = _tinygp(tk, x, C + SN2 * np.eye(N))
    assert fit.log_marginal_likelihood == pytest.approx(
        float(gp.log_probability(jnp.asarray(y))), rel=1e-9
    )
    # diag=0: tinygp would otherwise add sqrt(eps) to the predictive variance
    cond = gp.condition(jnp.asarray(y), jnp.asarray(xs), diag=0.0).gp
    mean, std = fit.predict(xs, return_std=True)
    assert_allclose(mean, np.asarray(cond.loc), rtol=1e-9, atol=1e-12)
    assert_allclose(std**2, np.asarray(cond.variance), rtol=1e-9, atol=1e-12 * V)
    _, cov = fit.predict(xs, return_cov=True)
    assert_allclose(cov, np.asarray(cond.covariance), rtol=0, atol=1e-10 * V)


def test_dense_noise_without_learned_scalar(data):
    x, y, C, xs = data
    ck, tk = KERNELS["se"]
    fit = fit_gp(x, y, kernel=ck, noise=C, learn_noise=False, hyperparameters=ck.params)
    assert fit.noise_variance == 0.0
    gp = _tinygp(tk, x, C)
    assert fit.log_marginal_likelihood == pytest.approx(
        float(gp.log_probability(jnp.asarray(y))), rel=1e-9
    )
    cond = gp.condition(jnp.asarray(y), jnp.asarray(xs), diag=0.0).gp
    assert_allclose(fit.predict(xs), np.asarray(cond.loc), rtol=1e-9, atol=1e-12)


def test_stage_b_of_a_cascade():
    # the fitted device stage of Algorithm 1, replayed in tinygp from its own matrices
    t = simulate_trial(np.random.default_rng(17))
    fc = Cascade([t.d2, t.d1], "bayes", n_restarts=2, seed=0).fit()
    dev = fc.device
    n = dev.x.size
    hp = dev.hyperparameters
    tk = hp["variance"] * tinygp.kernels.ExpSquared(scale=hp["length_scale"])
    gp = _tinygp(tk, dev.x, dev.noise.dense(n) + hp["noise_variance"] * np.eye(n))
    assert dev.log_marginal_likelihood == pytest.approx(
        float(gp.log_probability(jnp.asarray(dev.y))), rel=1e-9
    )
    r = np.linspace(*t.device_range, 57)
    cond = gp.condition(jnp.asarray(dev.y), jnp.asarray(r), diag=0.0).gp
    mean, std = fc.correct(r, return_std=True)
    assert_allclose(mean, np.asarray(cond.loc), rtol=1e-9, atol=1e-12)
    assert_allclose(std**2, np.asarray(cond.variance), rtol=1e-9, atol=1e-12 * np.max(std**2))
