"""Checks at the library boundary: shapes, finiteness, duplicates, monotone sensor relations."""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = [
    "MIN_POINTS",
    "STAGE_MAX",
    "STAGE_MIN_CORRECTION",
    "STAGE_MIN_SPAN",
    "Repeats",
    "aggregate_repeats",
    "as_positions",
    "as_readings",
    "check_corrections",
    "check_count",
    "check_increasing",
    "check_pair",
    "check_scale",
    "frozen",
    "unwrap",
]

#: Fewest points a stage fit accepts.
MIN_POINTS = 3
#: Stage values must lie below this in magnitude: the fit's products of variances (the
#: unit to the 4th power) stay finite (a stage scaled by 1e100 failed inside the fit).
STAGE_MAX = 1e75
#: A stage's positions must span at least this (where they span anything): its variances,
#: in the unit squared, stay well above float64's smallest normal number.
STAGE_MIN_SPAN = 1e-100
#: A fitted stage's corrections (targets less the prior mean), where any is not 0, must
#: reach this in magnitude: their variance, its products and the jitter of a noiseless
#: factor (a 1e-12 fraction of it) stay well within float64. Corrections of 1e-170 had
#: failed with a message about the data, and a noiseless fit of 1e-74 on a NaN length
#: scale; 1e-60 fits with and without a known noise.
STAGE_MIN_CORRECTION = 1e-60


def as_positions(a: object, name: str) -> np.ndarray:
    """``a`` as a finite float64 vector, shape (n,); raises :class:`InputError` naming ``name``."""
    if isinstance(a, str | bytes) or a is None:  # (NumPy would read "0.5" as a number)
        raise InputError(f"{name}: expected numbers, got {type(a).__name__} {a!r}")
    kinds = _element_kinds(a)
    if "text" in kinds:  # (text, read as numbers by NumPy: a CSV column not converted, say)
        raise InputError(f"{name}: expected numbers, got text (convert it first)")
    if "bool" in kinds:  # (read as 1.0 and 0.0: a mask passed for readings, say)
        raise InputError(f"{name}: expected numbers, got bools")
    try:  # (a ragged list fails in either call)
        complex_ = np.iscomplexobj(a)
        arr = np.asarray(a, dtype=float) if not complex_ else None
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: expected numbers, got {type(a).__name__} ({exc})") from None
    if arr is None:
        raise InputError(f"{name}: expected real numbers, got complex ones")
    if isinstance(a, np.ma.MaskedArray) and np.ma.count_masked(a):
        first = int(np.flatnonzero(np.ma.getmaskarray(a))[0])
        raise InputError(  # (np.asarray takes the values under the mask: they were fitted)
            f"{name}: a masked array with {np.ma.count_masked(a)} masked entries (first at "
            f"index {first}): masked values are not left out by themselves; pass the unmasked "
            "ones (a.compressed(), the same for every aligned array)"
        )
    if arr.ndim != 1:
        raise InputError(f"{name}: expected shape (n,), got {arr.shape}")
    finite = np.isfinite(arr)
    if finite.all():
        return arr
    bad = np.flatnonzero(~finite)
    if bad.size:
        raise InputError(
            f"{name}: expected finite values, got {arr[bad[0]]} at index {bad[0]}"
            + (f" (and {bad.size - 1} more)" if bad.size > 1 else "")
        )
    return arr


def _element_kinds(a: object) -> set[str]:
    """Which of ``"text"`` and ``"bool"`` occur among the entries of an array or list
    ``a`` (a list's top level; an object array's every entry): NumPy reads both as numbers,
    ``"1.0"`` and ``True`` alike, also mixed with numbers."""
    if not isinstance(a, np.ndarray | list | tuple | numbers.Number | str | bytes):
        try:  # (a pandas Series, a deque, a memoryview: as an array, its dtype tells)
            a = np.asarray(a)
        except (TypeError, ValueError):  # (ragged: as_positions names it)
            return set()
    if isinstance(a, np.ndarray):  # (object arrays: an unconverted pandas column's)
        kind = a.dtype.kind
        if kind in "SU":
            return {"text"}
        if kind == "b":
            return {"bool"}
        items = a.flat if kind == "O" else ()
    else:
        items = a if isinstance(a, list | tuple) else ()
    kinds = set()
    for t in set(map(type, items)):  # (the types first: a review timed 0.6 s for 2e6 items)
        if issubclass(t, str | bytes):
            kinds.add("text")
        elif issubclass(t, bool | np.bool_):
            kinds.add("bool")
    return kinds


def as_readings(a: object, name: str) -> tuple[np.ndarray, bool]:
    """``a`` as :func:`as_positions` gives it, a single number (a 0-d array too) as shape
    (1,), and whether it was one: :func:`scalar_out` then gives the answer as one number."""
    if isinstance(a, bool | np.bool_) or (isinstance(a, np.ndarray) and a.dtype.kind == "b"):
        what = f"a bool ({a!r})" if np.ndim(a) == 0 else "bools"  # (0-d too: a review)
        raise InputError(f"{name}: expected numbers, got {what}")
    try:  # (text, also a 0-d array of it, goes to as_positions, which names it)
        textual = isinstance(a, np.ndarray) and a.dtype.kind in "SUO"
        one = not (isinstance(a, str | bytes) or a is None or textual) and np.ndim(a) == 0
    except ValueError:  # (a ragged list: as_positions names it)
        one = False
    if not one or np.iscomplexobj(a):
        return as_positions(a, name), False
    try:  # one number: a float, a NumPy number, a Decimal, a 0-d array
        value = float(a)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected numbers, got {type(a).__name__} {a!r}") from None
    return as_positions(np.array([value]), name), True


def scalar_out(value: np.ndarray, scalar: bool) -> np.ndarray:
    """``value`` (1, ...) as its first entry where the readings were one number, else as
    it is: numbers in, a number out (as ``np.interp`` does)."""
    return value[0] if scalar else value


def check_count(value: object, name: str, what: str, minimum: int) -> None:
    """Refuse ``value`` (a number of ``what``, named ``name``) unless a whole number >=
    ``minimum``."""
    whole = isinstance(value, int | np.integer) and not isinstance(value, bool)
    if not whole or value < minimum:  # type: ignore[operator]
        raise InputError(f"{name}: expected a whole number of {what} >= {minimum}, got {value!r}")


def frozen(a: np.ndarray) -> np.ndarray:
    """A read-only copy of ``a``: what a fitted object keeps, so neither the caller's later
    edits of the array given nor edits of the array returned change it. An array this made
    is returned as it is."""
    if isinstance(a, np.ndarray) and a.dtype == float and a.flags.owndata and not a.flags.writeable:
        return a
    out = np.array(a, dtype=float)
    out.setflags(write=False)
    return out


def unwrap(x: np.ndarray, y: np.ndarray, period: float) -> np.ndarray:
    """Rotary readings ``y`` (n,) moved by whole periods to within half a period of ``x``
    (n,): a reference reading that wrapped past 360 to 0.2 next to a reading of 359.9
    becomes 360.2, so the correction is 0.3, not -359.7."""
    return x + (np.mod(y - x + 0.5 * period, period) - 0.5 * period)


def check_pair(
    x: object, y: object, names: tuple[str, str] = ("x", "y"), *, min_points: int = MIN_POINTS
) -> tuple[np.ndarray, np.ndarray]:
    """Validate aligned readings ``x`` (n,) and targets ``y`` (n,) of one stage.

    Raises:
        InputError: On non-finite values, mismatched lengths, fewer than ``min_points`` points,
            or one position with contradicting targets.
    """
    xa = as_positions(x, names[0])
    ya = as_positions(y, names[1])
    if xa.shape != ya.shape:
        raise InputError(
            f"{names[0]} and {names[1]}: expected the same length, got {xa.size} and {ya.size}"
        )
    if xa.size < min_points:
        raise InputError(f"{names[0]}: expected at least {min_points} points, got {xa.size}")
    order = np.argsort(xa, kind="stable")
    xs = xa[order]
    repeated = xs[1:] == xs[:-1]
    if not repeated.any():
        return xa, ya
    ys = ya[order]
    same = np.flatnonzero(repeated & (ys[1:] != ys[:-1]))
    if same.size:
        i, j = order[same[0]], order[same[0] + 1]
        raise InputError(
            f"{names[0]}: duplicated position {float(xs[same[0]])!r} at indices {i} and {j} "
            f"with contradicting {names[1]} {float(ya[i])!r} and {float(ya[j])!r}; average "
            "repeated readings "
            "(cascal.aggregate_repeats) so their spread becomes a known noise variance"
        )
    return xa, ya


def check_scale(x: np.ndarray, y: np.ndarray, names: tuple[str, str] = ("x", "y")) -> None:
    """Refuse a stage (``x``, ``y``: (n,)) whose values reach :data:`STAGE_MAX` in magnitude
    or whose positions span less than :data:`STAGE_MIN_SPAN`: scales whose variances
    float64 cannot hold.

    Raises:
        InputError: Naming the value or the span and the remedy, another unit.
    """
    for name, v in zip(names, (x, y), strict=True):
        big = float(np.max(np.abs(v), initial=0.0))
        if big >= STAGE_MAX:
            raise InputError(
                f"{name}: a value of {big:.3g} in magnitude: too large a scale to compute "
                f"with (variances in the unit squared overflow); use a larger unit"
            )
    span = float(np.max(x) - np.min(x)) if x.size else 0.0
    if 0.0 < span < STAGE_MIN_SPAN:
        raise InputError(
            f"{names[0]}: the positions span only {span:.3g}: too small a scale to compute "
            "with (variances in the unit squared underflow); use a smaller unit"
        )


def check_corrections(r: np.ndarray, name: str, mean: str) -> None:
    """Refuse corrections ``r`` (n,) to fit hyperparameters to whose largest magnitude is
    below :data:`STAGE_MIN_CORRECTION` but not 0: a scale whose variances underflow.

    Raises:
        InputError: Naming the targets, the prior mean and the remedy, a smaller unit.
    """
    big = float(np.max(np.abs(r), initial=0.0))
    if 0.0 < big < STAGE_MIN_CORRECTION:
        raise InputError(
            f"{name}: the corrections (targets less the prior mean, {mean}) are at most "
            f"{big:.3g} in magnitude: too small a scale to learn hyperparameters at "
            "(variances in the unit squared underflow); use a smaller unit"
        )


def check_increasing(x: np.ndarray, y: np.ndarray, names: tuple[str, str] = ("x", "y")) -> None:
    """Require ``y`` strictly increasing in ``x``: two aligned sensors must relate one-to-one.

    Raises:
        InputError: Naming the first pair of neighbouring points where ``y`` does not increase.
    """
    order = np.argsort(x, kind="stable")
    xs, ys = x[order], y[order]
    if (ys[1:] > ys[:-1]).all() and (xs[1:] > xs[:-1]).all():
        return
    keep = np.r_[True, np.diff(xs) > 0]
    xs, ys, idx = xs[keep], ys[keep], order[keep]
    bad = np.flatnonzero(np.diff(ys) <= 0)
    if bad.size:
        k = bad[0]
        xk, yk, xn, yn = (float(v) for v in (xs[k], ys[k], xs[k + 1], ys[k + 1]))
        raise InputError(
            f"{names[1]} is not increasing in {names[0]}: {names[0]}={xk!r} -> "
            f"{names[1]}={yk!r} (index {idx[k]}) but {names[0]}={xn!r} -> "
            f"{names[1]}={yn!r} (index {idx[k + 1]}); {names[1]} must increase with "
            f"{names[0]} (one-to-one, the paper's bijectivity assumption)"
        )


@dataclass(frozen=True, slots=True)
class Repeats:
    """Readings averaged per position (see :func:`aggregate_repeats`).

    Attributes:
        x: Distinct positions, increasing, shape (k,).
        y: Mean of the targets read at each position, shape (k,).
        noise: Variance of that mean, ``s^2 / count`` (0 where count is 1), shape (k,).
        counts: Readings per position, shape (k,).
        first: Index of each position's first reading in the input, shape (k,).
        inverse: Position of each reading of the input, shape (n,).
    """

    x: np.ndarray
    y: np.ndarray
    noise: np.ndarray
    counts: np.ndarray
    first: np.ndarray
    inverse: np.ndarray


def aggregate_repeats(x: object, y: object, names: tuple[str, str] = ("x", "y")) -> Repeats:
    """Average repeated readings: one point per distinct ``x``, its spread as known noise.

    The target of a position read ``c`` times is the mean of its ``y``; its known noise is
    the variance of that mean, ``s^2 / c`` with the sample variance ``s^2`` (ddof 1). A
    position read once gets 0: the learned white-noise variance covers it.

    Args:
        x: Readings of the sensor being calibrated, shape (n,); repeats are exactly equal.
        y: Readings of the more accurate sensor, shape (n,), same unit.
    """
    xa = as_positions(x, names[0])
    ya = as_positions(y, names[1])
    if xa.shape != ya.shape:
        raise InputError(
            f"{names[0]} and {names[1]}: expected the same length, got {xa.size} and {ya.size}"
        )
    ux, first, inverse, counts = np.unique(
        xa, return_index=True, return_inverse=True, return_counts=True
    )
    # a position's readings summed in increasing order, not in the file's: the means do
    # not depend on the rows' order to the last bit (a review: rows reordered moved a mean
    # by an ulp, and compare took one test-bed calibration for two)
    order = np.lexsort((ya, inverse)) if xa.size > ux.size else slice(None)
    group, ys = inverse[order], ya[order]
    ym = np.bincount(group, weights=ys, minlength=ux.size) / counts
    ss = np.bincount(group, weights=(ys - ym[group]) ** 2, minlength=ux.size)
    noise = np.where(counts > 1, ss / np.maximum(counts - 1, 1) / counts, 0.0)
    return Repeats(ux, ym, noise, counts, first, inverse)
