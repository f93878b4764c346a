"""A compensation table as text: a C header for controller firmware, or CSV.

Every number is written with the shortest decimal that reads back as the same double
(Python's ``repr``), so the header's table, compiled, holds exactly the library's values,
and its correction function does the same operations as
:meth:`cascal.compensation.CompensationTable.__call__`: compiled as ISO C (no contraction
of a multiply and an add into one rounding), it gives the same doubles.
"""

from __future__ import annotations

import hashlib
import re

import numpy as np

from ..compensation import CompensationTable
from ..errors import InputError

__all__ = ["c_header", "c_identifier", "table_csv"]

_IDENTIFIER = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
#: Beginnings of macro names the C standard library reserves where its headers are
#: included (C99 7.26: errno's, signal's, locale's, inttypes' and fenv's), as the header's
#: ``NAME_N`` is one. (Its functions' beginnings, ``is``, ``to``, ``str``, ..., are
#: reserved with external linkage, and at file scope only where ctype.h or string.h is
#: included, which the header does not do: refusing them refused ordinary names.)
_RESERVED = re.compile(r"E[0-9A-Z]|SIG_?[A-Z]|LC_[A-Z]|PRI[a-zX]|SCN[a-zX]|FE_[A-Z]")


def c_identifier(name: str) -> str:
    """``name`` checked as the prefix of C identifiers: a letter, then letters, digits and
    underscores (a leading underscore would make reserved names), no two underscores
    together or at its end (C++ reserves ``__``), and none of the beginnings of macro names
    the C library reserves (``E1``, ``SIGX``, ``LC_X``, ...)."""
    if not _IDENTIFIER.fullmatch(name):
        raise InputError(
            f"--name: expected a C identifier starting with a letter (then letters, digits, "
            f"_), got {name!r}"
        )
    if "__" in name or name.endswith("_"):
        raise InputError(
            f"--name {name}: two underscores in a row (the identifiers add _N, _LO, ...: "
            "a trailing _ makes them) are reserved in C++; choose another prefix"
        )
    reserved = _RESERVED.match(name)
    if reserved:
        raise InputError(
            f"--name {name}: identifiers beginning {reserved.group()!r} are reserved by the C "
            "standard library (C99 7.26); choose another prefix"
        )
    return name


def _numbers(values: np.ndarray, per_line: int = 4) -> str:
    text = [repr(float(v)) for v in values]
    lines = [", ".join(text[i : i + per_line]) for i in range(0, len(text), per_line)]
    return ",\n".join(f"    {line}" for line in lines)


def c_header(table: CompensationTable, name: str, about: list[str]) -> str:
    """A self-contained C99 header: the table and ``int NAME_correct(double NAME_reading,
    double *NAME_corrected)``, which returns 0 inside the table (any reading, for a periodic
    one) and 1 outside it, where the nearest end's correction is held.

    Args:
        table: The compensation table.
        name: Prefix of every identifier, a C identifier.
        about: Lines for the header's opening comment (provenance, unit, tolerance); a
            ``*/`` and ``/*`` in them are broken up, so the comment cannot end early.
    """
    p = c_identifier(name)
    safe = [line.replace("*/", "* /").replace("/*", "/ *") for line in about]
    intro = "\n".join(f" * {line}".rstrip() for line in safe)
    # Quiet comparisons (isless, isgreaterequal, ...) and isfinite where a reading may be
    # NaN or infinite: an ordered comparison with NaN, or fmod of an infinity, would raise
    # the invalid-operation exception, which a controller may trap.
    # Locals and parameters carry the prefix too (a firmware's own global ``status`` or ``t``
    # had been shadowed: an error with -Wshadow -Werror), and none ends in _t (a typedef
    # ``NAME_t`` would be shadowed; such names are the types').
    names = ("pos", "node", "status", "angle", "reading", "corrected")
    t, i, st, a, r, c = (f"{p}_{v}" for v in names)
    if table.period is not None:
        limit = "HUGE_VAL" if table.limit == float("inf") else repr(table.limit)
        reduce = (
            f"    double {t} = 0.0;\n"
            f"    /* infinite, NaN, or so large that a double holds it less finely than u */\n"
            f"    int {st} = isless(fabs({r}), {p}_LIMIT) ? 0 : 1;\n"
            f"    if (isfinite({r})) {{\n"
            f"        {t} = fmod({r} - {p}_LO, {p}_PERIOD);\n"
            f"        if ({t} < 0.0) {t} += {p}_PERIOD;\n"
            f"        {t} /= {p}_STEP;\n"
            f"        if ({t} > {p}_N - 1) {t} = {p}_N - 1;\n"
        )
        extra = (
            f"static const double {p}_PERIOD = {table.period!r};\n"
            f"static const double {p}_LIMIT = {limit};\n"
        )
        if table.arc is not None:  # the part of the turn the device readings left out
            reduce += (
                f"        double {a} = fmod({r} - {p}_ARC_START, {p}_PERIOD);\n"
                f"        if ({a} < 0.0) {a} += {p}_PERIOD;\n"
                f"        if ({a} > 0.0 && {a} < {p}_ARC_WIDTH) {st} = 1; /* never measured */\n"
            )
            extra += (
                f"static const double {p}_ARC_START = {table.arc[0]!r};\n"
                f"static const double {p}_ARC_WIDTH = {table.arc[1]!r};\n"
            )
        reduce += "    }\n"
    else:
        # outside the range, no division: a huge reading's would overflow (a trap)
        reduce = (
            f"    int {st} = islessequal({p}_LO, {r}) && islessequal({r}, {p}_HI) ? 0 : 1;\n"
            f"    double {t} = isgreater({r}, {p}_HI) ? {p}_N - 1 : 0.0; /* below, or NaN */\n"
            f"    if ({st} == 0) {t} = ({r} - {p}_LO) / {p}_STEP;\n"
            f"    if ({t} > {p}_N - 1) {t} = {p}_N - 1;\n"
        )
        extra = f"static const double {p}_HI = {table.hi!r};\n"
    maths = (  # (a README review: the linear table's comment asked for -lm it does not need)
        "fmod, fabs and the quiet comparisons: link with -lm"
        if table.period is not None
        else "the quiet comparisons (macros: no -lm needed)"
    )
    include = (
        f"#include <math.h> /* {maths} */\n"
        "#include <float.h>\n\n"
        "#if DBL_MANT_DIG != 53 || DBL_MAX_EXP != 1024\n"
        '#error "this table needs IEEE 754 binary64 doubles: a 32-bit double loses its '
        'corrections"\n'
        "#endif\n\n"
    )
    returns = (
        "Returns 0, or 1 for an infinite or NaN reading or one from LIMIT on\n * in "
        "magnitude (a double holds it less finely than the smallest u)."
        if table.period is not None and table.arc is None
        else "Returns 0, or 1 for an infinite or NaN reading, one from LIMIT on\n * in "
        "magnitude (a double holds it less finely than the smallest u) or one in the\n * "
        "part of the turn the device readings left out (from ARC_START over ARC_WIDTH)."
        if table.period is not None
        else "Returns 0 inside the calibrated range, 1 outside\n * it or for a NaN reading "
        "(the nearest end's correction is then held)."
    )
    comment = f"""/*
{intro}
 *
 * corrected = reading + correction(reading), the correction interpolated linearly between
 * {table.n} equally spaced readings from {p}_LO in steps of {p}_STEP.
 * Compiled as ISO C (e.g. -std=c99, or with -ffp-contract=off: no fused multiply-add)
 * where doubles are evaluated in double precision (FLT_EVAL_METHOD 0: SSE2, every 64-bit
 * target; not the x87 unit), {p}_correct gives cascal's doubles to the last bit; with
 * contraction or x87, within one rounding.
 * Infinite and NaN readings need IEEE arithmetic: not with -ffast-math or
 * -ffinite-math-only. They raise no floating-point exception here (quiet comparisons),
 * so a controller that traps invalid operations gets status 1 for them, not a trap.
 */
"""
    body = f"""{include}#define {p}_N {table.n}

static const double {p}_LO = {table.lo!r};
static const double {p}_STEP = {table.step!r};
{extra}
static const double {p}_CORRECTION[{p}_N] = {{
{_numbers(table.correction)}
}};

/* Corrected reading of a device reading. {returns} */
static inline int {p}_correct(double {r}, double *{c})
{{
{reduce}    long {i} = (long){t};
    if ({i} > {p}_N - 2) {i} = {p}_N - 2;
    {t} -= (double){i};
    *{c} = {r} + ({p}_CORRECTION[{i}] + {t} * ({p}_CORRECTION[{i} + 1] - {p}_CORRECTION[{i}]));
    return {st};
}}

"""
    # The guard names the content too: two different tables of one name, included
    # together, fail to compile (duplicate definitions) instead of one being skipped.
    guard = f"CASCAL_TABLE_{p}_{hashlib.sha256(body.encode()).hexdigest()[:12].upper()}_H"
    return f"{comment}#ifndef {guard}\n#define {guard}\n\n{body}#endif /* {guard} */\n"


def table_csv(table: CompensationTable) -> str:
    """CSV text: ``reading,correction,corrected`` (and ``u`` where the model has one) at
    every node, each number as the shortest decimal that reads back as the same double."""
    x = table.nodes()
    cols = [x, table.correction, x + table.correction]
    head = ["reading", "correction", "corrected"]
    if table.u is not None:
        cols.append(table.u)
        head.append("u")
    rows = (",".join(repr(float(v)) for v in row) for row in zip(*cols, strict=True))
    return ",".join(head) + "\n" + "\n".join(rows) + "\n"
