"""GP regression against GPML's dense formulas: posterior, log marginal likelihood, gradients,
profiling, hyperparameter recovery and the fitted state."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from cascal import FittedGP, InputError, Posterior, fit_gp, log_marginal_likelihood
from cascal.gp import Objective
from cascal.kernels import Constant, Matern32, Matern52, Periodic, SquaredExp
from cascal.noise import Dense, Diagonal
from utils import assert_allclose, dense_lml, dense_posterior, fd_gradient, se

L0, V0, SN0 = 0.2, 1e-4, 1e-6  # hyperparameters of the posterior tests
N = 20


@pytest.fixture
def data():
    g = np.random.default_rng(11)
    x = np.sort(g.random(N))
    y = x + 0.01 * np.sin(7 * x) + 0.004 * np.cos(17 * x) + 1e-3 * g.normal(size=N)
    return x, y


@pytest.fixture
def vec():
    return np.linspace(0.5e-6, 3e-6, N)


@pytest.fixture
def dense(data):
    x, _ = data
    # exponential (Ornstein-Uhlenbeck) correlation: correlated and positive definite
    return 2e-6 * np.exp(-np.abs(x[:, None] - x[None, :]) / 0.15)


def _fit_and_noise(form, data, vec, dense):
    """A FittedGP at given hyperparameters and the dense target-noise matrix it should use."""
    x, y = data
    hp = {"length_scale": L0, "variance": V0}
    if form == "learned":
        fit = fit_gp(x, y, kernel="se", hyperparameters={**hp, "noise_variance": SN0})
        return fit, SN0 * np.eye(N)
    if form == "vector":
        fit = fit_gp(x, y, kernel="se", noise=vec, hyperparameters=hp)
        return fit, np.diag(vec)
    if form == "vector+learned":
        fit = fit_gp(
            x, y, noise=vec, learn_noise=True, hyperparameters={**hp, "noise_variance": SN0}
        )
        return fit, np.diag(vec) + SN0 * np.eye(N)
    if form == "dense":
        fit = fit_gp(x, y, kernel="se", noise=dense, hyperparameters={**hp, "noise_variance": SN0})
        return fit, dense + SN0 * np.eye(N)
    raise AssertionError(form)


FORMS = ["learned", "vector", "vector+learned", "dense"]
EPS = np.finfo(float).eps
XS = np.linspace(-0.2, 1.2, 37)


@pytest.mark.parametrize("form", FORMS)
def test_posterior_against_dense_formula(form, data, vec, dense):
    x, y = data
    fit, Nmat = _fit_and_noise(form, data, vec, dense)
    assert isinstance(fit, FittedGP)
    # GPML Alg. 2.1 with the identity prior mean m(x) = x
    mean, cov = dense_posterior(
        se(x, x, L0, V0), se(XS, x, L0, V0), se(XS, XS, L0, V0), Nmat, y - x, XS
    )
    got_mean, got_cov = fit.predict(XS, return_cov=True)
    assert_allclose(got_mean, mean, rtol=1e-11, atol=1e-13)
    assert_allclose(got_cov, cov, rtol=0, atol=1e-10 * V0)
    assert_allclose(got_cov, got_cov.T, rtol=0)
    m2, std = fit.predict(XS, return_std=True)
    assert_allclose(m2, mean, rtol=1e-11, atol=1e-13)
    assert_allclose(std, np.sqrt(np.clip(np.diagonal(cov), 0, None)), rtol=1e-7, atol=1e-9)
    assert_allclose(fit.predict(XS), mean, rtol=1e-11, atol=1e-13)
    post = fit.posterior(XS)
    assert isinstance(post, Posterior)
    assert_allclose(post.mean, mean, rtol=1e-11, atol=1e-13)
    assert_allclose(post.std, std, rtol=1e-12, atol=1e-15)
    # stored state: weights alpha = Kt^-1 (y - m(x)), L L^T = Kt
    Kt = se(x, x, L0, V0) + Nmat
    assert_allclose(fit.alpha, np.linalg.solve(Kt, y - x), rtol=1e-9)
    assert_allclose(fit.L @ fit.L.T, Kt, rtol=1e-12, atol=1e-20)
    assert fit.optimization is None


@pytest.mark.parametrize("form", FORMS)
def test_posterior_factor_against_dense_formula(form, data, vec, dense):
    x, y = data
    fit, Nmat = _fit_and_noise(form, data, vec, dense)
    mean, cov = dense_posterior(
        se(x, x, L0, V0), se(XS, x, L0, V0), se(XS, XS, L0, V0), Nmat, y - x, XS
    )
    got_mean, U = fit.posterior_factor(XS)
    assert_allclose(got_mean, fit.predict(XS), rtol=0, atol=0)
    assert_allclose(got_mean, mean, rtol=1e-11, atol=1e-13)
    assert U.shape[0] == XS.size and 0 < U.shape[1] < XS.size + x.size
    # equal to the dense formula's own round-off, which scales with the prior variance
    assert_allclose(U @ U.T, cov, rtol=0, atol=1e-12 * V0)
    assert_allclose(U @ U.T, fit.predict(XS, return_cov=True)[1], rtol=0, atol=1e3 * EPS * V0)


@pytest.mark.parametrize("kernel", ["matern32", "matern52", "periodic"])
def test_posterior_factor_of_other_kernels(kernel, data):
    x, y = data
    hp = {"length_scale": 0.3, "variance": V0, "noise_variance": SN0}
    fit = fit_gp(
        x, y, kernel=kernel, hyperparameters=hp, period=1.3 if kernel == "periodic" else None
    )
    mean, U = fit.posterior_factor(XS)
    expected_mean, cov = fit.predict(XS, return_cov=True)
    assert_allclose(mean, expected_mean, rtol=0, atol=0)
    assert_allclose(U @ U.T, cov, rtol=0, atol=1e3 * EPS * V0)
    assert np.linalg.eigvalsh(U @ U.T).min() > -1e3 * EPS * V0


@pytest.mark.parametrize("form", FORMS)
def test_log_marginal_likelihood_against_dense_formula(form, data, vec, dense):
    x, y = data
    fit, Nmat = _fit_and_noise(form, data, vec, dense)
    expected = dense_lml(y - x, se(x, x, L0, V0) + Nmat)
    assert fit.log_marginal_likelihood == pytest.approx(expected, rel=1e-12)
    known = {"learned": None, "vector": vec, "vector+learned": vec, "dense": dense}[form]
    sn2 = 0.0 if form == "vector" else SN0
    value = log_marginal_likelihood(
        x, y, kernel=SquaredExp(L0, V0), noise=known, noise_variance=sn2
    )
    assert value == pytest.approx(expected, rel=1e-12)


def test_log_marginal_likelihood_not_trivially_constant(data):
    # the check above would be void if the value ignored its hyperparameters
    x, y = data
    a = log_marginal_likelihood(x, y, kernel=SquaredExp(L0, V0), noise_variance=SN0)
    b = log_marginal_likelihood(x, y, kernel=SquaredExp(L0, V0), noise_variance=4 * SN0)
    c = log_marginal_likelihood(x, y, kernel=SquaredExp(2 * L0, V0), noise_variance=SN0)
    assert abs(a - b) > 1.0 and abs(a - c) > 1.0


KERNELS = {
    "se": SquaredExp(0.15, 2e-4),
    "matern32": Matern32(0.3, 5e-5),
    "matern52": Matern52(0.25, 1e-4),
    "periodic": Periodic(0.9, 1e-4, period=0.7),
    "const+se": Constant(3e-5) + SquaredExp(0.2, 1e-4),
    "se*periodic": SquaredExp(0.5, 1e-2) * Periodic(1.2, 0.02, period=0.4),
    "number*matern52": 3.0 * Matern52(0.2, 4e-5),
}
NOISES = [("none", True), ("vector", False), ("vector", True), ("dense", True), ("dense", False)]


@pytest.mark.parametrize("kname", sorted(KERNELS))
@pytest.mark.parametrize(("nform", "learn"), NOISES)
def test_objective_value_and_gradient(kname, nform, learn, data, vec, dense):
    x, y = data
    r = y - x
    kernel = KERNELS[kname]
    known = {"none": None, "vector": Diagonal(vec), "dense": Dense(dense)}[nform]
    Nknown = np.zeros((N, N)) if known is None else known.dense(N)
    obj = Objective(x, r, kernel, known, learn)
    p = kernel.n_params
    assert obj.dim == p + int(learn)

    def full(theta):
        Kt = kernel.with_theta(theta[:p])(x) + Nknown
        if learn:
            Kt = Kt + np.exp(theta[p]) * np.eye(N)
        return dense_lml(r, Kt)

    theta = np.r_[kernel.theta, np.log(3e-6)] if learn else kernel.theta
    value, grad = obj.value_and_grad(theta)
    assert value == pytest.approx(full(theta), rel=1e-11)
    assert obj.value(theta) == pytest.approx(value, rel=1e-14)
    assert grad.shape == (obj.dim,)
    fd = fd_gradient(full, theta, h=1e-5)
    # central differences: O(h^2) truncation and ~eps |lml| / h round-off, both far below 1e-6
    assert_allclose(grad, fd, rtol=1e-6, atol=1e-6 * max(1.0, np.max(np.abs(fd))))
    assert np.max(np.abs(grad)) > 1e-2  # a point away from the optimum: the check has teeth


@pytest.mark.parametrize("nform", ["none", "vector", "dense"])
def test_log_marginal_likelihood_eval_gradient(nform, data, vec, dense):
    x, y = data
    known = {"none": None, "vector": vec, "dense": dense}[nform]
    Nknown = {"none": np.zeros((N, N)), "vector": np.diag(vec), "dense": dense}[nform]
    k = Matern52(0.25, 1e-4)

    def full(theta):
        Kt = k.with_theta(theta[:2])(x) + Nknown + np.exp(theta[2]) * np.eye(N)
        return dense_lml(y - x, Kt)

    theta = np.r_[k.theta, np.log(2e-6)]
    v, g = log_marginal_likelihood(
        x, y, kernel=k, noise=known, noise_variance=2e-6, eval_gradient=True
    )
    assert g.shape == (3,)
    assert v == pytest.approx(full(theta), rel=1e-11)
    fd = fd_gradient(full, theta)
    assert_allclose(g, fd, rtol=1e-6, atol=1e-6 * np.max(np.abs(fd)))


def _profiled_dense(kernel, x, r, theta2):
    """Profiled LML by hand: s2 = r^T A^-1 r / n, A = R + g I, then the full dense LML."""
    R = kernel.with_theta(np.array([theta2[0], 0.0]))(x)
    A = R + np.exp(theta2[1]) * np.eye(len(x))
    s2 = float(r @ np.linalg.solve(A, r)) / len(x)
    return dense_lml(r, s2 * A), s2


PROFILE_KERNELS = ["se", "matern32", "matern52", "periodic"]


@pytest.mark.parametrize("kname", PROFILE_KERNELS)
def test_profiled_objective(kname, data):
    x, y = data
    r = y - x
    kernel = KERNELS[kname]
    prof = Objective(x, r, kernel, None, True, profile=True)
    full = Objective(x, r, kernel, None, True)
    assert prof.dim == 2
    theta2 = np.array([np.log(0.3), np.log(0.05)])
    expected, s2 = _profiled_dense(kernel, x, r, theta2)
    value, grad = prof.value_and_grad(theta2)
    assert value == pytest.approx(expected, rel=1e-11)
    ft = prof.full_theta(theta2)
    assert_allclose(ft, [theta2[0], np.log(s2), theta2[1] + np.log(s2)], rtol=1e-12)
    # the profiled value is the full objective at full_theta, and the overall scale is
    # optimal: scaling variance and noise variance together (d log s2 = d log sn2) is flat
    fv, fg = full.value_and_grad(ft)
    assert fv == pytest.approx(value, rel=1e-11)
    assert abs(fg[1] + fg[2]) < 1e-9 * np.max(np.abs(fg))
    assert np.max(np.abs(fg)) > 1e-2
    fd = fd_gradient(lambda t: _profiled_dense(kernel, x, r, t)[0], theta2)
    assert_allclose(grad, fd, rtol=1e-6, atol=1e-6 * np.max(np.abs(fd)))
    # zero profiled gradient <=> zero full gradient: d P / d log l = d F / d log l and
    # d P / d log g = d F / d log noise_variance at full_theta
    assert_allclose(grad, fg[[0, 2]], rtol=1e-8, atol=1e-9 * np.max(np.abs(grad)))


def test_profile_needs_plain_problem(data, vec):
    x, y = data
    with pytest.raises(ValueError, match="profiling needs"):
        Objective(x, y - x, SquaredExp(), Diagonal(vec), True, profile=True)
    with pytest.raises(ValueError, match="profiling needs"):
        Objective(x, y - x, Constant(1.0) + SquaredExp(), None, True, profile=True)


def test_profiled_optimum_has_zero_full_gradient(data):
    x, y = data
    fit = fit_gp(x, y, kernel="se", seed=3)
    assert fit.optimization is not None
    full = Objective(x, y - x, SquaredExp(), None, True)
    theta = np.r_[fit.kernel.theta, np.log(fit.noise_variance)]
    b = full.bounds()
    assert np.all((theta > b[:, 0] + 0.1) & (theta < b[:, 1] - 0.1)), "optimum on a bound"
    value, grad = full.value_and_grad(theta)
    assert value == pytest.approx(fit.log_marginal_likelihood, rel=1e-10)
    assert value == pytest.approx(fit.optimization.value, rel=1e-10)
    # L-BFGS-B stops at a projected gradient of 1e-5 on the unit box (log-widths ~10) or on
    # a relative LML change of ~2e-9: |gradient| well below 1e-2 in log space; a step of 0.3
    # in any log-hyperparameter changes the gradient by orders of magnitude more.
    assert np.max(np.abs(grad)) < 1e-2
    for j in range(3):
        e = np.zeros(3)
        e[j] = 0.3
        assert np.max(np.abs(full.value_and_grad(theta + e)[1])) > 0.5


def test_fit_recovers_hyperparameters_of_a_gp_sample():
    g = np.random.default_rng(2024)
    n, l, v, sn2 = 300, 0.5, 1.0, 0.01
    x = np.sort(g.uniform(0.0, 10.0, n))
    f = np.linalg.cholesky(se(x, x, l, v) + 1e-10 * np.eye(n)) @ g.normal(size=n)
    y = f + np.sqrt(sn2) * g.normal(size=n)
    fit = fit_gp(x, y, kernel="se", mean="zero", seed=0)
    hp = fit.hyperparameters
    # 10 units / l = 20 correlation lengths: the variance is estimated from ~20 effectively
    # independent values (relative sd ~ sqrt(2/20) = 0.3), so allow a factor of 2; the length
    # scale is better determined (curvature of the whole sample), allow 30 %; the noise
    # variance comes from 300 residuals (relative sd ~ 0.08), allow 30 %.
    assert hp["length_scale"] == pytest.approx(l, rel=0.3)
    assert 0.5 * v < hp["variance"] < 2.0 * v
    assert hp["noise_variance"] == pytest.approx(sn2, rel=0.3)
    assert fit.jitter == 0.0


def test_fit_beats_random_hyperparameters(data):
    x, y = data
    fit = fit_gp(x, y, kernel="matern52", seed=1)
    b = Objective(x, y - x, Matern52(), None, True).bounds()
    g = np.random.default_rng(5)
    for theta in b[:, 0] + g.random((25, 3)) * (b[:, 1] - b[:, 0]):
        k = Matern52().with_theta(theta[:2])
        other = log_marginal_likelihood(x, y, kernel=k, noise_variance=float(np.exp(theta[2])))
        assert fit.log_marginal_likelihood >= other
    # and the recorded value is the LML at the fitted hyperparameters
    again = log_marginal_likelihood(x, y, kernel=fit.kernel, noise_variance=fit.noise_variance)
    assert fit.log_marginal_likelihood == pytest.approx(again, rel=1e-12)


def test_fit_with_known_dense_noise_is_optimal(data, dense):
    x, y = data
    fit = fit_gp(x, y, kernel="se", noise=dense, seed=2, n_restarts=3)
    assert fit.noise is not None and not fit.noise.is_diagonal
    assert fit.noise_variance > 0
    full = Objective(x, y - x, SquaredExp(), Dense(dense), True)
    theta = np.r_[fit.kernel.theta, np.log(fit.noise_variance)]
    assert fit.log_marginal_likelihood == pytest.approx(full.value(theta), rel=1e-10)
    for e in np.eye(3) * 0.05:
        assert full.value(theta + e) <= fit.log_marginal_likelihood + 1e-6
        assert full.value(theta - e) <= fit.log_marginal_likelihood + 1e-6


def test_jitter_zero_for_well_conditioned_fit(data):
    x, y = data
    fit = fit_gp(x, y, hyperparameters={"length_scale": L0, "variance": V0, "noise_variance": SN0})
    assert fit.jitter == 0.0


def test_determinism(data):
    x, y = data
    a = fit_gp(x, y, kernel="matern32", seed=7)
    b = fit_gp(x, y, kernel="matern32", seed=7)
    c = fit_gp(x, y, kernel="matern32", seed=np.random.default_rng(7))
    for other in (b, c):
        assert other.hyperparameters == a.hyperparameters  # bit-identical
        assert other.log_marginal_likelihood == a.log_marginal_likelihood
        for s, t in zip(a.optimization.starts, other.optimization.starts, strict=True):
            assert np.array_equal(s.theta0, t.theta0) and np.array_equal(s.theta, t.theta)


def test_optimization_diagnostics(data):
    x, y = data
    # screened random candidates (a sum of kernels has no table of starts), then runs from
    # each part fitted alone, the other part short or long
    kernel = SquaredExp() + Periodic(period=2.0 * np.ptp(x))
    fit = fit_gp(x, y, kernel=kernel, n_restarts=4, seed=0)
    opt = fit.optimization
    assert len(opt.starts) == 4 + 4
    assert opt.value == max(s.value for s in opt.starts)
    assert opt.n_evals == opt.n_candidates + opt.n_probes + sum(s.n_evals for s in opt.starts)
    assert opt.n_candidates >= 16
    # starts from the table of the profiled likelihood: its best local maxima, at most 4
    opt = fit_gp(x, y, kernel="se", n_restarts=4, seed=0).optimization
    assert 1 <= len(opt.starts) <= 4 and opt.n_candidates == 0
    assert opt.value == max(s.value for s in opt.starts)


def test_hyperparameters_dict(data):
    x, y = data
    fit = fit_gp(x, y, kernel="se", seed=0)
    hp = fit.hyperparameters
    assert set(hp) == {"length_scale", "variance", "noise_variance"}
    assert hp["length_scale"] == fit.kernel.length_scale
    assert hp["variance"] == fit.kernel.variance
    assert hp["noise_variance"] == fit.noise_variance > 0
    p = fit_gp(
        x * 360,
        y * 360,
        kernel="periodic",
        period=360.0,
        hyperparameters={"length_scale": 1.0, "variance": 1.0, "noise_variance": 0.1},
    )
    assert p.hyperparameters == {
        "length_scale": pytest.approx(1.0, rel=1e-15),
        "variance": pytest.approx(1.0, rel=1e-15),
        "period": 360.0,
        "noise_variance": 0.1,
    }
    # given hyperparameters round-trip through the fit
    again = fit_gp(x, y, hyperparameters=hp)
    assert again.hyperparameters == pytest.approx(hp, rel=1e-14)
    assert again.log_marginal_likelihood == pytest.approx(fit.log_marginal_likelihood, rel=1e-11)


def test_predict_many_points_mean_only_matches_std_path(data):
    x, y = data
    fit = fit_gp(x, y, hyperparameters={"length_scale": L0, "variance": V0, "noise_variance": SN0})
    xs = np.linspace(-0.5, 1.5, 100_000)  # many blocks
    mean = fit.predict(xs)
    mean2, std = fit.predict(xs, return_std=True)
    assert mean.shape == std.shape == (100_000,)
    assert_allclose(mean, mean2, rtol=0)
    assert_allclose(mean, xs + se(xs, x, L0, V0) @ fit.alpha, rtol=1e-12, atol=1e-14)
    sub = np.r_[0:100_000:997, 99_999]
    _, cov = fit.predict(xs[sub], return_cov=True)
    assert_allclose(std[sub], np.sqrt(np.clip(np.diagonal(cov), 0, None)), rtol=1e-9, atol=1e-12)
    assert np.all(std <= np.sqrt(V0) * (1 + 1e-12))


def test_predict_refuses_std_and_cov(data):
    x, y = data
    fit = fit_gp(x, y, hyperparameters={"length_scale": L0, "variance": V0, "noise_variance": SN0})
    with pytest.raises(ValueError, match="not both"):
        fit.predict(XS, return_std=True, return_cov=True)


@pytest.mark.parametrize(
    ("mean", "name", "value"),
    [
        ("identity", "identity", None),
        ("zero", "zero", 0.0),
        ("constant", "constant", "avg"),
        (0.3, "constant", 0.3),
        ("offset", "offset", "shift"),
    ],
)
def test_prior_means(mean, name, value, data):
    x, y = data
    hp = {"length_scale": L0, "variance": 0.5, "noise_variance": SN0}
    fit = fit_gp(x, y, mean=mean, hyperparameters=hp)
    assert fit.mean.name == name
    if value is None:
        mx, ms = x, XS
    elif value == "shift":  # identity plus the average of y - x
        c = float(np.mean(y - x))
        mx, ms = x + c, XS + c
    else:
        c = float(np.mean(y)) if value == "avg" else value
        mx, ms = np.full(N, c), np.full(XS.size, c)
    exp_mean, exp_cov = dense_posterior(
        se(x, x, L0, 0.5), se(XS, x, L0, 0.5), se(XS, XS, L0, 0.5), SN0 * np.eye(N), y - mx, ms
    )
    got, cov = fit.predict(XS, return_cov=True)
    # cond(Kt) ~ variance / noise_variance = 5e5: allow 1e-10 absolute on values of order 1
    assert_allclose(got, exp_mean, rtol=1e-10, atol=1e-10)
    assert_allclose(cov, exp_cov, rtol=0, atol=1e-10 * 0.5)
    expected_lml = dense_lml(y - mx, se(x, x, L0, 0.5) + SN0 * np.eye(N))
    assert fit.log_marginal_likelihood == pytest.approx(expected_lml, rel=1e-11)
    lml = log_marginal_likelihood(x, y, kernel=SquaredExp(L0, 0.5), mean=mean, noise_variance=SN0)
    assert lml == pytest.approx(expected_lml, rel=1e-11)
    # far from the data the prediction returns to the prior mean
    far = fit.predict(np.array([50.0]))[0]
    prior = {None: 50.0, "shift": 50.0 + mx[0] - x[0]}.get(value, ms[0])  # type: ignore[arg-type]
    assert far == pytest.approx(prior, rel=1e-12, abs=1e-12)


def test_offset_mean_follows_a_zero_offset_the_identity_cannot():
    """Two sensors whose zeros differ: with ``mean="offset"`` the fit is the
    unshifted fit moved by 10 m (a shift of the targets changes nothing else); the identity
    mean has to reach an offset of 1000 m with its variance and a length scale at its upper
    bound, and misses the corrections by more than 0.1 mm."""
    rng = np.random.default_rng(3)
    x = np.linspace(0.0, 1.0, 40)
    y = x + 1e-3 * np.sin(6 * x) + 2e-5 * rng.standard_normal(40)
    base = fit_gp(x, y, mean="offset")
    moved = fit_gp(x, y + 10.0, mean="offset")
    for k, v in base.hyperparameters.items():
        assert moved.hyperparameters[k] == pytest.approx(v, rel=1e-6), k
    m0, s0 = base.predict(XS, return_std=True)
    m1, s1 = moved.predict(XS, return_std=True)
    assert_allclose(m1 - 10.0, m0, rtol=0, atol=1e-9)
    assert_allclose(s1, s0, rtol=1e-5, atol=0)
    assert base.optimization.at_bounds() == moved.optimization.at_bounds() == []
    stuck = fit_gp(x, y + 1000.0)
    assert stuck.optimization.at_bounds() == [("length_scale", "upper")]
    assert np.max(np.abs(stuck.predict(XS) - 1000.0 - m0)) > 1e-4  # 0.1 mm off


def test_fitted_gp_is_frozen(data):
    import dataclasses

    x, y = data
    fit = fit_gp(x, y, hyperparameters={"length_scale": L0, "variance": V0, "noise_variance": SN0})
    with pytest.raises(dataclasses.FrozenInstanceError):
        fit.noise_variance = 1.0


SCALED = ["se", "matern32", "matern52", "periodic"]


@pytest.mark.skipif(not hasattr(Objective, "value_grad_hess"), reason="no exact Hessian")
@pytest.mark.parametrize("kname", SCALED)
@pytest.mark.parametrize(("nform", "learn"), [*NOISES, ("profile", True)])
def test_objective_hessian(kname, nform, learn, data, vec, dense):
    x, y = data
    kernel = KERNELS[kname]
    profile = nform == "profile"
    known = {"none": None, "profile": None, "vector": Diagonal(vec), "dense": Dense(dense)}[nform]
    obj = Objective(x, y - x, kernel, known, learn, profile=profile)
    assert obj.has_hessian
    if profile:
        theta = np.array([np.log(0.3), np.log(0.05)])
    else:
        theta = np.r_[kernel.theta, np.log(3e-6)] if learn else kernel.theta
    value, grad, H = obj.value_grad_hess(theta)
    v2, g2 = obj.value_and_grad(theta)
    assert value == pytest.approx(v2, rel=1e-12)
    assert_allclose(grad, g2, rtol=1e-9, atol=1e-10 * np.max(np.abs(g2)))
    assert H.shape == (obj.dim, obj.dim)
    assert_allclose(H, H.T, rtol=1e-12, atol=1e-12 * np.max(np.abs(H)))
    h = 1e-5
    fd = np.empty_like(H)
    for j in range(obj.dim):
        e = np.zeros(obj.dim)
        e[j] = h
        fd[:, j] = (obj.value_and_grad(theta + e)[1] - obj.value_and_grad(theta - e)[1]) / (2 * h)
    assert_allclose(H, fd, rtol=1e-5, atol=1e-6 * np.max(np.abs(fd)))


@pytest.mark.parametrize("learn", [True, False])
def test_objective_hessian_against_textbook_formula(learn, data, dense):
    """Gradient and Hessian of the dense-noise objective against explicit inverses."""
    x, y = data
    kernel = SquaredExp(0.3, 2e-4)
    obj = Objective(x, y - x, kernel, Dense(dense), learn)
    sn2 = 3e-6
    theta = np.r_[kernel.theta, np.log(sn2)] if learn else kernel.theta
    _, g, H = obj.value_grad_hess(theta)
    d2 = np.subtract.outer(x, x) ** 2 / 0.3**2
    rho = np.exp(-0.5 * d2)
    sf2 = 2e-4
    dK = [sf2 * rho * d2, sf2 * rho] + ([sn2 * np.eye(x.size)] if learn else [])
    Kt = sf2 * rho + obj.known_matrix + (sn2 * np.eye(x.size) if learn else 0.0)
    Ki = np.linalg.inv(Kt)
    a = Ki @ (y - x)
    p = len(dK)
    d2K = [[np.zeros_like(Kt) for _ in range(p)] for _ in range(p)]
    d2K[0][0] = sf2 * rho * d2 * (d2 - 2.0)
    d2K[0][1] = d2K[1][0] = dK[0]
    d2K[1][1] = dK[1]
    if learn:
        d2K[2][2] = dK[2]
    g_ref = np.array([0.5 * a @ Kj @ a - 0.5 * np.trace(Ki @ Kj) for Kj in dK])
    H_ref = np.array(
        [
            [
                0.5 * a @ d2K[i][j] @ a
                - a @ dK[i] @ Ki @ dK[j] @ a
                + 0.5 * np.trace(Ki @ dK[i] @ Ki @ dK[j])
                - 0.5 * np.trace(Ki @ d2K[i][j])
                for j in range(p)
            ]
            for i in range(p)
        ]
    )
    assert_allclose(g, g_ref, rtol=1e-9, atol=1e-9 * np.max(np.abs(g_ref)))
    assert_allclose(H, H_ref, rtol=1e-9, atol=1e-9 * np.max(np.abs(H_ref)))


def test_user_bounds_on_variance_or_noise_are_respected():
    rng = np.random.default_rng(5)
    x = np.linspace(0.0, 1.0, 30)
    y = x + 0.01 * np.sin(8 * x) + 1e-3 * rng.standard_normal(30)
    free = fit_gp(x, y)
    assert free.hyperparameters["noise_variance"] < 1e-5
    lo = 1e-4  # far above the free optimum: the fit must sit at this lower bound
    held = fit_gp(x, y, bounds={"noise_variance": (lo, 1e-2)})
    assert held.hyperparameters["noise_variance"] == pytest.approx(lo, rel=1e-9)
    capped = fit_gp(x, y, bounds={"variance": (1e-8, 1e-6)})
    assert capped.hyperparameters["variance"] <= 1e-6 * (1 + 1e-9)
    # and the fits say which bound set which value
    assert free.optimization.at_bounds() == []
    assert held.optimization.at_bounds() == [("noise_variance", "lower")]
    assert capped.optimization.at_bounds() == [("variance", "upper")]


def test_single_threaded_blas_nests_and_restores_the_setting(monkeypatch):
    from threadpoolctl import threadpool_info, threadpool_limits

    from cascal import gp
    from cascal.gp import single_threaded_blas

    monkeypatch.setattr(gp, "_PINNED", [])  # as in a process that pin_blas never ran in

    def blas_threads() -> set[int]:
        return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    if not blas_threads():
        pytest.skip("no BLAS library reports its threads")
    with threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        with single_threaded_blas():
            assert blas_threads() == {1}
            with single_threaded_blas():
                assert blas_threads() == {1}
            assert blas_threads() == {1}  # the outer context still holds the limit
        assert blas_threads() == before


@pytest.mark.parametrize("kernel", ["se", "matern52"])
@pytest.mark.parametrize("with_dense", [False, True])
def test_fit_reuses_the_optimisers_last_factor(monkeypatch, data, dense, kernel, with_dense):
    from cascal.likelihood import Objective

    reused = []
    original = Objective.factor_at

    def spy(self, theta):
        out = original(self, theta)
        reused.append(out is not None)
        return out

    monkeypatch.setattr(Objective, "factor_at", spy)
    x, y = data
    noise = dense if with_dense else None
    fit = fit_gp(x, y, kernel=kernel, noise=noise, n_restarts=1, seed=0)
    assert reused and reused[-1]  # the optimum was the latest evaluation: no new factor
    # the stored state is that of the fitted hyperparameters, as a fresh factorisation
    Kt = fit.kernel(x) + (dense if with_dense else 0.0) + fit.noise_variance * np.eye(N)
    assert fit.jitter == 0.0
    assert_allclose(fit.L @ fit.L.T, Kt, rtol=1e-12, atol=1e-12 * np.max(Kt))
    assert_allclose(np.triu(fit.L, 1), 0.0, rtol=0, atol=0)
    assert_allclose(fit.alpha, np.linalg.solve(Kt, y - x), rtol=1e-8)
    assert fit.log_marginal_likelihood == pytest.approx(dense_lml(y - x, Kt), rel=1e-12)
    assert fit.log_marginal_likelihood == pytest.approx(fit.optimization.value, rel=1e-12)


def test_a_noise_below_the_first_floor_is_found():
    """Rotary readings with 1e-4 degree noise on errors of 0.01 degree about a 360 degree
    constant mean: the noise wants about 1e-12 of the signal variance, below the first
    bound (1e-10), so the fit searches again below it. It must end inside, as high as a fit
    that learns the noise variance directly from bounds far below (no profiling), and
    learn the readings' noise."""
    rng = np.random.default_rng(7)
    x = np.linspace(0.0, 350.0, 60)
    y = x + 0.01 * np.sin(np.deg2rad(2 * x)) + 0.003 * np.cos(np.deg2rad(5 * x))
    y = y + 1e-4 * rng.standard_normal(60)
    fit = fit_gp(x, y, mean="constant")
    hp = fit.hyperparameters
    assert 1e-13 < hp["noise_variance"] / hp["variance"] < 1e-10
    assert fit.optimization.at_bounds() == []
    assert 0.5e-4 < np.sqrt(hp["noise_variance"]) < 2e-4
    free = fit_gp(x, y, mean="constant", bounds={"noise_variance": (1e-12, 1.0)})
    assert fit.log_marginal_likelihood >= free.log_marginal_likelihood - 0.05
    r = y - np.mean(y)
    K = se(x, x, hp["length_scale"], hp["variance"]) + hp["noise_variance"] * np.eye(60)
    assert fit.log_marginal_likelihood == pytest.approx(dense_lml(r, K), abs=0.05)


def test_a_noise_larger_than_the_error_is_learned_beyond_a_ratio_of_ten():
    """100 readings with noise of 1e-3 on a smooth error of 3e-4 (a review's case): the
    optimum has noise / variance = 32.5. With the profiled ratio capped at 10, the fit ended
    0.039 lower, at a length scale 440 times below the spacing that read the noise as
    signal (RMS error 2.9e-4 against the truth). It must reach the optimum of the search
    without profiling (the variances' box given as bounds) and follow the error."""
    rng = np.random.default_rng(2)
    x = np.sort(rng.uniform(0.0, 1.0, 100))
    error = 3e-4 * np.sin(2 * np.pi * x + 2)
    y = x + error + rng.normal(0.0, 1e-3, 100)
    fit = fit_gp(x, y, seed=2)
    hp = fit.hyperparameters
    assert 20 < hp["noise_variance"] / hp["variance"] < 50
    assert 0.1 < hp["length_scale"] < 0.3
    v = float(np.var(y - x))  # the box of the search without profiling, as given bounds
    free = fit_gp(x, y, seed=2, bounds={"variance": (1e-6 * v, 1e4 * v)})
    assert free.optimization.names == ("length_scale", "variance", "noise_variance")
    assert fit.log_marginal_likelihood == pytest.approx(free.log_marginal_likelihood, abs=1e-6)
    K = se(x, x, hp["length_scale"], hp["variance"]) + hp["noise_variance"] * np.eye(100)
    assert fit.log_marginal_likelihood == pytest.approx(dense_lml(y - x, K), rel=1e-10)
    assert np.sqrt(np.mean((fit.predict(x) - x - error) ** 2)) < 1.5e-4


def test_a_noise_variance_that_would_be_ignored_is_refused(data):
    x, y = data
    hp = {"length_scale": L0, "variance": V0, "noise_variance": 1e-4}
    with pytest.raises(InputError, match="learn_noise=True"):
        fit_gp(x, y, noise=1e-8, hyperparameters=hp)
    fit = fit_gp(x, y, noise=1e-8, learn_noise=True, hyperparameters=hp)
    assert fit.noise_variance == 1e-4


def _large_stage(n: int, seed: int):
    """n readings at random positions over [0, 1] whose correction has a smooth part and,
    only near the ends, a ripple of period 0.009 (what neither a spread subset nor one at
    the middle sees), with 1 um noise."""
    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(0.0, 1.0, n))
    edge = (x < 0.25) | (x > 0.75)
    f = 3e-4 * np.sin(7 * x) + edge * 3e-5 * np.sin(2 * np.pi * x / 0.009)
    return x, x + f + 1e-6 * rng.standard_normal(n)


def _screened(obj: Objective, seed: int = 0, bounds=None):
    """The optimum of the search without a table or subsets: five Newton runs from 30
    screened random candidates (what large stages had before)."""
    from cascal.optimize import maximize

    vgh, rng = obj.value_and_derivatives, np.random.default_rng(seed)
    return maximize(obj.value, obj.value_and_grad, obj.bounds(bounds), n_restarts=5, rng=rng,
                    value_grad_hess=vgh)  # fmt: skip


def _a_posterior(x: np.ndarray) -> Dense:
    """A 30-point stage A's posterior at ``x`` as a known noise, as in a cascade."""
    xa = np.linspace(-0.02, 1.02, 30)
    _, U = fit_gp(xa, xa + 2e-4 * np.sin(5 * xa), noise=1e-12).posterior_factor(x)
    return Dense.from_factor(U)


@pytest.mark.parametrize("with_dense", [False, True])
def test_a_large_stage_starts_from_its_subsets_optima(with_dense):
    """600 readings, no table (over 500): the runs start from the subsets' optima ranked on
    all readings (counted as candidates) and end at least as high as five runs from
    screened random candidates; the edge ripple is found (a subset at the middle alone
    misses it: 1009 nats lower on 900 readings); the optimum is a stationary point of the
    full objective (finite differences)."""
    from cascal.surrogate import MAX_OFFGRID

    n = MAX_OFFGRID + 100
    x, y = _large_stage(n, 5)
    dense = _a_posterior(x) if with_dense else None
    fit = fit_gp(x, y, noise=dense)
    opt = fit.optimization
    assert opt.n_candidates > 0 and 1 <= len(opt.starts) <= 5 + 2
    obj = Objective(x, y - x, SquaredExp(), dense, True, profile=dense is None)
    assert opt.value >= _screened(obj).value - 1e-6
    assert fit.kernel.length_scale < 0.01  # the ripple's, not the smooth part's
    assert opt.at_bounds() == []
    assert np.max(np.abs(fd_gradient(obj.value, opt.theta, h=1e-5))) < 1e-2


def test_a_large_stage_whose_middle_equals_the_prior_mean_is_fitted():
    """Readings and reference rounded to 1 um, the error below that in mid-travel: 392 of
    599 corrections are exactly 0, so a subset there has no optimum. It is skipped (the
    fit used to fail) and the fit is as high as the screened search. (One reading of the
    600 drawn repeats another after rounding: with a learned noise such a pair is refused,
    so the stage keeps it once.)"""
    rng = np.random.default_rng(3)
    x = np.unique(np.round(rng.uniform(0, 100, 600), 3))
    y = np.round(x + 2e-3 * ((x - 50) / 50) ** 3, 3)
    assert x.size == 599 and np.sum(y == x) == 392
    fit = fit_gp(x, y)
    obj = Objective(x, y - x, SquaredExp(), None, True, profile=True)
    assert fit.optimization.value >= _screened(obj).value - 1e-6


def test_a_periodic_stage_over_several_turns_finds_the_short_harmonic():
    """700 readings at random angles over 7 turns with a harmonic of order 23: subsets and
    the periodic kernel's table reach the screened search's optimum (the table's rows 0.8
    apart had missed it by 454 nats)."""
    rng = np.random.default_rng(1)
    a = np.sort(rng.uniform(0, 360 * 7, 700))
    f = 0.01 * np.sin(np.deg2rad(a)) + 0.001 * np.sin(np.deg2rad(23 * a))
    y = a + f + 3e-4 * rng.standard_normal(700)
    fit = fit_gp(a, y, kernel="periodic", period=360.0)
    obj = Objective(a, y - a, Periodic(period=360.0), None, True, profile=True)
    assert fit.optimization.value >= _screened(obj).value - 1e-6
    assert fit.kernel.length_scale < 1.0


def test_a_periodic_stage_with_a_harmonic_finer_than_one_turns_readings():
    """600 readings at random angles over 6 turns (100 a turn) with harmonic 60: only the
    turns together resolve it, so the subsets' windows gather readings by phase (windows
    of neighbouring angles, one turn each, ended over 1000 nats low in a review)."""
    rng = np.random.default_rng(722)
    a = np.sort(rng.uniform(0, 360 * 6, 600))
    y = a + 0.01 * np.sin(np.deg2rad(a)) + 0.002 * np.sin(np.deg2rad(60 * a))
    y = y + 2e-4 * rng.standard_normal(600)
    fit = fit_gp(a, y, kernel="periodic", period=360.0)
    obj = Objective(a, y - a, Periodic(period=360.0), None, True, profile=True)
    assert fit.optimization.value >= _screened(obj).value - 1e-6


def test_a_dense_noise_off_the_grid_keeps_the_given_length_scale_bounds():
    """250 readings with a stage-A posterior as the noise and length scales bounded to
    [0.02, 0.2]: the table without the noise keeps those bounds (it had searched the
    default ones and its clipped start ended 97.5 nats lower)."""
    rng = np.random.default_rng(21)
    x = np.sort(rng.uniform(0, 1, 250))
    dense = _a_posterior(x)
    y = x + 3e-4 * np.sin(7 * x) + 3e-5 * np.sin(2 * np.pi * x / 0.08)
    y = y + 2e-5 * np.sin(2 * np.pi * x * 250 / 6) + 1e-6 * rng.standard_normal(250)
    bounds = {"length_scale": (0.02, 0.2)}
    fit = fit_gp(x, y, noise=dense, bounds=bounds)
    assert fit.optimization.n_candidates == 30  # the table's starts, then screened ones
    obj = Objective(x, y - x, SquaredExp(), dense, True)
    assert fit.optimization.value >= _screened(obj, bounds=bounds).value - 1e-6


def test_a_strong_correlated_noise_off_the_grid_can_hold_the_white_noise_in_the_kernel():
    """250 readings whose known noise (smooth, variance 1.2) dwarfs a correction that
    varies faster than the spacing: the optimum reads it as a kernel too short to correlate
    neighbours, a basin that neither the table without the noise nor every screening starts
    in (both the search before the extra run and the screening with seed 0 ended 17.56 nats
    lower). The extra run from a length scale below the spacing reaches it."""
    rng = np.random.default_rng(2)
    n = 250
    x = np.sort((np.arange(n) + rng.uniform(-0.3, 0.3, n)) / n)
    d = np.subtract.outer(x, x)
    known = 1.2 * np.exp(-0.5 * (d / 0.04) ** 2) + 1e-4 * np.eye(n)
    fast = 0.1 * np.exp(-0.5 * (d / 0.0027) ** 2) + 1e-9 * np.eye(n)
    y = x + np.linalg.cholesky(known) @ rng.standard_normal(n)
    y = y + np.linalg.cholesky(fast) @ rng.standard_normal(n) + 1e-2 * rng.standard_normal(n)
    fit = fit_gp(x, y, noise=known)
    obj = Objective(x, y - x, SquaredExp(), Dense(known), True)
    screened = [_screened(obj, seed).value for seed in range(3)]
    # (the learned noise, e^-17.6 of a variance e^-2.3, barely moves the value: 2e-6 flat)
    assert fit.optimization.value >= max(screened) - 1e-5
    assert min(screened) < fit.optimization.value - 1.0  # a basin screening can miss
    assert fit.kernel.length_scale < np.median(np.diff(x))
    assert np.max(np.abs(fd_gradient(obj.value, fit.optimization.theta, h=1e-5))) < 1e-2


def test_a_large_dense_stage_adds_its_windows_short_optima_as_starts(monkeypatch):
    """560 readings with a smooth known noise: the windows' runs from a short length scale
    start extra runs after the search (filling free runs, at least one). With the default
    five runs one of them ends 0.31 higher than the search without them; with one run the
    fit is never lower than without them (a review's case had ended 0.076 lower when they
    competed for the runs)."""
    import cascal.gp as gp

    rng = np.random.default_rng(7)
    n = 560
    x = (np.arange(n) + rng.uniform(-0.35, 0.35, n)) * 10.0 / n
    known = 0.01 * np.exp(-0.5 * (np.subtract.outer(x, x) / 1.5) ** 2) + 1e-8 * np.eye(n)
    y = x + np.linalg.cholesky(known) @ rng.standard_normal(n)
    y = y + 0.02 * np.tanh(x - 5.0) + 5e-4 * rng.standard_normal(n)
    short_start, fits = gp._short_start, {}
    for n_restarts, gain in ((5, 0.3), (1, 0.0)):
        monkeypatch.setattr(gp, "_short_start", short_start)
        fits[n_restarts] = fit = fit_gp(x, y, noise=known, n_restarts=n_restarts).optimization
        monkeypatch.setattr(gp, "_short_start", lambda *args: None)
        without = fit_gp(x, y, noise=known, n_restarts=n_restarts).optimization
        assert fit.value >= without.value + gain - 1e-6
    obj = Objective(x, y - x, SquaredExp(), Dense(known), True)
    assert np.max(np.abs(fd_gradient(obj.value, fits[5].theta, h=1e-5))) < 1e-2


def test_subset_noise_is_the_restricted_noise():
    from cascal.gp import _restrict

    rng = np.random.default_rng(0)
    A = rng.standard_normal((6, 3))
    idx = np.array([0, 2, 5])
    sub = _restrict(Dense(A @ A.T), idx, 6)
    assert_allclose(sub.dense(3), (A @ A.T)[np.ix_(idx, idx)], rtol=1e-14, atol=1e-14)
    v = rng.random(6)
    d = _restrict(Diagonal(v), idx, 6)
    assert d.is_diagonal and np.array_equal(d.diagonal(3), v[idx])


def test_predictions_do_not_depend_on_blas_threads(monkeypatch):
    """A review saw predictions differ in their last bits with two BLAS threads (the
    standard deviation's triangular solve): predict runs single-threaded, as fits do."""
    from threadpoolctl import threadpool_limits

    from cascal import gp

    monkeypatch.setattr(gp, "_PINNED", [])  # as in a process that pin_blas never ran in
    rng = np.random.default_rng(0)
    x = np.sort(rng.uniform(0.0, 1.0, 300))
    y = x + 1e-3 * np.sin(7 * x) + 1e-5 * rng.standard_normal(300)
    fit = fit_gp(x, y, n_restarts=1)
    xs = np.linspace(0.0, 1.0, 20001)
    out = []
    for threads in (1, 2):
        with threadpool_limits(limits=threads, user_api="blas"):
            out.append(fit.predict(xs, return_std=True))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])


def _two_scales(n: int = 20, amp: float = 1e-4):
    """A review's data: readings (n,), targets (n,) of a smooth map plus a correlated part
    of covariance ``A`` (n, n, SE of length scale 0.15) and white noise, in that order."""
    rng = np.random.default_rng(n + int(amp * 1e6))
    x = np.sort(rng.uniform(0, 1, n))
    A = amp**2 * np.exp(-0.5 * (x[:, None] - x[None, :]) ** 2 / 0.15**2)
    y = (
        x
        + 1e-4 * np.sin(8 * x)
        + np.linalg.cholesky(A + 1e-14 * np.eye(n)) @ rng.standard_normal(n)
    )
    return x, y + 1e-5 * rng.standard_normal(n), A


def test_a_sum_of_kernels_also_starts_from_its_parts_fitted_alone():
    """A review's case: on 20 readings of a smooth map plus a short-scale one, SE + Matern
    3/2 from screened random starts ended at 182.434 (181.015 for seed 2), reading the
    short part as noise; a brute-force search found 182.726 in the same bounds. Runs from
    each part fitted alone (the other part short or long) reach it for every seed."""
    from cascal import Matern32

    x, y, _ = _two_scales()
    kernel = SquaredExp(0.2, 1e-8) + Matern32(0.05, 1e-10)
    for seed in range(5):
        fit = fit_gp(x, y, kernel=kernel, seed=seed)
        assert fit.log_marginal_likelihood == pytest.approx(182.726, abs=1e-3)


def _drift_and_ripple(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """40 readings at random positions on [0, 1]: a 59 µm drift and a ripple of 13 periods
    (0.29 of its size), with 0.15 nm of noise."""
    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(0, 1, 40))
    e = np.sin(2 * np.pi * x / 0.966 + 1.0) + 0.3 * x**2
    e += 0.286 * np.sin(2 * np.pi * 13.13 * x + 2.0) * (1 + 0.3 * np.cos(5 * x + 3.0))
    return x, x + e * 5.9e-5 / np.std(e) + 1.5e-10 * rng.standard_normal(40)


@pytest.mark.parametrize("seed", [3, 4, 10, 11])
def test_a_sum_of_kernels_tries_its_parts_in_each_others_roles(seed):
    """A review's cases (Matern 5/2 + 3/2, a drift and a ripple): the search ended 1.3 to
    3.5 nats below a 30-start L-BFGS-B, at the mirror image of its optimum (each part in
    the other's role: seeds 3, 11) or with one part switched off (its variance at the
    floor: seeds 4, 10). Runs from the optimum with the parts exchanged, or with the part
    that is off switched on, reach the reference's optimum."""
    from cascal.optimize import maximize

    x, y = _drift_and_ripple(seed)
    kernel = Matern52() + Matern32()
    fit = fit_gp(x, y, kernel=kernel, seed=0)
    obj = Objective(x, y - x, kernel, None, learn_noise=True)
    ref = maximize(obj.value, obj.value_and_grad, obj.bounds(), n_restarts=30,
                   rng=np.random.default_rng(12345), n_candidates=30)  # fmt: skip
    assert fit.log_marginal_likelihood >= ref.value - 1e-3


def test_a_short_kernel_can_share_the_white_noise_with_a_dense_known_noise():
    """A review's case: 20 readings with a stage-A-like dense known noise; for seed 0 the
    fit ended 0.41 nats low, all noise (the variance at its bound), since the short start
    put the learned noise 10 log units down. A second short start splits it between a
    short kernel and the noise: every seed reaches the best (brute force: 182.468585)."""
    from cascal.noise import Dense

    x, y, A = _two_scales()
    for seed in range(3):
        fit = fit_gp(x, y, kernel="se", noise=Dense(A, atol=1e-20), seed=seed)
        assert fit.log_marginal_likelihood == pytest.approx(182.468585, abs=1e-5)


def _quasi_periodic_turn(n: int, seed: int, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` readings at random angles over a turn (degrees) with an error of size
    ``scale`` (a third harmonic that decays over the turn, a first one) and noise."""
    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(0, 360, n))
    t = np.radians(x)
    e = np.sin(3 * t) * np.exp(-x / 300) + 0.3 * np.cos(t)
    return x, x + scale * e + scale * 0.02 * rng.standard_normal(n)


def test_a_product_of_kernels_reaches_data_of_any_scale():
    """Every variance of a product was bounded by the data's: on micrometre readings
    (variance about 1e-13) two factors could not multiply up to the data's scale, and SE x
    periodic ended at 263.168, below the periodic kernel alone (291.072). A 60-start
    L-BFGS-B in today's bounds (the second factor's variance a number of 1e-6 to 1e4)
    found 291.102205; the fit reaches it for every seed, from each factor fitted alone."""
    from cascal.likelihood import search_bounds

    x, y = _quasi_periodic_turn(20, 1, 1e-6)
    kernel = SquaredExp(50.0, 1.0) * Periodic(1.0, 1.0, period=360.0)
    alone = fit_gp(x, y, kernel=Periodic(1.0, 1.0, period=360.0), seed=0)
    for seed in range(3):
        fit = fit_gp(x, y, kernel=kernel, seed=seed)
        assert fit.log_marginal_likelihood == pytest.approx(291.102205, abs=1e-5)
        assert fit.log_marginal_likelihood >= alone.log_marginal_likelihood
    r = y - x
    v = float(np.var(r))
    b = np.exp(search_bounds(x, r, kernel, None, True, False))
    assert_allclose(b[1], [1e-6 * v, 1e4 * v], rtol=1e-12)  # k1_variance: the unit
    assert_allclose(b[3], [1e-6, 1e4], rtol=1e-12)  # k2_variance: a factor
    nested = SquaredExp(1.0, 1.0) + SquaredExp(1.0, 1.0) * (SquaredExp(1.0, 1.0) + kernel)
    b = np.exp(search_bounds(x, r, nested, None, True, False))
    units = [b[i, 0] / 1e-6 for i in range(1, nested.n_params, 2)]
    assert_allclose(units, [v, v, 1.0, 1.0, 1.0], rtol=1e-12)


def test_a_product_of_two_scaled_kernels_also_starts_from_its_factors_alone():
    """SE x SE on 20 micrometre readings over a turn: with today's bounds, screened starts
    alone ended 27.93 nats below a 60-start L-BFGS-B (291.102266) for one seed of three.
    Starting from each factor fitted alone (the other flat) every seed reaches it."""
    x, y = _quasi_periodic_turn(20, 1, 1e-6)
    kernel = SquaredExp(50.0, 1.0) * SquaredExp(100.0, 1.0)
    for seed in range(3):
        fit = fit_gp(x, y, kernel=kernel, seed=seed)
        assert fit.log_marginal_likelihood == pytest.approx(291.102266, abs=1e-5)


def test_the_public_likelihood_warns_where_it_needed_jitter():
    """A review's case: 50 readings, SE(0.2, 1e-6) and a noise of 1e-22 factorise only
    with jitter 1e-18 (mean diagonal times 1e-12), and the value returned was the jittered
    matrix's with no word of it (136 nats from the exact one). Now a JitterWarning names
    the jitter; the value equals a fit's with those hyperparameters, which records it."""
    from cascal import JitterWarning

    x = np.linspace(0, 1, 50)
    y = x + 1e-3 * np.sin(5 * x)
    k = SquaredExp(0.2, 1e-6)
    with pytest.warns(JitterWarning, match=r"needed jitter 1e-18 on its diagonal") as rec:
        v = log_marginal_likelihood(x, y, kernel=k, noise_variance=1e-22)
    assert len(rec) == 1 and rec[0].filename == __file__
    # a fit given those hyperparameters warns too (it had recorded the jitter in silence)
    with pytest.warns(JitterWarning, match=r"needed jitter 1e-18 .* \(FittedGP.jitter\)") as rec:
        fit = fit_gp(x, y, kernel=k, hyperparameters=dict(k.params, noise_variance=1e-22))
    assert len(rec) == 1 and rec[0].filename == __file__
    assert fit.jitter == pytest.approx(1e-18, rel=1e-12) and v == fit.log_marginal_likelihood
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # none where no jitter is needed, nor for a search
        log_marginal_likelihood(x, y, kernel=k, noise_variance=1e-10)
        fit_gp(x, y, kernel=k, hyperparameters=dict(k.params, noise_variance=1e-10))
        fit_gp(x, y, n_restarts=1)


def test_a_sum_of_kernels_with_a_known_noise_also_starts_from_its_parts():
    """A review's generated set: 200 readings, a dense known noise, SE + SE. From screened
    starts seed 0 ended at 3863.743, 14.0 nats below the review's L-BFGS-B optimum
    (3877.751137, inside the bounds); each part fitted alone with the known noise (the
    other part short or long) gives starts that reach it for every seed."""
    g = np.random.default_rng(166)  # the review's generator, draw for draw
    n = int(g.choice([3, 4, 5, 6, 7, 8, 10, 15, 25, 50, 80, 120, 200]))
    g.integers(8)
    g.integers(4)
    x = np.sort(g.uniform(0, 1, n))
    x = x * 10 ** g.uniform(-4, 1) * g.choice([1, 100, 1e4])
    span = x.max() - x.min()
    amp = 10 ** g.uniform(-6, -2) * span
    f = 0.0
    for _ in range(g.integers(1, 5)):
        f = f + amp * g.normal() * np.sin(g.uniform(1, 60) * x / span + g.uniform(0, 6))
    sd = amp * 10 ** g.uniform(-5, 0)
    y = x + f + sd * g.standard_normal(n)
    if g.random() < 0.2:
        y[g.integers(n)] += 20 * sd + amp
    g.integers(3)
    A = g.standard_normal((n, 5))
    noise = Dense(A @ A.T * sd**2 / 5, atol=1e-300)
    for seed in range(3):
        fit = fit_gp(x, y, kernel=SquaredExp() + SquaredExp(), noise=noise, seed=seed)
        assert fit.log_marginal_likelihood == pytest.approx(3877.7511, abs=1e-3)


def test_a_reading_far_beyond_the_data_gives_the_prior_without_warnings():
    """An API review's case: a reading 1e154 or more from the data made NumPy warn of an
    overflow in the kernel's square (the result was right: the prior)."""
    import warnings

    x = np.linspace(0, 1, 12)
    y = x + 1e-3 * np.sin(6 * x)
    gp = fit_gp(
        x, y, hyperparameters={"length_scale": 0.3, "variance": 1e-6, "noise_variance": 1e-10}
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mean, std = gp.predict(np.array([1e200, -1e300]), return_std=True)
    np.testing.assert_array_equal(mean, [1e200, -1e300])  # the identity mean
    np.testing.assert_allclose(std, np.sqrt(1e-6), rtol=1e-12)


def test_corrections_all_zero_with_a_known_noise_fit_alike_in_any_unit():
    """A review's case: every correction exactly 0 (a reference rounded to the readings'
    digits) with a known noise of sd 0.1 mm. The variances' bounds fell back to 1 in the
    data's unit squared before the known noise was consulted, so u came out 2.2e-5 m, 1e-6
    m and 1e-7 m for the same data in m, mm and um. The known noise now sets the scale."""
    x = np.linspace(0, 1, 20)
    u = []
    for s in (1.0, 1e3, 1e6):
        fit = fit_gp(s * x, s * x, noise=(1e-4 * s) ** 2)
        u.append(fit.predict(s * np.array([0.5, 3.0]), return_std=True)[1] / s)
        assert np.exp(fit.optimization.bounds[1, 1]) / s**2 == pytest.approx(1e-4, rel=1e-12)
    assert_allclose(u[1], u[0], rtol=1e-9)
    assert_allclose(u[2], u[0], rtol=1e-9)


def test_a_periodic_kernel_with_a_constant_predicts_any_turn_as_its_angle():
    """A review: the turn a periodic kernel's far readings are moved into served the plain
    periodic kernel only; with a constant beside it (a sum that repeats whole too), u came
    out 0 a billion turns away."""
    from cascal.kernels import Constant, Periodic

    rng = np.random.default_rng(2)
    x = np.sort(rng.uniform(0.0, 360.0, 30))
    y = x + 1e-3 * np.sin(np.deg2rad(2 * x)) + 1e-5 * rng.standard_normal(30)
    gp = fit_gp(x, y, kernel=Periodic(period=360.0) + Constant(1e-8), n_restarts=1)
    angle = np.array([10.0, 200.0])
    mean, std = gp.predict(angle, return_std=True)
    far = angle + 360.0 * 1e9
    far_mean, far_std = gp.predict(far, return_std=True)
    assert_allclose(far_std, std, rtol=1e-6)
    assert np.all(np.abs((far_mean - far) - (mean - angle)) <= 4.0 * np.spacing(far))
