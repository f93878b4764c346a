"""Simulated calibration data for ``cascal demo`` and the end-to-end tests.

Two cases with known truth, each reference -> test bed -> device:

* ``linear_demo``: a linear axis over [0, 1] m with the paper's sensor errors (ten random
  sinusoids). The reference cannot reach the middle stretch [0.42, 0.58] m; it reads three
  times at every other position, where the test bed holds its reading (repeats).
* ``rotary_demo``: a rotary table over 360 degrees with harmonic errors (whole periods per
  turn). The reference cannot reach the sector from 340 to 20 degrees, across the 0/360
  seam; the device is calibrated against the test bed over the full turn.

Readings to correct come with the true map at each reading (device reading -> true
position), the quantity a correction estimates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .simulation import NOISE_VARIANCE, SensorMap, draw_map

__all__ = [
    "DemoCase",
    "DemoStage",
    "fleet_demo",
    "linear_demo",
    "linear_recalibration",
    "rotary_demo",
]


@dataclass(frozen=True, slots=True)
class DemoStage:
    """One stage file's content: column names and readings, shape (n,) each."""

    file: str
    columns: tuple[str, str]
    x: np.ndarray
    y: np.ndarray


@dataclass(frozen=True, slots=True)
class DemoCase:
    """A simulated cascade with known truth.

    Attributes:
        name: ``linear`` or ``rotary``.
        unit: Unit of all readings.
        kernel: Kernel to fit with; ``period`` for a periodic one.
        stages: Reference end first.
        readings: Device readings to correct, shape (m,).
        truth: True position of the true map at each reading, shape (m,).
        unreachable: True positions the reference could not reach, (start, end); for the
            rotary case the sector runs from start up through 360 to end.
        testbed_map, device_map: True position -> noise-free reading.
    """

    name: str
    unit: str
    kernel: str
    period: float | None
    stages: tuple[DemoStage, ...]
    readings: np.ndarray
    truth: np.ndarray
    unreachable: tuple[float, float]
    testbed_map: SensorMap
    device_map: SensorMap


def linear_demo(seed: int = 0) -> DemoCase:
    """The linear-axis case (m), drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    testbed, device = _increasing(rng), _increasing(rng)
    sd = np.sqrt(NOISE_VARIANCE)
    # Stage 0: the test bed holds its reading at 51 set points; the reference reads 3 times.
    setpoints = np.linspace(
        float(testbed(np.array([0.0]))[0]), float(testbed(np.array([1.0]))[0]), 51
    )
    true = testbed.inverse(setpoints)
    keep = (true < 0.42) | (true > 0.58)
    x0 = np.repeat(setpoints[keep], 3)
    y0 = np.repeat(true[keep], 3) + rng.normal(0.0, sd, x0.size)
    # Stage 1: 200 device readings equally spaced, inside the test bed's calibrated stretch.
    ends = device(np.array([0.01, 0.99]))
    grid = np.linspace(ends[0], ends[1], 200)
    t1 = device.inverse(grid)
    x1 = grid + rng.normal(0.0, sd, grid.size)
    y1 = testbed(t1) + rng.normal(0.0, sd, grid.size)
    readings = np.sort(device(rng.uniform(0.02, 0.98, 2000)) + rng.normal(0.0, sd, 2000))
    readings = np.r_[readings, device(np.array([1.0])) + 0.002]  # one beyond the range
    return DemoCase(
        "linear",
        "m",
        "se",
        None,
        _two_stages(x0, y0, x1, y1),
        readings,
        device.inverse(readings, -0.5, 1.5),
        (0.42, 0.58),
        testbed,
        device,
    )


def linear_recalibration(seed: int = 0, drift: float = 2.5e-4) -> DemoStage:
    """The linear case's device measured again on its test bed (200 fresh readings, fresh
    noise) after the device drifted: at true position t it now reads ``drift * (2 t - 1)``
    more (m). ``drift = 0``: a recalibration of an unchanged device."""
    case = linear_demo(seed)
    rng = np.random.default_rng([seed, 2])
    sd = np.sqrt(NOISE_VARIANCE)
    ends = case.device_map(np.array([0.01, 0.99]))
    t = case.device_map.inverse(np.linspace(ends[0], ends[1], 200))
    x = case.device_map(t) + drift * (2.0 * t - 1.0) + rng.normal(0.0, sd, t.size)
    y = case.testbed_map(t) + rng.normal(0.0, sd, t.size)
    return DemoStage("testbed_device_recalibrated.csv", ("device", "testbed"), x, y)


def _two_stages(x0, y0, x1, y1) -> tuple[DemoStage, DemoStage]:
    """The reference-test bed and test bed-device files of a two-stage case."""
    return (
        DemoStage("reference_testbed.csv", ("testbed", "reference"), x0, y0),
        DemoStage("testbed_device.csv", ("device", "testbed"), x1, y1),
    )


def rotary_demo(seed: int = 0) -> DemoCase:
    """The rotary-table case (degrees, period 360), drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    testbed = _harmonics(rng, 0.01)
    device = _harmonics(rng, 0.05)
    sd = 1e-4  # deg, 0.36 arcsec
    setpoints = np.arange(0.0, 360.0, 5.0)
    true = testbed.inverse(setpoints, -10.0, 370.0)
    keep = (true > 20.0) & (true < 340.0)
    x0 = np.repeat(setpoints[keep], 2)
    y0 = np.repeat(true[keep], 2) + rng.normal(0.0, sd, x0.size)
    t1 = np.arange(0.0, 360.0, 2.0) + 1.0
    x1 = device(t1) + rng.normal(0.0, sd, t1.size)
    y1 = testbed(t1) + rng.normal(0.0, sd, t1.size)
    t = rng.uniform(0.0, 360.0, 2000)
    readings = device(t) + rng.normal(0.0, sd, t.size)
    return DemoCase(
        "rotary",
        "deg",
        "periodic",
        360.0,
        _two_stages(x0, y0, x1, y1),
        readings,
        device.inverse(readings, -10.0, 370.0),
        (340.0, 20.0),
        testbed,
        device,
    )


def fleet_demo(seed: int = 0, n_devices: int = 3) -> tuple[DemoStage, list[DemoStage]]:
    """One test bed (the linear case's stage 0) and ``n_devices`` devices measured on it,
    each a different draw of the device error, 100 points each."""
    case = linear_demo(seed)
    rng = np.random.default_rng([seed, 1])
    sd = np.sqrt(NOISE_VARIANCE)
    devices = []
    for i in range(n_devices):
        device = _increasing(rng)
        ends = device(np.array([0.01, 0.99]))
        grid = np.linspace(ends[0], ends[1], 100)
        x = grid + rng.normal(0.0, sd, grid.size)
        y = case.testbed_map(device.inverse(grid)) + rng.normal(0.0, sd, grid.size)
        devices.append(DemoStage(f"device{i + 1:02d}.csv", ("device", "testbed"), x, y))
    return case.stages[0], devices


def _increasing(rng: np.random.Generator) -> SensorMap:
    while True:
        m = draw_map(rng)
        if m.is_increasing():
            return m


def _harmonics(rng: np.random.Generator, amplitude: float) -> SensorMap:
    """Error of whole periods per turn: harmonics 1 to 4 of 360 degrees, amplitudes in deg."""
    k = np.arange(1, 5)
    a = rng.normal(0.0, amplitude, k.size) / k
    b = rng.normal(0.0, amplitude, k.size) / k
    return SensorMap(a, b, 2.0 * np.pi * k / 360.0)
