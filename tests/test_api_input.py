"""The library's boundary: fitted objects keep their own read-only arrays, and odd but
plausible arguments are refused with InputError instead of being ignored or failing deep
inside."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from cascal import Cascade, InputError, fit_gp, log_marginal_likelihood
from cascal.baselines import OffsetTable
from cascal.io.modelfile import _checksum
from cascal.kernels import Periodic, SquaredExp
from cascal.noise import Diagonal

HP = {"length_scale": 0.3, "variance": 1e-4, "noise_variance": 1e-8}


def _rotary_stages() -> list[tuple[np.ndarray, np.ndarray]]:
    """A rotary table's two stages over 0 to 350 degrees (a reference and a device)."""
    rng = np.random.default_rng(0)
    ang = np.sort(rng.uniform(0, 350, 30))
    dev = np.sort(rng.uniform(0, 350, 40))
    return [
        (ang, ang + 0.01 * np.sin(np.radians(ang))),
        (dev, dev + 0.02 * np.cos(np.radians(dev))),
    ]


@pytest.fixture
def data():
    x = np.linspace(0.0, 1.0, 12)
    return x, x + 1e-3 * np.sin(5 * x)


def test_a_fit_keeps_its_own_read_only_arrays(data):
    x, y = data
    fit = fit_gp(x, y, hyperparameters=HP)
    before = fit.predict(np.array([0.5]))
    x += 0.1  # the caller reuses its arrays
    y[:] = 0.0
    np.testing.assert_array_equal(fit.predict(np.array([0.5])), before)
    for name in ("x", "y", "L", "alpha"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(fit, name)[0] = 1.0
    v = np.full(12, 1e-8)
    noise = Diagonal(v)
    v[:] = -1.0
    assert np.all(noise.variance == 1e-8)
    from cascal.noise import Dense  # (a review: its covariance stayed writeable)

    cov = np.eye(3)
    for dense in (Dense(cov), Dense.from_factor(cov), Dense.repaired(cov)):
        with pytest.raises(ValueError, match="read-only"):
            dense.cov[0, 0] = 5.0
    assert cov.flags.writeable and cov[0, 0] == 1.0


def test_a_fitted_cascade_keeps_its_range_when_the_inputs_change():
    t = np.linspace(0.0, 1.0, 20)
    testbed, device = t + 1e-3 * np.sin(4 * t), np.linspace(0.1, 0.9, 15)
    upper = device + 1e-3 * np.cos(3 * device)
    fitted = Cascade([(testbed, t), (device, upper)], "Bayes", n_restarts=1).fit()
    lo, hi = fitted.calibrated_range
    device -= 0.05
    assert fitted.calibrated_range == (lo, hi) == (0.1, 0.9)
    assert fitted.method == "bayes"


def test_log_marginal_likelihood_refuses_what_it_cannot_mean(data):
    x, y = data
    k = SquaredExp(0.3, 1e-4)
    for bad in (-1e-6, float("nan")):
        with pytest.raises(InputError, match="noise_variance: expected a finite number >= 0"):
            log_marginal_likelihood(x, y, kernel=k, noise_variance=bad)
    with pytest.raises(InputError, match="expected a Kernel with its hyperparameters"):
        log_marginal_likelihood(x, y, kernel="se")


def test_hyperparameters_are_checked_by_name(data):
    x, y = data
    with pytest.raises(InputError, match=r"unknown \['noise_var'\]"):
        fit_gp(x, y, hyperparameters={"length_scale": 0.3, "variance": 1e-4, "noise_var": 1e-8})
    with pytest.raises(InputError, match=r"missing \['noise_variance'\]; expected \[.*'noise_v"):
        fit_gp(x, y, hyperparameters={"length_scale": 0.3, "variance": 1e-4})
    with pytest.raises(InputError, match="expected numbers"):
        fit_gp(x, y, hyperparameters={**HP, "variance": None})
    deg = np.linspace(0.0, 350.0, 12)
    wobble = 1e-4 * np.cos(np.arange(12.0) ** 2)  # some noise: a well-conditioned fit
    fit = fit_gp(
        deg, deg + 0.01 * np.sin(np.deg2rad(deg)) + wobble, kernel="periodic", period=360.0
    )
    again = fit_gp(deg, fit.y, kernel="periodic", period=360.0, hyperparameters=fit.hyperparameters)
    np.testing.assert_allclose(again.alpha, fit.alpha, rtol=1e-9, atol=0)
    with pytest.raises(InputError, match=r"period 2\.0 differs from the kernel's 360\.0"):
        fit_gp(deg, fit.y, kernel="periodic", period=360.0,
               hyperparameters={**fit.hyperparameters, "period": 2.0})  # fmt: skip


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"n_restarts": 2.7}, "n_restarts: expected a whole number"),
        ({"bounds": {"length_scale": 0.5}}, "bounds: length_scale: expected (lower, upper)"),
        ({"noise": "abc"}, "noise: expected a number"),
        ({"mean": float("nan")}, "mean: expected a finite number"),
    ],
)
def test_fit_gp_refuses_odd_arguments(data, kwargs, words):
    x, y = data
    with pytest.raises(InputError, match=re.escape(words)):
        fit_gp(x, y, **kwargs)


def test_numpy_numbers_and_complex_values(data):
    x, y = data
    a = fit_gp(x, y, mean=np.float32(0.25), hyperparameters=HP)
    b = fit_gp(x, y, mean=0.25, hyperparameters=HP)
    assert a.mean == b.mean
    with pytest.raises(InputError, match="expected real numbers, got complex"):
        fit_gp(x + 0j, y)


@pytest.mark.parametrize(
    ("args", "kwargs", "words"),
    [
        ((None,), {}, "stages: expected a sequence of (x, y) pairs"),
        (([],), {}, "at least one"),
        ((), {"seed": np.random.default_rng(0)}, "seed: expected a whole number"),
        ((), {"kernel": "bogus"}, "unknown kernel 'bogus'"),
        ((), {"mean": "bogus"}, "unknown mean 'bogus'"),
        ((), {"period": 360.0}, "period: only the periodic kernel"),
        (  # a review: this had said "only the periodic kernel has one" of a periodic one
            (),
            {"period": 1.0, "kernel": SquaredExp() * Periodic(period=1.0)},
            "period: a kernel object carries its own (Periodic(period=...)); give it there",
        ),
        ((), {"method": "gp"}, "method: expected one of"),
    ],
)
def test_a_cascade_refuses_bad_settings_before_fitting(args, kwargs, words):
    t = np.linspace(0.0, 1.0, 10)
    stages = args[0] if args else [(t, t + 1e-3 * t**2)]
    with pytest.raises(InputError, match=re.escape(words)):
        Cascade(stages, **kwargs)


def test_offset_tables_built_by_hand_are_checked():
    with pytest.raises(InputError, match="strictly increasing"):
        OffsetTable(np.array([1.0, 0.0]), np.array([0.1, 0.2]))
    with pytest.raises(InputError, match="the same length"):
        OffsetTable(np.array([0.0, 1.0]), np.array([0.1]))
    table = OffsetTable([0.0, 1.0], [0.1, 0.2])
    np.testing.assert_allclose(table(np.array([0.5])), [0.65])


def test_unwrap_moves_a_rotary_reading_past_the_period_back_beyond_it():
    """Reference readings 2 degrees ahead of the table's, the last ones past 360 and so
    read near 0: unwrapped, they fit exactly what the readings taken beyond 360 give."""
    from cascal.validation import unwrap

    x = np.linspace(0.0, 359.9, 60)
    y = x + 2.0 + 0.01 * np.sin(np.deg2rad(3 * x))
    wrapped = np.where(y >= 360.0, y - 360.0, y)
    assert np.count_nonzero(wrapped != y) >= 1
    np.testing.assert_allclose(unwrap(x, wrapped, 360.0), y, rtol=0, atol=1e-12)
    hp = {"length_scale": 1.0, "variance": 4.0, "noise_variance": 1e-8}
    a = fit_gp(x, unwrap(x, wrapped, 360.0), kernel="periodic", period=360.0, hyperparameters=hp)
    b = fit_gp(x, y, kernel="periodic", period=360.0, hyperparameters=hp)
    xs = np.array([10.0, 180.0, 359.99])
    np.testing.assert_allclose(a.predict(xs), b.predict(xs), rtol=0, atol=1e-9)


def test_importing_cascal_leaves_the_slow_scipy_modules_for_later():
    """scipy.stats and scipy.optimize take 0.24 and 0.13 s to load: they are imported where
    used, so every command starts without them (``cascal correct`` of 10 readings: 0.42 s
    against 0.85 s before this; measured once, not asserted)."""
    import subprocess
    import sys

    code = (
        "import sys, cascal, cascal.cli, cascal.workflow, cascal.study; "
        "print(sorted(m for m in ('scipy.stats', 'scipy.optimize', 'matplotlib') "
        "if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_submodules_are_attributes_after_a_plain_import():
    """A diff review's case: with the package's names loaded on first use, ``cascal.workflow``
    after a plain ``import cascal`` raised AttributeError (it had worked, as the README's
    ``cascal.workflow.screen_stages`` needs)."""
    import subprocess
    import sys

    code = (
        "import cascal\n"
        "print(cascal.workflow.fit_model.__name__, cascal.verification.verify.__name__,\n"
        "      cascal.compensation.CompensationTable.__name__, cascal.gp.fit_gp is cascal.fit_gp)\n"
        "try:\n    cascal.no_such_name\nexcept AttributeError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.splitlines() == [
        "fit_model verify CompensationTable True",
        "module 'cascal' has no attribute 'no_such_name'",
    ]


def test_a_stage_beyond_float64s_scales_is_refused_by_name():
    """A review's cases: data scaled by 1e200 failed inside the fit with a NumericalError
    and some 60 NumPy overflow warnings, data scaled by 1e-200 with a message about a
    length scale never given. The limits are the CSV reader's (values below 1e75, a span
    of positions above 1e-100); a stage at 1e74 still fits."""
    x = np.linspace(0.0, 1.0, 20)
    y = x + 1e-3 * np.sin(5 * x)
    with pytest.raises(InputError, match=r"x: a value of 1e\+200 in magnitude: .*larger unit"):
        fit_gp(1e200 * x, 1e200 * y)
    with pytest.raises(InputError, match=r"y: a value of 1e\+75 in magnitude"):
        fit_gp(x, np.r_[y[:-1], 1e75])
    with pytest.raises(InputError, match=r"x: the positions span only 1e-200: .*smaller unit"):
        fit_gp(1e-200 * x, 1e-200 * y)
    with pytest.raises(InputError, match=r"testbed x: a value of 1e\+200"):
        Cascade([(1e200 * x, 1e200 * y)]).fit()
    y = y + 1e-5 * np.random.default_rng(0).standard_normal(20)  # an optimum off the floor
    big, small = fit_gp(1e74 * x, 1e74 * y), fit_gp(x, y)
    for name, power in (("length_scale", 1), ("variance", 2), ("noise_variance", 2)):
        assert big.hyperparameters[name] == pytest.approx(
            1e74**power * small.hyperparameters[name], rel=1e-5
        )


@pytest.mark.parametrize("method", ["bayes", "lut"])
def test_one_reading_as_a_number_gives_numbers_as_the_vector_path_does(method):
    from cascal.simulation import simulate_trial

    trial = simulate_trial(np.random.default_rng(3))
    fitted = Cascade([trial.d2, trial.d1], method).fit()
    r = 0.4321
    vector = fitted.correct(np.array([r]))
    for one in (r, np.float64(r), np.array(r)):
        got = fitted.correct(one)
        assert np.ndim(got) == 0 and got == vector[0]
    assert fitted.correct(np.float32(r)) == fitted.correct(np.array([np.float32(r)]))[0]
    with pytest.raises(InputError, match="readings: expected numbers, got str"):
        fitted.correct("0.5")
    with pytest.raises(InputError, match="readings: expected finite values, got nan"):
        fitted.correct(float("nan"))
    if method == "lut":
        return
    mean, std = fitted.correct(r, return_std=True)
    mv, sv = fitted.correct([r], return_std=True)
    assert (mean, std) == (mv[0], sv[0])
    m, var = fitted.device.predict(r, return_cov=True)
    assert np.ndim(var) == 0 and m == mv[0]
    assert var == pytest.approx(std**2, rel=1e-9)


def test_the_workflows_correct_takes_one_reading_as_a_number():
    from cascal.workflow import correct, fit_model
    from utils import demo_stages

    model = fit_model(demo_stages(), n_restarts=1)
    lo, hi = model.calibrated_range
    for r in ((lo + hi) / 2, hi + 1.0):  # inside, and outside (flagged)
        one, many = correct(model, r), correct(model, [r])
        fields = (one.reading, one.corrected, one.u, one.out_of_range, one.U)
        assert all(np.ndim(f) == 0 for f in fields)
        assert fields == (
            many.reading[0],
            many.corrected[0],
            many.u[0],
            many.out_of_range[0],
            many.U[0],
        )


@pytest.mark.parametrize("noise", [None, 0.0, 1e-150])
def test_corrections_too_small_to_learn_from_are_refused_by_name(noise):
    """Corrections of 1e-170 failed with a message about near-duplicates in the data, and
    noiseless ones of 1e-74 on a NaN length scale; 2e-60 (above the limit) fits as 1 does,
    with hyperparameters given any scale fits."""
    x = np.linspace(0.0, 1.0, 20)
    c = np.sin(5 * x)
    for scale in (1e-170, 1e-74):
        with pytest.raises(InputError, match=r"y: the corrections .* at most .*smaller unit"):
            fit_gp(x, scale * c, noise=noise, mean="zero")
    assert fit_gp(x, 1e-170 * c, mean="zero", hyperparameters=HP | {"variance": 1e-300})
    tiny, unit = fit_gp(x, 2e-60 * c, mean="zero", noise=noise), fit_gp(x, c, mean="zero")
    assert tiny.predict(0.3) / 2e-60 == pytest.approx(unit.predict(0.3), rel=1e-4)


def test_a_periodic_kernel_object_needs_its_period_and_its_model_keeps_it(tmp_path):
    """A review's cases: Periodic() took 2 pi on data in degrees; a cascade with a Periodic
    object saved a model with no period, whose file was refused on loading; a NumPy
    integer seed stopped save_model with a raw TypeError."""
    from cascal import CalibrationModel, load_model, save_model

    with pytest.raises(InputError, match="Periodic: give its period"):
        Periodic(30.0, 1e-4)
    stages = _rotary_stages()
    cascade = Cascade(
        stages, kernel=Periodic(30.0, 1e-4, period=360.0), seed=np.int64(3), n_restarts=1
    )
    fitted = cascade.fit()
    model = CalibrationModel.from_cascade(cascade, fitted, unit="deg")
    assert model.periodic and model.period == 360.0 and type(model.seed) is int
    save_model(tmp_path / "m.json", model)
    back = load_model(tmp_path / "m.json")
    assert back.period == 360.0 and back.fitted.correct(370.0) == fitted.correct(370.0)


def test_matrix_results_take_one_number_as_one_position(data):
    x, y = data
    fit = fit_gp(x, y, hyperparameters=HP)
    post = fit.posterior(0.5)  # (the review found a 0-d Posterior whose std failed)
    assert post.mean.shape == (1,) and post.cov.shape == (1, 1)
    np.testing.assert_allclose(post.std, fit.predict([0.5], return_std=True)[1], rtol=1e-9)
    assert fit.posterior_factor(0.5)[1].shape[0] == 1
    np.testing.assert_array_equal(
        fit.cross_covariance(0.5, [0.5]), fit.cross_covariance([0.5], [0.5])
    )
    with pytest.raises(InputError, match="x: expected numbers, got NoneType"):
        fit.predict(None)


def test_array_level_verify_and_other_entry_points_refuse_what_they_cannot_mean():
    """A review's cases: NaN statistics from NaN references, negative uncertainties taken,
    raw TypeErrors and IndexErrors, and k=2.7 planned as 2 measurements."""
    from cascal.planning import plan_reference
    from cascal.simulation import simulate_trial
    from cascal.verification import verify

    r = np.linspace(0.0, 1.0, 5)
    with pytest.raises(InputError, match="reference must be finite, got nan at index 4"):
        verify(r, np.r_[r[:-1], np.nan], r, np.ones(5))
    with pytest.raises(InputError, match="u_calibration must be finite and >= 0"):
        verify(r, r, r, -np.ones(5))
    with pytest.raises(InputError, match="u_calibration must be finite and >= 0"):
        verify(r, r, r, np.r_[np.ones(4), np.inf])
    with pytest.raises(InputError, match="verify: expected numbers"):
        verify(["a"], [1.0], [1.0], [0.1])
    with pytest.raises(InputError, match="u_reading must be a number, got '1e-6'"):
        verify(r, r, r, np.ones(5), u_reading="1e-6")
    assert verify(r, r, r, np.full(5, np.nan)).summary()["rms_after"] == 0.0  # no u: a table
    with pytest.raises(InputError, match="names: expected two names"):
        fit_gp(r, r + 1e-3 * r**2, names="x")
    with pytest.raises(InputError, match=r"rng: expected a numpy\.random\.Generator"):
        simulate_trial(0)
    trial = simulate_trial(np.random.default_rng(0))
    testbed = fit_gp(*trial.d2, hyperparameters=HP)
    for k in ("x", None, 2.7):
        with pytest.raises(InputError, match="k: expected a whole number of measurements"):
            plan_reference(testbed, np.linspace(0.0, 0.35, 20), k, where=trial.d1[1])


def test_one_number_and_text_as_readings():
    """A review of the scalar readings: True had been read as 1.0 while np.bool_ and a
    Decimal met a message about shapes, and text in a list was read as numbers."""
    from decimal import Decimal

    from cascal.validation import as_readings

    assert as_readings(Decimal("0.25"), "r")[0].tolist() == [0.25]
    assert as_readings(np.float32(0.5), "r") == (np.array([0.5]), True)
    for bad in (True, np.bool_(True)):
        with pytest.raises(InputError, match="r: expected numbers, got a bool"):
            as_readings(bad, "r")
    for text in (["0.5", "1.0"], np.array(["0.5"]), ("0.5",), np.array(["0.5"], dtype=object),
                 np.array("0.5")):  # fmt: skip
        with pytest.raises(InputError, match="r: expected numbers, got text"):
            as_readings(text, "r")
    with pytest.raises(InputError, match="r: expected numbers, got object"):
        as_readings(object(), "r")


def test_text_or_bools_among_numbers_are_refused():
    """A leftover of the scalar readings' review: a list mixing numbers and text, and a
    list or array of bools, had been read as numbers (``"1.0"`` as 1.0, ``True`` as 1.0)."""
    from cascal.validation import as_positions

    mixed = ([0.5, "1.0"], (0.5, b"1.0"), np.array([0.5, "1.0"], dtype=object))
    for text in mixed:
        with pytest.raises(InputError, match="r: expected numbers, got text"):
            as_positions(text, "r")
    for flags in ([0.5, True], [True, False], np.array([True, False]), [np.bool_(False), 1.0]):
        with pytest.raises(InputError, match="r: expected numbers, got bools"):
            as_positions(flags, "r")
    assert as_positions([0.5, np.float32(1.0), 2], "r").tolist() == [0.5, 1.0, 2.0]

    class Column:  # an array-like, as a pandas Series is: its dtype tells
        def __init__(self, values):
            self.values = np.asarray(values)

        def __array__(self, dtype=None, copy=None):
            return self.values if dtype is None else self.values.astype(dtype)

    with pytest.raises(InputError, match="r: expected numbers, got bools"):
        as_positions(Column([True, False]), "r")
    with pytest.raises(InputError, match="r: expected numbers, got text"):
        as_positions(Column(np.array(["0.5", "1.0"], dtype=object)), "r")
    assert as_positions(Column([0.5, 1.5]), "r").tolist() == [0.5, 1.5]
    # a diff review's cases: a 0-d bool array as one reading, a deque and a memoryview
    import collections

    from cascal.validation import as_readings

    with pytest.raises(InputError, match=r"r: expected numbers, got a bool \(array\(True\)\)"):
        as_readings(np.array(True), "r")
    for flags in (collections.deque([True, False]), memoryview(np.array([True, False]))):
        with pytest.raises(InputError, match="r: expected numbers, got bools"):
            as_readings(flags, "r")
    assert as_readings(collections.deque([0.5, 1.0]), "r")[0].tolist() == [0.5, 1.0]
    fitted = fit_gp(np.linspace(0.0, 1.0, 8), np.linspace(0.0, 1.0, 8) + 1e-3, noise=1e-8)
    with pytest.raises(InputError, match="x: expected numbers, got bools"):
        fitted.predict([0.5, True])


def test_from_cascade_writes_the_period_its_method_and_kernel_have(tmp_path):
    """A review of the period's fix: a lut cascade given a periodic kernel wrote a period,
    which the loader refused (0.4.10's such files too); a Periodic with a Constant, which
    repeats whole, wrote none, so other turns were flagged."""
    from cascal import CalibrationModel, Constant, load_model, save_model

    stages = _rotary_stages()
    lut = Cascade(stages, "lut", kernel="periodic", period=360.0)
    model = CalibrationModel.from_cascade(lut, lut.fit(), unit="deg")
    assert model.period is None
    save_model(tmp_path / "lut.json", model)
    assert load_model(tmp_path / "lut.json").period is None
    doc = json.loads((tmp_path / "lut.json").read_text())  # as 0.4.10 wrote it
    doc["period"] = 360.0
    body = {k: v for k, v in doc.items() if k != "checksum"}
    doc["checksum"]["value"] = _checksum(body)
    (tmp_path / "old.json").write_text(json.dumps(doc))
    assert load_model(tmp_path / "old.json").period is None  # (a review: other turns in range)
    kernel = Periodic(30.0, 1e-4, period=360.0) + Constant(1e-6)
    gp = Cascade(stages, kernel=kernel, n_restarts=1)
    model = CalibrationModel.from_cascade(gp, gp.fit(), unit="deg")
    assert model.period == 360.0
    save_model(tmp_path / "sum.json", model)
    assert load_model(tmp_path / "sum.json").period == 360.0


def test_the_remaining_entry_points_refuse_odd_arguments_by_name(data):
    """An API review's cases that had raised Python's or NumPy's own errors, or named what
    the user never gave."""
    from cascal.noise import Dense
    from cascal.screening import screen

    x, y = data
    fit = fit_gp(x, y, hyperparameters=HP)
    with pytest.raises(InputError, match=r"level: expected a probability"):
        screen(fit, level="0.01")
    table = Cascade([(x, y)], "lut").fit().models[0]
    with pytest.raises(InputError, match="screen: expected a fitted GP stage, got OffsetTable"):
        screen(table)
    with pytest.raises(InputError, match="dense noise: expected a square"):
        Dense([[1.0, 2.0], [3.0]])
    with pytest.raises(InputError, match=r"a number is Diagonal\(number\)"):
        Diagonal(1.0) + 1.0
    with pytest.raises(
        InputError, match=r"bounds: length_scale: expected 0 < lower <= upper, got \(1\.0, 0\.1\)"
    ):
        fit_gp(x, y, bounds={"length_scale": (1, 0.1)})
    with pytest.raises(InputError, match="seed: expected a whole number of seeds >= 0"):
        Cascade([(x, y)], seed=np.random.default_rng(0))


def test_a_ragged_reading_list_is_named_not_numpys_error():
    from cascal.validation import as_readings

    with pytest.raises(InputError, match="r: expected numbers, got list"):
        as_readings([[1.0], [1.0, 2.0]], "r")
