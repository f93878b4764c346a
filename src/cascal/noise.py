"""Known target-noise models: per-point variances, a dense covariance, and their sum.

A learned white-noise variance is a hyperparameter of the GP, not a noise object; these
types hold what is known before the fit (stage B of the cascade gets ``Dense(Sigma)``).
Every type offers ``diagonal(n)`` and ``dense(n)``, and is tested against its dense matrix.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .validation import frozen

__all__ = ["Dense", "Diagonal", "Noise", "NoiseSum", "as_noise"]


class Noise:
    """Base class of known noise covariances."""

    #: True when the covariance is diagonal (no correlations between points).
    is_diagonal: bool = True

    def diagonal(self, n: int) -> np.ndarray:
        """Variances of the n targets, shape (n,), in the target unit squared."""
        raise NotImplementedError

    def dense(self, n: int) -> np.ndarray:
        """Full covariance, shape (n, n), in the target unit squared."""
        raise NotImplementedError

    def factor(self, n: int) -> np.ndarray:
        """Low-rank ``U`` (n, m) with ``U @ U.T`` the covariance up to eigenvalues below
        1e-4 of the largest (at most 16 columns): for cheap start-point surrogates."""
        w, V = np.linalg.eigh(self.dense(n))
        return _low_rank(w, V)

    def floor(self, n: int) -> float:
        """A lower bound of the covariance's smallest eigenvalue (target unit squared): 0
        where it may be singular. A factorisation of a kernel matrix plus this noise has
        every squared pivot above it."""
        return float(np.min(self.diagonal(n), initial=np.inf)) if self.is_diagonal else 0.0

    def add_to(self, K: np.ndarray) -> np.ndarray:
        """``K + covariance`` as a new array, K of shape (n, n)."""
        n = len(K)
        if self.is_diagonal:
            out = K.copy()
            out.flat[:: n + 1] += self.diagonal(n)
            return out
        return K + self.dense(n)

    def __add__(self, other: Noise) -> NoiseSum:
        return NoiseSum((self, other))


@dataclass(frozen=True, slots=True)
class Diagonal(Noise):
    """Independent noise: one variance for all points (float) or one per point, shape (n,)."""

    variance: float | np.ndarray = 0.0

    def __post_init__(self) -> None:
        try:
            v = np.asarray(self.variance, dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"noise variance: expected numbers, got {self.variance!r}") from None
        if v.ndim > 1:
            raise InputError(f"noise variance: expected a number or shape (n,), got {v.shape}")
        if not np.all(np.isfinite(v)) or np.any(v < 0):
            raise InputError("noise variance: expected finite values >= 0")
        object.__setattr__(self, "variance", float(v) if v.ndim == 0 else frozen(v))

    def diagonal(self, n: int) -> np.ndarray:
        v = np.asarray(self.variance, dtype=float)
        if v.ndim == 1 and v.shape != (n,):
            raise InputError(f"noise variance: expected shape ({n},), got {v.shape}")
        return np.broadcast_to(v, (n,)).copy()

    def dense(self, n: int) -> np.ndarray:
        return np.diag(self.diagonal(n))


@dataclass(frozen=True, slots=True)
class Dense(Noise):
    """Correlated noise with a known covariance, shape (n, n).

    The matrix is symmetrised and round-off negative eigenvalues are clipped to zero
    (posterior covariances of an earlier stage have them at about -1e-15). What was repaired
    is recorded in ``n_clipped`` and ``min_eigenvalue``. An eigenvalue more negative than
    ``tol`` times the largest is not round-off, and is refused.

    Args:
        cov: Covariance, shape (n, n), target unit squared.
        tol: Size of negative eigenvalues accepted as round-off, relative to the largest.
        atol: Absolute size accepted as round-off; a posterior covariance ``K** - V^T V``
            carries round-off of order eps times the prior variance, whatever its own size.
    """

    cov: np.ndarray
    tol: float = 1e-8
    atol: float = 0.0
    n_clipped: int = field(default=0, init=False)
    min_eigenvalue: float = field(default=0.0, init=False)
    _factor: np.ndarray = field(default=None, init=False, repr=False, compare=False)  # type: ignore[assignment]
    is_diagonal = False  # type: ignore[misc]

    def __post_init__(self) -> None:
        try:
            C = np.array(self.cov, dtype=float)
        except (TypeError, ValueError):  # (a review: NumPy's own error for a ragged matrix)
            raise InputError(
                "dense noise: expected a square (n, n) matrix of numbers, got "
                f"{type(self.cov).__name__}"
            ) from None
        if C.ndim != 2 or C.shape[0] != C.shape[1]:
            raise InputError(f"dense noise: expected a square (n, n) matrix, got shape {C.shape}")
        if not np.all(np.isfinite(C)):
            raise InputError("dense noise: the covariance contains NaN or inf")
        scale = float(np.max(np.abs(C))) if C.size else 0.0
        asym = float(np.max(np.abs(C - C.T))) if C.size else 0.0
        if asym > 1e-8 * max(scale, np.finfo(float).tiny):
            raise InputError(
                f"dense noise: expected a symmetric matrix, got max |C - C^T| = {asym:.3g} "
                f"(largest entry {scale:.3g})"
            )
        C = 0.5 * (C + C.T)
        w, V = np.linalg.eigh(C) if C.size else (np.zeros(0), C)
        wmin = float(w.min()) if w.size else 0.0
        if wmin < -max(self.tol * float(w.max()), self.atol, np.finfo(float).tiny):
            raise InputError(
                f"dense noise: expected a positive semi-definite covariance, got an eigenvalue "
                f"of {wmin:.3g} against a largest of {float(w.max()):.3g}; a posterior "
                "covariance k(x, x) - V^T V carries round-off of about eps times the prior "
                "variance: give its factor (FittedGP.posterior_factor, Dense.from_factor) "
                "or an atol of that size"
            )
        neg = w < 0
        if np.any(neg):
            C = (V * np.where(neg, 0.0, w)) @ V.T
            C = 0.5 * (C + C.T)
        C.flags.writeable = False  # its own copy, read-only as a fit's arrays (a review)
        object.__setattr__(self, "cov", C)
        object.__setattr__(self, "_factor", _low_rank(np.where(neg, 0.0, w), V))
        object.__setattr__(self, "n_clipped", int(np.count_nonzero(neg)))
        object.__setattr__(self, "min_eigenvalue", wmin)

    @classmethod
    def from_factor(
        cls, factor: np.ndarray, eigh: tuple[np.ndarray, np.ndarray] | None = None
    ) -> Dense:
        """The covariance ``U U^T`` of a factor ``U`` (n, k), positive semi-definite by
        construction: nothing is clipped, and :meth:`factor` comes from ``U`` in O(n k^2)
        instead of an eigendecomposition of the (n, n) matrix. ``eigh``: the eigenpairs
        ``np.linalg.eigh(U.T @ U)`` where the caller has them already."""
        U = np.array(factor, dtype=float)
        if U.ndim != 2:
            raise InputError(f"dense noise: expected a factor of shape (n, k), got {U.shape}")
        if not np.all(np.isfinite(U)):
            raise InputError("dense noise: the factor contains NaN or inf")
        C = U @ U.T
        C = 0.5 * (C + C.T)
        w, V = eigh if eigh is not None else np.linalg.eigh(U.T @ U)
        w = np.clip(w, 0.0, None)  # U V_i / sqrt(w_i): eigenvectors of U U^T
        out = object.__new__(cls)
        fields = cls.__dataclass_fields__  # tol and atol keep their defaults: no repair here
        for name in ("tol", "atol"):
            object.__setattr__(out, name, fields[name].default)
        C.flags.writeable = False
        object.__setattr__(out, "cov", C)
        object.__setattr__(out, "n_clipped", 0)
        extra = U.shape[1] - len(U)  # U^T U has this many more (zero) eigenvalues
        object.__setattr__(out, "min_eigenvalue", float(w[extra]) if extra >= 0 else 0.0)
        object.__setattr__(out, "_factor", _low_rank(w, U @ V, scaled=True))
        return out

    @classmethod
    def repaired(cls, cov: np.ndarray, tol: float = 1e-8, atol: float = 0.0) -> Dense:
        """A covariance a Dense held already (read back from a checksummed model file):
        symmetric and repaired, so it is taken as it is and its eigendecomposition waits for
        the first :meth:`factor` (0.75 s at 2000 readings, which predicting never needs).
        Checked in O(n^2) only: finite, square, no negative variance and no covariance
        above the geometric mean of its two variances, beyond round-off of 1e-8 of the
        largest variance (a Dense keeps a diagonal's round-off below zero where no
        eigenvalue needs clipping)."""
        C = np.array(cov, dtype=float)
        if C.ndim != 2 or C.shape[0] != C.shape[1] or not np.all(np.isfinite(C)):
            raise InputError(f"dense noise: expected a finite square matrix, got shape {C.shape}")
        v = np.diagonal(C)
        eps = 1e-8 * float(v.max()) if v.size else 0.0
        root = np.sqrt(np.clip(v, 0.0, None))
        if v.size and (v.min() < -eps or np.any(np.abs(C) > np.outer(root, root) + eps)):
            raise InputError(
                "dense noise: not a covariance (a negative variance, or a covariance larger "
                "than its variances allow)"
            )
        out = object.__new__(cls)
        C.flags.writeable = False  # (np.array made it a copy)
        fields = {"cov": C, "tol": tol, "atol": atol, "n_clipped": 0, "min_eigenvalue": 0.0}
        for name, value in (*fields.items(), ("_factor", None)):
            object.__setattr__(out, name, value)
        return out

    def floor(self, n: int) -> float:
        """The smallest eigenvalue found when the covariance was checked (0 where none
        was, as for a model file's, or where it is within round-off, n eps times the
        trace, of 0: a shared offset's rank-1 covariance)."""
        self._check(n)
        small = n * np.finfo(float).eps * float(np.trace(self.cov))
        return self.min_eigenvalue if self.min_eigenvalue > small else 0.0

    def _check(self, n: int) -> None:
        if self.cov.shape != (n, n):
            raise InputError(f"dense noise: expected shape ({n}, {n}), got {self.cov.shape}")

    def diagonal(self, n: int) -> np.ndarray:
        self._check(n)
        return np.diagonal(self.cov).copy()

    def factor(self, n: int) -> np.ndarray:
        self._check(n)
        if self._factor is None:  # (see :meth:`repaired`)
            w, V = np.linalg.eigh(self.cov)
            object.__setattr__(self, "_factor", _low_rank(np.clip(w, 0.0, None), V))
        return self._factor

    def dense(self, n: int) -> np.ndarray:
        self._check(n)
        return self.cov


@dataclass(frozen=True, slots=True)
class NoiseSum(Noise):
    """Sum of independent noise sources."""

    parts: tuple[Noise, ...] = ()

    def __post_init__(self) -> None:
        odd = [p for p in self.parts if not isinstance(p, Noise)]
        if odd:  # (a review: Diagonal(1.0) + 1.0 failed later, in the fit)
            raise InputError(
                f"noise: a sum of noise objects (Diagonal, Dense), got {type(odd[0]).__name__} "
                f"{odd[0]!r} in it; a number is Diagonal(number)"
            )

    @property
    def is_diagonal(self) -> bool:  # type: ignore[override]
        return all(p.is_diagonal for p in self.parts)

    def diagonal(self, n: int) -> np.ndarray:
        return np.sum([p.diagonal(n) for p in self.parts], axis=0) if self.parts else np.zeros(n)

    def floor(self, n: int) -> float:
        """The sum of its parts' floors (Weyl's inequality)."""
        return float(sum(p.floor(n) for p in self.parts))

    def dense(self, n: int) -> np.ndarray:
        out = np.zeros((n, n))
        for p in self.parts:
            out = p.add_to(out)
        return out

    def __add__(self, other: Noise) -> NoiseSum:
        return NoiseSum((*self.parts, other))


def _low_rank(
    w: np.ndarray, V: np.ndarray, rel: float = 1e-4, rank: int = 16, scaled: bool = False
) -> np.ndarray:
    """Columns ``sqrt(w_i) v_i`` of the eigenpairs (ascending ``w``) within ``rel`` of the
    largest, at most ``rank`` of them; shape (n, m). ``scaled``: V's columns are already
    ``sqrt(w_i) v_i``."""
    if not w.size or not w[-1] > 0.0:
        return np.zeros((len(V), 0))
    m = min(int(np.count_nonzero(w >= rel * w[-1])), rank)
    top = V[:, w.size - m :]
    return top if scaled else top * np.sqrt(w[w.size - m :])


def as_noise(spec: float | np.ndarray | Noise | None, n: int) -> Noise | None:
    """Known noise from a number, an (n,) vector, an (n, n) matrix or a Noise; None stays None."""
    if spec is None or isinstance(spec, Noise):
        if isinstance(spec, Noise):
            spec.diagonal(n)  # validates the size
        return spec
    try:
        a = np.asarray(spec, dtype=float)
    except (TypeError, ValueError):
        raise InputError(
            f"noise: expected a number, shape ({n},) or ({n}, {n}), or a Noise, got {spec!r:.60}"
        ) from None
    if a.ndim == 0 or a.ndim == 1:
        noise = Diagonal(a)
        noise.diagonal(n)
        return noise
    if a.ndim == 2:
        noise = Dense(a)
        noise.dense(n)
        return noise
    raise InputError(f"noise: expected a number, shape ({n},) or ({n}, {n}), got shape {a.shape}")
