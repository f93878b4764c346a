"""The paper's simulated sensors and designs, checked against independent computations."""

from __future__ import annotations

import numpy as np
import pytest

from cascal import simulation
from cascal.errors import InputError
from cascal.simulation import (
    COEF_VARIANCE,
    FREQ_VARIANCE,
    NOISE_VARIANCE,
    SensorMap,
    cost_j,
    draw_map,
    j_reference,
    reference_positions,
    simulate_trial,
)
from utils import assert_allclose

SD = np.sqrt(NOISE_VARIANCE)


@pytest.fixture(scope="module")
def trial():
    return simulate_trial(np.random.default_rng(123))


def _bisect_inverse(m: SensorMap, r: np.ndarray) -> np.ndarray:
    """Inverse of an increasing map by plain bisection on [0, 1] (independent of Newton)."""
    lo, hi = np.zeros_like(r), np.ones_like(r)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        below = m(mid) < r
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def test_reference_positions():
    p = reference_positions()
    assert p.shape == (64,)
    full = np.linspace(0.0, 1.0, 100)
    assert_allclose(p, full[np.r_[10:42, 58:90]], rtol=0)
    assert p[0] == pytest.approx(10 / 99) and p[-1] == pytest.approx(89 / 99)
    # the gap: 16 of the 80 middle positions are missing, around 0.5
    gaps = np.diff(p)
    assert np.sum(gaps > 1.5 / 99) == 1
    assert gaps.max() == pytest.approx(17 / 99)


def test_trial_shapes_and_redraws(trial):
    assert trial.d2[0].shape == trial.d2[1].shape == (64,)
    assert trial.d1[0].shape == trial.d1[1].shape == (100,)
    assert trial.redraws == 0


def test_d2_readings(trial):
    p = reference_positions()
    e3 = trial.d2[1] - p
    e2 = trial.d2[0] - trial.testbed_map(p)
    for e in (e3, e2):
        # 64 draws of N(0, 1e-8): all within 5 sd, sample sd within 30 % (sd of sd ~ 9 %)
        assert np.max(np.abs(e)) < 5 * SD
        assert 0.7 * SD < np.std(e) < 1.3 * SD
    assert not np.allclose(e3, e2)  # each reading carries its own noise draw


def test_d1_device_readings_equally_spaced(trial):
    dev = trial.device_map
    grid = np.linspace(dev(np.array([0.0]))[0], dev(np.array([1.0]))[0], 100)
    assert trial.device_range == pytest.approx((grid[0], grid[-1]), rel=0, abs=0)
    e1 = trial.d1[0] - grid
    assert np.max(np.abs(e1)) < 5 * SD  # O(1e-4)
    assert 0.7 * SD < np.std(e1) < 1.3 * SD
    # the test-bed reading is taken at the true position of the noise-free device reading
    ys = _bisect_inverse(dev, grid)
    e2 = trial.d1[1] - trial.testbed_map(ys)
    assert np.max(np.abs(e2)) < 5 * SD
    assert 0.7 * SD < np.std(e2) < 1.3 * SD
    assert not np.allclose(e1, e2)


def test_maps_strictly_increasing(trial):
    y = np.linspace(0.0, 1.0, 20001)
    for m in (trial.testbed_map, trial.device_map):
        assert m.is_increasing()
        assert np.all(np.diff(m(y)) > 0)
        assert np.all(m.slope(y) > 0)


def test_slope_is_derivative(trial):
    m = trial.device_map
    y = np.linspace(0.0, 1.0, 51)
    h = 1e-6
    assert_allclose(m.slope(y), (m(y + h) - m(y - h)) / (2 * h), rtol=1e-8)


def test_map_terms_of_different_lengths_are_refused():
    with pytest.raises(InputError, match=r"a, b and w of one shape .*\(3,\), \(2,\)"):
        SensorMap(np.zeros(3), np.zeros(2), np.ones(3))
    with pytest.raises(InputError, match="one shape"):
        SensorMap(np.zeros((2, 2)), np.zeros((2, 2)), np.ones((2, 2)))


def test_the_trials_j_nodes_are_read_only(trial):
    grid, truth = j_reference(trial)
    assert not grid.flags.writeable and not truth.flags.writeable
    fields = ("testbed_map", "device_map", "d2", "d1", "redraws")
    fresh = j_reference(type(trial)(*(getattr(trial, f) for f in fields)))  # (computed)
    assert np.array_equal(fresh[0], grid) and np.array_equal(fresh[1], truth)


def test_map_formula():
    a = np.array([0.01, -0.02])
    b = np.array([0.005, 0.0])
    w = np.array([3.0, -1.5])
    m = SensorMap(a, b, w)
    y = np.array([0.0, 0.25, 1.0])
    expected = y + 0.01 * np.sin(3 * y) - 0.02 * np.sin(-1.5 * y) + 0.005 * np.cos(3 * y)
    assert_allclose(m(y), expected, rtol=1e-15)


def test_inverse_round_trip(trial):
    m = trial.device_map
    y = np.linspace(0.0, 1.0, 1001)
    assert_allclose(m.inverse(m(y)), y, rtol=0, atol=1e-12)
    r = np.linspace(*trial.device_range, 777)
    assert_allclose(m(m.inverse(r)), r, rtol=0, atol=1e-12)
    assert_allclose(m.inverse(r), _bisect_inverse(m, r), rtol=0, atol=1e-12)


def test_on_grid_equals_direct_evaluation(trial):
    for m in (trial.device_map, trial.testbed_map):
        for n, lo, hi in ((2001, 0.0, 1.0), (513, 0.0, 1.0), (7, 0.2, 0.9), (2, 0.0, 1.0)):
            y, v = m.on_grid(n, lo, hi)
            assert_allclose(y, np.linspace(lo, hi, n), rtol=0, atol=0)
            assert_allclose(v, m(y), rtol=0, atol=1e-15)


def test_cost_j_of_truth_is_zero(trial):
    assert cost_j(trial, correct=trial.truth) < 1e-12
    grid, truth = simulation.j_reference(trial)
    assert grid.size >= 2000
    assert_allclose(truth, np.linspace(0.0, 1.0, grid.size), rtol=0, atol=0)
    assert_allclose(grid, trial.device_map(truth), rtol=0, atol=1e-15)
    assert_allclose((grid[0], grid[-1]), trial.device_range, rtol=0, atol=1e-15)
    assert np.all(np.diff(grid) > 0)
    assert_allclose(truth, _bisect_inverse(trial.device_map, grid), rtol=0, atol=1e-12)
    assert cost_j(trial, corrected=truth) < 1e-12
    assert cost_j(trial, corrected=grid, reference=(grid, truth)) == cost_j(trial, corrected=grid)


def _rms_by_quadrature(trial, correct) -> float:
    """J by adaptive quadrature over true positions (y1 = g(y*), dy1 = g'(y*) dy*)."""
    from scipy.integrate import quad

    m = trial.device_map
    lo, hi = trial.device_range

    def f(y: float) -> float:
        r = m(np.array([y]))
        return float((correct(r)[0] - y) ** 2 * m.slope(np.array([y]))[0])

    val, _ = quad(f, 0.0, 1.0, limit=500, epsabs=1e-16, epsrel=1e-12)
    return float(np.sqrt(val / (hi - lo)))


def test_cost_j_of_identity(trial):
    rms = _rms_by_quadrature(trial, lambda r: r)
    assert rms > 1e-3  # the uncorrected device is visibly wrong
    # the trapezoid rule on 2001 nodes is exact to O(h^2): 4e-7 relative here
    assert cost_j(trial, correct=lambda r: r) == pytest.approx(rms, rel=2e-6)
    grid, _ = simulation.j_reference(trial)
    assert cost_j(trial, corrected=grid) == pytest.approx(rms, rel=2e-6)
    # a constant error of 1e-4 gives J = 1e-4
    assert cost_j(trial, correct=lambda r: trial.truth(r) + 1e-4) == pytest.approx(1e-4, rel=1e-9)
    # a smooth estimate: J against the quadrature of the same integral
    smooth = lambda r: trial.truth(r) + 1e-4 * np.sin(7.0 * r)  # noqa: E731
    expected = _rms_by_quadrature(trial, smooth)
    assert cost_j(trial, correct=smooth) == pytest.approx(expected, rel=2e-6)


def test_not_increasing_map_detected():
    z = np.zeros(9)
    huge = SensorMap(np.r_[0.5, z], np.r_[0.0, z], np.r_[10.0, z])  # slope 1 + 5 cos(10 y)
    assert not huge.is_increasing()
    # a narrow dip: slope 1 + 1.01 cos(10 y) < 0 only for |10 y - pi| < 0.14
    dip = SensorMap(np.r_[0.101, z], np.r_[0.0, z], np.r_[10.0, z])
    assert not dip.is_increasing()
    # B1 = sum |w| hypot(a, b) = 1.2 >= 1 but the true amplitude 0.6 sqrt(2) < 1: increasing
    ok = SensorMap(np.r_[0.06, 0.0, z[:8]], np.r_[0.0, 0.06, z[:8]], np.r_[10.0, 10.0, z[:8]])
    assert np.min(ok.slope(np.linspace(0, 1, 10001))) == pytest.approx(
        1 - 0.6 * np.sqrt(2), abs=1e-4
    )
    assert ok.is_increasing()


def test_redraws_counted(monkeypatch):
    z = np.zeros(9)
    bad = SensorMap(np.r_[0.5, z], np.r_[0.0, z], np.r_[10.0, z])
    good = SensorMap(np.full(10, 1e-3), np.zeros(10), np.linspace(-3, 3, 10))
    queue = [bad, good, good, bad, good, good]
    monkeypatch.setattr(simulation, "draw_map", lambda rng: queue.pop(0))
    t = simulate_trial(np.random.default_rng(0))
    assert t.redraws == 2
    assert t.testbed_map is good and t.device_map is good
    assert queue == []


def test_draw_map_variances():
    g = np.random.default_rng(99)
    maps = [draw_map(g) for _ in range(2000)]
    a = np.concatenate([m.a for m in maps])
    b = np.concatenate([m.b for m in maps])
    w = np.concatenate([m.w for m in maps])
    assert a.shape == (20000,)
    # 20000 draws: the sample variance is within 5 % (its relative sd is sqrt(2/20000) = 1 %)
    assert np.var(a) == pytest.approx(COEF_VARIANCE, rel=0.05)
    assert np.var(b) == pytest.approx(COEF_VARIANCE, rel=0.05)
    assert np.var(w) == pytest.approx(FREQ_VARIANCE, rel=0.05)  # a VARIANCE of 6, not an sd
    assert abs(np.mean(w)) < 5 * np.sqrt(FREQ_VARIANCE / 20000)


def test_simulation_deterministic():
    a = simulate_trial(np.random.default_rng(5))
    b = simulate_trial(np.random.default_rng(5))
    c = simulate_trial(np.random.default_rng(6))
    for u, v in zip((*a.d1, *a.d2), (*b.d1, *b.d2), strict=True):
        assert np.array_equal(u, v)
    assert not np.array_equal(a.d1[0], c.d1[0])


def test_value_and_slope_equal_separate_evaluations(trial):
    y = np.linspace(0.0, 1.0, 2001)  # several blocks
    value, slope = trial.device_map.value_and_slope(y)
    np.testing.assert_array_equal(value, trial.device_map(y))
    np.testing.assert_array_equal(slope, trial.device_map.slope(y))
