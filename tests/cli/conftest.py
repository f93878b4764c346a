"""Fixtures of the workflow tests: simulated stage files and a model fitted by the command.

The stage files come from :func:`cascal.demo.linear_demo` (seed 0): a reference that
cannot reach the middle of a 1 m axis, a test bed, and a device, with the true map known.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from cli_helpers import run_cascal, spoil, write_case

from cascal.demo import DemoCase, linear_demo


@pytest.fixture(scope="session")
def linear_case() -> DemoCase:
    return linear_demo(0)


@pytest.fixture(scope="session")
def linear_files(tmp_path_factory, linear_case) -> tuple[list[Path], Path]:
    """Stage files (reference end first) and a readings file of the linear case."""
    return write_case(linear_case, tmp_path_factory.mktemp("linear"))


@pytest.fixture(scope="session")
def linear_model(linear_files) -> Path:
    """A model fitted by ``cascal fit`` on the linear case (method bayes, SE kernel)."""
    files, _ = linear_files
    model = files[0].parent / "model.json"
    res = run_cascal("fit", *files, "-o", model)
    assert res.returncode == 0, res.stderr
    return model


@pytest.fixture(scope="session")
def spoiled(linear_files, tmp_path_factory):
    """The linear case with one reference reading of a repeated position 10 noise standard
    deviations off (file row 41) and one test-bed value of the device file off (row 101)."""
    (ref, dev), _ = linear_files
    tmp = tmp_path_factory.mktemp("spoiled")
    bad_ref, bad_dev = tmp / "reference_testbed.csv", tmp / "testbed_device.csv"
    spoil(ref, bad_ref, {41: 1e-3})
    spoil(dev, bad_dev, {101: 5e-4})
    return tmp, bad_ref, bad_dev
