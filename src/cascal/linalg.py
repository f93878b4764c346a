"""Dense linear algebra for GP fits: Cholesky with escalating, recorded jitter."""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack

from .errors import NumericalError

__all__ = [
    "JITTER_STEPS",
    "cho_solve",
    "cholesky",
    "inverse_diagonal",
    "inverse_from_cholesky",
    "logdet",
    "pivots_ok",
]

#: Relative jitters tried after a plain Cholesky fails, times the mean diagonal.
JITTER_STEPS = (1e-12, 1e-11, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6)


def cholesky(
    A: np.ndarray, *, what: str = "covariance matrix", noiseless: bool = False
) -> tuple[np.ndarray, float]:
    """Lower Cholesky factor of a symmetric positive-definite matrix.

    When ``A`` is not numerically positive definite, ``jitter * I`` is added with a jitter
    escalating through :data:`JITTER_STEPS` times the mean diagonal.

    Args:
        A: Symmetric matrix, shape (n, n).
        what: Name of the matrix for the error message.
        noiseless: ``A`` has no noise on its diagonal (a kernel matrix alone): a factor
            with a pivot of round-off (:func:`pivots_ok`) then counts as failed too.

    Returns:
        ``(L, jitter)``: lower factor, shape (n, n), and the absolute jitter added (0.0 if none).

    Raises:
        NumericalError: No jitter up to 1e-6 of the mean diagonal made ``A`` factorisable.
    """
    L, info = lapack.dpotrf(A, lower=1, clean=1, overwrite_a=0)
    # OpenBLAS's dpotrf reports success (info == 0) on NaN input, leaving NaN in L.
    if info == 0 and np.all(np.isfinite(np.diagonal(L))) and (not noiseless or pivots_ok(L, A)):
        return L, 0.0
    if not np.all(np.isfinite(A)):
        raise NumericalError(f"{what} contains NaN or inf; check the inputs and hyperparameters")
    scale = float(np.mean(np.abs(np.diag(A)))) or 1.0
    for rel in JITTER_STEPS:
        jitter = rel * scale
        Aj = A + jitter * np.eye(len(A))
        L, info = lapack.dpotrf(Aj, lower=1, clean=1)
        if info == 0:
            return L, jitter
    raise NumericalError(
        f"{what} ({len(A)}x{len(A)}) is not positive definite even with a jitter of "
        f"{JITTER_STEPS[-1]:g} x its mean diagonal; remove duplicated positions, raise the "
        "lower bound of the noise variance, or shorten the length scale's upper bound"
    )


def pivots_ok(L: np.ndarray, A: np.ndarray) -> bool:
    """Whether ``dpotrf``'s factor ``L`` (n, n) of ``A`` (n, n) holds no pivot of round-off:
    every squared pivot above ``eps trace(A)`` (n eps times the mean variance, the size of
    the factorisation's own error), and none NaN. An exactly singular ``A`` (repeated
    positions and no noise) factorises "successfully" with pivots of about 1e-8 of the
    standard deviation, each of which would add 18 nats of round-off to the likelihood.
    Nor may its estimated reciprocal condition number (LAPACK ``dpocon``, O(n^2)) be
    below ``n eps``.
    For matrices with no noise on the diagonal only: with a noise, however small, the
    pivots are bounded below and a backward-stable factor's likelihood is that of a
    nearby matrix (a review found jitter there cost optima at the noise floor 40 to 540
    nats)."""
    d = float(L.diagonal().min())
    if not d * d > _EPS * float(A.trace()):
        return False
    # and a condition number the factor can carry: beyond 1 / (n eps) its solves are
    # round-off (a review: a smooth kernel at 30 points, condition 6.8e17, passed the
    # pivots with a likelihood 30 times off and no jitter recorded)
    rcond, info = lapack.dpocon(L, float(np.abs(A).sum(axis=0).max()), uplo="L")
    return info == 0 and rcond > len(A) * _EPS


_EPS = float(np.finfo(float).eps)


def cho_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``(L L^T) x = b`` for ``b`` of shape (n,) or (n, k)."""
    x, info = lapack.dpotrs(L, b, lower=1)
    if info != 0:  # pragma: no cover - dpotrs only fails on bad arguments
        raise NumericalError(f"dpotrs failed with info={info}")
    return x


def logdet(L: np.ndarray) -> float:
    """log |L L^T| from the Cholesky factor ``L`` (n, n)."""
    return 2.0 * float(np.log(L.diagonal()).sum())


def _triangular_inverse(L: np.ndarray) -> np.ndarray:
    Linv, info = lapack.dtrtri(L, lower=1)
    if info != 0:
        raise NumericalError(f"triangular inverse failed (info={info})")
    return Linv


def inverse_from_cholesky(L: np.ndarray) -> np.ndarray:
    """``(L L^T)^{-1}`` as a full symmetric matrix, shape (n, n)."""
    Linv = _triangular_inverse(L)
    return Linv.T @ Linv


def inverse_diagonal(L: np.ndarray) -> np.ndarray:
    """Diagonal of ``(L L^T)^{-1}``, shape (n,): the squared column norms of ``L^-1``, in
    O(n^3 / 3) without forming the inverse."""
    Linv = _triangular_inverse(L)
    return np.einsum("ij,ij->j", Linv, Linv)
