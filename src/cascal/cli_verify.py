"""``cascal verify``: a model against independent check points (device reading, reference)."""

from __future__ import annotations

import argparse

__all__ = ["add_verify_parser"]

#: Warn when the RMS of error / u exceeds this (or lies below its inverse). Neighbouring
#: check points share the calibration's error, so they count as few independent ones; but
#: even one standard normal error exceeds 3 in only 0.27 % of cases.
_TOO_LARGE = 3.0


def _cmd_verify(args: argparse.Namespace) -> int:
    import numpy as np

    from .cli import (
        EXIT_NOT_CONFORMING,
        HUGE,
        check_outputs,
        file_label,
        load_checked,
        warn,
        warn_homoscedastic,
        write_outputs,
    )
    from .errors import InputError
    from .io.atomic import save_figure
    from .io.csvout import auto_decimals, exact_decimals, write_columns
    from .io.data import check_units, read_table
    from .text import measured_ends, range_text
    from .verification import expected_within
    from .workflow import verify_model

    check_outputs(args.output, args.plot, inputs=(args.model, args.check))
    if args.x_column is not None and args.x_column == args.y_column:
        raise InputError(f"--x-column and --y-column both name {args.x_column!r}; give two")
    model = load_checked(args.model, o=args.output, plot=args.plot)
    warn_homoscedastic("verify", model)
    hint = "; choose two by name with --x-column and --y-column"
    table = read_table(args.check, (args.x_column, args.y_column), hint=hint, max_abs=HUGE)
    reading, reference = table.columns
    check_units(reading, reference, table.source.columns, args.check)  # (warns: mm and m?)
    v = verify_model(
        model,
        reading,
        reference,
        u_reading=args.reading_u,
        u_reference=args.reference_u,
        mpe=args.mpe,
    )
    s, unit = v.summary(), model.unit
    lo, hi = model.calibrated_range
    where = f"the calibrated range {range_text(lo, hi)} {unit}"
    if model.periodic:  # every turn is calibrated, less an arc the device readings left out
        from .workflow import unmeasured_arc

        where = f"the range a float64 holds to better than u (any turn of {model.period:g} {unit})"
        arc = unmeasured_arc(model)
        if arc is not None:
            a, b = measured_ends(arc)
            where = (
                f"the arc {a} to {b} {unit} (of any turn of "
                f"{model.period:g} {unit}) that the device readings cover"
            )
    if s["points"] == 0:
        from .workflow import far_off

        far = not model.periodic and far_off(reading, lo, hi)
        hint = f": all far off, in another unit than the model's ({unit})?" if far else ""
        raise InputError(f"no check point lies inside {where}{hint}", file=args.check)
    fig = None
    if args.plot is not None:  # drawn before anything is written
        from .report import verification_figure

        names = (file_label(args.model, "a model"), file_label(args.check, "check points"))
        fig = verification_figure(model, v, names)
    m = v.inside
    outside = ""
    first_out = int(table.rows[np.argmax(~m)])  # (the first row when none is outside)
    if s["outside_range"]:
        outside = f"; {s['outside_range']} outside {where} left out"
        warn(
            "verify",
            f"{s['outside_range']} of {m.size} check points lie outside {where} (first: "
            f"{args.check}, row {first_out}); they are not judged",
        )
    n = s["points"]
    print(f"Verified {args.model} at {_points(n)} of {args.check}{outside}.")
    worst = int(np.flatnonzero(m)[np.argmax(np.abs(v.error[m]))])
    print(
        f"  error before correction: RMS {s['rms_before']:.4g} {unit}, largest "
        f"{s['max_before']:.4g} {unit}"
    )
    print(
        f"  error after correction:  RMS {s['rms_after']:.4g} {unit}"
        f"{_ratio(s['rms_before'], s['rms_after'])}, largest {abs(v.error[worst]):.4g} {unit} "
        f"(row {int(table.rows[worst])}, reading {v.reading[worst]:.9g})"
    )
    reading_note = "" if args.reading_u else " (not given: --reading-u)"
    reference_note = "" if args.reference_u else " (taken as exact: --reference-u)"
    if v.has_u:
        uc = v.u_calibration[m]
        print(
            f"  standard uncertainty: calibration {uc.min():.3g} to {uc.max():.3g} {unit}, "
            f"one reading {v.u_reading:.3g} {unit}{reading_note}, reference "
            f"{v.u_reference:.3g} {unit}{reference_note}"
        )
        z = s["rms_normalised"]
        print(
            f"  |error| <= U = {v.k:g} u at {s['within_U']} of {n} "
            f"({100 * s['within_U'] / n:.1f} %, about {100 * expected_within(v.k):.1f} % "
            f"expected); RMS of error / u {z:.3g} (about 1 expected)"
        )
        if z > _TOO_LARGE:
            warn(
                "verify",
                f"the errors are {z:.3g} times their standard uncertainty (RMS): the model's "
                "uncertainty is too small for these check points; has the device or the test "
                "bed changed since the fit, or are --reading-u and --reference-u too small?",
            )
        elif z < 1.0 / _TOO_LARGE:
            warn(
                "verify",
                f"the errors are only {z:.3g} times their standard uncertainty (RMS): these "
                "check points test little of the model's uncertainty; are --reading-u and "
                "--reference-u too large?",
            )
    else:
        warn("verify", "method lut gives no uncertainty: En and the U columns are left empty")
    bad = 0
    if v.conforms is not None:
        bad = n - s["conforming"]
        rule = f"|error| + {v.k:g} u_reference <= MPE"
        print(f"  MPE {v.mpe:.4g} {unit}: {s['conforming']} of {n} conform ({rule})")
        if not args.reference_u:
            warn(
                "verify",
                "reference values taken as exact (no --reference-u): the MPE check has no "
                "guard band for the reference's own uncertainty",
            )
    if args.output is not None:
        judged = np.where(m, 1.0, np.nan)  # points outside the range are not judged
        cols = {
            "reading": v.reading,
            "reference": v.reference,
            "corrected": v.corrected,
            "error": v.error,
            "u_calibration": v.u_calibration,
            "u": v.u,
            "U": v.k * v.u,
            "En": v.en * judged,
            "out_of_range": ~m,
        }
        if v.conforms is not None:
            cols["conforms"] = np.ma.masked_array(v.conforms, ~m)
        shared = auto_decimals(
            [v.reading[m], v.reference[m], v.corrected[m]], v.u[m] if v.has_u else None
        )
        decimals = [shared] * len(cols)  # the check file's own columns as read
        decimals[0] = exact_decimals(v.reading, shared)[0]
        decimals[1] = exact_decimals(v.reference, shared)[0]
    write_outputs(
        ("Check points", args.output, lambda: write_columns(args.output, cols, decimals=decimals)),
        ("Figure", args.plot, lambda: save_figure(fig, args.plot, dpi=130)),
    )
    not_judged = ""
    if s["outside_range"]:
        not_judged = f"; {s['outside_range']} outside the range not judged"
    if bad:
        first = int(table.rows[np.argmax(m & ~v.conforms)])
        print(
            f"Verification failed: {_points(bad)} not shown to conform to the MPE "
            f"(first: row {first}){not_judged}."
        )
        return EXIT_NOT_CONFORMING
    if v.mpe is not None and s["outside_range"]:  # a go/no-go passes on every point only
        print(
            f"Verification failed: {_points(s['outside_range'])} outside the range, not "
            f"judged, so not shown to conform to the MPE (first: row {first_out}); the "
            f"{_points(n)} inside conform."
        )
        return EXIT_NOT_CONFORMING
    if v.mpe is not None:
        print(f"Verification passed: all {_points(n)} conform.")
    else:
        print("No --mpe given: reported, not judged.")
    return 0


def _points(n: int) -> str:
    return f"{n} check point{'' if n == 1 else 's'}"


def _ratio(before: float, after: float) -> str:
    if after < before:
        return f" ({before / after:.0f}x smaller)" if after > 0 else " (none left)"
    return " (no smaller than before: is this the model of this device?)"


def add_verify_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cascal verify`` on the subparsers ``sub``."""
    from .cli import add_outputs, nonnegative, positive

    p = sub.add_parser(
        "verify",
        help="check a model against independent check points (device reading, reference)",
        description="Correct the device readings of check points the fit never saw and "
        "compare them with the reference: errors before and after correction, how many lie "
        "within the expanded uncertainty U = 2u, and, with --mpe, conformance to a maximum "
        "permissible error (exit status 3 when a point is not shown to conform).",
    )
    p.add_argument("model", metavar="MODEL.json")
    p.add_argument(
        "check",
        metavar="CHECK.csv",
        help="check points: device reading, then the reference's value (header row)",
    )
    p.add_argument("--x-column", metavar="NAME", help="column of the device readings")
    p.add_argument("--y-column", metavar="NAME", help="column of the reference values")
    p.add_argument(
        "--reading-u",
        type=nonnegative,
        default=0.0,
        metavar="S",
        help="standard uncertainty of one device reading (its repeatability), in the model's "
        "unit (default 0: not counted)",
    )
    p.add_argument(
        "--reference-u",
        type=nonnegative,
        default=0.0,
        metavar="S",
        help="standard uncertainty of one reference value (default 0: taken as exact)",
    )
    p.add_argument(
        "--mpe",
        type=positive,
        metavar="E",
        help="maximum permissible error: a point conforms when |error| + 2 u_reference <= E",
    )
    add_outputs(p, "VERIFY", "every check point", "the errors", _cmd_verify)
