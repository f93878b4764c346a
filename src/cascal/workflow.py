"""The calibration workflow on files: fit stage files, correct readings, calibrate a fleet.

This is the library behind the ``cascal`` command (which only parses, calls one function
here and prints). Numerics stay in the core: :class:`~cascal.cascade.Cascade` fits,
:func:`~cascal.tabulate.predict_many` corrects many readings fast. What this module adds is
the bookkeeping of files: which row of which file a problem is on, provenance, and a pool
of processes for a fleet of devices.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.linalg import solve_triangular

from . import pool
from .cascade import Cascade, Stage
from .compensation import MAX_NODES, CompensationTable, compensation_table, in_arc
from .errors import CascalError, CascalWarning, InputError, NumericalError
from .gp import FittedGP, pin_blas
from .io.data import Source, StageData, read_stage
from .io.modelfile import CalibrationModel, load_model, save_model
from .planning import LowerStage, Plan, candidate_readings, check_interval, covered, plan_reference
from .screening import LEVEL, Screening, Spread, repeats_screening, screen
from .tabulate import predict_many
from .text import arc_text, exclude_spec, range_text, shown
from .validation import as_readings, check_count
from .verification import COVERAGE_FACTOR, Comparison, Verification, compare, verify

__all__ = [
    "COVERAGE_FACTOR",
    "BoundHit",
    "Correction",
    "DeviceResult",
    "MeasurementPlan",
    "StageOffset",
    "StageScreening",
    "change_covariance",
    "compare_models",
    "compensation",
    "correct",
    "fit_devices",
    "fit_findings",
    "fit_model",
    "measured_arc",
    "plan_measurements",
    "reverse_order",
    "same_readings",
    "screen_stages",
    "shares_upstream",
    "summarize_device",
    "unmeasured_arc",
    "verify_model",
]

_SUMMARY_GRID = 1001
#: Planning: readings at which a target's uncertainty is counted.
_PLAN_TARGET = 201


@dataclass(frozen=True, slots=True)
class Correction:
    """Corrected device readings (of one number: each field one number, not shape (m,)).

    Attributes:
        reading: Device readings, shape (m,).
        corrected: Corrected positions, shape (m,), same unit.
        u: Standard uncertainty of each correction (of the calibration map at that
            reading, not of the reading's own repeatability), shape (m,); NaN for ``lut``.
        out_of_range: True where the reading lies outside the calibrated range (a periodic
            model's covers every turn, less any arc its device readings left out: there,
            or where a float64 holds the reading less finely than its u), shape (m,).
    """

    reading: np.ndarray
    corrected: np.ndarray
    u: np.ndarray
    out_of_range: np.ndarray

    @property
    def U(self) -> np.ndarray:
        """Expanded uncertainty ``k u`` with k = 2 (about 95 %), shape (m,)."""
        return COVERAGE_FACTOR * self.u


def fit_model(
    stages: Sequence[StageData],
    *,
    method: str = "bayes",
    kernel: str = "se",
    period: float | None = None,
    unit: str = "m",
    n_restarts: int = 5,
    seed: int | None = 0,
    prefix: CalibrationModel | None = None,
    mean: str = "identity",
) -> CalibrationModel:
    """Fit a cascade to stage files, reference end first.

    Args:
        stages: The stage files, read by :func:`~cascal.io.data.read_stage`.
        method: ``bayes``, ``homoscedastic`` or ``lut``.
        kernel: ``se``, ``matern32``, ``matern52`` or ``periodic`` (with ``period``).
        period: Period of a periodic kernel, in ``unit``.
        unit: Unit of the readings (labels only).
        n_restarts: Optimiser starts per stage.
        seed: Seed; stage k uses child k of ``SeedSequence(seed)`` whether or not the stages
            above come from ``prefix``, so a device fitted on a prefix equals a full fit.
        prefix: A fitted one-stage model (a test bed) that ``stages`` continue; its stage is
            reused, not refitted.
        mean: Prior mean of each GP stage: ``identity`` (the paper's) or ``offset``
            (identity plus the stage's mean correction: sensors whose zeros differ).

    Raises:
        InputError: A stage's upper readings leave the range calibrated by the stage above
            (naming file and row), or the library refuses the data.
    """
    if kernel == "periodic" and period is None:
        raise InputError("the periodic kernel needs a period (e.g. --period 360 for degrees)")
    head = [] if prefix is None else list(prefix.data)
    if prefix is not None and len(head) != 1:
        raise InputError(f"prefix: expected a one-stage model, got {len(head)} stages")
    all_stages = head + [s.stage(shown(Path(s.source.file).name)) for s in stages]
    if not all_stages:
        raise InputError("expected at least one stage file")
    periodic = kernel == "periodic" and method != "lut"
    _check_distinct(head + list(stages))
    if method != "lut":
        for s in stages:
            _check_size(s)
    if not periodic:
        turn = TURNS.get(unit.strip().lower()) if kernel != "periodic" else None
        for k, s in enumerate(stages):
            upper = all_stages[len(head) + k - 1].x if len(head) + k else None
            _check_inside(s, upper, turn, stages[k - 1] if k else None)
    cascade = Cascade(
        all_stages,
        method,
        kernel=kernel,
        mean=mean,
        n_restarts=n_restarts,
        seed=seed,
        period=period,
        check_range=not periodic,
    )
    first = None
    if prefix is not None and method != "lut":
        first = prefix.fitted.models[0]
        if prefix.method != method or not isinstance(first, FittedGP):
            raise InputError(f"prefix: fitted with method {prefix.method!r}, not {method!r}")
    fitted = cascade.fit(first=first)
    return CalibrationModel(
        fitted,
        tuple(all_stages),
        (*(prefix.counts if prefix else ()), *(s.counts for s in stages)),
        (*(prefix.sources if prefix else ()), *(s.source for s in stages)),
        unit=unit,
        kernel=None if method == "lut" else kernel,
        period=period if periodic else None,
        seed=seed,
        n_restarts=n_restarts,
    )


#: Most positions of a GP stage that a model file is fitted for: its matrices take 8 n^2
#: bytes each (0.8 GB at 10 000, several of them during the fit) and the fit O(n^3) time.
MAX_GP_POINTS = 10_000


def _check_size(s: StageData) -> None:
    n = s.x.size
    if n > MAX_GP_POINTS:
        raise InputError(
            f"{n} distinct positions; a GP stage takes at most {MAX_GP_POINTS} (its matrices "
            f"need {8 * n * n / 1e9:.3g} GB each): average neighbouring readings, or fit "
            "--method lut",
            file=s.source.file,
        )


@dataclass(frozen=True, slots=True)
class StageScreening:
    """Outlier screening of one stage file of a fit (see :mod:`cascal.screening`).

    Attributes:
        stage: Index of the stage in the model.
        data: The stage file as read.
        fit: Points its fit's other points do not support; None for a lookup table or
            where the screening failed.
        spread: Positions whose repeated readings scatter too much.
        problem: Why the fit's screening failed (a numerical error), or None.
        level: Family-wise false-alarm probability of each check.
        spread_capped: More repeated positions scatter too much than ``spread`` names
            (:func:`~cascal.screening.repeats_screening`).
    """

    stage: int
    data: StageData
    fit: Screening | None
    spread: tuple[Spread, ...]
    problem: str | None = None
    level: float = LEVEL
    spread_capped: bool = False

    @property
    def rows(self) -> list[int]:
        """File rows of every finding, increasing: all readings of a suspect point, the
        farthest reading of a repeated position (both of a pair)."""
        out: set[int] = set()
        for q in self.fit.suspects if self.fit else ():
            out.update(int(r) for r in self.data.point_rows(q.index))
        raw_rows = self.data.raw_rows
        for s in self.spread if raw_rows is not None else ():
            pick = s.members if s.members.size == 2 else [s.farthest]
            out.update(int(raw_rows[i]) for i in pick)
        return sorted(out)


def screen_stages(
    model: CalibrationModel, stages: Sequence[StageData], *, level: float = LEVEL
) -> list[StageScreening]:
    """Screen the stage files a model was fitted from for outliers.

    Args:
        model: The fitted model; ``stages`` are its last ``len(stages)`` stages (a device
            fitted on a test-bed prefix: the device's file alone).
        stages: The files as read by :func:`~cascal.io.data.read_stage`.
        level: Family-wise false-alarm probability per stage and check (default 1 %).
    """
    first = len(model.fitted.models) - len(stages)
    if first < 0:
        raise InputError(f"expected at most {len(model.fitted.models)} stage files")
    out = []
    for k, data in enumerate(stages, start=first):
        gp = model.fitted.models[k]
        fit = problem = None
        if isinstance(gp, FittedGP):
            try:
                fit = screen(gp, level=level)
            except NumericalError as exc:  # a screening never costs the user the fit
                problem = str(exc)
        spread, capped = (), False
        if data.raw_x is not None and data.raw_y is not None:
            spread, capped = repeats_screening(data.raw_x, data.raw_y, level=level)
        out.append(StageScreening(k, data, fit, spread, problem, level, capped))
    return out


#: Corrections whose mean is this many times their spread are one offset between the two
#: sensors' zeros, not a calibration map (the stage-A data of the paper's 12 000 trials reach 93).
OFFSET_RATIO = 1000.0
#: A profiled fit whose noise exceeds its map's variance this many times (the map's
#: amplitude below 1 % of the noise's) takes the readings for noise about the prior mean,
#: as at the noise's upper bound: the likelihood is flat beyond, where the search stops.
NOISE_ONLY_RATIO = 1e4


#: Points from which a stage whose length scale ends at its upper bound (a straight
#: correction plus noise) is taken at its word; below, too few to tell (3 of the demo's
#: reference points: 59 % of its check points within U).
STRAIGHT_MIN_POINTS = 12


@dataclass(frozen=True, slots=True)
class BoundHit:
    """A fitted stage hyperparameter at a bound of its search range (see
    :meth:`~cascal.optimize.OptimResult.at_bounds`): the bound set it, not the data.

    Attributes:
        stage: Index of the stage in the model.
        parameter: ``length_scale``, ``variance``, ``noise_variance`` or ``noise_ratio``
            (noise_variance / variance), as named by the fit (``k1_`` ... in a sum).
        side: ``"lower"`` or ``"upper"``.
        points: Points of the stage.
    """

    stage: int
    parameter: str
    side: str
    points: int


@dataclass(frozen=True, slots=True)
class StageOffset:
    """A stage with the identity prior mean whose corrections (targets minus readings) are
    mostly one offset: their mean beyond :data:`OFFSET_RATIO` times their spread.

    Attributes:
        stage: Index of the stage in the model.
        offset: Mean of the corrections, unit of the readings.
        spread: Their standard deviation about that mean, same unit.
    """

    stage: int
    offset: float
    spread: float


def fit_findings(model: CalibrationModel, *, first: int = 0) -> list[BoundHit | StageOffset]:
    """What makes the u of stages ``first``, ... of a freshly fitted model doubtful.

    A :class:`StageOffset` where the identity prior mean has to reach a constant offset
    through the map's variance (``mean="offset"`` fits it); else each hyperparameter that
    ended at a bound: a length scale at its lower bound (the map varies faster than the
    points show), a variance at either bound, the learned noise at its upper bound (the
    readings taken for noise) or, with no known noise, at its lower bound (the fit
    interpolates; the noise is not estimated); a profiled noise over
    :data:`NOISE_ONLY_RATIO` times the variance counts as at its upper bound. A length
    scale at its upper bound (the points read as a straight correction plus noise) is
    listed for stages of fewer than :data:`STRAIGHT_MIN_POINTS` points only, and a learned
    noise at its lower bound on top of a known noise not at all. A model file stores no
    bounds: loading puts them back for files of cascal 0.4.2 and later
    (:func:`~cascal.gp.restore_bounds`); an older file's model shows offsets only.
    """
    out: list[BoundHit | StageOffset] = []
    for k in range(first, len(model.fitted.models)):
        gp = model.fitted.models[k]
        if not isinstance(gp, FittedGP):
            continue
        r = gp.y - gp.mean(gp.x)
        mean, spread = float(r.mean()), float(r.std())
        if gp.mean.name == "identity" and abs(mean) > OFFSET_RATIO * spread:
            out.append(StageOffset(k, mean, spread))
            continue
        opt, hp = gp.optimization, gp.hyperparameters
        hits = opt.at_bounds() if opt else []
        if (  # a profiled fit's noise ratio far beyond any map: as at its upper bound
            opt
            and "noise_ratio" in opt.names
            and ("noise_ratio", "upper") not in hits
            and hp["noise_variance"] >= NOISE_ONLY_RATIO * hp["variance"]
        ):
            hits.append(("noise_ratio", "upper"))
        for name, side in hits:
            straight = name.endswith("length_scale") and side == "upper"
            if straight and gp.x.size >= STRAIGHT_MIN_POINTS:
                continue  # a straight correction (plus noise): the points can show it
            noise = name in ("noise_variance", "noise_ratio")
            if not (noise and side == "lower" and gp.noise is not None):
                out.append(BoundHit(k, name, side, gp.x.size))
    return out


#: A full turn in the angle units a rotary stage may be read in (lower case).
TURNS = {
    "deg": 360.0,
    "degree": 360.0,
    "degrees": 360.0,
    "\N{DEGREE SIGN}": 360.0,
    "rad": 2 * np.pi,
    "radian": 2 * np.pi,
    "radians": 2 * np.pi,
    "arcmin": 21600.0,
    "arcsec": 1296000.0,
    "grad": 400.0,
    "gon": 400.0,
}


def beyond(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """How far each of ``values`` (m,) lies outside ``[lo, hi]``, shape (m,); <= 0 inside."""
    return np.maximum(lo - values, values - hi)


def far_off(readings: np.ndarray, lo: float, hi: float) -> bool:
    """Whether every reading (m,) lies more than the range's span beyond ``[lo, hi]``, as
    readings in mm against a model in m do."""
    return bool(np.all(beyond(np.asarray(readings, dtype=float), lo, hi) > hi - lo))


def _check_inside(
    stage: StageData,
    upper_x: np.ndarray | None,
    turn: float | None,
    above: StageData | None = None,
) -> None:
    """Refuse a stage whose upper readings leave the range of the stage above (its
    ``upper_x``); ``turn``: a full turn in the readings' angle unit, when the kernel is
    not periodic (the message then names the periodic kernel); ``above``: the stage
    file above (where it shares the file's name, the message gives the path)."""
    if upper_x is None:
        return
    lo, hi = float(upper_x.min()), float(upper_x.max())
    out = np.flatnonzero((stage.y < lo) | (stage.y > hi))
    if out.size:
        i = out[np.argmin(stage.rows[out])]
        y, span = float(stage.y[i]), hi - lo
        far = float(np.max(beyond(stage.y[out], lo, hi)))
        rows = np.concatenate([stage.point_rows(int(j)) for j in out])
        name = Path(stage.source.file).name  # the path where the file above shares it (a
        # review: --exclude names one stage file, and the name alone named two)
        if above is not None and Path(above.source.file).name == name:
            name = stage.source.file
        spec = exclude_spec(name, np.sort(rows))
        advice = (
            "the reference never confirmed it: measure the stage above over this range too, "
            f"or leave {'it' if out.size == 1 else 'them'} out (--exclude {spec})"
        )
        if span > 0 and (far > 10 * span or 2 * out.size > stage.y.size):
            advice = (
                f"{out.size} of {stage.y.size} points lie outside, up to {far:.4g} beyond it: "
                "are the two files' readings of this sensor in different units?"
            )
        reverse = None if above is None else reverse_order(above.source, stage.source)
        if reverse is not None:
            advice = reverse
        elif turn is not None:
            advice += (
                "; or, for a rotary axis whose readings wrap at the full turn, fit with the "
                f"periodic kernel (--kernel periodic --period {turn:.15g}, a GP method)"
            )
        n = int(stage.counts[i])
        mean = f" (the mean of this position's {n} rows)" if n > 1 else ""
        raise InputError(
            f"{stage.source.columns[1]} reading {y!r}{mean} lies outside the range "
            f"[{lo!r}, {hi!r}] calibrated by the stage above ({out.size} point(s) outside); "
            f"{advice}",
            file=stage.source.file,
            row=int(stage.rows[i]),
            column=stage.source.columns[1],
        )


def reverse_order(above: Source, below: Source) -> str | None:
    """Where the column names link two consecutive stage files' :class:`Source` the wrong
    way round (the lower one's first column is the upper one's second, its second not the
    upper one's first), what to do; else None. Names are only labels (a logger's ``ch1,
    ch2`` above ``ch2, ch3``), so the command line warns of it, and refuses it only where
    the range check fails too (a review)."""
    (xa, ya), (xs, ys) = (tuple(c.lower() for c in d.columns) for d in (above, below))
    if not (xs == ya and ys != xa):
        return None
    return (
        f"the stage files look to be in reverse order ({Path(below.file).name}'s first "
        f"column, {below.columns[0]}, is the second of {Path(above.file).name}): give them "
        "from the reference down, the file with the reference's readings first"
    )


def _check_distinct(stages: Sequence[StageData | Stage]) -> None:
    """Refuse two stages with the same readings: one stage file given twice (a review: it
    was fitted as one more stage, the device's error applied twice). A prefix's stage is a
    :class:`~cascal.cascade.Stage`, named by its file's name."""

    def file(d: StageData | Stage) -> str:
        return d.source.file if isinstance(d, StageData) else d.name

    for j, later in enumerate(stages):
        for i in range(j):
            first = stages[i]
            if same_readings(first, later):
                raise InputError(
                    f"stages {i} and {j} hold the same readings ({file(first)} and "
                    f"{file(later)}): one stage file given twice? Each stage of the chain is "
                    "its own file, from the reference down",
                    file=file(later),
                )


#: A rotary device's readings leave part of the turn unmeasured where the largest gap
#: between neighbouring angles exceeds this many times their median spacing and
#: :data:`_ARC_TURN` of the period.
_ARC_SPACINGS = 4.0
_ARC_TURN = 1.0 / 36.0


def arc_width(arc: tuple[float, float], period: float) -> tuple[float, float]:
    """``(start, width)`` of an arc ``(start, end)`` of :func:`unmeasured_arc`."""
    return arc[0], float(np.mod(arc[1] - arc[0], period))


def measured_arc(model: CalibrationModel) -> tuple[float, float] | None:
    """For a periodic model whose device readings cover only part of the turn, that part
    as readings ``(lo, hi)``, ``lo < hi`` (``hi`` may lie beyond the period: readings are
    corrected as their angle), from where :func:`unmeasured_arc` ends round to where it
    starts; None where there is no such arc."""
    arc = unmeasured_arc(model)
    if arc is None:
        return None
    start, width = arc_width(arc, float(model.period))
    return start + width, start + float(model.period)


def unmeasured_arc(model: CalibrationModel) -> tuple[float, float] | None:
    """For a periodic model whose device readings cover only part of the turn, the arc
    ``(start, end)`` they leave out, as angles in ``[0, period)`` (from ``start`` up to
    ``end``, through the period where ``end < start``); None where they cover the turn
    (no gap between neighbouring angles over 4 median spacings and a 36th of the turn)
    or the model is not periodic."""
    if not model.periodic:
        return None
    period = float(model.period)
    angles = np.unique(np.mod(model.fitted.stages[-1].x, period))
    if angles.size < 2:
        return None
    gaps = np.diff(np.append(angles, angles[0] + period))
    i = int(np.argmax(gaps))
    if gaps[i] <= max(_ARC_SPACINGS * float(np.median(gaps)), _ARC_TURN * period):
        return None
    return float(angles[i]), float(angles[(i + 1) % angles.size])


def correct(model: CalibrationModel, readings: object) -> Correction:
    """Correct device readings (m,) with the model's last stage (one number: each field
    of the result one number).

    Readings outside the calibrated range are flagged; they are still corrected, by the
    GP's extrapolation (back to the prior mean, with a growing u) or the lookup table's
    held end offset. A periodic model covers every turn: a reading is corrected as its
    angle in the calibrated turn, and flagged where that angle lies in the part of the turn
    the device readings left out (:func:`unmeasured_arc`) or where the reading is so large
    that a float64 holds it less finely than its u.
    """
    r, scalar = as_readings(readings, "readings")
    lo, hi = model.calibrated_range
    device = model.fitted.device
    with np.errstate(over="ignore"):  # squared distances of readings near 1e308 overflow
        if isinstance(device, FittedGP):  # (a periodic GP takes any turn as its angle)
            corrected, u = predict_many(device, r, return_std=True)
        else:
            corrected, u = device(r), np.full(r.shape, np.nan)
        if model.periodic:  # a reading too large for its correction's digits
            out = np.spacing(np.abs(r)) > u
            arc = unmeasured_arc(model)
            if arc is not None:  # or in the part of the turn the device was not measured on
                out |= in_arc(r, arc_width(arc, float(model.period)), float(model.period))
        else:
            out = (r < lo) | (r > hi)
    if scalar:  # one number in: each field one number
        return Correction(r[0], corrected[0], u[0], out[0])
    return Correction(r, corrected, u, out)


def compare_models(
    old: CalibrationModel, new: CalibrationModel, *, n: int = _SUMMARY_GRID
) -> Comparison:
    """Compare a recalibration ``new`` with the calibration ``old`` of the same device on
    ``n`` equally spaced readings of their common calibrated range (one turn for periodic
    models): the change and, for GP models, :func:`change_covariance`.

    Raises:
        InputError: The models differ in unit, period or number of stages, or their
            ranges do not overlap.
    """
    if old.unit != new.unit:
        raise InputError(f"the models are in different units ({old.unit!r} and {new.unit!r})")
    if old.period != new.period:
        what = [f"period {m.period:g}" if m.periodic else "not periodic" for m in (old, new)]
        raise InputError(f"the models differ in their period ({what[0]} and {what[1]})")
    na, nb = len(old.fitted.models), len(new.fitted.models)
    if na != nb:
        raise InputError(
            f"the models have {na} and {nb} stages: compare two calibrations of one device "
            "along the same chain"
        )
    if old.periodic:
        grid = _common_turn(old, new, n)
    else:
        (lo_a, hi_a), (lo_b, hi_b) = old.calibrated_range, new.calibrated_range
        lo, hi = max(lo_a, lo_b), min(hi_a, hi_b)
        if not lo < hi:
            raise InputError(
                f"the calibrated ranges {range_text(lo_a, hi_a)} and {range_text(lo_b, hi_b)} "
                f"{old.unit} do not overlap: nothing to compare"
            )
        grid = np.linspace(lo, hi, n)
    a, b = correct(old, grid), correct(new, grid)
    shared = shares_upstream(old, new)
    cov = None
    if isinstance(old.fitted.device, FittedGP) and isinstance(new.fitted.device, FittedGP):
        cov = change_covariance(old, new, grid, shared=shared)
    return compare(
        grid, a.corrected, a.u, b.corrected, b.u, change_cov=cov, shared=shared, period=old.period
    )


def _common_turn(old: CalibrationModel, new: CalibrationModel, n: int) -> np.ndarray:
    """``n`` readings (n,), increasing, over the part of the turn that both periodic
    models' device readings cover (:func:`measured_arc`; the whole turn where both cover
    it): equally spaced over one stretch, or shared by length between two (two arcs can
    overlap at both ends: :func:`cascal.verification.breaks` finds where). A review:
    compare judged the arc a swivel's device readings leave out, where both models only
    extrapolate (a change of 0.0074 deg there failed a --max-change that the measured
    arc passed with 0.00032).

    Raises:
        InputError: The two arcs do not overlap.
    """
    period = float(old.period)  # type: ignore[arg-type]
    arcs = [a for a in (measured_arc(old), measured_arc(new)) if a is not None]
    if not arcs:
        return np.linspace(0.0, period, n, endpoint=False)
    pieces = arcs[:1]  # one arc: itself; two: where they meet (at one end or at both)
    if len(arcs) == 2:
        (a1, b1), (a2, b2) = arcs
        move = a1 + float(np.mod(a2 - a1, period)) - a2  # the second from within a turn of a1
        a2, b2 = a2 + move, b2 + move
        meet = [(max(a1, lo), min(b1, hi)) for lo, hi in ((a2, b2), (a2 - period, b2 - period))]
        pieces = sorted((lo, hi) for lo, hi in meet if hi > lo)
        if not pieces:
            ends = [f"{a:.9g} to {b:.9g}" for a, b in arcs]
            raise InputError(
                f"the arcs the two models' device readings cover ({ends[0]} and {ends[1]} "
                f"{old.unit}) do not overlap: nothing to compare"
            )
    shift = period * float(np.floor(pieces[0][0] / period))  # readings from the first turn on
    pieces = [(lo - shift, hi - shift) for lo, hi in pieces]
    if len(pieces) == 1:
        return np.linspace(*pieces[0], n)
    (a, b), (c, d) = pieces  # n readings shared by length, two at least in each
    k = min(max(2, round(n * (b - a) / (b - a + d - c))), n - 2)
    return np.concatenate([np.linspace(a, b, k), np.linspace(c, d, n - k)])


def shares_upstream(a: CalibrationModel, b: CalibrationModel, *, rtol: float = 1e-6) -> bool:
    """Whether two GP models hold the same stages above their device stage: the same data
    and, within ``rtol``, the same hyperparameters (one test-bed calibration, fitted once or
    again by another cascal version), whose error is then part of both devices' errors."""
    ma, mb = a.fitted.models, b.fitted.models
    if len(ma) != len(mb) or len(ma) < 2 or not all(isinstance(m, FittedGP) for m in ma + mb):
        return False
    for k in range(len(ma) - 1):
        da, db = a.data[k], b.data[k]
        ha, hb = ma[k].hyperparameters, mb[k].hyperparameters  # type: ignore[union-attr]
        same = (
            same_readings(da, db)
            and ha.keys() == hb.keys()
            and all(np.isclose(ha[h], hb[h], rtol=rtol, atol=0.0) for h in ha)
        )
        if not same:
            return False
    return True


def change_covariance(
    old: CalibrationModel, new: CalibrationModel, readings: object, *, shared: bool = False
) -> np.ndarray:
    """Covariance (m, m) that the change ``new - old`` of two GP models' corrections at
    device readings (m,) would have if the device had not changed.

    Each correction is its device GP's mean, ``m(r) + w^T (t - m(X))`` with weights
    ``w = (K + noise)^-1 k(X, r)``; under that hypothesis both estimate one device map, so
    the change is ``v^T e`` with ``v = [-w_old; w_new]`` and ``e`` the two target vectors'
    deviations from it, of covariance ``C``: the map at both files' readings (the old fit's
    kernel), each file's repeat noise and learned white noise, and the errors of the stage
    above at each file's upper readings (its posterior covariance; the same for either
    method: a ``homoscedastic`` fit ignores them, they are there all the same), between the
    two files too where that stage is shared (``shared``, :func:`shares_upstream`). Where
    both models hold the same device readings but other stages above (the test bed
    recalibrated, the device file reused), the file's noise is one draw in both: its repeat
    noise and white noise (the geometric mean of the two fits' variances) are shared too;
    where every stage is the same, the two stay independent (what two calibrations would
    differ by: ``compare`` warns of it). The covariance is ``v^T C v``, positive
    semi-definite by construction.
    """
    r = np.asarray(readings, dtype=float)
    ga, gb = old.fitted.device, new.fitted.device
    if not (isinstance(ga, FittedGP) and isinstance(gb, FittedGP)):
        raise InputError("change_covariance: both models need a GP device stage")
    na = ga.x.size
    C = ga.kernel(np.concatenate([ga.x, gb.x]))  # the device map, one under the hypothesis
    C[:na, :na] += _own_noise(old) + ga.noise_variance * np.eye(na)
    C[na:, na:] += _own_noise(new) + gb.noise_variance * np.eye(gb.x.size)
    ya, yb = old.data[-1].y, new.data[-1].y
    ups = [m.fitted.models[-2] if len(m.fitted.models) > 1 else None for m in (old, new)]
    if isinstance(ups[0], FittedGP):
        C[:na, :na] += ups[0].cross_covariance(ya, ya)
    if isinstance(ups[1], FittedGP):
        C[na:, na:] += ups[1].cross_covariance(yb, yb)
    if shared and isinstance(ups[0], FittedGP):
        S = ups[0].cross_covariance(ya, yb)
        C[:na, na:] += S
        C[na:, :na] += S.T
    if same_readings(old.data[-1], new.data[-1]) and not (
        len(old.data) == len(new.data)
        and all(same_readings(a, b) for a, b in zip(old.data, new.data, strict=True))
    ):  # (a user review: a recalibrated test bed over the same device file)
        N = _own_noise(old) + np.sqrt(ga.noise_variance * gb.noise_variance) * np.eye(na)
        C[:na, na:] += N
        C[na:, :na] += N
    v = np.concatenate([-_weights(ga, r), _weights(gb, r)])
    cov = v.T @ (C @ v)
    return 0.5 * (cov + cov.T)


def same_readings(a: StageData | Stage, b: StageData | Stage) -> bool:
    """Whether two stages hold the same readings (and repeat noise)."""
    na, nb = (np.zeros(d.x.size) if d.noise is None else d.noise for d in (a, b))
    return bool(np.array_equal(a.x, b.x) and np.array_equal(a.y, b.y) and np.array_equal(na, nb))


def _own_noise(model: CalibrationModel) -> np.ndarray:
    """The device file's own known noise (the spread of its repeats), dense (n, n)."""
    st = model.data[-1]
    n = st.x.size
    return np.zeros((n, n)) if st.noise is None else np.diag(np.broadcast_to(st.noise, n))


def _weights(gp: FittedGP, r: np.ndarray) -> np.ndarray:
    """``(K + noise)^-1 k(X, r)``, shape (n, m): each target's weight in the mean at r."""
    return solve_triangular(gp.L.T, gp.whitened(r), lower=False, check_finite=False)


def verify_model(
    model: CalibrationModel,
    reading: object,
    reference: object,
    *,
    u_reading: float = 0.0,
    u_reference: float = 0.0,
    mpe: float | None = None,
) -> Verification:
    """Verify ``model`` at independent check points: device readings (m,) and the
    reference's values there (m,). Points outside the calibrated range are corrected but
    left out of the statistics; see :func:`cascal.verification.verify` for the rest.
    """
    c = correct(model, as_readings(reading, "reading")[0])  # (one number: one check point)
    ref = as_readings(reference, "reference")[0]  # (a NaN had made every figure NaN)
    if ref.shape != c.reading.shape:
        raise InputError(
            f"reading and reference: expected the same length, got {c.reading.size} and {ref.size}"
        )
    return verify(
        c.reading,
        ref,
        c.corrected,
        c.u,
        inside=~c.out_of_range,
        u_reading=u_reading,
        u_reference=u_reference,
        period=model.period if model.periodic else None,
        mpe=mpe,
    )


def compensation(
    model: CalibrationModel, tolerance: float | None = None, *, rtol: float = 0.1
) -> CompensationTable:
    """The model's correction as a compensation table for a controller (linear
    interpolation on a uniform grid over the calibrated range, or over one period).

    Args:
        model: The calibration model; its last stage corrects device readings.
        tolerance: Largest interpolation error, in the model's unit. Default: ``rtol``
            times the smallest standard uncertainty over the range (a GP model only).
        rtol: Default tolerance relative to the smallest standard uncertainty.

    Raises:
        InputError: No tolerance for a lookup-table model, a tolerance that is not a
            positive number, or one that needs more than ``MAX_NODES`` nodes.
    """
    device = model.fitted.device
    lo, hi = (0.0, float(model.period)) if model.periodic else model.calibrated_range
    gp = isinstance(device, FittedGP)
    if tolerance is None:
        if not gp:
            raise InputError(
                "a lookup-table (lut) model carries no uncertainty to set the table's "
                f"tolerance by: give one, in {model.unit} (--tolerance)"
            )
        u_min = float(np.min(device.predict(np.linspace(lo, hi, 2001), return_std=True)[1]))
        tolerance = rtol * u_min
    try:
        ok = bool(np.isfinite(tolerance) and tolerance > 0)
    except TypeError:  # ("1e-6", None ...)
        ok = False
    if not ok:
        raise InputError(
            f"tolerance: expected a positive number of {model.unit}, got {tolerance!r}"
        )
    table = compensation_table(
        device.predict if gp else device,
        lo,
        hi,
        float(tolerance),
        std=(lambda r: device.predict(r, return_std=True)[1]) if gp else None,
        period=model.period,
        extra=model.fitted.stages[-1].x,
    )
    if table is None:
        raise InputError(
            f"a table within {tolerance:.3g} {model.unit} needs more than {MAX_NODES} nodes; "
            "give a larger tolerance"
        )
    arc = unmeasured_arc(model)
    return table if arc is None else replace(table, arc=arc_width(arc, float(model.period)))


@dataclass(frozen=True, slots=True)
class MeasurementPlan:
    """Reference measurements proposed for a model's stage 0, with what they were chosen for.

    Attributes:
        plan: Positions and uncertainties (:class:`~cascal.planning.Plan`).
        reach: Intervals ``(lo, hi)`` of test-bed readings the candidates covered.
        candidates: Number of candidate readings.
        target: What the plan lowers, in words.
        lower_name: Name of the stage below when its uncertainty is the target, else None.
    """

    plan: Plan
    reach: tuple[tuple[float, float], ...]
    candidates: int
    target: str
    lower_name: str | None


def plan_measurements(
    model: CalibrationModel,
    k: int,
    *,
    reach: Sequence[tuple[float, float]] | None = None,
    where: tuple[float, float] | None = None,
    noise_std: float | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> MeasurementPlan:
    """Propose ``k`` further reference measurements of the model's stage 0 (the test bed).

    The target is, for a ``bayes`` model of two or more stages, the device's (the last
    stage's) uncertainty over its readings (stage 0's covariance is part of stage 1's
    noise, and each stage's of the next one's); for a
    ``homoscedastic`` one, stage 0's uncertainty at stage 1's test-bed readings; for a
    one-stage model, stage 0's uncertainty over ``where`` (default: its readings' span, one
    turn for a periodic model). Periodic models get their proposals on one turn.

    Args:
        model: A ``bayes`` or ``homoscedastic`` model.
        k: Measurements to propose.
        reach: Intervals ``(lo, hi)`` of test-bed readings the reference can reach (``lo ==
            hi`` for a single reading); default: the stretches stage 0's readings cover,
            their gaps left out (:func:`~cascal.planning.covered`).
        where: Test-bed readings ``(lo, hi)`` to lower the uncertainty over (one-stage
            models only).
        noise_std: Standard deviation of one new reference measurement, in the model's
            unit; default: as precise as the average existing point.
        progress: Called as ``progress(chosen, k)`` after every choice.
    """
    check_count(k, "k", "measurements", 1)
    testbed = model.fitted.models[0]
    if not isinstance(testbed, FittedGP):
        raise InputError(
            "a lookup-table (lut) model carries no uncertainty to plan by: fit the stages "
            "with method bayes or homoscedastic"
        )
    x0 = model.data[0].x
    period = model.period
    span = (0.0, float(period)) if period is not None else (float(x0.min()), float(x0.max()))
    if reach is not None and len(reach) == 0:
        raise InputError("reach: expected at least one interval (lo, hi); None for the default")
    intervals = tuple(check_interval(r, "reach") for r in (reach or covered(x0, period)))
    if noise_std is not None and not (0 <= noise_std < 1e150):
        raise InputError(
            f"noise_std: expected a number >= 0 below 1e150 of {model.unit}, got {noise_std!r}"
        )
    s2 = None if noise_std is None else float(noise_std) ** 2
    candidates = candidate_readings(intervals)
    if period is not None:  # readings of any turn: one turn's
        candidates = np.unique(np.mod(candidates, period))
    unit = model.unit
    if len(model.data) == 1:
        lo, hi = span if where is None else check_interval(where, "where")
        turn = period is not None and where is None  # one turn: 0 and the period are one
        grid = np.linspace(lo, hi, _PLAN_TARGET, endpoint=not turn) if hi > lo else np.array([lo])
        plan = plan_reference(
            testbed, candidates, k, where=grid, noise_variance=s2, progress=progress
        )
        what = f"stage 0's uncertainty over test-bed readings {range_text(lo, hi)} {unit}"
        return MeasurementPlan(plan, intervals, candidates.size, what, None)
    if where is not None:
        raise InputError(
            f"where (--where): only for a one-stage model; this one has {len(model.data)} "
            "stages, and the stages below the test bed say where it is used"
        )
    name = model.data[1].name
    if model.method == "bayes":
        last = len(model.data) - 1
        xd, name = model.data[last].x, model.data[last].name
        measured = measured_arc(model)
        if period is None:
            grid = np.linspace(float(xd.min()), float(xd.max()), _PLAN_TARGET)
            span = f"range {range_text(float(grid[0]), float(grid[-1]))} {unit}"
        elif measured is None:
            grid = np.linspace(0.0, period, _PLAN_TARGET, endpoint=False)
            span = f"full turn (period {period:g})"
        else:  # the measured part of the turn
            grid = np.mod(np.linspace(*measured, _PLAN_TARGET), period)
            span = arc_text(model)
        # the chain from stage 1 down: each stage's covariance where the next one reads it
        chain = [
            LowerStage(
                model.fitted.models[j],  # type: ignore[arg-type]
                model.data[j].y,
                model.data[j + 1].y if j < last else grid,
            )
            for j in range(1, last + 1)
        ]
        plan = plan_reference(
            testbed, candidates, k, lower=chain, noise_variance=s2, progress=progress
        )
        what = f"stage {last} ({name})'s uncertainty over its calibrated {span}"
        if last > 1:
            through = "stage 1" if last == 2 else f"stages 1 to {last - 1}"
            what += f" (the device; the test bed's covariance passes down through {through})"
        return MeasurementPlan(plan, intervals, candidates.size, what, name)
    upper = model.data[1].y
    plan = plan_reference(testbed, candidates, k, where=upper, noise_variance=s2, progress=progress)
    what = f"stage 0's uncertainty at the test-bed readings of stage 1 ({name})"
    return MeasurementPlan(plan, intervals, candidates.size, what, None)


@dataclass(frozen=True, slots=True)
class DeviceResult:
    """Outcome of one device of a fleet.

    Attributes:
        device: Device name (the file's stem).
        file: The device's stage file.
        error: Why it was skipped, or None.
        model: Path of the written model, or None.
        hyperparameters: Device stage's hyperparameters by name (empty for ``lut``).
        rms_correction: RMS of ``corrected - reading`` over the calibrated range.
        max_u: Largest standard uncertainty there (NaN for ``lut``).
        calibrated_range: Smallest and largest device reading calibrated.
        points: Points of the device stage (after averaging repeats).
        screening: Outlier screening of the device's file, or None when skipped.
        findings: What makes the device stage's u doubtful (:func:`fit_findings`).
        source: The device file's provenance (its columns among it), or None.
        warnings: cascal's warnings while reading and fitting it
            (:class:`~cascal.errors.CascalWarning`), as text.
        arc: For a periodic model, the part of the turn its readings leave out
            (:func:`unmeasured_arc`), or None.
    """

    device: str
    file: str
    error: str | None = None
    model: str | None = None
    hyperparameters: dict[str, float] = field(default_factory=dict)
    rms_correction: float = float("nan")
    max_u: float = float("nan")
    calibrated_range: tuple[float, float] = (float("nan"), float("nan"))
    points: int = 0
    screening: StageScreening | None = None
    findings: tuple[BoundHit | StageOffset, ...] = ()
    source: Source | None = None
    warnings: tuple[str, ...] = ()
    arc: tuple[float, float] | None = None


def summarize_device(model: CalibrationModel) -> dict[str, object]:
    """Size of a device's correction: RMS correction and largest u over the calibrated
    range (for a periodic model, the turn, less the arc its device readings leave out), on
    a grid of 1001 readings."""
    lo, hi = model.calibrated_range
    if model.periodic:
        lo, hi = measured_arc(model) or (0.0, float(model.period))
    grid = np.linspace(lo, hi, _SUMMARY_GRID)
    c = correct(model, grid)
    device = model.fitted.device
    return {
        "hyperparameters": device.hyperparameters if isinstance(device, FittedGP) else {},
        "rms_correction": float(np.sqrt(np.mean((c.corrected - grid) ** 2))),
        "max_u": float(np.max(c.u)),
    }


def fit_devices(
    testbed: str | os.PathLike,
    devices: Sequence[str | os.PathLike],
    outdir: str | os.PathLike,
    *,
    options: dict[str, object],
    jobs: int = 1,
    on_result: Callable[[DeviceResult], None] | None = None,
) -> list[DeviceResult]:
    """Fit each device file against one fitted test-bed model, in parallel processes.

    Args:
        testbed: A one-stage model file (the test bed against the reference).
        devices: Device stage files (device readings, test-bed readings).
        outdir: Folder for the device models, ``<device stem>.json``.
        options: ``x_column``, ``y_column`` for the files; ``method``, ``kernel``, ``period``,
            ``unit``, ``n_restarts``, ``seed``, ``mean`` as for :func:`fit_model` (every device gets
            the same seed, so its model equals ``cascal fit TESTBED DEVICE`` with it).
            ``exclude``: file rows to leave out, by device file path as in ``devices``;
            ``screening_level``: false-alarm level of the outlier screening of each device
            file (default 1 %; None skips it).
        jobs: Worker processes; 1 fits in this process.
        on_result: Called with each result as it completes.

    Returns:
        One result per device, in the order of ``devices``; a bad device file has
        ``error`` set and no model, the others complete.
    """
    exclude = {str(Path(k)): v for k, v in dict(options.get("exclude") or {}).items()}  # type: ignore[call-overload]
    unknown = sorted(set(exclude) - {str(Path(d)) for d in devices})
    if unknown:
        raise InputError(f"exclude: {unknown[0]} is none of the device files")
    options = dict(options, exclude=exclude)
    jobs_args = [(str(testbed), str(Path(d)), str(model_path(outdir, d)), options) for d in devices]
    results: dict[int, DeviceResult] = {}

    def done(i: int, res: DeviceResult) -> None:
        results[i] = res
        if on_result is not None:
            on_result(res)

    if jobs <= 1 or len(devices) <= 1:
        for i, a in enumerate(jobs_args):
            done(i, _device_job(*a))
    else:
        stop = multiprocessing.get_context("spawn").Event()  # set on an interrupt
        ex = pool.spawn_pool(min(jobs, len(devices)), _init_worker, (stop,))
        futures: dict[cf.Future, int] = {}
        try:
            submitted = pool.submit_all(ex, _device_job, jobs_args)
            futures = dict(zip(submitted, range(len(devices)), strict=True))
            for fut in cf.as_completed(futures):
                done(futures[fut], fut.result())
        except BaseException as exc:  # Ctrl-C: the devices under way finish, no other starts
            stop.set()
            interrupted = isinstance(exc, KeyboardInterrupt)
            stopped = pool.shutdown(ex, wait_for_tasks=True, interrupted=interrupted)
            for fut, i in futures.items():  # those that finished meanwhile are reported
                if i not in results and fut.done() and not fut.cancelled():
                    if fut.exception() is None:
                        done(i, fut.result())
                    elif stopped:  # a worker stopped by a second Ctrl-C
                        _, device, out, _ = jobs_args[i]
                        discard_model(out)
                        done(i, DeviceResult(Path(device).stem, device, error=INTERRUPTED))
            raise
        pool.shutdown(ex, wait_for_tasks=True, interrupted=False)
    return [results[i] for i in range(len(devices))]


#: The error of a device that an interrupt left unfitted.
INTERRUPTED = "not fitted: the fleet was interrupted"

#: In a worker process of :func:`fit_devices`: the event set when the fleet is interrupted.
_STOP = None


def model_path(outdir: str | os.PathLike, device: str | os.PathLike) -> Path:
    """Where :func:`fit_devices` writes the model of the device file ``device``."""
    return Path(outdir) / f"{Path(device).stem}.json"


def discard_model(out: str | os.PathLike) -> None:
    """Remove the model path ``out`` of a device left unfitted, and any temporary file a
    worker stopped mid-device left beside it: as for a device that failed, no model (of
    this run or an earlier one) stays where the summary says "not fitted"."""
    path = Path(out)
    for tmp in [path, *path.parent.glob(f".{path.name}.*.tmp")]:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _init_worker(stop) -> None:
    """Worker start: Ctrl-C is the parent's to handle (a device under way finishes, and
    its model is whole); ``stop`` tells the worker to start no further device. BLAS runs
    on one thread: the workers share the cores, and a review found models of workers on
    two BLAS threads each differing from `cascal fit`'s in their last digits."""
    global _STOP
    pool.ignore_interrupts()
    pin_blas()
    _STOP = stop


def _device_job(testbed: str, device: str, out: str, options: dict[str, object]) -> DeviceResult:
    """Fit one device (runs in a worker process). Any failure becomes a skipped result (a
    fleet does not stop for one device), and a model of an earlier run at ``out`` goes."""
    name = Path(device).stem
    if _STOP is not None and _STOP.is_set():
        discard_model(out)
        return DeviceResult(name, device, error=INTERRUPTED)
    with warnings.catch_warnings(record=True) as caught:  # to the summary, not a worker's stderr
        warnings.simplefilter("always", CascalWarning)
        res = _device_fit(testbed, device, out, options, name)
    ours = [w for w in caught if issubclass(w.category, CascalWarning)]
    for w in caught:  # the others as usual
        if w not in ours:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return replace(res, warnings=tuple(str(w.message) for w in ours)) if ours else res


def _device_fit(
    testbed: str, device: str, out: str, options: dict[str, object], name: str
) -> DeviceResult:
    try:
        prefix = load_model(testbed)
        data = read_stage(
            device,
            x_column=options.get("x_column"),  # type: ignore[arg-type]
            y_column=options.get("y_column"),  # type: ignore[arg-type]
            period=options.get("period") if options.get("kernel") == "periodic" else None,  # type: ignore[arg-type]
            exclude=options.get("exclude", {}).get(device, ()),  # type: ignore[attr-defined]
        )
        if data.source.sha256 == prefix.sources[0].sha256:  # (a review: a copy in the folder)
            raise InputError(
                f"the test bed's own stage file ({prefix.sources[0].file}, the same "
                "SHA-256), not a device file",
                file=device,
            )
        fit_opts = {
            k: options[k]
            for k in ("method", "kernel", "period", "unit", "n_restarts", "seed", "mean")
            if k in options
        }
        model = fit_model([data], prefix=prefix, **fit_opts)  # type: ignore[arg-type]
        level = options.get("screening_level", LEVEL)
        check = None
        if level is not None:
            (check,) = screen_stages(model, [data], level=float(level))  # type: ignore[arg-type]
        path = save_model(out, model)
        s = summarize_device(model)
    except (CascalError, OSError) as exc:
        error = str(exc)
    except Exception as exc:  # reported, with its type, in the fleet summary
        error = f"unexpected {type(exc).__name__}: {exc}"
    else:
        error = None
    if error is not None:
        discard_model(out)
        return DeviceResult(name, device, error=error)
    return DeviceResult(
        name,
        device,
        model=str(path),
        hyperparameters=s["hyperparameters"],  # type: ignore[arg-type]
        rms_correction=s["rms_correction"],  # type: ignore[arg-type]
        max_u=s["max_u"],  # type: ignore[arg-type]
        calibrated_range=model.calibrated_range,
        arc=unmeasured_arc(model),
        points=int(data.x.size),
        screening=check,
        findings=tuple(fit_findings(model, first=len(model.fitted.models) - 1)),
        source=data.source,
    )
