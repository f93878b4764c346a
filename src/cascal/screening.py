"""Outlier screening of a fitted stage: leave-one-out residuals and backward deletion.

A reference reading taken while the beam was interrupted, or a typo in a stage file, pulls
a GP fit towards it and inflates the learned noise of every other point. Each point is
compared with what all the others predict for it (the leave-one-out posterior of its
target, GPML section 5.4.2, in closed form from the fit's Cholesky factor): a point is
suspect where the standardised residual exceeds the two-sided Bonferroni threshold at a
family-wise false-alarm probability ``level`` for the stage. The worst suspect is taken
out, the stage's white noise learned again without it and the rest screened again, until
no point exceeds the threshold. Each suspect is finally judged against the fit without all
of them, where it no longer inflates the noise it is measured by.

A single bad reading among repeats at one position hides from that screening: it inflates
its own point's known noise. :func:`screen_repeats` compares the spread of each position's
repeats with the pooled spread of the other positions' (an F test, as in Cochran's test of
ISO 5725-2), again by backward deletion.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_triangular

from .errors import InputError
from .gp import FittedGP, refit
from .likelihood import Objective
from .linalg import inverse_diagonal
from .noise import Dense, Diagonal, Noise
from .validation import MIN_POINTS, aggregate_repeats

__all__ = [
    "LEVEL",
    "MAX_FRACTION",
    "MIN_LEVEL",
    "Screening",
    "Spread",
    "Suspect",
    "loo_residuals",
    "min_points",
    "repeats_screening",
    "screen",
    "screen_repeats",
    "threshold",
]

#: Default family-wise false-alarm probability per stage.
LEVEL = 0.01
#: Smallest level accepted (below it the thresholds' tail probabilities underflow).
MIN_LEVEL = 1e-12
#: Default largest share of a stage's points taken out as suspects.
MAX_FRACTION = 0.1
#: A refit's white-noise variance is searched down to this factor (log) below the fit's.
_NOISE_DROP = 30.0


@dataclass(frozen=True, slots=True)
class Suspect:
    """A point its stage's other points do not support.

    Attributes:
        index: Position in the stage's points (increasing readings).
        reading: Its reading of the sensor being calibrated.
        target: Its target (the more accurate reading, or the stage above's correction).
        predicted: The target predicted by the stage fitted without every suspect.
        std: Standard deviation of the target around ``predicted`` (the map's posterior
            and the target's noise), same unit.
        z: ``(target - predicted) / std``.
    """

    index: int
    reading: float
    target: float
    predicted: float
    std: float
    z: float


@dataclass(frozen=True, slots=True)
class Screening:
    """Outcome of :func:`screen` for one stage.

    Attributes:
        z: Leave-one-out standardised residual of every point in the fit as given, (n,).
        threshold: The threshold |z| was compared with at n points.
        suspects: Points taken out, in the order found (largest |z| first at each round).
        noise_std: Learned noise standard deviation of the fit as given.
        noise_std_without: The same, fitted without the suspects.
        capped: True when the search stopped at its largest share of points with more
            above the threshold: the model, not single readings, is then in doubt.
        cap: The most points the search takes out.
        detectable: False where a single outlier cannot be found at all: with a learned
            noise, no |z| of the fit as given exceeds sqrt(n) (the noise grows to cover the
            worst point), and below 12 points at 1 % that is under the threshold.
    """

    z: np.ndarray
    threshold: float
    suspects: tuple[Suspect, ...]
    noise_std: float
    noise_std_without: float
    capped: bool = False
    cap: int = 1
    detectable: bool = True


def _check_level(level: float) -> None:
    number = isinstance(level, numbers.Real) and not isinstance(level, bool)
    if not (number and MIN_LEVEL <= level < 1.0):
        raise InputError(f"level: expected a probability in [{MIN_LEVEL:g}, 1), got {level!r}")


def threshold(n: int, level: float = LEVEL) -> float:
    """|z| above which one of ``n`` standard normals is suspect at family-wise ``level``
    (two-sided, Bonferroni): 3.78 for 64 points at 1 %, 4.56 for 2000."""
    from scipy.special import ndtri

    return float(-ndtri(0.5 * level / n))


def min_points(level: float = LEVEL) -> int:
    """Fewest points at which a fit with a learned noise can show a single outlier at
    ``level``: the smallest n with sqrt(n) above :func:`threshold` (12 at 1 %)."""
    n = 2
    while np.sqrt(n) <= threshold(n, level):
        n += 1
    return n


def loo_residuals(gp: FittedGP) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-out residuals of the targets and their standard deviations, each (n,).

    ``residual_i = y_i - E[y_i | y_-i] = alpha_i / [Kt^-1]_ii`` and
    ``std_i = [Kt^-1]_ii^-1/2``, Kt the target covariance (kernel, known and learned
    noise) of the fit; hyperparameters held at their fitted values.
    """
    d = inverse_diagonal(gp.L)
    return gp.alpha / d, 1.0 / np.sqrt(d)


def screen(gp: FittedGP, *, level: float = LEVEL, max_fraction: float = MAX_FRACTION) -> Screening:
    """Screen a fitted stage for outliers by backward deletion.

    Each round takes out the point of largest |z| beyond the threshold and re-learns the
    stage's white-noise variance without it, the kernel's hyperparameters held at their
    fitted values: the noise is what an outlier inflates to hide itself and the others
    (a few Cholesky factorisations per round, not a fit). A stage fitted with given
    hyperparameters keeps its noise too.

    Args:
        gp: The fitted stage.
        level: Family-wise false-alarm probability of each round (default 1 %).
        max_fraction: Take out at most this share of the points (at least one).
    """
    if not isinstance(gp, FittedGP):  # (a review: an AttributeError for a lookup table)
        raise InputError(
            f"screen: expected a fitted GP stage, got {type(gp).__name__} (a lookup table has "
            "no noise model to screen against)"
        )
    _check_level(level)
    n = gp.x.size
    residual, std = loo_residuals(gp)
    z0 = residual / std
    keep = np.ones(n, bool)
    found: list[int] = []
    current, z = gp, z0
    capped = False
    cap = max(1, int(max_fraction * n))
    while True:
        worst = int(np.argmax(np.abs(z)))
        if not abs(z[worst]) > threshold(int(keep.sum()), level):
            break
        if len(found) == cap or keep.sum() <= MIN_POINTS:
            capped = True
            break
        found.append(int(np.flatnonzero(keep)[worst]))
        keep[found[-1]] = False
        current = _refit(gp, keep)
        r, s = loo_residuals(current)
        z = r / s
    suspects = _judge(gp, current, keep, found) if found else ()
    return Screening(
        z0, threshold(n, level), suspects, _noise_std(gp), _noise_std(current), capped, cap,
        not _learned(gp) or n >= min_points(level),
    )  # fmt: skip


def _noise_std(gp: FittedGP) -> float:
    return float(np.sqrt(gp.noise_variance))


def _learned(gp: FittedGP) -> bool:
    """Whether ``gp`` learned its white-noise variance (not given, not left out)."""
    return gp.optimization is not None and gp.noise_variance > 0.0


def _refit(gp: FittedGP, keep: np.ndarray) -> FittedGP:
    """``gp`` on the points ``keep`` (mask, shape (n,)): the kernel's hyperparameters held,
    the white-noise variance re-learned (bounded scalar search in its log) if it was."""
    x, y = gp.x[keep], gp.y[keep]
    noise = _subset(gp.noise, gp.x.size, keep)
    sn2 = gp.noise_variance
    if _learned(gp):
        objective = Objective(x, y - gp.mean(x), gp.kernel, noise, learn_noise=True)
        theta = gp.kernel.theta

        def cost(log_sn2: float) -> float:
            return -objective.value(np.r_[theta, log_sn2])

        t0 = np.log(sn2)
        from scipy.optimize import minimize_scalar  # here: scipy.optimize costs 0.13 s to load

        found = minimize_scalar(cost, bounds=(t0 - _NOISE_DROP, t0 + 1.0), method="bounded")
        sn2 = float(np.exp(found.x))
    return refit(x, y, gp, dict(gp.hyperparameters, noise_variance=sn2), noise)


def _subset(noise: Noise | None, n: int, keep: np.ndarray) -> Noise | None:
    """The known noise of the points ``keep`` (mask, shape (n,))."""
    if noise is None:
        return None
    if noise.is_diagonal:
        return Diagonal(noise.diagonal(n)[keep])
    return Dense(noise.dense(n)[np.ix_(keep, keep)])


def _judge(gp: FittedGP, fit: FittedGP, keep: np.ndarray, found: list[int]) -> tuple[Suspect, ...]:
    """Each suspect's target against its posterior given the kept points under ``fit``
    (the stage fitted without the suspects), the noise's correlations included."""
    n = gp.x.size
    idx = np.array(found)
    xs = gp.x[idx]
    noise = np.zeros((n, n)) if gp.noise is None else gp.noise.dense(n)
    cross = fit.kernel(xs, gp.x[keep]) + noise[np.ix_(idx, keep)]
    own = fit.kernel.diag(xs) + np.diagonal(noise)[idx] + fit.noise_variance
    V = solve_triangular(fit.L, cross.T, lower=True, check_finite=False)
    mean = fit.mean(xs) + cross @ fit.alpha
    sd = np.sqrt(np.clip(own - np.einsum("ij,ij->j", V, V), np.finfo(float).tiny, None))
    y = gp.y[idx]
    return tuple(
        Suspect(int(i), float(x), float(v), float(m), float(s), float((v - m) / s))
        for i, x, v, m, s in zip(idx, xs, y, mean, sd, strict=True)
    )


@dataclass(frozen=True, slots=True)
class Spread:
    """A position whose repeated readings scatter more than the other positions' repeats.

    Attributes:
        members: Indices of its readings in the input, shape (c,).
        reading: The repeated reading of the sensor being calibrated.
        farthest: Index (in the input) of the reading farthest from the mean of the others.
        ratio: Its sample standard deviation over the pooled one of the other positions.
        p: Probability of a ratio this large or larger when all spreads are equal (F test).
    """

    members: np.ndarray
    reading: float
    farthest: int
    ratio: float
    p: float


#: The repeats check's level after a round that found no suspect, relative to its own.
_UNMASK = 0.1


def screen_repeats(
    x: np.ndarray, y: np.ndarray, *, level: float = LEVEL, max_fraction: float = MAX_FRACTION
) -> tuple[Spread, ...]:
    """Positions read more than once whose readings scatter too much, worst first.

    Each position's sample variance is compared with the pooled variance of the other
    positions' repeats still in the pool (F distribution); a position is suspect where the
    probability is below ``level`` divided by the number of repeated positions. As in
    Rosner's generalised ESD test, the worst leaves the pool each round whether suspect or
    not, and the suspects are the first ``k`` to leave, ``k`` the last round whose worst
    was suspect: two bad positions, each inflating the pool the other is judged against,
    no longer hide each other (a review: 10 positions of 3 readings with two bad ones,
    28 % found before). Positions whose pool has no spread (identical repeats everywhere
    else, e.g. a coarse resolution) are not judged. Where more are suspect than
    ``max_fraction`` of the positions (at least one) allows, the first that many are
    returned and :func:`repeats_screening` also says so.

    Args:
        x: Readings of the sensor being calibrated, shape (n,); repeats are exactly equal.
        y: Readings of the more accurate sensor, shape (n,).
        level: Family-wise false-alarm probability of each round (default 1 %).
        max_fraction: Return at most this share of the repeated positions (at least one).
    """
    return repeats_screening(x, y, level=level, max_fraction=max_fraction)[0]


def repeats_screening(
    x: np.ndarray, y: np.ndarray, *, level: float = LEVEL, max_fraction: float = MAX_FRACTION
) -> tuple[tuple[Spread, ...], bool]:
    """:func:`screen_repeats`, and whether it found more suspect positions than it
    returns (its cap)."""
    _check_level(level)
    rep = aggregate_repeats(x, y)
    y = np.asarray(y, dtype=float)
    ux, inverse, counts = rep.x, rep.inverse, rep.counts
    ss = np.bincount(inverse, weights=(y - rep.y[inverse]) ** 2, minlength=ux.size)
    groups = np.flatnonzero(counts > 1)
    if groups.size < 2:
        return (), False
    from scipy.stats import f as f_dist  # here: scipy.stats costs 0.24 s to load

    df = counts[groups] - 1.0
    ssg = ss[groups]
    pool = np.ones(groups.size, bool)
    cap = max(1, int(max_fraction * groups.size))
    rounds: list[Spread] = []
    suspect = 0  # rounds up to the last whose worst was suspect
    for _ in range(min(groups.size - 1, max(cap + 1, 2))):  # one more tells the cap
        df_rest = df[pool].sum() - df
        ss_rest = ssg[pool].sum() - ssg
        judged = pool & (df_rest > 0) & (ss_rest > 0)
        if not np.any(judged):
            break
        ratio2 = np.where(judged, (ssg / df) / np.where(judged, ss_rest / df_rest, 1.0), 0.0)
        p = np.where(judged, f_dist.sf(ratio2, df, np.maximum(df_rest, 1.0)), 1.0)
        worst = int(np.argmin(p))
        pool[worst] = False
        members = np.flatnonzero(inverse == groups[worst])
        rounds.append(
            Spread(
                members,
                float(ux[groups[worst]]),
                int(members[_farthest(y[members])]),
                float(np.sqrt(ratio2[worst])),
                float(p[worst]),
            )
        )
        # suspect at the level while every round before was; after a round that was
        # not, at a tenth of it: the pool has lost its widest spreads, so it is narrower
        # than the F test assumes (without the tenth, 1.27 % of 12 000 clean files of 6
        # shapes alarmed, not 1.21 %)
        strict = 1.0 if suspect == len(rounds) - 1 else _UNMASK
        if p[worst] < strict * level / groups.size:
            suspect = len(rounds)
    return tuple(rounds[: min(suspect, cap)]), suspect > cap


def _farthest(v: np.ndarray) -> int:
    """Index of the value of ``v`` (c,) farthest from the mean of the others."""
    others = (v.sum() - v) / (v.size - 1)
    return int(np.argmax(np.abs(v - others)))
