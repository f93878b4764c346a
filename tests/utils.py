"""Shared test helpers: one float64 ``assert_allclose`` and independent dense GP formulas."""

from __future__ import annotations

import numpy as np

__all__ = ["assert_allclose", "demo_stages", "dense_lml", "dense_posterior", "fd_gradient", "se"]


def assert_allclose(actual, desired, *, rtol: float = 1e-10, atol: float = 0.0, err_msg=""):
    """``numpy.testing.assert_allclose`` that also requires ``actual`` to be float64."""
    a = np.asarray(actual)
    assert a.dtype == np.float64, f"expected float64, got {a.dtype}"
    np.testing.assert_allclose(
        a, np.asarray(desired, dtype=float), rtol=rtol, atol=atol, err_msg=err_msg
    )


def se(a, b, length_scale: float, variance: float) -> np.ndarray:
    """Squared-exponential covariance written out by hand, shape (len(a), len(b))."""
    d = np.asarray(a, float)[:, None] - np.asarray(b, float)[None, :]
    return variance * np.exp(-(d**2) / (2.0 * length_scale**2))


def dense_lml(r: np.ndarray, Kt: np.ndarray) -> float:
    """-1/2 r^T Kt^-1 r - 1/2 log|Kt| - n/2 log 2 pi with a plain solve and slogdet."""
    sign, logdet = np.linalg.slogdet(Kt)
    assert sign > 0
    return float(
        -0.5 * r @ np.linalg.solve(Kt, r) - 0.5 * logdet - 0.5 * len(r) * np.log(2 * np.pi)
    )


def dense_posterior(Kxx, Ksx, Kss, noise, r, mean_s):
    """GPML Alg. 2.1 with np.linalg.solve: posterior mean (m,) and covariance (m, m)."""
    Kt = Kxx + noise
    mean = mean_s + Ksx @ np.linalg.solve(Kt, r)
    cov = Kss - Ksx @ np.linalg.solve(Kt, Ksx.T)
    return mean, cov


def fd_gradient(f, theta: np.ndarray, h: float = 1e-5) -> np.ndarray:
    """Central finite differences of the scalar function ``f`` at ``theta`` (p,)."""
    theta = np.asarray(theta, dtype=float)
    g = np.empty_like(theta)
    for j in range(theta.size):
        e = np.zeros_like(theta)
        e[j] = h
        g[j] = (f(theta + e) - f(theta - e)) / (2 * h)
    return g


def three_stages():
    """The linear demo's stages and a third below them, reference end first: a device read
    by the demo's device over its range less 5 cm at either end, with its own 0.2 mm
    error."""
    from dataclasses import replace

    ref, dev = demo_stages()
    keep = (dev.x > dev.x.min() + 0.05) & (dev.x < dev.x.max() - 0.05)
    third = replace(
        dev, x=dev.x[keep] + 2e-4 * np.sin(9 * dev.x[keep]), y=dev.x[keep],
        counts=dev.counts[keep], rows=dev.rows[keep],
    )  # fmt: skip
    return [ref, dev, third]


def demo_stages(case=None):
    """A demo case's stages (default: the linear one, seed 0) as the workflow reads them
    from files (repeats averaged, provenance filled in), reference end first."""
    from cascal.demo import linear_demo
    from cascal.io.data import Source, StageData
    from cascal.validation import aggregate_repeats

    out = []
    for stage in (case or linear_demo(0)).stages:
        rep = aggregate_repeats(stage.x, stage.y)
        noise = rep.noise if np.any(rep.counts > 1) else None
        src = Source(stage.file, "ab" * 32, stage.x.size, stage.columns)
        out.append(StageData(rep.x, rep.y, noise, rep.counts, rep.first + 2, src))
    return out


def stored_trials(db) -> int:
    """Trials in the study database ``db`` so far, read-only (0 before it exists)."""
    import sqlite3

    try:
        con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=1)
        try:
            return con.execute("SELECT COUNT(*) FROM trials").fetchone()[0]
        finally:
            con.close()
    except sqlite3.Error:
        return 0
