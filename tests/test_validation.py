"""Public entry points refuse bad input with InputError naming what was expected and got."""

from __future__ import annotations

import numpy as np
import pytest

from cascal import (
    Cascade,
    CascalError,
    InputError,
    JitterWarning,
    SquaredExp,
    fit_gp,
    log_marginal_likelihood,
)
from cascal.cascade import Stage

X = np.linspace(0.0, 1.0, 6)
Y = X + 0.01 * np.sin(5 * X)
HP = {"length_scale": 0.3, "variance": 1e-4, "noise_variance": 1e-6}


def _fit(x, y, **kw):
    return fit_gp(x, y, hyperparameters=HP, **kw)


def _lml(x, y, **kw):
    return log_marginal_likelihood(x, y, kernel=SquaredExp(0.3, 1e-4), noise_variance=1e-6, **kw)


def _cascade(x, y, **kw):
    # the bad pair is the device stage, below a valid test-bed stage
    return Cascade([(X, Y), (x, y)], **kw)


def _cascade_top(x, y, **kw):
    return Cascade([(x, y), (X, Y)], **kw)


ENTRY_POINTS = {"fit_gp": _fit, "lml": _lml, "cascade": _cascade, "cascade_top": _cascade_top}


def _with(a, i, v):
    a = a.copy()
    a[i] = v
    return a


BAD = {
    # case: (x, y, message pattern)
    "nan_x": (_with(X, 2, np.nan), Y, r"x: expected finite values, got nan at index 2"),
    "nan_y": (X, _with(Y, 4, np.nan), r"y: expected finite values, got nan at index 4"),
    "inf_x": (_with(X, 0, np.inf), Y, r"x: expected finite values, got inf at index 0"),
    "minus_inf_y": (X, _with(Y, 1, -np.inf), r"y: expected finite values, got -inf at index 1"),
    "lengths": (X, Y[:-1], r"expected the same length, got 6 and 5"),
    "too_few": (X[:2], Y[:2], r"x: expected at least 3 points, got 2"),
    "two_d": (np.column_stack([X, X]), Y, r"x: expected shape \(n,\), got \(6, 2\)"),
    "duplicate": (
        _with(X, 3, X[1]),
        Y,
        r"x: duplicated position 0.2 at indices 1 and 3 "
        r"with contradicting (\w+ )?y 0\.2084.* and 0\.6014",
    ),
    "text": (["a", "b", "c"], [1.0, 2.0, 3.0], r"x: expected numbers, got text"),
}


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_data_refused(entry, case):
    x, y, pattern = BAD[case]
    with pytest.raises(InputError, match=pattern) as info:
        ENTRY_POINTS[entry](x, y)
    assert isinstance(info.value, CascalError)
    assert isinstance(info.value, ValueError)  # what sklearn users catch


def test_cascade_names_the_stage():
    with pytest.raises(InputError, match=r"^device x: expected finite values, got nan"):
        _cascade(_with(X, 2, np.nan), Y)
    with pytest.raises(InputError, match=r"^testbed y: expected at least|^testbed x: expected"):
        _cascade_top(X[:2], Y[:2])
    with pytest.raises(InputError, match=r"^encoder x: expected finite values, got inf"):
        Stage(_with(X, 1, np.inf), Y, name="encoder")  # (refused as it is made)
    with pytest.raises(InputError, match=r"^encoder: expected x and y of one length, got 6 and 5"):
        Stage(X, Y[:5], name="encoder")


def test_fit_gp_uses_given_names():
    with pytest.raises(InputError, match=r"^reading: expected finite values"):
        fit_gp(_with(X, 0, np.nan), Y, names=("reading", "reference"))


def test_repeated_positions_with_equal_targets_are_accepted():
    x = _with(X, 3, X[1])
    y = _with(Y, 3, Y[1])
    fit = _fit(x, y)
    assert np.all(np.isfinite(fit.alpha))


@pytest.mark.parametrize(
    "make",
    [
        lambda: Cascade([(X, Y), (X, Y[::-1])]),
        lambda: Cascade([(X, -Y)]),
        lambda: Cascade([(X, Y), (X, _with(Y, 3, Y[2]))]),  # flat: not strictly increasing
    ],
)
def test_cascade_refuses_non_increasing_relation(make):
    with pytest.raises(InputError, match=r"y is not increasing in .*x: .*one-to-one"):
        make()


def test_non_increasing_message_names_the_points():
    y = _with(Y, 4, Y[2] - 0.01)
    with pytest.raises(
        InputError, match=r"x=0\.6000000000000001 -> .*\(index 3\) but .*x=0\.8 -> .*\(index 4\)"
    ):
        Cascade([(X, y)])


NOISE_BAD = {
    "matrix_shape": (np.eye(7) * 1e-6, r"expected shape \(6, 6\), got \(7, 7\)"),
    "vector_shape": (np.full(5, 1e-6), r"expected shape \(6,\), got \(5,\)"),
    "non_square": (
        np.ones((6, 5)) * 1e-6,
        r"expected a square \(n, n\) matrix, got shape \(6, 5\)",
    ),
    "non_symmetric": (
        np.eye(6) * 1e-6 + np.triu(np.ones((6, 6)), 1) * 1e-7,
        r"expected a symmetric matrix, got max \|C - C\^T\| = 1e-07",
    ),
    "negative": (-np.eye(6), r"expected a positive semi-definite covariance, got an eigenvalue"),
    "nan": (_with(np.eye(6), (2, 2), np.nan), r"NaN or inf"),
    "negative_vector": (np.full(6, -1.0), r"expected finite values >= 0"),
}


@pytest.mark.parametrize("case", sorted(NOISE_BAD))
@pytest.mark.parametrize("entry", ["fit_gp", "lml", "cascade_stage"])
def test_bad_noise_refused(case, entry):
    noise, pattern = NOISE_BAD[case]
    with pytest.raises(InputError, match=pattern):
        if entry == "fit_gp":
            _fit(X, Y, noise=noise)
        elif entry == "lml":
            _lml(X, Y, noise=noise)
        else:
            Cascade([Stage(X, Y, noise=noise)])


def test_unknown_method():
    with pytest.raises(
        InputError, match=r"method: expected one of bayes, homoscedastic, lut, got 'gp'"
    ):
        Cascade([(X, Y)], method="gp")


def test_no_stages():
    with pytest.raises(InputError, match="expected at least one"):
        Cascade([])


def test_stage_not_a_pair():
    with pytest.raises(InputError, match=r"stages\[1\]: expected an \(x, y\) pair or a Stage"):
        Cascade([(X, Y), (X, Y, Y)])


def test_check_range():
    # the device stage's upper-sensor readings reach 1.2, beyond the test bed's [0, 1]
    lower_y = np.linspace(0.1, 1.2, 8)
    lower = (lower_y - 0.01, lower_y)
    Cascade([(X, Y), lower])  # accepted without the check
    with pytest.raises(
        InputError,
        match=r"device y: reading 1\.0428\d* \(index 6\) lies outside the range \[0\.0, 1\.0\] "
        r"calibrated by testbed; 2 reading\(s\) outside",
    ):
        Cascade([(X, Y), lower], check_range=True)
    inside = (np.linspace(0.1, 0.9, 8) - 0.01, np.linspace(0.1, 0.9, 8))
    Cascade([(X, Y), inside], check_range=True)


def test_hyperparameters_checked():
    with pytest.raises(InputError, match=r"missing \['noise_variance'\]"):
        fit_gp(X, Y, hyperparameters={"length_scale": 0.3, "variance": 1e-4})
    with pytest.raises(InputError, match=r"missing \['variance'\]"):
        fit_gp(X, Y, hyperparameters={"length_scale": 0.3, "noise_variance": 1e-6})
    with pytest.raises(InputError, match="expected positive finite values"):
        fit_gp(X, Y, hyperparameters={**HP, "length_scale": -1.0})
    with pytest.raises(InputError, match="noise_variance must be >= 0"):
        fit_gp(X, Y, hyperparameters={**HP, "noise_variance": -1.0})


def test_bounds_checked():
    with pytest.raises(InputError, match="unknown hyperparameter 'length'"):
        fit_gp(X, Y, bounds={"length": (0.1, 1.0)})
    with pytest.raises(InputError, match="expected 0 < lower <= upper"):
        fit_gp(X, Y, bounds={"length_scale": (1.0, 0.1)})


def test_learn_noise_false_needs_known_noise():
    with pytest.raises(InputError, match="a known noise must be given"):
        fit_gp(X, Y, learn_noise=False)


def test_huge_finite_values_are_accepted_and_a_nan_after_them_named():
    from cascal.validation import as_positions

    big = np.array([1e308, 1e308, -1e308])
    np.testing.assert_array_equal(as_positions(big, "x"), big)
    with pytest.raises(InputError, match=r"x: expected finite values, got nan at index 3"):
        as_positions(np.r_[big, np.nan], "x")


def test_averaged_repeats_learn_the_noise_of_positions_read_once():
    """A review's case: aggregate_repeats gives a position read once a known variance of
    0, to be covered by the learned white noise, but fit_gp took a vector of known noise
    as all there is, so those readings were fitted as exact: a length scale of 0.019
    instead of 0.38, an error 22 times larger and RMS error / u of 24. Zeros now leave
    the noise to learn where they lie among positive ones, as for the cascade; noise=0
    and learn_noise=False still interpolate."""
    from cascal import aggregate_repeats

    rng = np.random.default_rng(0)
    pos = np.sort(rng.uniform(0, 1, 30))
    x = np.repeat(pos, np.where(np.arange(30) % 5 == 0, 3, 1))  # every 5th read 3 times
    truth = lambda t: t + 1e-4 * np.sin(6 * t)  # noqa: E731
    r = aggregate_repeats(x, truth(x) + 2e-6 * rng.standard_normal(x.size))
    q = np.linspace(0.05, 0.95, 200)
    default = fit_gp(r.x, r.y, noise=r.noise)
    learned = fit_gp(r.x, r.y, noise=r.noise, learn_noise=True)
    assert default.noise_variance == learned.noise_variance > 0
    m, s = default.predict(q, return_std=True)
    err = m - truth(q)
    assert np.sqrt(np.mean(err**2)) < 3e-6 and np.sqrt(np.mean((err / s) ** 2)) < 3
    exact = fit_gp(r.x, r.y, noise=r.noise, learn_noise=False)
    assert exact.noise_variance == 0.0 and "noise_variance" not in exact.optimization.names
    positive = fit_gp(r.x, r.y, noise=np.full(r.x.size, 4e-12))  # every variance known
    assert positive.noise_variance == 0.0
    hp = {"length_scale": 0.5, "variance": 1e-8}  # noise=0 stays exact (a diff review)
    for zero in (0.0, np.zeros(r.x.size)):
        with pytest.warns(JitterWarning, match="needed jitter"):  # (repeated positions)
            assert fit_gp(r.x, r.y, noise=zero, hyperparameters=hp).noise_variance == 0.0


def test_averaged_readings_none_repeated_learn_the_noise_too():
    """An API review's case: where no position was read twice (or every repeat agreed),
    aggregate_repeats gives all zeros, which fit_gp took as exact readings: u about a
    seventh of the error. Zeros in a vector now leave the noise to learn wherever they lie;
    the number noise=0 and learn_noise=False still interpolate."""
    from cascal import aggregate_repeats

    rng = np.random.default_rng(1)
    x = np.linspace(0, 1, 25)
    truth = lambda t: t + 1e-4 * np.sin(6 * t)  # noqa: E731
    y = truth(x) + 2e-6 * rng.standard_normal(x.size)
    r = aggregate_repeats(x, y)
    assert not np.any(r.noise)
    plain, averaged = fit_gp(x, y), fit_gp(r.x, r.y, noise=r.noise)
    assert averaged.noise_variance == pytest.approx(plain.noise_variance, rel=1e-3)
    assert averaged.noise_variance > 1e-13  # (the true 4e-12; 0 before)
    lml = plain.log_marginal_likelihood
    assert averaged.log_marginal_likelihood == pytest.approx(lml, abs=1e-6)
    assert fit_gp(r.x, r.y, noise=0.0).noise_variance == 0.0
    assert fit_gp(r.x, r.y, noise=r.noise, learn_noise=False).noise_variance == 0.0


def test_a_position_repeated_exactly_is_refused_where_the_noise_is_learned():
    """An API review's case: one (x, y) pair given twice made the learned noise's
    likelihood grow without bound as the noise went to 0: the fit took the noise as
    signal (u 10 times below the error). Such a pair is now refused with the remedy, as
    contradicting ones are. With a known noise at either reading, or given
    hyperparameters, it stays. To the periodic kernel, readings whole periods apart are one
    position: with the same correction (to the round-off of y - x) they are refused too,
    with their own remedy (averaging cannot merge them: keep one), also across the turn's
    end and over several turns; with a correction that differs, they stay."""
    x = np.array([0.0, 0.2, 0.35, 0.5, 0.65, 0.8])
    y = x + 0.01 * np.sin(2 * np.pi * x)
    xx, yy = np.r_[x, x[1]], np.r_[y, y[1]]
    with pytest.raises(InputError, match=r"position 0.2 at indices 1 and 6, .*aggregate_repeats"):
        fit_gp(xx, yy)
    with pytest.raises(InputError, match=r"at indices 1 and 6"):
        Cascade([(xx, yy)]).fit()
    one_known = np.r_[np.zeros(6), 1e-8]  # the pair's difference has variance 1e-8 at least
    assert np.isfinite(fit_gp(xx, yy, noise=one_known, learn_noise=True).noise_variance)
    assert fit_gp(xx, yy, hyperparameters=HP).noise_variance == HP["noise_variance"]
    turn = np.r_[x, x[1] + 1.0], np.r_[y, y[1] + 1.0]  # one period on, the same correction
    assert turn[1][-1] - turn[0][-1] != y[1] - x[1]  # equal only to round-off
    with pytest.raises(InputError, match=r"0.2 and 1.2, whole periods apart, at indices 1 and 6"):
        fit_gp(*turn, kernel="periodic", period=1.0)
    with pytest.raises(InputError, match=r"keep one of them"):
        fit_gp(*turn, kernel="periodic", period=1.0, seed=3)
    # across the end of the turn (phases 0.9999... and 0), and three turns on
    end = np.r_[x, -1.0, 3.8], np.r_[y, y[0] - 1.0, y[5] + 3.0]
    with pytest.raises(InputError, match=r"0.0 and -1.0, whole periods apart, at indices 0 and 6"):
        fit_gp(*end, kernel="periodic", period=1.0)
    # a second review: sums and products with constants repeat whole too; and two
    # readings the same to round-off are named so
    from cascal.kernels import Constant, Periodic

    for kernel in (Periodic(period=1.0) + Constant(1e-6), Constant(1.0) * Periodic(period=1.0)):
        with pytest.raises(InputError, match=r"whole periods apart"):
            fit_gp(*turn, kernel=kernel)
    near = np.r_[x, np.nextafter(x[1], 1.0)], np.r_[y, y[1]]
    with pytest.raises(InputError, match=r"0.2 and 0.20000000000000004, the same to round-off"):
        fit_gp(*near, kernel="periodic", period=1.0)
    moved = np.r_[x, x[1] + 1.0], np.r_[y, y[1] + 1.0 + 1e-4]
    assert np.isfinite(fit_gp(*moved, kernel="periodic", period=1.0).noise_variance)
    assert np.isfinite(fit_gp(*turn, kernel="se").noise_variance)  # not one position there


def test_api_misuse_is_an_input_error():
    """A review's cases: these escaped as NumPy's or Python's own errors (or a misleading
    NumericalError), and seed -1 was taken by table-started fits but refused by others."""
    from cascal import Diagonal, Mean

    x = np.linspace(0, 1, 20)
    y = x + 1e-3 * np.sin(5 * x)
    cases = {
        "x: expected numbers": lambda: fit_gp([[1], [2, 3]], [1, 2]),
        "seed: expected a whole number >= 0": lambda: fit_gp(x, y, seed=-1),
        "seed: expected a whole": lambda: fit_gp(x, y, kernel=SquaredExp() * 1.0, seed=1.5),
        "combines with kernels and numbers": lambda: SquaredExp() * "a",
        "noise variance: expected numbers": lambda: Diagonal("a"),
        "stage x: expected numbers": lambda: Stage([1, 2, "a"], [1, 2, 3]),
        "mean offset: expected a finite number": lambda: Mean(1.0, float("nan")),
    }
    for words, call in cases.items():
        with pytest.raises(InputError, match=words):
            call()
    rng = np.random.default_rng(1)
    assert (
        fit_gp(x, y, seed=rng).log_marginal_likelihood
        == fit_gp(x, y, seed=0).log_marginal_likelihood
    )


def test_more_api_misuse_is_an_input_error(tmp_path):
    """An API review's cases: each escaped as Python's or NumPy's own TypeError,
    ValueError or AttributeError."""
    from cascal import Constant, Periodic, save_model
    from cascal.workflow import compensation

    x = np.linspace(0, 1, 12)
    y = x + 1e-3 * np.sin(6 * x)
    cases = {
        r"length_scale must be a positive and finite number, got '0.1'": lambda: SquaredExp(
            "0.1", 1e-6
        ),
        r"length_scale .* got None": lambda: SquaredExp(None, 1e-6),
        r"length_scale .* got array": lambda: SquaredExp(np.array([0.1, 0.2]), 1.0),
        r"period must be a positive and finite number, got '360'": lambda: Periodic(
            1.0, 1.0, period="360"
        ),
        r"value must be .* got 'a'": lambda: Constant("a"),
        r"period must be .* got 'deg'": lambda: fit_gp(x, y, kernel="periodic", period="deg"),
        r"bounds: expected a dict": lambda: fit_gp(x, y, bounds=[(1e-3, 1.0)]),
        r"first: expected a fitted stage-0 GP": lambda: Cascade([(x, y)]).fit(first="gp"),
        r"expected a CalibrationModel, got FittedCascade: make one of a fitted cascade with "
        r"CalibrationModel.from_cascade": lambda: save_model(
            tmp_path / "m.json", Cascade([(x, y)]).fit()
        ),
    }
    for words, call in cases.items():
        with pytest.raises(InputError, match=words):
            call()
    from cascal import CalibrationModel

    cascade = Cascade([(x, y)])
    model = CalibrationModel.from_cascade(cascade, cascade.fit())
    with pytest.raises(InputError, match=r"tolerance: expected a positive number of m, got '1e-6'"):
        compensation(model, "1e-6")
    assert not (tmp_path / "m.json").exists()


def test_a_masked_array_with_masked_entries_is_refused():
    """An API review's case: np.asarray takes the values under a mask, so a masked-out
    suspect reading was fitted. Masked entries are refused, with the remedy."""
    x = np.ma.masked_array(X, mask=[False, False, True, False, False, False])
    with pytest.raises(InputError, match=r"x: a masked array with 1 masked entries \(first at"):
        fit_gp(x, Y)
    assert fit_gp(np.ma.masked_array(X), Y, hyperparameters=HP).x.size == X.size  # none masked
