"""The ``cascal`` command: subcommands parse arguments, load, call the library once, write.

Bad input ends with a one-line message on stderr and exit status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from . import __version__
from .errors import CascalError

__all__ = ["main"]

EXIT_BAD_INPUT = 2


def _cmd_example(args: argparse.Namespace) -> int:
    """Simulate one cascade as in the paper, fit the three methods, print J, draw Fig. 4."""
    import numpy as np

    from .cascade import METHODS, Cascade
    from .io.atomic import save_figure
    from .plots import plot_cascade
    from .simulation import cost_j, simulate_trial

    trial = simulate_trial(np.random.default_rng(args.seed))
    print(f"Simulated cascade (seed {args.seed}): D2 = {trial.d2[0].size} test-bed/reference")
    print(f"pairs with gaps at the ends and centre, D1 = {trial.d1[0].size} device/test-bed pairs.")
    print(f"J of the uncorrected device: {cost_j(trial, correct=lambda r: r) * 1e6:9.3f} µm")
    fits = {}
    for method in METHODS:
        fits[method] = Cascade([trial.d2, trial.d1], method, seed=args.seed).fit()
        j = cost_j(trial, correct=fits[method].correct)
        print(f"J {method:>13}: {j * 1e6:9.3f} µm")
    truths = [trial.testbed_map.inverse, trial.device_map.inverse]
    fig = plot_cascade(fits["bayes"], truths=truths)
    path = save_figure(fig, Path(args.out) / "example_cascade.png", dpi=130)
    print(f"Figure (stage fits, targets with error bars, true map): {path}")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cascal", description="Cascaded calibration of position sensors with GPs."
    )
    p.add_argument("--version", action="version", version=f"cascal {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    ex = sub.add_parser("example", help="simulate one cascade as in the paper and fit it")
    ex.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ex.add_argument("--out", default="out", help="output folder (default out/)")
    ex.set_defaults(func=_cmd_example)
    from .cli_study import add_study_parser

    add_study_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cascal`` console script; returns the exit status."""
    args = _parser().parse_args(argv)
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except CascalError as exc:
        print(f"cascal {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"cascal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
