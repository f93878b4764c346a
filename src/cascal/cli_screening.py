"""Outlier screening's findings as lines for ``cascal fit`` and ``cascal fit-devices``."""

from __future__ import annotations

from .screening import LEVEL, MAX_FRACTION
from .workflow import StageScreening

__all__ = ["report_screening", "screening_lines", "screening_summary"]


def _rows(rows) -> str:
    rows = [int(r) for r in rows]
    if len(rows) == 1:
        return f"row {rows[0]}"
    return "rows " + ", ".join(map(str, rows[:-1])) + f" and {rows[-1]}"


def screening_lines(check: StageScreening, unit: str) -> list[str]:
    """One line per finding of a stage file (naming the file and rows), then what the
    suspects did to the fit."""
    data = check.data
    file = data.source.file
    xn, yn = data.source.columns
    lines = []
    for q in check.fit.suspects if check.fit else ():
        rows = data.point_rows(q.index)
        mean = f" (the mean of {len(rows)} readings)" if len(rows) > 1 else ""
        side = "above" if q.z > 0 else "below"
        lines.append(
            f"{file} {_rows(rows)}: {yn} {float(data.y[q.index]):.9g}{mean} at {xn} "
            f"{q.reading:.9g} lies {abs(q.z):.1f} standard deviations {side} what the other "
            f"points predict ({q.target - q.predicted:+.3g} {unit}); check that measurement"
        )
    for s in check.spread:
        rows = data.raw_rows[s.members] if data.raw_rows is not None else []
        if s.members.size == 2:
            lines.append(
                f"{file} {_rows(rows)}: the two readings at {xn} {s.reading:.9g} differ "
                f"{s.ratio:.1f} times as much as the other positions' repeats scatter "
                f"(p = {s.p:.2g}); one of them is suspect"
            )
        else:
            far = int(data.raw_rows[s.farthest]) if data.raw_rows is not None else s.farthest
            lines.append(
                f"{file} row {far}: {yn} {float(data.raw_y[s.farthest]):.9g} is the farthest "
                f"of the {s.members.size} readings at {xn} {s.reading:.9g} ({_rows(rows)}), "
                f"which scatter {s.ratio:.1f} times as much as the other positions' repeats "
                f"(p = {s.p:.2g}); check that measurement"
            )
    fit = check.fit
    if fit and fit.suspects:
        k = len(fit.suspects)
        lines.append(
            f"{file}: without the {k} suspect point{'s' * (k > 1)} its learned noise would be "
            f"{fit.noise_std_without:.3g} {unit} instead of {fit.noise_std:.3g}; remove or "
            f"re-measure {'them' if k > 1 else 'it'} and fit again"
        )
    if fit and fit.capped:
        lines.append(
            f"{file}: more points disagree with the others than the screening takes out (at "
            f"most {MAX_FRACTION:.0%} of them): its noise may not be Gaussian, or the map may "
            "be rougher than the kernel allows (see the residuals in cascal report)"
        )
    return lines


def screening_summary(checks: list[StageScreening]) -> str:
    """One line: what was screened and how many rows are suspect."""
    rows = sum(len(c.rows) for c in checks)
    found = f"{rows} suspect row{'s' * (rows != 1)}, see the warnings" if rows else "none found"
    if not rows and any(c.fit and c.fit.capped for c in checks):
        found = "no single suspect row, but see the warning"
    return f"Outlier screening ({LEVEL * 100:g} % false-alarm level per stage and check): {found}"


def report_screening(command: str, checks: list[StageScreening], unit: str) -> None:
    """Print every finding as a warning of ``command``, then the summary line."""
    from .cli import warn

    for check in checks:
        for line in screening_lines(check, unit):
            warn(command, line)
    print(screening_summary(checks))
