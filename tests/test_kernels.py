"""Kernels against hand-written formulas, finite-difference gradients, PSD-ness and algebra."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cascal import kernels
from cascal.kernels import (
    Constant,
    Matern32,
    Matern52,
    Periodic,
    Product,
    SquaredExp,
    Sum,
    make_kernel,
)
from utils import assert_allclose, fd_gradient


def _d(a, b):
    return np.asarray(a)[:, None] - np.asarray(b)[None, :]


def f_se(a, b, l, v):
    return v * np.exp(-(_d(a, b) ** 2) / (2 * l**2))


def f_m32(a, b, l, v):
    t = np.sqrt(3.0) * np.abs(_d(a, b)) / l
    return v * (1 + t) * np.exp(-t)


def f_m52(a, b, l, v):
    d = np.abs(_d(a, b))
    return v * (1 + np.sqrt(5.0) * d / l + 5 * d**2 / (3 * l**2)) * np.exp(-np.sqrt(5.0) * d / l)


def f_per(a, b, l, v, p):
    return v * np.exp(-2 * np.sin(np.pi * _d(a, b) / p) ** 2 / l**2)


def f_const(a, b, c):
    return np.full((len(a), len(b)), c)


# (kernel, hand formula, positions a, positions b); the positions fit the kernel's scale.
_X = np.linspace(0.0, 1.0, 13) ** 1.3
_Y = np.array([-0.2, 0.05, 0.5, 0.77, 1.4])
_DEG = np.array([0.0, 10.0, 45.0, 170.0, 200.0, 359.0, 361.0, 725.0])
_RAD = np.array([0.0, 0.3, 1.0, 3.0, 6.0, 6.5, 12.0])

CASES = {
    "se": (SquaredExp(0.23, 1.7), lambda a, b: f_se(a, b, 0.23, 1.7), _X, _Y),
    "matern32": (Matern32(0.31, 0.4), lambda a, b: f_m32(a, b, 0.31, 0.4), _X, _Y),
    "matern52": (Matern52(0.17, 2.5), lambda a, b: f_m52(a, b, 0.17, 2.5), _X, _Y),
    "periodic360": (
        Periodic(0.8, 3e-3, period=360.0),
        lambda a, b: f_per(a, b, 0.8, 3e-3, 360.0),
        _DEG,
        _DEG[::-2] + 7.0,
    ),
    "periodic2pi": (
        Periodic(1.3, 0.5, period=2 * np.pi),
        lambda a, b: f_per(a, b, 1.3, 0.5, 2 * np.pi),
        _RAD,
        _RAD + 0.1,
    ),
    "constant": (Constant(0.7), lambda a, b: f_const(a, b, 0.7), _X, _Y),
    "sum": (
        SquaredExp(0.23, 1.7) + Matern32(0.5, 0.2),
        lambda a, b: f_se(a, b, 0.23, 1.7) + f_m32(a, b, 0.5, 0.2),
        _X,
        _Y,
    ),
    "product": (
        Matern52(0.4, 1.1) * Periodic(0.9, 2.0, period=0.5),
        lambda a, b: f_m52(a, b, 0.4, 1.1) * f_per(a, b, 0.9, 2.0, 0.5),
        _X,
        _Y,
    ),
    "number_times": (
        2.5 * SquaredExp(0.3, 0.6),
        lambda a, b: 2.5 * f_se(a, b, 0.3, 0.6),
        _X,
        _Y,
    ),
    "kernel_plus_number": (
        SquaredExp(0.3, 0.6) + 0.25,
        lambda a, b: f_se(a, b, 0.3, 0.6) + 0.25,
        _X,
        _Y,
    ),
}


@pytest.fixture(params=sorted(CASES))
def case(request):
    return CASES[request.param]


def test_matrix_against_formula(case):
    k, f, a, b = case
    assert_allclose(k(a, b), f(a, b), rtol=1e-13, atol=1e-300)
    assert_allclose(k(a), f(a, a), rtol=1e-13, atol=1e-300)
    assert k(a, b).shape == (len(a), len(b))


def test_diag_is_diagonal_of_matrix(case):
    k, f, a, _ = case
    assert_allclose(k.diag(a), np.diagonal(f(a, a)), rtol=1e-14)


def test_gradient_returns_matrix_and_matches_finite_differences(case):
    k, f, a, _ = case
    K, dK = k.gradient(a)
    assert dK.shape == (k.n_params, len(a), len(a))
    assert_allclose(K, f(a, a), rtol=1e-13, atol=1e-300)
    theta = k.theta
    h = 1e-5
    for j in range(k.n_params):
        e = np.zeros_like(theta)
        e[j] = h
        fd = (k.with_theta(theta + e)(a) - k.with_theta(theta - e)(a)) / (2 * h)
        scale = np.max(np.abs(dK[j])) + np.max(np.abs(K)) * 1e-3
        # central differences: error O(h^2) ~ 1e-10 relative; round-off ~ eps / h ~ 1e-11.
        np.testing.assert_allclose(dK[j], fd, rtol=1e-6, atol=1e-7 * scale)


def test_matrix_is_symmetric_positive_semidefinite(case):
    k, _, a, _ = case
    K = k(np.r_[a, a[:3] + 1e-3])
    assert_allclose(K, K.T, rtol=0, atol=0)
    w = np.linalg.eigvalsh(K)
    assert w.min() >= -1e-10 * w.max()


def test_theta_round_trip(case):
    k, _, a, _ = case
    theta = k.theta
    assert theta.shape == (k.n_params,) == (len(k.names),)
    k2 = k.with_theta(theta)
    assert type(k2) is type(k)
    assert_allclose(k2.theta, theta, rtol=1e-15, atol=1e-15)
    assert_allclose(k2(a), k(a), rtol=1e-14)
    new = theta + np.linspace(-0.5, 0.7, theta.size)
    k3 = k.with_theta(new)
    assert_allclose(k3.theta, new, rtol=1e-14, atol=1e-14)
    assert_allclose(np.log(list(k3.params.values())), new, rtol=1e-14, atol=1e-14)
    assert k.theta is not k3.theta
    assert_allclose(k.theta, theta, rtol=0)  # the original is unchanged


def test_params_are_natural_units():
    k = SquaredExp(0.23, 1.7)
    assert k.params == pytest.approx({"length_scale": 0.23, "variance": 1.7}, rel=1e-15)
    assert_allclose(k.theta, np.log([0.23, 1.7]), rtol=1e-15)
    p = Periodic(0.8, 3e-3, period=360.0)
    assert p.with_theta(np.log([2.0, 5.0])).period == 360.0
    s = SquaredExp(0.1, 2.0) + Matern32(0.3, 4.0)
    assert s.names == ("k1_length_scale", "k1_variance", "k2_length_scale", "k2_variance")
    assert_allclose(s.theta, np.log([0.1, 2.0, 0.3, 4.0]), rtol=1e-15)
    pr = 3.0 * SquaredExp(0.1, 2.0)
    assert isinstance(pr, Product) and isinstance(pr.left, Constant)
    assert pr.names == ("k1_value", "k2_length_scale", "k2_variance")


@pytest.mark.parametrize(
    ("kernel", "attr"),
    [
        (SquaredExp(0.2, 1.0), "length_scale"),
        (Matern32(0.2, 1.0), "variance"),
        (Periodic(0.2, 1.0, period=360.0), "period"),
        (Constant(1.0), "value"),
        (SquaredExp(0.2, 1.0) + Constant(1.0), "left"),
    ],
)
def test_frozen(kernel, attr):
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(kernel, attr, 2.0)


def test_composition_types():
    a, b = SquaredExp(0.2, 1.0), Matern52(0.3, 2.0)
    assert isinstance(a + b, Sum)
    assert isinstance(a * b, Product)
    assert isinstance(2.0 + a, Sum) and (2.0 + a).left == Constant(2.0)
    assert isinstance(a * 2.0, Product) and (a * 2.0).right == Constant(2.0)
    x = np.linspace(0, 1, 7)
    assert_allclose((a + b)(x), a(x) + b(x), rtol=1e-15)
    assert_allclose((a * b)(x), a(x) * b(x), rtol=1e-15)


def test_builtin_sum_of_kernels():
    a, b, c = SquaredExp(0.2, 1.0), Matern52(0.3, 2.0), Constant(0.5)
    x = np.linspace(0, 1, 7)
    total = sum([a, b, c])
    assert_allclose(total(x), a(x) + b(x) + c(x), rtol=1e-15)
    # sum() starts from 0: no zero-valued Constant (theta = -inf) may enter the kernel.
    assert np.all(np.isfinite(total.theta))
    assert_allclose(total.theta, np.r_[a.theta, b.theta, c.theta], rtol=0)


@pytest.mark.parametrize(
    ("name", "cls"),
    [
        ("se", SquaredExp),
        ("SE", SquaredExp),
        ("rbf", SquaredExp),
        ("squared_exp", SquaredExp),
        ("matern32", Matern32),
        ("Matern52", Matern52),
    ],
)
def test_make_kernel_names(name, cls):
    k = make_kernel(name, length_scale=0.3, variance=2.0)
    assert type(k) is cls
    assert k.params == pytest.approx({"length_scale": 0.3, "variance": 2.0}, rel=1e-15)


def test_make_kernel_periodic_and_passthrough():
    k = make_kernel("periodic", length_scale=0.5, variance=1.5, period=360)
    assert type(k) is Periodic and k.period == 360.0
    assert (k.length_scale, k.variance) == (0.5, 1.5)
    given = Matern32(0.1, 0.2)
    assert make_kernel(given) is given
    assert set(kernels.KERNEL_NAMES) == {"se", "matern32", "matern52", "periodic"}


def test_make_kernel_errors():
    with pytest.raises(ValueError, match="period"):
        make_kernel("periodic")
    with pytest.raises(ValueError, match=r"unknown kernel 'cubic'.*se, matern32"):
        make_kernel("cubic")


@pytest.mark.parametrize(
    "build",
    [
        lambda: SquaredExp(0.0, 1.0),
        lambda: SquaredExp(-1.0, 1.0),
        lambda: Matern32(1.0, np.nan),
        lambda: Matern52(np.inf, 1.0),
        lambda: Periodic(1.0, 1.0, period=0.0),
        lambda: Periodic(1.0, 1.0, period=-360.0),
        lambda: Constant(0.0),
        lambda: Constant(-2.0),
    ],
)
def test_invalid_hyperparameters_refused(build):
    with pytest.raises(ValueError, match="positive and finite number, got"):
        build()


def test_periodic_is_periodic():
    k = Periodic(0.7, 2.0, period=360.0)
    x = np.array([3.0, 50.0, 181.0])
    assert_allclose(k(x, x + 360.0), k(x, x), rtol=1e-12)
    assert_allclose(k(x, x + 720.0), k(x), rtol=1e-12)
    r = Periodic(0.7, 2.0, period=2 * np.pi)
    assert_allclose(r(x, x + 2 * np.pi), r(x), rtol=1e-12)
    # gradient with respect to log length scale: 2 s rho with s = 2 sin^2 / l^2
    K, dK = k.gradient(x)
    s = 2 * np.sin(np.pi * (x[:, None] - x[None, :]) / 360.0) ** 2 / 0.7**2
    assert_allclose(dK[0], 2.0 * 2.0 * s * np.exp(-s), rtol=1e-13, atol=1e-300)
    assert_allclose(dK[1], K, rtol=1e-15)


def test_fd_helper_on_kernel_entry():
    # One entry of the Matern 3/2 matrix as a function of log-theta, through the helper.
    k = Matern32(0.3, 0.8)
    a, b = 0.1, 0.45

    def entry(t):
        return float(k.with_theta(t)(np.array([a]), np.array([b]))[0, 0])

    _, dK = k.gradient(np.array([a, b]))
    assert_allclose(fd_gradient(entry, k.theta), dK[:, 0, 1], rtol=1e-7)


@pytest.mark.parametrize("cls", [SquaredExp, Matern32, Matern52])
def test_a_length_scale_whose_square_underflows_is_refused(cls):
    # (a review's case: 1e-300 from the user's hyperparameters gave a ZeroDivisionError)
    with pytest.raises(ValueError, match="length_scale must be above 1e-154, got 1e-300"):
        cls(1e-300, 1.0)
    assert cls(1e-150, 1.0)(np.array([0.0]), np.array([0.0]))[0, 0] == 1.0


def test_common_period_of_kernels_that_repeat_whole():
    from cascal.kernels import Constant, Periodic, common_period

    p = Periodic(period=360.0)
    assert common_period(p) == 360.0
    assert common_period(p + Constant(1.0)) == 360.0
    assert common_period(Constant(2.0) * (p + Periodic(0.5, 1.0, period=360.0))) == 360.0
    assert common_period(p + Periodic(period=180.0)) is None  # two periods
    assert common_period(p + SquaredExp()) is None  # the SE part does not repeat
    assert common_period(SquaredExp()) is None and common_period(Constant(1.0)) is None
