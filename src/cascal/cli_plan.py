"""``cascal plan``: where to take the next reference measurements of the test bed."""

from __future__ import annotations

import argparse

__all__ = ["INTERVAL_OPTIONS", "add_plan_parser"]

#: Plans of more measurements than this show progress.
_QUIET = 20
#: A plan that lowers the RMS u by less than this fraction is reported as of little use.
_NEGLIGIBLE = 1e-3
#: Options whose value may start with a minus sign (see :func:`cascal.cli.join_negative`).
INTERVAL_OPTIONS = ("--reach", "--where")


def _cmd_plan(args: argparse.Namespace) -> int:
    import numpy as np

    from .cli import check_outputs, load_checked, warn, write_outputs
    from .cli_study import Progress
    from .errors import InputError
    from .io.atomic import save_figure
    from .io.csvout import auto_decimals, write_columns
    from .planning import MAX_MEASUREMENTS
    from .workflow import plan_measurements

    check_outputs(args.output, args.plot, inputs=(args.model,))
    if args.n > MAX_MEASUREMENTS:
        raise InputError(f"-n: expected at most {MAX_MEASUREMENTS} measurements, got {args.n}")
    model = load_checked(args.model, o=args.output, plot=args.plot)
    reach = [_interval(r, "--reach") for r in args.reach] if args.reach else None
    where = None if args.where is None else _interval(args.where, "--where")
    _check_reach(model, reach, warn)
    progress = Progress(unit="measurement") if args.n > _QUIET else None
    try:
        mp = plan_measurements(
            model, args.n, reach=reach, where=where, noise_std=args.noise_std, progress=progress
        )
    finally:
        if progress is not None:
            progress.close()
    plan, unit = mp.plan, model.unit
    spans = ", ".join(f"[{a:.9g}, {b:.9g}]" for a, b in mp.reach)
    print(
        f"{plan.positions.size} reference measurement(s) proposed for stage 0 "
        f"({model.data[0].name}) from {mp.candidates} candidate readings in {spans} {unit}; "
        f"each measurement's standard deviation {np.sqrt(plan.noise_variance):.3g} {unit}."
    )
    print(f"Lowered: {mp.target} ({plan.where.size} points).")
    head = [f"test-bed reading [{unit}]", f"RMS u after [{unit}]", f"largest u after [{unit}]"]
    w = [max(len(h), 12) for h in head]
    print(f"{'order':>5}  {head[0]:>{w[0]}}  {head[1]:>{w[1]}}  {head[2]:>{w[2]}}")
    print(f"{'now':>5}  {'':>{w[0]}}  {plan.u_rms[0]:{w[1]}.4g}  {plan.u_max[0]:{w[2]}.4g}")
    for k, p in enumerate(plan.positions, 1):
        print(f"{k:5d}  {p:{w[0]}.9g}  {plan.u_rms[k]:{w[1]}.4g}  {plan.u_max[k]:{w[2]}.4g}")
    if args.noise_std is not None and plan.noise_variance > args.noise_std**2:
        warn(
            "plan",
            f"--noise-std {args.noise_std:g} raised to {np.sqrt(plan.noise_variance):.3g} "
            f"{unit}, the least this plan resolves (10^-4 of stage 0's prior u)",
        )
    if not plan.u_rms[-1] < (1.0 - _NEGLIGIBLE) * plan.u_rms[0]:
        warn(
            "plan",
            f"these measurements lower the RMS u by less than {100 * _NEGLIGIBLE:g} %: the "
            "reachable readings tell little about where the uncertainty counts",
        )
    if args.output is not None:
        cols = {
            "order": np.arange(1, plan.positions.size + 1),
            "reading": plan.positions,
            "u_rms": plan.u_rms[1:],
            "u_max": plan.u_max[1:],
        }
        decimals = auto_decimals([plan.positions], plan.u_rms[1:])
    fig = None
    if args.plot is not None:
        from .report import plan_figure

        fig = plan_figure(model, mp)
    write_outputs(
        ("Plan", args.output, lambda: write_columns(args.output, cols, decimals=decimals)),
        ("Figure", args.plot, lambda: save_figure(fig, args.plot, dpi=130)),
    )
    return 0


def _check_reach(model, reach: list[tuple[float, float]] | None, warn) -> None:
    """Warn of a ``--reach`` interval more than the span of the test-bed readings the
    model holds (stage 0's, and stage 1's targets) away from them: measurements there
    inform none of its corrections, and its unit may differ (a review's case: 5:6 on a
    1 m axis planned five measurements with no word of it); and, more mildly, of one
    wholly outside them."""
    import numpy as np

    from .text import range_text
    from .workflow import far_off

    if not reach or model.periodic:  # (a periodic model plans on one turn: any reading)
        return
    known = np.concatenate([model.data[0].x, *(d.y for d in model.data[1:2])])
    lo, hi = float(known.min()), float(known.max())
    for a, b in reach:
        if far_off(np.array([a, b]), lo, hi):
            warn(
                "plan",
                f"--reach {a:.9g}:{b:.9g} lies more than their span away from the test-bed "
                f"readings of the model ({range_text(lo, hi)} {model.unit}): measurements "
                "there inform none of its corrections (readings in another unit?)",
            )
        elif b < lo or a > hi:  # (a review's case: 0.5:0.9 typed for 0.05:0.09)
            warn(
                "plan",
                f"--reach {a:.9g}:{b:.9g} lies wholly outside the test-bed readings of the "
                f"model ({range_text(lo, hi)} {model.unit}): measurements there inform only "
                "the corrections near its nearer end (a typing slip?)",
            )


def _interval(text: str, option: str) -> tuple[float, float]:
    """``LO:HI`` (or a single reading ``X``) as a checked pair of floats."""
    from .cli import as_number
    from .errors import InputError
    from .planning import check_interval

    parts = text.split(":")
    try:
        values = [as_number(p) for p in parts]
    except ValueError:
        values = []
    if len(values) not in (1, 2) or len(values) != len(parts):
        raise InputError(f"{option} {text!r}: expected LO:HI or a single reading")
    return check_interval((values[0], values[-1]), f"{option} {text!r}")


def add_plan_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cascal plan`` on the subparsers ``sub``."""
    from .cli import add_outputs, nonnegative, positive_int

    p = sub.add_parser(
        "plan",
        help="propose where to take the next reference measurements of the test bed",
        description="Propose reference measurements of stage 0 (the test bed), one at a time, "
        "each where it most lowers the uncertainty that matters: the device's (the last "
        "stage's) for a bayes model, else the test bed's where it is used.",
    )
    p.add_argument("model", metavar="MODEL.json")
    p.add_argument(
        "-n", type=positive_int, default=5, help="measurements to propose (default 5, at most 1000)"
    )
    p.add_argument(
        "--reach",
        action="append",
        metavar="LO:HI",
        help="test-bed readings the reference can reach; repeat for several intervals, or "
        "give a single reading; --reach=-0.04:0.3 or --reach -0.04:0.3 for a negative LO "
        "(default: the stretches the reference points cover, leaving out gaps wider than 3 "
        "median spacings, and a tenth of the span or 3 times the spacings beside them)",
    )
    p.add_argument(
        "--where",
        metavar="LO:HI",
        help="test-bed readings where the uncertainty counts (one-stage models; default: "
        "the span of the reference points, one turn for a periodic model)",
    )
    p.add_argument(
        "--noise-std",
        type=nonnegative,
        default=None,
        metavar="S",
        help="standard deviation of one new reference measurement, in the model's unit "
        "(default: as precise as the average existing point)",
    )
    add_outputs(p, "PLAN", "the plan", "the plan", _cmd_plan)
