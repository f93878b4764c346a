"""Compensation tables for controllers: the correction on a uniform grid, linear in between.

A controller corrects a reading ``r`` as ``r + c(r)``, with ``c`` interpolated linearly
between the nodes of a uniform grid: one subtraction, one division, one truncation and one
multiply-add per reading (and a ``fmod`` on a periodic table), no search and no
exponentials. The grid spans the calibrated range (one period for a periodic model) with
``2^k + 1`` nodes, ``k >= 4``, the coarsest whose interpolation error, measured against the
exact correction at check points, is within 0.95 of a tolerance (the error between them
may be larger). The check points of interval
``j`` are at the fractions 1/4, 1/2, 3/4 and ``frac((j + 1) phi)`` of it (``phi`` the golden
ratio: no periodic error whose period divides the spacing vanishes at all of them), and at
given extra points (the data's readings, where a lookup-table model has its kinks).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

__all__ = ["CompensationTable", "compensation_table"]

#: Fewest intervals tried, and the most nodes a table may have (512 KiB of doubles).
_START_INTERVALS = 16
MAX_NODES = 2**16 + 1
_FRACTIONS = np.array([0.25, 0.5, 0.75])
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0
#: A table is taken where its error at the check points is within this fraction of the
#: tolerance: the largest error may lie between them (a cubic error's extremes lie at
#: 0.21 and 0.79 of an interval, 2.6 % above its values at 1/4 and 3/4; a review found
#: a table built to the error at its check points 0.11 % over it in between).
_MARGIN = 0.95


@dataclass(frozen=True, slots=True)
class CompensationTable:
    """The correction ``corrected - reading`` at ``n`` equally spaced readings.

    Attributes:
        lo: First node and start of the range, reading unit.
        hi: End of the range (the last node up to rounding), reading unit; readings
            outside ``[lo, hi]`` are flagged (not those of a periodic table).
        step: Node spacing, reading unit.
        correction: Correction at the nodes, shape (n,), reading unit.
        u: Standard uncertainty of the correction at the nodes, shape (n,), or None (a
            lookup-table model has none).
        period: Period of a periodic model (readings wrap onto ``[lo, lo + period)``), or
            None.
        tolerance: Interpolation error the table was built to, reading unit.
        error: Largest interpolation error found at the check points, reading unit.
        checked: Number of check points.
        arc: For a periodic table, ``(start, width)``: readings whose angle lies strictly
            between ``start`` and ``start + width`` (modulo the period) are flagged, the
            part of the turn the device readings left out; None for none.

    A periodic table also flags a reading from :attr:`limit` on (in magnitude): where a
    float64 holds the reading less finely than the smallest u on the nodes, its correction
    is lost to rounding. :func:`cascal.workflow.correct` flags by each reading's own u,
    at least the nodes' smallest but where u dips between two nodes, so the table flags
    what it flags (bar such dips, within a factor of 2 of the limit), and a few more.
    """

    lo: float
    hi: float
    step: float
    correction: np.ndarray
    u: np.ndarray | None
    period: float | None
    tolerance: float
    error: float
    checked: int
    arc: tuple[float, float] | None = None

    @property
    def limit(self) -> float:
        """Smallest reading magnitude a periodic table flags as too large for its
        correction's digits: the power of two from which a float64's step exceeds the
        smallest u on the nodes; inf for a table without u or not periodic."""
        if self.period is None or self.u is None or not np.all(self.u > 0.0):
            return math.inf
        k = math.frexp(float(np.min(self.u)))[1]  # u_min in [2^(k-1), 2^k)
        return math.ldexp(1.0, k + 52)  # the step there is 2^k > u_min; just below, <= u_min

    @property
    def n(self) -> int:
        """Number of nodes."""
        return int(self.correction.size)

    def nodes(self) -> np.ndarray:
        """The readings at the nodes, shape (n,)."""
        return self.lo + self.step * np.arange(self.n)

    def __call__(self, readings: object) -> tuple[np.ndarray, np.ndarray]:
        """Corrected readings and an outside-the-table flag, each shape (m,), computed with
        the operations of the generated C function (so with the same doubles): outside
        the table the nearest end's correction is held and the flag is set; a periodic
        table wraps every reading onto its period."""
        r = np.asarray(readings, dtype=float)
        with np.errstate(invalid="ignore", over="ignore"):  # huge, inf, NaN: as in C
            if self.period is not None:
                t = np.fmod(r - self.lo, self.period)
                t = np.where(t < 0.0, t + self.period, t) / self.step
                outside = ~(np.abs(r) < self.limit)  # (also infinite and NaN readings)
                if self.arc is not None:
                    outside |= in_arc(r, self.arc, self.period)
            else:  # outside the range, the end's node (the C divides only inside)
                outside = ~((r >= self.lo) & (r <= self.hi))
                end = np.where(r > self.hi, self.n - 1, 0.0)
                t = np.where(outside, end, (r - self.lo) / self.step)
        t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, self.n - 1)
        i = np.minimum(t.astype(np.int64), self.n - 2)
        t = t - i
        c = self.correction
        return r + (c[i] + t * (c[i + 1] - c[i])), outside


def in_arc(readings: np.ndarray, arc: tuple[float, float], period: float) -> np.ndarray:
    """True where a reading's angle lies strictly inside ``arc = (start, width)`` modulo
    ``period``, computed as the generated C function does (``fmod``, then one addition)."""
    start, width = arc
    with np.errstate(invalid="ignore"):
        a = np.fmod(np.asarray(readings, dtype=float) - start, period)
        a = np.where(a < 0.0, a + period, a)
        return (a > 0.0) & (a < width)


def compensation_table(
    correct: Callable[[np.ndarray], np.ndarray],
    lo: float,
    hi: float,
    tolerance: float,
    *,
    std: Callable[[np.ndarray], np.ndarray] | None = None,
    period: float | None = None,
    extra: np.ndarray | None = None,
    max_nodes: int = MAX_NODES,
) -> CompensationTable | None:
    """The coarsest table of ``correct`` on ``[lo, hi]`` within ``tolerance`` (within
    :data:`_MARGIN` of it at the check points), or None if more than ``max_nodes`` nodes
    would be needed.

    Args:
        correct: Corrected readings at readings (m,) -> (m,), the exact model.
        lo, hi: Calibrated range, ``lo < hi`` (for a periodic model, ``hi = lo + period``).
        tolerance: Largest interpolation error allowed, reading unit, > 0.
        std: Standard uncertainty at readings (m,) -> (m,), tabulated alongside if given.
        period: Period of a periodic model, or None.
        extra: Further readings inside ``[lo, hi]`` to check the error at, shape (k,).
        max_nodes: Most nodes tried.
    """
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise ValueError(f"compensation_table: expected finite lo < hi, got {lo!r}, {hi!r}")
    if not (math.isfinite(tolerance) and tolerance > 0.0):
        raise ValueError(f"compensation_table: expected a tolerance > 0, got {tolerance!r}")
    extra = np.zeros(0) if extra is None else np.asarray(extra, dtype=float)
    if period is not None:  # (a review: readings of -180 to 0 had not been checked)
        extra = lo + np.mod(extra - lo, period)
    extra = extra[(extra >= lo) & (extra <= hi)]
    intervals = _START_INTERVALS
    while intervals + 1 <= max_nodes:
        step = (hi - lo) / intervals
        nodes = lo + step * np.arange(intervals + 1)
        golden = np.mod(_GOLDEN * np.arange(1, intervals + 1), 1.0)[:, None]
        fractions = np.hstack([np.broadcast_to(_FRACTIONS, (intervals, 3)), golden])
        checks = np.concatenate([(nodes[:-1, None] + step * fractions).ravel(), extra])
        corrected = correct(np.concatenate([nodes, checks]))
        correction = corrected[: nodes.size] - nodes
        table = CompensationTable(
            lo, hi, step, correction, None, period, tolerance, 0.0, checks.size
        )
        exact = corrected[nodes.size :]
        error = float(np.max(np.abs(table(checks)[0] - exact)))
        if error <= _MARGIN * tolerance:
            u = None if std is None else np.asarray(std(nodes), dtype=float)
            return replace(table, u=u, error=error)
        intervals *= 2
    return None
