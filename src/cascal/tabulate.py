"""Fast prediction of many readings: a verified interpolation table of a fitted GP.

Correcting 10^6 readings exactly costs one kernel row per reading (and a triangular solve
for the uncertainty). A :class:`PredictionTable` instead evaluates the GP exactly on a
uniform grid, and interpolates the correction ``mean(x) - m(x)`` and the variance with
4-point (cubic) Lagrange polynomials. The grid is refined by halving its spacing until the
interpolation error, measured against the exact GP at the midpoints of every interval, is
at most ``rtol`` times the smallest posterior standard deviation on the grid; the table is
then built on the refined grid (node set plus midpoints), so the recorded error bound is
that of the coarser grid, about 16 times larger than the table's own error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gp import FittedGP
from .kernels import Periodic
from .means import Mean
from .validation import as_positions

__all__ = ["PredictionTable", "chebyshev_mean", "predict_many", "tabulate"]

#: Below this many readings, exact prediction is cheaper than building a table.
MIN_READINGS_FOR_TABLE = 20000
_START_INTERVALS = 256
_MAX_NODES = 2**17 + 1
#: Degrees of the Chebyshev interpolants tried by :func:`chebyshev_mean`, in turn.
_CHEB_DEGREES = (32, 64, 128)
#: Exact check points of a Chebyshev interpolant (spread over the readings).
_CHEB_CHECKS = 33


@dataclass(frozen=True, slots=True)
class PredictionTable:
    """Posterior mean and standard deviation of a GP on ``[lo, lo + step * (n - 1)]``.

    Attributes:
        lo: First grid node, in the reading unit.
        step: Grid spacing, in the reading unit.
        correction: ``mean(node) - m(node)`` at the nodes, shape (n,), target unit.
        variance: Posterior variance at the nodes, shape (n,), target unit squared.
        mean: The GP's prior mean m, added back exactly.
        period: Period of a periodic GP (readings are reduced onto one period), or None.
        error_mean: Largest interpolation error of the mean found at the check points.
        error_std: Largest interpolation error of the standard deviation found there.
    """

    lo: float
    step: float
    correction: np.ndarray
    variance: np.ndarray
    mean: Mean
    period: float | None
    error_mean: float
    error_std: float

    @property
    def hi(self) -> float:
        """Last grid node."""
        return self.lo + self.step * (self.correction.size - 1)

    def __call__(
        self, x: object, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Interpolated posterior mean at readings ``x`` (m,) inside the table (or any
        reading for a periodic GP), and with ``return_std`` the standard deviation (m,)."""
        xs = as_positions(x, "x")
        u = xs
        if self.period is not None:
            u = self.lo + np.mod(xs - self.lo, self.period)
        j, w = _stencil(u, self.lo, self.step, self.correction.size)
        mean = self.mean(xs) + _apply(self.correction, j, w)
        if not return_std:
            return mean
        var = _apply(self.variance, j, w)
        return mean, np.sqrt(np.clip(var, 0.0, None))


def tabulate(
    gp: FittedGP, lo: float, hi: float, *, rtol: float = 1e-6, max_nodes: int = _MAX_NODES
) -> PredictionTable | None:
    """Tabulate ``gp`` on ``[lo, hi]`` (on one period for a periodic GP), or None if the
    interpolation error does not fall below ``rtol`` times the smallest standard deviation
    with at most ``max_nodes`` nodes (then predict exactly).

    Args:
        gp: The fitted GP.
        lo, hi: Range of readings to cover, in the reading unit, ``lo < hi``.
        rtol: Allowed interpolation error, relative to the smallest posterior standard
            deviation on the grid (for the mean and for the standard deviation).
        max_nodes: Largest grid tried.
    """
    period = gp.kernel.period if isinstance(gp.kernel, Periodic) else None
    if period is not None:
        lo, hi = 0.0, float(period)
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise ValueError(f"tabulate: expected finite lo < hi, got {lo!r}, {hi!r}")
    nodes = np.linspace(lo, hi, _START_INTERVALS + 1)
    c, v = _exact(gp, nodes)
    while True:
        mids = 0.5 * (nodes[:-1] + nodes[1:])
        cm, vm = _exact(gp, mids)
        step = (hi - lo) / (nodes.size - 1)
        j, w = _stencil(mids, lo, step, nodes.size)
        err_mean = float(np.max(np.abs(_apply(c, j, w) - cm)))
        std_m = np.sqrt(np.clip(vm, 0.0, None))
        err_std = float(np.max(np.abs(np.sqrt(np.clip(_apply(v, j, w), 0.0, None)) - std_m)))
        fine = np.empty(2 * nodes.size - 1)
        fine[0::2], fine[1::2] = nodes, mids
        cf = np.empty(fine.size)
        cf[0::2], cf[1::2] = c, cm
        vf = np.empty(fine.size)
        vf[0::2], vf[1::2] = v, vm
        floor = float(np.sqrt(max(float(np.min(vf)), 0.0)))
        tol = rtol * floor
        if err_mean <= tol and err_std <= tol:
            return PredictionTable(
                lo, (hi - lo) / (fine.size - 1), cf, vf, gp.mean, period, err_mean, err_std
            )
        if 2 * fine.size - 1 > max_nodes:
            return None
        nodes, c, v = fine, cf, vf


def predict_many(
    gp: FittedGP, x: object, *, return_std: bool = False, rtol: float = 1e-6
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Posterior mean (and standard deviation) at many readings ``x`` (m,).

    Readings inside the span of the data (any reading, for a periodic GP) come from a
    :func:`tabulate` table when there are at least ``MIN_READINGS_FOR_TABLE`` of them;
    all others, and all readings when the table does not reach ``rtol``, are exact. The
    table always spans the data, so a reading's value does not depend on the other
    readings of the batch; table and exact values agree to ``rtol`` times the smallest u.
    """
    xs = as_positions(x, "x")
    mean = np.empty(xs.shape)
    std = np.empty(xs.shape)
    lo, hi = float(gp.x.min()), float(gp.x.max())
    periodic = isinstance(gp.kernel, Periodic)
    inside = np.ones(xs.shape, bool) if periodic else (xs >= lo) & (xs <= hi)
    table = None
    if np.count_nonzero(inside) >= MIN_READINGS_FOR_TABLE:
        table = tabulate(gp, lo, hi, rtol=rtol) if hi > lo else None
    if table is None:
        inside[:] = False
    else:
        out = table(xs[inside], return_std=return_std)
        mean[inside], std[inside] = out if return_std else (out, 0.0)
    rest = ~inside
    if np.any(rest):
        out = gp.predict(xs[rest], return_std=return_std)
        mean[rest], std[rest] = out if return_std else (out, 0.0)
    return (mean, std) if return_std else mean


def chebyshev_mean(gp: FittedGP, x: object, *, rtol: float = 1e-12) -> np.ndarray:
    """Posterior mean at many readings ``x`` (m,) of a smooth GP: the correction
    ``mean - m`` interpolated on the readings' span by a Chebyshev polynomial.

    The kernel is evaluated at the degree's Chebyshev points instead of at every reading
    (the study's cost J: 33 rows instead of 2001). The exact mean itself carries a
    rounding error of up to ``eps sum_i |alpha_i k(x, x_i)|`` (1e-10 of the correction
    where the weights alpha are large), so the tolerance ``tol`` is the larger of ``rtol``
    times the largest correction at the points and four times the largest such rounding
    there. A degree is taken when the last quarter of its coefficients has decayed below
    ``tol / 16`` and the interpolant agrees with the exact mean to ``tol`` at 33 readings
    spread over ``x``; failing all of ``32, 64, 128`` (short length scales), or with a
    periodic kernel, the mean is exact.
    """
    from numpy.polynomial.chebyshev import chebval
    from scipy.fft import dct

    xs = as_positions(x, "x")
    if isinstance(gp.kernel, Periodic) or xs.size < 4 * _CHEB_DEGREES[0]:
        return gp.predict(xs)
    lo, hi = float(xs.min()), float(xs.max())
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    if not (np.isfinite(mid) and half > 0):
        return gp.predict(xs)
    check = np.unique(np.linspace(0, xs.size - 1, _CHEB_CHECKS).astype(np.intp))
    exact = gp.kernel(xs[check], gp.x) @ gp.alpha
    weights = np.abs(gp.alpha)
    for degree in _CHEB_DEGREES:
        n = degree + 1
        K = gp.kernel(mid + half * np.cos(np.pi * (np.arange(n) + 0.5) / n), gp.x)
        values = K @ gp.alpha
        rounding = float(np.max(np.abs(K) @ weights)) * np.finfo(float).eps
        tol = max(rtol * float(np.max(np.abs(values))), 4.0 * rounding)
        coef = dct(values, type=2) / n
        coef[0] *= 0.5
        if float(np.max(np.abs(coef[-(n // 4) :]))) > tol / 16:
            continue  # not decayed: levelled off at tol, the interpolant can be off more
        correction = chebval((xs - mid) / half, coef)
        if float(np.max(np.abs(correction[check] - exact))) <= tol:
            return gp.mean(xs) + correction
    return gp.predict(xs)


def _exact(gp: FittedGP, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean, std = gp.predict(x, return_std=True)
    return mean - gp.mean(x), std * std


def _stencil(u: np.ndarray, lo: float, step: float, n: int) -> tuple[np.ndarray, tuple]:
    # Cubic Lagrange through nodes j..j+3 with s = (u - node_j) / step in [0, 3]; the
    # stencil is centred on the interval holding u and shifted inwards at the two ends.
    t = (u - lo) / step
    j = np.clip(np.floor(t).astype(np.intp) - 1, 0, n - 4)
    s = t - j
    s1, s2, s3 = s - 1.0, s - 2.0, s - 3.0
    a, b = s * s1, s2 * s3
    w = (-(s1 * b) / 6.0, s * b / 2.0, -(a * s3) / 2.0, a * s2 / 6.0)
    return j, w


def _apply(f: np.ndarray, j: np.ndarray, w: tuple) -> np.ndarray:
    return w[0] * f[j] + w[1] * f[j + 1] + w[2] * f[j + 2] + w[3] * f[j + 3]
