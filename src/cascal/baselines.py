"""Alternative 2 of the paper: offset lookup tables with linear interpolation.

A table stores the correction offset ``reference - reading`` at its knots and interpolates
it linearly; beyond the table's ends the offset is held constant, as controllers'
error-compensation tables do (and as the identity prior mean suggests). Alternative 1 (a
homoscedastic GP) is :func:`cascal.fit_gp` with a learned scalar noise; see ``cascade``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .validation import as_positions, as_readings, check_pair, frozen, scalar_out

__all__ = ["OffsetTable", "fit_table"]


@dataclass(frozen=True, slots=True)
class OffsetTable:
    """Lookup table of correction offsets.

    Attributes:
        knots: Readings at the table entries, strictly increasing, shape (k,).
        offsets: Correction ``reference - reading`` at each knot, shape (k,), same unit.
    """

    knots: np.ndarray
    offsets: np.ndarray

    def __post_init__(self) -> None:
        knots, offsets = as_positions(self.knots, "knots"), as_positions(self.offsets, "offsets")
        if knots.shape != offsets.shape or knots.size < 1:
            raise InputError(
                f"knots and offsets: expected the same length >= 1, got {knots.size} and "
                f"{offsets.size}"
            )
        if np.any(np.diff(knots) <= 0):
            raise InputError("knots: expected strictly increasing readings")
        object.__setattr__(self, "knots", frozen(knots))
        object.__setattr__(self, "offsets", frozen(offsets))

    def __call__(self, readings: object) -> np.ndarray:
        """Corrected positions ``readings + offset(readings)``, shape (m,); a number for one."""
        r, scalar = as_readings(readings, "readings")
        return scalar_out(r + np.interp(r, self.knots, self.offsets), scalar)


def fit_table(x: object, y: object, names: tuple[str, str] = ("x", "y")) -> OffsetTable:
    """Table mapping readings ``x`` (n,) to references ``y`` (n,). A repeated reading
    must repeat its reference too (:func:`~cascal.validation.check_pair` refuses others:
    average them first, ``cascal.aggregate_repeats``); it is one knot."""
    xa, ya = check_pair(x, y, names)
    order = np.argsort(xa, kind="stable")
    knots = xa[order]
    if (knots[1:] > knots[:-1]).all():  # no repeats: the readings sorted are the knots
        return OffsetTable(knots, (ya - xa)[order])
    knots, inverse = np.unique(xa, return_inverse=True)
    offsets = np.bincount(inverse, weights=ya - xa) / np.bincount(inverse)
    return OffsetTable(knots, offsets)
