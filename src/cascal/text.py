"""Words and numbers as people read them: ranges, units of hyperparameters, and what the
findings of a fit mean. Shared by the command line and the report; no I/O."""

from __future__ import annotations

from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal

__all__ = [
    "HOMOSCEDASTIC_CAUTION",
    "HOMOSCEDASTIC_U",
    "caution_lines",
    "exclude_spec",
    "finding_line",
    "hyperparameter_unit",
    "measured_ends",
    "range_ends",
    "range_text",
    "reading_in_range",
    "shown",
    "turn_text",
    "understates_u",
]

#: Reviews' simulations: U = 2u of a two-stage homoscedastic cascade covered 65.8 % of the
#: errors in 2000 of the paper's trials, and 42 % in GP-drawn chains with 16 reference
#: points (24 % in their gap, 16 % beyond them), not 95 %.
HOMOSCEDASTIC_CAUTION = (
    "leaves the correlated error of the stages above the device out (the test bed's; the "
    "paper's Alternative 1): in simulated "
    "cascades U = 2u covered 66 % of the errors, not 95 %, and as few as 16 % where the "
    "reference did not measure"
)
HOMOSCEDASTIC_U = (
    f"u of --method homoscedastic {HOMOSCEDASTIC_CAUTION}; for u, fit with --method bayes"
)


def exclude_spec(file: str, rows) -> str:
    """``FILE:ROWS`` of ``--exclude``, quoted for a shell where it needs it; three or more
    consecutive rows as a range (``104-201``)."""
    import shlex

    rows = sorted({int(r) for r in rows})
    parts, start = [], 0
    for i in range(1, len(rows) + 1):
        if i == len(rows) or rows[i] != rows[i - 1] + 1:  # the end of a run
            run = rows[start:i]
            parts += [f"{run[0]}-{run[-1]}"] if len(run) > 2 else [str(r) for r in run]
            start = i
    return shlex.quote(f"{file}:{','.join(parts)}")


def range_text(lo: float, hi: float, digits: int = 9) -> str:
    """``"[lo, hi]"`` to ``digits`` significant digits (more where the range is narrower),
    rounded inward: every reading in the printed range lies in the true one (a report had
    printed a range ending at 0.9493815934 as ending at 0.949382, holding readings that
    ``correct`` flags). An end that ``digits`` digits give exactly is printed so (0.1, not
    0.100000001, whose double is a little above 0.1)."""
    a, b = range_ends(lo, hi, digits)
    return f"[{a}, {b}]"


def range_ends(lo: float, hi: float, digits: int = 9) -> tuple[str, str]:
    """The two ends :func:`range_text` prints."""
    for d in range(digits, 18):
        a, b = _inward(lo, d, ROUND_CEILING), _inward(hi, d, ROUND_FLOOR)
        if float(a) <= float(b) or d == 17:
            return a, b
    raise AssertionError("unreachable")  # pragma: no cover


def outward_ends(lo: float, hi: float, digits: int = 6) -> tuple[str, str]:
    """``lo`` and ``hi`` to ``digits`` significant digits, rounded outward: a stretch the
    reference could not measure is printed covering all of it (a report review found one
    printed shrunk at both ends)."""
    return _inward(lo, digits, ROUND_FLOOR), _inward(hi, digits, ROUND_CEILING)


def reading_in_range(v: float, lo: float, hi: float, digits: int = 9) -> str:
    """A reading ``v`` of the range ``[lo, hi]`` to ``digits`` digits, kept within the
    range as :func:`range_text` prints it (a reading at an end is printed as that end: a
    compare had named its largest change at 0.940129143 of a range printed to end at
    0.940129142)."""
    a, b = range_ends(lo, hi, digits)
    text = f"{v:.{digits}g}"
    return b if float(text) > float(b) else a if float(text) < float(a) else text


def _inward(v: float, digits: int, rounding: str) -> str:
    short = f"{v:.{digits}g}"
    if float(short) == v:
        return "0" if v == 0 else short
    d = Decimal(v)
    q = d.quantize(Decimal(1).scaleb(d.adjusted() - digits + 1), rounding=rounding)
    return f"{float(q):.{digits}g}"


def arc_text(model) -> str | None:
    """``"a to b unit of the turn (period p; c to d unit left out: readings there are
    flagged)"`` for a periodic model whose device readings cover part of the turn only
    (:func:`cascal.workflow.unmeasured_arc`), else None."""
    from .workflow import unmeasured_arc

    arc = unmeasured_arc(model)
    return None if arc is None else turn_text(arc, model.unit, float(model.period))


def turn_text(arc: tuple[float, float], unit: str, period: float) -> str:
    """:func:`arc_text` of the arc ``(start, end)`` the device readings leave out. The
    measured arc is rounded inward (a reading inside the printed one is inside the true
    one), which rounds the arc left out outward: the same two numbers."""
    a, b = measured_ends(arc)
    return (
        f"{a} to {b} {unit} of the turn (period {period:g}; the device "
        f"readings leave out {b} to {a} {unit}: readings there are flagged)"
    )


def measured_ends(arc: tuple[float, float]) -> tuple[str, str]:
    """The measured part of a turn whose device readings leave out ``arc`` (start, end):
    from the gap's end round to its start, printed to 9 digits rounded inward (so the arc
    left out, from the second to the first, is rounded outward)."""
    left, back = arc
    return _inward(back, 9, ROUND_CEILING), _inward(left, 9, ROUND_FLOOR)


def hyperparameter_unit(name: str, unit: str, periodic: bool) -> str:
    """The unit of a hyperparameter, with a leading space (empty where dimensionless): a
    length scale and a period in ``unit`` (the periodic kernel's length scale is relative
    to its period), an offset in ``unit``, variances in ``unit`` squared."""
    if name.endswith("length_scale"):
        return "" if periodic else f" {unit}"
    if name.endswith(("period", "offset")):  # (a report review: the offset had none)
        return f" {unit}"
    if name.endswith("variance"):
        return f" {unit}\N{SUPERSCRIPT TWO}"
    return ""


def finding_line(finding, file: str, unit: str) -> str:
    """What a :func:`~cascal.workflow.fit_findings` finding means for the stage of ``file``."""
    from .workflow import StageOffset

    if isinstance(finding, StageOffset):
        return (
            f"{file}: the corrections average {finding.offset:+.6g} {unit}, "
            f"{abs(finding.offset) / max(finding.spread, 1e-300):.3g} times as much as they "
            "vary, as when the two sensors' zeros differ; the identity prior mean reaches "
            "that offset only through the map's variance, which can cost the fit its "
            "accuracy and u its meaning: fit with --mean offset, or zero the readings"
        )
    name = finding.parameter.replace("_", " ")
    if finding.parameter.endswith("length_scale") and finding.side == "upper":
        return (
            f"{file}: the fitted {name} sits at the upper end of its range: the fit reads "
            f"the {finding.points} points as a straight correction plus noise (constant "
            "over the turn, with a periodic kernel), and so few cannot show whether the "
            "corrections bend between them; u cannot be trusted: measure more points"
        )
    if finding.parameter.endswith("length_scale"):
        return (
            f"{file}: the fitted {name} sits at the lower end of its range: the corrections "
            "vary faster than the points show, or the two columns do not belong together; "
            "u between the points cannot be trusted"
        )
    if finding.parameter in ("noise_variance", "noise_ratio") and finding.side == "upper":
        return (
            f"{file}: the learned noise sits at the upper end of its range: the fit takes the "
            f"readings for noise about the prior mean, and {finding.points} points cannot show "
            "otherwise; u cannot be trusted: measure more points"
        )
    if finding.parameter in ("noise_variance", "noise_ratio"):
        return (
            f"{file}: the learned noise sits at the lower end of its range: the fit passes "
            f"through every point, and {finding.points} points cannot tell the readings' noise "
            "from the map; u is likely too small: measure more points, or repeat readings "
            "(their spread gives a known noise)"
        )
    why = (
        "the corrections are larger than the fit can follow"
        if finding.side == "upper"
        else "the fit puts every deviation from the prior mean down to noise"
    )
    where = finding.side
    return f"{file}: the fitted {name} sits at the {where} end of its range: {why}; u may be wrong"


def understates_u(model) -> bool:
    """Whether ``model``'s u leaves the test bed's correlated error out: a homoscedastic
    cascade of two or more stages (:data:`HOMOSCEDASTIC_U`)."""
    return model.method == "homoscedastic" and len(model.fitted.models) > 1


def caution_lines(model) -> list[str]:
    """What makes ``model``'s u doubtful, as far as the model shows it, one line each: the
    findings of :func:`~cascal.workflow.fit_findings` named by stage file, then
    :data:`HOMOSCEDASTIC_U` where it applies. What ``fit`` warns of, and ``info`` and the
    report repeat."""
    from .workflow import fit_findings

    files = [s.file for s in model.sources]
    lines = [finding_line(f, files[f.stage], model.unit) for f in fit_findings(model)]
    return [*lines, HOMOSCEDASTIC_U] if understates_u(model) else lines


def shown(name: str) -> str:
    """A file name as text to show: bytes of it that are not UTF-8 (a Latin-1 share's, held
    by Python as surrogates) as U+FFFD. Written as they came, they had stopped UTF-8
    outputs, terminals and figures with a traceback."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")
