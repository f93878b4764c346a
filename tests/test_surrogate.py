"""Start points from likelihood tables: exact on a grid and off it, never a worse fit."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy import ndimage

from cascal import surrogate
from cascal.gp import fit_gp
from cascal.kernels import Matern32, Matern52, Periodic, SquaredExp
from cascal.likelihood import Objective
from cascal.noise import Dense, NoiseSum
from cascal.optimize import maximize
from utils import dense_lml, se

N = 48


def grid_data(jitter: float, seed: int = 0, n: int = N):
    """Readings on [0.2, 1.2] off an equally spaced grid by ``jitter`` spacings (rms), and
    residuals of a smooth map plus noise."""
    rng = np.random.default_rng(seed)
    h = 1.0 / (n - 1)
    x = 0.2 + h * np.arange(n) + jitter * h * rng.standard_normal(n)
    r = 0.01 * np.sin(6.0 * x + 1.0) + 0.004 * np.cos(17.0 * x) + 1e-4 * rng.standard_normal(n)
    return x, r


def stage_a_covariance(x: np.ndarray) -> np.ndarray:
    """Posterior covariance at ``x`` of a GP on 20 points with a gap: low rank, dense."""
    t = np.r_[np.linspace(0.2, 0.55, 10), np.linspace(0.85, 1.2, 10)]
    K = se(t, t, 0.15, 1e-4) + 1e-8 * np.eye(t.size)
    Ks = se(x, t, 0.15, 1e-4)
    C = se(x, x, 0.15, 1e-4) - Ks @ np.linalg.solve(K, Ks.T)
    return 0.5 * (C + C.T)


def test_grid_spacing_accepts_near_grids_in_any_order_and_refuses_others():
    x, _ = grid_data(0.01)
    h = 1.0 / (N - 1)
    assert surrogate.grid_spacing(x) == pytest.approx(h, rel=1e-3)
    assert surrogate.grid_spacing(x[::-1].copy()) == pytest.approx(h, rel=1e-3)
    assert surrogate.grid_spacing(np.sort(np.random.default_rng(1).random(N))) is None
    assert surrogate.grid_spacing(np.array([0.0, 1.0])) is None
    assert surrogate.grid_spacing(np.arange(surrogate.MAX_POINTS + 1.0)) is None


@pytest.mark.parametrize("kernel", [SquaredExp(), Matern32()])
def test_table_is_the_exact_profiled_likelihood_on_a_grid(kernel):
    x, r = grid_data(0.0)
    rng = np.random.default_rng(3)
    perm = rng.permutation(N)  # the table does not depend on the order of the points
    xp, rp = x[perm], r[perm]
    obj = Objective(xp, rp, kernel, None, True, profile=True)
    scan = surrogate._scan(kernel, xp, rp, np.array([-np.inf, np.inf]))
    const = 0.5 * N * (np.log(N) - 1.0 - np.log(2 * np.pi))
    h = 1.0 / (N - 1)
    for i, j in [(20, 30), (30, 20), (35, 25), (40, 35), (25, 44)]:
        theta = np.array([np.log(surrogate.RATIOS[i] * h), np.log(surrogate.GAINS[j])])
        assert scan.table[i, j] + const == pytest.approx(obj.value(theta), abs=1e-7)


@pytest.mark.parametrize("white", [True, False])
def test_dense_table_is_the_exact_likelihood_on_a_grid(white):
    # On an exact grid the Woodbury table is the log marginal likelihood with U U^T as the
    # known noise: for white noise (U = sqrt(c) I, full rank) and a low-rank stage-A factor.
    x, r = grid_data(0.0)
    U = np.sqrt(3e-8) * np.eye(N) if white else Dense(stage_a_covariance(x), atol=1e-12).factor(N)
    scan = surrogate._scan(SquaredExp(), x, r, np.array([-np.inf, np.inf]))
    table, ll, signal, noise = surrogate._dense_table(scan, U)
    checked = 0
    for a, b, k in [(0, 3, 3), (2, 1, 5), (len(ll) - 1, 6, 0), (len(ll) // 2, 4, 2), (4, 5, 6)]:
        sf2, ls, sn2 = np.exp(signal[a, b]), np.exp(ll[a]), np.exp(noise[a, k])
        Kt = se(x, x, ls, sf2) + U @ U.T + sn2 * np.eye(N)
        if np.linalg.cond(Kt) > 1e9:  # both formulas are then only good to round-off
            continue
        expected = dense_lml(r, Kt) + 0.5 * N * np.log(2 * np.pi)
        assert table[a, b, k] == pytest.approx(expected, abs=1e-6)
        checked += 1
    assert checked >= 3


def test_dense_table_rows_reach_further_towards_longer_length_scales():
    x, r = grid_data(0.0)
    scan = surrogate._scan(SquaredExp(), x, r, np.array([-np.inf, np.inf]))
    _, ll, _, _ = surrogate._dense_table(scan, np.zeros((N, 0)))
    prof = scan.table.max(axis=1)  # the profiled rows, known noise ignored
    all_ll = np.log(surrogate.RATIOS * scan.h)
    best = int(np.argmax(prof))
    first, last = np.searchsorted(all_ll, ll[0]), np.searchsorted(all_ll, ll[-1])
    assert np.allclose(ll, all_ll[first : last + 1])
    assert first < best < last
    assert prof[first] >= prof[best] - surrogate._ROWS_SHORT > prof[first - 1]
    assert prof[last] >= prof[best] - surrogate._ROWS
    assert last == all_ll.size - 1 or prof[last + 1] < prof[best] - surrogate._ROWS
    assert prof[best] - prof[last] > surrogate._ROWS_SHORT  # wider on the long side


def test_dense_table_without_known_noise_is_the_plain_likelihood():
    x, r = grid_data(0.0)
    scan = surrogate._scan(SquaredExp(), x, r, np.array([-np.inf, np.inf]))
    table, ll, signal, noise = surrogate._dense_table(scan, np.zeros((N, 0)))
    Kt = se(x, x, np.exp(ll[1]), np.exp(signal[1, 2])) + np.exp(noise[1, 3]) * np.eye(N)
    assert table[1, 2, 3] == pytest.approx(dense_lml(r, Kt) + 0.5 * N * np.log(2 * np.pi))


def test_dense_factor_reproduces_the_covariance():
    x, _ = grid_data(0.01)
    C = stage_a_covariance(x)
    noise = Dense(C, atol=1e-12)
    U = noise.factor(N)
    assert U.shape[1] <= 16
    lam_max = np.linalg.eigvalsh(C)[-1]
    assert np.linalg.norm(U @ U.T - noise.cov, 2) <= 1e-4 * lam_max
    # the base-class factor (an eigendecomposition of the dense matrix) agrees
    V = NoiseSum((noise,)).factor(N)
    np.testing.assert_allclose(V @ V.T, U @ U.T, atol=1e-12 * lam_max)


def thorough(obj: Objective) -> float:
    """Best of 12 Newton starts from 96 screened candidates: an independent reference."""
    b = obj.bounds()
    res = maximize(
        obj.value,
        obj.value_and_grad,
        b,
        n_restarts=12,
        n_candidates=96,
        rng=np.random.default_rng(7),
        value_grad_hess=obj.value_grad_hess,
    )
    return res.value


@pytest.mark.parametrize("seed", range(4))
def test_fit_from_surrogate_starts_is_as_good_as_a_thorough_search(seed):
    x, r = grid_data(0.02, seed)
    gp = fit_gp(x, x + r, n_restarts=3, seed=seed)
    assert gp.optimization.n_candidates == 0  # the surrogate chose the starts
    obj = Objective(x, r, SquaredExp(), None, True, profile=True)
    assert gp.log_marginal_likelihood >= thorough(obj) - 1e-6


@pytest.mark.parametrize("seed", range(4))
def test_dense_noise_fit_from_surrogate_starts_is_as_good_as_a_thorough_search(seed):
    x, r = grid_data(0.02, seed)
    noise = Dense(stage_a_covariance(x), atol=1e-12)
    gp = fit_gp(x, x + r, noise=noise, n_restarts=3, seed=seed)
    assert gp.optimization.n_candidates == 0
    obj = Objective(x, r, SquaredExp(), noise, True)
    assert gp.log_marginal_likelihood >= thorough(obj) - 1e-6


def scattered_data(seed: int, n: int = N):
    """Readings at random positions with a gap in the middle (like the paper's D2), in
    random order, and residuals of a smooth map plus noise."""
    rng = np.random.default_rng(seed)
    x = np.r_[rng.uniform(0.0, 0.4, n // 2), rng.uniform(0.6, 1.0, n - n // 2)]
    r = 0.01 * np.sin(6.0 * x + 1.0) + 0.004 * np.cos(17.0 * x) + 1e-4 * rng.standard_normal(n)
    return x, r


@pytest.mark.parametrize(
    "kernel", [SquaredExp(), Matern32(), Matern52(), Periodic(period=0.7), Periodic(period=3.0)]
)
def test_offgrid_table_is_the_exact_profiled_likelihood(kernel):
    x, r = scattered_data(5)
    assert surrogate.grid_spacing(x) is None
    obj = Objective(x, r, kernel, None, True, profile=True)
    log_ls = np.log([0.01, 0.07, 0.3, 2.0])
    table = surrogate._tridiagonal_table(kernel, np.subtract.outer(x, x), r, log_ls)
    const = 0.5 * N * (np.log(N) - 1.0 - np.log(2 * np.pi))
    checked = 0
    for i, ll in enumerate(log_ls):
        for j in range(0, surrogate.GAINS.size, 4):
            A = kernel.unit(np.exp(ll))(x) + surrogate.GAINS[j] * np.eye(N)
            cond = np.linalg.cond(A)
            if cond > 1e8:  # both formulas are then only good to round-off
                continue
            theta = np.array([ll, np.log(surrogate.GAINS[j])])
            # r^T A^-1 r to cond * eps relatively, times N / 2 in the log likelihood (an
            # AVX2 machine's rounding differed by 1.2e-7 at cond 5.8e7)
            tol = max(1e-7, N * cond * np.finfo(float).eps)
            assert table[i, j] + const == pytest.approx(obj.value(theta), abs=tol)
            checked += 1
    assert checked >= 20


def test_offgrid_table_marks_non_positive_definite_cells():
    x, r = scattered_data(5)
    x[1] = x[0]  # a repeated position: R is singular, R + g I only just positive definite
    table = surrogate._tridiagonal_table(SquaredExp(), np.subtract.outer(x, x), r, np.log([1e3]))
    assert np.all(np.isneginf(table) | np.isfinite(table))
    assert np.all(np.isfinite(table[:, -10:]))


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("kernel", ["se", "matern32"])
def test_fit_from_offgrid_starts_is_as_good_as_a_thorough_search(seed, kernel):
    x, r = scattered_data(seed)
    gp = fit_gp(x, x + r, kernel=kernel, n_restarts=3, seed=seed)
    assert gp.optimization.n_candidates == 0  # the table chose the starts
    k = SquaredExp() if kernel == "se" else Matern32()
    obj = Objective(x, r, k, None, True, profile=True)
    assert gp.log_marginal_likelihood >= thorough(obj) - 1e-6


def test_periodic_kernels_get_the_offgrid_table_and_composite_ones_are_screened():
    x, r = scattered_data(2)
    gp = fit_gp(x, x + r, kernel="periodic", period=2.0, n_restarts=2)
    assert gp.optimization.n_candidates == 0  # the off-grid table chose the starts
    obj = Objective(x, r, Periodic(period=2.0), None, True, profile=True)
    assert gp.log_marginal_likelihood >= thorough(obj) - 1e-6
    both = fit_gp(x, x + r, kernel=SquaredExp() + Periodic(period=2.0), n_restarts=2)
    assert both.optimization.n_candidates == 16
    xg, rg = grid_data(0.0)
    assert surrogate._scan(Periodic(1.0, 1.0, period=2.0), xg, rg, np.zeros(2)) is None
    b = np.array([[-3.0, 1.0], [-20.0, 2.0]])
    xl = np.sort(np.random.default_rng(3).random(surrogate.MAX_OFFGRID + 1))
    assert surrogate.profiled_starts(SquaredExp(), xl, np.sin(xl), b, 2) is None


def test_a_rotary_fit_with_the_periodic_kernel_finds_the_best_optimum():
    """72 readings at random angles of a table whose error has harmonics 1, 3 and 9: five
    Newton runs from 30 screened candidates ended 10.3 nats low for seeds 0 and 2 (a
    likelihood with several maxima); the table's starts reach the thorough search's best."""
    rng = np.random.default_rng(1)
    x = np.sort(rng.uniform(0.0, 360.0, 72))
    f = 0.01 * np.sin(np.deg2rad(x) + 1) + 0.004 * np.cos(np.deg2rad(3 * x))
    y = x + f + 0.001 * np.sin(np.deg2rad(9 * x)) + 5e-4 * rng.standard_normal(72)
    obj = Objective(x, y - x, Periodic(period=360.0), None, True, profile=True)
    best = thorough(obj)
    for seed in (0, 2):
        gp = fit_gp(x, y, kernel="periodic", period=360.0, seed=seed)
        assert gp.optimization.n_candidates == 0
        assert gp.log_marginal_likelihood >= best - 1e-6


def test_maximize_runs_the_given_starts_and_screens_nothing():
    obj = Objective(*grid_data(0.0), SquaredExp(), None, True, profile=True)
    b = obj.bounds()
    t0 = [np.array([-2.0, -8.0]), np.array([-1.0, -6.0])]
    res = maximize(
        obj.value,
        obj.value_and_grad,
        b,
        rng=np.random.default_rng(0),
        value_grad_hess=obj.value_and_derivatives,
        starts=t0,
    )
    assert res.n_candidates == 0
    assert [s.theta0.tolist() for s in res.starts] == [t.tolist() for t in t0]


def _spy_ranks(monkeypatch) -> list:
    """Record the rank of every low-rank reduction (None where it fell back to dense)."""
    ranks = []
    lowrank = surrogate._lowrank_reduction

    def spy(R, r):
        out = lowrank(R, r)
        ranks.append(None if out is None else out[0].size - 1)
        return out

    monkeypatch.setattr(surrogate, "_lowrank_reduction", spy)
    return ranks


def test_lowrank_rows_agree_with_the_dense_reduction_within_the_dropped_part(monkeypatch):
    n = 120
    x, r = scattered_data(7, n=n)
    d = np.subtract.outer(x, x)
    log_ls = np.log([0.004, 0.03, 0.08, 0.3, 1.0, 30.0])
    used = _spy_ranks(monkeypatch)
    fast = surrogate._tridiagonal_table(SquaredExp(), d, r, log_ls)
    assert used[-1] is None and len(used) >= 4  # long scales low rank, the shortest not
    assert all(k is not None and k <= n // 2 for k in used[:-1])
    monkeypatch.setattr(surrogate, "LOWRANK", 0.0)
    dense = surrogate._tridiagonal_table(SquaredExp(), d, r, log_ls)
    assert np.array_equal(np.isfinite(fast), np.isfinite(dense))
    # the dropped part (trace below PIVOT_TOL) and round-off (n eps) bound the difference
    g = surrogate.GAINS
    bound = 0.5 * (n + 1) * (surrogate.PIVOT_TOL + n * np.finfo(float).eps) / g + 1e-9
    ok = np.isfinite(dense)
    assert np.all((np.abs(fast - dense) <= bound)[ok])
    assert np.max(np.abs(fast - dense)[:, g >= 1e-6]) < 1e-6


def test_a_scan_is_shared_by_fits_of_the_same_data_and_read_only():
    x, r = grid_data(0.02)
    b = np.array([-6.0, 3.0])
    first = surrogate._scan(SquaredExp(), x, r, b)
    assert surrogate._scan(SquaredExp(), x.copy(), r.copy(), b.copy()) is first
    assert not first.table.flags.writeable and not first.z.flags.writeable
    other = surrogate._scan(SquaredExp(), x, 2.0 * r, b)
    assert other is not first
    np.testing.assert_allclose(other.quad, 4.0 * first.quad, rtol=1e-12)
    assert surrogate._scan(Matern52(), x, r, b) is not first


@pytest.mark.parametrize("kernel", [SquaredExp(), Matern52(), Periodic(period=0.5)])
@pytest.mark.parametrize("n", [3, 4, 9])
def test_tiny_sets_and_long_length_scales_match_the_dense_formula(kernel, n, monkeypatch):
    # low-rank rows down to rank one (k + 2 = 3) and padding beyond n: the table still
    # equals the profiled likelihood computed from a dense factorisation
    x = np.linspace(0.0, 1.0, n) + 0.01 * np.sin(np.arange(n))
    r = 0.01 * np.cos(3.0 * x) + 1e-3 * np.arange(n)
    log_ls = np.log([0.05, 1.0, 30.0, 1e8])
    ranks = _spy_ranks(monkeypatch)
    table = surrogate._tridiagonal_table(kernel, np.subtract.outer(x, x), r, log_ls)
    assert ranks[0] == 1  # the longest length scale: R is all ones to round-off
    checked = 0
    for i, ll in enumerate(log_ls):
        for j in range(0, surrogate.GAINS.size, 6):
            A = kernel.unit(np.exp(ll))(x) + surrogate.GAINS[j] * np.eye(n)
            if np.linalg.cond(A) > 1e6:
                continue
            quad = r @ np.linalg.solve(A, r)
            expected = -0.5 * n * np.log(quad) - 0.5 * np.linalg.slogdet(A)[1]
            bound = 0.5 * (n + 1) * surrogate.PIVOT_TOL / surrogate.GAINS[j] + 1e-9
            assert abs(table[i, j] - expected) <= bound
            checked += int(i == 3)  # cells of the rank-one row
    assert checked >= 2


@pytest.mark.parametrize("k", [1, 5, 8, 13, 16, 100])
def test_sum_log_equals_the_sum_of_logs_along_any_axis(k):
    rng = np.random.default_rng(k)
    a = np.exp(rng.uniform(-3.0, 3.0, (k, 3, 4)))
    for axis, b in ((0, a), (-1, np.moveaxis(a, 0, -1).copy()), (1, np.moveaxis(a, 0, 1))):
        expected = np.log(b).sum(axis=axis)
        np.testing.assert_allclose(surrogate._sum_log(b, axis), expected, rtol=1e-13)


@pytest.mark.parametrize("n", [2, 7, 8, 31])
@pytest.mark.parametrize("kind", [SquaredExp, Matern32])
def test_half_bases_diagonalise_the_correlation(kind, n):
    basis = surrogate._basis(kind, n)
    u = np.arange(n, dtype=float)
    for i in (0, 30, 60):
        R = kind(float(surrogate.RATIOS[i]), 1.0)(u)
        Qt = basis.project(np.eye(n), slice(i, i + 1))[0]  # (n, n): Q^T
        np.testing.assert_allclose(Qt @ Qt.T, np.eye(n), atol=1e-13)
        np.testing.assert_allclose(Qt @ R @ Qt.T, np.diag(basis.lam[i]), atol=1e-12)
        np.testing.assert_allclose(
            np.sort(basis.lam[i]), np.clip(np.linalg.eigvalsh(R), 0, None), atol=1e-12
        )


@settings(max_examples=60, deadline=None)
@given(
    hnp.arrays(
        float,
        hnp.array_shapes(min_dims=1, max_dims=3, min_side=1, max_side=9),
        elements=st.sampled_from([-np.inf, -2.0, -1.0, 0.0, 0.5, 1.0, 3.0]),
    )
)
def test_neighbourhood_max_is_scipys_maximum_filter(table):
    expected = ndimage.maximum_filter(table, size=3, mode="constant", cval=-np.inf)
    np.testing.assert_array_equal(surrogate._neighbourhood_max(table), expected)


def test_probes_reach_the_higher_of_two_maxima_the_grid_table_merges(monkeypatch):
    # The homoscedastic stage-B data of one trial of the study's quality sample: its profiled
    # likelihood has maxima at log length scales -0.128 and 0.076 (0.024 nats apart, a
    # 0.04-nat dip between), and the grid table, off by the readings' noise, shows only the
    # lower one. The fit looks 0.2 to both sides of its optimum and finds the higher one.
    from cascal import gp as gp_module
    from cascal.cascade import Cascade
    from cascal.montecarlo import trial_rng
    from cascal.simulation import simulate_trial

    trial = simulate_trial(trial_rng(0, 10_000_000 + 104))
    stage0 = Cascade([trial.d2], "bayes", n_restarts=3, seed=104).fit().models[0]
    x, y = trial.d1[0], stage0.predict(trial.d1[1])
    obj = Objective(x, y - x, SquaredExp(), None, True, profile=True)
    best = thorough(obj)
    fitted = fit_gp(x, y, n_restarts=3)
    assert fitted.optimization.n_candidates == 0  # started from the grid table
    assert fitted.log_marginal_likelihood >= best - 1e-6
    monkeypatch.setattr(gp_module, "_probes", lambda dim: [])
    assert fit_gp(x, y, n_restarts=3).log_marginal_likelihood < best - 0.02  # without them
