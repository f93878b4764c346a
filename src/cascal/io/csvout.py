"""CSV output: columns of numbers as fixed-decimal text, built by integer arithmetic.

Formatting floats one at a time in Python takes about a second per million; here whole
columns are scaled to integers and cut into digits with array operations (in blocks of
rows on several threads), so writing 10^6 corrected readings takes a fraction of that.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from .atomic import atomic_write

__all__ = ["auto_decimals", "exact_decimals", "format_columns", "write_columns"]

#: Above this many rows, CSV text is built on several threads.
_THREADED_ROWS = 200_000
#: Cells rounded one by one in Python (half-way cases) before a block is left to Python:
#: this many, plus a quarter of the block's rows (readings with one decimal more than the
#: output keeps are half-way in a tenth of the cells: a review's 10^6 of them took 9 s, not
#: 3 s, when a 64th was the limit).
_EXACT_CELLS = 256
#: The four decimal digits of 0..9999 as ASCII, one column per number: shape (4, 10000).
_DIGITS4T = np.array([list(f"{i:04d}".encode()) for i in range(10000)], dtype=np.uint8).T.copy()


def auto_decimals(values: Sequence[np.ndarray], u: np.ndarray | None = None) -> int:
    """Decimals that keep 12 significant digits of the largest value and a resolution of
    at most 1/1000 of the smallest positive uncertainty ``u`` (at most 17).

    Args:
        values: Arrays to be written, any shapes; non-finite entries are ignored.
        u: Standard uncertainties, or None.
    """
    big = max((float(np.max(np.abs(v[np.isfinite(v)]), initial=0.0)) for v in values), default=0)
    k = 12 - (math.floor(math.log10(big)) if big > 0 else 0)
    if u is not None:
        pos = u[np.isfinite(u) & (u > 0)]
        if pos.size:
            k = max(k, math.ceil(-math.log10(float(pos.min()))) + 3)
    return int(min(max(k, 0), 17))


def exact_decimals(values: np.ndarray, least: int) -> tuple[int, bool]:
    """The fewest decimals, at least ``least``, with which every finite value of ``values``
    (any shape) is written back exactly (its text reads as the same float), and True; for
    echoing readings as they were read, whose file may keep more decimals than the
    corrections need. Where none does up to 17, or up to where ``|value| * 10**decimals``
    reaches 2^50 (16 and 17 significant digits: from 2^51 on, :func:`format_columns`
    leaves every cell to Python's slow formatting), the most that keep ``|value| *
    10**decimals`` below 2^46 (beyond, values that are not exact lie near a half-way point
    too often for its fast path), and False; ``least`` and False where that is fewer."""
    a = np.abs(np.asarray(values, dtype=float))
    a = a[np.isfinite(a)]
    best = least
    for k in range(least, 18):
        with np.errstate(over="ignore"):  # (a reading of 1e308: inf, and the loop ends)
            q = np.rint(a * 10.0**k)
        top = float(q.max()) if q.size else 0.0
        if top >= 2.0**50:
            break
        if np.array_equal(q / 10.0**k, a):  # (q exact, 10^k exact: one correct rounding)
            return k, True
        if top < 2.0**46:
            best = k
    return best, False


def format_columns(columns: Sequence[np.ndarray], decimals: int | Sequence[int]) -> bytes | None:
    """CSV rows (no header) of equal-length columns, as UTF-8 bytes.

    Float columns get ``decimals`` decimals, correctly rounded as Python's ``format``
    rounds them (half-way cases of the exact binary value to even); NaN becomes an empty
    cell. Integer and boolean columns are written as integers, and their
    masked entries (a :class:`numpy.ma.MaskedArray`) as empty cells. The text is
    built by integer arithmetic on whole columns, in blocks of rows on several threads.
    Returns None when a value is too large for exact integers
    (``|value| * 10**decimals >= 2**53``), or when more than a few values lie so near a
    half-way point that they need Python's exact rounding (beyond ``2**51`` every one
    does): then format the cells in Python.

    Args:
        columns: Arrays, each shape (n,).
        decimals: Decimals of the float columns, 0 to 17: one for all, or one per column.
    """
    cols = [np.asanyarray(c) for c in columns]
    decs = _per_column(decimals, len(cols))
    n = cols[0].size if cols else 0
    workers = min(os.cpu_count() or 1, 8)
    if n < _THREADED_ROWS or workers == 1:
        return _format_block(cols, decs)
    edges = np.linspace(0, n, workers + 1).astype(int)
    blocks = [[c[a:b] for c in cols] for a, b in itertools.pairwise(edges)]
    with ThreadPoolExecutor(workers) as pool:
        parts = list(pool.map(lambda b: _format_block(b, decs), blocks))
    return None if any(p is None for p in parts) else b"".join(parts)  # type: ignore[arg-type]


def _per_column(decimals: int | Sequence[int], n: int) -> list[int]:
    """``decimals`` as one count per column of ``n``."""
    if isinstance(decimals, int | np.integer):
        return [int(decimals)] * n
    if len(decimals) != n:
        raise ValueError(f"decimals: expected one per column ({n}), got {len(decimals)}")
    return [int(d) for d in decimals]


def _format_block(cols: list[np.ndarray], decs: list[int]) -> bytes | None:
    n = cols[0].size if cols else 0
    plans = []
    for v, decimals in zip(cols, decs, strict=True):
        k = 0 if v.dtype.kind in "biu" else decimals
        v = np.ma.filled(v.astype(float), np.nan)
        ok = np.isfinite(v)
        a = np.abs(v) if ok.all() else np.where(ok, np.abs(v), 0.0)
        with np.errstate(over="ignore"):  # (beyond 2^53 anyway: formatted one by one)
            scaled = a * 10.0**k
        q = np.rint(scaled)
        if q.size and float(q.max()) >= 2.0**53:
            return None
        q = q.astype(np.int64)
        if k:  # near a half-way point the product's rounding may tip it: round exactly
            near = np.flatnonzero(np.abs(np.abs(scaled - q) - 0.5) <= scaled * 2.0**-51)
            if near.size > _EXACT_CELLS + n // 4:  # (beyond 2^51: every cell is near)
                return None  # the caller formats every cell in Python
            for i in near.tolist():
                q[i] = int(f"{float(a[i]):.{k}f}".replace(".", ""))
        nd = len(str((int(q.max()) if q.size else 0) // 10**k))
        neg = (v < 0) & (q > 0)
        plans.append((k, q, nd, neg if neg.any() else None, None if ok.all() else ~ok))
    width = sum(int(p[3] is not None) + p[2] + (p[0] + 1 if p[0] else 0) + 1 for p in plans)
    buf = np.empty((width, n), np.uint8)  # one row per byte position: contiguous writes
    o = 0
    for j, (k, q, nd, neg, bad) in enumerate(plans):
        first = o
        if neg is not None:
            buf[o] = np.where(neg, ord("-"), 0)
            o += 1
        _digits(buf, o, q, nd, k)
        for p in range(nd - 1):  # leading zeros of the integer part
            buf[o + p][q < 10 ** (nd - 1 - p + k)] = 0
        o += nd + (k + 1 if k else 0)
        if bad is not None:
            buf[first:o, bad] = 0
        buf[o] = ord("\n") if j == len(plans) - 1 else ord(",")
        o += 1
    data = buf.T.tobytes()
    return data.replace(b"\0", b"") if b"\0" in data else data


def _digits(buf: np.ndarray, o: int, q: np.ndarray, nd: int, k: int) -> None:
    """Write the ``nd + k`` digits of integers ``q`` (n,), zero-padded, to rows from ``o``,
    with a decimal point after the first ``nd`` when ``k > 0``."""
    p = nd + k
    while p > 0:
        q, r = np.divmod(q, 10000)
        w = min(4, p)
        digits = np.take(_DIGITS4T[4 - w :], r, axis=1)
        for i in range(w):
            d = p - w + i  # index of this digit in the string of nd + k digits
            buf[o + d + (d >= nd)] = digits[i]
        p -= w
    if k:
        buf[o + nd] = ord(".")


def write_columns(
    path: str | os.PathLike, columns: dict[str, np.ndarray], *, decimals: int | Sequence[int]
) -> Path:
    """Write a CSV file atomically: a header, then one row per entry of the columns.

    Args:
        path: Destination.
        columns: Name -> values, all shape (n,); see :func:`format_columns`.
        decimals: Decimals of the float columns: one for all, or one per column.
    """
    sizes = {np.shape(v) for v in columns.values()}
    if len(sizes) > 1 or any(len(sz) != 1 for sz in sizes):
        raise ValueError(f"columns: expected equal shapes (n,), got {sorted(sizes)}")
    body = format_columns(list(columns.values()), decimals)
    if body is None:
        return _write_slow(path, columns, decimals)
    data = (",".join(columns) + "\n").encode() + body
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))


def _write_slow(
    path: str | os.PathLike, columns: dict[str, np.ndarray], decimals: int | Sequence[int]
) -> Path:
    """As :func:`write_columns`, one cell at a time: for values beyond 2^53 / 10^decimals
    (or many near half-way points, see :func:`format_columns`).
    Those up to 1e16 keep the decimals too; larger ones are written in full (``1e+300``)."""

    def cell(x: float | int | None, decimals: int) -> str:
        if x is None:  # masked
            return ""
        if isinstance(x, float):
            if not math.isfinite(x):
                return ""
            if abs(x) >= 1e16:
                return repr(x)
            text = f"{x:.{decimals}f}"
            return text[1:] if text[0] == "-" and not text.strip("-0.") else text  # no -0.000
        return str(int(x))

    lists = [np.ma.asarray(c).tolist() for c in columns.values()]
    decs = _per_column(decimals, len(lists))
    text = ",".join(columns) + "\n"
    text += "".join(
        ",".join(cell(x, k) for x, k in zip(row, decs, strict=True)) + "\n"
        for row in zip(*lists, strict=True)
    )
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
