"""Fixtures shared by the core tests: the float64 ``assert_allclose`` helper and seeded data."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import settings

from utils import assert_allclose as _assert_allclose

# Property tests draw the same examples on every run and machine: CI is reproducible.
settings.register_profile("cascal", derandomize=True, deadline=None)
settings.load_profile("cascal")


@pytest.fixture
def assert_allclose():
    """The float64 ``assert_allclose`` of :mod:`utils` as a fixture."""
    return _assert_allclose


@pytest.fixture
def rng():
    """A fixed-seed generator, fresh for every test."""
    return np.random.default_rng(20230710)


@pytest.fixture(scope="session", autouse=True)
def _compiled_study():
    """The study's compiled fits, compiled once before any test (Numba caches them, about
    55 s the first time): a study that a test runs in a subprocess, waiting a few seconds
    for its trials or its signals, then loads them instead of compiling them first."""
    from cascal.montecarlo import StudyConfig, run_trial

    run_trial(StudyConfig(), 0)
