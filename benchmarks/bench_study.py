"""The paper's Monte Carlo study, timed: wall time, trials per second, split per method.

Then a quality check on a sample of trials: every stage fit of the study's optimiser
(screened seeded starts, ``StudyConfig.n_restarts``) must reach a log marginal likelihood
at least as good (to 1e-3) as a plain five-start L-BFGS-B reference from uniformly random
starts in the same bounds.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from cascal.cascade import Cascade
from cascal.gp import Objective
from cascal.kernels import SquaredExp
from cascal.montecarlo import StudyConfig, trial_rng
from cascal.optimize import maximize
from cascal.simulation import simulate_trial
from cascal.study import run_study


def reference_lml(x, y, noise, rng) -> float:
    """Best LML of five L-BFGS-B runs from uniformly random starts (no screening)."""
    obj = Objective(x, y - x, SquaredExp(), noise, learn_noise=True)
    res = maximize(
        obj.value, obj.value_and_grad, obj.bounds(), n_restarts=5, rng=rng, n_candidates=5
    )
    return res.value


def quality(config: StudyConfig, sample: int) -> tuple[int, float]:
    """(fits checked, largest shortfall of the study's LML below the reference)."""
    worst, checked = -np.inf, 0
    for i in range(sample):
        rng = trial_rng(config.seed, 10_000_000 + i)
        trial = simulate_trial(rng)
        fitted = Cascade([trial.d2, trial.d1], "bayes", n_restarts=config.n_restarts, seed=i).fit()
        homo = Cascade(
            [trial.d2, trial.d1], "homoscedastic", n_restarts=config.n_restarts, seed=i
        ).fit(first=fitted.models[0])
        a, b_bayes, b_homo = fitted.models[0], fitted.models[1], homo.models[1]
        ref_rng = np.random.default_rng(i)
        pairs = [
            (a.log_marginal_likelihood, reference_lml(a.x, a.y, None, ref_rng)),
            (
                b_bayes.log_marginal_likelihood,
                reference_lml(b_bayes.x, b_bayes.y, b_bayes.noise, ref_rng),
            ),
            (b_homo.log_marginal_likelihood, reference_lml(b_homo.x, b_homo.y, None, ref_rng)),
        ]
        for ours, ref in pairs:
            worst = max(worst, ref - ours)
            checked += 1
    return checked, worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--trials", type=int, default=12000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--sample", type=int, default=30, help="trials in the quality check")
    args = ap.parse_args()
    config = StudyConfig()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        out = run_study(tmp, trials=args.trials, config=config, workers=args.workers)
        wall = time.perf_counter() - t0
    s = out.summary
    print(
        f"study: {args.trials} trials, {args.workers} workers, {wall:.1f} s wall, "
        f"{args.trials / wall:.1f} trials/s"
    )
    sec = s["seconds_per_trial"]
    cpu = sum(sec.values())
    print(
        f"CPU per trial {cpu * 1e3:.1f} ms:",
        ", ".join(f"{k} {v * 1e3:.1f} ms" for k, v in sorted(sec.items())),
    )
    print(
        "median J [µm]:", ", ".join(f"{m} {v['median'] * 1e6:.2f}" for m, v in s["methods"].items())
    )
    checked, worst = quality(config, args.sample)
    verdict = "OK" if worst <= 1e-3 else "WORSE"
    print(
        f"quality: {checked} stage fits on {args.sample} trials vs five-start L-BFGS-B: "
        f"largest LML shortfall {worst:.2e} ({verdict}; negative means ours is better)"
    )


if __name__ == "__main__":
    main()
