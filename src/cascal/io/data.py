"""CSV input: stage files and readings to validated arrays (output: :mod:`.csvout`).

A stage file has a header row and two columns: the readings of the sensor being calibrated,
then the readings of the more accurate sensor it was aligned with (or any two columns picked
by name). Repeated readings at one position (exactly equal readings of the calibrated
sensor) are averaged; the variance of their mean becomes a known noise of that point. Every
error is an :class:`~cascal.errors.InputError` naming the file, the 1-based row (the header
is row 1) and the column.
"""

from __future__ import annotations

import csv
import hashlib
import io
import math
import os
import re
import warnings
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..cascade import Stage
from ..errors import DataWarning, InputError
from ..text import exclude_spec
from ..validation import MIN_POINTS, STAGE_MAX, STAGE_MIN_SPAN, aggregate_repeats, unwrap

__all__ = [
    "Source",
    "StageData",
    "Table",
    "check_units",
    "is_number",
    "read_readings",
    "read_stage",
    "read_table",
]

#: Above this many lines, a file is parsed by NumPy first (an error is then located exactly).
_FAST_LINES = 5000


@dataclass(frozen=True, slots=True)
class Source:
    """Provenance of an input file.

    Attributes:
        file: The path as given.
        sha256: SHA-256 of the file's bytes, hex.
        rows: Data rows below the header that were read (those excluded not counted).
        columns: Names of the columns used.
        excluded: File rows left out on request (``--exclude``), increasing.
    """

    file: str
    sha256: str
    rows: int
    columns: tuple[str, ...]
    excluded: tuple[int, ...] = ()


@dataclass(frozen=True, slots=True)
class Table:
    """Numeric columns read from a CSV file.

    Attributes:
        columns: The columns, each shape (n,).
        rows: File row of each value (the header is row 1), shape (n,).
        source: The file's provenance.
    """

    columns: tuple[np.ndarray, ...]
    rows: np.ndarray
    source: Source


@dataclass(frozen=True, slots=True)
class StageData:
    """One stage file, validated and with repeated readings averaged.

    Attributes:
        x: Distinct readings of the calibrated sensor, increasing, shape (k,).
        y: Mean reading of the more accurate sensor at each, shape (k,).
        noise: Variance of each mean from the spread of its repeats, shape (k,), or None
            when no position was read twice.
        counts: Readings averaged into each point, shape (k,).
        rows: File row of each point's first reading, shape (k,).
        source: The file's provenance.
        raw_x, raw_y: Every reading as read (``raw_y`` moved by whole periods for a rotary
            sensor), shape (n,), before averaging; None when not kept.
        raw_rows: File row of each, shape (n,).
    """

    x: np.ndarray
    y: np.ndarray
    noise: np.ndarray | None
    counts: np.ndarray
    rows: np.ndarray
    source: Source
    raw_x: np.ndarray | None = None
    raw_y: np.ndarray | None = None
    raw_rows: np.ndarray | None = None

    def point_rows(self, i: int) -> np.ndarray:
        """File rows of the readings averaged into point ``i``, increasing; its first row
        alone when the readings were not kept."""
        if self.raw_x is None or self.raw_rows is None:
            return self.rows[i : i + 1]
        return np.sort(self.raw_rows[self.raw_x == self.x[i]])

    def stage(self, name: str) -> Stage:
        """The points as a :class:`~cascal.cascade.Stage` called ``name``."""
        return Stage(self.x, self.y, self.noise, name)


def read_table(
    path: str | os.PathLike,
    columns: Sequence[str | None],
    *,
    hint: str = "",
    min_rows: int = 1,
    max_abs: float | None = None,
    exclude: Collection[int] = (),
) -> Table:
    """Read numeric columns of a CSV file with a header row.

    Args:
        path: The file, comma, semicolon or tab separated (detected from the header and
            the first data row).
        columns: One entry per wanted column: its name, or all None to take the columns in
            order (the file must then have exactly ``len(columns)`` columns).
        hint: Appended to the message about missing or extra columns.
        min_rows: Fewest data rows accepted.
        max_abs: If given, values of the wanted columns must lie below it in magnitude.
        exclude: File rows to leave out (the header is row 1), e.g. a reading known to be
            bad; their cells are not read. Each must be a data row of the file.

    Raises:
        InputError: Naming the file, row and column of the first problem.
    """
    name = str(path)
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read the file ({exc.strerror or exc})", file=name) from None
    digest = hashlib.sha256(raw).hexdigest()
    head = raw[:4096]
    zeros = sorted((head[0::2].count(0), head[1::2].count(0)))
    if len(head) >= 8 and zeros[1] > len(head) // 4 and zeros[0] <= len(head) // 64:
        raise InputError(  # every other byte 0, the others not: UTF-16 without its mark
            "UTF-16 text, not UTF-8: save it as CSV (UTF-8) instead", file=name
        )
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        if raw[:2] in (b"\xff\xfe", b"\xfe\xff"):  # spreadsheets' "Unicode text"
            raise InputError(
                "UTF-16 text, not UTF-8: save it as CSV (UTF-8) instead", file=name
            ) from None
        head = exc.object[: exc.start]  # (after a BOM)
        row = head.count(b"\n") + 1 if b"\n" in exc.object else head.count(b"\r") + 1
        raise InputError(
            f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x}, {exc.reason}): saved as "
            "Windows-1252 or Latin-1 (a spreadsheet's plain CSV)? save it as CSV UTF-8",
            file=name,
            row=row,
        ) from None
    text = text.replace("\r\n", "\n").replace("\r", "\n")  # CRLF, and CR alone (old Macs)
    first = text.split("\n", 1)[0]
    _check_preamble(text, first, len(columns), name)
    delim = _delimiter(text)
    header = _header(first, delim, name)
    idx, unnamed = _pick(header, columns, name, hint)
    skip = frozenset(int(r) for r in exclude)
    values = rows = None
    if raw.count(b"\n") > _FAST_LINES and not unnamed:
        values = _fast(raw, delim, len(header))
        if values is not None:
            rows = np.arange(2, values.shape[0] + 2)
            _check_excluded(skip, set(range(2, values.shape[0] + 2)), name)
            keep = ~np.isin(rows, list(skip))
            values, rows = values[keep], rows[keep]
    if values is None:
        values, rows = _slow(text, delim, header, idx, name, skip, unnamed, hint)
    if rows.size < min_rows:
        left = f" ({len(skip)} excluded)" if skip else ""
        raise InputError(
            f"expected at least {min_rows} data rows below the header, got {rows.size}{left}",
            file=name,
            row=int(rows[-1]) if rows.size else 1,
        )
    names = tuple(header[i] for i in idx)
    cols = tuple(np.ascontiguousarray(values[:, i]) for i in idx)
    if not raw.endswith((b"\n", b"\r")):
        _check_cut_short(text, delim, idx, names, name)
    if max_abs is not None:
        for column, col in zip(names, cols, strict=True):
            big = np.flatnonzero(np.abs(col) >= max_abs)
            if big.size:
                raise InputError(
                    f"{float(col[big[0]])!r} is too large (|value| < {max_abs:g} expected)",
                    file=name,
                    row=int(rows[big[0]]),
                    column=column,
                )
    return Table(cols, rows, Source(name, digest, int(rows.size), names, tuple(sorted(skip))))


#: Rows before the last whose decimals :func:`_check_cut_short` compares it with.
_CUT_ROWS = 200


def _check_cut_short(
    text: str, delim: str, idx: Sequence[int], names: Sequence[str], name: str
) -> None:
    """Warn (:class:`DataWarning`) where a file that ends without a line break has a last
    row whose number in a wanted column (``idx``, named ``names``) has a decimal point and
    at most half the decimals of that column's every other number among the
    :data:`_CUT_ROWS` rows before it, and they at least 3: the file cut short within that
    number (a fuzz review: ``0.486`` of ``0.4861985463790`` was read with no word)."""
    # the last lines alone (the first part, the header or all before them, left out)
    lines = [ln for ln in text.rsplit("\n", _CUT_ROWS + 1)[1:] if ln.strip()]
    if len(lines) < 4:
        return
    rows = [next(csv.reader([ln], delimiter=delim)) for ln in lines]

    def decimals(cell: str) -> int | None:
        c = cell.strip()
        if not is_number(c) or "e" in c.lower() or c.lower().lstrip("+-") in ("nan", "inf"):
            return None
        return len(c.partition(".")[2])

    last, before = rows[-1], rows[:-1]
    for i, column in zip(idx, names, strict=True):
        here = decimals(last[i]) if i < len(last) else None
        others = [decimals(r[i]) for r in before if i < len(r)]
        if here is None or not others or None in others:
            continue
        least = min(others)  # type: ignore[type-var]
        # at most half the decimals, and a point: numbers written to fixed significant
        # digits (100 after 99.4737, 1.00001 after 0.999990) or with trailing zeros dropped
        # (0.1234 of 0.123400) are not cut short (a review found them warned of)
        if least >= 3 and 2 * here <= least and "." in last[i]:
            warnings.warn(
                f"{name}: the file ends without a line break, and the last row's {column} "
                f"{last[i].strip()!r} has {here} decimal{'' if here == 1 else 's'} where the "
                "rows before have "
                f"{least} or more: the file cut short in that number? (row "
                f"{text.count(chr(10)) + 1})",
                DataWarning,
                stacklevel=4,
            )
            return


def read_stage(
    path: str | os.PathLike,
    *,
    x_column: str | None = None,
    y_column: str | None = None,
    period: float | None = None,
    exclude: Collection[int] = (),
) -> StageData:
    """Read a stage file: readings of the calibrated sensor and of the more accurate one.

    Args:
        path: CSV file with a header row.
        x_column, y_column: Column names; both None: the file's two columns, in order.
        period: For a rotary sensor (periodic kernel), the period: each more accurate
            reading is moved by whole periods to within half a period of its reading.
        exclude: File rows to leave out (see :func:`read_table`).

    Raises:
        InputError: Missing or extra columns, non-numeric or non-finite cells, fewer than
            three rows or positions, or a relation between the two sensors that is not
            increasing; the message names the file and row.
    """
    hint = "; choose two by name with --x-column and --y-column"
    table = read_table(
        path,
        (x_column, y_column),
        hint=hint,
        min_rows=MIN_POINTS,
        exclude=exclude,
        max_abs=STAGE_MAX,
    )
    name = table.source.file
    x, y = table.columns
    for col, values in zip(table.source.columns, (x, y), strict=True):
        span = float(values.max() - values.min())
        if 0 < span < STAGE_MIN_SPAN:  # variances, in the unit squared, would underflow
            raise InputError(
                f"the readings in column {col!r} span only {span:.3g}: too small a scale to "
                "compute with (variances in the unit squared underflow); use a smaller unit",
                file=name,
                row=int(table.rows[np.argmax(values)]),
            )
    check_units(x, y, table.source.columns, name)  # (before a rotary stage's unwrapping)
    if period is not None:
        span = float(x.max() - x.min())
        lo, hi = int(np.argmin(x)), int(np.argmax(x))
        if period <= span < period * (1 + 1 / 36):  # (a closure: the start read again)
            past = table.rows[x >= x[lo] + period]  # (all of them: a diff review's closure
            # position read twice had been named one row at a time)
            raise InputError(
                f"rows {int(table.rows[lo])} and {int(table.rows[hi])} read "
                f"{float(x[lo])!r} and {float(x[hi])!r} in column "
                f"{table.source.columns[0]!r}, a turn apart (--period {period:g}) or a little "
                "more: a closure reading of the start? A rotary stage's readings lie within "
                "one turn, and to the periodic kernel the two are one position: leave the "
                f"readings a turn past the first out (--exclude {exclude_spec(name, past)})",
                file=name,
                row=int(table.rows[hi]),
            )
        if span >= period:
            raise InputError(
                f"readings in column {table.source.columns[0]!r} span {span:.6g}, a full "
                f"--period ({period:g}) or more: a rotary sensor's readings lie within one "
                "turn; check the period and its unit",
                file=name,
                row=int(table.rows[np.argmax(x)]),
            )
        y = unwrap(x, y, period)
    rep = aggregate_repeats(x, y, table.source.columns)
    rows = table.rows[rep.first]
    if rep.x.size < MIN_POINTS:
        raise InputError(
            f"expected readings at {MIN_POINTS} or more distinct positions in column "
            f"{table.source.columns[0]!r}, got {rep.x.size}"
            + (f" ({len(table.source.excluded)} rows excluded)" if table.source.excluded else ""),
            file=name,
            row=int(table.rows[-1]),
        )
    bad = np.flatnonzero(np.diff(rep.y) <= 0)
    if bad.size:
        k = bad[0]
        xn, yn = table.source.columns

        def group(j: int) -> np.ndarray:
            return np.flatnonzero(rep.inverse == j)  # its readings, in file order

        def value(j: int) -> str:
            r = table.rows[group(j)].tolist()
            if len(r) == 1:
                where = f"row {r[0]}"
            else:
                listed = ", ".join(map(str, r[:-1])) if len(r) <= 5 else f"{r[0]}, {r[1]}, ..."
                where = f"the mean of its {len(r)} readings, rows {listed} and {r[-1]}"
            return f"{yn} {float(rep.y[j])!r} at {xn} {float(rep.x[j])!r} ({where})"

        # the point out of step: the first one too high (above the point after the next;
        # at the end, the second above the point before the first), else the second too
        # low; within a mean, its reading furthest that way
        if k + 2 < rep.y.size:
            high = bool(rep.y[k] >= rep.y[k + 2])
        else:
            high = k >= 1 and bool(rep.y[k + 1] > rep.y[k - 1])
        members = group(k if high else k + 1)
        culprit = members[np.argmax(y[members]) if high else np.argmin(y[members])]

        steps = rep.y.size - 1
        flat = int(np.count_nonzero(np.diff(rep.y) == 0))
        back = bad.size - flat
        if back:
            also = f" and {flat} are flat" if flat else ""
            hint = f"; {back} of its {steps} steps go back{also}: " + (
                "is one sensor's direction reversed, or are the columns swapped?"
                if 2 * back > steps
                else "are the points closer together than the readings' noise? Then repeat "
                "readings at fewer, wider-spaced positions (repeats are averaged)"
            )
        else:  # none goes back: the more accurate reading stands still
            hint = f"; {flat} of its {steps} steps are flat ({yn} the same at other {xn}): " + (
                f"is column {yn!r} a sensor that did not move, or a constant?"
                if 2 * flat > steps
                else "are the points closer together than the readings' resolution?"
            )
        if bad.size == 1:  # (a wrong reading of xn moves its point among others)
            hint = f"; a mistyped cell (of {yn} or of {xn}), or rows out of step?"
        gap = float(rep.x[k + 1] - rep.x[k])
        usual = float(np.quantile(np.diff(rep.x), 0.9))
        if gap < 0.05 * usual:  # (a user review: repeats read with jitter, told to space out)
            hint = (
                f"; {xn} {float(rep.x[k])!r} and {float(rep.x[k + 1])!r} lie {gap:.3g} apart, "
                f"under a twentieth of the usual spacing ({usual:.3g}): repeated readings of "
                f"one position? Only readings of exactly the same {xn} are averaged as "
                f"repeats: write each repeat's set point in {xn}, or average them first"
            )
        raise InputError(
            f"{value(k + 1)} is not above {value(k)}; "
            "the more accurate reading must increase with the calibrated one (one-to-one, "
            f"the paper's bijectivity assumption){hint}",
            file=name,
            row=int(table.rows[culprit]),
        )
    noise = rep.noise if np.any(rep.counts > 1) else None
    return StageData(rep.x, rep.y, noise, rep.counts, rows, table.source, x, y, table.rows)


#: Ratio of the two columns' spans beyond which (either way) a stage file is warned of:
#: two readings of one position differ by far less (a scale error of 1e-3 is large), and
#: units differ by more (inch and mm 25.4, degree and radian 57, mm and m 1000).
UNIT_RATIO = 10.0


def check_units(x: np.ndarray, y: np.ndarray, columns: tuple[str, ...], name: str) -> None:
    """Warn (:class:`DataWarning`) where the more accurate readings ``y`` (n,) span over
    :data:`UNIT_RATIO` times, or under its inverse, the span of the readings ``x`` (n,):
    the columns in two units (mm and m, degrees and radians). The spans are those of the
    middle 80 % of each column, so that one mistyped cell does not set them."""
    sx, sy = (float(np.subtract(*np.percentile(v, [90, 10]))) for v in (x, y))
    if not (sx > 0 and sy > 0) or 1 / UNIT_RATIO <= sy / sx <= UNIT_RATIO:
        return
    xn, yn = columns
    warnings.warn(
        f"{name}: the readings of column {yn!r} span {sy / sx:.4g} times those of column "
        f"{xn!r}, where two readings of one position differ little: are the columns in "
        "different units (mm and m)? The corrections are taken as their difference, in "
        "one unit",
        DataWarning,
        stacklevel=3,
    )


def read_readings(path: str | os.PathLike, *, column: str | None = None) -> Table:
    """Read device readings to correct: a one-column file, or the column named ``column``."""
    return read_table(path, (column,), hint="; choose one by name with --column")


def _check_preamble(text: str, first: str, width: int, name: str) -> None:
    """Refuse lines above the header that a spreadsheet or an instrument writes: Excel's
    ``sep=;`` line, comments and header blocks (the header, the nearest row of ``width``
    cells above the first row of numbers that is not one of units, is named); where two
    rows of text could be a line above the header or a header and a row of units, name
    both readings."""
    line = first.strip()
    if re.fullmatch(r'"?sep=.?"?,*;*', line, flags=re.IGNORECASE):
        raise InputError(
            f"{line!r} is a spreadsheet's separator line, not the header: delete it (the "
            "header row is the next one)",
            file=name,
            row=1,
        )
    lines = text[:65536].split("\n")[:400]
    numbers = next(  # the first row of numbers (1-based), where one comes soon
        (
            k
            for k, later in enumerate(lines, start=1)
            if len(cells := _nonempty(later)) >= width and all(_is_value(c) for c in cells)
        ),
        None,
    )
    above = [j for j in range(1, numbers or 0) if lines[j - 1].strip()]
    if len(above) < 2 or any(_numberish(lines[j - 1]) for j in above):
        return  # (a row of numbers with a typo: the rows below name it)
    nearest = lines[above[-1] - 1]
    if (
        _widest(nearest) >= width
        and any(_is_value(c) for c in _nonempty(nearest))
        and any(_widest(lines[j - 1]) >= width and not _units(lines[j - 1]) for j in above[:-1])
    ):  # the first data row, a word beside a number (an instrument's ERR, n/a), below a
        # header: the rows below name it (a review: it had been taken for a second header
        # row); lines above that header are still named (a second: "position,1" under a
        # comment is the header, its "1" a column's name)
        above = above[:-1]
        if len(above) < 2:
            return
    # the header: the nearest row above the numbers of as many cells, not one of units
    header = next(
        (j for j in reversed(above) if _widest(lines[j - 1]) >= width and not _units(lines[j - 1])),
        None,
    )
    if header is None or header == above[0]:
        return  # a header, then rows of units or stray text: the rows below name them
    named = f"the header looks like row {header} ({lines[header - 1].strip()[:60]!r})"
    if len(above) > 2 or line.startswith(_COMMENTS) or _widest(first) < width:
        raise InputError(
            f"{line[:60]!r} is not the header: {named}: delete the lines above it (comments, "
            "or an instrument's header block)",
            file=name,
            row=1,
        )
    raise InputError(
        f"rows 1 and {header} are both text above the first numbers ({line[:60]!r}, then "
        f"{lines[header - 1].strip()[:60]!r}): if row {header} is the header, delete row 1 "
        f"(a comment, an instrument's line); if row {header} holds units, delete it",
        file=name,
        row=1,
    )


#: How comment lines above a header begin.
_COMMENTS = ("#", "//", "%", ";", "!")
#: A cell naming a unit: mm, [mm], (deg), µm, arcsec, counts ... (brackets: anything short).
_UNIT = re.compile(
    r"\s*(?:[\[(].{0,12}[\])]|(?:[pnuµμmck]?(?:m|rad|s|v|hz)|deg|degrees?|°|arc ?(?:sec|min)"
    r"|[\"']|in|inch(?:es)?|counts?|cts|%|-|unit(?:s|less)?|lsb|steps?|mm/s|rpm)\.?)\s*",
    re.IGNORECASE,
)


def _numberish(line: str) -> bool:
    """Whether every non-empty cell of ``line`` begins as a number does (a typo further on)."""
    cells = _nonempty(line)
    return bool(cells) and all(_begins_as_number(c) for c in cells)


def _begins_as_number(cell: str) -> bool:
    """``0.1_16``, ``1O``, a fullwidth ``０.５``: a number mistyped, not a word."""
    return re.match(r"\s*[-+]?[.\d]", cell) is not None


def _units(line: str) -> bool:
    """Whether every non-empty cell of ``line`` names a unit."""
    cells = _nonempty(line)
    return bool(cells) and all(_UNIT.fullmatch(c) for c in cells)


def _split(line: str) -> list[str]:
    """The cells of ``line`` by the separator (comma, semicolon or tab) that gives most."""
    best: list[str] = []
    for d in ",;\t":
        try:
            cells = next(csv.reader([line], delimiter=d), [])
        except csv.Error:
            continue
        best = cells if len(cells) > len(best) else best
    return best


def _nonempty(line: str) -> list[str]:
    """The cells of ``line`` that are not empty, by the separator that gives most cells."""
    return [c for c in _split(line) if c.strip()]


def _widest(line: str) -> int:
    """How many cells of ``line`` are not empty."""
    return len(_nonempty(line))


def _delimiter(text: str) -> str:
    """The separator (comma, semicolon or tab) most frequent in the header row that splits
    the first data row into as many cells as the header; else the most frequent one.
    Column names may then contain the other separators (``pos (mm; raw),ref (mm; raw)``)."""
    lines = text[:65536].split("\n")
    first = lines[0]
    data = next((line for line in lines[1:50] if line.strip()), "")
    candidates = sorted((",", ";", "\t"), key=first.count, reverse=True)  # ties: in order
    for d in candidates:
        if first.count(d) and data and _cells(first, d) == _cells(data, d):
            return d
    return candidates[0]


def _cells(line: str, delim: str) -> int:
    try:
        return len(next(csv.reader([line], delimiter=delim)))
    except csv.Error:
        return -1


def _header(first: str, delim: str, name: str) -> list[str]:
    if not first.strip():
        raise InputError(
            "expected a header row with column names, got an empty line", file=name, row=1
        )
    try:
        header = [c.strip() for c in next(csv.reader([first], delimiter=delim))]
    except csv.Error as exc:
        raise InputError(f"the header row is not readable CSV ({exc})", file=name, row=1) from None
    if all(is_number(c) for c in header):
        raise InputError(
            f"expected a header row with column names, got numbers ({first.strip()!r}); "
            "add a first line naming the columns",
            file=name,
            row=1,
        )
    return header


def _pick(
    header: list[str], columns: Sequence[str | None], name: str, hint: str
) -> tuple[list[int], frozenset[int]]:
    """Header indices of the wanted columns (None entries take the remaining ones in
    order), and the columns left unnamed that those passed over (a spreadsheet's trailing
    ``,,``): they must be empty."""
    have = ", ".join(repr(h) for h in header)
    idx: list[int | None] = []
    for c in columns:
        if c is None:
            idx.append(None)
            continue
        if c not in header:
            raise InputError(f"missing column {c!r}; the header has {have}", file=name, row=1)
        if header.count(c) > 1:
            raise InputError(f"column {c!r} appears {header.count(c)} times", file=name, row=1)
        if header.index(c) in idx:
            raise InputError(f"column {c!r} is named twice; name two columns", file=name, row=1)
        idx.append(header.index(c))
    free = [i for i in range(len(header)) if i not in idx]
    want = idx.count(None)
    passed: frozenset[int] = frozenset()
    if want and len(free) > want:  # more columns than wanted: unnamed ones are passed over
        passed = frozenset(i for i in free if not header[i])
        free = [i for i in free if header[i]]
    if want and len(free) != want:
        what = "missing" if len(free) < want else "extra"
        n = len(columns)
        expect = "a reading and a more accurate reading" if n == 2 else "the readings"
        raise InputError(
            f"{what} columns: expected {n} ({expect}), got {len(header)} ({have}){hint}",
            file=name,
            row=1,
        )
    it = iter(free)
    return [next(it) if i is None else i for i in idx], passed


def _fast(raw: bytes, delim: str, width: int) -> np.ndarray | None:
    """All columns parsed by NumPy, or None when anything is unusual (then parse exactly)."""
    try:
        values = np.loadtxt(
            io.BytesIO(raw),  # (the path again: a pipe's is empty, and NumPy warned of it)
            delimiter=delim,
            skiprows=1,
            ndmin=2,
            comments=None,
            dtype=float,
            encoding="utf-8-sig",
        )
    except ValueError:
        return None
    body = raw.split(b"\n", 1)[1] if b"\n" in raw else b""
    lines = body.count(b"\n") + (0 if body.endswith(b"\n") or not body else 1)
    if values.shape != (lines, width) or not np.all(np.isfinite(values)):
        return None
    return values


def _checked(reader, name: str):
    """The rows of a ``csv.reader``; a row it cannot parse is an InputError naming it."""
    while True:
        try:
            cells = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise InputError(f"not readable CSV ({exc})", file=name, row=reader.line_num) from None
        yield cells


def _check_excluded(skip: frozenset[int], data_rows: set[int], name: str) -> None:
    """Refuse an excluded row that is not a data row of the file."""
    wrong = sorted(skip - data_rows)
    if wrong:
        r, last = wrong[0], max(data_rows, default=1)
        what = f"past the last, row {last}" if r > last else "blank, or inside a quoted cell"
        if r < 2:
            what = "the header" if r == 1 else "rows count from 1, the header"
        raise InputError(
            f"row {r} is to be excluded, but it is no data row of the file ({what})",
            file=name,
            row=r,
        )


def _slow(
    text: str,
    delim: str,
    header: list[str],
    idx: list[int],
    name: str,
    skip: frozenset[int] = frozenset(),
    unnamed: frozenset[int] = frozenset(),
    hint: str = "",
) -> tuple[np.ndarray, np.ndarray]:
    """Parse every record (``idx``: the columns to read as numbers); a value in one of the
    ``unnamed`` columns, which the columns taken by place passed over, is an error, and a
    record may leave those cells out where they end it."""
    reader = csv.reader(io.StringIO(text), delimiter=delim)
    next(reader)
    out: list[list[float]] = []
    rows: list[int] = []
    seen: set[int] = set()
    width = len(header)
    last = reader.line_num
    lines: list[str] = []
    joined: list[tuple[int, int]] = []
    for cells in _checked(reader, name):
        row = reader.line_num
        start, last = last + 1, row
        if row > start and _unclosed(text, start, delim):  # it ran to the end of the file
            raise InputError(
                "a quoted cell opens in this row and is never closed", file=name, row=start
            )
        if row > start and len(cells) != width:  # lines run together by a stray quote
            raise InputError(
                f"a quoted cell opens in this row and runs on to row {row}, which leaves "
                f"{len(cells)} cell{'s' * (len(cells) != 1)} for {width} columns: a stray "
                "quote?",
                file=name,
                row=start,
            )
        if row > start:  # a quoted cell spans lines: a note, or a stray quote
            joined.append((start, row))
        row = start  # a record of several lines is named by its first
        if not cells or all(not c.strip() for c in cells):
            if width - len(unnamed) > 1 or '"' not in _line(text, row, lines):
                continue  # blank line; a spreadsheet writes an empty row as ",,"
            # a lone quoted empty cell ("") is a reading left empty: _number names it
        seen.add(row)
        if row in skip:
            continue
        if len(cells) < width and unnamed.issuperset(range(len(cells), width)):
            cells += [""] * (width - len(cells))  # trailing unnamed cells left out
        if len(cells) != width:
            what = "missing cells" if len(cells) < width else "extra cells"
            why = ""
            if delim == "," and len(cells) == 2 * width and all(c.isdigit() for c in cells[1::2]):
                why = "; decimal commas? Write numbers with a decimal point"
            raise InputError(
                f"{what}: expected {width} ({', '.join(header)}), got {len(cells)}{why}",
                file=name,
                row=row,
            )
        if not out and all(_is_text(cells[j]) and not _begins_as_number(cells[j]) for j in idx):
            got = ", ".join(repr(cells[j].strip()) for j in idx)
            later = next(
                (c for c in reader if len(c) > max(idx) and all(_is_value(c[j]) for j in idx)),
                None,
            )
            if later is None:
                named = [j for j in idx if _is_text(cells[j])]  # (the reader ran to the end)
                raise InputError(  # (a review: a text column taken was called a units row)
                    f"expected numbers, got {got}, and no later row has them: column"
                    f"{'s' * (len(named) > 1)} {', '.join(repr(header[j]) for j in named)} "
                    f"hold{'s' * (len(named) == 1)} no readings (the wrong column?){hint}",
                    file=name,
                    row=row,
                )
            comma = any(_DECIMAL_COMMA.fullmatch(later[j].strip()) for j in idx)
            raise InputError(  # no number where one is due: a second header row?
                f"expected numbers, got {got}: a row of units under the header? Delete it"
                + ("; and the rows below write decimal commas: use a point" if comma else ""),
                file=name,
                row=row,
            )
        vals = []
        for j, cell in enumerate(cells):
            if j not in idx:
                if j in unnamed and cell.strip():
                    raise InputError(
                        f"{cell.strip()!r} in column {j + 1}, which the header row leaves "
                        f"unnamed: name it, or delete the cell{hint}",
                        file=name,
                        row=row,
                    )
                vals.append(math.nan)
                continue
            vals.append(_number(cell, name, row, header[j]))
        out.append(vals)
        rows.append(row)
    _check_excluded(skip, seen, name)
    joined = [(a, b) for a, b in joined if a not in skip]  # (one left out is dealt with)
    if joined:
        (a, b), more = joined[0], len(joined) - 1
        others = f" (and {more} more record{'s' * (more > 1)} like it)" if more else ""
        warnings.warn(
            f"{name}, rows {a} to {b}: read as one record, a quoted cell spanning the "
            f"lines{others}; if a stray quote joined them, those rows are not read",
            DataWarning,
            stacklevel=4,
        )
    values = np.array(out, dtype=float).reshape(len(out), width)
    return values, np.array(rows, dtype=np.int64)


def _line(text: str, row: int, lines: list[str]) -> str:
    """Line ``row`` (1-based) of ``text``; ``lines`` caches the split (empty until needed)."""
    if not lines:
        lines.extend(text.split("\n"))
    return lines[row - 1]


def _unclosed(text: str, start: int, delim: str) -> bool:
    """Whether the record starting on line ``start`` (1-based) opens a quote it never
    closes (a lenient reader takes the rest of the file into that cell)."""
    tail = text.split("\n", start - 1)[-1]
    try:
        next(csv.reader(io.StringIO(tail), delimiter=delim, strict=True), None)
    except csv.Error as exc:
        return "unexpected end of data" in str(exc)
    return False


#: A number as a CSV cell may write it: ASCII digits, an optional sign, point and exponent,
#: or nan / inf (refused later, by name). Python's ``float`` also takes digit-group
#: underscores (``0.1_16``) and other scripts' digits (full-width ``１.0``): mistyped cells.
_NUMBER = re.compile(
    r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|(?i:nan|inf|infinity))", re.ASCII
)


def _number(cell: str, name: str, row: int, column: str) -> float:
    s = cell.strip()
    if not s:
        raise InputError("expected a number, got an empty cell", file=name, row=row, column=column)
    if not _NUMBER.fullmatch(s):
        hint = ""
        if _DECIMAL_COMMA.fullmatch(s):
            hint = ": a decimal comma (or a thousands separator)? Write numbers with a point"
        raise InputError(
            f"expected a number, got {_cell(s)}{hint}", file=name, row=row, column=column
        )
    v = float(s)
    if not math.isfinite(v):
        raise InputError(
            f"expected a finite number, got {_cell(s)}", file=name, row=row, column=column
        )
    return v


#: A number written with a decimal comma (``-0,045``), as spreadsheets of many locales do.
_DECIMAL_COMMA = re.compile(r"[+-]?\d+,\d+(?:[eE][+-]?\d+)?", re.ASCII)


def _is_text(cell: str) -> bool:
    """A cell that is neither empty nor a number (with a decimal point or comma)."""
    s = cell.strip()
    return bool(s) and not _NUMBER.fullmatch(s) and not _DECIMAL_COMMA.fullmatch(s)


def _is_value(cell: str) -> bool:
    """A cell that holds a number, with a decimal point or a decimal comma."""
    return bool(cell.strip()) and not _is_text(cell)


def is_number(s: str) -> bool:
    """Whether ``s`` is a number as a CSV cell writes it (:data:`_NUMBER`)."""
    return _NUMBER.fullmatch(s.strip()) is not None


def _cell(s: str) -> str:
    """A cell's text for a message, a long one shortened (a review: a cell of 5000 digits
    had made a message of 5 kB)."""
    return repr(s) if len(s) <= 40 else f"{s[:24]!r}...{s[-8:]!r} ({len(s)} characters)"
