"""``cascal study``: the paper's Monte Carlo study from the command line, with progress."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

__all__ = ["Progress", "add_study_parser"]


def _columns(stream) -> int:
    """Width of the terminal ``stream`` is, in characters; 0 where it has none."""
    import os

    try:
        return os.get_terminal_size(stream.fileno()).columns
    except (OSError, ValueError, AttributeError):
        return 0


class Progress:
    """A bar with rate and ETA on a terminal; sparse plain lines otherwise (logs, CI)."""

    def __init__(self, stream=None, every_s: float = 15.0, unit: str = "trial") -> None:
        self.stream = stream or sys.stderr
        self.unit = unit
        self.tty = self.stream.isatty() and _columns(self.stream) > 0  # (tqdm draws no bar
        # on a terminal of no width, as a pseudo-terminal whose size was never set)
        self.bar = None
        self.every_s = every_s
        self.t0 = 0.0  # (the first call's time)
        self.last = -1e9
        self.start_done = 0

    def __call__(self, done: int, total: int) -> None:
        if self.tty:
            if self.bar is None:
                from tqdm import tqdm

                self.bar = tqdm(total=total, initial=done, unit=self.unit, file=self.stream)
                self.start_done = done
            else:
                self.bar.update(done - self.bar.n)
            if done >= total:  # the rate of the trials, not of writing the outputs after
                self.close()
            return
        now = time.perf_counter()
        if self.last < -1e8:  # (the rate counts from here: not the set-up before)
            self.start_done, self.last, self.t0 = done, now, now
            return
        if done < total and now - self.last < self.every_s:
            return
        self.last = now
        rate = (done - self.start_done) / max(now - self.t0, 1e-9)
        eta = f"{(total - done) / rate:.0f} s" if rate > 0 else "unknown (none done yet)"
        print(
            f"{done}/{total} {self.unit}s ({100 * done / total:.0f} %), {rate:.1f} {self.unit}s/s, "
            f"ETA {eta}",
            file=self.stream,
            flush=True,
        )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _cmd_study(args: argparse.Namespace) -> int:
    from .cli import check_output, check_writable
    from .montecarlo import StudyConfig
    from .study import OUTPUTS, run_study

    check_output(args.out, folder=True, option="--out")
    for name in OUTPUTS:  # (a review: a write-protected output was replaced)
        check_writable(Path(args.out) / name, f"--out {args.out}: {name}")
    config = StudyConfig(seed=args.seed, n_restarts=args.restarts)
    progress = Progress()
    t0 = time.perf_counter()
    try:
        outcome = run_study(
            args.out,
            trials=args.trials,
            config=config,
            workers=args.workers,
            scheduler=args.scheduler,
            progress=progress,
            notice=lambda line: print(f"{line}...", file=sys.stderr, flush=True),
        )
    except KeyboardInterrupt as exc:  # Ctrl-C, SIGTERM: what was stored stays
        raise type(exc)(f"the trials stored in {args.out} stay: the same command resumes") from None
    finally:
        progress.close()
    wall = time.perf_counter() - t0 - outcome.compile_s
    s = outcome.summary
    print(f"Study of {s['n_trials']} trials in {args.out}/ ({outcome.ran} run now, {wall:.1f} s).")
    if outcome.compile_s:
        print(
            f"Before it, compiling the study's code took {outcome.compile_s:.1f} s "
            "(once: later runs load it from Numba's cache)."
        )
    if outcome.stored > s["n_trials"]:
        print(
            f"The folder holds {outcome.stored} trials; its outputs now cover the first "
            f"{s['n_trials']} (run with --trials {outcome.span} for all)."
        )
    print(f"{'method':>14} {'median J':>12} {'mean J':>12} {'q10':>10} {'q90':>10}  [µm]")
    for m, st in s["methods"].items():
        print(
            f"{m:>14} {st['median'] * 1e6:12.3f} {st['mean'] * 1e6:12.3f} "
            f"{st['q10'] * 1e6:10.3f} {st['q90'] * 1e6:10.3f}"
        )
    for pair, st in s["pairs"].items():
        a = pair.split(" vs ")[0]
        print(
            f"{pair:>30}: {a} better in {100 * st['fraction_a_better']:.1f} % of trials, "
            f"Wilcoxon p {_p(st['wilcoxon_p'])}"
        )
    print(f"Bijectivity redraws: {s['redraws']}. Figure: {args.out}/cost_distribution.png")
    return 0


def _p(p: float) -> str:
    """A p-value as text; 0.0 means it underflowed double precision."""
    return "< 1e-300" if p == 0.0 else f"= {p:.2e}"


def _trials(text: str) -> int:
    """argparse type: a trial count from 1 to 10^8 (the pending trials are listed)."""
    from .cli import positive_int

    value = positive_int(text)
    if value > 10**8:
        raise argparse.ArgumentTypeError(f"expected at most 100000000 trials, got {value}")
    return value


def add_study_parser(sub) -> None:
    """Register ``cascal study`` on the subparsers ``sub``."""
    from .cli import restarts, seed, worker_count

    p = sub.add_parser("study", help="run the paper's Monte Carlo study (resumable)")
    p.add_argument("--trials", type=_trials, default=12000, help="number of trials (12000)")
    p.add_argument("--seed", type=seed, default=0, help="root seed (0)")
    p.add_argument("--restarts", type=restarts, default=3, help="optimiser starts (3)")
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=worker_count,
        default=None,
        help="processes (default: the CPUs this process may use)",
    )
    where.add_argument(
        "--scheduler", default=None, help="Dask scheduler address, e.g. tcp://h:8786"
    )
    p.add_argument("--out", default="out/study", help="output folder (out/study)")
    p.set_defaults(func=_cmd_study)
