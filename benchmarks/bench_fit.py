"""One stage fit, cascal against scikit-learn, on the same data and the same bounds.

Both fit three hyperparameters (length scale, signal variance, noise variance) of a
squared-exponential GP to test-bed corrections from the paper's simulator, with five
optimiser starts each (scikit-learn: ``n_restarts_optimizer=4``; cascal: ``n_restarts=5``,
at most five Newton runs, started at the best local maxima of an exact table of the
profiled likelihood, so fewer when the table has fewer maxima). Prints the median time of
each, their ratio and both final log marginal likelihoods as a Markdown table.

A second table says where cascal's time goes: the table of start points (its time alone),
the Newton runs and their evaluations (gradient and Hessian each), the time of one Newton
evaluation, and the time of the LAPACK/BLAS calls inside it alone (Cholesky, triangular
inverse and two matrix products).
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy.linalg import lapack

import cascal
from blas import describe as blas
from cascal.gp import Objective
from cascal.kernels import SquaredExp
from cascal.surrogate import profiled_starts


def data(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    trial = cascal.simulation.simulate_trial(np.random.default_rng(seed))
    if n == 64:
        return trial.d2
    _device, testbed = trial.d1
    return testbed, trial.testbed_map.inverse(testbed) + 1e-4 * np.random.default_rng(
        seed
    ).standard_normal(testbed.size)


def sklearn_fit(x, y, bounds_log, starts):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    b = np.exp(bounds_log)
    r = y - x  # cascal's identity prior mean, given to scikit-learn as targets
    kernel = ConstantKernel(np.sqrt(b[1, 0] * b[1, 1]), tuple(b[1])) * RBF(
        np.sqrt(b[0, 0] * b[0, 1]), tuple(b[0])
    ) + WhiteKernel(np.sqrt(b[2, 0] * b[2, 1]), tuple(b[2]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gp = GaussianProcessRegressor(kernel, n_restarts_optimizer=starts - 1, random_state=0)
        gp.fit(x[:, None], r)
    return gp.log_marginal_likelihood_value_


def timed(f, repeats):
    times, value = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        value = f()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), value


def evaluation_costs(x, y, fit, repeats: int = 300) -> tuple[float, float]:
    """Seconds of one Newton evaluation at the optimum, and of its LAPACK/BLAS calls alone."""
    obj = Objective(x, y - x, SquaredExp(), None, True, profile=True)
    theta = np.array(
        [np.log(fit.kernel.length_scale), np.log(fit.noise_variance / fit.kernel.variance)]
    )
    A = SquaredExp(fit.kernel.length_scale, 1.0)(x)
    A.flat[:: x.size + 1] += np.exp(theta[1])

    def floor():
        L, _ = lapack.dpotrf(A, lower=1, clean=1)
        Li, _ = lapack.dtrtri(L, lower=1)
        Ainv = Li.T @ Li
        return Ainv @ A

    return (
        timed(lambda: [obj.value_grad_hess(theta) for _ in range(repeats)], 5)[0] / repeats,
        timed(lambda: [floor() for _ in range(repeats)], 5)[0] / repeats,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--starts", type=int, default=5)
    args = ap.parse_args()
    print("| N | starts | cascal [ms] | scikit-learn [ms] | speed-up | LML cascal | LML sklearn |")
    print("|---|---|---|---|---|---|---|")
    costs = []
    for n in (64, 100):
        x, y = data(n)
        bounds = Objective(x, y - x, SquaredExp(), None, True).bounds()
        t_c, fit = timed(lambda x=x, y=y: cascal.fit_gp(x, y, n_restarts=args.starts), args.repeats)
        t_s, lml_s = timed(
            lambda x=x, y=y, b=bounds: sklearn_fit(x, y, b, args.starts), max(3, args.repeats // 3)
        )
        lml_c = fit.log_marginal_likelihood
        print(
            f"| {n} | {args.starts} | {t_c * 1e3:.2f} | {t_s * 1e3:.1f} | {t_s / t_c:.1f}x "
            f"| {lml_c:.6f} | {lml_s:.6f} |"
        )
        pb = Objective(x, y - x, SquaredExp(), None, True, profile=True).bounds()
        t_table = timed(
            lambda x=x, y=y, pb=pb: profiled_starts(SquaredExp(), x, y - x, pb, args.starts),
            args.repeats,
        )[0]
        costs.append((n, fit, t_table, *evaluation_costs(x, y, fit)))
    print()
    print(
        "| N | table of starts [ms] | screened candidates | probes | Newton runs "
        "| Newton evaluations | one Newton evaluation [µs] | its LAPACK/BLAS [µs] |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for n, fit, t_table, t_eval, t_floor in costs:
        opt = fit.optimization
        newton = sum(s.n_evals for s in opt.starts)
        print(
            f"| {n} | {t_table * 1e3:.2f} | {opt.n_candidates} | {opt.n_probes} "
            f"| {len(opt.starts)} | {newton} | {t_eval * 1e6:.0f} | {t_floor * 1e6:.0f} |"
        )
    print()
    print(f"BLAS: {blas()}")


if __name__ == "__main__":
    main()
