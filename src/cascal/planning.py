"""Planning: where the scarce reference measurements of stage 0 help most.

A further reference measurement at test-bed reading ``c``, with variance ``s2``, lowers
stage 0's posterior covariance ``C`` by the rank-one term ``C[:, c] C[c, :] / (C[c, c] +
s2)`` whatever value it reads (hyperparameters held at their fitted values). Measurements
are chosen one at a time from candidate readings (where the reference can reach), each
where it most lowers the summed posterior variance of a target:

* stage 0's own variance at given test-bed readings (where the lower stages read the test
  bed), or
* the variance of the stage below over its readings, when stage 0's posterior covariance at
  that stage's upper readings is part of its noise (method ``bayes``): a reduction
  ``w w^T`` of that noise lowers the summed variance at readings ``g`` by
  ``|K_g A^-1 w|^2 / (1 - w^T A^-1 w)`` (Sherman-Morrison; ``A`` the stage's target
  covariance, ``K_g`` its kernel between ``g`` and its readings); or
* the variance of the last of a chain of such stages (the device of three or more): the
  reduction passes down the chain as a rank-one term, each stage's posterior covariance at
  the next one's upper readings falling by ``v v^T``, ``v = K_u A^-1 w / sqrt(1 - w^T A^-1
  w)`` (``K_u`` its kernel between those readings and its own).

Greedy choice is the usual sequential design for a summed posterior variance; a point may
be chosen twice (a repeat averages the reference's noise down). The uncertainties after
the whole plan are recomputed with all its measurements at once, not from the step-by-step
updates: stage 0's from a new Cholesky factor (:func:`variance_after`), the stage below's
by one Woodbury block update (:func:`lower_variance_after`).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack, solve_triangular

from . import linalg
from .errors import InputError, NumericalError
from .gp import FittedGP
from .validation import as_positions

__all__ = [
    "CANDIDATES",
    "GAP_FACTOR",
    "REACH_GAP",
    "LowerStage",
    "Plan",
    "candidate_readings",
    "check_interval",
    "covered",
    "default_noise_variance",
    "find_gaps",
    "lower_variance_after",
    "plan_reference",
    "variance_after",
]

#: A spacing this many times the median spacing of stage 0's readings counts as a gap.
GAP_FACTOR = 3.0
#: Stretches without reference points narrower than this fraction of the span are gaps for
#: a plan's default reach only where they are also over GAP_FACTOR times the spacings on
#: either side (a sparse stretch is passed by the reference, not out of its reach).
REACH_GAP = 0.1
#: Candidate test-bed readings over the reachable intervals, about.
CANDIDATES = 1001
#: Most measurements one plan proposes.
MAX_MEASUREMENTS = 1000
#: Least variance of one new measurement, relative to stage 0's largest prior variance:
#: below it, the variances a plan reaches are lost in round-off (the covariance updates'
#: errors are about 1e-16 of the prior variance each).
NOISE_FLOOR = 1e-8


@dataclass(frozen=True, slots=True)
class LowerStage:
    """The stage below stage 0, as planning sees it.

    Attributes:
        gp: Its fitted GP, whose known noise holds stage 0's posterior covariance at
            ``upper`` (method ``bayes``).
        upper: Its upper (test-bed) readings, where stage 0 was evaluated, shape (n,).
        where: Its own readings at which its variance is the target, shape (m,).
    """

    gp: FittedGP
    upper: np.ndarray
    where: np.ndarray


def _chain(lower: LowerStage | Sequence[LowerStage]) -> tuple[LowerStage, ...]:
    """``lower`` as a chain of stages from stage 1 down, checked: each a
    :class:`LowerStage`, each one's ``where`` the next one's ``upper``."""
    chain = tuple(lower) if isinstance(lower, tuple | list) and lower else (lower,)
    for stage in chain:
        if not isinstance(stage, LowerStage):  # (a README review: a FittedGP given met an
            # AttributeError)
            raise InputError(
                "lower: expected a cascal.planning.LowerStage(gp, upper, where) (the stage "
                "below: its fitted GP, its readings of this stage's sensor, where it is used), "
                f"or a list of them from stage 1 down, got {type(stage).__name__}"
            )
    for k, (above, below) in enumerate(itertools.pairwise(chain), start=1):
        here = as_positions(above.where, "where")
        if not np.array_equal(here, as_positions(below.upper, "upper")):
            raise InputError(
                f"lower: stage {k}'s where must be the upper readings of stage {k + 1} (where "
                "the stage below reads it): the chain passes its covariance down there"
            )
    return tuple(chain)


@dataclass(frozen=True, slots=True)
class Plan:
    """Proposed reference measurements, in the order chosen, and what they are worth.

    Attributes:
        positions: Test-bed readings at which to measure with the reference, shape (k,).
        u_rms: RMS of the target's standard uncertainty before (entry 0) and after each
            measurement, shape (k + 1,), target unit.
        u_max: Largest standard uncertainty of the target, likewise, shape (k + 1,).
        noise_variance: Variance assumed for one new reference measurement, unit squared.
        where: Readings at which the target's uncertainty is counted, shape (m,): test-bed
            readings, or the (last) lower stage's own readings.
        u_before: Target's standard uncertainty at ``where`` now, shape (m,).
        u_after: The same after all ``positions`` are measured, recomputed at once,
            shape (m,).
    """

    positions: np.ndarray
    u_rms: np.ndarray
    u_max: np.ndarray
    noise_variance: float
    where: np.ndarray
    u_before: np.ndarray
    u_after: np.ndarray


def default_noise_variance(testbed: FittedGP) -> float:
    """Variance of one further reference measurement, as precise as the average existing
    point: the learned noise variance plus the mean known variance, unit squared."""
    known = 0.0 if testbed.noise is None else float(np.mean(testbed.noise.diagonal(testbed.x.size)))
    return float(testbed.noise_variance) + known


def plan_reference(
    testbed: FittedGP,
    candidates: object,
    k: int,
    *,
    where: object | None = None,
    lower: LowerStage | Sequence[LowerStage] | None = None,
    noise_variance: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Plan:
    """Choose ``k`` reference measurements among test-bed readings ``candidates`` (c,),
    greedily, each lowering the target's summed variance most.

    Args:
        testbed: Stage 0's fitted GP (test-bed readings -> reference readings).
        candidates: Test-bed readings the reference can reach, shape (c,).
        k: Measurements to propose, 1 to :data:`MAX_MEASUREMENTS`.
        where: Target: stage 0's variance at these test-bed readings, shape (m,); or
        lower: Target: the variance of the stage below at ``lower.where``; or of the last
            of a chain of stages (a list from stage 1 down, each one's ``where`` the next
            one's ``upper``) at its ``where``.
        noise_variance: Variance of one new measurement; default
            :func:`default_noise_variance`; at least :data:`NOISE_FLOOR` times stage 0's
            largest prior variance (:attr:`Plan.noise_variance` is the one used).
        progress: Called as ``progress(chosen, k)`` after every choice.
    """
    cand = as_positions(candidates, "candidates")
    if cand.size == 0:
        raise InputError("candidates: expected at least one reading the reference can reach")
    whole = isinstance(k, int | np.integer) and not isinstance(k, bool)
    if not (whole and 1 <= k <= MAX_MEASUREMENTS):  # (a review: 2.7 had planned 2)
        raise InputError(
            f"k: expected a whole number of measurements, 1 to {MAX_MEASUREMENTS}, got {k!r}"
        )
    if (where is None) == (lower is None):
        raise InputError("plan_reference: give the target as where= or lower=, not both")
    chain = None if lower is None else _chain(lower)
    s2 = _noise(testbed, noise_variance)
    points = (
        as_positions(where, "where") if chain is None else as_positions(chain[0].upper, "upper")
    )
    # Stage 0's posterior covariance between the target's points and the candidates (q, c),
    # among the candidates (c, c), and the target points' variances (q,): updated in place.
    Vp, Vc = testbed.whitened(points), testbed.whitened(cand)
    cross = testbed.kernel(points, cand) - Vp.T @ Vc
    among = testbed.kernel(cand) - Vc.T @ Vc
    var_p = testbed.kernel.diag(points) - np.einsum("ij,ij->j", Vp, Vp)
    prior = float(np.max(testbed.kernel.diag(np.concatenate([cand, points]))))
    s2 = max(s2, NOISE_FLOOR * prior)  # also keeps every candidate's variance plus noise up
    if chain is None:
        target: _TestbedTarget | _LowerTarget | _ChainTarget = _TestbedTarget(var_p)
    elif len(chain) == 1:
        target = _LowerTarget(chain[0], cross)
    else:
        target = _ChainTarget(chain, cross)
    var = [target.variance()]
    chosen = []
    for _ in range(int(k)):
        d = np.clip(np.diagonal(among), 0.0, None) + s2
        j = int(np.argmax(target.gains(cross, d)))
        col_p, col_c = cross[:, j] / np.sqrt(d[j]), among[:, j] / np.sqrt(d[j])
        target.update(cross, j, float(d[j]), col_c)
        cross -= np.outer(col_p, col_c)
        among -= np.outer(col_c, col_c)
        chosen.append(float(cand[j]))
        var.append(target.variance())
        if progress is not None:
            progress(len(chosen), int(k))
    positions = np.asarray(chosen)
    if chain is None:
        where_out, after = points, variance_after(testbed, points, positions, s2)
    else:
        where_out = as_positions(chain[-1].where, "where")
        after = lower_variance_after(chain, testbed, positions, s2)
    v = np.clip(np.asarray(var), 0.0, None)
    return Plan(
        positions,
        np.sqrt(v.mean(axis=1)),
        np.sqrt(v.max(axis=1)),
        s2,
        where_out,
        np.sqrt(v[0]),
        np.sqrt(np.clip(after, 0.0, None)),
    )


def _noise(testbed: FittedGP, noise_variance: float | None) -> float:
    s2 = default_noise_variance(testbed) if noise_variance is None else float(noise_variance)
    if not (np.isfinite(s2) and s2 >= 0.0):
        raise InputError(f"noise_variance: expected a finite value >= 0, got {noise_variance!r}")
    return s2


def _variance_now(stage: LowerStage) -> tuple[np.ndarray, np.ndarray]:
    """The stage's kernel between its ``where`` and its readings (m, n), and its posterior
    variance at ``where`` now (m,)."""
    g = as_positions(stage.where, "where")
    Kg = stage.gp.kernel(g, stage.gp.x)
    W = solve_triangular(stage.gp.L, Kg.T, lower=True, check_finite=False)
    return Kg, stage.gp.kernel.diag(g) - np.einsum("ij,ij->j", W, W)


class _TestbedTarget:
    """Stage 0's own variance at the target's points ``var`` (q,)."""

    def __init__(self, var: np.ndarray) -> None:
        self.var = var

    def gains(self, S: np.ndarray, d: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->j", S, S) / d

    def update(self, S: np.ndarray, j: int, d: float, col_c: np.ndarray) -> None:
        w = S[:, j] / np.sqrt(d)
        self.var = self.var - w * w

    def variance(self) -> np.ndarray:
        return self.var


class _LowerTarget:
    """The lower stage's variance at its ``where`` (m,); its noise holds stage 0's
    covariance at its upper readings, the target's points. With ``A`` its target
    covariance (n, n) and ``S`` stage 0's cross-covariance between those points and the
    candidates (n, c), it keeps ``P = A^-1 S`` and ``G = K_g P`` and updates them (and the
    variance) by rank-one terms: O((n + m) c) per measurement, no refactorisation."""

    def __init__(self, lower: LowerStage, S: np.ndarray) -> None:
        self.Kg, self.var = _variance_now(lower)
        self.P = linalg.cho_solve(lower.gp.L, S)
        self.G = self.Kg @ self.P

    def gains(self, S: np.ndarray, d: np.ndarray) -> np.ndarray:
        # w = S_j / sqrt(d_j): |K_g A^-1 w|^2 / (1 - w^T A^-1 w)
        fit = np.einsum("ij,ij->j", S, self.P) / d
        return np.einsum("ij,ij->j", self.G, self.G) / d / np.clip(1.0 - fit, 1e-12, None)

    def update(self, S: np.ndarray, j: int, d: float, col_c: np.ndarray) -> None:
        # A' = A - w w^T: A'^-1 = A^-1 + a a^T / beta, a = A^-1 w; S' = S - w col_c^T.
        w, a = S[:, j] / np.sqrt(d), self.P[:, j] / np.sqrt(d)
        beta = max(1.0 - float(w @ a), 1e-12)
        aS = a @ S - float(a @ w) * col_c  # a^T S'
        Ka = self.Kg @ a
        self.P += np.outer(a, aS / beta - col_c)
        self.G += np.outer(Ka, aS / beta - col_c)
        self.var = self.var - Ka * Ka / beta

    def variance(self) -> np.ndarray:
        return self.var


class _ChainTarget:
    """The last stage's variance at its ``where`` (m,), of a chain of two or more stages
    below stage 0, each one's noise holding the posterior covariance of the one above at its
    upper readings. It keeps every stage's target covariance ``A`` and its factor: a
    measurement's reduction ``w w^T`` at stage 1 passes down as ``v v^T`` (module
    docstring), lowering each ``A`` by a rank-one term. O(n^2 c + n^3) per stage and
    measurement, ``c`` candidates."""

    def __init__(self, chain: tuple[LowerStage, ...], S: np.ndarray) -> None:
        self.Ku = [
            a.gp.kernel(as_positions(b.upper, "upper"), a.gp.x)
            for a, b in itertools.pairwise(chain)
        ]
        self.Kg, self.var = _variance_now(chain[-1])
        self.A = [s.gp.L @ s.gp.L.T for s in chain]
        self.L = [s.gp.L for s in chain]

    def _down(self, W: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
        """Reductions ``W`` (n1, c) of stage 0's covariance at stage 1's upper readings,
        passed down: the last stage's ``A^-1 W`` and ``1 - diag(W^T A^-1 W)``, and each
        stage's reductions."""
        passed = []
        for k, L in enumerate(self.L):
            passed.append(W)
            P = linalg.cho_solve(L, W)
            beta = np.clip(1.0 - np.einsum("ij,ij->j", W, P), 1e-12, None)
            if k == len(self.L) - 1:
                return P, beta, passed
            W = self.Ku[k] @ P / np.sqrt(beta)
        raise AssertionError("unreachable")

    def gains(self, S: np.ndarray, d: np.ndarray) -> np.ndarray:
        P, beta, _ = self._down(S / np.sqrt(d))
        G = self.Kg @ P
        return np.einsum("ij,ij->j", G, G) / beta

    def update(self, S: np.ndarray, j: int, d: float, col_c: np.ndarray) -> None:
        P, beta, passed = self._down(S[:, j : j + 1] / np.sqrt(d))
        for k, w in enumerate(passed):
            self.A[k] -= w @ w.T
            self.L[k] = _factor(self.A[k], f"the target covariance of stage {k + 1}")
        Ka = (self.Kg @ P)[:, 0]
        self.var = self.var - Ka * Ka / float(beta[0])

    def variance(self) -> np.ndarray:
        return self.var


def _factor(A: np.ndarray, what: str) -> np.ndarray:
    """Cholesky factor of a covariance ``what`` the planned measurements change; refused
    (no jitter: it would change the plan's figures unseen) when singular to round-off."""
    L, info = lapack.dpotrf(A, lower=1, clean=1)
    if info != 0 or not np.all(np.isfinite(np.diagonal(L))):
        raise NumericalError(
            f"planning: the measurements leave {what} singular to round-off; plan fewer "
            "measurements or give a larger noise of a new one"
        )
    return L


def variance_after(
    testbed: FittedGP, x: object, positions: object, noise_variance: float
) -> np.ndarray:
    """Stage 0's posterior variance at test-bed readings ``x`` (m,) once reference
    measurements at ``positions`` (k,) with variance ``noise_variance`` are added, from a
    new Cholesky factor of the enlarged target covariance: shape (m,)."""
    xs, pos = as_positions(x, "x"), as_positions(positions, "positions")
    L = _enlarged_factor(testbed, pos, noise_variance)
    xa = np.concatenate([testbed.x, pos])
    V = solve_triangular(L, testbed.kernel(xa, xs), lower=True, check_finite=False)
    return testbed.kernel.diag(xs) - np.einsum("ij,ij->j", V, V)


def _enlarged_factor(testbed: FittedGP, positions: np.ndarray, s2: float) -> np.ndarray:
    n = testbed.x.size
    xa = np.concatenate([testbed.x, positions])
    K = testbed.kernel(xa)
    K[:n, :n] = testbed.L @ testbed.L.T  # the fitted target covariance, noise included
    K.flat[n * (xa.size + 1) :: xa.size + 1] += s2
    return _factor(K, "stage 0's enlarged target covariance")


def lower_variance_after(
    lower: LowerStage | Sequence[LowerStage],
    testbed: FittedGP,
    positions: object,
    noise_variance: float,
) -> np.ndarray:
    """The lower stage's posterior variance at ``lower.where`` (m,) once stage 0 has the
    reference measurements at ``positions`` (k,), all at once: stage 0's covariance at
    ``lower.upper`` falls by ``Z Z^T`` (``Z = C_uk R^-T``, ``R R^T = C_kk + s2 I``, ``C``
    stage 0's posterior covariance), and the lower stage's target covariance ``A`` with
    it; by the Woodbury identity the variance falls by the diagonal of
    ``K_g A^-1 Z (I - Z^T A^-1 Z)^-1 Z^T A^-1 K_g^T`` over its value now. O(n^2 k). Of a
    chain (a list from stage 1 down), the last stage's: each stage's posterior covariance
    at the next one's upper readings falls by ``Z' Z'^T``, ``Z' = K_u A^-1 Z M^-T``
    (``M M^T = I - Z^T A^-1 Z``), down to the last."""
    chain = _chain(lower)
    pos = as_positions(positions, "positions")
    Kg, var = _variance_now(chain[-1])
    if pos.size == 0:
        return var
    up = as_positions(chain[0].upper, "upper")
    Vu, Vk = testbed.whitened(up), testbed.whitened(pos)
    Cuk = testbed.kernel(up, pos) - Vu.T @ Vk
    Ckk = testbed.kernel(pos) - Vk.T @ Vk
    Ckk.flat[:: pos.size + 1] += noise_variance
    R = _factor(Ckk, "stage 0's covariance at the new points")
    Z = solve_triangular(R, Cuk.T, lower=True, check_finite=False).T  # (n, k)
    for k, stage in enumerate(chain):
        Q = linalg.cho_solve(stage.gp.L, Z)
        M = -(Z.T @ Q)
        M.flat[:: pos.size + 1] += 1.0
        Lm = _factor(0.5 * (M + M.T), "the lower stage's target covariance")
        if k == len(chain) - 1:
            T = solve_triangular(Lm, (Kg @ Q).T, lower=True, check_finite=False)
            return var - np.einsum("ij,ij->j", T, T)
        Ku = stage.gp.kernel(as_positions(chain[k + 1].upper, "upper"), stage.gp.x)
        Z = solve_triangular(Lm, (Ku @ Q).T, lower=True, check_finite=False).T
    raise AssertionError("unreachable")


def find_gaps(
    x: np.ndarray, *, factor: float = GAP_FACTOR, period: float | None = None
) -> list[tuple[float, float]]:
    """Stretches between neighbouring readings ``x`` (n,) wider than ``factor`` times the
    median spacing; with ``period``, also the stretch across the seam (ending above it)."""
    xs = np.unique(np.asarray(x, dtype=float))
    if xs.size < 3:
        return []
    d = np.diff(xs)
    limit = factor * float(np.median(d))
    gaps = [(float(xs[i]), float(xs[i + 1])) for i in np.flatnonzero(d > limit)]
    if period is not None and xs[0] + period - xs[-1] > limit:
        gaps.append((float(xs[-1]), float(xs[0] + period)))
    return gaps


def covered(x: np.ndarray, period: float | None = None) -> list[tuple[float, float]]:
    """Stretches of readings ``x`` (n,) without their gaps: where the reference has been.
    A gap is wider than :data:`GAP_FACTOR` median spacings (as the report hatches), and
    than :data:`REACH_GAP` of the span (one turn, for a ``period``) or :data:`GAP_FACTOR`
    times the spacing on either side of it; without a gap across the seam of a turn, the
    last stretch runs on across it."""
    xs = np.unique(x)
    span = float(xs[-1] - xs[0]) if period is None else float(period)
    d = np.diff(xs)

    def stands_out(a: float, b: float) -> bool:  # against its neighbouring spacings
        i = int(np.searchsorted(xs, a))  # the gap is d[i]; the seam's comes after d[-1]
        if i == d.size:
            before, after = d[-1], d[0]
        else:
            before = d[i - 1] if i > 0 else 0.0
            after = d[i + 1] if i + 1 < d.size else 0.0
        return b - a > GAP_FACTOR * float(max(before, after))

    gaps = [
        (a, b)
        for a, b in find_gaps(xs, period=period)
        if b - a > REACH_GAP * span or stands_out(a, b)
    ]
    out, start, end = [], float(xs[0]), float(xs[-1])
    for a, b in gaps:
        if a == end:  # the seam's
            break
        out.append((start, a))
        start = b
    else:
        if period is not None:
            end = float(xs[0]) + period
    return [*out, (start, end)]


def check_interval(pair: object, name: str) -> tuple[float, float]:
    """``(lo, hi)`` as floats, finite, ``lo <= hi`` and a finite width; ``name`` is used in
    the message."""
    try:
        lo, hi = (float(v) for v in pair)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected an interval (lo, hi), got {pair!r}") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo <= hi and np.isfinite(hi - lo)):
        raise InputError(f"{name}: expected finite lo <= hi, got {lo!r}, {hi!r}")
    return lo, hi


def candidate_readings(intervals: list[tuple[float, float]] | tuple) -> np.ndarray:
    """About :data:`CANDIDATES` readings over the intervals ``(lo, hi)``, in proportion to
    their lengths (both ends of each; a point interval gives its one reading), sorted."""
    total = sum(hi - lo for lo, hi in intervals)
    parts = []
    for lo, hi in intervals:
        n = 1 if hi == lo else max(2, round(CANDIDATES * ((hi - lo) / total)))
        parts.append(np.linspace(lo, hi, n))
    return np.unique(np.concatenate(parts))
