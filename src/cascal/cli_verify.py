"""``cascal verify``: a model against independent check points (device reading, reference)."""

from __future__ import annotations

import argparse

__all__ = ["add_verify_parser"]

#: Warn when the RMS of error / u exceeds this. Neighbouring check points share the
#: calibration's error, so they count as few independent ones; but even one standard normal
#: error exceeds 3 in only 0.27 % of cases.
_TOO_LARGE = 3.0


def _cmd_verify(args: argparse.Namespace) -> int:
    import numpy as np

    from .cli import EXIT_FAILURE, check_outputs, warn
    from .errors import InputError
    from .io.csvout import auto_decimals, write_columns
    from .io.data import read_table
    from .io.modelfile import load_model
    from .verification import expected_within
    from .workflow import verify_model

    check_outputs(args.output, args.plot, inputs=(args.model, args.check))
    for option, value in (("--reading-u", args.reading_u), ("--reference-u", args.reference_u)):
        if value is not None and not (0 <= value < 1e150):
            raise InputError(f"{option}: expected a number >= 0 below 1e150, got {value}")
    if args.mpe is not None and not (0 < args.mpe < 1e150):
        raise InputError(f"--mpe: expected a number > 0 below 1e150, got {args.mpe}")
    model = load_model(args.model)
    hint = "; choose two by name with --x-column and --y-column"
    table = read_table(args.check, (args.x_column, args.y_column), hint=hint)
    reading, reference = table.columns
    v = verify_model(
        model,
        reading,
        reference,
        u_reading=args.reading_u,
        u_reference=args.reference_u or 0.0,
        mpe=args.mpe,
    )
    s, unit = v.summary(), model.unit
    lo, hi = model.calibrated_range
    if s["points"] == 0:
        raise InputError(
            f"no check point lies inside the calibrated range [{lo:.9g}, {hi:.9g}] {unit}",
            file=args.check,
        )
    outside = ""
    if s["outside_range"]:
        first = int(table.rows[np.argmax(~v.inside)])
        outside = f" ({s['outside_range']} outside the calibrated range left out)"
        warn(
            "verify",
            f"{s['outside_range']} of {v.inside.size} check points lie outside the calibrated "
            f"range [{lo:.9g}, {hi:.9g}] {unit} (first: {args.check}, row {first}); left out",
        )
    print(f"Verified {args.model} at {s['points']} check points of {args.check}{outside}.")
    m = v.inside
    worst = int(np.flatnonzero(m)[np.argmax(np.abs(v.error[m]))])
    print(f"  error before correction: RMS {s['rms_before']:.4g} {unit}")
    print(
        f"  error after correction:  RMS {s['rms_after']:.4g} {unit}"
        f"{_ratio(s['rms_before'], s['rms_after'])}, largest "
        f"{abs(v.error[worst]):.4g} {unit} (row {int(table.rows[worst])}, "
        f"reading {v.reading[worst]:.9g})"
    )
    source = " (given)" if args.reading_u is not None else " (the model's learned noise)"
    if v.has_u:
        uc = v.u_calibration[m]
        print(
            f"  standard uncertainty: calibration {uc.min():.3g} to {uc.max():.3g} {unit}, "
            f"one reading {v.u_reading:.3g} {unit}{source}, reference {v.u_reference:.3g} {unit}"
        )
        expected = expected_within(v.k)
        print(
            f"  |error| <= U = {v.k:g} u at {s['within_U']} of {s['points']} points "
            f"({100 * s['within_U'] / s['points']:.1f} %, about {100 * expected:.1f} % expected); "
            f"RMS of error / u {s['rms_normalised']:.3g} (about 1 expected)"
        )
        if s["rms_normalised"] > _TOO_LARGE:
            warn(
                "verify",
                f"the errors are {s['rms_normalised']:.3g} times their standard uncertainty "
                "(RMS): the model's uncertainty is too small for these check points; has the "
                "device or the test bed changed since the fit, or are --reading-u and "
                "--reference-u too small?",
            )
    else:
        warn("verify", "method lut gives no uncertainty: En and the U columns are left empty")
    bad = 0
    if v.conforms is not None:
        bad = s["points"] - s["conforming"]
        rule = f"|error| + {v.k:g} u_reference <= MPE"
        print(
            f"  MPE {v.mpe:.4g} {unit}: {s['conforming']} of {s['points']} points conform ({rule})"
        )
    if args.output is not None:
        cols = {
            "reading": v.reading,
            "reference": v.reference,
            "corrected": v.corrected,
            "error": v.error,
            "u_calibration": v.u_calibration,
            "u": v.u,
            "U": v.k * v.u,
            "En": v.en,
            "out_of_range": ~v.inside,
        }
        if v.mpe is not None:
            cols["conforms"] = v.conforms
        decimals = auto_decimals(
            [v.reading[m], v.reference[m], v.corrected[m]], v.u[m] if v.has_u else None
        )
        print(f"Check points written to {write_columns(args.output, cols, decimals=decimals)}")
    if args.plot is not None:
        from .io.atomic import save_figure
        from .report import verification_figure

        fig = verification_figure(model, v)
        print(f"Figure written to {save_figure(fig, args.plot, dpi=130)}")
    if bad:
        first = int(table.rows[np.argmax(m & ~v.conforms)])
        print(
            f"Verification failed: {bad} check point(s) not shown to conform to the MPE "
            f"(first: row {first})."
        )
        return EXIT_FAILURE
    print("Verification passed." if v.mpe is not None else "No --mpe given: reported, not judged.")
    return 0


def _ratio(before: float, after: float) -> str:
    if after < before:
        return f" ({before / after:.0f}x smaller)" if after > 0 else " (none left)"
    return " (no smaller than before: is this the model of this device?)"


def add_verify_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``cascal verify`` on the subparsers ``sub``."""
    p = sub.add_parser(
        "verify",
        help="check a model against independent check points (device reading, reference)",
        description="Correct the device readings of check points the fit never saw and "
        "compare them with the reference: errors before and after correction, how many lie "
        "within the expanded uncertainty U = 2u, and, with --mpe, conformance to a maximum "
        "permissible error (exit status 1 when a point is not shown to conform).",
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
        type=float,
        metavar="S",
        help="standard uncertainty of one device reading, in the model's unit (default: the "
        "white noise the last stage learned, which errs on the large side; 0 for lut)",
    )
    p.add_argument(
        "--reference-u",
        type=float,
        metavar="S",
        help="standard uncertainty of one reference value (default 0: taken as exact)",
    )
    p.add_argument(
        "--mpe",
        type=float,
        metavar="E",
        help="maximum permissible error: a point conforms when |error| + 2 u_reference <= E",
    )
    p.add_argument("-o", "--output", metavar="VERIFY.csv", help="write every check point as CSV")
    p.add_argument("--plot", metavar="VERIFY.png", help="draw the errors (PNG, SVG or PDF)")
    p.set_defaults(func=_cmd_verify)
