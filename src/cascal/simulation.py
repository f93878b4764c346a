"""The paper's simulated sensors and calibration designs (its Monte Carlo study, SPEC.md).

Each sensor reads ``y_i = y* + e_i(y*) + eps`` with ``e_i`` a sum of ten random sinusoids;
the reference reads ``y3 = y* + eps``. ``D2`` pairs test-bed and reference readings at 64
positions (edges and centre unreachable); ``D1`` pairs device and test-bed readings at 100
positions equally spaced in the device reading. Positions are in m on ``[0, 1]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from .errors import InputError
from .validation import check_count

__all__ = [
    "COEF_VARIANCE",
    "FREQ_VARIANCE",
    "NOISE_VARIANCE",
    "SensorMap",
    "Trial",
    "cost_j",
    "draw_map",
    "j_reference",
    "reference_positions",
    "simulate_trial",
]

NOISE_VARIANCE = 1e-8  #: variance of every reading's noise eps, m^2
COEF_VARIANCE = 1e-4  #: variance of the sinusoid amplitudes a, b, c, d, m^2
FREQ_VARIANCE = 6.0  #: variance of the angular frequencies w, (rad/m)^2
N_TERMS = 10
J_GRID = 2001  #: points of the trapezoid rule in the cost J


@dataclass(frozen=True, slots=True)
class SensorMap:
    """True position -> reading: ``y* + sum_k a_k sin(w_k y*) + b_k cos(w_k y*)``.

    Attributes:
        a, b: Sine and cosine amplitudes, shape (10,), m.
        w: Angular frequencies, shape (10,), rad/m.
    """

    a: np.ndarray
    b: np.ndarray
    w: np.ndarray

    def __post_init__(self) -> None:
        terms = [np.ascontiguousarray(getattr(self, name), float) for name in ("a", "b", "w")]
        if not (terms[0].ndim == 1 and terms[0].shape == terms[1].shape == terms[2].shape):
            shapes = ", ".join(str(t.shape) for t in terms)
            raise InputError(f"sensor map: expected a, b and w of one shape (k,), got {shapes}")
        for name, value in zip(("a", "b", "w"), terms, strict=True):  # (as the compiled sums
            object.__setattr__(self, name, value)  # take them: contiguous float64)

    def __call__(self, y: np.ndarray) -> np.ndarray:
        """Noise-free reading at true positions ``y`` (m,), m."""
        return self._evaluate(y, False)[0]

    def on_grid(self, n: int, lo: float = 0.0, hi: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """``n`` equally spaced true positions on ``[lo, hi]`` and their noise-free readings,
        each (n,), m.

        No sine or cosine per position: position ``j q + p`` is a coarse angle ``c_j`` plus
        a fine one ``f_p``, ``q`` about ``sqrt(n)``, and ``a sin(c + f) + b cos(c + f) =
        cos c (b cos f + a sin f) + sin c (a cos f - b sin f)``, from tables of ``sqrt(n)``
        rows (round-off of 1e-16 relative to the amplitudes).
        """
        y = np.linspace(lo, hi, n)
        h = (hi - lo) / max(n - 1, 1)
        return y, _on_grid(y, float(lo), h, math.isqrt(max(n - 1, 0)) + 1, self.a, self.b, self.w)

    def slope(self, y: np.ndarray) -> np.ndarray:
        """d reading / d y* at ``y`` (m,), dimensionless."""
        return self._evaluate(y, True)[1]

    def is_increasing(self, lo: float = 0.0, hi: float = 1.0) -> bool:
        """True if the map is strictly increasing on ``[lo, hi]`` (a rigorous check).

        The slope deviates from 1 by at most ``B1 = sum |w| hypot(a, b)``; if ``B1 < 1`` the
        map is increasing. Otherwise the slope is sampled with spacing ``h`` and the smallest
        sample must exceed ``B2 h / 2``, ``B2 = sum w^2 hypot(a, b)`` bounding its change.
        """
        amp = np.hypot(self.a, self.b)
        if float(np.sum(np.abs(self.w) * amp)) < 1.0:
            return True
        b2 = float(np.sum(self.w**2 * amp))
        n = max(1001, int(np.ceil(b2 * (hi - lo) / 0.02)) + 1)
        grid = np.linspace(lo, hi, n)
        return bool(self.slope(grid).min() > b2 * (grid[1] - grid[0]) / 2)

    def inverse(
        self,
        readings: np.ndarray,
        lo: float = 0.0,
        hi: float = 1.0,
        table: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """True positions whose noise-free reading is ``readings`` (m,), m.

        Linear interpolation in a table of the map gives the start (``table``: positions
        and readings on ``[lo, hi]`` as :meth:`on_grid` gives them; 2049 points by
        default, within about 1e-8 of the root); Newton steps (clipped to ``[lo, hi]``)
        then converge quadratically to round-off, mostly in two. The map must be
        increasing on ``[lo, hi]``.
        """
        r = np.asarray(readings, dtype=float)
        positions, values = table if table is not None else self.on_grid(2049, lo, hi)
        y = np.interp(r.ravel(), values, positions)
        y = _newton(r.ravel(), y, self.a, self.b, self.w, float(lo), float(hi))
        return y.reshape(r.shape)

    def value_and_slope(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``self(y)`` and ``self.slope(y)`` from one evaluation of the sinusoids."""
        return self._evaluate(y, True)

    def _evaluate(self, y: np.ndarray, slope: bool) -> tuple[np.ndarray, np.ndarray]:
        y = np.asarray(y, dtype=float)
        value, grad = _sinusoids(y.ravel(), self.a, self.b, self.w, slope)
        return value.reshape(y.shape), grad.reshape(y.shape) if slope else grad


@njit(cache=True)
def _sinusoids(y, a, b, w, slope):
    """Readings ``y + sum_k a_k sin(w_k y) + b_k cos(w_k y)`` at ``y`` (m,), and where
    ``slope``, their derivatives (m,) (else an empty array); compiled: no temporaries of
    m x 10."""
    m = y.size
    value = np.empty(m)
    grad = np.empty(m if slope else 0)
    for i in range(m):
        e = 0.0  # the sinusoids' sum, added to y last (the smaller terms summed first)
        g = 0.0
        for k in range(w.size):
            t = w[k] * y[i]
            sn = math.sin(t)
            cs = math.cos(t)
            e += a[k] * sn + b[k] * cs
            if slope:
                g += w[k] * (a[k] * cs - b[k] * sn)
        value[i] = y[i] + e
        if slope:
            grad[i] = 1.0 + g
    return value, grad


@njit(cache=True)
def _on_grid(y, lo, h, q, a, b, w):
    """:meth:`SensorMap.on_grid`'s readings at ``y`` (n,), ``y[j q + p] = lo + (j q + p) h``."""
    n = y.size
    nc = -(-n // q)
    cc = np.empty((nc, w.size))  # cos and sin of the coarse angles w (lo + j q h)
    sc = np.empty((nc, w.size))
    for j in range(nc):
        for k in range(w.size):
            t = w[k] * (lo + q * h * j)
            cc[j, k] = math.cos(t)
            sc[j, k] = math.sin(t)
    fb = np.empty((w.size, q))  # b cos f + a sin f and a cos f - b sin f, f = w p h
    fa = np.empty((w.size, q))
    for k in range(w.size):
        for p in range(q):
            t = w[k] * (h * p)
            cf = math.cos(t)
            sf = math.sin(t)
            fb[k, p] = b[k] * cf + a[k] * sf
            fa[k, p] = a[k] * cf - b[k] * sf
    e = (cc @ fb + sc @ fa).ravel()  # position j q + p at j, p
    return y + e[:n]


@njit(cache=True)
def _newton(r, y, a, b, w, lo, hi):
    """Newton's method for the positions ``y`` (m,) whose readings are ``r`` (m,), from
    ``y``, each step clipped to [lo, hi], until no position moves by more than 1e-15."""
    for _ in range(30):
        value, slope = _sinusoids(y, a, b, w, True)
        y_new = np.minimum(np.maximum(y - (value - r) / slope, lo), hi)
        done = np.max(np.abs(y_new - y)) <= 1e-15 if y.size else True
        y = y_new
        if done:
            break
    return y


def draw_map(rng: np.random.Generator) -> SensorMap:
    """One random sensor-error map as in the paper (amplitude and frequency variances)."""
    a = rng.normal(0.0, np.sqrt(COEF_VARIANCE), N_TERMS)
    b = rng.normal(0.0, np.sqrt(COEF_VARIANCE), N_TERMS)
    w = rng.normal(0.0, np.sqrt(FREQ_VARIANCE), N_TERMS)
    return SensorMap(a, b, w)


def reference_positions() -> np.ndarray:
    """The 64 true positions of D2: 100 equally spaced on [0, 1], minus 10 at each end and
    the middle 16 of the 80 left (where the reference instrument cannot reach). A copy."""
    return _REFERENCE.copy()


_REFERENCE = np.delete(np.linspace(0.0, 1.0, 100)[10:90], np.s_[32:48])


@dataclass(frozen=True, slots=True)
class Trial:
    """One simulated calibration problem.

    Attributes:
        testbed_map, device_map: Maps true position -> test-bed / device reading.
        d2: (test-bed readings, reference readings), each (64,), m.
        d1: (device readings, test-bed readings), each (100,), m.
        redraws: Map draws discarded because a map was not strictly increasing.
        nodes: :func:`j_reference`'s nodes where the simulation has them (its inversion's
            table), else None.
    """

    testbed_map: SensorMap
    device_map: SensorMap
    d2: tuple[np.ndarray, np.ndarray]
    d1: tuple[np.ndarray, np.ndarray]
    redraws: int
    nodes: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def device_range(self) -> tuple[float, float]:
        """Noise-free device readings at y* = 0 and 1: the range of the cost J."""
        ends = self.device_map(np.array([0.0, 1.0]))
        return float(ends[0]), float(ends[1])

    def truth(self, device_readings: np.ndarray) -> np.ndarray:
        """True map f_1->3: device reading -> true position, shape (m,)."""
        return self.device_map.inverse(device_readings)


def simulate_trial(rng: np.random.Generator, *, n1: int = 100) -> Trial:
    """Draw one trial of the paper's study from ``rng`` (maps first, then reading noise)."""
    if not isinstance(rng, np.random.Generator):
        raise InputError(
            f"rng: expected a numpy.random.Generator (np.random.default_rng(seed)), got "
            f"{type(rng).__name__}"
        )
    check_count(n1, "n1", "device points", 2)
    redraws = 0
    while True:
        testbed, device = draw_map(rng), draw_map(rng)
        if testbed.is_increasing() and device.is_increasing():
            break
        redraws += 1
    sd = np.sqrt(NOISE_VARIANCE)
    ys2 = reference_positions()
    y3 = ys2 + rng.normal(0.0, sd, ys2.size)
    y2 = testbed(ys2) + rng.normal(0.0, sd, ys2.size)
    ends = device(np.array([0.0, 1.0]))
    grid = np.linspace(ends[0], ends[1], n1)
    truth, readings = device.on_grid(J_GRID)  # J's nodes, and the inversion's table
    truth.setflags(write=False)  # (the trial keeps them: j_reference returns them)
    readings.setflags(write=False)
    ys1 = device.inverse(grid, table=(truth, readings))
    y1 = grid + rng.normal(0.0, sd, n1)
    y2_1 = testbed(ys1) + rng.normal(0.0, sd, n1)
    return Trial(testbed, device, (y2, y3), (y1, y2_1), redraws, (readings, truth))


def cost_j(
    trial: Trial,
    corrected: np.ndarray | None = None,
    correct=None,
    reference: tuple[np.ndarray, np.ndarray] | None = None,
) -> float:
    """RMS of ``fhat_1->3 - f_1->3`` over the device range (trapezoid rule, 2001 points).

    Args:
        trial: The simulated trial (its true device map).
        corrected: Estimated true positions at the readings of :func:`j_reference`, (2001,); or
        correct: A callable device readings -> estimated true positions.
        reference: ``j_reference(trial)``, when already computed.
    """
    grid, truth = reference if reference is not None else j_reference(trial)
    est = correct(grid) if correct is not None else np.asarray(corrected, dtype=float)
    err = est - truth
    err2 = err * err
    area = 0.5 * float((grid[1:] - grid[:-1]) @ (err2[1:] + err2[:-1]))  # the trapezoid rule
    return math.sqrt(area / float(grid[-1] - grid[0]))


def j_reference(trial: Trial) -> tuple[np.ndarray, np.ndarray]:
    """Nodes of J's trapezoid rule: device readings (2001,), increasing from the device
    range's start to its end, and the true positions there (2001,), m.

    The nodes are the noise-free readings at 2001 equally spaced true positions on [0, 1],
    so the truth there is exact, with no inversion; the map's slope (0.56 to 1.45 in 20 000
    draws) keeps their spacing within a factor of 3 of uniform.
    """
    if trial.nodes is not None:
        return trial.nodes
    truth, grid = trial.device_map.on_grid(J_GRID)
    return grid, truth
