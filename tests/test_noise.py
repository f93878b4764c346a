"""Noise models against their explicit dense matrices; Dense's repairs and refusals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cascal import CascalError, InputError
from cascal.noise import Dense, Diagonal, Noise, NoiseSum, as_noise
from utils import assert_allclose

N = 6


@pytest.fixture
def K(rng):
    B = rng.normal(size=(N, N))
    return B @ B.T + N * np.eye(N)


@pytest.fixture
def C(rng):
    # a correlated, positive-definite covariance: exponential correlation plus a nugget
    x = np.sort(rng.random(N))
    return 1e-4 * (0.8 * np.exp(-np.abs(x[:, None] - x[None, :]) / 0.3) + 0.2 * np.eye(N))


def test_diagonal_scalar(K):
    d = Diagonal(0.3)
    assert d.is_diagonal
    assert_allclose(d.diagonal(N), np.full(N, 0.3), rtol=0)
    assert_allclose(d.dense(N), 0.3 * np.eye(N), rtol=0)
    K0 = K.copy()
    assert_allclose(d.add_to(K), K + 0.3 * np.eye(N), rtol=1e-15)
    assert_allclose(K, K0, rtol=0)  # add_to returns a new array


def test_diagonal_vector(K):
    v = np.arange(1.0, N + 1) * 1e-3
    d = Diagonal(v)
    assert_allclose(d.diagonal(N), v, rtol=0)
    assert_allclose(d.dense(N), np.diag(v), rtol=0)
    assert_allclose(d.add_to(K), K + np.diag(v), rtol=1e-15)
    with pytest.raises(InputError, match=rf"expected shape \({N + 1},\), got \({N},\)"):
        d.diagonal(N + 1)


@pytest.mark.parametrize("bad", [-1e-3, np.array([1.0, np.nan]), np.array([1.0, -1.0]), np.inf])
def test_diagonal_refuses_bad_variances(bad):
    with pytest.raises(InputError, match="expected finite values >= 0"):
        Diagonal(bad)


def test_diagonal_refuses_matrix():
    with pytest.raises(InputError, match=r"expected a number or shape \(n,\), got \(2, 2\)"):
        Diagonal(np.eye(2))


def test_dense(K, C):
    d = Dense(C)
    assert not d.is_diagonal
    assert d.n_clipped == 0
    assert_allclose(d.dense(N), C, rtol=1e-15)
    assert_allclose(d.diagonal(N), np.diagonal(C), rtol=1e-15)
    assert_allclose(d.add_to(K), K + C, rtol=1e-15)
    assert d.min_eigenvalue == pytest.approx(np.linalg.eigvalsh(C).min(), rel=1e-10)
    with pytest.raises(InputError, match=rf"expected shape \({N - 1}, {N - 1}\), got \({N}, {N}\)"):
        d.dense(N - 1)


def test_dense_symmetrises(C):
    A = C.copy()
    A[0, 1] += 1e-13 * C.max()  # below the symmetry tolerance (1e-8 relative)
    d = Dense(A)
    assert_allclose(d.cov, d.cov.T, rtol=0)
    assert_allclose(d.cov, 0.5 * (A + A.T), rtol=1e-15)


def test_a_repaired_dense_defers_its_factor_to_the_first_use(rng):
    """Dense.repaired (a model file's noise) keeps the matrix bit for bit and gives the
    factor Dense computes, from an eigendecomposition made on first use only."""
    B = rng.normal(size=(12, 3))
    d = Dense(B @ B.T - 1e-15 * np.eye(12))  # clipped round-off, as a posterior has
    back = Dense.repaired(d.cov, d.tol, d.atol)
    assert back._factor is None and back.n_clipped == 0
    assert (back.tol, back.atol) == (d.tol, d.atol)
    assert np.array_equal(back.dense(12), d.cov)
    U0, U1 = d.factor(12), back.factor(12)
    assert U1.shape == U0.shape
    assert_allclose(U1 @ U1.T, U0 @ U0.T, rtol=0, atol=1e-14 * np.abs(d.cov).max())
    for bad in (np.ones((2, 3)), np.array([[1.0, np.inf], [np.inf, 1.0]])):
        with pytest.raises(InputError, match="finite square"):
            Dense.repaired(bad)
    # a variance of round-off below zero (Dense keeps one where no eigenvalue is clipped:
    # a row of a near-zero variance, as a review found in 32 of 3000 random matrices)
    C = np.array([[1.0, 1e-18], [1e-18, -1e-19]])
    assert np.array_equal(Dense.repaired(C).dense(2), C)
    for bad in ([[-1.0, 0.0], [0.0, 1.0]], [[1.0, 1.1], [1.1, 1.0]]):  # checked in O(n^2)
        with pytest.raises(InputError, match="not a covariance"):
            Dense.repaired(np.array(bad))


def test_dense_clips_round_off_negative_eigenvalues(rng):
    n, rank = 12, 3
    B = rng.normal(size=(n, rank))
    P = B @ B.T  # positive semi-definite, rank 3: nine zero eigenvalues
    scale = np.linalg.eigvalsh(P).max()
    A = P - 1e-15 * scale * np.eye(n)  # the round-off seen on posterior covariances
    assert np.linalg.eigvalsh(A).min() < 0
    d = Dense(A)
    assert d.n_clipped > 0
    assert d.n_clipped <= n - rank
    assert -1e-13 * scale < d.min_eigenvalue < 0
    w = np.linalg.eigvalsh(d.cov)
    # reconstruction V max(w, 0) V^T leaves only eigenvalues of round-off size below zero
    assert w.min() >= -4 * np.finfo(float).eps * scale
    assert_allclose(d.cov, d.cov.T, rtol=0)
    assert_allclose(d.cov, P, rtol=0, atol=1e-13 * scale)  # clipping changes next to nothing
    # what matters downstream: the clipped covariance is a valid (Cholesky-able) noise
    np.linalg.cholesky(d.cov + 1e-12 * scale * np.eye(n))


@pytest.mark.parametrize(
    ("matrix", "pattern"),
    [
        (np.ones((2, 3)), r"expected a square \(n, n\) matrix, got shape \(2, 3\)"),
        (np.ones(4), r"expected a square \(n, n\) matrix, got shape \(4,\)"),
        (
            np.array([[1.0, 0.5], [0.0, 1.0]]),
            r"expected a symmetric matrix, got max \|C - C\^T\| = 0.5",
        ),
        (np.array([[1.0, np.nan], [np.nan, 1.0]]), "NaN or inf"),
        (np.array([[np.inf, 0.0], [0.0, 1.0]]), "NaN or inf"),
        (-np.eye(3), "expected a positive semi-definite covariance, got an eigenvalue of -1"),
        (np.array([[1.0, 2.0], [2.0, 1.0]]), "positive semi-definite.*got an eigenvalue of -1"),
    ],
)
def test_dense_refuses(matrix, pattern):
    with pytest.raises(InputError, match=pattern) as info:
        Dense(matrix)
    assert isinstance(info.value, CascalError)


def test_noise_sum(K, C):
    v = np.linspace(1e-5, 2e-5, N)
    s = Dense(C) + Diagonal(v)
    assert isinstance(s, NoiseSum) and not s.is_diagonal
    expected = C + np.diag(v)
    assert_allclose(s.dense(N), expected, rtol=1e-15)
    assert_allclose(s.diagonal(N), np.diagonal(expected), rtol=1e-15)
    assert_allclose(s.add_to(K), K + expected, rtol=1e-15)

    t = s + Diagonal(0.5)
    assert len(t.parts) == 3
    assert_allclose(t.dense(N), expected + 0.5 * np.eye(N), rtol=1e-15)

    dd = Diagonal(0.1) + Diagonal(v)
    assert dd.is_diagonal
    assert_allclose(dd.diagonal(N), 0.1 + v, rtol=1e-15)
    assert_allclose(dd.add_to(K), K + np.diag(0.1 + v), rtol=1e-15)
    assert_allclose(NoiseSum().dense(N), np.zeros((N, N)), rtol=0)


def test_frozen(C):
    with pytest.raises(dataclasses.FrozenInstanceError):
        Diagonal(0.1).variance = 0.2
    with pytest.raises(dataclasses.FrozenInstanceError):
        Dense(C).cov = C


def test_as_noise(C):
    assert as_noise(None, N) is None
    d = as_noise(0.25, N)
    assert isinstance(d, Diagonal)
    assert_allclose(d.dense(N), 0.25 * np.eye(N), rtol=0)
    v = np.linspace(1.0, 2.0, N)
    d = as_noise(v, N)
    assert isinstance(d, Diagonal)
    assert_allclose(d.diagonal(N), v, rtol=0)
    dense = as_noise(C, N)
    assert isinstance(dense, Dense)
    assert_allclose(dense.dense(N), C, rtol=1e-15)
    given = Dense(C)
    assert as_noise(given, N) is given
    assert isinstance(given, Noise)


@pytest.mark.parametrize(
    ("spec", "pattern"),
    [
        (np.ones(N - 1), rf"expected shape \({N},\), got \({N - 1},\)"),
        (np.eye(N + 1), rf"expected shape \({N}, {N}\), got \({N + 1}, {N + 1}\)"),
        (np.ones((N, N, 1)), rf"expected a number, shape \({N},\) or \({N}, {N}\), got shape"),
        (Diagonal(np.ones(N + 2)), rf"expected shape \({N},\), got \({N + 2},\)"),
    ],
)
def test_as_noise_shape_errors(spec, pattern):
    with pytest.raises(InputError, match=pattern):
        as_noise(spec, N)


@pytest.mark.parametrize("k", [2, N, N + 3])
def test_dense_from_factor(rng, k):
    U = rng.normal(size=(N, k)) * 1e-2
    d = Dense.from_factor(U)
    C = U @ U.T
    assert_allclose(d.dense(N), C, rtol=1e-14, atol=0)
    assert_allclose(d.dense(N), d.dense(N).T, rtol=0, atol=0)
    assert_allclose(d.diagonal(N), np.sum(U * U, axis=1), rtol=1e-14)
    assert d.n_clipped == 0 and not d.is_diagonal
    w = np.linalg.eigvalsh(C)
    if k < N:
        assert d.min_eigenvalue == 0.0
    else:
        assert d.min_eigenvalue == pytest.approx(w[0], rel=1e-8)
    # the factor: the eigen-directions within 1e-4 of the largest, as from the matrix
    F, G = d.factor(N), Dense(C).factor(N)
    assert F.shape == G.shape
    assert_allclose(F @ F.T, G @ G.T, rtol=0, atol=1e-12 * w[-1])
    given = Dense.from_factor(U, np.linalg.eigh(U.T @ U))  # the caller's eigenpairs
    assert np.array_equal(given.factor(N), F) and np.array_equal(given.dense(N), d.dense(N))
    assert given.min_eigenvalue == d.min_eigenvalue
    with pytest.raises(InputError, match="factor"):
        Dense.from_factor(np.ones(N))
    with pytest.raises(InputError, match="NaN"):
        Dense.from_factor(np.where(U > 0, np.nan, U))


def test_floor_bounds_the_smallest_eigenvalue(rng):
    """``floor`` is a lower bound of the covariance's smallest eigenvalue, 0 where it may
    be singular: it decides whether a factor needs the noiseless check."""
    n = 12
    A = rng.standard_normal((n, n))
    full = A @ A.T + 0.5 * np.eye(n)
    shared = 1e-10 * np.ones((n, n))  # rank 1
    v = rng.uniform(1.0, 2.0, n)
    assert Diagonal(v).floor(n) == v.min()
    assert Dense(full).floor(n) == pytest.approx(np.linalg.eigvalsh(full).min(), rel=1e-10)
    assert Dense(shared).floor(n) == 0.0
    assert Dense.from_factor(np.ones((n, 1))).floor(n) == 0.0
    total = Diagonal(v) + Dense(full)
    assert 0.0 < total.floor(n) <= np.linalg.eigvalsh(total.dense(n)).min()
    assert (Diagonal(0.0) + Dense(shared)).floor(n) == 0.0
