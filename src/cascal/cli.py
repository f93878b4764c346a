"""The ``cascal`` command: subcommands parse arguments, load, call the library once, write.

Bad input ends with a one-line message on stderr and exit status 2, without a traceback
and without an output file. Library calls print nothing; this module prints.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import stat
import sys
import tempfile
import time
import typing
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

from ._version import __version__
from .errors import CascalError, InputError, WorkerError
from .io.atomic import is_stdout

__all__ = ["main"]

EXIT_BAD_INPUT = 2
EXIT_FAILURE = 1  # an output could not be written, or some devices of a fleet failed
EXIT_NOT_CONFORMING = 3  # cascal verify: a check point is not shown to conform to the MPE
EXIT_BROKEN_PIPE = 141  # the reader of stdout left (as a shell reports a process SIGPIPE ended)
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT, as a shell reports)
EXIT_TERMINATED = 143  # SIGTERM, where the command stops its workers first (128 + SIGTERM)


def _cmd_example(args: argparse.Namespace) -> int:
    """Simulate one cascade as in the paper, fit the three methods, print J, draw Fig. 4."""
    import numpy as np

    from .cascade import METHODS, Cascade
    from .io.atomic import save_figure
    from .plots import plot_cascade
    from .simulation import cost_j, simulate_trial

    check_output(args.out, folder=True, option="--out")
    trial = simulate_trial(np.random.default_rng(args.seed))
    print(f"Simulated cascade (seed {args.seed}): D2 = {trial.d2[0].size} test-bed/reference")
    print(f"pairs with gaps at the ends and centre, D1 = {trial.d1[0].size} device/test-bed pairs.")
    print(f"J of the uncorrected device: {cost_j(trial, correct=lambda r: r) * 1e6:9.3f} µm")
    fits = {}
    for method in METHODS:
        fits[method] = Cascade([trial.d2, trial.d1], method, seed=args.seed).fit()
        j = cost_j(trial, correct=fits[method].correct)
        print(f"J {method:>13}: {j * 1e6:9.3f} µm")
    # the true maps a little beyond [0, 1] too: stage 0 is drawn over the test-bed readings
    # stage 1 asks of it, a noise draw past the map's ends included
    truths = [
        lambda r, m=m: m.inverse(r, -0.25, 1.25) for m in (trial.testbed_map, trial.device_map)
    ]
    fig = plot_cascade(fits["bayes"], truths=truths, upper=[trial.d1[1]])
    path = save_figure(fig, Path(args.out) / "example_cascade.png", dpi=130)
    print(f"Figure (stage fits, targets with error bars, true map): {path}")
    return 0


def check_output(
    path: str | Path,
    *,
    folder: bool = False,
    option: str = "-o",
    inputs: Sequence[str | Path] = (),
) -> None:
    """Refuse an output path that cannot be written, before any work: a folder where a
    file is due (or a file where a folder is), a location under a file or in a folder
    this process may not write to, or one of the command's ``inputs`` (named by ``option``
    in messages)."""
    p = Path(path)
    if str(path) == "":
        what = "folder" if folder else "file"
        raise InputError(f"{option}: expected a {what} name, got an empty one")
    if is_stdout(path):
        if folder:
            raise InputError(f"{option} {path}: expected a folder, not standard output")
        return
    _check_name_lengths(p, option)
    if folder and p.exists() and not p.is_dir():
        raise InputError(f"{option} {p}: expected a folder, got an existing file")
    if folder and p.is_symlink() and not p.exists():
        raise InputError(f"{option} {p}: a link to {os.readlink(p)}, which does not exist")
    if not folder and p.is_dir():
        raise InputError(f"{option} {p}: expected a file name, got an existing folder")
    last = os.path.basename(str(path))
    if not folder and last in ("", ".", ".."):
        raise InputError(  # (a review: "odir/" and "odir/." wrote a file "odir")
            f"{option} {path}: expected a file name, got a folder's (ending in {last or '/'})"
        )
    for other in inputs:  # also a path through a folder not made yet and then "..", resolved
        # as the writer will take it once it has made that folder, links and all (a review:
        # -o nosuch/../ref.csv had replaced the input ref.csv)
        if same_file(p, other):
            raise InputError(
                f"{option} {path}: is an input of this command ({other}); not overwritten"
            )
    try:
        mode = os.stat(p).st_mode  # through links
    except OSError:
        mode = None
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        return  # a device or a named pipe: written in place
    target = Path(os.path.realpath(p)) if p.is_symlink() else p  # a link's file is replaced
    parent = (target if folder else target.parent).absolute()
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"{option} {p}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{option} {p}: no permission to write in {parent}")
    try:  # what the write will do first (root passes os.access on a read-only /proc too)
        fd, probe = tempfile.mkstemp(prefix=".cascal-probe.", dir=parent)
    except OSError as exc:
        why = f"cannot create a file in {parent}: {exc.strerror}"
        raise InputError(f"{option} {p}: {why}") from None
    os.close(fd)
    os.unlink(probe)
    if not folder:
        check_writable(p, f"{option} {path}")


def file_label(path: str | Path, what: str = "a file") -> str:
    """The name of the input file ``path`` for a title or header, or ``"<what> read from a
    pipe"`` where it is none (``/dev/fd/63`` of a process substitution, standard input):
    a review found titles naming "63"."""
    from .text import shown

    p = Path(path)
    return shown(p.name) if p.is_file() else f"{what} read from a pipe"


def _check_name_lengths(p: Path, option: str) -> None:
    """Refuse a path with a part longer than its file system takes, or longer in all than
    the system does (a fuzz review: the write failed after the work, with exit 1)."""
    where = p.absolute().parent
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        most, whole = os.pathconf(where, "PC_NAME_MAX"), os.pathconf(where, "PC_PATH_MAX")
    except (OSError, ValueError, AttributeError):  # (no pathconf: Windows)
        most, whole = 255, 4096
    text = str(p)
    short = text if len(text) <= 60 else f"{text[:40]}...{text[-16:]} ({len(text)} characters)"
    for part in p.parts:
        if len(os.fsencode(part)) > most:
            raise InputError(
                f"{option} {short}: a name of {len(os.fsencode(part))} bytes in the path, "
                f"longer than the file system takes ({most})"
            )
    if len(os.fsencode(str(p.absolute()))) >= whole:
        raise InputError(f"{option} {short}: a path longer than the system takes ({whole} bytes)")


def check_writable(path: Path, what: str) -> None:
    """Refuse (naming it ``what``) an existing file ``path`` that is write-protected: no
    write bit for anyone, or none for this user. The atomic write's rename would replace
    it, needing only the folder's permission (a review's leftover); `rm` asks first."""
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return
    if stat.S_ISREG(mode) and (not mode & 0o222 or not os.access(path, os.W_OK)):
        raise InputError(
            f"{what}: the file is write-protected; not replaced (make it writable, or "
            "choose another name)"
        )


def check_outputs(output: str | None, plot: str | None, inputs: Sequence[str | Path]) -> None:
    """Refuse, before any work, a table ``-o`` and a figure ``--plot`` that cannot be
    written (:func:`check_output`), a figure of another format than PNG, SVG or PDF, or
    both naming one file."""
    if output is not None:
        check_output(output, inputs=inputs)
    if plot is None:
        return
    check_output(plot, option="--plot", inputs=inputs)
    if Path(plot).suffix.lower() not in (".png", ".svg", ".pdf"):
        raise InputError(f"--plot {plot}: expected a .png, .svg or .pdf file name")
    if output is not None and same_file(plot, output):
        raise InputError(f"--plot {plot}: the same file as -o; give two names")


def write_outputs(*outputs: tuple[str, str | None, Callable[[], Path]]) -> None:
    """Write each ``(what, path, write)`` whose path is given, all or none (a failed second
    file leaves the first's old content: :func:`cascal.io.atomic.together`), then say
    where each went."""
    from .io.atomic import together

    done = []
    with together():
        for what, path, write in outputs:
            if path is not None:
                done.append((what, write()))
    for what, path in done:
        print(f"{what} written to {path}")


def load_checked(model: str, **outputs: str | None):
    """The model file ``model``, loaded and checked by :func:`check_not_inputs`."""
    from .io.modelfile import load_model

    loaded = load_model(model)
    check_not_inputs(model, loaded, **outputs)
    return loaded


def check_not_inputs(model: str, loaded, **outputs: str | None) -> None:
    """Refuse an output (by option name: ``o=...``, ``plot=...``; None for none) that is
    one of the files the model ``loaded`` from file ``model`` was fitted from: found as
    ``cascal info`` finds them, or, wherever it lies, an existing file whose SHA-256 is
    one the model recorded (a fit run from another folder: a review's report written over
    ``../data/reference.csv``). Writing it would destroy that file."""
    from .cli_info import file_sha256, input_paths

    for option, out in outputs.items():
        if out is None or is_stdout(out):
            continue
        flag = f"-{option}" if len(option) == 1 else f"--{option}"
        for src in loaded.sources:
            for path in input_paths(src.file, Path(model).parent):
                if same_file(out, path):
                    raise InputError(
                        f"{flag} {out}: is the input file {src.file} of {model}; not overwritten"
                    )
        digest = file_sha256(out)
        for src in loaded.sources:
            if digest is not None and digest == src.sha256:
                raise InputError(
                    f"{flag} {out}: holds the input file {src.file} of {model} (the same "
                    "SHA-256); not overwritten"
                )


def add_outputs(p: argparse.ArgumentParser, stem: str, table: str, figure: str, func) -> None:
    """Register the ``-o STEM.csv`` table (``table``: what it holds), the ``--plot
    STEM.png`` figure (``figure``: what it draws) and the handler ``func`` of a command."""
    p.add_argument("-o", "--output", metavar=f"{stem}.csv", help=f"write {table} as CSV")
    p.add_argument("--plot", metavar=f"{stem}.png", help=f"draw {figure} (PNG, SVG or PDF)")
    p.set_defaults(func=func)


def same_file(a: str | Path, b: str | Path) -> bool:
    """True when paths ``a`` and ``b`` name the same regular file, or the same location
    (links and ``..`` resolved) when one does not exist yet. Devices such as
    ``/dev/stdout`` are never the same file as anything."""
    pa, pb = Path(a), Path(b)
    try:
        if pa.exists() and pb.exists():
            return pa.is_file() and pb.is_file() and os.path.samefile(pa, pb)
        return pa.resolve() == pb.resolve()
    except (OSError, RuntimeError):  # (RuntimeError: a loop of links, on Python 3.11)
        return False


#: Options that take a number, whose value may start with a minus sign (see join_negative).
NUMBER_OPTIONS = (
    "--noise-std",
    "--reading-u",
    "--reference-u",
    "--mpe",
    "--tolerance",
    "--period",
    "--max-change",
)


def join_negative(argv: list[str]) -> list[str]:
    """``--reach -0.04:0.3`` as ``--reach=-0.04:0.3`` (for the options that take a number,
    a reading or an interval): argparse takes a value that starts with ``-`` and is not a
    plain decimal (``-1e-3``) for an option. Nothing after ``--`` is changed."""
    from .cli_plan import INTERVAL_OPTIONS

    options = INTERVAL_OPTIONS + NUMBER_OPTIONS
    out: list[str] = []
    for i, a in enumerate(argv):
        if a == "--":
            return out + argv[i:]
        if out and out[-1] in options and _negative_value(a):
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


def _negative_value(text: str) -> bool:
    """True for ``-X`` or ``-X:Y`` with numbers X and Y."""
    if text[:1] != "-":
        return False
    try:
        [as_number(p) for p in text.split(":")]
    except ValueError:
        return False
    return True


def rows_text(rows) -> str:
    """``row 41`` or ``rows 41, 42 and 43``."""
    rows = [int(r) for r in rows]
    if len(rows) == 1:
        return f"row {rows[0]}"
    return "rows " + ", ".join(map(str, rows[:-1])) + f" and {rows[-1]}"


def exclusions(specs: Sequence[str] | None, paths: Sequence[str | Path]) -> list[frozenset[int]]:
    """Per file of ``paths``, the rows ``--exclude FILE:ROWS`` leaves out. FILE is one of
    ``paths`` (the same file, or its name alone where that is unique); ROWS are file rows
    as the warnings name them (the header is row 1): ``41``, ``41,57`` or ``50-52``."""
    out: list[set[int]] = [set() for _ in paths]
    for spec in specs or ():
        file, sep, rows = spec.rpartition(":")
        if not sep or not file or not rows.strip():
            raise InputError(
                f"--exclude {spec}: expected FILE:ROWS, e.g. reference.csv:41 or "
                "reference.csv:41,50-52"
            )
        hits = [i for i, p in enumerate(paths) if same_file(file, p)]
        if not hits and not Path(file).exists():  # a name alone, or a path from elsewhere
            hits = [i for i, p in enumerate(paths) if Path(p).name == Path(file).name]
        if len(hits) != 1:
            given = ", ".join(str(p) for p in paths)
            what = "names several of" if hits else "is none of"
            named = [p for p in paths if Path(p).name == Path(file).name]
            hint = ""
            if not hits and len(named) == 1:  # the name alone, but a file of that path exists
                hint = f"; {file} is another file here: write --exclude {named[0]}:{rows}"
            raise InputError(f"--exclude {spec}: {file} {what} the stage files ({given}){hint}")
        out[hits[0]] |= _row_numbers(rows, spec, _line_count(paths[hits[0]]))
    return [frozenset(s) for s in out]


def _line_count(path: str | Path) -> int | None:
    """Lines of a file (LF, CRLF or CR), its last row number; None when it cannot be read
    (reading it then says why)."""
    try:
        raw = Path(path).read_bytes().replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    except OSError:
        return None
    return raw.count(b"\n") + (not raw.endswith(b"\n"))


def _row_numbers(text: str, spec: str, last: int | None = None) -> set[int]:
    """The rows of ``41,57,50-52``; rows count from 1, the header, so data rows from 2, and
    none lies past ``last``."""
    rows: set[int] = set()
    for part in text.split(","):
        lo, dash, hi = part.strip().partition("-")
        try:
            a, b = as_whole(lo), as_whole(hi if dash else lo)
        except ValueError:
            raise InputError(
                f"--exclude {spec}: expected row numbers such as 41,57 or 50-52, got {part!r}"
            ) from None
        if a > b:
            raise InputError(f"--exclude {spec}: {part.strip()} is an empty range of rows")
        if a < 2:
            raise InputError(
                f"--exclude {spec}: row {a} is no data row (row 1 is the header, data rows "
                "start at 2)"
            )
        if last is not None and b > last:
            raise InputError(
                f"--exclude {spec}: row {b} lies past the end of the file (its last row is {last})"
            )
        rows.update(range(a, b + 1))
    return rows


def _cmd_fit(args: argparse.Namespace) -> int:
    """Fit stage files (reference end first) and write a model file."""
    from .cli_screening import SKIPPED, report_screening
    from .io.modelfile import save_model
    from .workflow import fit_model, screen_stages

    check_output(args.output, inputs=args.stages)
    data = _read_stages(args.stages, args)
    model = fit_model(data, **_fit_kwargs(args))
    path = save_model(args.output, model)
    print("\n".join(model_lines(model)))
    _report_chain("fit", model.sources)
    warn_cautions("fit", model)
    if args.no_screening:
        print(SKIPPED)
    else:
        report_screening("fit", screen_stages(model, data, level=_level(args)), model.unit)
    print(f"Model written to {path}")
    return 0


def _cmd_correct(args: argparse.Namespace) -> int:
    """Correct device readings with a model; write reading, corrected, u, U, out_of_range."""
    import numpy as np

    from .io.csvout import auto_decimals, exact_decimals, write_columns
    from .io.data import read_readings
    from .text import measured_ends, range_text
    from .workflow import correct, far_off, unmeasured_arc

    check_output(args.output, inputs=(args.model, args.readings))
    model = load_checked(args.model, o=args.output)
    table = read_readings(args.readings, column=args.column)
    warn_homoscedastic("correct", model)
    c = correct(model, table.columns[0])
    out = c.out_of_range
    n_out = int(np.count_nonzero(out))
    lo, hi = model.calibrated_range
    where = f"outside the calibrated range {range_text(lo, hi)} {model.unit}"
    arc = unmeasured_arc(model)  # (a periodic model's part of the turn never measured)
    if model.periodic:  # every turn is calibrated: only a reading too large is flagged
        where = "so far out that a float64 holds them less finely than their u"
        if arc is not None:
            a, b = measured_ends(arc)
            where = (
                f"in the part of the turn the device readings leave out ({b} to {a} "
                f"{model.unit}), or {where}"
            )
    unit_hint = ""
    if n_out == out.size > 1 and not model.periodic and far_off(c.reading, lo, hi):
        unit_hint = f"; all far off: readings in another unit than the model's ({model.unit})?"
    if n_out and args.out_of_range == "error":
        first = int(table.rows[np.argmax(out)])
        raise InputError(f"{n_out} reading(s) {where}{unit_hint}", file=args.readings, row=first)
    corrected, u = c.corrected, c.u
    if n_out and args.out_of_range == "empty":
        corrected, u = np.where(out, np.nan, corrected), np.where(out, np.nan, u)
    gp = not np.all(np.isnan(c.u))
    columns = {
        "reading": c.reading,
        "corrected": corrected,
        "u": u,
        "U": 2.0 * u,
        "out_of_range": out,
    }
    inside = ~out  # far-off readings must not cost the others their decimals
    decimals = auto_decimals([c.reading[inside], c.corrected[inside]], c.u[inside] if gp else None)
    given, exact = exact_decimals(c.reading, decimals)  # the readings as read, not rounded
    path = write_columns(args.output, columns, decimals=[given] + [decimals] * 3 + [0])
    if n_out:
        first = int(table.rows[np.argmax(out)])
        what = "left empty" if args.out_of_range == "empty" else "extrapolated, do not trust them"
        if model.periodic and args.out_of_range != "empty":
            what = "rounded beyond their u, do not trust them"
            if arc is not None:
                what = "extrapolated or rounded beyond their u, do not trust them"
        warn(
            "correct",
            f"{n_out} of {out.size} readings lie {where} (first: {args.readings}, row {first}); "
            f"flagged in column out_of_range and {what}{unit_hint}",
        )
    if not gp:
        warn("correct", "method lut gives no uncertainty: columns u and U are left empty")
    what = "reading" if out.size == 1 else "readings"
    as_read = ""
    if given > decimals:
        as_read = f"; readings as read, {given}" if exact else f"; readings {given}"
    print(f"Corrected {out.size} {what} -> {path} ({decimals} decimals{as_read})")
    return 0


def _cmd_fit_devices(args: argparse.Namespace) -> int:
    """Fit the test bed once, then every device file in a folder against it, in parallel."""
    from .cli_screening import SKIPPED, report_findings, report_screening, screening_lines
    from .io.atomic import write_text
    from .io.modelfile import save_model
    from .pool import default_workers
    from .text import HOMOSCEDASTIC_U, turn_text
    from .workflow import fit_devices, fit_findings, fit_model, model_path, screen_stages

    check_output(args.output, folder=True)
    folder = Path(args.devices)
    if not folder.is_dir():
        what = "a file, not a folder" if folder.exists() else "no such folder"
        raise InputError(f"--devices {folder}: {what}")
    if Path(args.output).resolve() == folder.resolve():  # its summary: a device file next time
        raise InputError(f"-o {args.output}: the same folder as --devices; give another")
    # a link to a file that is gone (a share not mounted) is a device that cannot be read,
    # reported as such (a review: it had been left out without a word)
    entries = [p for p in folder.iterdir() if p.suffix.lower() == ".csv"]
    hidden = sorted(p.name for p in entries if p.name.startswith("."))  # macOS's ._x.csv:
    entries = [p for p in entries if not p.name.startswith(".")]  # no device (a review)
    files = sorted(p for p in entries if p.is_file() or not p.exists())
    # a folder or a pipe named *.csv: reported as a device skipped, never read (a pipe
    # would wait for a writer; a review found them left out without a word)
    odd = sorted(p for p in entries if p.exists() and not p.is_file())
    left_out = f"{len(hidden)} hidden file(s) left out ({_listed(hidden)})" if hidden else ""
    if not files:  # (what it holds named: a review)
        named = "".join(f"; {p.name} is {_not_a_file(p)}" for p in odd[:3])
        named += f"; {left_out}" if left_out else ""
        raise InputError(f"no .csv device files in folder {folder}{named}")
    if hidden:
        warn("fit-devices", f"--devices {folder}: {left_out}")
    from .workflow import DeviceResult

    others = [DeviceResult(p.stem, str(p), error=f"{p} is {_not_a_file(p)}") for p in odd]
    stems: dict[str, Path] = {}
    for f in files:  # each device's model is <stem>.json
        other = stems.setdefault(f.stem.casefold(), f)
        if other != f:
            raise InputError(
                f"--devices {folder}: {other.name} and {f.name} would both be device "
                f"{f.stem}; rename one"
            )
    out = Path(args.output)
    tb_path, summary_path = out / "testbed.json", out / "fleet_summary.csv"
    written = [tb_path, summary_path, *(out / "devices" / f"{f.stem}.json" for f in files)]
    for path in written:  # e.g. a test-bed file kept as <out>/testbed.json
        check_writable(path, f"-o {args.output}: {path}")  # (a review: only -o files were)
        for other in (args.testbed, *files):
            if path.exists() and same_file(path, other):
                raise InputError(
                    f"-o {args.output}: would overwrite {path}, an input of this command "
                    f"({other}); give another folder"
                )
    skip = exclusions(args.exclude, [args.testbed, *files])
    (tb_x, dev_x), (tb_y, dev_y) = (
        _fleet_columns(args.x_column, "--x-column"),
        _fleet_columns(args.y_column, "--y-column"),
    )
    (testbed,) = _read_stages([args.testbed], args, skip[:1], columns=(tb_x, tb_y))
    tb = fit_model([testbed], **_fit_kwargs(args))
    notes: dict[str, list[str]] = {}  # each device's warnings, for the summary too
    finished = []  # as reported: an interrupted fleet's summary lists these

    def interrupted(exc: KeyboardInterrupt) -> None:
        """Summarise the devices done, list every other as not fitted, keeping no model of
        an earlier run (a review: those never started were left out, their old models
        beside the summary; a second: a new testbed.json beside the old devices' models,
        interrupted before the first device), say so and raise ``exc`` again. A further
        signal waits until the summary is written (one had cut it short)."""
        from .pool import Terminated, deferred_signals
        from .workflow import INTERRUPTED, DeviceResult, discard_model, model_path

        with deferred_signals():
            n_done = sum(r.error != INTERRUPTED for r in finished)  # (a review: the rest
            fitted = {r.device for r in finished}  # had been counted too)
            for f in files:
                if f.stem not in fitted:
                    discard_model(model_path(out / "devices", f))
                    finished.append(DeviceResult(f.stem, str(f), error=INTERRUPTED))
            finished.extend(others)
            finished.sort(key=lambda r: Path(r.file).name)  # file order, as a finished run's
            path = write_text(summary_path, _fleet_csv(finished, notes, tb.unit))
            what = "terminated" if isinstance(exc, Terminated) else "interrupted"
            warn("fit-devices", f"{what} after {n_done} of {len(files)} devices: {path}")
        raise exc

    every: list[str] = []  # cautions of every device's u, in each one's summary row too
    try:
        tb_model = save_model(tb_path, tb)
        print(f"Test bed fitted once: {tb_model}")
        with _collected(every):  # (a review: no row carried the test bed's)
            report_findings("fit-devices", fit_findings(tb), [tb.sources[0].file], tb.unit)
        every[:] = [f"test bed: {line}" for line in every]
        if args.method == "homoscedastic":  # (a review: fit gave it, fit-devices not)
            warn("fit-devices", HOMOSCEDASTIC_U)
            every.append(HOMOSCEDASTIC_U)
        level = None if args.no_screening else _level(args)
        if level is None:
            print(SKIPPED)
        else:
            checks = screen_stages(tb, [testbed], level=level)
            report_screening("fit-devices", checks, tb.unit, " of the test bed")
    except KeyboardInterrupt as exc:
        interrupted(exc)
    options = dict(
        _fit_kwargs(args),
        x_column=dev_x,
        y_column=dev_y,
        screening_level=level,
        exclude={str(f): sorted(e) for f, e in zip(files, skip[1:], strict=True) if e},
    )

    t0, done = time.perf_counter(), [0]
    headers: set = set()  # the pairs of headers warned of

    def report(r) -> None:
        finished.append(r)  # first: an interrupt while its lines print keeps it summarised
        into = notes.setdefault(r.device, [])
        if not r.error:
            into += every
        with _collected(into):
            _report_device(r)

    def _report_device(r) -> None:
        done[0] += 1
        rate = done[0] / max(time.perf_counter() - t0, 1e-9)
        eta = (len(files) - done[0]) / rate
        where = f"[{done[0]}/{len(files)}, {rate:.2g} devices/s, ETA {eta:.0f} s]"
        for line in r.warnings:  # (a record joining rows may be why a device is skipped)
            warn("fit-devices", line)
        if r.error:
            with _collected([]):  # not in the summary's warnings: its column error holds it
                warn("fit-devices", f"{where} skipped device {r.device}: {r.error}")
        else:
            n_rows = len(r.screening.rows) if r.screening else 0
            suspect = f", {n_rows} suspect row{'s' * (n_rows > 1)}" if n_rows else ""
            u = (  # (a review: "largest u nan m" for a lookup table)
                f"largest u {r.max_u:.4g} {tb.unit}" if r.max_u == r.max_u else "no u (lut)"
            )
            print(
                f"  {where} {r.device}: rms correction {r.rms_correction:.4g} {tb.unit}, "
                f"{u}{suspect}",
                flush=True,
            )
            if r.arc is not None:  # (a review: a partly measured rotary device, in silence)
                turn = turn_text(r.arc, tb.unit, float(tb.period))
                warn("fit-devices", f"{r.device}: calibrated over {turn}")
            for line in screening_lines(r.screening, tb.unit) if r.screening else ():
                warn("fit-devices", line)
            stage_files = [tb.sources[0].file, r.file]
            report_findings("fit-devices", r.findings, stage_files, tb.unit)
            if r.source is not None:
                _report_chain("fit-devices", [tb.sources[0], r.source], headers)

    jobs = args.jobs or default_workers()
    try:
        results = fit_devices(
            tb_model, files, out / "devices", options=options, jobs=jobs, on_result=report
        )
    except KeyboardInterrupt as exc:  # the summary of this run's devices so far
        interrupted(exc)
    for r in others:
        warn("fit-devices", f"skipped device {r.device}: {r.error}")
    results = sorted([*results, *others], key=lambda r: Path(r.file).name)  # (file order)
    summary = write_text(summary_path, _fleet_csv(results, notes, tb.unit))
    n_bad = sum(r.error is not None for r in results)
    n_sus = sum(bool(r.screening and r.screening.rows) for r in results)
    if level is not None:
        print(
            f"Outlier screening of the devices: {n_sus} of {len(results) - n_bad} with "
            "suspect rows (column suspect_rows of the summary)"
        )
    print(f"{len(results) - n_bad} of {len(results)} devices calibrated; summary: {summary}")
    # a model is current where it is a device's model file: by name, or, on a file system
    # that ignores case, the same file (a review: dev01.json beside DEV01.json, from a file
    # renamed by case, had gone unnamed)
    models = [model_path(out / "devices", f) for f in files]
    names = {m.name for m in models}
    stale = sorted(
        p.name
        for p in (out / "devices").glob("*.json")
        if p.name not in names and not any(same_file(p, m) for m in models)
    )
    if stale:  # an earlier run's devices: kept, but no longer in the summary
        warn(
            "fit-devices",
            f"{out / 'devices'}: {len(stale)} model(s) of devices with no file in {folder} now "
            f"({_listed(stale)}): left as they were, "
            "not in the summary",
        )
    return EXIT_FAILURE if n_bad else 0


def _cmd_report(args: argparse.Namespace) -> int:
    """Write a self-contained HTML report of a model file."""
    from .cli_info import file_sha256
    from .io.atomic import write_text
    from .io.modelfile import load_model_checksum
    from .report import build_report

    check_output(args.output, inputs=(args.model,))
    model, checksum = load_model_checksum(args.model)
    check_not_inputs(args.model, model, o=args.output)
    if not is_stdout(args.output) and Path(args.output).suffix.lower() not in (".html", ".htm"):
        raise InputError(f"-o {args.output}: expected an .html file name (the report is HTML)")
    page = build_report(
        model,
        source=file_label(args.model, "a model"),
        checksum=checksum,
        sha256=file_sha256(args.model),
    )
    path = write_text(args.output, page)
    print(f"Report written to {path}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    """Simulate a linear and a rotary cascade; fit, correct, report, export, plan, verify;
    recalibrate the linear device after a drift and compare."""
    from .cli_demo import run_demo

    check_output(args.out, folder=True, option="--out")
    return run_demo(Path(args.out), seed=args.seed, main=main)


def _read_stages(
    paths: Sequence[str],
    args: argparse.Namespace,
    skip: list[frozenset[int]] | None = None,
    columns: tuple[str | None, str | None] | None = None,
) -> list:
    """The stage files, with the options' columns (or ``columns``, x and y of every file),
    period and excluded rows (``skip``, per file; default from ``--exclude``)."""
    from .io.data import read_stage

    n = len(paths)
    if columns is None:
        xs = _per_file(args.x_column, n, "--x-column")
        ys = _per_file(args.y_column, n, "--y-column")
    else:
        xs, ys = [columns[0]] * n, [columns[1]] * n
    skip = exclusions(args.exclude, paths) if skip is None else skip
    period = args.period if args.kernel == "periodic" else None
    if args.kernel == "periodic" and period is None:
        raise InputError("--kernel periodic needs --period (e.g. --period 360 for degrees)")
    if args.kernel != "periodic" and args.period is not None:
        raise InputError(
            f"--period is the period of --kernel periodic, not of {args.kernel}: add "
            "--kernel periodic for a rotary axis, or leave --period out"
        )
    if args.period is not None and not (0 < args.period < float("inf")):
        raise InputError(f"--period: expected a positive number, got {args.period!r}")
    stages = [
        read_stage(p, x_column=x, y_column=y, period=period, exclude=e)
        for p, x, y, e in zip(paths, xs, ys, skip, strict=True)
    ]
    _check_unit_names(stages, args.unit, args.command)
    return stages


#: Units a column's name may carry (``position_mm``, ``x [um]``, ``angle (deg)``).
_NAMED_UNITS = ("nm", "um", "µm", "mm", "cm", "m", "deg", "rad", "arcsec")


def _check_unit_names(stages: list, unit: str, command: str) -> None:
    """Warn where a stage's column names carry a unit other than ``unit`` (a user review:
    columns named ``encoder_mm`` fitted as metres, --unit left at its default, every
    label 1000 times off)."""
    pattern = re.compile(r"(?:^|[_\s\[(])(" + "|".join(_NAMED_UNITS) + r")(?:$|[\])\s])", re.I)

    def norm(u: str) -> str:  # (µm and um are one unit)
        return u.lower().replace("µ", "u")

    for stage in stages:
        named = {norm(m.group(1)) for c in stage.source.columns if (m := pattern.search(c))}
        other = sorted(named - {norm(unit)})
        if other and len(named) == 1:
            cols = ", ".join(stage.source.columns)
            warn(
                command,
                f"{stage.source.file}: its columns ({cols}) name the unit {other[0]}, and the "
                f"readings are taken as {unit} (--unit): give --unit {other[0]} if they are",
            )


def _per_file(values: list[str] | None, n: int, option: str) -> list[str | None]:
    if not values:
        return [None] * n
    if len(values) == 1:
        return values * n
    if len(values) != n:
        raise InputError(
            f"{option}: give it once (all files) or once per file ({n}), got {len(values)}"
        )
    return list(values)


def _fleet_columns(values: list[str] | None, option: str) -> tuple[str | None, str | None]:
    """A fleet's column of the test bed and of the devices: ``option`` given once names
    both, twice the test bed's, then the devices'."""
    if not values:
        return None, None
    if len(values) > 2:
        raise InputError(
            f"{option}: give it once (the test bed and every device) or twice (the test "
            f"bed's, then the devices'), got {len(values)}"
        )
    return values[0], values[-1]


def _fit_kwargs(args: argparse.Namespace) -> dict[str, object]:
    if args.mean != "identity" and args.method == "lut":
        raise InputError(
            f"--mean {args.mean}: the lookup tables of --method lut have no prior mean; "
            "leave --mean out, or choose a GP method"
        )
    if args.kernel in ("matern32", "matern52") and args.method == "lut":
        raise InputError(
            f"--kernel {args.kernel}: the lookup tables of --method lut have no kernel; "
            "leave --kernel out, or choose a GP method"
        )
    if args.kernel == "periodic" and args.method == "lut":  # (a review: it was ignored)
        raise InputError(
            "--kernel periodic: the lookup tables of --method lut do not wrap at the turn "
            "(their model and compensation table would not be rotary); fit a rotary axis "
            "with a GP method (--method bayes)"
        )
    return dict(
        method=args.method,
        kernel=args.kernel,
        period=args.period,
        unit=args.unit,
        n_restarts=args.restarts,
        seed=args.seed,
        mean=args.mean,
    )


def _report_chain(command: str, sources: Sequence, seen: set | None = None) -> None:
    """Warn where two consecutive stage files (their :class:`~cascal.io.data.Source`) look
    wrongly linked by their column names: in reverse order (the range check passed), one
    file's columns swapped (exactly one name shared, in the same place), or no name shared
    (a stage left out, or a file of another chain); each file's second column should be
    the first column's sensor of the file before it. ``seen``: the pairs of headers warned
    of already (a fleet's devices share theirs: once per fleet, a review found them once
    per device)."""
    from itertools import pairwise

    from .workflow import reverse_order

    for up, low in pairwise(sources):
        (xu, yu), (xl, yl) = up.columns, low.columns
        key = (xu.lower(), yu.lower(), xl.lower(), yl.lower())
        if seen is not None and key in seen:
            continue
        reverse = reverse_order(up, low)
        if reverse is not None:  # (a chain review: rotary files, with no range check, and
            # linear ones within it; names are labels only, so a warning: a review's
            # logger channels ch1,ch2 above ch2,ch3)
            text = f"{low.file}: {reverse}"
        elif len(set(key)) == 4:  # (a chain review: a stage left out, or a device of
            # another test bed, fitted with no word)
            text = (
                f"{low.file}: its columns ({xl}, {yl}) share no name with {up.file}'s ({xu}, "
                f"{yu}), where its second column should hold the readings of {xu}, the sensor "
                "calibrated one stage up: is a stage missing between them, or is the file of "
                "another chain?"
            )
        elif (xl.lower() == xu.lower()) != (yl.lower() == yu.lower()):
            text = (
                f"{low.file}: its columns ({xl}, {yl}) follow {up.file}'s ({xu}, {yu}), "
                f"sharing a name in the same place; its second column should hold the "
                f"readings of {xu}, the sensor calibrated one stage up: are one file's "
                "columns swapped? (--x-column and --y-column pick them by name)"
            )
        else:
            continue
        if seen is not None:
            seen.add(key)
            text += " (said once for every device file headed so)"
        warn(command, text)


def _level(args: argparse.Namespace) -> float:
    """The screening level given, or the library's default."""
    from .screening import LEVEL

    return LEVEL if args.level is None else args.level


def model_lines(model) -> list[str]:
    """One line per stage (file, rows, points, hyperparameters), then the calibrated
    range."""
    from .text import arc_text, hyperparameter_unit, range_text

    lines = []
    for k, (m, src, counts) in enumerate(
        zip(model.fitted.models, model.sources, model.counts, strict=True)
    ):
        hp = getattr(m, "hyperparameters", {})
        unit = {name: hyperparameter_unit(name, model.unit, model.periodic) for name in hp}
        text = ", ".join(f"{n} {v:.4g}{unit[n]}" for n, v in hp.items()) or "lookup table"
        mean = getattr(m, "mean", None)
        if mean is not None and mean.name == "offset":
            text += f", prior mean offset {mean.offset:+.6g} {model.unit}"
        left = f", {rows_text(src.excluded)} left out" if src.excluded else ""
        lines.append(f"Stage {k} ({src.file}: {src.rows} rows{left}, {counts.size} points): {text}")
    lo, hi = model.calibrated_range
    span = f"full turn (period {model.period:g})" if model.periodic else range_text(lo, hi)
    arc = arc_text(model)
    return [*lines, f"Calibrated device range: {arc or f'{span} {model.unit}'}"]


def _listed(names: Sequence[str]) -> str:
    """The first three of ``names``, then ``...`` where there are more."""
    return ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")


def _not_a_file(path: Path) -> str:
    """What ``path``, which exists but is not a regular file, is, for a message."""
    return "a folder, not a file" if path.is_dir() else "not a regular file (a pipe or a device)"


def _fleet_csv(results, notes: dict[str, list[str]], unit: str) -> str:
    """The fleet summary: one row per device; ``notes``: its warnings, by device; ``unit``
    of the readings (a column: a review found the file silent on it). A rotary device
    measured over part of the turn gives the arc its readings leave out (``arc_left_out``,
    ``from to to``, rounded outward): its range columns span the readings on 0 to 360."""
    import csv
    import io

    from .text import measured_ends

    names = []
    for r in results:
        names += [n for n in r.hyperparameters if n not in names]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "device",
            "status",
            "points",
            "unit",
            *names,
            "rms_correction",
            "max_u",
            "range_lo",
            "range_hi",
            "arc_left_out",
            "suspect_rows",
            "model",
            "error",
            "warnings",
        ]
    )
    for r in results:
        hp = [repr(r.hyperparameters[n]) if n in r.hyperparameters else "" for n in names]
        nums = [r.rms_correction, r.max_u, *r.calibrated_range]
        cells = ["" if v != v else repr(float(v)) for v in nums]
        arc = "{1} to {0}".format(*measured_ends(r.arc)) if r.arc is not None else ""
        w.writerow(
            [
                r.device,
                "error" if r.error else "ok",
                r.points or "",
                unit if not r.error else "",
                *hp,
                *cells,
                arc,
                " ".join(map(str, r.screening.rows)) if r.screening else "",
                r.model or "",
                r.error or "",
                " | ".join(notes.get(r.device, ())),
            ]
        )
    return buf.getvalue()


def warn_homoscedastic(command: str, model) -> None:
    """Say that a homoscedastic model of two or more stages understates u."""
    from .text import HOMOSCEDASTIC_U, understates_u

    if understates_u(model):
        warn(command, HOMOSCEDASTIC_U)


def warn_cautions(command: str, model) -> None:
    """Warn of everything that makes ``model``'s u doubtful (:func:`~cascal.text.caution_lines`)."""
    from .text import caution_lines

    for line in caution_lines(model):
        warn(command, line)


def _show_warning(command: str, default: Callable) -> Callable:
    """A ``warnings.showwarning`` that prints cascal's own warnings as :func:`warn` lines
    and leaves the others to ``default``."""
    from .errors import CascalWarning

    def show(message, category, *args, **kwargs) -> None:
        if issubclass(category, CascalWarning):
            warn(command, str(message))
        else:
            default(message, category, *args, **kwargs)

    return show


#: Lists that :func:`warn` also appends its messages to (innermost last), see _collected.
_COLLECTORS: list[list[str]] = []


@contextlib.contextmanager
def _collected(into: list[str]):
    """Within the block, :func:`warn`'s messages are also appended to ``into``."""
    _COLLECTORS.append(into)
    try:
        yield into
    finally:
        _COLLECTORS.pop()


def warn(command: str, message: str) -> None:
    if sys.stdout is not None:  # None: the process was started with stdout closed
        sys.stdout.flush()
    print(f"cascal {command}: warning: {message}", file=sys.stderr)
    if _COLLECTORS:
        _COLLECTORS[-1].append(message)


def _fit_options(p: argparse.ArgumentParser, fleet: bool = False) -> None:
    """Options shared by ``fit`` and ``fit-devices`` (``fleet``)."""
    p.add_argument(
        "--method",
        choices=("bayes", "homoscedastic", "lut"),
        default="bayes",
        help="bayes: Algorithm 1 (default); homoscedastic: Alternative 1; lut: lookup tables",
    )
    p.add_argument(
        "--kernel",
        choices=("se", "matern32", "matern52", "periodic"),
        default="se",
        help="GP kernel (default se)",
    )
    p.add_argument(
        "--period",
        type=real,
        default=None,
        help="period of --kernel periodic, e.g. 360 for degrees",
    )
    p.add_argument(
        "--mean",
        choices=("identity", "offset"),
        default="identity",
        help=(
            "prior mean of each stage: identity (default; the reading is right until the data "
            "say otherwise) or offset (identity plus the stage's mean correction, for sensors "
            "whose zeros differ)"
        ),
    )
    p.add_argument("--unit", type=unit, default="m", help="unit of the readings (default m)")
    p.add_argument(
        "--x-column",
        action="append",
        metavar="NAME",
        help="column of the sensor being calibrated (once for all files, or "
        + ("twice: the test bed's, then the devices')" if fleet else "once per file)"),
    )
    p.add_argument(
        "--y-column",
        action="append",
        metavar="NAME",
        help="column of the more accurate sensor (once, or "
        + ("twice: the test bed's, then the devices')" if fleet else "once per file)"),
    )
    p.add_argument(
        "--seed", type=seed, default=0, help="seed of the optimiser's starts (default 0)"
    )
    p.add_argument(
        "--restarts", type=restarts, default=5, help="optimiser starts per stage (default 5)"
    )
    p.add_argument(
        "--exclude",
        action="append",
        metavar="FILE:ROWS",
        help=(
            "leave rows of a stage file out of the fit, e.g. reference.csv:41 or "
            "device.csv:41,50-52 (file rows as the warnings name them; repeatable); "
            "recorded in the model file"
        ),
    )
    screening = p.add_mutually_exclusive_group()
    screening.add_argument(
        "--screening-level",
        dest="level",
        type=probability,
        default=None,
        metavar="P",
        help=(
            "false-alarm probability of the outlier screening, per stage file and check "
            "(default 0.01); smaller finds fewer, larger outliers"
        ),
    )
    screening.add_argument(
        "--no-screening",
        action="store_true",
        help="skip the outlier screening of the stage files",
    )


def unit(text: str) -> str:
    """argparse type: a unit label, 1 to 20 printable characters on one line."""
    if not (1 <= len(text) <= 20 and text.isprintable()):
        raise argparse.ArgumentTypeError(f"expected 1 to 20 printable characters, got {text!r}")
    return text


#: A whole number as an option or a row of ``--exclude`` writes it: ASCII digits.
_WHOLE = re.compile(r"\s*[+-]?\d+\s*", re.ASCII)


def as_number(text: str) -> float:
    """``float(text)`` for numbers written as a CSV cell writes them (ASCII digits, a
    point, an exponent, inf or nan): a ValueError for the rest Python's ``float`` reads,
    full-width digits and ``1_000`` (a fuzz review: options took them, the CSV reader
    did not)."""
    from .io.data import is_number

    if not is_number(text):
        raise ValueError(f"not a number: {text!r}")
    return float(text)


def as_whole(text: str) -> int:
    """``int(text)`` for ASCII digits with an optional sign; a ValueError for the rest."""
    if not _WHOLE.fullmatch(text):
        raise ValueError(f"not a whole number: {text!r}")
    return int(text)


def real(text: str) -> float:
    """argparse type: a number (checked further by the command)."""
    try:
        return as_number(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def _whole(text: str, low: int, expected: str) -> int:
    """A whole number of at least ``low`` for argparse; ``expected`` words the refusal."""
    try:
        value = as_whole(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"expected {expected}, got {value}")
    return value


def seed(text: str) -> int:
    """argparse type: a seed, a whole number of at least 0."""
    return _whole(text, 0, "a seed >= 0")


def probability(text: str) -> float:
    """argparse type: a false-alarm probability, from the screening's smallest to below 1."""
    from .screening import MIN_LEVEL

    try:
        value = as_number(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not MIN_LEVEL <= value < 1.0:
        raise argparse.ArgumentTypeError(
            f"expected a probability from {MIN_LEVEL:g} to below 1, got {text}"
            + (" (--no-screening turns the screening off)" if value == 0 else "")
        )
    return value


#: Largest magnitude a number option or a check file's value may have (its squares stay finite).
HUGE = 1e150


def _real(text: str, positive: bool) -> float:
    """A number from 0 (excluded where ``positive``) to below :data:`HUGE` for argparse."""
    try:
        value = as_number(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not ((0 < value) if positive else (0 <= value)) or not value < HUGE:
        sign = ">" if positive else ">="
        raise argparse.ArgumentTypeError(f"expected a number {sign} 0 below 1e150, got {text}")
    return value


def nonnegative(text: str) -> float:
    """argparse type: a number >= 0 below 1e150 (an uncertainty)."""
    return _real(text, positive=False)


def positive(text: str) -> float:
    """argparse type: a number > 0 below 1e150 (a limit)."""
    return _real(text, positive=True)


def positive_int(text: str) -> int:
    """argparse type: an integer of at least 1."""
    return _whole(text, 1, "at least 1")


def worker_count(text: str) -> int:
    """argparse type: local worker processes, 1 to :data:`cascal.pool.MAX_WORKERS`."""
    from .pool import MAX_WORKERS

    value = _whole(text, 1, "at least 1")
    if value > MAX_WORKERS:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_WORKERS} processes, got {value}")
    return value


#: Most optimiser starts per stage on the command line: beyond, a fit's time grows with no
#: optimum left to find (a table's local maxima cap the runs well below).
MAX_RESTARTS = 100


def restarts(text: str) -> int:
    """argparse type: optimiser starts per stage, 1 to :data:`MAX_RESTARTS`."""
    value = _whole(text, 1, "at least 1")
    if value > MAX_RESTARTS:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_RESTARTS}, got {value}")
    return value


def _model_command(sub, name: str, what: str, details: str) -> argparse.ArgumentParser:
    """Register command ``name`` that reads a model file: ``what`` it does (its help, and
    with ``details`` its description) and its MODEL.json argument."""
    p = sub.add_parser(name, help=what, description=f"{what[0].upper()}{what[1:]}: {details}")
    p.add_argument("model", metavar="MODEL.json", help="model file written by cascal fit")
    return p


class _Parser(argparse.ArgumentParser):
    """argparse's parser with its errors on one line, as every other error of the command
    (a fuzz review: an option's bad value came under a usage block of 3 to 6 lines)."""

    def error(self, message: str) -> typing.NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="cascal", description="Cascaded calibration of position sensors with GPs.")
    p.add_argument("--version", action="version", version=f"cascal {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    ex = sub.add_parser(
        "example",
        help="simulate one cascade as in the paper and fit it",
        description="Simulate one cascade as in the paper (reference -> test bed -> device), "
        "fit it with the three methods, print each one's cost J and draw the stage fits as "
        "the paper's Fig. 4: OUT/example_cascade.png. For data files to try the other "
        "commands on, run cascal demo.",
    )
    ex.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    ex.add_argument("--out", default="out", help="output folder (default out/)")
    ex.set_defaults(func=_cmd_example)

    fit = sub.add_parser(
        "fit",
        help="fit stage CSV files (reference end first) into a model file",
        description="Fit stage CSV files, reference end first (reference against test bed, "
        "then test bed against device, ...), into a versioned JSON model file; warn of "
        "suspect rows and of fits the data cannot pin down.",
    )
    fit.add_argument(
        "stages", nargs="+", metavar="STAGE.csv", help="stage files: reading, more accurate reading"
    )
    fit.add_argument(
        "-o", "--output", required=True, metavar="MODEL.json", help="model file to write"
    )
    _fit_options(fit)
    fit.set_defaults(func=_cmd_fit)

    cor = _model_command(
        sub,
        "correct",
        "correct device readings with a model file",
        "each reading's estimated true position and its standard uncertainty u, as CSV: u is "
        "the calibration's (of the correction at that reading); the repeatability of a single "
        "reading comes on top (cascal verify --reading-u combines them). Beyond the calibrated "
        "range the GP's correction extrapolates (a compensation table from cascal export holds "
        "the end's); a rotary reading's corrected angle is not wrapped to one turn.",
    )
    cor.add_argument(
        "readings", metavar="READINGS.csv", help="device readings, one column with a header"
    )
    cor.add_argument("-o", "--output", required=True, metavar="OUT.csv", help="file to write")
    cor.add_argument(
        "--column",
        default=None,
        metavar="NAME",
        help="column of the readings (if the file has several)",
    )
    cor.add_argument(
        "--out-of-range",
        choices=("flag", "empty", "error"),
        default="flag",
        help=(
            "readings outside the calibrated range: flag and extrapolate (default), "
            "flag and leave the cells empty, or refuse the file"
        ),
    )
    cor.set_defaults(func=_cmd_correct)

    fd = sub.add_parser(
        "fit-devices",
        help="calibrate a folder of device files against one test bed",
        description="Fit the test bed once (OUT/testbed.json), then every .csv device file "
        "of a folder against it in parallel (OUT/devices/<name>.json), and summarise the "
        "fleet in OUT/fleet_summary.csv. A bad device file is skipped (exit status 1).",
    )
    fd.add_argument("testbed", metavar="TESTBED.csv", help="test bed against the reference")
    fd.add_argument(
        "--devices",
        required=True,
        metavar="DIR",
        help="folder of device files (*.csv): device reading, test-bed reading",
    )
    fd.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUTDIR",
        help="folder for testbed.json, devices/*.json and fleet_summary.csv",
    )
    fd.add_argument(
        "--jobs",
        type=worker_count,
        default=None,
        help="worker processes (default: the CPUs this process may use)",
    )
    _fit_options(fd, fleet=True)
    fd.set_defaults(func=_cmd_fit_devices)

    rep = _model_command(
        sub,
        "report",
        "write a self-contained HTML report of a model file",
        "its stages, fits, uncertainty and figures, in one file with no external links.",
    )
    rep.add_argument("-o", "--output", required=True, metavar="REPORT.html", help="file to write")
    rep.set_defaults(func=_cmd_report)

    demo = sub.add_parser(
        "demo",
        help="simulate example files, then fit, correct, report, export, plan, verify and "
        "compare them",
        description="Simulate the files of a linear and a rotary cascade and run every "
        "command on them, as a user would: OUT/demo/linear/ and OUT/demo/rotary/ hold the "
        "data files, models, corrected readings, reports, tables and figures, "
        "OUT/rotary_periodic.png the rotary correction across 0/360 degrees.",
    )
    demo.add_argument("--out", default="out", help="output folder (default out/)")
    demo.add_argument("--seed", type=seed, default=0, help="seed of the simulation (default 0)")
    demo.set_defaults(func=_cmd_demo)

    from .cli_compare import add_compare_parser
    from .cli_export import add_export_parser
    from .cli_info import add_info_parser
    from .cli_plan import add_plan_parser
    from .cli_study import add_study_parser
    from .cli_verify import add_verify_parser

    add_export_parser(sub)
    add_compare_parser(sub)
    add_info_parser(sub)
    add_plan_parser(sub)
    add_verify_parser(sub)
    add_study_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cascal`` console script; returns the exit status."""
    from .pool import sigterm_as_interrupt

    for stream in (sys.stdout, sys.stderr):  # a file name that is not UTF-8, printed: its
        # bytes escaped, not a UnicodeEncodeError (a review: info and fit stopped), where
        # the stream is strict (under the C locale or PYTHONUTF8, it writes them back as
        # they came)
        if getattr(stream, "errors", None) == "strict" and hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")
    with sigterm_as_interrupt():  # SIGTERM as Ctrl-C: outputs left whole
        try:  # Ctrl-C while the subcommands' modules load (NumPy, SciPy: a few tenths of a s)
            return _main(argv)
        except KeyboardInterrupt as exc:  # a further Ctrl-C as it exits: the status all the same
            return _stopped("cascal", exc)


def _stopped(who: str, exc: KeyboardInterrupt) -> int:
    """Say that the command ``who`` was interrupted (Ctrl-C) or terminated (SIGTERM), with
    ``exc``'s text; returns the exit status."""
    from .pool import Terminated, stop_listening

    stop_listening()
    what = "terminated" if isinstance(exc, Terminated) else "interrupted"
    detail = f" ({exc})" if str(exc) else ""
    print(f"{who}: {what}{detail}", file=sys.stderr)
    return EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED


def _main(argv: Sequence[str] | None) -> int:
    parser = _parser()
    given = join_negative(list(sys.argv[1:] if argv is None else argv))
    for a in given:
        if a == "--":
            break
        if a.startswith("-") and a.endswith("=--"):  # (Python 3.11's argparse passes a
            parser.error(f"argument {a[:-3]}: expected a value, got '--'")  # [] on, untyped)
    args = parser.parse_args(given)
    func: Callable[[argparse.Namespace], int] = args.func
    to_stdout = is_stdout(getattr(args, "output", None))
    from .gp import pin_blas

    pin_blas()  # one BLAS thread: the same numbers on every machine (fits run so anyway)
    try:  # an output written to stdout keeps it: the command's own lines go to stderr
        with (
            contextlib.redirect_stdout(sys.stderr) if to_stdout else contextlib.nullcontext(),
            warnings.catch_warnings(),
        ):
            warnings.showwarning = _show_warning(args.command, warnings.showwarning)
            return func(args)
    except WorkerError as exc:  # not the input: the machines failed
        print(f"cascal {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except CascalError as exc:
        print(f"cascal {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except BrokenPipeError:  # the reader of the output left (| head): stop quietly
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except OSError as exc:
        text = exc.strerror or exc
        if exc.filename is not None and exc.strerror:
            text = f"{exc.filename}: {exc.strerror}"
        print(f"cascal {args.command}: error: {text}", file=sys.stderr)
        return EXIT_FAILURE
    except MemoryError:
        print(
            f"cascal {args.command}: error: out of memory (the data too large for this machine?)",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    except KeyboardInterrupt as exc:
        return _stopped(f"cascal {args.command}", exc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
