"""Cholesky with escalating, recorded jitter; solves and log-determinants against NumPy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import lapack

from cascal import JitterWarning, NumericalError, SquaredExp, fit_gp, log_marginal_likelihood
from cascal.linalg import (
    JITTER_STEPS,
    cho_solve,
    cholesky,
    inverse_diagonal,
    inverse_from_cholesky,
    logdet,
    pivots_ok,
)
from cascal.noise import Dense, Diagonal
from utils import assert_allclose, dense_lml, se


@pytest.fixture
def spd(rng):
    B = rng.normal(size=(30, 30))
    return B @ B.T + 30 * np.eye(30)


def _singular():
    # SE kernel on 50 close points, no noise: numerically rank-deficient.
    x = np.linspace(0.0, 0.05, 50)
    return x, se(x, x, 0.2, 1e-4)


def test_cholesky_spd_no_jitter(spd):
    L, jitter = cholesky(spd)
    assert jitter == 0.0
    assert_allclose(np.triu(L, 1), 0.0, rtol=0)
    assert_allclose(L @ L.T, spd, rtol=1e-13)
    assert_allclose(L, np.linalg.cholesky(spd), rtol=1e-12)


def test_cholesky_singular_gets_jitter():
    _, A = _singular()
    with pytest.raises(np.linalg.LinAlgError):  # the premise: a plain Cholesky fails
        np.linalg.cholesky(A)
    L, jitter = cholesky(A)
    scale = np.mean(np.diagonal(A))
    assert jitter > 0
    assert any(jitter == pytest.approx(r * scale, rel=1e-15, abs=0) for r in JITTER_STEPS)
    assert_allclose(L @ L.T, A + jitter * np.eye(len(A)), rtol=1e-10, atol=1e-12 * scale)
    assert np.all(np.isfinite(L))


def test_jitter_recorded_in_fit():
    x, _ = _singular()
    y = x + 1e-3 * np.sin(20 * x)
    with pytest.warns(JitterWarning, match="needed jitter"):
        fit = fit_gp(
            x,
            y,
            noise=0.0,
            learn_noise=False,
            hyperparameters={"length_scale": 0.2, "variance": 1e-4},
        )
    assert fit.jitter > 0
    assert fit.jitter == pytest.approx(cholesky(se(x, x, 0.2, 1e-4))[1], rel=1e-12, abs=0)
    Kt = se(x, x, 0.2, 1e-4) + fit.jitter * np.eye(x.size)
    assert_allclose(fit.L @ fit.L.T, Kt, rtol=1e-10, atol=1e-12 * 1e-4)


def test_a_factor_of_round_off_pivots_gets_jitter():
    """Repeated positions and no noise: K is exactly singular, yet LAPACK's dpotrf reports
    success with pivots of round-off (a review's case: 1.2e-8 of the standard deviation,
    each adding about 18 nats to the likelihood). For a matrix with no noise on its
    diagonal, such a factor counts as failed: jitter is added and recorded, in the fit
    too, whose likelihood is then that of K + jitter."""

    a = 1.0 / 3.0  # [[1, a], [a, a^2 + 1 ulp]]: its second pivot is round-off
    A = np.array([[1.0, a], [a, np.nextafter(a * a, 1.0)]])
    L0, info = lapack.dpotrf(A, lower=1, clean=1)
    assert info == 0 and 0 < L0[1, 1] ** 2 < 1e-15  # the premise
    L, jitter = cholesky(A, noiseless=True)
    assert jitter == pytest.approx(JITTER_STEPS[0] * np.mean(np.diagonal(A)), rel=1e-12, abs=0)
    assert L[1, 1] ** 2 > 0.5 * jitter
    # with a noise on the diagonal, however small, the pivots are bounded below: kept (a
    # review found jitter there cost fits at the noise floor up to 540 nats)
    L, jitter = cholesky(A)
    assert jitter == 0.0 and L[1, 1] == L0[1, 1]
    # a fit: whether dpotrf fails or "succeeds" on such a K is round-off's luck; either way
    # it gets jitter now (it had recorded none, with a likelihood 14 nats too high)
    x = np.array([0, 0.1, 0.1, 0.2, 0.3, 0.3, 0.3, 0.5, 0.7, 0.9])
    y = x + 1e-3 * np.sin(10 * x)
    fit = fit_gp(x, y, noise=0.0)
    assert fit.jitter > 0
    hp = fit.hyperparameters
    Kt = se(x, x, hp["length_scale"], hp["variance"]) + fit.jitter * np.eye(x.size)
    sign, logdet_kt = np.linalg.slogdet(Kt)
    r = y - x
    lml = -0.5 * (r @ np.linalg.solve(Kt, r) + logdet_kt + x.size * np.log(2 * np.pi))
    # (K + jitter has a condition number of about 1e12: the dense formula holds 1e-3)
    assert sign > 0 and fit.log_marginal_likelihood == pytest.approx(lml, abs=1e-3)


def test_cholesky_refuses_indefinite(rng):
    Q, _ = np.linalg.qr(rng.normal(size=(5, 5)))
    A = (Q * np.array([3.0, 2.0, 1.0, 0.5, -1.0])) @ Q.T
    with pytest.raises(NumericalError, match="not positive definite even with a jitter"):
        cholesky(A, what="test matrix")
    with pytest.raises(NumericalError, match=r"test matrix \(5x5\)"):
        cholesky(A, what="test matrix")


@pytest.mark.parametrize("where", ["full", "diagonal", "off_diagonal", "last"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_cholesky_refuses_non_finite(spd, where, bad):
    A = spd.copy()
    if where == "full":
        A[:] = bad
    elif where == "diagonal":
        A[3, 3] = bad
    elif where == "off_diagonal":
        A[7, 2] = A[2, 7] = bad
    else:
        A[-1, -1] = bad
    with pytest.raises(NumericalError, match="NaN or inf"):
        cholesky(A)


def test_cho_solve(spd, rng):
    L, _ = cholesky(spd)
    b = rng.normal(size=30)
    B = rng.normal(size=(30, 4))
    assert_allclose(cho_solve(L, b), np.linalg.solve(spd, b), rtol=1e-11)
    assert_allclose(cho_solve(L, B), np.linalg.solve(spd, B), rtol=1e-11)


def test_logdet_and_inverse(spd):
    L, _ = cholesky(spd)
    sign, ld = np.linalg.slogdet(spd)
    assert sign == 1
    assert logdet(L) == pytest.approx(ld, rel=1e-13)
    inv = inverse_from_cholesky(L)
    assert_allclose(inv, inv.T, rtol=1e-14, atol=1e-18)
    assert_allclose(inv, np.linalg.inv(spd), rtol=1e-10, atol=1e-14)
    assert_allclose(inverse_diagonal(L), np.diag(np.linalg.inv(spd)), rtol=1e-10)


def test_a_noiseless_factor_beyond_round_off_conditioning_gets_jitter():
    """A review's case: 30 points, SE of length scale 0.1 and no noise, condition number
    6.8e17: the fit's factor passed the pivot check, no jitter was recorded and the
    likelihood was 30 times off the exact one (-3.9e11 against -1.2e13 in 80-digit
    arithmetic). A noiseless factor whose reciprocal condition number (dpocon) is below
    n eps now counts as failed; the likelihood function and the fit agree (that of K plus
    the recorded jitter)."""
    rng = np.random.default_rng(1)
    x = np.sort(rng.uniform(0, 1, 30))
    y = x + 1e-3 * np.sin(5 * x) + 1e-5 * rng.standard_normal(30)
    hp = {"length_scale": 0.1, "variance": 1e-6, "noise_variance": 0.0}
    with pytest.warns(JitterWarning, match="needed jitter 1e-18"):
        fit = fit_gp(x, y, hyperparameters=hp)
    assert fit.jitter == pytest.approx(JITTER_STEPS[0] * 1e-6, rel=1e-12, abs=0)
    with pytest.warns(JitterWarning, match="needed jitter 1e-18"):
        value = log_marginal_likelihood(x, y, kernel=SquaredExp(0.1, 1e-6))
    assert value == fit.log_marginal_likelihood
    well = SquaredExp(0.02, 1e-6)(x)  # condition 4.7e4: kept as it is
    L, jitter = cholesky(well, noiseless=True)
    assert jitter == 0.0 and pivots_ok(L, well)


def test_a_singular_known_noise_with_correlations_and_no_white_noise_gets_jitter():
    """A review's case: a shared offset of known variance (``1e-10`` everywhere, rank 1) as
    the whole noise, no white noise: ``K + N`` (condition 2.8e16) was factorised as it was,
    with no jitter recorded and a likelihood of round-off. Its positive diagonal had
    counted as noise, but a singular dense noise bounds no pivot below: the factor is now
    checked as a noiseless one's (jitter recorded and warned of, as with ``noise=0``). A
    dense noise of full rank, or one beside a white part (a second review: jitter had been
    added there too), bounds the pivots and keeps the exact factor."""
    n = 20
    x = np.linspace(0, 1, n)
    y = x + 1e-4 * np.sin(3 * x) + 1e-7 * np.random.default_rng(0).standard_normal(n)
    hp = {"length_scale": 0.2, "variance": 1e-6}
    shared = 1e-10 * np.ones((n, n))
    with pytest.warns(JitterWarning, match="needed jitter"):
        fit = fit_gp(x, y, noise=shared, learn_noise=False, hyperparameters=hp)
    assert fit.jitter > 0.0
    with pytest.warns(JitterWarning, match="needed jitter"):
        value = log_marginal_likelihood(x, y, kernel=SquaredExp(0.2, 1e-6), noise=shared)
    assert value == fit.log_marginal_likelihood
    full = shared + 1e-9 * np.eye(n)  # the same offset beside a white part: no jitter
    fit = fit_gp(x, y, noise=full, learn_noise=False, hyperparameters=hp)
    Kt = se(x, x, 0.2, 1e-6) + full
    assert fit.jitter == 0.0
    assert fit.log_marginal_likelihood == pytest.approx(dense_lml(y - x, Kt), rel=1e-12)
    beside = Diagonal(np.full(n, 1e-9)) + Dense(shared)  # the same, as a sum of two parts
    fit = fit_gp(x, y, noise=beside, learn_noise=False, hyperparameters=hp)
    assert fit.jitter == 0.0
    assert fit.log_marginal_likelihood == pytest.approx(dense_lml(y - x, Kt), rel=1e-12)
