"""Verification at check points: errors, combined uncertainty, En, MPE conformance."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cascal.demo import linear_demo, rotary_demo
from cascal.errors import InputError
from cascal.verification import expected_within, verify
from cascal.workflow import fit_model, verify_model
from utils import assert_allclose, demo_stages


@settings(max_examples=50, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    u_read=st.floats(0.0, 2.0),
    u_ref=st.floats(0.0, 2.0),
    mpe=st.floats(0.1, 5.0),
)
def test_numbers_against_the_formulas_written_out(seed, u_read, u_ref, mpe):
    rng = np.random.default_rng(seed)
    m = 40
    reading = np.sort(rng.uniform(0.0, 10.0, m))
    reference = reading + rng.normal(0.0, 1.0, m)
    corrected = reference + rng.normal(0.0, 1.0, m)
    u_cal = rng.uniform(0.1, 2.0, m)
    inside = rng.uniform(size=m) > 0.2
    v = verify(reading, reference, corrected, u_cal, inside=inside, u_reading=u_read,
               u_reference=u_ref, mpe=mpe)  # fmt: skip
    for i in range(m):
        err = corrected[i] - reference[i]
        u = math.sqrt(u_cal[i] ** 2 + u_read**2 + u_ref**2)
        assert v.error[i] == err
        assert v.error_before[i] == reading[i] - reference[i]
        assert math.isclose(v.u[i], u, rel_tol=1e-14)
        assert math.isclose(v.en[i], abs(err) / (2.0 * u), rel_tol=1e-14)
        assert v.conforms[i] == (abs(err) + 2.0 * u_ref <= mpe)
    s = v.summary()
    idx = [i for i in range(m) if inside[i]]
    assert s["points"] == len(idx) and s["outside_range"] == m - len(idx)
    errs = [corrected[i] - reference[i] for i in idx]
    assert math.isclose(s["rms_after"], math.sqrt(sum(e * e for e in errs) / len(idx)))
    assert s["max_after"] == max(abs(e) for e in errs)
    assert s["within_U"] == sum(v.en[i] <= 1.0 for i in idx)
    assert s["conforming"] == sum(bool(v.conforms[i]) for i in idx)
    z = [errs[j] / v.u[i] for j, i in enumerate(idx)]
    assert math.isclose(s["rms_normalised"], math.sqrt(sum(t * t for t in z) / len(z)))


def test_coverage_of_independent_normal_errors():
    """Errors drawn with the stated u lie within U = 2u at erf(sqrt 2) of the points."""
    assert math.isclose(expected_within(2.0), 0.9544997361036416, rel_tol=1e-15)
    assert math.isclose(expected_within(1.0), 0.6826894921370859, rel_tol=1e-15)
    rng = np.random.default_rng(1)
    m = 200_000
    u_cal, u_read, u_ref = rng.uniform(0.5, 2.0, m), 0.7, 0.3
    u = np.sqrt(u_cal**2 + u_read**2 + u_ref**2)
    reference = rng.uniform(0.0, 1.0, m)
    corrected = reference + rng.normal(0.0, 1.0, m) * u
    s = verify(
        reference, reference, corrected, u_cal, u_reading=u_read, u_reference=u_ref
    ).summary()
    assert abs(s["within_U"] / m - expected_within()) < 0.002  # binomial sd 4.7e-4
    assert abs(s["rms_normalised"] - 1.0) < 0.005


def test_rotary_errors_go_the_shortest_way_round():
    c = np.array([359.99, 0.01, 180.0, 10.0])
    ref = np.array([0.01, 359.99, 180.0 + 360.0, 370.0 + 0.5])
    v = verify(c, ref, c, np.ones(4), period=360.0)
    assert_allclose(v.error, [-0.02, 0.02, 0.0, -0.5], atol=1e-12, rtol=0)
    assert_allclose(v.error_before, v.error, atol=0, rtol=0)
    assert np.all(np.abs(verify(c, ref, c, np.ones(4)).error[:2]) > 359)
    before = verify(c + 1.0, ref, c, np.ones(4), period=360.0).error_before
    assert_allclose(before, [0.98, 1.02, 1.0, 0.5], atol=1e-12, rtol=0)


def test_exact_points_and_huge_errors():
    """A zero error with zero u is inside U (En 0); the RMS of errors near the largest
    doubles does not overflow."""
    x = np.array([1.0, 2.0])
    v = verify(x, x, x, np.zeros(2))
    assert np.array_equal(v.en, [0.0, 0.0]) and v.summary()["within_U"] == 2
    big = verify(x, np.array([-1e300, 1e300]), np.array([1e300, -1e300]), np.ones(2))
    with np.errstate(all="raise"):
        s = big.summary()
    assert math.isclose(s["rms_after"], 2e300) and math.isclose(s["rms_normalised"], 2e300)


def test_lookup_table_without_uncertainty_and_bad_arguments():
    x = np.linspace(0.0, 1.0, 5)
    v = verify(x, x + 0.1, x, np.full(5, np.nan), mpe=0.3, u_reference=0.05)
    s = v.summary()
    assert not v.has_u and s["within_U"] is None and s["rms_normalised"] is None
    assert s["conforming"] == 5 and np.all(np.isnan(v.en))
    assert verify(x, x, x, np.ones(5)).conforms is None
    with pytest.raises(InputError, match="one shape"):
        verify(x, x[:4], x, x)
    with pytest.raises(InputError, match="u_reading"):
        verify(x, x, x, x, u_reading=-1.0)
    with pytest.raises(InputError, match="u_reference"):
        verify(x, x, x, x, u_reference=math.inf)
    with pytest.raises(InputError, match="mpe"):
        verify(x, x, x, x, mpe=0.0)
    with pytest.raises(InputError, match="inside"):
        verify(x, x, x, x, inside=np.ones(3, bool))


def test_model_check_points_use_the_device_stage():
    """verify_model corrects with the device GP (its own predict, exactly), counts only
    the calibration's u by default, leaves out-of-range points out, and on the demo's truth
    the errors are about the size of the stated uncertainty."""
    case = linear_demo(0)
    model = fit_model(demo_stages(case), n_restarts=2)
    gp = model.fitted.device
    v = verify_model(model, case.readings, case.truth)
    mean, std = gp.predict(case.readings, return_std=True)
    assert_allclose(v.corrected, mean, rtol=0, atol=1e-12)
    assert_allclose(v.u_calibration, std, rtol=1e-10)
    assert v.u_reading == 0.0 and v.u_reference == 0.0 and np.array_equal(v.u, v.u_calibration)
    lo, hi = model.calibrated_range
    assert np.array_equal(v.inside, (case.readings >= lo) & (case.readings <= hi))
    s = v.summary()
    assert s["outside_range"] == 1
    assert 0.5 < s["rms_normalised"] < 2.0
    assert s["rms_after"] < 1e-3 * s["rms_before"]


def test_rotary_model_check_points_across_the_seam():
    case = rotary_demo(0)
    model = fit_model(demo_stages(case), kernel="periodic", period=360.0, unit="deg",
                      n_restarts=2)  # fmt: skip
    turned = case.truth + 360.0 * np.where(case.truth < 180.0, 1.0, -1.0)
    a = verify_model(model, case.readings, case.truth, u_reading=0.0)
    b = verify_model(model, case.readings, turned, u_reading=0.0)
    assert_allclose(b.error, a.error, rtol=0, atol=1e-9)
    assert a.inside.all() and np.max(np.abs(a.error)) < 1e-3


def test_rotary_readings_many_turns_away_are_corrected_as_their_angle():
    """A review's case: a reading 1e9 turns away was corrected by the kernel evaluated
    there, which lost digits (u came out 0, the correction 0.0017 deg off). Now any turn
    is corrected as its angle in the calibrated turn: the same correction and u as the
    GP's own at that angle, and only a reading so far out that a float64 holds it less
    finely than u is flagged."""
    from cascal.workflow import correct

    case = rotary_demo(0)
    model = fit_model(demo_stages(case), kernel="periodic", period=360.0, unit="deg",
                      n_restarts=2)  # fmt: skip
    gp = model.fitted.device
    angle = np.array([10.0, 123.456, 359.0])
    mean, std = gp.predict(angle, return_std=True)
    for turns in (0, 1, -3, 10**6, 10**8):
        r = angle + 360.0 * turns
        c = correct(model, r)
        err = np.abs((c.corrected - r) - (mean - angle))
        assert np.all(err <= 1e-4 * std + 4.0 * np.spacing(r)), (turns, err)
        assert_allclose(c.u, std, rtol=1e-5)
        assert not c.out_of_range.any()
    far_mean, far_std = gp.predict(angle + 360.0 * 10**8, return_std=True)  # the GP itself
    assert_allclose(far_std, std, rtol=1e-5)
    assert np.all(np.abs((far_mean - 360.0 * 10**8) - mean) <= 1e-4 * std + 1e-5)
    edge = correct(model, angle + 360.0 * 10**9)  # float64 steps of 6.1e-5 deg there
    assert np.array_equal(edge.out_of_range, np.spacing(edge.reading) > edge.u)
    assert edge.out_of_range.any() and not edge.out_of_range.all()
    far = correct(model, angle + 360.0 * 10**12)
    assert far.out_of_range.all() and np.all(far.u > 0.5 * std)
    with warnings.catch_warnings():  # a review's case: NumPy's overflow warnings, printed
        warnings.simplefilter("error")  # by cascal correct with their source lines
        huge = correct(model, [1.7976931348623157e308, -1e300, 1e18])
    assert huge.out_of_range.all() and np.all(np.isfinite(huge.corrected))
    with pytest.raises(InputError, match="readings: expected finite values, got inf"):
        correct(model, [np.inf, 5.0])


def test_verify_model_refuses_a_missing_reference_value():
    """An API review's case: a NaN among the reference values (a blank cell) made every
    figure of the verification NaN, silently. It is refused by index, as a NaN reading is."""
    from cascal import CalibrationModel, Cascade
    from cascal.simulation import simulate_trial
    from cascal.workflow import verify_model

    trial = simulate_trial(np.random.default_rng(0))
    cascade = Cascade([trial.d2, trial.d1])
    model = CalibrationModel.from_cascade(cascade, cascade.fit())
    r = np.linspace(0.2, 0.8, 20)
    reference = model.fitted.correct(r)
    reference[-1] = np.nan
    with pytest.raises(InputError, match="reference: expected finite values, got nan at index 19"):
        verify_model(model, r, reference)
    with pytest.raises(InputError, match="expected the same length, got 20 and 19"):
        verify_model(model, r, reference[:-1])


def test_a_point_exactly_at_the_mpe_conforms_whatever_its_binary_round_off():
    """A numerical review's cases: five points whose |error| + 2 u_reference equals the MPE
    in decimals; two failed, as their subtraction rounded up in binary. They all conform
    now (the limit belongs to the zone), and one a micrometre beyond it does not."""
    from decimal import Decimal

    cases = [("0.5", "0.49997", "0.000035"), ("0.5", "0.49990", "0"),
             ("0.3", "0.29993", "0.000015"), ("0.7", "0.70006", "0.00002"),
             ("0.1", "0.1001", "0")]  # fmt: skip
    for corrected, reference, u_ref in cases:
        exact = abs(Decimal(corrected) - Decimal(reference)) + 2 * Decimal(u_ref)
        assert exact == Decimal("0.0001")
        c, r = np.array([float(corrected)]), np.array([float(reference)])
        v = verify(c, r, c, np.array([1e-5]), u_reference=float(u_ref), mpe=1e-4)
        assert v.conforms.tolist() == [True], (corrected, reference, v.error)
        # a millionth of the MPE beyond the limit, outward: not (a diff review: the test had
        # moved it by 1 % and accepted either direction)
        out = np.sign(c - r) * 1e-10
        beyond = verify(c + out, r, c + out, np.array([1e-5]), u_reference=float(u_ref), mpe=1e-4)
        assert abs(beyond.error[0]) > abs(v.error[0]) and beyond.conforms.tolist() == [False]
    # large readings against a tiny MPE: the allowance stays within 1e-9 of the MPE (a
    # review: readings of 1e6 with an MPE of 1e-9 had conformed at 2.4 times it)
    c, r = np.array([1e6 + 2.44e-9]), np.array([1e6])
    v = verify(c, r, c, np.array([1e-12]), u_reference=0.0, mpe=1e-9)
    assert v.error[0] > 2e-9 and v.conforms.tolist() == [False]
