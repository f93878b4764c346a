"""Planning reference measurements: the greedy choice against brute force, the uncertainties
it reports against refitted GPs and sklearn, and its bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cascal import Cascade, fit_gp
from cascal.errors import InputError
from cascal.planning import (
    NOISE_FLOOR,
    LowerStage,
    default_noise_variance,
    lower_variance_after,
    plan_reference,
    variance_after,
)
from cascal.simulation import simulate_trial
from utils import assert_allclose, se


@pytest.fixture(scope="module")
def cascade():
    """A paper trial (reference points with gaps at the ends and centre) fitted with bayes."""
    trial = simulate_trial(np.random.default_rng(5))
    return trial, Cascade([trial.d2, trial.d1], "bayes").fit()


def _hp(gp) -> dict[str, float]:
    return {k: v for k, v in gp.hyperparameters.items()}


def _refit_testbed(testbed, positions):
    """Stage 0 refitted from scratch at its hyperparameters with the extra points (targets
    at the posterior mean: a variance does not depend on them)."""
    u, back = np.unique(positions, return_inverse=True)  # repeats read the same value
    x = np.concatenate([testbed.x, positions])
    y = np.concatenate([testbed.y, testbed.predict(u)[back]])
    return fit_gp(x, y, kernel="se", hyperparameters=_hp(testbed))


def test_testbed_target_matches_textbook_variance(cascade):
    """Every step's RMS and largest u equal the posterior variance written out by hand
    (np.linalg.solve on the enlarged covariance) with the points chosen so far."""
    _, fitted = cascade
    tb = fitted.models[0]
    where = np.linspace(0.0, 1.0, 51)
    cand = np.linspace(0.05, 0.95, 91)
    calls = []
    plan = plan_reference(tb, cand, 6, where=where, progress=lambda i, k: calls.append((i, k)))
    assert calls == [(i, 6) for i in range(1, 7)]
    hp = tb.hyperparameters
    s2 = hp["noise_variance"]
    assert plan.noise_variance == s2 == default_noise_variance(tb)
    for i in range(plan.positions.size + 1):
        xa = np.concatenate([tb.x, plan.positions[:i]])
        Kt = se(xa, xa, hp["length_scale"], hp["variance"]) + s2 * np.eye(xa.size)
        Ks = se(where, xa, hp["length_scale"], hp["variance"])
        var = hp["variance"] - np.einsum("ij,ji->i", Ks, np.linalg.solve(Kt, Ks.T))
        assert_allclose(plan.u_rms[i], np.sqrt(np.mean(var)), rtol=1e-7)
        assert_allclose(plan.u_max[i], np.sqrt(np.max(var)), rtol=1e-7)
    assert_allclose(plan.u_after, np.sqrt(var), rtol=1e-7)
    assert_allclose(plan.u_before, tb.predict(where, return_std=True)[1], rtol=1e-9)
    assert np.all(np.diff(plan.u_rms) < 0)  # every measurement helps


def test_testbed_variance_after_matches_sklearn(cascade):
    """The enlarged posterior's standard deviation equals sklearn's at the same
    hyperparameters with the points added."""
    pytest.importorskip("sklearn")
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    _, fitted = cascade
    tb = fitted.models[0]
    hp = tb.hyperparameters
    pos = np.array([0.02, 0.5, 0.5, 0.97])
    xs = np.linspace(-0.1, 1.1, 37)
    xa = np.concatenate([tb.x, pos])
    kern = ConstantKernel(hp["variance"], "fixed") * RBF(hp["length_scale"], "fixed")
    peer = GaussianProcessRegressor(kern, alpha=hp["noise_variance"], optimizer=None)
    peer.fit(xa[:, None], np.zeros(xa.size))
    _, std = peer.predict(xs[:, None], return_std=True)
    ours = variance_after(tb, xs, pos, hp["noise_variance"])
    assert_allclose(np.sqrt(ours), std, rtol=1e-6)


def test_first_choice_is_the_best_single_measurement(cascade):
    """The first proposal is the candidate whose measurement alone, refitted from scratch,
    leaves the smallest summed variance at the target."""
    _, fitted = cascade
    tb = fitted.models[0]
    where = np.linspace(0.0, 1.0, 41)
    cand = np.linspace(0.0, 1.0, 61)
    plan = plan_reference(tb, cand, 1, where=where)
    totals = []
    for c in cand:
        gp = _refit_testbed(tb, np.array([c]))
        totals.append(np.sum(gp.predict(where, return_std=True)[1] ** 2))
    assert plan.positions[0] == cand[int(np.argmin(totals))]
    assert_allclose(plan.u_rms[1], np.sqrt(min(totals) / where.size), rtol=1e-7)


def _lower(fitted, trial, n=41):
    dev = fitted.models[1]
    return LowerStage(dev, trial.d1[1], np.linspace(dev.x.min(), dev.x.max(), n))


def _refit_lower(fitted, trial, positions, where):
    """The device stage refitted from scratch at its hyperparameters, with stage 0's
    covariance at its test-bed readings recomputed from the refitted stage 0."""
    tb2 = _refit_testbed(fitted.models[0], positions)
    _, cov = tb2.predict(trial.d1[1], return_cov=True)
    dev = fitted.models[1]
    gp = fit_gp(dev.x, dev.y, kernel="se", noise=cov, hyperparameters=_hp(dev))
    return gp.predict(where, return_std=True)[1]


def test_device_target_matches_refitted_cascade(cascade):
    """With the device stage as target, the reported u equals a device GP refitted on stage
    0's new covariance, after each step; the first choice is the brute-force best."""
    trial, fitted = cascade
    low = _lower(fitted, trial)
    cand = np.linspace(0.0, 1.0, 41)
    plan = plan_reference(fitted.models[0], cand, 4, lower=low)
    with pytest.raises(InputError, match=r"lower: expected a cascal.planning.LowerStage\(gp, "):
        plan_reference(fitted.models[0], cand, 4, lower=fitted.models[1])  # (a README review)
    # (u is a square root of k - v^T v: the planner's BLAS threads and predict's single one
    # sum in different orders, 1.6e-10 apart at a point where the difference cancels)
    u_before = fitted.models[1].predict(low.where, return_std=True)[1]
    assert_allclose(plan.u_before, u_before, rtol=1e-9)
    for i in range(plan.positions.size + 1):
        u = _refit_lower(fitted, trial, plan.positions[:i], low.where)
        assert_allclose(plan.u_rms[i], np.sqrt(np.mean(u**2)), rtol=1e-6)
        assert_allclose(plan.u_max[i], np.max(u), rtol=1e-6)
    assert_allclose(plan.u_after, u, rtol=1e-6)
    totals = [np.sum(_refit_lower(fitted, trial, np.array([c]), low.where) ** 2) for c in cand]
    assert plan.positions[0] == cand[int(np.argmin(totals))]


def test_lower_variance_after_nothing_is_the_device_fit(cascade):
    trial, fitted = cascade
    low = _lower(fitted, trial)
    u2 = lower_variance_after(low, fitted.models[0], np.empty(0), 1e-9)
    assert_allclose(np.sqrt(u2), fitted.models[1].predict(low.where, return_std=True)[1], rtol=1e-8)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    k=st.integers(1, 5),
    noise=st.floats(1e-8, 1e-2),
)
def test_greedy_steps_match_refits_on_random_data(seed, k, noise):
    """On random data and hyperparameters, each step's u equals a from-scratch
    computation, u never rises, and the target is lowered nowhere less than nothing."""
    g = np.random.default_rng(seed)
    x = np.sort(g.uniform(0.0, 1.0, 12))
    y = x + 1e-3 * g.normal(size=12)
    hp = {"length_scale": g.uniform(0.05, 0.5), "variance": 1e-6, "noise_variance": 1e-8}
    tb = fit_gp(x, y, kernel="se", hyperparameters=hp)
    where = np.linspace(-0.2, 1.2, 15)
    cand = g.uniform(-0.3, 1.3, 20)
    plan = plan_reference(tb, cand, k, where=where, noise_variance=noise * 1e-6)
    assert np.all(np.isin(plan.positions, cand))
    for i in range(k + 1):
        var = variance_after(tb, where, plan.positions[:i], noise * 1e-6)
        assert_allclose(plan.u_rms[i], np.sqrt(np.mean(var)), rtol=1e-6, atol=1e-12)
    assert np.all(np.diff(plan.u_rms) <= 1e-12)
    assert np.all(plan.u_after <= plan.u_before * (1 + 1e-9) + 1e-15)


def test_repeats_average_the_noise_down():
    """With one candidate the plan measures there k times: the variance there falls as
    for k averaged readings of a point the data say nothing about (short length scale)."""
    x = np.array([0.0, 1.0, 2.0])
    tb = fit_gp(
        x,
        x,
        kernel="se",
        hyperparameters={"length_scale": 1e-3, "variance": 1.0, "noise_variance": 0.1},
    )
    plan = plan_reference(tb, [0.5], 3, where=[0.5], noise_variance=0.25)
    assert np.all(plan.positions == 0.5)
    # prior variance 1, k readings of variance 0.25: posterior 1 / (1 + 4 k)
    assert_allclose(plan.u_rms**2, 1.0 / (1.0 + 4.0 * np.arange(4)), rtol=1e-9)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"k": 0}, "1 to 1000"),
        ({"k": 1001}, "1 to 1000"),
        ({"candidates": []}, "at least one"),
        ({"candidates": [0.1, np.nan]}, "candidates"),
        ({"where": None}, "not both"),
        ({"lower": "both"}, "not both"),
        ({"noise_variance": -1.0}, "noise_variance"),
        ({"noise_variance": np.inf}, "noise_variance"),
    ],
)
def test_bad_input(cascade, kwargs, match):
    trial, fitted = cascade
    args = {"candidates": [0.2, 0.5], "k": 2, "where": [0.3]}
    args.update(kwargs)
    if args.get("lower") == "both":
        args["lower"] = _lower(fitted, trial)
    with pytest.raises(InputError, match=match):
        plan_reference(fitted.models[0], args.pop("candidates"), args.pop("k"), **args)


def test_a_noiseless_measurement_is_floored_and_stays_consistent(cascade):
    """A new measurement's variance is at least NOISE_FLOOR times the prior variance: with
    none given, 40 steps still agree with the from-scratch recomputation and never rise."""
    trial, fitted = cascade
    tb = fitted.models[0]
    where = np.linspace(0.0, 1.0, 41)
    plan = plan_reference(tb, np.linspace(0.0, 1.0, 51), 40, where=where, noise_variance=0.0)
    assert plan.noise_variance == NOISE_FLOOR * tb.kernel.params["variance"]
    assert np.all(np.diff(plan.u_rms) <= 0)
    assert_allclose(plan.u_rms[-1], np.sqrt(np.mean(plan.u_after**2)), rtol=1e-6)
    low = _lower(fitted, trial)
    plan = plan_reference(tb, np.linspace(0.0, 1.0, 51), 10, lower=low, noise_variance=0.0)
    assert_allclose(plan.u_rms[-1], np.sqrt(np.mean(plan.u_after**2)), rtol=1e-6)


@pytest.fixture(scope="module")
def chain():
    """A three-stage bayes model (the linear demo's stages and a device below them) and
    the chain below its stage 0, the device's uncertainty at 31 readings its target."""
    from cascal.workflow import fit_model
    from utils import three_stages

    stages = three_stages()
    model = fit_model(stages, n_restarts=1)
    _, g1, g2 = model.fitted.models
    where = np.linspace(stages[2].x.min(), stages[2].x.max(), 31)
    low = [LowerStage(g1, stages[1].y, stages[2].y), LowerStage(g2, stages[2].y, where)]
    return stages, model, low


def _refit_chain(stages, model, positions, s2):
    """The device's u at the chain's target refitted from scratch through the public API:
    stage 0 with the extra points (variance ``s2`` each: its learned noise, and the rest as
    known noise), then each stage at its hyperparameters on the covariance the stage above
    predicts at its upper readings."""
    g0, g1, g2 = model.fitted.models
    u, back = np.unique(positions, return_inverse=True)
    x = np.concatenate([g0.x, positions])
    y = np.concatenate([g0.y, g0.predict(u)[back]])
    extra = np.full(positions.size, s2 - g0.hyperparameters["noise_variance"])
    known = np.concatenate([stages[0].noise, extra])
    above = fit_gp(x, y, kernel="se", noise=known, hyperparameters=_hp(g0), learn_noise=True)
    for stage, gp in zip(stages[1:], (g1, g2), strict=True):
        _, cov = above.predict(stage.y, return_cov=True)
        above = fit_gp(gp.x, gp.y, kernel="se", noise=cov, hyperparameters=_hp(gp))
    return above.predict(np.linspace(stages[2].x.min(), stages[2].x.max(), 31), return_std=True)[1]


def test_a_chain_target_matches_the_refitted_chain(chain):
    """With the device of a three-stage chain as target, every step's u and the u after the
    whole plan equal the chain refitted from scratch with the points chosen so far (stage 0's
    covariance carried down two stages); the first choice is the brute-force best."""
    stages, model, low = chain
    g0 = model.fitted.models[0]
    assert stages[0].noise is not None and np.any(stages[0].noise > 0)  # (known noise too)
    # (off stage 0's readings: a refit refuses a position twice with two targets)
    cand = np.linspace(stages[0].x.min() + 1e-3, stages[0].x.max() - 1e-3, 25)
    assert not np.isin(cand, g0.x).any()
    plan = plan_reference(g0, cand, 4, lower=low)
    s2 = plan.noise_variance
    u_before = model.fitted.models[2].predict(low[1].where, return_std=True)[1]
    assert_allclose(plan.u_before, u_before, rtol=1e-9)
    # (the refits' noise is the stage above's predicted covariance, which matches the
    # fitted model's to 1e-7 of itself: the models' factors carry their own round-off)
    for i in range(plan.positions.size + 1):
        u = _refit_chain(stages, model, plan.positions[:i], s2)
        assert_allclose(plan.u_rms[i], np.sqrt(np.mean(u**2)), rtol=2e-6)
        assert_allclose(plan.u_max[i], np.max(u), rtol=2e-6)
    assert_allclose(plan.u_after, u, rtol=5e-6)
    assert np.all(np.diff(plan.u_rms) < 0)
    totals = [np.sum(_refit_chain(stages, model, np.array([c]), s2) ** 2) for c in cand]
    assert plan.positions[0] == cand[int(np.argmin(totals))]
    # stage 1 as the target (the plan before chains) lowers the device's u less
    one = plan_reference(g0, cand, 4, lower=LowerStage(low[0].gp, low[0].upper, low[0].where))
    u_one = _refit_chain(stages, model, one.positions, s2)
    assert np.mean(u_one**2) >= np.mean(u**2) * (1 - 1e-9)


def test_lower_variance_after_nothing_is_the_last_stage_of_a_chain(chain):
    _, model, low = chain
    var = lower_variance_after(low, model.fitted.models[0], np.empty(0), 1e-9)
    u = model.fitted.models[2].predict(low[1].where, return_std=True)[1]
    assert_allclose(np.sqrt(var), u, rtol=1e-9)


def test_a_chain_is_checked(chain):
    stages, model, low = chain
    g0 = model.fitted.models[0]
    from dataclasses import replace

    bad = [replace(low[0], where=stages[2].y[:-1]), low[1]]
    with pytest.raises(InputError, match="stage 1's where must be the upper readings of stage 2"):
        plan_reference(g0, [0.2, 0.5], 2, lower=bad)
    with pytest.raises(InputError, match=r"or a list of them from stage 1 down, got FittedGP"):
        plan_reference(g0, [0.2, 0.5], 2, lower=[low[0], model.fitted.models[2]])


def test_the_plan_of_a_three_stage_model_targets_the_device(chain):
    """A report review's case: a three-stage model's plan had lowered stage 1's uncertainty,
    labelled so. It now lowers the device's over its calibrated range, the chain's plan."""
    from cascal.workflow import fit_model, plan_measurements

    stages, model, _ = chain
    mp = plan_measurements(model, 2)
    start = "stage 2 (testbed_device.csv)'s uncertainty over its calibrated range ["
    assert mp.target.startswith(start), mp.target
    assert mp.target.endswith("(the device; the test bed's covariance passes down through stage 1)")
    assert_allclose(mp.plan.where, np.linspace(stages[2].x.min(), stages[2].x.max(), 201))
    assert_allclose(
        mp.plan.u_before, model.fitted.models[2].predict(mp.plan.where, return_std=True)[1]
    )
    two = plan_measurements(fit_model(stages[:2], n_restarts=1), 2).target
    assert two.startswith("stage 1 (testbed_device.csv)'s uncertainty over its calibrated range [")
    assert "the device;" not in two
