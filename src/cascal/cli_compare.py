"""``cascal compare``: a recalibration against the calibration before it."""

from __future__ import annotations

import argparse

__all__ = ["add_compare_parser"]


def _cmd_compare(args: argparse.Namespace) -> int:
    import numpy as np

    from .cli import (
        EXIT_NOT_CONFORMING,
        check_outputs,
        file_label,
        load_checked,
        warn,
        write_outputs,
    )
    from .io.atomic import save_figure
    from .io.csvout import auto_decimals, write_columns
    from .text import range_ends, range_text
    from .verification import BAND_LEVEL, breaks
    from .workflow import compare_models, measured_arc, same_readings

    check_outputs(args.output, args.plot, inputs=(args.old, args.new))
    old = load_checked(args.old, o=args.output, plot=args.plot)
    new = load_checked(args.new, o=args.output, plot=args.plot)
    c = compare_models(old, new)
    s, unit = c.summary(), old.unit
    differ = [  # the stages whose readings differ (compare refused other numbers of stages)
        k
        for k, (a, b) in enumerate(zip(old.data, new.data, strict=True))
        if not same_readings(a, b)
    ]
    if not differ:
        warn(
            "compare",
            "both models were fitted on the same readings: the band below is what two "
            "independent calibrations of an unchanged device would differ by, not a "
            "recalibration",
        )
    parts = np.split(c.reading, breaks(c.reading))  # (two where rotary arcs meet twice)
    span = f"their common range {range_text(c.reading[0], c.reading[-1])} {unit}"
    if old.periodic:
        span = f"one turn (period {old.period:g} {unit})"
        if measured_arc(old) or measured_arc(new):
            ends = [range_ends(p[0], p[-1]) for p in parts]
            span = (
                "the part of the turn both models' device readings cover, "
                + " and ".join(f"{a} to {b}" for a, b in ends)
                + f" {unit} (period {old.period:g})"
            )
    print(
        f"Compared {args.new} (new) with {args.old} (old) over {span}, {c.reading.size} readings."
    )
    print(
        f"  old: fitted {old.created}, method {old.method}; new: fitted {new.created}, "
        f"method {new.method}"
    )
    at = _at(parts, s["at"])
    print(
        f"  change of the correction (new - old): RMS {s['rms_change']:.4g} {unit}, largest "
        f"{s['max_change']:.4g} {unit} at reading {at}"
    )
    fig = None
    if args.plot is not None:  # drawn before anything is written
        from .report import comparison_figure

        names = (file_label(args.old, "a model"), file_label(args.new, "a model"))
        fig = comparison_figure(old, c, names, limit=args.max_change)
    if c.has_u:
        how = (  # (a review: with three stages the stages they share are more than the test bed)
            "the test bed's calibration both share counted once"
            if c.shared and len(old.fitted.models) <= 2
            else "the upstream calibrations both share counted once"
            if c.shared
            else "their upstream calibrations counted as independent"
            if len(old.fitted.models) > 1
            else "no upstream stage"
        )
        print(
            f"  standard uncertainty the change would have if the device had not changed "
            f"({how}): {c.u.min():.3g} to {c.u.max():.3g} {unit}"
        )
        band = (
            f"an unchanged device's |change| / u stays below {c.k_band:.2f} over the whole "
            f"range with {100 * BAND_LEVEL:g} % probability"
        )
        z_at = _at(parts, s["max_z_at"])
        print(f"  largest |change| / u {s['max_z']:.3g}, at reading {z_at}; {band}")
        if c.changed:
            # (a review: a test bed's recalibration, the device file unchanged, had been
            # called a change of the device; another: a middle stage's, the test bed's)
            named = [  # (a diff review: "stage 0, the test bed's calibration, stage 1, ...")
                "stage 0 (the test bed's calibration)"
                if k == 0
                else f"stage {k} ({new.data[k].name})"
                for k in differ
            ]
            above = " and ".join(filter(None, [", ".join(named[:-1]), *named[-1:]]))
            cause = (
                f"the device's readings are the same in both models, so the stages above it "
                f"changed, not the device: {above}"
                if differ and differ[-1] < len(old.data) - 1
                else "the device (or its mounting) has changed since the old calibration"
                if differ
                else "the two fits of the same readings differ (their settings), not the device"
            )
            print(
                f"  beyond that band over {100 * s['share_beyond_band']:.1f} % of the range: "
                f"{cause}"
            )
        else:
            print(
                "  within that band everywhere: no change shown beyond what the two "
                f"calibrations' uncertainties explain (pointwise, |change| > {c.k:g} u over "
                f"{100 * s['share_beyond_U']:.1f} % of the range)"
            )
    else:
        warn("compare", "method lut gives no uncertainty: only the change is reported")
    if args.output is not None:
        cols = {
            "reading": c.reading,
            "old": c.old,
            "new": c.new,
            "change": c.change,
            "u_old": c.u_old,
            "u_new": c.u_new,
            "u": c.u,
            "En": c.en,
        }
        decimals = auto_decimals([c.reading, c.old, c.new], c.u if c.has_u else None)
    write_outputs(
        ("Readings", args.output, lambda: write_columns(args.output, cols, decimals=decimals)),
        ("Figure", args.plot, lambda: save_figure(fig, args.plot, dpi=130)),
    )
    if args.max_change is None:
        return 0
    t, v = args.max_change, c.against(args.max_change)
    largest = f"largest change {s['max_change']:.4g} {unit} at reading {at}"
    if not c.has_u:
        if v.verdict == "beyond":
            print(
                f"Changed by more than --max-change {t:g} {unit} over "
                f"{100 * v.share_beyond:.1f} % of the range ({largest}; no uncertainty: "
                "judged by the change alone)."
            )
            return EXIT_NOT_CONFORMING
        print(f"Within --max-change {t:g} {unit} everywhere (judged by the change alone).")
        return 0
    k = f"{c.k_band:.2f} u"
    if v.share_unresolved > 0:  # (a review: an unchanged device failed a --max-change
        # below the band in 22 of 40 recalibrations, as the change's noise fell)
        warn(
            "compare",
            f"--max-change {t:g} {unit} is within the band ({k}, up to "
            f"{c.k_band * float(np.max(c.u)):.3g} {unit}) over {100 * v.share_unresolved:.1f} % "
            "of the range: there the two calibrations cannot show even an unchanged device "
            "within it",
        )
    if v.verdict == "within":
        print(
            f"Within --max-change {t:g} {unit} everywhere, the change's uncertainty counted "
            f"(|change| + {k} <= {t:g} {unit})."
        )
        return 0
    if v.verdict == "beyond":
        print(
            f"Changed by more than --max-change {t:g} {unit}, beyond its uncertainty "
            f"(|change| - {k} > {t:g} {unit}), over {100 * v.share_beyond:.1f} % of the "
            f"range ({largest})."
        )
    else:
        print(
            f"Not shown within --max-change {t:g} {unit}: |change| + {k} exceeds it over "
            f"{100 * v.share_not_within:.1f} % of the range, and nowhere is the change beyond "
            f"it by more than its uncertainty ({largest})."
        )
    return EXIT_NOT_CONFORMING


def _at(parts, v: float) -> str:
    """A compared reading ``v``, printed within the stretch of ``parts`` (the compared
    readings' stretches, each increasing) that holds it, as that stretch's ends are
    printed."""
    from .text import reading_in_range

    part = next(p for p in parts if p[0] <= v <= p[-1])
    return reading_in_range(v, float(part[0]), float(part[-1]))


def add_compare_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cascal compare`` on the subparsers ``sub``."""
    from .cli import add_outputs, positive

    p = sub.add_parser(
        "compare",
        help="compare a recalibration of a device with its calibration before",
        description="Correct the same device readings with two models of one device (old, "
        "then new) over their common calibrated range and report how much the correction "
        "changed, against the uncertainty the change would have if the device had not changed "
        "(a test-bed calibration both share counted once) and a simultaneous 95 % band over "
        "the range; with --max-change, exit status 3 unless the change, its uncertainty "
        "counted (the band), is shown within it.",
    )
    p.add_argument("old", metavar="OLD.json", help="the earlier calibration")
    p.add_argument("new", metavar="NEW.json", help="the recalibration")
    p.add_argument(
        "--max-change",
        type=positive,
        metavar="T",
        help="largest change of the correction accepted, in the models' unit: passed where "
        "|change| + the band (k u) stays within it everywhere, failed where |change| - the "
        "band exceeds it somewhere, else not shown within it (also status 3)",
    )
    add_outputs(p, "CHANGE", "the readings compared", "the change", _cmd_compare)
