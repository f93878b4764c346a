"""The cascade: propagated covariance, the baselines, more stages, and the paper's ordering."""

from __future__ import annotations

import numpy as np
import pytest

from cascal import Cascade, CascalError, FittedGP, OffsetTable, fit_gp, fit_table
from cascal.noise import Dense
from cascal.simulation import SensorMap, cost_j, simulate_trial
from utils import assert_allclose, dense_posterior, se


@pytest.fixture(scope="module")
def trial():
    return simulate_trial(np.random.default_rng(7))


@pytest.fixture(scope="module")
def bayes(trial):
    return Cascade([trial.d2, trial.d1], "bayes", n_restarts=3, seed=0).fit()


@pytest.fixture(scope="module")
def homo(trial):
    return Cascade([trial.d2, trial.d1], "homoscedastic", n_restarts=3, seed=0).fit()


def test_zero_propagated_covariance_is_a_plain_gp_at_given_hyperparameters(bayes):
    x, y = bayes.stages[1].x, bayes.stages[1].y
    hp = {"length_scale": 0.1, "variance": 1e-5, "noise_variance": 1e-8}
    with_dense = fit_gp(x, y, noise=np.zeros((x.size, x.size)), hyperparameters=hp)
    plain = fit_gp(x, y, hyperparameters=hp)
    assert isinstance(with_dense.noise, Dense) and plain.noise is None
    xs = np.linspace(x.min() - 0.05, x.max() + 0.05, 301)
    m1, c1 = with_dense.predict(xs, return_cov=True)
    m2, c2 = plain.predict(xs, return_cov=True)
    assert_allclose(m1, m2, rtol=0, atol=1e-10)
    assert_allclose(c1, c2, rtol=0, atol=1e-10 * hp["variance"])
    assert with_dense.log_marginal_likelihood == pytest.approx(
        plain.log_marginal_likelihood, rel=1e-12
    )


def test_zero_propagated_covariance_is_a_plain_gp_when_optimised(bayes):
    # full 3-parameter objective (known dense noise) against the profiled 2-parameter one
    x, y = bayes.stages[1].x, bayes.stages[1].y
    with_dense = fit_gp(x, y, noise=np.zeros((x.size, x.size)), seed=0)
    plain = fit_gp(x, y, seed=0)
    assert with_dense.log_marginal_likelihood == pytest.approx(
        plain.log_marginal_likelihood, abs=1e-6
    )
    xs = np.linspace(x.min(), x.max(), 301)
    m1, s1 = with_dense.predict(xs, return_std=True)
    m2, s2 = plain.predict(xs, return_std=True)
    assert_allclose(m1, m2, rtol=0, atol=1e-3 * np.max(s2))
    assert_allclose(s1, s2, rtol=1e-2)


def test_bayes_stage_one_noise_is_stage_zero_posterior_covariance(trial, bayes):
    m0, m1 = bayes.models
    assert isinstance(m0, FittedGP) and isinstance(m1, FittedGP)
    n = trial.d1[0].size
    mean, cov = m0.predict(trial.d1[1], return_cov=True)
    assert_allclose(bayes.stages[1].y, mean, rtol=0)
    assert_allclose(bayes.stages[1].x, trial.d1[0], rtol=0)
    assert_allclose(m1.x, trial.d1[0], rtol=0)
    assert isinstance(m1.noise, Dense)
    # the propagated covariance comes from a factor, positive semi-definite by construction;
    # it equals K** - V^T V up to that formula's own round-off, which cancels entries of
    # the size of the stage-0 prior variance (a few hundred eps times that variance)
    prior = m0.hyperparameters["variance"]
    assert m1.noise.n_clipped == 0
    C = m1.noise.dense(n)
    assert_allclose(C, C.T, rtol=0, atol=0)
    assert np.linalg.eigvalsh(C).min() > -1e3 * np.finfo(float).eps * prior
    assert_allclose(C, cov, rtol=0, atol=1e3 * np.finfo(float).eps * prior)
    w = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    assert np.all(-w[w < 0] < 1e3 * np.finfo(float).eps * prior)
    scale = np.max(np.abs(cov))
    # the stage-0 posterior covariance by GPML Alg. 2.1, independently of cascal
    hp = m0.hyperparameters
    x0, y0 = trial.d2
    k = lambda a, b: se(a, b, hp["length_scale"], hp["variance"])  # noqa: E731
    _, cov_ref = dense_posterior(
        k(x0, x0),
        k(trial.d1[1], x0),
        k(trial.d1[1], trial.d1[1]),
        hp["noise_variance"] * np.eye(x0.size),
        y0 - x0,
        trial.d1[1],
    )
    assert_allclose(cov, cov_ref, rtol=0, atol=1e-9 * scale)
    assert m1.noise_variance > 0  # the learned scalar is kept (SPEC, step 3)
    assert m0.noise is None


def test_homoscedastic_stage_one_has_no_known_noise(bayes, homo):
    assert homo.method == "homoscedastic"
    assert homo.models[1].noise is None
    assert homo.models[1].noise_variance > 0
    # same stage 0 and the same propagated targets as Algorithm 1
    assert homo.models[0].hyperparameters == bayes.models[0].hyperparameters
    assert_allclose(homo.stages[1].y, bayes.stages[1].y, rtol=0)


def test_lut_hand_computed():
    # stage 0: test bed -> reference; offsets 0.1, 0.3, 0.0 at knots 0, 1, 2
    s0 = (np.array([1.0, 0.0, 2.0]), np.array([1.3, 0.1, 2.0]))
    # stage 1: device -> test bed; test-bed readings corrected by table 0:
    # 0.5 -> 0.5 + 0.2 = 0.7, 1.0 -> 1.3, 1.5 -> 1.5 + 0.15 = 1.65, 2.5 -> 2.5 + 0.0 (held)
    s1 = (np.array([0.0, 1.0, 2.0, 3.0]), np.array([0.5, 1.0, 1.5, 2.5]))
    fc = Cascade([s0, s1], "lut").fit()
    t0, t1 = fc.models
    assert isinstance(t0, OffsetTable) and isinstance(t1, OffsetTable)
    assert_allclose(t0.knots, [0.0, 1.0, 2.0], rtol=0)
    assert_allclose(t0.offsets, [0.1, 0.3, 0.0], rtol=1e-14, atol=1e-15)
    assert_allclose(t0(np.array([-1.0, 0.5, 1.5, 3.0])), [-0.9, 0.7, 1.65, 3.0], rtol=1e-14)
    assert_allclose(fc.stages[1].y, [0.7, 1.3, 1.65, 2.5], rtol=1e-14)
    assert_allclose(t1.offsets, [0.7, 0.3, -0.35, -0.5], rtol=1e-13)
    # corrected device readings: r + offset, offsets held constant beyond both ends
    r = np.array([-2.0, 0.0, 0.5, 2.5, 3.0, 10.0])
    assert_allclose(fc.correct(r), [-1.3, 0.7, 1.0, 2.075, 2.5, 9.5], rtol=1e-13)


def test_lut_on_trial_matches_np_interp(trial):
    fc = Cascade([trial.d2, trial.d1], "lut").fit()
    (x2, y2), (x1, y1) = trial.d2, trial.d1
    o2 = np.argsort(x2)
    t1 = y1 + np.interp(y1, x2[o2], (y2 - x2)[o2])  # np.interp holds the end values
    o1 = np.argsort(x1)
    r = np.linspace(x1.min() - 0.1, x1.max() + 0.1, 500)
    expected = r + np.interp(r, x1[o1], (t1 - x1)[o1])
    assert_allclose(fc.correct(r), expected, rtol=0, atol=1e-15)


def test_fit_table_averages_repeats():
    t = fit_table([0.0, 1.0, 1.0, 2.0], [0.5, 1.25, 1.25, 2.0])
    assert_allclose(t.knots, [0.0, 1.0, 2.0], rtol=0)
    assert_allclose(t.offsets, [0.5, 0.25, 0.0], rtol=0)


def test_correct_uncertainty(bayes, trial):
    r = np.linspace(*trial.device_range, 50)
    mean, std = bayes.correct(r, return_std=True)
    m, s = bayes.device.predict(r, return_std=True)
    assert_allclose(mean, m, rtol=0)
    assert_allclose(std, s, rtol=0)
    assert np.all(std > 0)
    assert_allclose(bayes.correct(r), m, rtol=0)
    assert bayes.calibrated_range == (trial.d1[0].min(), trial.d1[0].max())


def test_the_homoscedastic_u_comes_with_its_caution(trial, bayes, homo):
    """A review: the command line cautions that the homoscedastic u leaves the test bed's
    error out (U covered 16 to 66 % in simulations), Python gave it silently. It warns
    where a u is asked of a chain; the corrections alone, bayes and one stage do not."""
    import warnings

    from cascal.errors import CascalWarning

    with pytest.warns(
        CascalWarning, match=r"homoscedastic' leaves the correlated error of the stages above"
    ):
        _, u = homo.correct(0.5, return_std=True)
    assert u == homo.device.predict(np.array([0.5]), return_std=True)[1][0]
    one = Cascade([trial.d2], "homoscedastic", n_restarts=1, seed=0).fit()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        homo.correct(0.5)
        bayes.correct(0.5, return_std=True)
        one.correct(0.5, return_std=True)


def test_lut_has_no_uncertainty(trial):
    fc = Cascade([trial.d2, trial.d1], "lut").fit()
    with pytest.raises(CascalError, match="gives no uncertainty"):
        fc.correct(np.array([0.5]), return_std=True)


def test_three_stages_propagate():
    # reference -> test bed -> intermediate -> device, smooth hand-made sensor errors
    z = np.zeros(9)
    testbed = SensorMap(np.r_[0.01, z], np.r_[0.002, z], np.r_[3.0, z])
    middle = SensorMap(np.r_[-0.008, z], np.r_[0.004, z], np.r_[5.0, z])
    device = SensorMap(np.r_[0.012, z], np.r_[-0.003, z], np.r_[2.0, z])
    g = np.random.default_rng(3)
    p0, p1, p2 = np.linspace(0.05, 0.95, 25), np.linspace(0.1, 0.9, 30), np.linspace(0.1, 0.9, 40)
    eps = lambda n: 1e-5 * g.normal(size=n)  # noqa: E731
    s0 = (testbed(p0) + eps(25), p0 + eps(25))
    s1 = (middle(p1) + eps(30), testbed(p1) + eps(30))
    s2 = (device(p2) + eps(40), middle(p2) + eps(40))
    fc = Cascade([s0, s1, s2], "bayes", n_restarts=3, seed=1).fit()
    m0, m1, m2 = fc.models
    assert len(fc.models) == 3 and [s.name for s in fc.stages] == ["testbed", "stage 1", "device"]
    mean1, cov1 = m0.predict(s1[1], return_cov=True)
    assert_allclose(fc.stages[1].y, mean1, rtol=0)
    mean2, cov2 = m1.predict(s2[1], return_cov=True)
    assert_allclose(fc.stages[2].y, mean2, rtol=0)
    for m, upper, cov in ((m1, m0, cov1), (m2, m1, cov2)):
        assert isinstance(m.noise, Dense)
        prior = upper.hyperparameters["variance"]  # round-off of K** - V^T V scales with it
        atol = 1e3 * np.finfo(float).eps * prior
        assert_allclose(m.noise.dense(cov.shape[0]), cov, rtol=0, atol=atol)
    # the chain corrects the device: error far below the raw sensor error (~1e-2)
    r = device(np.linspace(0.15, 0.85, 200))
    err = fc.correct(r) - device.inverse(r)
    raw = r - device.inverse(r)
    assert np.sqrt(np.mean(err**2)) < 0.02 * np.sqrt(np.mean(raw**2))


def test_cascade_deterministic(trial):
    a = Cascade([trial.d2, trial.d1], "bayes", n_restarts=2, seed=11).fit()
    b = Cascade([trial.d2, trial.d1], "bayes", n_restarts=2, seed=11).fit()
    for ma, mb in zip(a.models, b.models, strict=True):
        assert ma.hyperparameters == mb.hyperparameters
        assert np.array_equal(ma.alpha, mb.alpha)
    r = np.linspace(*trial.device_range, 20)
    assert np.array_equal(a.correct(r), b.correct(r))


def test_with_method_and_a_shared_first_stage_give_the_fits_of_fresh_cascades(trial, bayes, homo):
    chain = Cascade([trial.d2, trial.d1], "lut", n_restarts=3, seed=0)
    stage0 = Cascade([trial.d2], "bayes", n_restarts=3, seed=0).fit().models[0]
    assert stage0.log_marginal_likelihood == bayes.models[0].log_marginal_likelihood
    for _ in range(2):  # the second round takes the first stage's posterior from the cache
        for fresh in (bayes, homo):
            reused = chain.with_method(fresh.method).fit(first=stage0)
            assert reused.method == fresh.method
            np.testing.assert_array_equal(reused.stages[1].y, fresh.stages[1].y)
            lml = reused.models[1].log_marginal_likelihood
            assert lml == fresh.models[1].log_marginal_likelihood
    assert chain.method == "lut" and chain.fit().method == "lut"
    with pytest.raises(CascalError, match="method"):
        chain.with_method("spline")


def test_paper_ordering_of_methods():
    """Seeded: median J of Algorithm 1 <= Alternative 1 < Alternative 2 (paper, Fig. 5).

    Lookup tables lose by an order of magnitude in every trial. Algorithm 1's gain over
    Alternative 1 is small (paper: a shift of the J distribution), so 20 trials resolve it
    only statistically: over eight disjoint seed sets of 20 trials the paired median of
    log(J_bayes / J_homoscedastic) was negative in all eight, and the unpaired medians
    were ordered in seven; both are asserted here on one seed set.
    """
    J = {m: [] for m in ("bayes", "homoscedastic", "lut")}
    for i in range(20):
        t = simulate_trial(np.random.default_rng(2000 + i))
        for m in J:
            fc = Cascade([t.d2, t.d1], m, n_restarts=3, seed=i).fit()
            J[m].append(cost_j(t, correct=fc.correct))
    b, h, lut = (np.array(J[m]) for m in ("bayes", "homoscedastic", "lut"))
    assert np.median(b) <= np.median(h) < np.median(lut)
    assert np.median(np.log(b / h)) < 0
    assert np.all(h < lut) and np.all(b < lut)


def test_a_cascade_fits_the_same_numbers_whatever_blas_threads(trial, monkeypatch):
    """An API review's case: the stage-0 posterior that Cascade.fit hands to stage 1 was
    computed outside the one-thread BLAS limit of fit_gp, so with two BLAS threads a sum
    kernel's stage 1 moved (a log parameter -19.50 against -18.69): a library fit then
    differed from ``cascal fit``'s. The whole fit now runs on one BLAS thread."""
    from threadpoolctl import threadpool_limits

    from cascal import Matern32, SquaredExp, gp

    monkeypatch.setattr(gp, "_PINNED", [])  # (as in a process no command has pinned yet)
    kern = SquaredExp(0.1, 1e-6) + Matern32(0.05, 1e-7)
    fits = []
    for threads in (1, 2):
        with threadpool_limits(limits=threads, user_api="blas"):
            fits.append(Cascade([trial.d2, trial.d1], kernel=kern, seed=3).fit())
    a, b = fits
    assert np.array_equal(a.models[1].kernel.theta, b.models[1].kernel.theta)
    r = np.linspace(0.1, 0.9, 7)
    assert np.array_equal(a.correct(r), b.correct(r))


def test_a_stage_whose_known_noise_is_wrong_is_named():
    """A leftover of a review: a stage's malformed known noise was refused without the
    stage's name ("noise variance: expected shape (10,), got (9,)")."""
    from cascal import InputError
    from cascal.cascade import Stage

    x = np.linspace(0.0, 1.0, 10)
    cases = {
        "noise variance: expected shape \\(10,\\), got \\(9,\\)": [1e-8] * 9,
        "noise variance: expected finite values >= 0": -1.0,
        "dense noise: expected a square": np.ones((10, 3)),
    }
    for message, noise in cases.items():
        with pytest.raises(InputError, match=f"^encoder: {message}"):
            Cascade([(x, x + 1e-3), Stage(x, x, noise, "encoder")])
        with pytest.raises(InputError, match=f"^testbed: {message}"):
            Cascade([Stage(x, x + 1e-3, noise, "testbed"), (x, x)])
