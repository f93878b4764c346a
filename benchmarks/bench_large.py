"""Large stages: the fit of a stage too large for a likelihood table, against the search it
replaced.

A stage of over 2 * SUBSET (320) readings with no table (over 500 readings off the grid, or
a dense known noise off the grid or over 160 readings) starts its Newton runs from the
optima of the same search on two subsets of 160 readings (cascal.gp._subset_starts). Before,
it screened 30 random candidates and ran five Newton runs. Both are run here on the same
data, one BLAS thread, and their time, evaluations and final log marginal likelihood are
printed as a Markdown table. The data: readings over [0, 1] at random positions, a smooth
correction of 300 um plus, in the "short" cases, 20 um of period 6 readings (an encoder's
interpolation error), 1 um noise; the "dense" cases add the posterior of a 30-point stage
A as a known noise, as the test-bed stage of a cascade has.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import cascal
from blas import describe as blas
from cascal.gp import Objective
from cascal.kernels import SquaredExp
from cascal.noise import Dense
from cascal.optimize import maximize


def stage(n: int, short: bool, dense: bool, seed: int):
    rng = np.random.default_rng(seed)
    x = np.sort(rng.uniform(0.0, 1.0, n))
    f = 3e-4 * np.sin(7 * x + seed)
    if short:
        f = f + 2e-5 * np.sin(2 * np.pi * x * n / 6)
    known = None
    if dense:
        xa = np.linspace(-0.02, 1.02, 30)
        ya = xa + 2e-4 * np.sin(5 * xa) + 2e-6 * rng.standard_normal(xa.size)
        _, U = cascal.fit_gp(xa, ya).posterior_factor(x)
        known = Dense.from_factor(U)
        f = f + U @ rng.standard_normal(U.shape[1])
    return x, x + f + 1e-6 * rng.standard_normal(n), known


def screened(x, y, known):
    """The search large stages had before: five Newton runs from 30 screened candidates."""
    obj = Objective(x, y - x, SquaredExp(), known, True, profile=known is None)
    vgh, rng = obj.value_and_derivatives, np.random.default_rng(0)
    return maximize(obj.value, obj.value_and_grad, obj.bounds(), n_restarts=5, rng=rng,
                    value_grad_hess=vgh)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 2000])
    args = ap.parse_args()
    print(f"BLAS: {blas()}")
    print("| case | N | search | time [s] | evaluations | runs | LML | subsets - screened |")
    print("|---|---|---|---|---|---|---|---|")
    for n in args.sizes:
        for short, dense in ((False, False), (True, False), (False, True), (True, True)):
            name = ("short" if short else "smooth") + (", dense noise" if dense else "")
            x, y, known = stage(n, short, dense, seed=n)
            t = time.perf_counter()
            fit = cascal.fit_gp(x, y, noise=known).optimization
            t_new = time.perf_counter() - t
            t = time.perf_counter()
            ref = screened(x, y, known)
            t_ref = time.perf_counter() - t
            d = fit.value - ref.value
            for label, o, dt in (("subsets", fit, t_new), ("screened", ref, t_ref)):
                diff = f"{d:+.3g}" if label == "subsets" else ""
                print(f"| {name} | {n} | {label} | {dt:.2f} | {o.n_evals} | {len(o.starts)} "
                      f"| {o.value:.6f} | {diff} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
