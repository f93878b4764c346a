"""Prior mean functions m(x) of a calibration map: identity, identity plus an offset, zero
or a constant."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["Mean", "make_mean"]


@dataclass(frozen=True, slots=True)
class Mean:
    """m(x) = slope * x + offset; identity (1, 0): the reading is right until shown otherwise."""

    slope: float = 1.0
    offset: float = 0.0

    def __post_init__(self) -> None:
        for name in ("slope", "offset"):
            v = getattr(self, name)
            ok = np.ndim(v) == 0 and isinstance(np.asarray(v).item(), numbers.Real)
            if not (ok and math.isfinite(v)):
                raise InputError(f"mean {name}: expected a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Prior mean at positions ``x`` (n,), same unit, shape (n,)."""
        x = np.asarray(x, dtype=float)
        if self.slope == 0.0:
            return np.full(x.shape, self.offset)
        return self.slope * x + self.offset if self.offset else self.slope * x

    @property
    def name(self) -> str:
        if self.slope == 1.0:
            return "identity" if self.offset == 0.0 else "offset"
        if self.slope == 0.0:
            return "zero" if self.offset == 0.0 else "constant"
        return "linear"


def make_mean(
    spec: str | float | Mean, y: np.ndarray | None = None, x: np.ndarray | None = None
) -> Mean:
    """Mean from ``"identity"``, ``"offset"`` (identity plus the mean of ``y - x``: two
    sensors whose zeros differ), ``"zero"``, ``"constant"`` (mean of ``y``) or a number."""
    if isinstance(spec, Mean):
        return spec
    if isinstance(spec, numbers.Real) and not isinstance(spec, bool):
        if not math.isfinite(spec):
            raise InputError(f"mean: expected a finite number, got {spec!r}")
        return Mean(0.0, float(spec))
    key = str(spec).lower()
    if key == "identity":
        return Mean(1.0, 0.0)
    if key == "zero":
        return Mean(0.0, 0.0)
    if key in ("constant", "offset"):
        if y is None or (key == "offset" and x is None):
            raise InputError(f"mean={key!r} needs the positions and targets to take their average")
        if key == "constant":
            return Mean(0.0, float(np.mean(y)))
        return Mean(1.0, float(np.mean(np.asarray(y, float) - np.asarray(x, float))))
    raise InputError(
        f"unknown mean {spec!r}; expected 'identity', 'offset', 'zero', 'constant' or a number"
    )
