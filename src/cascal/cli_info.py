"""``cascal info``: what a model file holds, in the terminal, and whether its input files
are still as they were when it was fitted."""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

__all__ = ["add_info_parser", "file_sha256", "input_paths", "input_status"]


def input_status(
    file: str | Path, sha256: str, base: Path | None = None
) -> tuple[str, Path | None]:
    """``"unchanged"``, ``"changed since the fit"``, ``"not found"`` (or, for a model made
    from arrays, that there is no file), and the path
    checked: the file a model names against the SHA-256 recorded for it. The path is as
    given to the fit; a relative one is looked for from here, from ``base`` (the model
    file's folder) and by its name alone in ``base``, and any of them that matches counts."""
    if str(file).startswith("<") and str(file).endswith(">"):  # CalibrationModel.from_cascade
        return "fitted from arrays in Python, no file", None
    found = input_paths(file, base)
    for path in found:
        if file_sha256(path) == sha256:
            return "unchanged", path
    return ("changed since the fit", found[0]) if found else ("not found", None)


def file_sha256(path: str | Path) -> str | None:
    """The SHA-256 (hex) of the regular file ``path``, or None where there is none to read."""
    p = Path(path)
    try:
        if not p.is_file():
            return None
        with p.open("rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except OSError:
        return None


def input_paths(file: str | Path, base: Path | None = None) -> list[Path]:
    """The existing files that a model's input ``file`` may be: the path as given to the
    fit, from here, from ``base`` (the model file's folder) and by its name alone in
    ``base``."""
    candidates = [Path(file)]
    if base is not None and not Path(file).is_absolute():
        candidates += [base / file, base / Path(file).name]
    return [p for p in dict.fromkeys(candidates) if p.is_file()]


def _cmd_info(args: argparse.Namespace) -> int:
    from .cli import model_lines, warn, warn_cautions
    from .io.modelfile import load_model_checksum, schema_version
    from .workflow import summarize_device

    model, checksum = load_model_checksum(args.model)
    n = len(model.fitted.models)
    print(f"{args.model}: cascal model file, schema {schema_version(model)}, checksum verified")
    digest = file_sha256(args.model)  # (None for a pipe)
    file = "" if digest is None else f"SHA-256 of the file {digest}; "
    print(f"{file}content checksum (sha256) {checksum}")
    print(
        f"Fitted {model.created} with cascal {model.cascal_version} (seed {model.seed}, "
        f"{model.n_restarts} optimiser starts per stage)"
    )
    kernel = "" if model.kernel is None else f", kernel {model.kernel}"
    period = "" if model.period is None else f" (period {model.period:g})"
    print(f"Method {model.method}{kernel}{period}, unit {model.unit}, {n} stage{'s' * (n > 1)}")
    changed = []
    for k, line in enumerate(model_lines(model)):
        print(line)
        if k >= n:
            continue
        gp, src = model.fitted.models[k], model.sources[k]
        lml = getattr(gp, "log_marginal_likelihood", None)
        if lml is not None:
            jitter = f"jitter {gp.jitter:.3g}" if gp.jitter else "no jitter"
            print(f"  log marginal likelihood {lml:.6g}, {jitter}")
        status, path = input_status(src.file, src.sha256, Path(args.model).parent)
        where = f" (as {path})" if path is not None and str(path) != src.file else ""
        print(f"  input {src.file} (columns {', '.join(src.columns)}): {status}{where}")
        if status == "unchanged":
            print(f"    SHA-256 {src.sha256}")
        elif status == "changed since the fit":
            print(f"    SHA-256 {src.sha256} at the fit, {file_sha256(path)} now")
            changed.append(str(path))
        else:
            print(f"    SHA-256 {src.sha256} at the fit")
    s = summarize_device(model)
    u = s["max_u"]
    largest = "no uncertainty (lookup tables)" if u != u else f"largest u {u:.3g} {model.unit}"
    print(f"Correction over it: RMS {s['rms_correction']:.3g} {model.unit}, {largest}")
    for file in changed:
        warn("info", f"{file} is not the file this model was fitted from (its SHA-256 differs)")
    warn_cautions("info", model)
    # a changed input fails the check, for a script to see (a user review: status 0), as
    # verify's and compare's failed checks do; an input not found cannot be checked
    return EXIT_CHANGED if changed else 0


#: Exit status of ``cascal info`` where an input file differs from the one fitted.
EXIT_CHANGED = 3


def add_info_parser(sub) -> None:
    """Register ``cascal info`` on the subparsers ``sub``."""
    p = sub.add_parser(
        "info",
        help="summarise a model file and check its input files against their checksums",
        description="Summarise a model file (stages, hyperparameters, calibrated range, "
        "warnings about its u) and check the stage files it was fitted from against the "
        "checksums it stores: exit status 3 where one differs.",
    )
    p.add_argument("model", metavar="MODEL.json")
    p.set_defaults(func=_cmd_info)
