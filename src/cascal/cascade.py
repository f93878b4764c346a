"""The cascade: reference -> test bed -> ... -> device, each stage a fit on the previous one.

Stages are given from the reference end. Stage 0 maps test-bed readings to reference
readings. Stage k maps its sensor's readings to corrected readings of the sensor above it,
whose correction comes from stage k - 1 evaluated at the upper sensor's readings:

* ``bayes`` (Algorithm 1): targets are stage k-1's posterior mean and their noise is its
  FULL posterior covariance (:class:`~cascal.noise.Dense`, built from the factor of
  :meth:`~cascal.gp.FittedGP.posterior_factor`) plus a learned scalar.
* ``homoscedastic`` (Alternative 1): the same targets with a learned scalar noise only.
* ``lut`` (Alternative 2): offset lookup tables, one per stage, no uncertainty.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .baselines import OffsetTable, fit_table
from .errors import CascalError, CascalWarning, InputError
from .gp import FittedGP, fit_gp, single_threaded_blas
from .kernels import Kernel, make_kernel
from .means import make_mean
from .noise import Dense, Noise, as_noise
from .text import HOMOSCEDASTIC_CAUTION
from .validation import (
    as_positions,
    as_readings,
    check_count,
    check_increasing,
    check_pair,
    frozen,
    scalar_out,
)

__all__ = ["METHODS", "Cascade", "FittedCascade", "Stage"]

METHODS = ("bayes", "homoscedastic", "lut")


@dataclass(frozen=True, slots=True)
class Stage:
    """Aligned readings of one stage.

    Attributes:
        x: Readings of the sensor being calibrated, shape (n,).
        y: Readings of the more accurate sensor it was aligned with, shape (n,).
        noise: Known noise of ``y``: a number or (n,) variances, e.g. from repeated
            readings; an (n, n) covariance or a :mod:`cascal.noise` object also fits, but a
            model file keeps one variance per reading.
        name: Used in messages, e.g. ``"testbed"``.
    """

    x: np.ndarray
    y: np.ndarray
    noise: float | np.ndarray | None = None
    name: str = "stage"

    def __post_init__(self) -> None:
        x = as_positions(self.x, f"{self.name} x")
        y = as_positions(self.y, f"{self.name} y")
        if x.shape != y.shape:
            raise InputError(
                f"{self.name}: expected x and y of one length, got {x.size} and {y.size}"
            )
        object.__setattr__(self, "x", frozen(x))
        object.__setattr__(self, "y", frozen(y))
        if self.noise is not None and np.ndim(self.noise) > 0:
            object.__setattr__(self, "noise", frozen(self.noise))


@dataclass(frozen=True, slots=True)
class FittedCascade:
    """A fitted chain: one model per stage, the last maps device readings to positions.

    Attributes:
        method: ``bayes``, ``homoscedastic`` or ``lut``.
        models: Per stage, a :class:`~cascal.gp.FittedGP` or an :class:`OffsetTable`.
        stages: The data each model was fitted on (targets after propagation).
    """

    method: str
    models: tuple[FittedGP | OffsetTable, ...]
    stages: tuple[Stage, ...] = field(repr=False)

    @property
    def device(self) -> FittedGP | OffsetTable:
        """The last stage's model: device reading -> corrected position."""
        return self.models[-1]

    @property
    def calibrated_range(self) -> tuple[float, float]:
        """Smallest and largest device reading the last stage was fitted on."""
        x = self.stages[-1].x
        return float(x.min()), float(x.max())

    def correct(
        self, readings: object, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Corrected positions for device ``readings`` (m,), and their standard uncertainty;
        numbers for one number.

        Raises:
            CascalError: ``return_std`` with the ``lut`` method, which carries no uncertainty.
        """
        r, scalar = as_readings(readings, "readings")
        model = self.device
        if isinstance(model, OffsetTable):
            if return_std:
                raise CascalError(
                    "method 'lut' (lookup tables) gives no uncertainty; use 'bayes' or "
                    "'homoscedastic' for a standard uncertainty of each corrected reading"
                )
            return scalar_out(model(r), scalar)
        if not return_std:
            return scalar_out(model.predict(r), scalar)
        if self.method == "homoscedastic" and len(self.models) > 1:  # (a review: the
            # command line warned of this u, Python did not)
            warnings.warn(
                f"the u of method 'homoscedastic' {HOMOSCEDASTIC_CAUTION}; for u, use method "
                "'bayes'",
                CascalWarning,
                stacklevel=2,
            )
        mean, std = model.predict(r, return_std=True)
        return scalar_out(mean, scalar), scalar_out(std, scalar)


class Cascade:
    """A calibration chain from the reference end to the device.

    Args:
        stages: ``(x, y)`` pairs or :class:`Stage` values, reference end first; stage 0 is
            (test-bed readings, reference readings), the last is (device readings, readings
            of the sensor above it).
        method: ``bayes`` (Algorithm 1), ``homoscedastic`` (Alternative 1) or ``lut``.
        kernel: Kernel name or Kernel, for every GP stage.
        mean: Prior mean of every GP stage (default identity).
        n_restarts: Local optimiser starts per stage (after screening seeded candidates).
        seed: Seed of the whole fit; each stage gets its own child stream. None draws
            fresh entropy: fits that screen random starts (sums and products of kernels)
            may then differ from run to run.
        period: Period of a ``periodic`` kernel.
        check_range: Refuse a stage whose upper-sensor readings leave the range of the
            stage above (the reference could not confirm them).
    """

    def __init__(
        self,
        stages: Sequence[Stage | tuple[object, object]],
        method: str = "bayes",
        *,
        kernel: str | Kernel = "se",
        mean: str | float = "identity",
        n_restarts: int = 5,
        seed: int | None = 0,
        period: float | None = None,
        check_range: bool = False,
    ) -> None:
        method = _method(method)
        try:
            stages = list(stages)
        except TypeError:
            raise InputError(
                f"stages: expected a sequence of (x, y) pairs, got {stages!r}"
            ) from None
        if len(stages) < 1:
            raise InputError("stages: expected at least one (x, y) pair")
        check_count(n_restarts, "n_restarts", "optimiser starts", 1)
        if seed is not None:
            check_count(seed, "seed", "seeds", 0)  # ("a whole number of seeds >= 0")
        make_kernel(kernel, period=period)  # refused here, not at fit(): name, period
        if isinstance(mean, str):
            make_mean(mean, np.zeros(1), np.zeros(1))
        n = len(stages)
        self.stages = tuple(_as_stage(s, k, n) for k, s in enumerate(stages))
        self.method = method
        self.kernel, self.mean, self.period = kernel, mean, period
        self.n_restarts, self.seed, self.check_range = n_restarts, seed, check_range
        if check_range:
            for upper, lower in zip(self.stages, self.stages[1:], strict=False):
                _check_inside(lower, upper)

    def with_method(self, method: str) -> Cascade:
        """The same (already checked) stages and settings with another ``method``."""
        method = _method(method)
        other = object.__new__(type(self))  # a shallow copy without copy.copy's protocol
        other.__dict__.update(self.__dict__)
        other.method = method
        return other

    def fit(self, first: FittedGP | None = None) -> FittedCascade:
        """Fit every stage from the reference end down; returns a :class:`FittedCascade`.

        Args:
            first: An already fitted stage-0 GP to reuse (e.g. one test-bed calibration
                shared by several methods or devices); it must be fitted on stage 0's data.
        """
        if first is not None and not isinstance(first, FittedGP):
            raise InputError(f"first: expected a fitted stage-0 GP (FittedGP), got {first!r}")
        if self.method == "lut":
            return self._fit_tables()
        with single_threaded_blas():  # the same numbers whatever BLAS's threads (a review:
            return self._fit_gps(first)  # a sum kernel's stage 1 moved with two threads)

    def _fit_gps(self, first: FittedGP | None) -> FittedCascade:
        models: list[FittedGP] = []
        used: list[Stage] = []
        for k, stage in enumerate(self.stages):
            if k == 0 and first is not None:
                if not (np.array_equal(first.x, stage.x) and np.array_equal(first.y, stage.y)):
                    raise InputError("first: the given stage-0 GP was fitted on other data")
                models.append(first)
                used.append(stage)
                continue
            if k == 0:
                targets, noise = stage.y, stage.noise
            elif self.method == "bayes":
                targets, U = models[-1].posterior_factor(stage.y)
                noise = _propagated(U, stage)
            else:
                targets, noise = models[-1].predict(stage.y), stage.noise
            gp = fit_gp(
                stage.x,
                targets,
                kernel=self.kernel,
                mean=self.mean,
                noise=noise,
                learn_noise=True,
                n_restarts=self.n_restarts,
                seed=_stage_seed(self.seed, k),  # a generator only where starts are screened
                period=self.period,
                names=(f"{stage.name} x", f"{stage.name} y"),
            )
            models.append(gp)
            used.append(Stage(stage.x, targets, stage.noise, stage.name))
        return FittedCascade(self.method, tuple(models), tuple(used))

    def _fit_tables(self) -> FittedCascade:
        tables: list[OffsetTable] = []
        used: list[Stage] = []
        for k, stage in enumerate(self.stages):
            targets = stage.y if k == 0 else tables[-1](stage.y)
            tables.append(fit_table(stage.x, targets, (f"{stage.name} x", f"{stage.name} y")))
            used.append(Stage(stage.x, targets, stage.noise, stage.name))
        return FittedCascade("lut", tuple(tables), tuple(used))


def _method(method: object) -> str:
    key = str(method).lower()
    if key not in METHODS:
        raise InputError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
    return key


def _stage_seed(seed: int | None, k: int) -> np.random.SeedSequence:
    """Stage ``k``'s stream: ``SeedSequence(seed).spawn(n)[k]`` without the parent."""
    return np.random.SeedSequence(seed, spawn_key=(k,))


def _propagated(factor: np.ndarray, stage: Stage) -> Noise:
    """The previous stage's posterior covariance ``factor @ factor.T`` at this stage's
    upper readings, plus the stage's own known noise."""
    noise = Dense.from_factor(factor)
    own = as_noise(stage.noise, len(stage.x))
    return noise if own is None else noise + own


def _as_stage(s: Stage | tuple[object, object], k: int, n: int) -> Stage:
    name = "testbed" if k == 0 else "device" if k == n - 1 else f"stage {k}"
    if isinstance(s, Stage):
        x, y, noise, name = s.x, s.y, s.noise, s.name
    else:
        try:
            x, y = s
        except (TypeError, ValueError):
            raise InputError(f"stages[{k}]: expected an (x, y) pair or a Stage") from None
        noise = None
    xa, ya = check_pair(x, y, (f"{name} x", f"{name} y"))
    check_increasing(xa, ya, (f"{name} x", f"{name} y"))
    try:
        as_noise(noise, xa.size)
    except InputError as exc:  # (a leftover of a review: the stage went unnamed)
        raise InputError(f"{name}: {exc}") from None
    return Stage(xa, ya, noise, name)


def _check_inside(lower: Stage, upper: Stage) -> None:
    lo, hi = float(upper.x.min()), float(upper.x.max())
    out = np.flatnonzero((lower.y < lo) | (lower.y > hi))
    if out.size:
        i = out[0]
        raise InputError(
            f"{lower.name} y: reading {float(lower.y[i])!r} (index {i}) lies outside the range "
            f"[{lo!r}, {hi!r}] calibrated by {upper.name}; {out.size} reading(s) outside"
        )
