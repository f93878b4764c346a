"""The numbers a calibration report shows, computed from a model (no drawing, no files).

Per stage: the data, the fit with its 95 % band on a grid, residuals with the spread the fit
expected of them, the hyperparameters, and the stretches where the reference could not
measure (gaps in stage 0's readings wider than ``GAP_FACTOR`` times their median spacing,
carried down to each stage's readings through the stages' data), and the points the other
points do not support (:mod:`cascal.screening`). Then the final correction curve with its
uncertainty.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gp import Z95, FittedGP
from .io.modelfile import CalibrationModel
from .planning import GAP_FACTOR, find_gaps
from .screening import Screening, screen
from .workflow import correct, unmeasured_arc

__all__ = [
    "GAP_FACTOR",
    "CurveView",
    "StageView",
    "correction_curve",
    "find_gaps",
    "reference_gaps",
    "stage_views",
]

_GRID = 600


@dataclass(frozen=True, slots=True)
class StageView:
    """One stage as the report shows it; arrays of readings in the model's unit.

    Attributes:
        name: Stage name (its file name).
        x: Readings of the calibrated sensor, shape (n,).
        y: Averaged readings of the more accurate sensor, shape (n,).
        targets: What the stage was fitted to (``y`` for stage 0, the stage above's
            correction of ``y`` below), shape (n,).
        target_sd: Standard deviation of each target's known noise, shape (n,), or None.
        counts: Readings averaged into each point, shape (n,).
        grid: Readings at which the fit is drawn, shape (g,).
        mean: Fitted map on the grid, shape (g,).
        band: Half-width of the 95 % band of the fit on the grid, shape (g,), or None (lut).
        residuals: ``targets - fit(x)``, shape (n,).
        residual_band: Half-width of the 95 % band the residuals should fall in (known and
            learned noise), shape (n,), or None.
        hyperparameters: By name, natural units (empty for lut).
        gaps: Stretches of ``x`` where the reference could not measure, list of (lo, hi).
        log_marginal_likelihood: Of the fitted GP, or None.
        screening: Outlier screening of the GP's points (:func:`cascal.screening.screen`),
            or None (lut).
        arc: For the device stage of a periodic model, the part of the turn its readings
            leave out (:func:`~cascal.workflow.unmeasured_arc`), or None.
    """

    name: str
    x: np.ndarray
    y: np.ndarray
    targets: np.ndarray
    target_sd: np.ndarray | None
    counts: np.ndarray
    grid: np.ndarray
    mean: np.ndarray
    band: np.ndarray | None
    residuals: np.ndarray
    residual_band: np.ndarray | None
    hyperparameters: dict[str, float]
    gaps: list[tuple[float, float]]
    log_marginal_likelihood: float | None
    screening: Screening | None = None
    arc: tuple[float, float] | None = None


@dataclass(frozen=True, slots=True)
class CurveView:
    """The final correction: device reading -> correction, with its uncertainty.

    Attributes:
        grid: Device readings, shape (g,).
        correction: ``corrected - reading``, shape (g,).
        u: Standard uncertainty, shape (g,), or None (lut).
        gaps: Device readings where the reference could not measure, list of (lo, hi).
        calibrated_range: Smallest and largest device reading calibrated.
        arc: For a periodic model, the part of the turn the device readings leave out,
            ``(start, end)`` through the period where ``end < start``
            (:func:`~cascal.workflow.unmeasured_arc`), or None.
    """

    grid: np.ndarray
    correction: np.ndarray
    u: np.ndarray | None
    gaps: list[tuple[float, float]]
    calibrated_range: tuple[float, float]
    arc: tuple[float, float] | None = None


def _carry(
    gaps: list[tuple[float, float]], upper_readings: np.ndarray, x: np.ndarray, period: float | None
) -> list[tuple[float, float]]:
    """Map stretches of the upper sensor's readings to this stage's readings ``x``."""
    order = np.argsort(upper_readings)
    yu, xs = upper_readings[order], x[order]
    if period is not None:
        yu = np.r_[yu - period, yu, yu + period]
        xs = np.r_[xs - period, xs, xs + period]
    return [(float(np.interp(a, yu, xs)), float(np.interp(b, yu, xs))) for a, b in gaps]


def seam(model: CalibrationModel, k: int) -> float:
    """Where the readings of stage ``k`` of a periodic model wrap: the multiple of half a
    period nearest to its smallest reading (0 for readings in [0, 360), -180 for [-180,
    180)). Per stage: a review found a device's 20 to 300 deg drawn on the window of a
    reference's -180 to 180, its readings beyond 225 off the axis."""
    half = 0.5 * float(model.period)  # type: ignore[arg-type]
    return half * round(float(model.data[k].x.min()) / half)


def reference_gaps(model: CalibrationModel) -> list[list[tuple[float, float]]]:
    """Per stage, the stretches of its readings where the reference could not measure."""
    gaps = [find_gaps(model.data[0].x, period=model.period)]
    for data in model.data[1:]:
        gaps.append(_carry(gaps[-1], data.y, data.x, model.period))
    return gaps


def stage_views(model: CalibrationModel) -> list[StageView]:
    """Every stage of ``model`` as the report shows it, reference end first."""
    period = model.period
    views = []
    for k, (data, used, m, gaps) in enumerate(
        zip(
            model.data, model.fitted.stages, model.fitted.models, reference_gaps(model), strict=True
        )
    ):
        lo, hi = float(data.x.min()), float(data.x.max())
        if period is not None:
            o = seam(model, k)
            grid = np.linspace(o - period / 8, o + period * 9 / 8, _GRID)
        else:
            pad = 0.03 * (hi - lo)
            grid = np.linspace(lo - pad, hi + pad, _GRID)
        if isinstance(m, FittedGP):
            mean, std = m.predict(grid, return_std=True)
            known = np.zeros(data.x.size) if m.noise is None else m.noise.diagonal(data.x.size)
            fit_x = m.predict(data.x)
            extra = dict(
                target_sd=None if m.noise is None else np.sqrt(np.clip(known, 0.0, None)),
                mean=mean,
                band=Z95 * std,
                residuals=used.y - fit_x,
                residual_band=Z95 * np.sqrt(np.clip(known + m.noise_variance, 0.0, None)),
                hyperparameters=m.hyperparameters
                | ({"prior mean offset": m.mean.offset} if m.mean.name == "offset" else {}),
                log_marginal_likelihood=m.log_marginal_likelihood,
                screening=screen(m),
            )
        else:
            extra = dict(
                target_sd=None,
                mean=m(grid),
                band=None,
                residuals=used.y - m(data.x),
                residual_band=None,
                hyperparameters={},
                log_marginal_likelihood=None,
            )
        views.append(
            StageView(
                name=data.name,
                x=data.x,
                y=data.y,
                targets=used.y,
                counts=model.counts[k],
                grid=grid,
                gaps=gaps,
                arc=unmeasured_arc(model) if k == len(model.data) - 1 else None,
                **extra,  # type: ignore[arg-type]
            )
        )
    return views


def correction_curve(model: CalibrationModel) -> CurveView:
    """The final correction over the calibrated range; for a periodic model over one period
    from :func:`seam` and an eighth of a period beyond each end, to show the seam."""
    lo, hi = model.calibrated_range
    if model.periodic:
        p, o = float(model.period), seam(model, len(model.data) - 1)  # type: ignore[arg-type]
        grid = np.linspace(o - p / 8, o + p * 9 / 8, _GRID * 2)
    else:
        grid = np.linspace(lo, hi, _GRID * 2)
    c = correct(model, grid)
    u = None if np.all(np.isnan(c.u)) else c.u
    gaps = reference_gaps(model)[-1]
    return CurveView(grid, c.corrected - grid, u, gaps, (lo, hi), unmeasured_arc(model))
