"""Outlier screening's findings, and hyperparameters fitted at a bound, as lines for
``cascal fit`` and ``cascal fit-devices``."""

from __future__ import annotations

from .cli import rows_text
from .screening import LEVEL, min_points
from .text import exclude_spec, finding_line
from .workflow import StageScreening

__all__ = [
    "SKIPPED",
    "report_findings",
    "report_screening",
    "screening_lines",
    "screening_summary",
]

#: Below this many points (and no known noise) a stage's leave-one-out check is weak: a
#: review's simulated stages missed single outliers 100 times the noise in 12 to 15
#: points, found them in 49 of 50 at 18 and all at 20.
FEW_POINTS = 20

#: What ``fit`` and ``fit-devices`` print in place of the summary with --no-screening.
SKIPPED = "Outlier screening: skipped (--no-screening)"


def screening_lines(check: StageScreening, unit: str) -> list[str]:
    """One line per finding of a stage file (naming the file and rows), then what the
    suspects did to the fit."""
    data = check.data
    file = data.source.file
    xn, yn = data.source.columns
    lines = []
    for q in check.fit.suspects if check.fit else ():
        rows = data.point_rows(q.index)
        c = int(data.counts[q.index])
        mean = f" (the mean of {c} readings)" if c > 1 else ""
        side = "above" if q.z > 0 else "below"
        lines.append(
            f"{file} {rows_text(rows)}: {yn} {float(data.y[q.index]):.9g}{mean} at {xn} "
            f"{q.reading:.9g} lies {abs(q.z):.1f} standard deviations {side} what the other "
            f"points predict ({q.target - q.predicted:+.3g} {unit}); check that measurement"
        )
    for s in check.spread:
        rows = data.raw_rows[s.members] if data.raw_rows is not None else []
        if s.members.size == 2:
            lines.append(
                f"{file} {rows_text(rows)}: the two readings at {xn} {s.reading:.9g} differ "
                f"{s.ratio:.1f} times as much as the other positions' repeats scatter "
                f"(p = {s.p:.2g}); one of them is suspect"
            )
        else:
            far = int(data.raw_rows[s.farthest]) if data.raw_rows is not None else s.farthest
            lines.append(
                f"{file} row {far}: {yn} {float(data.raw_y[s.farthest]):.9g} is the farthest "
                f"of the {s.members.size} readings at {xn} {s.reading:.9g} ({rows_text(rows)}), "
                f"which scatter {s.ratio:.1f} times as much as the other positions' repeats "
                f"(p = {s.p:.2g}); check that measurement (--exclude {exclude_spec(file, [far])} "
                "leaves it out)"
            )
    fit = check.fit
    if fit and fit.suspects and fit.noise_std_without != fit.noise_std:
        k = len(fit.suspects)
        which = f"the {k} suspect points" if k > 1 else "the suspect point"
        rows = sorted(int(r) for q in fit.suspects for r in data.point_rows(q.index))
        them = "them" if k > 1 else "it"
        lines.append(
            f"{file}: without {which} its learned noise would be {fit.noise_std_without:.3g} "
            f"{unit} instead of {fit.noise_std:.3g}; re-measure {them}, or leave {them} out "
            f"with --exclude {exclude_spec(file, rows)}, and fit again"
        )
    if fit and fit.capped:
        lines.append(
            f"{file}: more points disagree with the others than the screening takes out (at "
            f"most {fit.cap} of its {fit.z.size}): its noise may not be Gaussian, or the map "
            "may be rougher than the kernel allows (see the residuals in cascal report)"
        )
    if check.spread_capped:
        lines.append(
            f"{file}: more repeated positions scatter too much than the check names (at most "
            f"a tenth of them, here {len(check.spread)}): the readings' noise may differ "
            "from position to position; look at the spread of each position's repeats"
        )
    if check.problem:
        lines.append(f"{file}: the leave-one-out check stopped: {check.problem}")
    if fit and not fit.detectable:
        lines.append(
            f"{file}: {fit.z.size} points are too few for the leave-one-out check to find an "
            f"outlier (the noise it learns covers any single point; it needs "
            f"{min_points(check.level)} or more)"
        )
    elif _few(check):
        lines.append(
            f"{file}: with {fit.z.size} points the leave-one-out check finds only outliers "
            "far beyond the noise, if any (the noise it learns grows to cover them: in a "
            "review's simulated stages of 12 to 15 points, one reading 100 times the noise off "
            "was missed in 147 of 150); more points, or a map smoother against their spacing, "
            "make it stronger"
        )
    return lines


def _few(check: StageScreening) -> bool:
    """A stage whose leave-one-out check can find a single point, but weakly."""
    fit = check.fit
    return bool(fit and fit.detectable and fit.z.size < FEW_POINTS and check.data.noise is None)


def screening_summary(checks: list[StageScreening], what: str = "") -> str:
    """One line: what was screened (``what``, e.g. ``" of the test bed"``), at which
    level, and how many rows are suspect."""
    rows = sum(len(c.rows) for c in checks)
    found = f"{rows} suspect row{'s' * (rows != 1)}, see the warnings" if rows else "none found"
    weak = any((c.fit and (c.fit.capped or not c.fit.detectable)) or _few(c) for c in checks)
    if not rows and weak:
        found = "no single suspect row, but see the warnings"
    if any(c.problem for c in checks):
        found = f"{found}; one check failed, see the warnings"
    elif any(c.fit is None for c in checks):
        found += " (lookup tables: repeated readings only)"
    level = checks[0].level if checks else LEVEL
    level = f"{level * 100:g} % false-alarm level per stage and check"
    return f"Outlier screening{what} ({level}): {found}"


def report_screening(command: str, checks: list[StageScreening], unit: str, what: str = "") -> None:
    """Print every finding as a warning of ``command``, then the summary line."""
    from .cli import warn

    for check in checks:
        for line in screening_lines(check, unit):
            warn(command, line)
    print(screening_summary(checks, what))


def report_findings(command: str, findings, files: list[str], unit: str) -> None:
    """Warn of every finding of :func:`~cascal.workflow.fit_findings` (``files``: the stage
    files, by stage index)."""
    from .cli import warn

    for f in findings:
        warn(command, finding_line(f, files[f.stage], unit))
