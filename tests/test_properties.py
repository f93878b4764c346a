"""Hypothesis properties of GP regression over random positions, targets and hyperparameters."""

from __future__ import annotations

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from cascal import fit_gp
from cascal.gp import Objective
from cascal.kernels import Matern32, Matern52, Periodic, SquaredExp
from cascal.noise import Dense
from utils import dense_lml

SETTINGS = settings(max_examples=30, deadline=None, derandomize=True)

KINDS = {
    "se": lambda l, v: SquaredExp(l, v),
    "matern32": lambda l, v: Matern32(l, v),
    "matern52": lambda l, v: Matern52(l, v),
    "periodic": lambda l, v: Periodic(l, v, period=0.7),
}


@st.composite
def problems(draw, min_log_noise: float = -8.0):
    """Sorted positions (n,), targets (n,), a kernel and a noise variance."""
    x = np.sort(
        np.array(
            draw(
                st.lists(
                    st.floats(0.0, 1.0, allow_nan=False, allow_subnormal=False),
                    min_size=3,
                    max_size=12,
                    unique=True,
                )
            )
        )
    )
    kind = draw(st.sampled_from(sorted(KINDS)))
    l = 10 ** draw(st.floats(-1.5, 0.5))
    v = 10 ** draw(st.floats(-6.0, 1.0))
    sn2 = v * 10 ** draw(st.floats(min_log_noise, 0.0))
    z = np.array(draw(st.lists(st.floats(-2.0, 2.0), min_size=x.size, max_size=x.size)))
    return x, x + np.sqrt(v) * z, KINDS[kind](l, v), sn2


def _fit(x, y, kernel, sn2):
    return fit_gp(x, y, kernel=kernel, hyperparameters={**kernel.params, "noise_variance": sn2})


@SETTINGS
@given(problems(), st.lists(st.floats(-0.5, 1.5), min_size=1, max_size=10))
def test_posterior_variance_between_zero_and_prior(problem, extra):
    x, y, kernel, sn2 = problem
    v = kernel.variance
    fit = _fit(x, y, kernel, sn2)
    xs = np.r_[np.array(extra), x]
    _, std = fit.predict(xs, return_std=True)
    var = std**2
    assert np.all(np.isfinite(var))
    assert np.all(var >= 0.0)
    assert np.all(var <= v * (1 + 1e-9))
    # at a training point the data point alone leaves v sn2 / (v + sn2); more data only helps
    at_train = var[len(extra) :]
    assert np.all(at_train <= v * sn2 / (v + sn2) * (1 + 1e-6) + 1e-9 * v)
    # and the std path agrees with the covariance path
    _, cov = fit.predict(xs, return_cov=True)
    np.testing.assert_allclose(var, np.clip(np.diagonal(cov), 0, None), rtol=1e-7, atol=1e-10 * v)


@SETTINGS
@given(problems(min_log_noise=-10.0))
def test_tiny_noise_reproduces_targets(problem):
    x, y, kernel, _ = problem
    v = kernel.variance
    K = kernel(x)
    lam = np.linalg.eigvalsh(K).min()
    assume(lam > 1e-3 * v)  # the property needs a kernel matrix that can be inverted
    sn2 = 1e-10 * v
    fit = _fit(x, y, kernel, sn2)
    mean = fit.predict(x)
    # m - y = -sn2 (K + sn2 I)^-1 (y - x): at most sn2 / lambda_min |y - x|
    bound = sn2 / lam * np.linalg.norm(y - x)
    assert np.max(np.abs(mean - y)) <= 2 * bound + 1e-12 * (np.max(np.abs(y)) + np.sqrt(v))


@SETTINGS
@given(problems(), st.booleans())
def test_objective_equals_dense_formula(problem, with_dense):
    x, y, kernel, sn2 = problem
    n = x.size
    r = y - x
    C = sn2 * np.exp(-np.abs(x[:, None] - x[None, :]) / 0.3) if with_dense else None
    obj = Objective(x, r, kernel, None if C is None else Dense(C), True)
    theta = np.r_[kernel.theta, np.log(sn2)]
    Kt = kernel(x) + sn2 * np.eye(n) + (0.0 if C is None else C)
    expected = dense_lml(r, Kt)
    cond = np.linalg.cond(Kt)
    # both are backward stable: the values agree to ~eps cond(Kt) times their size (over 300
    # examples the worst was 0.4 eps cond(Kt)); allow 10 eps cond(Kt)
    value = obj.value(theta)
    rel = max(10 * np.finfo(float).eps * cond, 1e-13)
    assert abs(value - expected) <= rel * (abs(expected) + n)
