"""A self-contained HTML calibration report: tables and figures (embedded PNG), no numerics.

The numbers come from :mod:`cascal.reportdata`; this module draws them with matplotlib
(``Figure``, not pyplot) and writes one HTML page with every figure inlined as base64, so
the page can be mailed or archived as a single file.
"""

from __future__ import annotations

import base64
import html
import io
import math

import numpy as np
from matplotlib.figure import Figure

from ._version import __version__
from .compensation import in_arc
from .errors import CascalError
from .gp import Z95
from .io.modelfile import CalibrationModel
from .planning import NOISE_FLOOR, default_noise_variance
from .plots import figure_style, plot_change, plot_plan, plot_verification, set_title
from .reportdata import CurveView, StageView, correction_curve, stage_views
from .screening import LEVEL, Screening
from .text import (
    arc_text,
    caution_lines,
    hyperparameter_unit,
    outward_ends,
    range_text,
    shown,
    understates_u,
)
from .verification import Comparison, Verification
from .workflow import MeasurementPlan, arc_width, plan_measurements, summarize_device

__all__ = [
    "build_report",
    "comparison_figure",
    "correction_figure",
    "display_scale",
    "plan_figure",
    "stage_figure",
    "verification_figure",
]

#: Units shown with a smaller SI prefix where values are small: each one's ladder.
_LADDERS = {
    "m": (("m", 1.0), ("mm", 1e3), ("µm", 1e6), ("nm", 1e9)),
    "mm": (("mm", 1.0), ("µm", 1e3), ("nm", 1e6)),
    "µm": (("µm", 1.0), ("nm", 1e3)),
    "um": (("um", 1.0), ("nm", 1e3)),
    "rad": (("rad", 1.0), ("mrad", 1e3), ("µrad", 1e6), ("nrad", 1e9)),
    "mrad": (("mrad", 1.0), ("µrad", 1e3), ("nrad", 1e6)),
}
_GAP_STYLE = dict(color="0.55", alpha=0.25, lw=0, hatch="//")
#: The part of the turn a rotary device's readings leave out (flagged by correct).
_ARC_STYLE = dict(color="C3", alpha=0.15, lw=0, hatch="\\\\")


def display_scale(unit: str, magnitude: float) -> tuple[float, str]:
    """Factor and unit to show corrections of about ``magnitude`` (in ``unit``) readably:
    metres, millimetres and radians get a smaller SI prefix (values of 1 or more shown,
    no detached multiplier beside the axis: a review read +-6e-6 rad as +-6 rad), small
    angles in degrees become arcseconds."""
    magnitude = abs(float(magnitude))
    ladder = _LADDERS.get(unit)
    if ladder is not None and magnitude > 0:
        for name, f in ladder:
            if magnitude * f >= 1.0:
                return f, name
        return ladder[-1][1], ladder[-1][0]
    if unit in ("deg", "°") and 0 < magnitude < 0.1:
        return 3600.0, "arcsec"
    return 1.0, unit


@figure_style
def stage_figure(view: StageView, *, unit: str, period: float | None = None) -> Figure:
    """One stage: above, the data and the fit as corrections (more accurate reading minus
    reading); below, the residuals about the fit with the fit's 95 % band and the 95 % band
    of the targets' noise. The stretches the reference could not reach are hatched."""
    table = view.band is None  # a lookup table passes through its points: no residuals
    fig = Figure(figsize=(8.0, 3.4 if table else 5.8), layout="constrained")
    ax, rx = (fig.subplots(), None) if table else fig.subplots(2, 1, sharex=True)
    corr = view.targets - view.x
    x, at = _drawn(view.x, view.grid, period)  # where the axis shows each reading (at: which)
    corr = corr[at]
    f, su = display_scale(unit, float(np.max(np.abs(corr))) if corr.size else 0.0)
    ax.plot(view.grid, (view.mean - view.grid) * f, color="C0", lw=1.5, label="fit")
    if view.target_sd is not None:
        ax.errorbar(
            x, corr * f, yerr=Z95 * view.target_sd[at] * f, fmt=".", color="k", ms=3,
            elinewidth=0.6, label="targets (95 % known noise)",
        )  # fmt: skip
    else:
        ax.plot(x, corr * f, "k.", ms=4, label="data")
    _shade(ax, view.gaps, period, "reference could not measure")
    ax.set_ylabel(f"correction [{su}]")
    ax.legend(fontsize=7, loc="best")
    set_title(ax, f"{view.name}: more accurate reading minus reading")
    if rx is None:
        ax.set_xlabel(f"reading [{unit}]")
        _seams(ax, period=period, grid=view.grid)
        return fig
    seen = _measured(view.grid, view.arc, period)  # (the arc left out: the band clipped)
    scale = max(
        np.max(np.abs(view.residuals), initial=0.0),
        np.max(view.band[seen], initial=0.0) if view.band is not None else 0.0,
        np.max(view.residual_band, initial=0.0) if view.residual_band is not None else 0.0,
    )
    fr, sr = display_scale(unit, float(scale) or 1.0)
    if view.band is not None:
        b = view.band * fr
        rx.fill_between(
            view.grid, -b, b, color="C0", alpha=0.25, lw=0, label="95 % band of the fit"
        )
    if view.residual_band is not None:
        order = np.argsort(x)
        xb, b = x[order], view.residual_band[at][order] * fr
        rx.plot(xb, b, color="C2", lw=0.8, label="95 % of target noise")
        rx.plot(xb, -b, color="C2", lw=0.8)
    rx.axhline(0.0, color="0.3", lw=0.8)
    rx.plot(x, view.residuals[at] * fr, ".", color="C3", ms=4, label="residual (target - fit)")
    sus = np.isin(at, [q.index for q in view.screening.suspects] if view.screening else [])
    if np.any(sus):
        rx.plot(
            x[sus], view.residuals[at][sus] * fr, "o", mfc="none", mec="k", ms=9, mew=1.2,
            label="suspect (outlier screening)",
        )  # fmt: skip
    _shade(rx, view.gaps, period, None)
    if view.arc is not None and not seen.all():
        if view.band is not None and np.max(view.band) > 1.15 * scale:
            rx.set_ylim(-1.15 * scale * fr, 1.15 * scale * fr)
        _shade_arc(ax, rx, arc=view.arc, period=period)
        ax.legend(fontsize=7, loc="best")  # again, with the arc
    rx.set_ylabel(f"residual, target - fit [{sr}]")
    rx.set_xlabel(f"reading [{unit}]")
    rx.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    _seams(ax, rx, period=period, grid=view.grid)
    return fig


@figure_style
def correction_figure(curve: CurveView, *, unit: str, period: float | None = None) -> Figure:
    """Final correction (corrected minus device reading) and, below, its expanded
    uncertainty U = 2u as a band about the correction."""
    has_u = curve.u is not None
    fig = Figure(figsize=(8.0, 5.4 if has_u else 3.6), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True) if has_u else [fig.subplots()]
    ax = axes[0]
    f, su = display_scale(unit, float(np.max(np.abs(curve.correction))))
    ax.plot(curve.grid, curve.correction * f, color="C0", lw=1.5, label="correction")
    ax.set_ylabel(f"corrected - reading [{su}]")
    if has_u:
        U = 2.0 * curve.u  # type: ignore[operator]
        seen = _measured(curve.grid, curve.arc, period)  # the arc left out: U there clipped
        top = float(np.max(U[seen], initial=0.0)) or float(np.max(U))
        fu, uu = display_scale(unit, top)
        clipped = bool(np.max(U) > 1.15 * top)
        label = "± U (k = 2), off the axis in the arc left out" if clipped else "± U (k = 2)"
        axes[1].fill_between(curve.grid, -U * fu, U * fu, color="C0", alpha=0.3, lw=0, label=label)
        axes[1].axhline(0.0, color="0.3", lw=0.8)
        axes[1].set_ylabel(f"expanded uncertainty [{uu}]")
        if clipped:
            axes[1].set_ylim(-1.15 * top * fu, 1.15 * top * fu)
    for a in axes:
        _shade(a, curve.gaps, period, "reference could not measure" if a is ax else None)
        if curve.arc is not None and period is not None:  # (a review: drawn unmarked)
            _shade_arc(a, arc=curve.arc, period=period, label=a is ax)
        if period is None:
            for edge in curve.calibrated_range:
                a.axvline(edge, color="0.4", ls=":", lw=1)
        a.legend(fontsize=7, loc="best")
    _seams(*axes, period=period, grid=curve.grid)
    axes[-1].set_xlabel(f"device reading [{unit}]")
    return fig


def _drawn(x: np.ndarray, grid: np.ndarray, period: float | None):
    """Where a figure draws readings ``x`` (n,), and which reading each is: ``(positions
    (d,), indices (d,))``. A periodic stage's readings are moved by whole periods onto the
    turn the figure shows (a review: those of another turn fell off the axis), and those
    within an eighth of a period of its seams drawn again beyond them, where the axis goes
    on (they had looked unmeasured there); others as given."""
    index = np.arange(x.size)
    if period is None:
        return x, index
    origin = float(grid[0]) + period / 8
    on = origin + np.mod(x - origin, period)
    copies = [on, on - period, on + period]
    keep = [(c >= grid[0]) & (c <= grid[-1]) for c in copies]
    return (
        np.concatenate([c[k] for c, k in zip(copies, keep, strict=True)]),
        np.concatenate([index[k] for k in keep]),
    )


def _measured(grid: np.ndarray, arc: tuple[float, float] | None, period: float | None):
    """True (g,) where ``grid`` lies outside a periodic model's arc its device readings
    leave out (everywhere without one): the figures' axes are scaled there, so that the
    extrapolation across that arc (U of 250 arcsec beside 1 arcsec measured: a review)
    does not flatten what was calibrated."""
    if arc is None or period is None:
        return np.ones(grid.shape, bool)
    return ~in_arc(grid, arc_width(arc, period), period)


def _shade_arc(*axes, arc: tuple[float, float], period: float | None, label: bool = True) -> None:
    """Shade a periodic model's arc its device readings leave out on ``axes`` (the first
    labelled, where ``label``)."""
    if period is None:
        return
    start, width = arc_width(arc, period)
    for k, a in enumerate(axes):
        name = "device readings leave out (flagged)" if label and k == 0 else None
        _shade(a, [(start, start + width)], period, name, _ARC_STYLE)


def _shade(ax, gaps, period, label, style=None) -> None:
    """Shade the stretches ``gaps`` (in every turn shown, for a ``period``)."""
    for a, b in gaps:
        spans = (
            [(a, b)]
            if period is None
            else [(a - period, b - period), (a, b), (a + period, b + period)]
        )
        for lo, hi in spans:
            ax.axvspan(lo, hi, label=label, **(style or _GAP_STYLE))
            label = None


def _seams(*axes, period, grid) -> None:
    """Dashed lines where a periodic reading wraps; the grid starts an eighth before."""
    if period is None:
        return
    origin = float(grid[0]) + period / 8
    for ax in axes:
        for s in (origin, origin + period):
            ax.axvline(s, color="0.2", ls="--", lw=0.8)
        ax.set_xlim(float(grid[0]), float(grid[-1]))


def _stretch(a: float, b: float, period: float | None) -> str:
    """``[a, b]``; on a rotary axis both ends on one turn, ``a to b (across 0)`` where the
    stretch passes the zero."""
    if period is None:
        return "[{}, {}]".format(*outward_ends(a, b))
    lo, hi = outward_ends(a % period, b % period)
    if float(hi) < float(lo):
        return f"{lo} to {hi} (across 0)"
    return f"[{lo}, {hi}]"


def _png(fig: Figure) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def build_report(
    model: CalibrationModel,
    *,
    title: str = "cascal calibration report",
    source: str = "",
    checksum: str | None = None,
    sha256: str | None = None,
) -> str:
    """The report of ``model`` as one self-contained HTML page.

    Args:
        model: A loaded or freshly fitted model.
        title: Page title.
        source: Name of the model file, shown in the summary.
        checksum: The model file's content checksum (sha256, hex), shown where given, as
            ``cascal info`` shows it: it ties the report to one model file (a review).
        sha256: The SHA-256 of the model file itself, shown where given.
    """
    e = html.escape
    unit = model.unit
    lo, hi = model.calibrated_range
    rng = arc_text(model) or (
        "full turn (period " + _num(model.period) + f" {unit})"
        if model.periodic
        else f"{range_text(lo, hi)} {unit}"
    )
    summary = [
        ("model file", source or "(in memory)"),
        *([("content checksum (sha256)", checksum)] if checksum else []),
        *([("SHA-256 of the file", sha256)] if sha256 else []),
        ("method", model.method),
        ("kernel", model.kernel or "none (lookup tables)"),
        ("unit", unit),
        ("calibrated device range", rng),
        ("stages", str(len(model.data))),
        (
            "fitted",
            f"{model.created or '(not saved yet)'} with cascal "
            f"{model.cascal_version or __version__}, seed {model.seed}"
            + (
                ""
                if model.kernel is None
                else f", up to {model.n_restarts} optimiser starts per stage"
            ),
        ),
    ]
    parts = [
        f"<h1>{e(title)}</h1>",
        _table(["", ""], summary, header=False),
        *_cautions(model),
        "<h2>Input files</h2>",
        _table(
            ["stage", "file", "rows", "rows left out", "points", "columns", "SHA-256"],
            [
                (
                    str(k),
                    shown(s.file),
                    str(s.rows),
                    ", ".join(map(str, s.excluded)) or "none",
                    str(c.size),
                    ", ".join(s.columns),
                    s.sha256,
                )
                for k, (s, c) in enumerate(zip(model.sources, model.counts, strict=True))
            ],
        ),
    ]
    for k, view in enumerate(stage_views(model)):
        parts.append(f"<h2>Stage {k}: {e(view.name)}</h2>")
        cols = model.sources[k].columns
        reps = int(np.sum(view.counts > 1))
        parts.append(
            f"<p>Maps readings of <b>{e(cols[0])}</b> to readings of <b>{e(cols[1])}</b>"
            + (" corrected by the stage above" if k else "")
            + f": {view.x.size} points"
            + (f", {reps} of them averages of repeated readings" if reps else "")
            + ".</p>"
        )
        if view.hyperparameters:
            rows = [
                (n, _num(v) + hyperparameter_unit(n, unit, model.periodic))
                for n, v in view.hyperparameters.items()
            ]
            if view.log_marginal_likelihood is not None:
                rows.append(("log marginal likelihood", _num(view.log_marginal_likelihood)))
            parts.append(_table(["hyperparameter", "value"], rows))
        else:
            parts.append(  # (a report review: nothing said the table was not screened)
                "<p>Lookup table: linear interpolation, no uncertainty. Outlier screening does "
                "not apply (no noise model): the table passes through every point, an outlier "
                "too; <code>cascal fit</code> checked the spread of repeated readings only.</p>"
            )
        if view.screening is not None:
            parts.append(_screening_html(view.screening, unit, bool(np.any(view.counts > 1))))
        if view.gaps:
            text = ", ".join(_stretch(a, b, model.period) for a, b in view.gaps)
            parts.append(
                f"<p>Stretches where the reference could not measure ({e(unit)}): {e(text)}.</p>"
            )
        parts.append(_img(stage_figure(view, unit=unit, period=model.period), f"stage {k} fit"))
    curve = correction_curve(model)
    parts.append("<h2>Correction of device readings</h2>")
    cover = (  # (a report review: "about 95 %" right below a caution saying 66 %)
        "nominally 95 %; this method's covered far less in simulations, see Cautions"
        if understates_u(model)
        else "about 95 %"
    )
    note = (
        f"The band is the expanded uncertainty U = 2u of the correction ({cover}). It is the "
        "uncertainty of the calibration map at a reading; the repeatability of a single reading "
        "comes on top."
        if curve.u is not None
        else "Lookup tables give no uncertainty."
    )
    parts.append(f"<p>{e(note)}</p>")
    size = summarize_device(model)  # (as info gives them: a rotary device's unmeasured arc
    # left out; the RMS correction had been info's alone, a review found)
    rms = _quantity(float(size["rms_correction"]), unit)
    parts.append(f"<p>RMS correction over the calibrated range: {e(rms)}.</p>")
    if curve.u is not None:
        largest = float(size["max_u"])
        parts.append(f"<p>Largest u over the calibrated range: {e(_quantity(largest, unit))}.</p>")
    parts.append(_img(correction_figure(curve, unit=unit, period=model.period), "final correction"))
    if curve.u is not None:
        parts += _plan_section(model)
    body = "\n".join(parts)
    return (
        '<!doctype html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{e(title)}</title><style>{_CSS}</style></head>\n<body>\n{body}\n</body></html>\n"
    )


def _cautions(model: CalibrationModel) -> list[str]:
    """What ``cascal fit`` warned of, as far as the model shows it (:func:`caution_lines`),
    as a heading and a list; none where there is nothing."""
    lines = caution_lines(model)
    if not lines:
        return []
    items = "".join(f"<li>{html.escape(line)}</li>" for line in lines)
    return ['<h2 class="warn">Cautions</h2>', f"<ul>{items}</ul>"]


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'s' * (n != 1)}"


def _screening_html(s: Screening, unit: str, repeats: bool) -> str:
    """The stage's outlier screening: a sentence, and a table of the suspects."""
    level = f"{LEVEL * 100:g} %"
    also = (
        " Repeated readings are averaged first: their spread is checked by cascal fit (its"
        " warnings), not here."
        if repeats
        else ""
    )
    if not s.detectable:
        return (
            f"<p>Outlier screening: {s.z.size} points are too few for the leave-one-out check "
            f"to find an outlier at the {level} level.{also}</p>"
        )
    if not s.suspects:
        return (
            f"<p>Outlier screening: every point agrees with the others' prediction of it "
            f"(leave-one-out, |z| below {s.threshold:.2f}, the {level} false-alarm level of the "
            f"stage).{also}</p>"
        )
    # readings and targets to 10 digits, with the difference z is about in its own column:
    # to 6 digits, a target and its prediction near 1000 mm printed alike (a report review)
    rows = [
        (
            f"{q.reading:.10g}",
            f"{q.target:.10g}",
            f"{q.predicted:.10g}",
            f"{q.target - q.predicted:+.4g}",
            f"{q.std:.4g}",
            f"{q.z:+.1f}",
        )
        for q in s.suspects
    ]
    names = ("reading", "target", "predicted by the others", "target - predicted", "u")
    head = [f"{h} [{unit}]" for h in names]
    head.append("z = (target - predicted) / u")
    k = len(s.suspects)
    cap = " More points disagree than the screening takes out: the model is in doubt."
    noise = (
        f" Without {'them' if k > 1 else 'it'} the learned noise would be "
        f"{html.escape(_quantity(s.noise_std_without, unit))} instead of "
        f"{html.escape(_quantity(s.noise_std, unit))}."
        if s.noise_std_without != s.noise_std
        else ""
    )
    return (
        f"<p class='warn'>Outlier screening: {_count(k, 'point')} the others do not support "
        f"(|z| above {s.threshold:.2f}, the {level} false-alarm level of the stage; circled "
        f"in the residuals).{noise} Check {'those measurements' if k > 1 else 'that measurement'}."
        f"{cap if s.capped else ''}{also}</p>" + _table(head, rows)
    )


#: Reference measurements the report proposes.
_PLAN_MEASUREMENTS = 5


def _plan_section(model: CalibrationModel) -> list[str]:
    """Where the next reference measurements help most (``cascal plan``'s defaults)."""
    e, unit = html.escape, model.unit
    out = ["<h2>Where to measure next with the reference</h2>"]
    try:
        mp = plan_measurements(model, _PLAN_MEASUREMENTS)
    except CascalError as exc:
        return [*out, f"<p>No plan: {e(str(exc))}</p>"]
    plan = mp.plan
    sd = _quantity(float(np.sqrt(plan.noise_variance)), unit)
    average = default_noise_variance(model.fitted.models[0])  # type: ignore[arg-type]
    precision = (  # (a review: the floor had been called the average point's precision)
        f"each as precise as the average existing point, repeated readings averaged as there "
        f"(standard deviation {sd})"
        if plan.noise_variance <= average
        else f"each with a standard deviation of {sd}, the planner's floor ({NOISE_FLOOR:g} "
        f"of stage 0's prior variance), above the average existing point's "
        f"{_quantity(float(np.sqrt(average)), unit)}"
    )
    reach = ", ".join(range_text(a, b) for a, b in mp.reach)  # (inward: a review)
    out.append(
        f"<p>{plan.positions.size} further reference measurements of stage 0, chosen one at a "
        f"time among the test-bed readings the reference points cover ({e(reach)} {e(unit)}), "
        f"each where it most lowers {e(mp.target)}; {e(precision)}. <code>cascal plan</code> "
        "proposes more, within other reach, or for another precision (--noise-std).</p>"
    )
    f, shown = display_scale(unit, float(plan.u_max[0]))  # the figure's unit
    rows = [("now", "", _num(plan.u_rms[0] * f), _num(plan.u_max[0] * f))]
    rows += [
        (str(k), _num(p), _num(plan.u_rms[k] * f), _num(plan.u_max[k] * f))
        for k, p in enumerate(plan.positions, 1)
    ]
    head = [
        "order",
        f"test-bed reading [{unit}]",
        f"RMS u after [{shown}]",
        f"largest u after [{shown}]",
    ]
    out.append(_table(head, rows))
    return [*out, _img(plan_figure(model, mp), "proposed reference measurements")]


def plan_figure(model: CalibrationModel, mp: MeasurementPlan) -> Figure:
    """The figure of a plan of ``model``'s reference measurements, in readable units."""
    scale, shown = display_scale(model.unit, float(mp.plan.u_max[0]))
    return plot_plan(
        mp.plan,
        model.fitted.models[0],  # type: ignore[arg-type]
        list(mp.reach),
        lower_name=mp.lower_name,
        scale=scale,
        unit=shown,
        xunit=model.unit,
        period=model.period,
    )


def verification_figure(
    model: CalibrationModel, v: Verification, names: tuple[str, str] | None = None
) -> Figure:
    """The figure of a verification of ``model`` at check points, in readable units;
    ``names``: the model's and the check points' file names."""
    e = v.error[v.inside]
    scale, shown = display_scale(model.unit, float(np.max(np.abs(e))) if e.size else 0.0)
    return plot_verification(v, scale=scale, unit=shown, xunit=model.unit, names=names)


def comparison_figure(
    model: CalibrationModel,
    c: Comparison,
    names: tuple[str, str],
    limit: float | None = None,
) -> Figure:
    """The figure of a recalibration's change (``model``: either of the two), in readable
    units, with the largest change allowed (``limit``, the model's unit) where given."""
    top = float(np.max(np.abs(c.change)))
    if limit is not None and limit <= 3.0 * top:  # (a limit far beyond: off the axis)
        top = max(top, limit)
    scale, shown = display_scale(model.unit, top)
    return plot_change(c, scale=scale, unit=shown, xunit=model.unit, names=names, limit=limit)


_CSS = (
    "body{font-family:sans-serif;max-width:60em;margin:2em auto;color:#222}"
    "table{border-collapse:collapse;margin:0.5em 0}td,th{border:1px solid #ccc;padding:2px 8px;"
    "font-size:90%;text-align:left}th{white-space:nowrap}td{overflow-wrap:anywhere}"
    "img{max-width:100%;display:block;margin:0.5em 0}"
    ".warn{color:#a33}"
)


def _table(head: list[str], rows: list[tuple[str, ...]], *, header: bool = True) -> str:
    e = html.escape
    out = ["<table>"]
    if header:
        out.append("<tr>" + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>")
    for r in rows:
        out.append("<tr>" + "".join(f"<td>{e(str(c))}</td>" for c in r) + "</tr>")
    out.append("</table>")
    return "".join(out)


def _img(fig: Figure, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{_png(fig)}">'


def _quantity(v: float | None, unit: str) -> str:
    """A small quantity (an uncertainty, a noise) in ``unit``, and in the unit the figures
    use where that differs: ``7.7213e-05 m (77.2 µm)``."""
    f, shown = display_scale(unit, v or 0.0)
    text = f"{_num(v)} {unit}"
    if shown == unit or v is None or not math.isfinite(v):
        return text
    return f"{text} ({v * f:.3g} {shown})"


def _num(v: float | None) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    return f"{v:.6g}"
