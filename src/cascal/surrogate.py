"""Start points for stage fits from a table of the profiled log marginal likelihood.

The profiled log marginal likelihood (kernel variance maximised out) at length scale ``l``
and noise ratio ``g`` is, up to a constant,
``-n/2 log(r^T (R + g I)^-1 r) - 1/2 log det(R + g I)`` with ``R`` the correlation matrix.
One decomposition of ``R`` per length scale gives a whole row over ``g``:

* On an equally spaced grid ``x_k = x_0 + k h``, ``R`` of a stationary kernel depends on
  ``l / h`` alone, so its eigenvectors ``Q`` and eigenvalues ``lam`` are computed once per
  kernel, size and ratio (in symmetric and antisymmetric halves), and cached; with
  ``z = Q^T r`` a row is
  ``-n/2 log(sum z^2 / (lam + g)) - 1/2 sum log(lam + g)``, one matrix-vector product.
  A known dense noise ``Sigma = U U^T`` (a low-rank factor) enters by the Woodbury
  identity, at the cost of one small m x m factorisation per table cell.
* Off the grid, each row costs a tridiagonal reduction of ``R`` whose first basis vector is
  ``r / |r|`` (:func:`_tridiagonal_table`): coarse rows over the length-scale bounds, then
  finer rows around the coarse table's best local maxima. Where ``R`` is numerically of
  low rank ``k`` (long length scales, above all for the squared exponential), a pivoted
  Cholesky factor makes the reduction O(n k^2) instead of O(n^3).

Real readings sit off the grid by their noise, so the grid table is a surrogate; the exact
off-grid table is coarse. Either way its best local maxima are where exact Newton runs
start, never results. The periodic kernel (its period fixed) has the off-grid table only:
its correlation depends on the period as well as on length scale / spacing. Composite
kernels get None: the caller screens random candidates instead.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.linalg import lapack

from .kernels import Kernel, Matern32, Matern52, Periodic, SquaredExp

__all__ = ["dense_starts", "grid_spacing", "profiled_starts"]

#: Length scale over grid spacing: the surrogate's rows (log-spaced).
RATIOS = np.exp(np.linspace(math.log(0.3), math.log(2e4), 100))
#: Noise over signal variance: the columns (log-spaced over the profiled bounds).
GAINS = np.exp(np.linspace(math.log(1e-10), math.log(10.0), 45))
#: Largest deviation from the equally spaced grid, in spacings, for the surrogate to apply.
TOLERANCE = 0.1
#: Local maxima this far (nats) below the best are not started from.
MARGIN = 3.0
#: Largest data set with a cached basis (100 eigenbases of n x n each, in halves).
MAX_POINTS = 160
#: Off the grid: coarse rows this far apart (log length scale), then rows this far apart
#: between the neighbours of the coarse table's best local maxima.
COARSE = 0.8
FINE = 0.2
#: The same for the periodic kernel, whose maxima in length scale are narrower (harmonics of
#: the turn compete): rows 0.8 apart missed one 1 to 3 nats above the rest in 160 readings.
_PERIODIC_ROWS = (0.4, 0.1)
#: Largest off-grid data set given a table (each row costs O(n^3)).
MAX_OFFGRID = 500
#: Off the grid: a row whose correlation matrix has a pivoted Cholesky factor of rank up to
#: this fraction of n, stopped where every remaining pivot is below PIVOT_TOL / n, is
#: reduced through the factor (O(n k^2)); other rows by a dense O(n^3) reduction.
LOWRANK = 0.5
PIVOT_TOL = 1e-13
#: Dense noise: length scales whose profiled row (known noise ignored) is within this many
#: nats of the best, longer than the best row's, and within _ROWS_SHORT nats, shorter. A
#: known noise only adds variance, which favours longer length scales: in 4000 simulated
#: bayes stage-B fits, every optimum whose row lay over 4 nats below the best row was on the
#: long side (up to 38; Newton runs climb there from the table's edge); in 1500 of them the
#: short side's largest gap was 1.3 nats.
_ROWS = 20.0
_ROWS_SHORT = 4.0
#: Dense noise: log offsets of the signal and noise variances around the row's profiled ones.
_SIGNAL = np.linspace(-3.0, 3.0, 7)
_NOISE = np.linspace(-4.0, 2.0, 7)
#: A cell's ``D / noise`` depends on its two offsets' difference alone: 13 distinct ones
#: (``_DIFF``, exact: both grids are integers) for the 49 cells (``_CELL`` indexes them).
_DIFF, _CELL = np.unique(np.subtract.outer(_SIGNAL, _NOISE).ravel(), return_inverse=True)
_KERNELS = (SquaredExp, Matern32, Matern52)
#: Kernels with an off-grid table: also the periodic one (its correlation depends on the
#: period too, so the grid's cached eigenbases do not serve it).
_OFFGRID_KERNELS = (*_KERNELS, Periodic)


@dataclass(frozen=True, slots=True)
class _Basis:
    """Eigenbases of the unit-spacing correlation at every ratio, in halves.

    That correlation is symmetric Toeplitz, so it commutes with reversal: its eigenvectors
    are symmetric or antisymmetric, and :func:`_fold` gives a vector's coordinates in the
    two subspaces. ``S`` (r, s, s) and ``A`` (r, a, a) stack the transposed eigenvectors
    there (``s + a = n``), ``lam`` (r, n) the eigenvalues (symmetric ones first, round-off
    negatives clipped), ``W`` (r, n, c) holds ``1 / (lam + g)`` and ``logdet`` (r, c)
    ``sum log(lam + g)``. Half the memory and flops of a full basis."""

    S: np.ndarray
    A: np.ndarray
    lam: np.ndarray
    W: np.ndarray
    logdet: np.ndarray

    def project(self, v: np.ndarray, rows: slice = slice(None)) -> np.ndarray:
        """``Q^T v`` at the ratios ``rows``: (r, n) for ``v`` (n,), (r, n, m) for (n, m)."""
        sym, anti = _fold(v)
        return np.concatenate([self.S[rows] @ sym, self.A[rows] @ anti], axis=1)


def _fold(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates of ``v`` (n, ...) in orthonormal bases of the symmetric (``(v_i +
    v_(n-1-i)) / sqrt 2`` for ``i < n // 2``, then the middle entry if n is odd) and the
    antisymmetric vectors (``(v_i - v_(n-1-i)) / sqrt 2``): shapes (n - n // 2, ...) and
    (n // 2, ...)."""
    n = v.shape[0]
    p = n // 2
    top, bottom = v[:p], v[::-1][:p]
    sym = (top + bottom) * math.sqrt(0.5)
    if n % 2:
        sym = np.concatenate([sym, v[p : p + 1]])
    return sym, (top - bottom) * math.sqrt(0.5)


@lru_cache(maxsize=4)
def _basis(kind: type, n: int) -> _Basis:
    u = np.arange(n, dtype=float)
    d = np.subtract.outer(u, u)
    Fs, Fa = _fold(np.eye(n))  # rows: the two orthonormal bases
    p = n // 2
    S = np.empty((RATIOS.size, n - p, n - p))
    A = np.empty((RATIOS.size, p, p))
    lam = np.empty((RATIOS.size, n))
    for i, ratio in enumerate(RATIOS):
        rho, _ = kind(float(ratio), 1.0).correlation(d, False)
        for F, out, part in ((Fs, S, slice(0, n - p)), (Fa, A, slice(n - p, n))):
            block = F @ rho @ F.T
            w, V = np.linalg.eigh(0.5 * (block + block.T))
            lam[i, part], out[i] = np.clip(w, 0.0, None), V.T
    shifted = lam[:, :, None] + GAINS
    return _Basis(S, A, lam, 1.0 / shifted, np.log(shifted).sum(axis=1))


def grid_spacing(x: np.ndarray) -> float | None:
    """Spacing ``h`` of readings (n,) that lie within a tenth of it of an equally spaced
    grid (in any order), else None."""
    n = x.size
    if n < 3 or n > MAX_POINTS:
        return None
    xs = np.sort(x)
    h = float(xs[-1] - xs[0]) / (n - 1)
    if not h > 0.0:
        return None
    dev = float(np.max(np.abs(xs - (xs[0] + h * np.arange(n)))))
    return h if dev <= TOLERANCE * h else None


@dataclass(frozen=True, slots=True)
class _Scan:
    order: np.ndarray  # sorting permutation of the readings
    h: float
    basis: _Basis
    z: np.ndarray  # (r, n): Q^T r at every ratio
    quad: np.ndarray  # (r, c): sum z^2 / (lam + g)
    table: np.ndarray  # (r, c): profiled log marginal likelihood up to a constant


#: The last scan, by its inputs: the homoscedastic and the bayes fit of a stage (same
#: readings, same targets) share it.
_LAST_SCAN: dict[tuple, _Scan | None] = {}
_MISSING = object()


def _scan(kernel: Kernel, x: np.ndarray, r: np.ndarray, log_ls: np.ndarray) -> _Scan | None:
    if type(kernel) not in _KERNELS:
        return None
    key = (type(kernel), x.tobytes(), r.tobytes(), np.asarray(log_ls, float).tobytes())
    scan = _LAST_SCAN.get(key, _MISSING)
    if scan is _MISSING:  # (threads at worst compute a scan twice)
        scan = _new_scan(kernel, x, r, log_ls)
        _LAST_SCAN.clear()
        _LAST_SCAN[key] = scan
    return scan


def _new_scan(kernel: Kernel, x: np.ndarray, r: np.ndarray, log_ls: np.ndarray) -> _Scan | None:
    h = grid_spacing(x)
    if h is None:
        return None
    n = x.size
    order = np.argsort(x, kind="stable")
    basis = _basis(type(kernel), n)
    z = basis.project(r[order])
    quad = np.matmul((z * z)[:, None, :], basis.W)[:, 0, :]
    with np.errstate(divide="ignore"):
        table = -0.5 * n * np.log(quad) - 0.5 * basis.logdet
    ll = np.log(RATIOS * h)
    table[(ll < log_ls[0]) | (ll > log_ls[1])] = -np.inf
    for a in (order, z, quad, table):
        a.flags.writeable = False  # shared by later fits of the same data
    return _Scan(order, h, basis, z, quad, table)


def _local_maxima(table: np.ndarray, k: int) -> list[tuple[int, ...]]:
    """Indices of the ``k`` best local maxima of ``table`` (any dimension, neighbours
    including diagonals) within :data:`MARGIN` of the best."""
    peak = np.isfinite(table) & (table >= _neighbourhood_max(table))
    idx = np.argwhere(peak)
    if not idx.size:
        return []
    vals = table[tuple(idx.T)]
    best = np.argsort(-vals, kind="stable")[:k]
    return [tuple(idx[i]) for i in best if vals[i] >= vals[best[0]] - MARGIN]


def _neighbourhood_max(table: np.ndarray) -> np.ndarray:
    """Largest entry of ``table`` within one step along every axis (diagonals included),
    as ``scipy.ndimage.maximum_filter(size=3)`` with -inf outside; one pass per axis
    (the maximum over a box is separable)."""
    out = table
    for axis in range(table.ndim):
        head = (slice(None),) * axis + (slice(None, -1),)
        tail = (slice(None),) * axis + (slice(1, None),)
        box = out.copy()
        np.maximum(box[tail], out[head], out=box[tail])
        np.maximum(box[head], out[tail], out=box[head])
        out = box
    return out


def profiled_starts(
    kernel: Kernel, x: np.ndarray, r: np.ndarray, bounds: np.ndarray, k: int
) -> list[np.ndarray] | None:
    """Up to ``k`` starts ``[log length_scale, log(noise / variance)]`` for the profiled
    objective of residuals ``r`` (n,) at readings ``x`` (n,); None where no surrogate applies.

    Args:
        bounds: Log bounds of the profiled parameters, shape (2, 2).
    """
    scan = _scan(kernel, x, r, bounds[0])
    if scan is not None:
        ll, table = np.log(RATIOS * scan.h), scan.table
    elif type(kernel) in _OFFGRID_KERNELS and 3 <= x.size <= MAX_OFFGRID:
        ll, table = _offgrid_table(kernel, x, r, bounds[0], k)
    else:
        return None
    return [np.array([ll[i], math.log(GAINS[j])]) for i, j in _local_maxima(table, k)]


def _offgrid_table(
    kernel: Kernel, x: np.ndarray, r: np.ndarray, log_ls: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``(log length scales (s,), table (s, c))``, sorted: :data:`COARSE` apart over
    ``log_ls`` (2,), plus rows :data:`FINE` apart out to the neighbours of each of the
    coarse table's ``k`` best local maxima (:data:`_PERIODIC_ROWS` for the periodic kernel)."""
    lo, hi = float(log_ls[0]), float(log_ls[1])
    coarse, fine_step = (COARSE, FINE) if type(kernel) in _KERNELS else _PERIODIC_ROWS
    ll = np.linspace(lo, hi, math.ceil((hi - lo) / coarse) + 1)
    d = np.subtract.outer(x, x)
    table = _tridiagonal_table(kernel, d, r, ll)
    if ll.size > 1:
        offsets = np.arange(fine_step, ll[1] - ll[0] - 0.5 * fine_step, fine_step)
        fine = np.unique(
            [ll[i] + s * o for i, _ in _local_maxima(table, k) for s in (-1, 1) for o in offsets]
        )
        fine = fine[(fine > lo) & (fine < hi)]
        if fine.size:
            ll = np.concatenate([ll, fine])
            table = np.concatenate([table, _tridiagonal_table(kernel, d, r, fine)])
            order = np.argsort(ll, kind="stable")
            ll, table = ll[order], table[order]
    return ll, table


def _tridiagonal_table(
    kernel: Kernel, d: np.ndarray, r: np.ndarray, log_ls: np.ndarray
) -> np.ndarray:
    """Profiled log marginal likelihood of ``kernel`` (its period, if periodic, kept), up to
    a constant, at length scales ``exp(log_ls)`` (s,) and noise ratios :data:`GAINS` (c,)
    for readings in any position, given by their differences ``d`` (n, n): shape (s, c),
    -inf where not positive definite.

    A tridiagonal ``T`` with ``R = V T V^T`` and ``V``'s first column ``r / |r|`` gives a
    row: with the pivots of the backward recurrence ``p_(m-1) = t_(m-1) + g``,
    ``p_i = t_i + g - e_i^2 / p_(i+1)`` (``t`` the diagonal of ``T``, ``e`` its
    off-diagonal), ``r^T (R + g I)^-1 r = |r|^2 / p_0`` and ``det(R + g I) = prod p_i``
    times ``g`` for each of the ``n - m`` directions in which ``R`` vanishes. So a row costs
    one reduction (:func:`_lowrank_reduction` or :func:`_full_reduction`) and O(n) per
    cell, vectorised over the table.
    """
    n, s = r.size, log_ls.size
    bordered = np.zeros((n + 1, n + 1))
    reductions: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    lowrank = True  # rows from the longest length scale down, while R stays of low rank
    for i in np.argsort(-log_ls, kind="stable").tolist():
        length_scale = math.exp(float(log_ls[i]))
        red = None
        if lowrank:
            red = _lowrank_reduction(_correlation(kernel, d, length_scale), r)
            lowrank = red is not None
        if red is None:
            bordered[0, 1:] = r  # the reduction overwrites it
            bordered[1:, 1:] = _correlation(kernel, d, length_scale)
            red = _full_reduction(bordered)
        reductions[i] = red
    m = -(-max(t.size for t, _ in reductions.values()) // 8) * 8  # rows of 8 for _sum_log
    diag = np.zeros((m, s))
    off2 = np.zeros((m, s, 1))
    for i, (t, e) in reductions.items():
        diag[: t.size, i] = t
        off2[: e.size, i, 0] = np.square(e)
    pivots = diag[:, :, None] + GAINS  # (m, s, c), overwritten by the recurrence
    ratio = np.empty((s, GAINS.size))
    for i in range(m - 2, -1, -1):
        np.divide(off2[i], pivots[i + 1], out=ratio)
        pivots[i] -= ratio
    with np.errstate(divide="ignore", invalid="ignore"):
        logdet = _sum_log(pivots, axis=0) + (n - m) * np.log(GAINS)  # pivots in [1e-10, n]
        table = -0.5 * n * np.log(float(r @ r) / pivots[0]) - 0.5 * logdet
    table[~np.isfinite(table) | np.any(pivots <= 0.0, axis=0)] = -np.inf
    return table


def _full_reduction(bordered: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(t (n,), e (n - 1,))`` of ``R``'s tridiagonal form from LAPACK's reduction of the
    bordered matrix ``[[0, r^T], [r, R]]`` (n + 1, n + 1; its upper triangle is read and
    overwritten), which keeps the first coordinate. O(n^3); a workspace of 8 columns is the
    fastest blocking here (n from 65 to 500)."""
    m = bordered.shape[0]
    _, t, e, _, _ = lapack.dsytrd(bordered.T, lower=1, lwork=8 * m, overwrite_a=1)
    return t[1:], e[1:]


def _lowrank_reduction(R: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(t (k + 1,), e (k,))`` of ``R``'s tridiagonal form when a pivoted Cholesky factor
    ``R = L L^T + E`` (L (n, k)) stops at rank ``k <= LOWRANK n``, else None. O(n k^2).

    The factor stops where every remaining pivot is below ``PIVOT_TOL / n``, so the dropped
    part ``E`` is positive semi-definite with trace below :data:`PIVOT_TOL`: it changes a
    cell by at most ``(n + 1) / 2 * PIVOT_TOL / g``, the size of the dense reduction's own
    round-off (R's eigenvalues are known to about ``n eps``). With ``L = Q S`` (``Q``
    orthonormal), ``c = Q^T r`` and ``rho = |r - Q c|``, ``R`` and ``r`` in the basis
    ``[Q, (r - Q c) / rho]`` are ``diag(S S^T, 0)`` and ``[c, rho]``: a bordered matrix of
    size k + 2 to reduce.
    """
    n = r.size
    c, piv, k, _ = lapack.dpstrf(R.T, lower=0, tol=PIVOT_TOL / n, overwrite_a=1)
    if k > LOWRANK * n:
        return None
    L = c.T[:, :k]  # rows in pivot order; clear the upper triangle dpstrf leaves as it was
    L[_strict_upper(k)] = 0.0
    qr, tau, _, _ = lapack.dgeqrf(L, overwrite_a=1)
    cq = lapack.dormqr("L", "T", qr, tau, r[piv - 1][:, None], 1)[0][:, 0]
    small = np.zeros((k + 2, k + 2))
    small[1:-1, 1:-1] = lapack.dlauum(qr[:k], lower=0)[0].T  # S S^T, lower triangle
    small[1:-1, 0] = cq[:k]
    small[-1, 0] = math.sqrt(float(cq[k:] @ cq[k:]))
    _, t, e, _, _ = lapack.dsytrd(small, lower=1)
    return t[1:], e[1:]


@lru_cache(maxsize=256)
def _strict_upper(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the strict upper triangle of a k x k matrix (cached)."""
    return np.triu_indices(k, 1)


@lru_cache(maxsize=64)
def _lower(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the lower triangle of a k x k matrix, diagonal included (cached)."""
    return np.tril_indices(k)


def _correlation(kernel: Kernel, d: np.ndarray, length_scale: float) -> np.ndarray:
    """Correlation matrix (n, n) at differences ``d`` (n, n), a new array."""
    return kernel.unit(length_scale).correlation(d, False)[0]  # type: ignore[attr-defined]


def _sum_log(a: np.ndarray, axis: int) -> np.ndarray:
    """``log(a).sum(axis)`` with 8 times fewer logarithms: the logs of products of 8.
    For entries between about 1e-30 and 1e30, so that no product over- or underflows."""
    axis %= a.ndim
    k = a.shape[axis]
    head = k - k % 8
    before = (slice(None),) * axis
    groups = a[(*before, slice(0, head))].reshape(*a.shape[:axis], -1, 8, *a.shape[axis + 1 :])
    out = np.log(groups.prod(axis=axis + 1)).sum(axis=axis)
    if head < k:
        out += np.log(a[(*before, slice(head, k))].prod(axis=axis))
    return out


def dense_starts(
    kernel: Kernel,
    x: np.ndarray,
    r: np.ndarray,
    factor: np.ndarray,
    bounds: np.ndarray,
    k: int,
) -> list[np.ndarray] | None:
    """Up to ``k`` starts ``[log length_scale, log variance, log noise_variance]`` for the
    objective with known noise ``factor @ factor.T`` (factor (n, m)) plus a learned white
    noise; None where no surrogate applies.

    The table spans the length scales whose profiled row (known noise ignored) comes within
    20 nats of the best (4 on the side of shorter length scales), and around each row's
    profiled variances 7 x 7 offsets.

    Args:
        bounds: Log bounds of the three parameters, shape (3, 2).
    """
    scan = _scan(kernel, x, r, bounds[0])
    if scan is None:
        return None
    dense = _dense_table(scan, factor)
    if dense is None:
        return []
    table, ll, signal, noise = dense
    return [np.array([ll[a], signal[a, b], noise[a, c]]) for a, b, c in _local_maxima(table, k)]


def _dense_table(scan: _Scan, factor: np.ndarray) -> tuple[np.ndarray, ...] | None:
    """Log marginal likelihood (up to a constant) on the grid with the known noise
    ``Sigma = U U^T`` (``U = factor``, (n, m)) by the Woodbury identity in the eigenbasis:
    ``K = Q D Q^T + U U^T`` with ``D = variance lam + noise``, ``C = I + U~^T D^-1 U~``,
    ``U~ = Q^T U``. Returns ``(table (s, 7, 7), log length scales (s,), log variances
    (s, 7), log noise variances (s, 7))``; None if no row is finite or round-off breaks a
    cell's factorisation (then the caller screens)."""
    n = scan.z.shape[1]
    col = np.argmax(scan.table, axis=1)
    prof = scan.table[np.arange(RATIOS.size), col]
    if not np.any(np.isfinite(prof)):
        return None
    best = int(np.argmax(prof))
    near_short = np.flatnonzero(prof[: best + 1] >= prof[best] - _ROWS_SHORT)
    near_long = np.flatnonzero(prof[best:] >= prof[best] - _ROWS)
    sel = slice(int(near_short[0]), best + int(near_long[-1]) + 1)  # a view, no copy
    rows = np.arange(RATIOS.size)[sel]
    Ut = scan.basis.project(factor[scan.order], sel)  # (s, n, m)
    s, m = Ut.shape[0], Ut.shape[2]
    log_sf = np.log(scan.quad[rows, col[rows]] / n)
    log_g = np.log(GAINS[col[rows]])
    signal = log_sf[:, None] + _SIGNAL
    noise = (log_sf + log_g)[:, None] + _NOISE
    # D = variance lam + noise = noise E with E = 1 + exp(signal - noise) lam: E (s, u, n)
    # per distinct offset difference u; a cell's D^-1 is E^-1 / noise, its log det D
    # n log noise + sum log E.
    E = np.exp(_DIFF[None, :] - log_g[:, None])[:, :, None] * scan.basis.lam[sel][:, None, :]
    E += 1.0
    cell_noise = np.tile(noise, _SIGNAL.size)  # (s, cells): signal offsets major, as _CELL
    # [U~, z]^T D^-1 [U~, z] holds C - I, w = U~^T D^-1 z and z^T D^-1 z; its Cholesky
    # factor (with I added to C) ends in sqrt(z^T D^-1 z - w^T C^-1 w) = sqrt(r^T K^-1 r)
    Uz = np.concatenate([Ut, scan.z[sel][:, :, None]], axis=2)  # (s, n, m + 1)
    lo, hi = _lower(m + 1)  # NumPy's Cholesky reads the lower triangle only
    G = np.reciprocal(E) @ (Uz[:, :, lo] * Uz[:, :, hi])  # (s, u, pairs)
    A = np.zeros((s, _CELL.size, m + 1, m + 1))
    A[..., lo, hi] = G[:, _CELL] * np.exp(-cell_noise)[:, :, None]
    A[..., np.arange(m), np.arange(m)] += 1.0
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:  # r^T K^-1 r lost to round-off in some cell
        return None
    piv = np.diagonal(L, axis1=-2, axis2=-1)
    logdet = n * cell_noise + _sum_log(E, axis=-1)[:, _CELL] + 2.0 * np.log(piv[..., :m]).sum(-1)
    table = -0.5 * np.square(piv[..., m]) - 0.5 * logdet
    table = table.reshape(s, _SIGNAL.size, _NOISE.size)
    table[~np.isfinite(prof[sel])] = -np.inf
    return table, np.log(RATIOS * scan.h)[sel], signal, noise
