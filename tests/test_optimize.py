"""Multi-start maximisation: Newton steps and L-BFGS-B reach the same optima."""

from __future__ import annotations

import numpy as np
import pytest

from cascal.kernels import Matern52, SquaredExp
from cascal.likelihood import Objective
from cascal.noise import Dense
from cascal.optimize import _ascent_step, latin_hypercube, maximize, newton_maximize


def quadratic(center, A):
    def vgh(t):
        d = t - center
        return -0.5 * float(d @ A @ d), -(A @ d), -A

    return vgh


def test_newton_finds_interior_maximum_of_a_quadratic():
    A = np.array([[3.0, 1.0], [1.0, 2.0]])
    c = np.array([0.3, -0.7])
    bounds = np.array([[-5.0, 5.0], [-5.0, 5.0]])
    s = newton_maximize(quadratic(c, A), np.array([4.0, 4.0]), bounds)
    assert s.converged
    np.testing.assert_allclose(s.theta, c, atol=1e-10)
    assert s.n_evals <= 6  # a quadratic takes one full Newton step once inside the radius


def test_newton_stops_at_an_active_bound():
    A = np.eye(2)
    c = np.array([2.0, 0.5])
    bounds = np.array([[-1.0, 1.0], [-1.0, 1.0]])
    s = newton_maximize(quadratic(c, A), np.zeros(2), bounds)
    np.testing.assert_allclose(s.theta, [1.0, 0.5], atol=1e-9)


def test_newton_escapes_a_saddle_region():
    # f = -(x^2 - 1)^2 - y^2 has maxima at x = +-1; x = 0 is a local minimum in x.
    def vgh(t):
        x, y = t
        f = -((x * x - 1) ** 2) - y * y
        g = np.array([-4 * x * (x * x - 1), -2 * y])
        H = np.array([[-12 * x * x + 4, 0.0], [0.0, -2.0]])
        return f, g, H

    s = newton_maximize(vgh, np.array([0.05, 1.0]), np.array([[-3.0, 3.0], [-3.0, 3.0]]))
    # stops once the Newton decrement promises < 2e-10 gain: |x - 1| ~ sqrt(2e-10 / 8)
    assert s.value > -2e-10
    np.testing.assert_allclose(np.abs(s.theta), [1.0, 0.0], atol=2e-5)


def _counted(vgh):
    """``vgh`` staged as ``(f, derivatives)``, and a dict counting values and derivatives."""
    calls = {"value": 0, "derivatives": 0}

    def staged(t):
        calls["value"] += 1
        f, g, H = vgh(t)

        def derivatives():
            calls["derivatives"] += 1
            return g, H

        return f, derivatives

    return staged, calls


def test_deferred_derivatives_give_the_same_run_and_are_skipped_on_rejected_steps():
    # A concave function whose quadratic model overshoots far from the top: some trust-region
    # steps are rejected, and only accepted points may pay for gradient and Hessian.
    def vgh(t):
        u = t - np.array([0.4, -0.2])
        w = 1.0 + u @ u
        f = -np.log(w) - 0.1 * float(u @ u)
        g = -2.0 * u / w - 0.2 * u
        H = -2.0 * np.eye(2) / w + 4.0 * np.outer(u, u) / w**2 - 0.2 * np.eye(2)
        return f, g, H

    staged, calls = _counted(vgh)
    bounds = np.array([[-20.0, 20.0], [-20.0, 20.0]])
    eager = newton_maximize(vgh, np.array([15.0, -12.0]), bounds)
    lazy = newton_maximize(staged, np.array([15.0, -12.0]), bounds)
    np.testing.assert_array_equal(lazy.theta, eager.theta)
    assert lazy.value == eager.value and lazy.n_evals == eager.n_evals == calls["value"]
    np.testing.assert_allclose(lazy.theta, [0.4, -0.2], atol=1e-6)
    assert calls["derivatives"] < calls["value"]  # at least one step was rejected


def test_last_full_step_is_taken_on_its_value_alone():
    # Near the top a full Newton step squares the decrement: the run ends at the point it
    # steps to, paying for its value but not its derivatives, and that point is the top
    # to well within the tolerance.
    top = np.array([0.4, -0.2])

    def vgh(t):
        u = t - top
        w = 1.0 + u @ u
        f = -np.log(w) - 0.1 * float(u @ u) - 0.05 * u[0] ** 3
        g = -2.0 * u / w - 0.2 * u - np.array([0.15 * u[0] ** 2, 0.0])
        H = -2.0 * np.eye(2) / w + 4.0 * np.outer(u, u) / w**2 - 0.2 * np.eye(2)
        H[0, 0] -= 0.3 * u[0]
        return f, g, H

    staged, calls = _counted(vgh)
    bounds = np.array([[-5.0, 5.0], [-5.0, 5.0]])
    s = newton_maximize(staged, top + np.array([0.05, 0.02]), bounds)
    assert s.converged and s.n_evals == calls["value"]
    assert calls["derivatives"] == calls["value"] - 1
    _, g, H = vgh(s.theta)
    assert float(g @ np.linalg.solve(-H, g)) < 2e-11  # the decrement at the end
    np.testing.assert_allclose(s.theta, top, atol=1e-6)
    assert s.value == vgh(s.theta)[0]


def test_objective_value_and_derivatives_match_value_grad_hess():
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0, 1, 30))
    r = 0.01 * np.sin(6 * x) + 1e-4 * rng.standard_normal(30)
    for obj, theta in (
        (Objective(x, r, SquaredExp(), None, True, profile=True), np.array([-1.5, -6.0])),
        (
            Objective(x, r, SquaredExp(), Dense(1e-8 * np.eye(30)), True),
            np.array([-1.5, -9.0, -15.0]),
        ),
    ):
        f, derivatives = obj.value_and_derivatives(theta)
        g, H = derivatives()
        f2, g2, H2 = obj.value_grad_hess(theta)
        assert f == f2 == obj.value(theta)
        np.testing.assert_array_equal(g, g2)
        np.testing.assert_array_equal(H, H2)


def test_latin_hypercube_is_stratified():
    rng = np.random.default_rng(0)
    b = np.array([[0.0, 1.0], [-2.0, 2.0]])
    pts = latin_hypercube(b, 10, rng)
    assert pts.shape == (10, 2)
    for k in range(2):
        u = (pts[:, k] - b[k, 0]) / (b[k, 1] - b[k, 0])
        assert sorted(np.floor(u * 10).astype(int)) == list(range(10))


@pytest.mark.parametrize("kernel", [SquaredExp(), Matern52()])
@pytest.mark.parametrize("profile", [True, False])
def test_newton_and_lbfgsb_reach_the_same_optimum(kernel, profile):
    rng = np.random.default_rng(3)
    x = np.sort(rng.uniform(0, 1, 40))
    y = x + 0.01 * np.sin(9 * x) + 1e-3 * rng.standard_normal(40)
    known = None
    if not profile:
        B = 1e-3 * rng.standard_normal((40, 4))
        known = Dense(B @ B.T)
    obj = Objective(x, y - x, kernel, known, True, profile=profile)
    b = obj.bounds()
    newton = maximize(
        obj.value,
        obj.value_and_grad,
        b,
        n_restarts=5,
        rng=np.random.default_rng(0),
        value_grad_hess=obj.value_grad_hess,
    )
    lbfgs = maximize(obj.value, obj.value_and_grad, b, n_restarts=5, rng=np.random.default_rng(0))
    assert newton.value >= lbfgs.value - 1e-6
    assert all(s.converged for s in newton.starts)
    best = max(newton.starts, key=lambda s: s.value)
    np.testing.assert_array_equal(best.theta, newton.theta)


@pytest.mark.parametrize(
    "H",
    [
        [[-3.0, 1.0, 0.2], [1.0, -2.0, 0.1], [0.2, 0.1, -0.5]],  # negative definite: Cholesky
        [[2.0, 0.5], [0.5, -1.0]],  # indefinite: eigenvalue magnitudes
        [[-1.0, 0.0], [0.0, -1e-12]],  # nearly singular: floored magnitudes
    ],
)
def test_ascent_step_matches_eigenvalue_magnitude_step(H):
    H = np.array(H)
    g = np.linspace(0.3, -0.7, len(H))
    step, decrement = _ascent_step(H.tolist(), g.tolist())
    lam, V = np.linalg.eigh(H)
    mag = np.maximum(np.abs(lam), 1e-8 * np.max(np.abs(lam)))
    ref = V @ ((V.T @ g) / mag)
    np.testing.assert_allclose(step, ref, rtol=1e-12)
    if np.all(lam < -1e-8 * np.max(np.abs(lam))):
        assert decrement == pytest.approx(float(g @ ref), rel=1e-12)
    else:
        assert decrement is None


def _twin_peaks(t):
    """Two bumps in x, at 0 (height 1) and at 0.2 (height 1.05), with a dip between; -y^2."""
    x, y = t
    f, g, h = -y * y, 0.0, 0.0
    for c, a in ((0.0, 1.0), (0.2, 1.05)):
        u = (x - c) / 0.06
        e = a * np.exp(-0.5 * u * u)
        f += e
        g += -e * u / 0.06
        h += e * (u * u - 1.0) / 0.0036
    return f, np.array([g, -2.0 * y]), np.array([[h, 0.0], [0.0, -2.0]])


def test_probes_find_a_nearby_higher_maximum_the_start_missed():
    bounds = np.array([[-1.0, 1.0], [-1.0, 1.0]])
    value = lambda t: _twin_peaks(t)[0]  # noqa: E731
    vg = lambda t: _twin_peaks(t)[:2]  # noqa: E731
    kw = dict(rng=None, value_grad_hess=_twin_peaks, starts=[np.array([-0.05, 0.3])])
    plain = maximize(value, vg, bounds, **kw)
    assert abs(plain.theta[0]) < 0.02 and len(plain.starts) == 1  # the lower bump
    step = np.array([0.2, 0.0])
    probed = maximize(value, vg, bounds, probes=[-step, step], **kw)
    assert len(probed.starts) == 2
    assert abs(probed.theta[0] - 0.2) < 0.02 and probed.value > plain.value + 0.04
    # from the higher bump, neither probe is higher: no run is added
    again = maximize(value, vg, bounds, **{**kw, "starts": [probed.theta]}, probes=[-step, step])
    assert len(again.starts) == 1 and again.value == pytest.approx(probed.value, abs=1e-12)
