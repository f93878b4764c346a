"""``cascal demo``: example files, fit, correct and report; the rotary case is continuous
across 0/360 degrees with the periodic kernel."""

from __future__ import annotations

import numpy as np
import pytest
from cli_helpers import run_cascal

from cascal.errors import InputError
from cascal.io.data import read_stage
from cascal.io.modelfile import load_model
from cascal.workflow import fit_model


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    res = run_cascal("demo", "--out", out)
    assert res.returncode == 0, res.stderr
    return out, res


def test_demo_writes_and_points_to_its_results(demo):
    out, res = demo
    for case in ("linear", "rotary"):
        folder = out / "demo" / case
        for name in ("reference_testbed.csv", "testbed_device.csv", "readings.csv",
                     "model.json", "corrected.csv", "report.html",
                     f"{case}_compensation.h", "plan.csv", "plan.png", "verify.csv",
                     "verify.png"):  # fmt: skip
            assert (folder / name).stat().st_size > 0, name
        assert str(folder / "report.html") in res.stdout
        assert f"$ cascal fit {folder}" in res.stdout
    linear = out / "demo" / "linear"
    for name in ("testbed_device_recalibrated.csv", "model_recalibrated.json", "change.png"):
        assert (linear / name).stat().st_size > 0, name
    assert "the device (or its mounting) has changed since the old calibration" in res.stdout
    assert "Within --max-change 0.001 m everywhere, the change's uncertainty counted" in (
        res.stdout
    )
    assert f"$ cascal info {linear / 'model_recalibrated.json'}" in res.stdout
    # the device zeroed 100 m away: named by the identity fit, fitted with --mean offset
    assert "testbed_device_zero_offset.csv: the corrections average -100.0" in res.stderr
    assert "prior mean offset -100.0" in res.stdout
    assert (linear / "model_zero_offset.json").stat().st_size > 0
    assert (out / "rotary_periodic.png").stat().st_size > 10_000
    assert "Where to look:" in res.stdout
    assert res.stdout.count("x smaller") == 2
    assert "warning: 1 of 2001 readings lie outside" in res.stderr  # the linear case's extra one


def test_rotary_fit_is_continuous_across_0_360(demo):
    out, _ = demo
    model = load_model(out / "demo" / "rotary" / "model.json")
    assert model.periodic and model.period == 360.0
    r = np.array([0.0, 360.0, -1e-6, 1e-6, 360.0 - 1e-6, 360.0 + 1e-6, 720.0])
    mean, u = model.fitted.correct(r, return_std=True)
    g = mean - r  # the correction, deg; equal up to the rounding of sin(pi * 720 / 360)
    tol = 1e-9  # deg, 4 micro-arcseconds, against a u of about 1e-4 deg
    assert abs(g[0] - g[1]) < tol and abs(g[0] - g[6]) < tol
    assert abs(g[2] - g[4]) < tol and abs(g[3] - g[5]) < tol
    assert abs(g[3] - g[2]) < 1e-7  # no step at the seam: at most the slope times 2e-6 deg
    assert abs(u[0] - u[1]) < tol
    # The reference could not reach 340..20 deg: the uncertainty is largest at the seam.
    grid = np.linspace(0.0, 360.0, 721)
    _, ug = model.fitted.correct(grid, return_std=True)
    assert ug[0] > 2 * np.median(ug)


def test_squared_exponential_is_not_continuous_across_the_seam(demo):
    """The same rotary data with the SE kernel: nothing ties 0 to 360 degrees, and the
    device's test-bed readings in the unreachable sector leave the calibrated range."""
    out, _ = demo
    folder = out / "demo" / "rotary"
    names = ("reference_testbed.csv", "testbed_device.csv")
    data = [read_stage(folder / f, period=360.0) for f in names]
    with pytest.raises(InputError, match="outside the range"):
        fit_model(data, kernel="se", n_restarts=2, unit="deg")
    ends = np.array([0.0, 360.0])
    se = fit_model(data[:1], kernel="se", n_restarts=2, unit="deg")
    periodic = fit_model(data[:1], kernel="periodic", period=360.0, n_restarts=2, unit="deg")
    g_se = se.fitted.correct(ends) - ends
    g_per = periodic.fitted.correct(ends) - ends
    assert abs(g_per[0] - g_per[1]) < 1e-9
    assert abs(g_se[0] - g_se[1]) > 1e-4  # deg
