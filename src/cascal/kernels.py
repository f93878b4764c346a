"""Covariance kernels on 1-D positions, their log-space hyperparameters and gradients.

Every kernel is an immutable value. ``theta`` holds the natural logarithms of its
hyperparameters; ``with_theta`` returns a new kernel. ``gradient`` returns ``K`` and
``dK/dtheta`` (the derivative with respect to the log-hyperparameters). Kernels compose
with ``+`` and ``*``; a number becomes a :class:`Constant`.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, replace

import numpy as np

from .errors import InputError

__all__ = [
    "KERNEL_NAMES",
    "Constant",
    "Kernel",
    "Matern32",
    "Matern52",
    "Periodic",
    "Product",
    "SquaredExp",
    "Sum",
    "make_kernel",
]

_SQRT3 = np.sqrt(3.0)
_SQRT5 = np.sqrt(5.0)


def _diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.subtract.outer(np.asarray(a, dtype=float), np.asarray(b, dtype=float))


class Kernel:
    """Base class: subclasses define ``names``, ``theta``, ``with_theta``, ``_eval``."""

    names: tuple[str, ...] = ()

    @property
    def theta(self) -> np.ndarray:
        """Log-hyperparameters, shape (p,)."""
        raise NotImplementedError

    def with_theta(self, theta: np.ndarray) -> Kernel:
        """A new kernel with log-hyperparameters ``theta`` (shape (p,))."""
        raise NotImplementedError

    @property
    def n_params(self) -> int:
        return len(self.names)

    @property
    def params(self) -> dict[str, float]:
        """Hyperparameters by name, in natural units."""
        return dict(zip(self.names, np.exp(self.theta).tolist(), strict=True))

    def __call__(self, a: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
        """Covariance matrix between positions ``a`` (m,) and ``b`` (n,): shape (m, n)."""
        d = _diff(a, a if b is None else b)
        return self._eval(d, grad=False)[0]

    def diag(self, x: np.ndarray) -> np.ndarray:
        """Prior variances k(x_i, x_i), shape (n,)."""
        return self._eval(np.zeros(np.shape(x)), grad=False)[0]

    def gradient(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """K (n, n) and dK/dtheta (p, n, n) at positions ``x`` (n,)."""
        return self.gradient_from_diff(_diff(x, x))

    def gradient_from_diff(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`gradient`, from the matrix of differences ``d`` (n, n)."""
        K, dK = self._eval(d, grad=True)
        return K, dK

    def _eval(self, d: np.ndarray, grad: bool) -> tuple[np.ndarray, np.ndarray | None]:
        raise NotImplementedError

    def __add__(self, other: Kernel | float) -> Sum:
        return Sum(self, _as_kernel(other))

    def __radd__(self, other: Kernel | float) -> Kernel:
        if not isinstance(other, Kernel) and other == 0:
            return self  # sum([k1, k2]) starts from 0: add no zero Constant (log 0 = -inf)
        return Sum(_as_kernel(other), self)

    def __mul__(self, other: Kernel | float) -> Product:
        return Product(self, _as_kernel(other))

    def __rmul__(self, other: Kernel | float) -> Product:
        return Product(_as_kernel(other), self)


def _as_kernel(k: Kernel | float) -> Kernel:
    if isinstance(k, Kernel):
        return k
    if np.ndim(k) == 0 and isinstance(np.asarray(k).item(), numbers.Real):
        return Constant(float(k))  # (a number, NumPy's scalars and 0-d arrays too)
    raise InputError(f"a kernel combines with kernels and numbers, not {k!r}")


def _check_positive(name: str, v: object) -> None:
    """InputError unless ``v`` is a positive, finite real number (a string, None or an
    array of several values is named, not left to ``math``'s TypeError)."""
    try:
        ok = math.isfinite(v) and v > 0  # type: ignore[arg-type,operator]  # math: 15x faster
    except TypeError:
        ok = False
    if not ok:
        raise InputError(f"{name} must be a positive and finite number, got {v!r}")


@dataclass(frozen=True, slots=True)
class _Scaled(Kernel):
    """Stationary kernel ``variance * rho(d / length_scale)``: the scale can be profiled."""

    length_scale: float = 1.0
    variance: float = 1.0
    names = ("length_scale", "variance")  # type: ignore[misc]

    def __post_init__(self) -> None:
        for name in ("length_scale", "variance"):
            _check_positive(name, getattr(self, name))
        if self.length_scale * self.length_scale == 0.0:  # d^2 / l^2 would divide by 0
            raise InputError(f"length_scale must be above 1e-154, got {self.length_scale!r}")

    @property
    def theta(self) -> np.ndarray:
        return np.log([self.length_scale, self.variance])

    def with_theta(self, theta: np.ndarray) -> _Scaled:
        l, v = np.exp(np.asarray(theta, dtype=float))
        return replace(self, length_scale=float(l), variance=float(v))

    def unit(self, length_scale: float) -> _Scaled:
        """This kernel at unit variance and the given length scale (fast constructor)."""
        if type(self) in (SquaredExp, Matern32, Matern52):
            return type(self)(length_scale, 1.0)
        return replace(self, length_scale=length_scale, variance=1.0)

    def correlation(self, d: np.ndarray, grad: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """rho (n, n) at unit variance and d rho / d log length_scale (or None)."""
        raise NotImplementedError

    def correlation2(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """rho, d rho / d log l and d^2 rho / d (log l)^2, each (n, n), at unit variance."""
        raise NotImplementedError

    def _eval(self, d: np.ndarray, grad: bool) -> tuple[np.ndarray, np.ndarray | None]:
        rho, drho = self.correlation(d, grad)
        if not grad:  # rho is a new array
            rho *= self.variance
            return rho, None
        K = self.variance * rho
        return K, np.stack([self.variance * drho, K])


@dataclass(frozen=True, slots=True)
class SquaredExp(_Scaled):
    """k(a, b) = variance * exp(-(a - b)^2 / (2 length_scale^2)); the paper's kernel."""

    def correlation(self, d, grad):
        s = np.square(d)
        if not grad:  # one temporary
            s *= -0.5 / (self.length_scale * self.length_scale)
            return np.exp(s, out=s), None
        s *= 1.0 / (self.length_scale * self.length_scale)
        rho = np.multiply(s, -0.5)
        np.exp(rho, out=rho)
        return rho, (np.multiply(rho, s, out=s) if grad else None)

    def correlation2(self, d):
        # s = d^2 / l^2, d s / d log l = -2 s: rho' = rho s, rho'' = rho s (s - 2)
        s = np.square(d)
        s *= 1.0 / (self.length_scale * self.length_scale)
        rho = np.exp(-0.5 * s)
        d1 = rho * s
        return rho, d1, d1 * (s - 2.0)


@dataclass(frozen=True, slots=True)
class Matern32(_Scaled):
    """Matern nu = 3/2: variance * (1 + sqrt3 r) exp(-sqrt3 r), r = |a - b| / length_scale."""

    def correlation(self, d, grad):
        r = np.abs(d) * (_SQRT3 / self.length_scale)
        e = np.exp(-r)
        rho = (1.0 + r) * e
        return rho, (r * r * e if grad else None)

    def correlation2(self, d):
        # d r / d log l = -r: rho' = r^2 e^-r, rho'' = r^2 e^-r (r - 2)
        r = np.abs(d) * (_SQRT3 / self.length_scale)
        e = np.exp(-r)
        d1 = r * r * e
        return (1.0 + r) * e, d1, d1 * (r - 2.0)


@dataclass(frozen=True, slots=True)
class Matern52(_Scaled):
    """Matern nu = 5/2: variance * (1 + sqrt5 r + 5 r^2 / 3) exp(-sqrt5 r)."""

    def correlation(self, d, grad):
        r = np.abs(d) * (_SQRT5 / self.length_scale)
        e = np.exp(-r)
        rho = (1.0 + r + r * r / 3.0) * e
        return rho, ((r * r / 3.0) * (1.0 + r) * e if grad else None)

    def correlation2(self, d):
        # rho' = r^2 (1 + r) e^-r / 3, rho'' = (r^4 - 2 r^3 - 2 r^2) e^-r / 3
        r = np.abs(d) * (_SQRT5 / self.length_scale)
        e = np.exp(-r)
        r2 = r * r
        rho = (1.0 + r + r2 / 3.0) * e
        return rho, r2 * (1.0 + r) * e / 3.0, r2 * (r2 - 2.0 * r - 2.0) * e / 3.0


@dataclass(frozen=True, slots=True)
class Periodic(_Scaled):
    """Exp-sine-squared: variance * exp(-2 sin^2(pi (a - b) / period) / length_scale^2).

    ``period`` is fixed (360 for degrees, 2*pi for radians) and not learned; it must be
    given (a review: a default of 2*pi had fitted data in degrees as if in radians).
    """

    period: float | None = None

    def __post_init__(self) -> None:
        _Scaled.__post_init__(self)
        if self.period is None:
            raise InputError("Periodic: give its period (period=360 for degrees, 2*pi for radians)")
        _check_positive("period", self.period)

    def correlation(self, d, grad):
        s = 2.0 * (np.sin(np.pi * d / self.period) / self.length_scale) ** 2
        rho = np.exp(-s)
        return rho, (2.0 * s * rho if grad else None)

    def correlation2(self, d):
        # d s / d log l = -2 s: rho' = 2 s rho, rho'' = 4 s rho (s - 1)
        s = 2.0 * (np.sin(np.pi * d / self.period) / self.length_scale) ** 2
        rho = np.exp(-s)
        return rho, 2.0 * s * rho, 4.0 * s * rho * (s - 1.0)


@dataclass(frozen=True, slots=True)
class Constant(Kernel):
    """k(a, b) = value: a constant offset of unknown size."""

    value: float = 1.0
    names = ("value",)  # type: ignore[misc]

    def __post_init__(self) -> None:
        _check_positive("value", self.value)

    @property
    def theta(self) -> np.ndarray:
        return np.log([self.value])

    def with_theta(self, theta: np.ndarray) -> Constant:
        return Constant(float(np.exp(theta[0])))

    def _eval(self, d, grad):
        K = np.full(np.shape(d), self.value)
        return K, (K[None] if grad else None)


@dataclass(frozen=True, slots=True)
class _Binary(Kernel):
    left: Kernel
    right: Kernel
    _names: tuple[str, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        names = [f"k1_{n}" for n in self.left.names]
        names += [f"k2_{n}" for n in self.right.names]
        object.__setattr__(self, "_names", tuple(names))

    @property
    def names(self) -> tuple[str, ...]:  # type: ignore[override]
        return self._names

    @property
    def theta(self) -> np.ndarray:
        return np.concatenate([self.left.theta, self.right.theta])

    def with_theta(self, theta):
        p = self.left.n_params
        return type(self)(self.left.with_theta(theta[:p]), self.right.with_theta(theta[p:]))


@dataclass(frozen=True, slots=True)
class Sum(_Binary):
    """k = left + right."""

    def _eval(self, d, grad):
        Ka, dA = self.left._eval(d, grad)
        Kb, dB = self.right._eval(d, grad)
        return Ka + Kb, (np.concatenate([dA, dB]) if grad else None)


@dataclass(frozen=True, slots=True)
class Product(_Binary):
    """k = left * right."""

    def _eval(self, d, grad):
        Ka, dA = self.left._eval(d, grad)
        Kb, dB = self.right._eval(d, grad)
        if not grad:
            return Ka * Kb, None
        return Ka * Kb, np.concatenate([dA * Kb, Ka * dB])


KERNEL_NAMES = ("se", "matern32", "matern52", "periodic")


def _leaves(kernel: Kernel) -> list[Kernel]:
    """The kernels a sum or product is made of, left to right (``[kernel]`` for one)."""
    if isinstance(kernel, _Binary):
        return _leaves(kernel.left) + _leaves(kernel.right)
    return [kernel]


def _has_periodic(kernel: Kernel) -> bool:
    """Whether ``kernel`` is or holds a :class:`Periodic` one."""
    return any(isinstance(k, Periodic) for k in _leaves(kernel))


def common_period(kernel: Kernel) -> float | None:
    """The period of a kernel that repeats whole: periodic kernels of one period, with
    constants, in any sums and products (positions whole periods apart are one position
    to it); None for any other."""
    leaves = _leaves(kernel)
    periods = {k.period for k in leaves if isinstance(k, Periodic)}
    if len(periods) != 1 or not all(isinstance(k, Periodic | Constant) for k in leaves):
        return None
    return float(periods.pop())


def make_kernel(
    name: str | Kernel,
    *,
    length_scale: float = 1.0,
    variance: float = 1.0,
    period: float | None = None,
) -> Kernel:
    """Build a kernel from its short name (``se``, ``matern32``, ``matern52``, ``periodic``).

    A :class:`Kernel` passes through unchanged. ``periodic`` needs ``period``, and only it
    takes one.
    """
    if period is not None and not (isinstance(name, str) and name.lower() == "periodic"):
        if isinstance(name, Kernel) and _has_periodic(name):
            raise InputError(
                f"period: a kernel object carries its own (Periodic(period=...)); give it "
                f"there alone, got period={period!r} beside {name!r}"
            )
        raise InputError(f"period: only the periodic kernel has one, got kernel {name!r}")
    if isinstance(name, Kernel):
        return name
    key = str(name).lower()
    if key in ("se", "rbf", "squared_exp", "squaredexp"):
        return SquaredExp(length_scale, variance)
    if key == "matern32":
        return Matern32(length_scale, variance)
    if key == "matern52":
        return Matern52(length_scale, variance)
    if key == "periodic":
        if period is None:
            raise InputError("the periodic kernel needs a period (e.g. 360 for degrees)")
        _check_positive("period", period)
        return Periodic(length_scale, variance, period=float(period))
    raise InputError(f"unknown kernel {name!r}; expected one of {', '.join(KERNEL_NAMES)}")
