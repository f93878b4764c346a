"""Figures of fits and results (matplotlib only). Plots draw finished results; they never fit.

Every function takes an optional ``fig`` and returns the :class:`~matplotlib.figure.Figure`.
Positions are drawn as corrections ``target - reading`` against the reading, the part of a
calibration map that is not the identity.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np
from matplotlib import rc_context
from matplotlib.figure import Figure

from .cascade import FittedCascade
from .gp import Z95, FittedGP
from .planning import Plan, find_gaps, variance_after
from .verification import Comparison, Verification, breaks

__all__ = [
    "figure_style",
    "plot_cascade",
    "plot_change",
    "plot_cost_distribution",
    "plot_plan",
    "plot_stage",
    "plot_verification",
]

#: Text and axes of cascal's figures: file names and units are drawn as written (a ``$``
#: is no maths; ``dev$^$.csv`` had ended the drawing with a parse error), and tick labels
#: carry no offset (a correction of -100 m had read as 0.04 under a small "-1e2").
_STYLE = {"text.parse_math": False, "axes.formatter.useoffset": False}

F = TypeVar("F", bound=Callable)


def set_title(ax, text: str) -> None:
    """``ax``'s title at 9 pt, each line wrapped to the figure's width as the font draws it
    (a long file name breaks, where a review found it running off both sides; a second
    found a count of 110 characters still too wide for capitals)."""
    import textwrap

    from matplotlib.textpath import TextPath

    # points; drawn text runs some 4 % wider than its path, and the axes (which the title
    # centres on) sit right of the figure's centre by their label
    room = 0.9 * ax.figure.get_figwidth() * 72.0

    def fits(line: str) -> bool:
        return TextPath((0.0, 0.0), line, size=9).get_extents().width <= room

    out = []
    for line in text.split("\n"):
        width = len(line)
        wrapped = [line]
        while width > 10 and not all(fits(part) for part in wrapped):
            width = int(width * 0.9)
            wrapped = textwrap.wrap(line, width, break_on_hyphens=False) or [line]
        out += wrapped
    ax.set_title("\n".join(out), fontsize=9)


def figure_style(draw: F) -> F:
    """Decorator: ``draw`` makes its text and axes in cascal's figure style (:data:`_STYLE`)."""

    @functools.wraps(draw)
    def styled(*args, **kwargs):
        with rc_context(_STYLE):
            return draw(*args, **kwargs)

    return styled  # type: ignore[return-value]


#: A plan's figure numbers this many of its first proposals.
_NUMBERED = 12
#: Width of a character of a plan's order labels, as a fraction of the axes' span (7 pt
#: on a 7.5 in figure, with a margin): labels closer than their text go a line higher.
_LABEL_CHAR = 0.009
#: A verification figure draws U as a band from this many check points, else error bars.
_BAND_POINTS = 50


@figure_style
def plot_stage(
    gp: FittedGP,
    *,
    ax=None,
    grid: np.ndarray | None = None,
    truth=None,
    label: str = "fit",
    color: str = "C0",
    errorbars: np.ndarray | None = None,
    scale: float = 1.0,
    unit: str = "m",
    xunit: str = "m",
    relative_to=None,
):
    """Draw one GP stage: data, posterior mean and 95 % band, optionally the true map.

    Args:
        gp: The fitted stage.
        ax: Axes to draw on (a new figure if None).
        grid: Readings to draw the fit at, shape (m,); default 400 points over the data.
        truth: Optional callable reading -> true position, drawn dashed.
        errorbars: Optional 95 % half-widths of the targets, shape (n,).
        scale: Factor applied to corrections (e.g. 1e6 for micrometres), with ``unit``.
        xunit: Unit of the readings on the horizontal axis.
        relative_to: Callable reading -> position subtracted from everything drawn; default
            the reading itself (corrections). With the true map, errors are drawn.
    """
    if ax is None:
        ax = Figure(figsize=(7, 4), layout="constrained").subplots()
    if grid is None:
        lo, hi = float(gp.x.min()), float(gp.x.max())
        grid = np.linspace(lo, hi, 400)
    ref = (lambda r: r) if relative_to is None else relative_to
    base = ref(grid)
    mean, std = gp.predict(grid, return_std=True)
    ax.fill_between(
        grid,
        (mean - Z95 * std - base) * scale,
        (mean + Z95 * std - base) * scale,
        color=color,
        alpha=0.2,
        lw=0,
        label=f"{label}: 95 % band",
    )
    ax.plot(grid, (mean - base) * scale, color=color, lw=1.5, label=f"{label}: mean")
    offsets = (gp.y - ref(gp.x)) * scale
    if errorbars is not None:
        ax.errorbar(
            gp.x,
            offsets,
            yerr=errorbars * scale,
            fmt=".",
            ms=3,
            color="k",
            elinewidth=0.6,
            alpha=0.7,
            label="targets (95 % of previous stage)",
        )
    else:
        ax.plot(gp.x, offsets, "k.", ms=4, label="data")
    if truth is not None:
        ax.plot(grid, (truth(grid) - base) * scale, "r--", lw=1, label="true map")
    ax.set_xlabel(f"reading [{xunit}]")
    what = "correction" if relative_to is None else "deviation from true map"
    ax.set_ylabel(f"{what} [{unit}]")
    ax.legend(fontsize=7, loc="best")
    return ax.figure


@figure_style
def plot_cascade(
    fitted: FittedCascade,
    *,
    truths: list | None = None,
    fig: Figure | None = None,
    scale: float = 1e6,
    unit: str = "µm",
    upper: Sequence[np.ndarray] = (),
) -> Figure:
    """One panel per GP stage, like the paper's Fig. 4: stage fits with their 95 % bands.

    Args:
        fitted: A fitted ``bayes`` or ``homoscedastic`` cascade.
        truths: Optional per-stage true maps (callables reading -> true position); when
            given, each panel shows deviations from the true map, so the bands are visible.
        fig: Figure to draw into (a new one if None).
        scale, unit: Display scale for corrections (default micrometres).
        upper: ``upper[k]``: the readings of stage ``k + 1``'s more accurate sensor, at
            which stage ``k`` was evaluated for its targets, shape (n,): stage ``k`` is
            drawn over them too, where it extrapolates (``truths[k]`` must hold there). Stage
            0 gets its gaps and ends hatched.
    """
    models = [m for m in fitted.models if isinstance(m, FittedGP)]
    if not models:
        raise ValueError("plot_cascade needs a GP cascade ('bayes' or 'homoscedastic')")
    if fig is None:
        fig = Figure(figsize=(7.5, 3.2 * len(models)), layout="constrained")
    axes = np.atleast_1d(fig.subplots(len(models), 1))
    for k, (gp, ax) in enumerate(zip(models, axes, strict=True)):
        bars = None
        if k > 0 and gp.noise is not None:
            bars = Z95 * np.sqrt(np.clip(gp.noise.diagonal(gp.x.size), 0.0, None))
        truth = truths[k] if truths is not None else None
        # drawn over the readings the next stage asks of it too, where it extrapolates
        # (a review: the ends the reference could not reach were off the example's figure)
        used = gp.x if k >= len(upper) else np.r_[gp.x, np.asarray(upper[k], float)]
        grid = np.linspace(float(used.min()), float(used.max()), 400)
        plot_stage(
            gp,
            ax=ax,
            grid=grid,
            truth=truth,
            errorbars=bars,
            scale=scale,
            unit=unit,
            label=f"stage {k}",
            color=f"C{k}",
            relative_to=truth,
        )
        if k == 0:  # where the reference could not measure: its gaps and beyond its ends
            lo, hi = float(gp.x.min()), float(gp.x.max())
            spans = [(grid[0], lo), *find_gaps(gp.x), (hi, grid[-1])]
            for j, (a, b) in enumerate((a, b) for a, b in spans if b > a):
                label = "reference could not measure" if j == 0 else None
                ax.axvspan(a, b, color="0.55", alpha=0.2, lw=0, hatch="//", label=label)
            ax.legend(fontsize=7, loc="best")
        set_title(ax, f"stage {k} ({fitted.stages[k].name}), method {fitted.method}")
    return fig


@figure_style
def plot_cost_distribution(
    costs: dict[str, object], *, fig: Figure | None = None, scale: float = 1e6, unit: str = "µm"
) -> Figure:
    """Normalised empirical PDFs and CDFs of J per method on a log axis (the paper's Fig. 5).

    Args:
        costs: J per method, each of shape (n_trials,), in m.
        fig: Figure to draw into (a new one if None).
        scale, unit: Display scale of J (default micrometres).
    """
    if fig is None:  # (margins fixed for the legend: constrained layout added 0.3 s to
        # the study's PNG and SVG of 12 000 trials)
        fig = Figure(figsize=(7.5, 5.5))
        fig.subplots_adjust(left=0.1, right=0.66, bottom=0.1, top=0.94, hspace=0.08)
    ax_pdf, ax_cdf = fig.subplots(2, 1, sharex=True)
    arrays = {m: np.sort(np.asarray(j, dtype=float)) * scale for m, j in costs.items()}
    positive = np.concatenate([a[a > 0] for a in arrays.values()])
    edges = np.geomspace(positive.min(), positive.max(), 60)
    for k, (m, j) in enumerate(arrays.items()):
        hist, _ = np.histogram(j, bins=edges)
        pdf = hist / max(hist.max(), 1)
        centres = np.sqrt(edges[:-1] * edges[1:])
        median = float(np.median(j))
        text = f"{median:.0f}" if abs(median) >= 100 else f"{median:.3g}"  # no 1.53e+03
        ax_pdf.plot(centres, pdf, color=f"C{k}", label=f"{m} (median {text} {unit})")
        ax_cdf.step(j, np.arange(1, j.size + 1) / j.size, where="post", color=f"C{k}", label=m)
    ax_pdf.set_xscale("log")
    ax_pdf.set_ylabel("normalised empirical PDF")
    ax_pdf.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    ax_cdf.set_ylabel("empirical CDF")
    ax_cdf.set_xlabel(f"J [{unit}]")
    ax_cdf.set_ylim(0, 1)
    n = len(next(iter(arrays.values())))
    ax_pdf.set_title(f"Cost J over {n} trials", fontsize=9)
    for ax in (ax_pdf, ax_cdf):
        ax.grid(True, which="both", alpha=0.3)
    return fig


@figure_style
def plot_plan(
    plan: Plan,
    testbed: FittedGP,
    reach: list[tuple[float, float]],
    *,
    lower_name: str | None = None,
    fig: Figure | None = None,
    scale: float = 1.0,
    unit: str = "m",
    xunit: str = "m",
    period: float | None = None,
) -> Figure:
    """Proposed reference measurements: stage 0's standard uncertainty now and after them,
    with the existing reference points, the reachable intervals and the proposals; and,
    when the target is the stage below (``lower_name``), that stage's uncertainty too.

    Args:
        plan: The plan of :func:`cascal.planning.plan_reference`.
        testbed: Stage 0's fitted GP.
        reach: Intervals ``(lo, hi)`` of test-bed readings the reference can reach.
        lower_name: Name of the lower stage when it is the plan's target, else None.
        scale, unit: Display scale of uncertainties; ``xunit`` of readings.
        period: A periodic model's period: one turn is drawn, the reach wrapped onto it.
    """
    panels = 1 if lower_name is None else 2
    if fig is None:
        fig = Figure(figsize=(7.5, 3.2 * panels), layout="constrained")
    axes = np.atleast_1d(fig.subplots(panels, 1))
    ax = axes[0]
    if period is not None:
        reach = _wrapped(reach, period)
        lo, hi, pad = 0.0, float(period), 0.0
    else:
        ends = [*testbed.x, *np.ravel(reach), *plan.positions]
        if lower_name is None:
            ends += [*plan.where]
        lo, hi = float(np.min(ends)), float(np.max(ends))
        pad = 0.02 * (hi - lo or 1.0)
    grid = np.linspace(lo - pad, hi + pad, 600)
    now = testbed.predict(grid, return_std=True)[1]
    after = np.sqrt(
        np.clip(variance_after(testbed, grid, plan.positions, plan.noise_variance), 0, None)
    )
    for k, (a, b) in enumerate(reach):
        ax.axvspan(a, b, color="C2", alpha=0.12, lw=0, label="reachable" if k == 0 else None)
    ax.plot(grid, now * scale, color="C0", lw=1.5, label="stage 0 u now")
    ax.plot(grid, after * scale, color="C1", lw=1.5, ls="--", label="after the plan")
    points = testbed.x if period is None else np.mod(testbed.x, period)  # on the turn drawn
    ax.plot(points, np.zeros_like(points), "k|", ms=8, label="reference points")
    for k, p in enumerate(plan.positions, 1):
        ax.axvline(p, color="C3", lw=0.8, alpha=0.7, label="proposed" if k == 1 else None)
    top = float(np.max(now)) * scale
    width = hi - lo + 2 * pad or 1.0
    level, end = 0, -np.inf  # a label reaching the next one's place goes a line higher
    for p, orders in _labels(plan.positions[:_NUMBERED], 0.015 * width):
        text = orders.replace(",", ", ")
        level = (level + 1) % 3 if p < end else 0
        end = p + _LABEL_CHAR * width * (len(text) + 1)
        ax.annotate(text, (p, (1.04 + 0.07 * level) * top), xytext=(2, 0),
                    textcoords="offset points", fontsize=7, color="C3", ha="left",
                    va="bottom", annotation_clip=False)  # fmt: skip
    ax.set_ylim(0, 1.3 * top if top > 0 else 1.0)
    ax.set_xlabel(f"test-bed reading [{xunit}]")
    ax.set_ylabel(f"standard uncertainty [{unit}]")
    numbered = "numbered" if plan.positions.size <= _NUMBERED else f"the first {_NUMBERED} numbered"
    ax.set_title(
        f"{plan.positions.size} proposed reference measurements (stage 0), {numbered} in order",
        fontsize=9,
    )
    # one turn with a margin, so a proposal at 0 or 360 stays in view
    limits = (lo - pad, hi + pad) if period is None else (-0.03 * period, 1.03 * period)
    ax.set_xlim(*limits)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.22), ncol=5, frameon=False)
    if lower_name is not None:
        bx = axes[1]
        bx.plot(plan.where, plan.u_before * scale, color="C0", lw=1.5, label=f"{lower_name} u now")
        bx.plot(
            plan.where, plan.u_after * scale, color="C1", lw=1.5, ls="--", label="after the plan"
        )
        bx.set_ylim(0, None)
        bx.set_xlabel(f"{lower_name} reading [{xunit}]")
        bx.set_ylabel(f"standard uncertainty [{unit}]")
        set_title(bx, f"the target: {lower_name}'s uncertainty over its readings")
        if period is not None:
            bx.set_xlim(*limits)  # the same turn as above
        bx.legend(fontsize=7, loc="best")
    return fig


@figure_style
def plot_verification(
    v: Verification,
    *,
    fig: Figure | None = None,
    scale: float = 1.0,
    unit: str = "m",
    xunit: str = "m",
    names: tuple[str, str] | None = None,
) -> Figure:
    """Check points' errors after correction against the reading, with the expanded
    uncertainty ``k u`` of each (a band, or error bars for fewer than 50 points), points
    outside it and points not shown to conform to the MPE marked, and the MPE if given.
    Points outside the calibrated range are left out, and counted in the title (with an
    MPE, they fail the verification as ``cascal verify`` does); a rotary model's readings
    are drawn on one turn.

    Args:
        v: The verification of :func:`cascal.verification.verify`.
        scale, unit: Display scale of errors; ``xunit`` of readings.
        names: The model's and the check points' file names, for the title.
    """
    if fig is None:
        fig = Figure(figsize=(7.5, 3.6), layout="constrained")
    ax = fig.subplots()
    m = v.inside
    r = v.reading[m] if v.period is None else np.mod(v.reading[m], v.period)
    order = np.argsort(r, kind="stable")
    r, e = r[order], v.error[m][order] * scale
    out = np.zeros(r.shape, bool)
    if v.has_u:
        band = v.k * v.u[m][order] * scale
        label = f"±U (k = {v.k:g})"
        if r.size >= _BAND_POINTS:
            ax.fill_between(r, -band, band, color="C0", alpha=0.2, lw=0, label=label)
        else:
            ax.errorbar(r, e, yerr=band, fmt="none", ecolor="C0", alpha=0.5, label=label)
        out = (v.en[m] > 1.0)[order]
    ax.axhline(0.0, color="k", lw=0.6)
    ms = 3 if r.size >= _BAND_POINTS else 5
    ax.plot(r[~out], e[~out], ".", color="C0", ms=ms, label="error after correction")
    if np.any(out):
        ax.plot(r[out], e[out], "x", color="C3", ms=5, label="outside ±U")
    s = v.summary()
    points = f"{s['points']} check point{'s' * (s['points'] != 1)}"
    title = f"{points}: RMS error {s['rms_after'] * scale:.3g} {unit}"
    if s["within_U"] is not None:
        title += f", {100 * s['within_U'] / s['points']:.1f} % within ±U"
    left = s["outside_range"]
    verdict = [f"{left} outside the calibrated range left out"] if left else []
    if v.mpe is not None:
        for sign in (-1.0, 1.0):
            ax.axhline(sign * v.mpe * scale, color="C1", ls="--", lw=1,
                       label="±MPE" if sign > 0 else None)  # fmt: skip
        accept = v.acceptance * scale
        if 0.0 < accept < v.mpe * scale:
            for sign in (-1.0, 1.0):
                ax.axhline(sign * accept, color="C1", ls=":", lw=1,
                           label="acceptance limit" if sign > 0 else None)  # fmt: skip
        failing = ~v.conforms[m][order]
        if np.any(failing):
            ax.plot(r[failing], e[failing], "o", mfc="none", mec="C1", ms=7,
                    label="not shown to conform")  # fmt: skip
            verdict.append(f"{np.count_nonzero(failing)} not shown to conform to the MPE")
        elif left:
            verdict[0] += ", not judged: not all shown to conform to the MPE"
        else:
            verdict.append("all conform to the MPE")
    ax.set_xlabel(f"device reading [{xunit}]")
    ax.set_ylabel(f"corrected - reference [{unit}]")
    lines = [] if names is None else [f"{names[1]} against {names[0]}"]
    lines += [title, "; ".join(verdict)] if verdict else [title]
    set_title(ax, "\n".join(lines))
    fig.legend(fontsize=7, loc="outside lower center", ncol=5, frameon=False)
    return fig


@figure_style
def plot_change(
    c: Comparison,
    *,
    fig: Figure | None = None,
    scale: float = 1.0,
    unit: str = "m",
    xunit: str = "m",
    names: tuple[str, str] = ("old", "new"),
    limit: float | None = None,
) -> Figure:
    """A recalibration's change of the correction against the reading, with the
    simultaneous band ``±k_band u`` an unchanged device stays within over the whole range
    with 95 % probability, and the readings beyond it marked.

    Args:
        c: The comparison of :func:`cascal.verification.compare`.
        scale, unit: Display scale of the change; ``xunit`` of readings.
        names: What to call the two calibrations.
        limit: The largest change allowed (``compare --max-change``), in the readings' unit:
            drawn as ``±limit``.
    """
    if fig is None:
        fig = Figure(figsize=(7.5, 3.6), layout="constrained")
    ax = fig.subplots()
    r, d = c.reading, c.change * scale
    band = c.k_band * c.u * scale if c.has_u else None
    beyond = np.where(c.z > c.k_band, d, np.nan) if c.has_u else None
    cut = breaks(r)
    if cut.size:  # two stretches of a turn: no line between them
        r, d = np.insert(r, cut, np.nan), np.insert(d, cut, np.nan)
        if band is not None and beyond is not None:
            band, beyond = np.insert(band, cut, np.nan), np.insert(beyond, cut, np.nan)
    s = c.summary()
    title = (
        f"RMS change {s['rms_change'] * scale:.3g} {unit}, "
        f"largest {s['max_change'] * scale:.3g} {unit}"
    )
    if band is not None and beyond is not None:
        label = f"95 % simultaneous band (±{c.k_band:.2f} u)"
        ax.fill_between(r, -band, band, color="C0", alpha=0.2, lw=0, label=label)
    ax.axhline(0.0, color="k", lw=0.6)
    ax.plot(r, d, "-", color="C0", lw=1.2, label="change of the correction")
    if limit is not None:
        # a limit far beyond the change stays off the axis (a review: +-1100 um flattened a
        # change of 2 um to a line on zero)
        top = max(np.nanmax(np.abs(d)), np.nanmax(band) if band is not None else 0.0)
        off = limit * scale > 3.0 * top > 0.0
        shown = f"±max change {limit * scale:.3g} {unit}" + (", off the axis" if off else "")
        for sign, label in ((1.0, shown), (-1.0, None)):
            ax.axhline(sign * limit * scale, color="C1", ls="--", lw=1.0, label=label)
        if off:
            ax.set_ylim(-1.15 * top, 1.15 * top)
        verdict = c.against(limit).verdict  # (the change's uncertainty counted)
        title += f"; {'not shown within' if verdict == 'undecided' else verdict} the max change"
    if band is not None and beyond is not None:
        if np.any(np.isfinite(beyond)):
            # (a review: "beyond it", next to the max change, read as beyond that)
            ax.plot(r, beyond, "-", color="C3", lw=2, label="beyond the band")
        title += f"; beyond the band over {100 * s['share_beyond_band']:.1f} % of the range"
    ax.set_xlabel(f"device reading [{xunit}]")
    ax.set_ylabel(f"change of correction [{unit}]")
    set_title(ax, f"{names[1]} - {names[0]}\n{title}")
    fig.legend(fontsize=7, loc="outside lower center", ncol=3, frameon=False)
    return fig


def _labels(positions: np.ndarray, near: float) -> list[tuple[float, str]]:
    """One label per group of proposals within ``near`` of the group's first: its mean
    position and the orders (1-based) of its proposals, left to right. (Groups chained
    from neighbour to neighbour had put one label over seven proposals 18 degrees apart.)"""
    order = np.argsort(positions, kind="stable")
    groups: list[list[int]] = []
    for i in order.tolist():
        if groups and positions[i] - positions[groups[-1][0]] < near:
            groups[-1].append(i)
        else:
            groups.append([i])
    return [(float(np.mean(positions[g])), ",".join(str(i + 1) for i in g)) for g in groups]


def _wrapped(reach: list[tuple[float, float]], period: float) -> list[tuple[float, float]]:
    """Intervals on one turn ``[0, period]``: each shifted onto it and split at the seam
    (a whole turn or more is the whole turn)."""
    out = []
    for a, b in reach:
        if b - a >= period:
            return [(0.0, period)]
        a0 = a % period
        b0 = a0 + (b - a)
        out += [(a0, b0)] if b0 <= period else [(a0, period), (0.0, b0 - period)]
    return out
