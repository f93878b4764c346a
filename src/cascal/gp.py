"""Gaussian-process regression of one calibration stage with known (dense) and learned noise.

The target covariance is ``K(theta) + N + noise_variance * I`` with ``N`` a known noise
(:mod:`cascal.noise`, dense for stage B of a cascade) and ``noise_variance`` learned or fixed.
:func:`fit_gp` maximises the log marginal likelihood (GPML eq. 2.30) over the
log-hyperparameters and returns a frozen :class:`FittedGP` whose predictions use stored
weights: O(M N) for the mean, O(M N^2) only when uncertainty is asked for.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import warnings
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import lapack, solve_triangular

from . import linalg, surrogate
from .errors import InputError, JitterWarning, NumericalError
from .kernels import Kernel, Periodic, Product, Sum, _Scaled, common_period, make_kernel
from .likelihood import Objective, noiseless, search_bounds, theta_names
from .means import Mean, make_mean
from .noise import Dense, Diagonal, Noise, as_noise
from .optimize import BOUND_TOL, OptimResult, _safe, maximize, newton_maximize
from .validation import (
    as_positions,
    as_readings,
    check_corrections,
    check_count,
    check_pair,
    check_scale,
    frozen,
)

__all__ = ["FittedGP", "Objective", "Posterior", "fit_gp", "log_marginal_likelihood"]

_LOG2PI = np.log(2.0 * np.pi)
#: Two-sided 95 % quantile of the normal distribution, for bands and error bars.
Z95 = 1.959963984540054
#: Cross-covariance entries per block of a prediction: small blocks stay in cache and avoid
#: the page faults of large fresh allocations (10x faster for 2000 x 100).
_BLOCK = 32768
#: A fit started from a likelihood table looks this far (log length scale) to both sides of
#: its optimum: a higher value there starts another run (two maxima closer than the table
#: resolves, e.g. 0.2 apart with a 0.04-nat dip, in a study fit).
PROBE = 0.2
_BLAS: list = []
#: Matrix entries (readings x points) up to which OpenBLAS computes a prediction on one
#: thread anyway (its products and solves thread from 9216 entries): no limit entered.
_ONE_THREAD = 8192
#: A learned noise (with no known noise) that ends at its lower bound (1e-10 of the signal
#: variance, or of the corrections' variance where that is not profiled) is searched again
#: with the bound this many times lower: readings of nanometre noise on millimetre errors
#: want a noise about 1e-12 of the signal variance.
NOISE_FLOOR_DROP = 1e3
#: Log marginal likelihood (nats) that the run below the first floor must gain to count as
#: estimating the noise there (a rotary case: 68; 3 or 5 readings on a smooth map: below
#: 1e-6, a likelihood flat in the noise).
NOISE_FLOOR_GAIN = 0.1
#: Points of each subset whose optima start the fit of a stage too large for a likelihood
#: table (over ``2 * SUBSET`` points), see :func:`_subset_starts`; on an equally spaced
#: grid the subsets use the cached eigenbases of :mod:`cascal.surrogate` (up to 160 points).
SUBSET = surrogate.MAX_POINTS
#: A part of a sum whose log variance lies this far below the other part's is (almost)
#: off: :func:`_mirror_runs` starts runs with it switched on.
WEAK = 5.0
#: Subset optima closer than this (log units, every parameter) are one candidate.
_DISTINCT = 0.05
#: Runs of a large stage start this far apart at least (log units): in length scale (the
#: first parameter), or in another parameter. Closer optima of different subsets are one
#: basin on all readings (their runs ended at the same optimum in bench_large).
_DIVERSE = (0.5, 3.0)

#: Set by :func:`pin_blas`: BLAS stays single-threaded, so the context has nothing to do.
_PINNED: list[bool] = []


def single_threaded_blas():
    """Context limiting BLAS to one thread: small GP matrices run faster and bit-reproducibly.
    In a pinned process (:func:`pin_blas`) it does nothing (entering a limit costs 10 us)."""
    if _PINNED:
        return contextlib.nullcontext()
    if not _BLAS:
        from threadpoolctl import ThreadpoolController

        _BLAS.append(ThreadpoolController())
    return _BLAS[0].limit(limits=1, user_api="blas")


def pin_blas() -> None:
    """Limit BLAS to one thread for the rest of this process (a study's worker process).

    threadpoolctl lets one thread at a time set OpenBLAS's process-wide limit: when worker
    threads each enter and leave :func:`single_threaded_blas`, one leaving restores the
    limit while another still computes, and a triangular solve of 21 columns already
    rounds differently on two threads. Pinned, every thread computes single-threaded."""
    if not _PINNED:
        single_threaded_blas()  # set, never restored: this thread keeps control of the limit
        _PINNED.append(True)


@dataclass(frozen=True, slots=True)
class Posterior:
    """Posterior of the latent map at some positions: mean (m,) and covariance (m, m)."""

    mean: np.ndarray
    cov: np.ndarray

    @property
    def std(self) -> np.ndarray:
        """Standard deviations, shape (m,)."""
        return np.sqrt(np.clip(np.diagonal(self.cov), 0.0, None))


def log_marginal_likelihood(
    x: object,
    y: object,
    *,
    kernel: Kernel,
    mean: str | float | Mean = "identity",
    noise: float | np.ndarray | Noise | None = None,
    noise_variance: float = 0.0,
    eval_gradient: bool = False,
) -> float | tuple[float, np.ndarray]:
    """log p(y | x) of a GP (GPML eq. 2.30 with the target covariance in place of s^2 I).

    Args:
        x: Positions, shape (n,).
        y: Targets, shape (n,), same unit.
        kernel: Kernel with its hyperparameters.
        mean: Prior mean (see :func:`cascal.means.make_mean`).
        noise: Known noise: number, (n,), (n, n) or a :class:`~cascal.noise.Noise`.
        noise_variance: Learned white-noise variance added on top.
        eval_gradient: Also return d lml / d [kernel.theta, log noise_variance]: shape
            (p+1,), or (p,) when ``noise_variance`` is 0 (then it is not a parameter).

    Warns:
        JitterWarning: The target covariance needed jitter on its diagonal to factorise;
            the value is then the jittered matrix's (as a fit with these hyperparameters
            records in ``FittedGP.jitter``).
    """
    xa, ya = check_pair(x, y)
    if not isinstance(kernel, Kernel):
        raise InputError(
            "kernel: expected a Kernel with its hyperparameters, e.g. "
            f"cascal.SquaredExp(0.2, 1e-4), got {kernel!r}"
        )
    if not (isinstance(noise_variance, numbers.Real) and 0.0 <= noise_variance < math.inf):
        raise InputError(f"noise_variance: expected a finite number >= 0, got {noise_variance!r}")
    m = make_mean(mean, ya, xa)
    known = as_noise(noise, len(xa))
    learned = noise_variance > 0.0  # (with none, the round-off checks of a noiseless fit)
    obj = Objective(xa, ya - m(xa), kernel, known, learn_noise=learned)
    theta = np.r_[kernel.theta, np.log(noise_variance)] if learned else kernel.theta
    v, g = obj.value_and_grad(theta, grad=eval_gradient)
    if obj.jitter:
        _warn_jitter(obj.jitter, "the value is the jittered matrix's")
    return (v, g) if eval_gradient else v


def _warn_jitter(jitter: float, what: str) -> None:
    """Warn (:class:`JitterWarning`, at the caller's caller) that given hyperparameters'
    target covariance needed ``jitter`` on its diagonal; ``what`` says what it changed."""
    warnings.warn(
        f"the target covariance needed jitter {jitter:.3g} on its diagonal to factorise "
        f"(not positive definite to round-off): {what}; more noise_variance, or a shorter "
        "length scale, avoids it",
        JitterWarning,
        stacklevel=3,
    )


@dataclass(frozen=True, slots=True)
class FittedGP:
    """A fitted stage: training data, hyperparameters and the stored Cholesky factor.

    Attributes:
        x: Training positions, shape (n,).
        y: Training targets, shape (n,).
        kernel: Kernel at the fitted hyperparameters.
        mean: Prior mean.
        noise: Known noise (or None).
        noise_variance: Learned (or fixed) white-noise variance, target unit squared.
        L: Lower Cholesky factor of the target covariance, shape (n, n).
        alpha: Weights ``Kt^-1 (y - m(x))``, shape (n,).
        jitter: Jitter added to the target covariance's diagonal (0.0 if none).
        log_marginal_likelihood: At the fitted hyperparameters.
        optimization: Per-start diagnostics, or None when hyperparameters were given.
    """

    x: np.ndarray
    y: np.ndarray
    kernel: Kernel
    mean: Mean
    noise: Noise | None
    noise_variance: float
    L: np.ndarray
    alpha: np.ndarray
    jitter: float
    log_marginal_likelihood: float
    optimization: OptimResult | None = None

    def __post_init__(self) -> None:
        for name in ("x", "y", "L", "alpha"):
            object.__setattr__(self, name, frozen(getattr(self, name)))

    @property
    def hyperparameters(self) -> dict[str, float]:
        """Kernel hyperparameters by name plus ``noise_variance``, natural units."""
        hp = dict(self.kernel.params)
        if isinstance(self.kernel, Periodic):
            hp["period"] = self.kernel.period
        hp["noise_variance"] = self.noise_variance
        return hp

    def predict(
        self, x: object, return_std: bool = False, return_cov: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Posterior of the latent map at ``x`` (m,) (GPML Alg. 2.1, lines 4-6).

        Returns:
            mean (m,); with ``return_std`` also the standard deviation (m,); with
            ``return_cov`` the covariance (m, m) instead. Same unit as the targets. For
            one number ``x``, numbers: the mean, the standard deviation or the variance.
        """
        if return_std and return_cov:
            raise InputError("predict: ask for return_std or return_cov, not both")
        xs, scalar = as_readings(x, "x")
        with np.errstate(over="ignore"):  # a reading 1e154 away: (d / l)^2 is inf, k is 0
            if xs.size * self.x.size <= _ONE_THREAD:  # (the limit's 10 us would dominate)
                out = self._predict(xs, return_std, return_cov)
            else:
                with single_threaded_blas():  # the same numbers whatever BLAS's threads
                    out = self._predict(xs, return_std, return_cov)
        if not scalar:
            return out
        if return_cov:
            return out[0][0], out[1][0, 0]
        return (out[0][0], out[1][0]) if return_std else out[0]

    def _predict(
        self, xs: np.ndarray, return_std: bool, return_cov: bool
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        ks = self._turn(xs)  # the kernel's argument; the prior mean's stays xs
        if return_cov:
            Ks = self.kernel(ks, self.x)
            V = solve_triangular(self.L, Ks.T, lower=True, check_finite=False)
            cov = self.kernel(ks) - V.T @ V
            return self.mean(xs) + Ks @ self.alpha, 0.5 * (cov + cov.T)
        mean = np.empty(xs.shape)
        std = np.empty(xs.shape) if return_std else None
        rows = max(64, _BLOCK // max(self.x.size, 1))
        for s in range(0, xs.size, rows):
            part = xs[s : s + rows]
            Ks = self.kernel(ks[s : s + rows], self.x)
            mean[s : s + rows] = self.mean(part) + Ks @ self.alpha
            if std is not None:
                V = solve_triangular(self.L, Ks.T, lower=True, check_finite=False)
                var = self.kernel.diag(part) - np.einsum("ij,ij->j", V, V)
                std[s : s + rows] = np.sqrt(np.clip(var, 0.0, None))
        return (mean, std) if std is not None else mean

    def _turn(self, x: np.ndarray) -> np.ndarray:
        """``x`` (m,) with a periodic kernel's positions beyond the data's turn moved into
        it by whole periods, else ``x`` itself: the kernel is the same there, and a
        position many turns away would lose digits in it (1e9 turns away, u came out 0)."""
        p = common_period(self.kernel)  # (periodic kernels with constants repeat too)
        if p is None or not x.size:
            return x
        lo = float(self.x.min())
        away = (x < lo) | (x >= lo + p)
        return np.where(away, lo + np.mod(x - lo, p), x) if away.any() else x

    def whitened(self, x: np.ndarray) -> np.ndarray:
        """``L^-1 k(X, x)`` (n, m) for positions ``x`` (m,): posterior covariances are
        ``k(a, b) - V_a^T V_b``, and ``L^-T V`` are the targets' weights in the mean."""
        k = self.kernel(self.x, self._turn(x))
        return solve_triangular(self.L, k, lower=True, check_finite=False)

    def cross_covariance(self, a: object, b: object) -> np.ndarray:
        """Posterior covariance (m, p) of the latent map between positions ``a`` (m,) and
        ``b`` (p,): ``k(a, b) - k(a, X) (K + noise)^-1 k(X, b)``."""
        xa, xb = as_readings(a, "a")[0], as_readings(b, "b")[0]  # (numbers: m or p = 1)
        k = self.kernel(self._turn(xa), self._turn(xb))
        return k - self.whitened(xa).T @ self.whitened(xb)

    def posterior(self, x: object) -> Posterior:
        """Posterior mean (m,) and full covariance (m, m) of the latent map at ``x`` (one
        number: m = 1)."""
        mean, cov = self.predict(as_readings(x, "x")[0], return_cov=True)
        return Posterior(mean, cov)

    def posterior_factor(self, x: object) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean (m,) at ``x`` and a factor ``U`` (m, k) whose ``U U^T`` is the
        posterior covariance (m, m), positive semi-definite by construction.

        ``U`` is the pivoted Cholesky factor (LAPACK ``dpstrf``) of ``K** - V^T V``, stopped
        where every remaining pivot is below eps times the largest prior variance: k is the
        covariance's numerical rank (13 to 28 at the paper's 100 device points in 100 study
        trials, squared exponential; up to m for rough kernels), and what is dropped (the
        round-off negative eigenvalues among it) is within that formula's own round-off.
        O(m^2 k) on top of ``predict(x, return_cov=True)``, instead of an O(m^3)
        eigendecomposition.
        """
        xs = as_readings(x, "x")[0]
        mean, cov = self.predict(xs, return_cov=True)
        tol = np.finfo(float).eps * float(np.max(self.kernel.diag(xs), initial=0.0))
        c, piv, k, _ = lapack.dpstrf(cov, lower=1, tol=tol, overwrite_a=1)
        U = np.empty((xs.size, k))
        U[piv - 1] = np.tril(c[:, :k])  # rows back in input order
        return mean, U

    @classmethod
    def from_arrays(
        cls,
        x: object,
        y: object,
        *,
        kernel: Kernel,
        mean: Mean,
        noise: Noise | None,
        noise_variance: float,
        L: object,
        alpha: object,
        jitter: float = 0.0,
        log_marginal_likelihood: float = float("nan"),
        optimization: OptimResult | None = None,
    ) -> FittedGP:
        """Rebuild a fitted GP from stored arrays (a model file), checking their shapes.

        Predictions use ``L`` and ``alpha`` as given, so they equal the original's exactly.

        Args:
            x, y: Training positions and targets, shape (n,).
            L: Lower Cholesky factor of the target covariance, shape (n, n).
            alpha: Weights, shape (n,).

        Raises:
            InputError: Mismatched shapes, non-finite values, or an ``L`` that is not lower
                triangular with a positive diagonal.
        """
        xa, ya = check_pair(x, y, ("x", "y"), min_points=1)
        n = xa.size
        La = np.array(L, dtype=float)
        al = as_positions(alpha, "alpha")
        if La.shape != (n, n) or al.shape != (n,):
            raise InputError(f"expected L ({n}, {n}) and alpha ({n},), got {La.shape}, {al.shape}")
        if not np.all(np.isfinite(La)) or np.any(np.triu(La, 1)) or np.any(np.diagonal(La) <= 0):
            raise InputError("L: expected a finite lower-triangular matrix, positive diagonal")
        if not (np.isfinite(noise_variance) and noise_variance >= 0):
            raise InputError(f"noise_variance: expected >= 0, got {noise_variance!r}")
        if noise is not None:
            noise.diagonal(n)  # validates the size
        return cls(
            xa, ya, kernel, mean, noise, float(noise_variance), La, al, float(jitter),
            float(log_marginal_likelihood), optimization,
        )  # fmt: skip


def fit_gp(
    x: object,
    y: object,
    *,
    kernel: str | Kernel = "se",
    mean: str | float | Mean = "identity",
    noise: float | np.ndarray | Noise | None = None,
    learn_noise: bool | None = None,
    hyperparameters: dict[str, float] | None = None,
    n_restarts: int = 5,
    seed: int | np.random.SeedSequence | np.random.Generator | None = 0,
    period: float | None = None,
    bounds: dict[str, tuple[float, float]] | None = None,
    names: tuple[str, str] = ("x", "y"),
) -> FittedGP:
    """Fit a GP to one stage: readings ``x`` (n,) mapped to more accurate readings ``y`` (n,).

    Args:
        x: Readings of the sensor being calibrated, shape (n,).
        y: Readings of the more accurate sensor, shape (n,), same unit.
        kernel: ``"se"``, ``"matern32"``, ``"matern52"``, ``"periodic"`` or a Kernel.
        mean: ``"identity"`` (default), ``"offset"`` (identity plus the targets' mean
            offset from it), ``"zero"``, ``"constant"`` or a number. Rotary readings that
            wrapped past the period (0.2 beside 359.9) are taken as given: unwrap them
            first (:func:`cascal.validation.unwrap`), as the command line does; the
            periodic kernel also serves linear axes (a lead screw's pitch error), where
            nothing wraps.
        noise: None (learn a scalar variance), a number or (n,) vector (known variances),
            an (n, n) covariance (known, plus a learned scalar), or a Noise.
        learn_noise: Learn a white-noise variance (one, for all readings) on top of
            ``noise``; default: learn it unless ``noise`` is a number or a vector, except a
            vector with zeros, as :func:`~cascal.validation.aggregate_repeats` gives (0 for
            a position read once, so all zeros where none repeats): its zeros say nothing of
            those readings' noise. ``noise=0`` (a number), or a vector with
            ``learn_noise=False``, interpolates exactly. With a learned noise, a position
            read twice with the same correction and no known noise is refused: average
            repeats first.
        hyperparameters: Given values by name (``length_scale``, ``variance``,
            ``noise_variance``, ...); nothing is optimised. A
            :class:`~cascal.errors.JitterWarning` says where their target covariance
            needed jitter to factorise (as :func:`log_marginal_likelihood` does).
        n_restarts: Local optimiser starts: the best local maxima of a likelihood table
            (SE, Matern and periodic kernels, :mod:`cascal.surrogate`), or for a stage of
            over ``2 * SUBSET`` points without one the best optima of its subsets, at most
            this many, then one more run wherever the likelihood is higher 0.2 (log) to
            either side of the best optimum's length scale (:data:`PROBE`); else exactly
            this many, after screening seeded random candidates.
        seed: Seed, SeedSequence or Generator for screened starts (unused where a table
            gives the starts; a large stage's subsets screen with it where they have none).
        period: Period of the ``"periodic"`` kernel, in the unit of ``x``.
        bounds: Optimisation bounds by hyperparameter name, natural units.
        names: Names of ``x`` and ``y`` in error messages.
    """
    with single_threaded_blas():
        gp = _fit_gp(
            x,
            y,
            kernel,
            mean,
            noise,
            learn_noise,
            hyperparameters,
            n_restarts,
            seed,
            period,
            bounds,
            names,
        )
    if hyperparameters is not None and gp.jitter:  # (as log_marginal_likelihood warns)
        _warn_jitter(gp.jitter, "the fit is the jittered matrix's (FittedGP.jitter)")
    return gp


def refit(x: np.ndarray, y: np.ndarray, gp: FittedGP, hyperparameters: dict, noise) -> FittedGP:
    """``gp``'s stage on readings ``x`` (n,) and targets ``y`` (n,) (a subset, say) with
    its kernel and mean and the given ``hyperparameters`` and known ``noise``: cascal's own
    refits (outlier screening's), which warn of no jitter the user did not choose (a
    review: screening had warned, naming settings the user never gave)."""
    with single_threaded_blas():
        return _fit_gp(
            x,
            y,
            gp.kernel,
            gp.mean,
            noise,
            hyperparameters.get("noise_variance", 0.0) > 0,
            hyperparameters,
            1,
            0,
            None,
            None,
            ("x", "y"),
        )


def _fit_gp(
    x, y, kernel, mean, noise, learn_noise, hyperparameters, n_restarts, seed, period, bounds, names
) -> FittedGP:
    if not (isinstance(names, tuple | list) and len(names) == 2):  # (a review: "x" failed)
        raise InputError(f"names: expected two names (of x and y), got {names!r}")
    names = (str(names[0]), str(names[1]))
    xa, ya = check_pair(x, y, names)
    check_scale(xa, ya, names)
    n = xa.size
    check_count(n_restarts, "n_restarts", "optimiser starts", 1)
    if not (seed is None or isinstance(seed, np.random.SeedSequence | np.random.Generator)):
        if not (isinstance(seed, numbers.Integral) and seed >= 0):  # (also where unused)
            raise InputError(f"seed: expected a whole number >= 0, got {seed!r}")
    kern = make_kernel(kernel, period=period)
    m = make_mean(mean, ya, xa)
    known = as_noise(noise, n)
    if learn_noise is None:
        # zeros among the variances (aggregate_repeats gives 0 to a position read once, and
        # to every position where none repeats) say nothing of those readings' noise:
        # learn one white noise for all; noise=0, a number, interpolates exactly, and so do
        # given hyperparameters without a noise_variance
        number = np.ndim(noise) == 0 and not isinstance(noise, Noise)
        unknown = hyperparameters is None or "noise_variance" in hyperparameters
        learn_noise = (
            known is None
            or not known.is_diagonal
            or (not number and unknown and bool(np.any(known.diagonal(n) == 0.0)))
        )
    if known is None and not learn_noise:
        raise InputError("noise: with learn_noise=False a known noise must be given")
    r = ya - m(xa)
    if hyperparameters is None:
        check_corrections(r, names[1], m.name)
    if learn_noise and hyperparameters is None:
        _check_no_exact_repeats(xa, r, known, names, kern)
    if hyperparameters is None and not np.any(r) and known is None:
        raise InputError(
            f"{names[1]}: every target equals the prior mean ({m.name}) exactly, so the data "
            "show no correction to learn; give hyperparameters or check the columns"
        )
    optimization = None
    if hyperparameters is not None:
        kern, sn2 = _from_dict(kern, hyperparameters, learn_noise)
    else:
        # The kernel variance is profiled out unless the user bounds it or the noise.
        bounded = {"variance", "noise_variance"} & set(bounds or {})
        profile = isinstance(kern, _Scaled) and known is None and learn_noise and not bounded
        obj = Objective(xa, r, kern, known, learn_noise, profile=profile)
        b = obj.bounds(bounds)
        optimization = _search(obj, b, n_restarts, seed, tabulate=not bounded)
        if known is None and learn_noise and "noise_variance" not in (bounds or {}):
            optimization = _below_noise_floor(obj, b, optimization)
        if not bounded:
            optimization = _mirror_runs(obj, optimization)
        theta = obj.full_theta(optimization.theta)
        p = kern.n_params
        kern = kern.with_theta(theta[:p])
        sn2 = float(np.exp(theta[p])) if learn_noise else 0.0
        factor = obj.factor_at(optimization.theta)
        return _condition(xa, ya, kern, m, known, sn2, optimization, factor)
    return _condition(xa, ya, kern, m, known, sn2, optimization)


def _search(
    obj: Objective, b: np.ndarray, n_restarts: int, seed, tabulate: bool, fill: bool = True
) -> OptimResult:
    """Maximise ``obj`` over the log bounds ``b`` (dim, 2): Newton runs from the best local
    maxima of a likelihood table where one applies (``tabulate``: no user bounds on the
    variances; with a dense known noise off the grid, the table without it and screened
    candidates, :func:`_white_starts`), else, for a stage of over ``2 * SUBSET`` points,
    from the optima of its subsets (:func:`_subset_starts`; their ranking's values count as
    candidates), else from screened random candidates. ``fill`` (the top level, not a
    subset): screen beside the table without the known noise and, with a dense known noise
    off the grid, run once more from a short length scale (:func:`_short_start`; for a
    large stage, from its windows' optima of such runs): :func:`_extra_runs`."""
    starts = None
    known = obj.known
    if obj.profile:
        starts = surrogate.profiled_starts(obj.kernel, obj.x, obj.r, b, n_restarts)
    elif known is not None and not known.is_diagonal and obj.learn_noise and tabulate:
        starts = surrogate.dense_starts(
            obj.kernel, obj.x, obj.r, known.factor(obj.n), b, n_restarts
        )
    ranked, screen, extra = 0, False, []
    off_grid = starts is None and known is not None and not known.is_diagonal
    if off_grid:
        starts = _white_starts(obj, b, n_restarts, tabulate)
        screen = fill and starts is not None
    if starts is None and obj.n > 2 * SUBSET:
        starts, ranked, extra = _subset_starts(obj, b, n_restarts, seed, tabulate)
    found = maximize(
        obj.value,
        obj.value_and_grad,
        b,
        n_restarts=n_restarts,
        rng=None if starts and not screen else np.random.default_rng(seed),
        value_grad_hess=obj.value_and_derivatives if obj.has_hessian else None,
        starts=starts,
        probes=_probes(obj.dim) if starts else None,
        names=obj.names,
        fill=screen,
    )
    if off_grid and fill and not ranked:  # (a large stage's windows made such runs)
        extra = _short_starts(obj, b, found.theta)
    if fill and tabulate and not ranked:
        extra = extra + _component_starts(obj, b, n_restarts, seed)
    if extra:
        found = _extra_runs(obj, b, found, extra)
    return replace(found, n_candidates=found.n_candidates + ranked) if ranked else found


def _length_scales(x: np.ndarray) -> tuple[float, float] | None:
    """Log length scales of starts at positions ``x`` (n,): short (e^-1 of the median
    spacing: too short to correlate neighbours) and long (the range); None where all
    positions are equal."""
    gaps = np.diff(np.sort(x))
    gaps = gaps[gaps > 0]
    if not gaps.size:
        return None
    return float(np.log(np.median(gaps))) - 1.0, float(np.log(gaps.sum()))


def _component_starts(obj: Objective, b: np.ndarray, n_restarts: int, seed) -> list[np.ndarray]:
    """Starts for a sum or product of two scaled kernels (SE, Matern, periodic) from each
    part fitted alone (its own search, the known noise and learned noise as given):

    * a sum: the other part small, its variance at that fit's noise (without a learned
      noise, 3 log units below the part's variance) and its length scale short (e^-1 of
      the median spacing) or long (the range), the noise 3 log units lower. The screened
      search alone ended 0.29 nats low on a review's 20 readings of an SE + Matern 3/2 map
      (1.7 for another seed), reading the short part as noise; with a known noise, 1.0
      to 14.0 nats low in another review's generated sets;
    * a product: where the part alone ended, the other part flat (its length scale at
      its upper bound); the fit's variance goes to the first part (in the target's unit),
      1 to the second (a factor). Screened starts alone ended below a 60-start L-BFGS-B
      for 18 of 56 generated sets (by up to 27.9 nats: SE x SE, 20 micrometre readings).

    Inside ``b``; empty for other kernels."""
    kern = obj.kernel
    parts = (getattr(kern, "left", None), getattr(kern, "right", None))
    if not (
        isinstance(kern, Sum | Product) and all(isinstance(k, _Scaled) for k in parts) and obj.n > 2
    ):
        return []
    lengths = _length_scales(obj.x)
    if lengths is None:
        return []
    learn = obj.learn_noise
    profile = obj.known is None and learn
    out = []
    for i, part in enumerate(parts):
        alone = Objective(obj.x, obj.r, part.unit(1.0), obj.known, learn, profile=profile)
        try:
            fit = _search(alone, alone.bounds(), n_restarts, seed, tabulate=True, fill=False)
        except NumericalError:
            continue
        ls, var, *rest = alone.full_theta(fit.theta)
        noise = rest[0] if learn else var - 3.0  # (the other part's variance, in a sum)
        tail = [noise] if learn else []
        if isinstance(kern, Product):  # theta: [ls1, var1 (the unit), ls2, var2 (a factor)]
            flat = b[2 - 2 * i, 1]
            pair = ([ls, var], [flat, 0.0]) if i == 0 else ([flat, var], [ls, 0.0])
            out.append(np.clip(np.array([*pair[0], *pair[1], *tail]), b[:, 0], b[:, 1]))
            continue
        for other in lengths:
            pair = ([ls, var], [other, noise]) if i == 0 else ([other, noise], [ls, var])
            t0 = np.array([*pair[0], *pair[1], *(t - 3.0 for t in tail)])
            out.append(np.clip(t0, b[:, 0], b[:, 1]))
    return out


def _mirror_runs(obj: Objective, found: OptimResult) -> OptimResult:
    """``found`` (the search's result, in its own bounds), or for a sum of two scaled
    stationary kernels (SE, Matern; not periodic) the better optimum of Newton runs from
    ``found``'s optimum changed so:

    * the two parts' parameters exchanged: a review's sums (SE + Matern 3/2, Matern 5/2 +
      3/2; 20 and 40 readings of a drift and a ripple) ended 1.6 and 2.5 nats below a
      30-start L-BFGS-B at the mirror image of its optimum, each part in the other's role;
    * a part :data:`WEAK` log units below the other switched on, at a short (e^-1 of the
      median spacing) and a long length scale (the range), its variance e^-1 of the
      other's, and that start mirrored: with a part switched off, the fits of such data
      ended up to 1.4 nats low (a part at its variance floor barely moves its length scale);
    * each part at the short length scale, with its own variance and with the learned
      noise's (the noise then 3 log units lower): a kernel too short to correlate
      neighbours, reading white noise or more (the same review: 160 readings, 0.77 nats;
      0.11 nats on 30 readings, where the run had stopped on a ridge of the noise).

    Made after the noise floor's run (:func:`_below_noise_floor`), which thus starts where
    it did; never lower than ``found``."""
    kern = obj.kernel
    parts = (getattr(kern, "left", None), getattr(kern, "right", None))
    if not (
        isinstance(kern, Sum)
        and all(isinstance(k, _Scaled) and not isinstance(k, Periodic) for k in parts)
        and obj.n > 2
    ):
        return found
    lengths = _length_scales(obj.x)
    if lengths is None:
        return found
    short = lengths[0]
    b = found.bounds
    theta = np.asarray(found.theta, dtype=float)

    def mirrored(t: np.ndarray) -> np.ndarray:
        return np.concatenate([t[2:4], t[0:2], t[4:]])

    starts = [mirrored(theta)]
    for i, j in ((0, 2), (2, 0)):
        if theta[i + 1] < theta[j + 1] - WEAK:  # part i (almost) off: switch it on
            for ls in lengths:
                t0 = theta.copy()
                t0[i : i + 2] = ls, theta[j + 1] - 1.0
                starts += [t0, mirrored(t0)]
        t0 = theta.copy()
        t0[i] = short
        starts.append(t0)
        if obj.learn_noise:
            t0 = theta.copy()
            t0[i : i + 2] = short, theta[-1]
            t0[-1] -= 3.0
            starts.append(t0)
    return _extra_runs(obj, b, found, [np.clip(t, b[:, 0], b[:, 1]) for t in starts])


def _short_start(obj: Objective, b: np.ndarray, theta: np.ndarray) -> np.ndarray | None:
    """With a strong, correlated known noise off the grid, an optimum can read the white
    noise as a kernel too short to correlate neighbours, where neither table nor screening
    starts (0.02 to 0.36 nats missed in a review's cases of 250 to 700 readings, 17.6 in a
    generated one). A start there: the length scale e^-1 of the median spacing, the
    variance at the learned noise of ``theta`` (an optimum) and that noise 10 log units
    lower (without learned noise, ``theta``'s variance), inside ``b``. None for kernels
    other than the stationary scaled ones (periodic excluded) or a single position."""
    kern = obj.kernel
    if not isinstance(kern, _Scaled) or isinstance(kern, Periodic):
        return None
    lengths = _length_scales(obj.x)
    if lengths is None:
        return None
    t0 = np.array(theta, dtype=float)
    t0[0] = lengths[0]
    if obj.learn_noise:
        t0[1:] = theta[2], theta[2] - 10.0
    return np.minimum(np.maximum(t0, b[:, 0]), b[:, 1])


def _short_starts(obj: Objective, b: np.ndarray, theta: np.ndarray) -> list[np.ndarray]:
    """:func:`_short_start`, and with a learned noise a second start that splits the white
    noise of ``theta`` between the short kernel (half its variance) and the noise (2 log
    units lower): on a review's 20 readings with a stage-A-like known noise the first
    alone ended 0.41 nats low for one seed of three (all noise: a variance at its bound)."""
    t0 = _short_start(obj, b, theta)
    if t0 is None:
        return []
    if not obj.learn_noise:
        return [t0]
    t1 = t0.copy()
    t1[1:] = theta[2] + math.log(0.5), theta[2] - 2.0
    return [t0, np.minimum(np.maximum(t1, b[:, 0]), b[:, 1])]


def _extra_runs(
    obj: Objective, b: np.ndarray, found: OptimResult, t0s: list[np.ndarray]
) -> OptimResult:
    """``found`` with Newton runs from ``t0s`` and probes about their best (a second
    :func:`maximize`, stopping at ``found``'s optima); that best replaces ``found``'s where
    it is higher (never lower: the search before is kept as it was, its probes included)."""
    try:
        more = maximize(
            obj.value,
            obj.value_and_grad,
            b,
            n_restarts=len(t0s),
            rng=None,
            value_grad_hess=obj.value_and_derivatives if obj.has_hessian else None,
            starts=t0s,
            probes=_probes(obj.dim),
            known=found.starts,
        )
    except NumericalError:  # no run reached a finite value
        more = None
    if more is not None:
        found = replace(
            found, starts=found.starts + more.starts, n_probes=found.n_probes + more.n_probes
        )
        if more.value > found.value:
            return replace(found, theta=more.theta, value=more.value)
    # the latest evaluation again: its factor is kept
    (obj.value_and_derivatives if obj.has_hessian else obj.value_and_grad)(found.theta)
    return found


def _white_starts(
    obj: Objective, b: np.ndarray, n_restarts: int, tabulate: bool
) -> list[np.ndarray] | None:
    """Starts ``[kernel theta, log noise_variance]`` for an objective with a known dense
    noise off the grid (learned noise, no user bounds on the variances): the local maxima
    of the profiled table without that noise, or None where no table applies. At the top
    level :func:`_search` fills the remaining runs from screened candidates (a strong,
    correlated known noise can move the optimum away from every maximum of that table:
    3.5 nats in a review's case); a large stage's subsets, whose optima are ranked on all
    readings, use the table's maxima alone."""
    if not (isinstance(obj.kernel, _Scaled) and obj.learn_noise and tabulate):
        return None
    white = Objective(obj.x, obj.r, obj.kernel, None, True, profile=True)
    wb = white.bounds()
    wb[0] = b[0]  # the length scale's bounds as given
    found = surrogate.profiled_starts(obj.kernel, obj.x, obj.r, wb, n_restarts)
    return None if found is None else [white.full_theta(t) for t in found]


def _subset_starts(
    obj: Objective, b: np.ndarray, n_restarts: int, seed, tabulate: bool
) -> tuple[list[np.ndarray] | None, int, list[np.ndarray]]:
    """Starts for a large stage from the optima of the same search on subsets of ``SUBSET``
    readings: one spread evenly over the range (it sees the long length scales) and windows
    of neighbouring readings tiling the range (each sees the short ones where it lies, down
    to the spacing there). The subsets' optima are ranked by the full objective's value at
    them; the best, :data:`_DIVERSE` apart, at most ``n_restarts``, start the
    runs (None where no subset gives one: then the caller screens). Also the number of
    values on all readings (the rankings'), and with a dense known noise the starts of
    extra runs after the search: the optima of the windows' runs from
    :func:`_short_start`, ranked alike, as many as the runs left up to ``n_restarts`` (at
    least one)."""
    n = obj.n
    # a periodic kernel's windows gather neighbours in phase (turns interleave there: a
    # window of neighbouring angles holds one turn, too coarse for a high harmonic)
    periodic = isinstance(obj.kernel, Periodic)
    order = np.argsort(obj.x % obj.kernel.period if periodic else obj.x, kind="stable")  # type: ignore[attr-defined]
    subsets = [order[np.round(np.linspace(0.0, n - 1.0, SUBSET)).astype(np.intp)]]
    firsts = np.round(np.linspace(0.0, n - SUBSET, math.ceil(n / SUBSET))).astype(np.intp)
    subsets += [order[a : a + SUBSET] for a in firsts.tolist()]
    dense = obj.known is not None and not obj.known.is_diagonal
    found: list[np.ndarray] = []
    shorts: list[np.ndarray] = []
    for k, idx in enumerate(subsets):
        known = None if obj.known is None else _restrict(obj.known, idx, n)
        sub = Objective(obj.x[idx], obj.r[idx], obj.kernel, known, obj.learn_noise, obj.profile)
        try:  # e.g. readings equal to the prior mean throughout the subset: no optimum
            best = _search(sub, b, n_restarts, seed, tabulate, fill=False)
        except NumericalError:
            continue
        for s in best.starts:
            if np.isfinite(s.value) and all(np.max(np.abs(s.theta - t)) > _DISTINCT for t in found):
                found.append(s.theta)
        t0 = _short_start(sub, b, best.theta) if dense and k > 0 else None  # (the windows)
        run = None if t0 is None else newton_maximize(sub.value_and_derivatives, t0, b)
        if run is not None and np.isfinite(run.value) and all(_apart(run.theta, t) for t in shorts):
            shorts.append(run.theta)
    starts = _ranked(obj, found, n_restarts)
    if not starts:  # (the caller screens; the short runs' optima are no starts alone)
        return None, len(found), []
    shorts = [t for t in shorts if all(_apart(t, u) for u in starts)]
    return starts, len(found) + len(shorts), _ranked(obj, shorts, max(n_restarts - len(starts), 1))


def _ranked(obj: Objective, thetas: list[np.ndarray], m: int) -> list[np.ndarray]:
    """The best of ``thetas`` by ``obj``'s value, :data:`_DIVERSE` apart, at most m."""
    values = np.array([_safe(obj.value, t) for t in thetas])
    out: list[np.ndarray] = []
    for i in np.argsort(-values, kind="stable").tolist():
        if len(out) == m or not np.isfinite(values[i]):
            break
        if all(_apart(thetas[i], t) for t in out):
            out.append(thetas[i])
    return out


def _apart(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two starts are :data:`_DIVERSE` apart."""
    return abs(a[0] - b[0]) >= _DIVERSE[0] or bool(np.max(np.abs(a[1:] - b[1:])) >= _DIVERSE[1])


def _restrict(noise: Noise, idx: np.ndarray, n: int) -> Noise:
    """``noise`` of n points at the points ``idx`` (diagonal noise stays diagonal)."""
    if noise.is_diagonal:
        return Diagonal(noise.diagonal(n)[idx])
    return Dense(noise.dense(n)[np.ix_(idx, idx)], atol=np.inf)


def _check_no_exact_repeats(
    x: np.ndarray, r: np.ndarray, known: Noise | None, names: tuple[str, str], kern: Kernel
) -> None:
    """Refuse a position read twice with the same correction ``r`` and no known noise at
    either reading (contradicting targets are refused before): the learned noise's
    likelihood then grows without bound as that noise goes to 0, and the fit reads the
    noise as signal (a review: 12 readings with one pair repeated ended with u 10 times
    below the error). For a periodic kernel (:func:`cascal.kernels.common_period`: with
    constants too), readings a whole number of periods apart (to round-off) are the same
    position. ``x``, ``r``: shape (n,)."""
    period = common_period(kern)
    key = x if period is None else np.mod(x, period)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    if period is None:
        pairs = np.stack([order[:-1], order[1:]], axis=1)[ks[1:] == ks[:-1]]
        same = pairs[r[pairs[:, 0]] == r[pairs[:, 1]]]
    else:  # neighbours in phase, the last and the first across the turn's end included;
        # a position and the correction then match to the round-off of x mod period, y - x
        tol = 8.0 * np.finfo(float).eps * max(float(np.max(np.abs(x))), period)
        gaps = np.append(np.diff(ks), ks[0] + period - ks[-1])
        pairs = np.stack([order, np.roll(order, -1)], axis=1)[gaps <= tol]
        same = pairs[np.abs(r[pairs[:, 0]] - r[pairs[:, 1]]) <= tol]
    if not same.size:
        return
    var = np.zeros(x.size) if known is None else known.diagonal(x.size)
    for pair in same:
        i, j = sorted(int(v) for v in pair)
        if i == j or var[i] != 0.0 or var[j] != 0.0:
            continue
        a, b = float(x[i]), float(x[j])
        fix = "keep one of them: to the periodic kernel they are one position"
        if a == b:
            where = f"the same position {a!r}"
            fix = (
                "average repeated readings (cascal.aggregate_repeats) so they become one "
                "point with a known noise variance"
            )
        elif abs(a - b) < 0.5 * (period or 0.0):
            where = f"positions {a!r} and {b!r}, the same to round-off,"
        else:
            where = f"positions {a!r} and {b!r}, whole periods apart,"
        raise InputError(
            f"{names[0]}: {where} at indices {i} and {j}, with the same correction and no "
            f"known noise: a learned noise would take the pair as noise-free; {fix}"
        )


def _below_floor(b: np.ndarray) -> np.ndarray:
    """Log bounds ``b`` (dim, 2) with the learned noise's (the last) lower bound
    :data:`NOISE_FLOOR_DROP` times lower: a copy."""
    wide = b.copy()
    wide[-1, 0] -= np.log(NOISE_FLOOR_DROP)
    return wide


def _below_noise_floor(obj: Objective, b: np.ndarray, found: OptimResult) -> OptimResult:
    """``found``, or where its learned noise (the last parameter) is at its lower bound, a
    run from there with that bound :data:`NOISE_FLOOR_DROP` times lower (never lower in
    value: it starts at ``found``'s optimum). Where that run gains less than
    :data:`NOISE_FLOOR_GAIN`, the data do not tell a smaller noise (3 points, say: the fit
    interpolates at any noise): the result keeps the first bound, at which
    :meth:`~cascal.optimize.OptimResult.at_bounds` shows the noise, so the fit's findings
    say that the noise is not estimated."""
    if (obj.names[-1], "lower") not in found.at_bounds():
        return found
    wide = _below_floor(b)
    run = maximize(
        obj.value,
        obj.value_and_grad,
        wide,
        n_restarts=1,
        rng=None,
        value_grad_hess=obj.value_and_derivatives if obj.has_hessian else None,
        starts=[found.theta],
    )
    return replace(
        found,
        theta=run.theta,
        value=run.value,
        starts=found.starts + run.starts,
        bounds=wide if run.value - found.value >= NOISE_FLOOR_GAIN else b,
    )


def restore_bounds(gp: FittedGP) -> FittedGP:
    """``gp`` with the bounds and names of its search put back into ``gp.optimization``,
    which a model file does not store, so that
    :meth:`~cascal.optimize.OptimResult.at_bounds` (and the fit's findings) work on a
    loaded model. For a fit as :class:`~cascal.Cascade` makes them (the default bounds,
    a learned noise): the bounds are those :func:`fit_gp` derives from the data, with the
    noise floor :data:`NOISE_FLOOR_DROP` times lower where the stored optimum lies below
    the first and its run from there gained :data:`NOISE_FLOOR_GAIN` or more (its last
    start). Unchanged where the stored optimum does not fit those bounds."""
    opt = gp.optimization
    if opt is None or opt.bounds is not None:
        return gp
    profile = isinstance(gp.kernel, _Scaled) and gp.noise is None
    r = gp.y - gp.mean(gp.x)
    try:
        b = search_bounds(gp.x, r, gp.kernel, gp.noise, True, profile)
    except InputError:
        return gp
    if b.shape[0] != opt.theta.size:
        return gp
    wide = _below_floor(b)
    if opt.theta[-1] < b[-1, 0] - BOUND_TOL and len(opt.starts) > 1:
        first = max(s.value for s in opt.starts[:-1])
        if opt.starts[-1].value - first >= NOISE_FLOOR_GAIN:
            b = wide
    if np.any(opt.theta < wide[:, 0] - BOUND_TOL) or np.any(opt.theta > b[:, 1] + BOUND_TOL):
        return gp
    names = theta_names(gp.kernel, True, profile)
    return replace(gp, optimization=replace(opt, bounds=b, names=names))


def _probes(dim: int) -> list[np.ndarray]:
    """Offsets of :data:`PROBE` in log length scale (the first parameter of a table-started
    fit), both ways."""
    step = np.zeros(dim)
    step[0] = PROBE
    return [-step, step]


def _from_dict(kern: Kernel, hp: dict[str, float], learn_noise: bool) -> tuple[Kernel, float]:
    known = [*kern.names, "noise_variance"]  # (the period is the kernel's, not fitted)
    expected = known if learn_noise else list(kern.names)
    missing = [k for k in expected if k not in hp]
    periodic = isinstance(kern, Periodic)  # .hyperparameters lists its period: accepted back
    unknown = [k for k in hp if k not in known and not (k == "period" and periodic)]
    if missing or unknown:
        what = ", ".join(f"{w} {v}" for w, v in (("missing", missing), ("unknown", unknown)) if v)
        raise InputError(f"hyperparameters: {what}; expected {expected}")
    if periodic and "period" in hp and hp["period"] != kern.period:  # type: ignore[attr-defined]
        raise InputError(
            f"hyperparameters: period {hp['period']!r} differs from the kernel's "
            f"{kern.period!r}; give it as period="  # type: ignore[attr-defined]
        )
    try:
        vals = np.array([float(hp[k]) for k in kern.names])
        given = float(hp.get("noise_variance", 0.0))
    except (TypeError, ValueError):
        raise InputError(f"hyperparameters: expected numbers, got {hp}") from None
    if np.any(~np.isfinite(vals)) or np.any(vals <= 0):
        raise InputError(f"hyperparameters: expected positive finite values, got {hp}")
    if not learn_noise and given != 0.0:
        raise InputError(
            "hyperparameters: noise_variance given, but no white noise is learned on top of "
            "the known noise (learn_noise=False, the default for a known diagonal noise); "
            "pass learn_noise=True to add it, or leave it out"
        )
    sn2 = given if learn_noise else 0.0
    if learn_noise and not (np.isfinite(sn2) and sn2 >= 0):
        raise InputError(f"hyperparameters: noise_variance must be >= 0, got {sn2}")
    return kern.with_theta(np.log(vals)), sn2


def _condition(x, y, kern, m, known, sn2, optimization, factor=None) -> FittedGP:
    """The fitted GP; ``factor``: ``(L, alpha)`` of the target covariance, when the
    optimiser's latest evaluation already factorised it without jitter."""
    n = x.size
    r = y - m(x)
    if factor is not None:
        (L, alpha), jitter = factor, 0.0
    else:
        Kt = kern(x)
        if known is not None:
            Kt = known.add_to(Kt)
        Kt.flat[:: n + 1] += sn2
        L, jitter = linalg.cholesky(
            Kt, what="target covariance", noiseless=noiseless(known, n, sn2)
        )
        alpha = linalg.cho_solve(L, r)
    lml = -0.5 * float(r @ alpha) - 0.5 * linalg.logdet(L) - 0.5 * n * _LOG2PI
    return FittedGP(x, y, kern, m, known, sn2, L, alpha, jitter, lml, optimization)
