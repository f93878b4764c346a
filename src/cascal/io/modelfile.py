"""Model files: a fitted cascade as versioned, checksummed JSON (never pickle).

A model file (schema ``io/schemas/<version>/model.json``) holds, per stage, the data (averaged
readings, their known noise and counts), the kernel and hyperparameters, and what a
prediction needs: the training positions, the weights ``alpha`` and the lower Cholesky
factor ``L`` of the target covariance, stored as computed, so a loaded model predicts the
same numbers as the fitted one, bit for bit. The known noise of each target (the previous
stage's full posterior covariance in method ``bayes``) is stored too, for plots and
inspection; predictions do not need it. Then the provenance (input files with SHA-256,
rows, columns; creation time; cascal version; seed) and a SHA-256 of the canonical JSON
(sorted keys, no spaces) of everything else. Files are written atomically; loading checks
the version, the checksum, the schema and the consistency of the arrays.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..baselines import OffsetTable, fit_table
from ..cascade import Cascade, FittedCascade, Stage
from ..errors import CascalError, InputError, ModelFileError
from ..gp import FittedGP, restore_bounds
from ..kernels import (
    Constant,
    Kernel,
    Matern32,
    Matern52,
    Periodic,
    Product,
    SquaredExp,
    Sum,
    common_period,
)
from ..means import Mean
from ..noise import Dense, Diagonal, Noise, NoiseSum, as_noise
from ..optimize import OptimResult, Start
from .atomic import write_text
from .data import Source
from .schema import SchemaError, load_schema, validate

__all__ = [
    "SCHEMA_VERSION",
    "CalibrationModel",
    "load_model",
    "load_model_checksum",
    "model_to_dict",
    "save_model",
    "schema_version",
]

#: Newest schema version this cascal writes and reads. A model is written in the oldest
#: version that holds it (1 unless rows were excluded), so older cascal versions read it.
SCHEMA_VERSION = 2
#: Entries of the kernel matrix built at once when a factor is checked (8 MB).
_BLOCK_ENTRIES = 1 << 20
#: Lone surrogates no text of cascal's holds: all but those of bytes that are not UTF-8
#: (U+DC80 to U+DCFF, as Python decodes a file name's), which a terminal writes back.
_LONE_SURROGATE = re.compile("[\ud800-\udc7f\udd00-\udfff]")
_SCALED = {"SquaredExp": SquaredExp, "Matern32": Matern32, "Matern52": Matern52}


@dataclass(frozen=True, slots=True)
class CalibrationModel:
    """A fitted cascade with its data and provenance: what a model file holds.

    Attributes:
        fitted: The fitted cascade (its last model corrects device readings).
        data: Per stage, the averaged input readings (``y`` of the more accurate sensor,
            not the propagated targets) and their known noise.
        counts: Per stage, readings averaged into each point, shape (k,).
        sources: Per stage, the input file's provenance.
        unit: Unit of all readings, e.g. ``"m"`` or ``"deg"``.
        kernel: Kernel family asked for (``"se"``, ...), None for ``lut``.
        period: Period of a periodic kernel, or None.
        seed: Seed of the fit.
        n_restarts: Optimiser starts per stage, at most (see :func:`cascal.fit_gp`).
        created: UTC time of the fit, ISO 8601.
        cascal_version: Version that fitted it.
    """

    fitted: FittedCascade
    data: tuple[Stage, ...]
    counts: tuple[np.ndarray, ...]
    sources: tuple[Source, ...]
    unit: str = "m"
    kernel: str | None = "se"
    period: float | None = None
    seed: int | None = 0
    n_restarts: int = 5
    created: str = ""
    cascal_version: str = ""

    @classmethod
    def from_cascade(
        cls, cascade: Cascade, fitted: FittedCascade, *, unit: str = "m"
    ) -> CalibrationModel:
        """A cascade fitted in Python (``fitted = cascade.fit()``) as a model to save with
        :func:`save_model` and use from the command line (``cascal correct``, ``export``).

        There are no input files: each stage's provenance names it as ``<name>`` with the
        SHA-256 of its readings (``x`` then ``y``, float64 bytes); ``unit`` labels them.
        """
        if len(fitted.models) != len(cascade.stages) or any(
            not np.array_equal(f.x, c.x) for f, c in zip(fitted.stages, cascade.stages, strict=True)
        ):
            raise InputError("fitted: not a fit of this cascade's stages")
        sources = tuple(
            Source(
                f"<{st.name}>",
                hashlib.sha256(st.x.tobytes() + st.y.tobytes()).hexdigest(),
                int(st.x.size),
                ("x", "y"),
            )
            for st in cascade.stages
        )
        kernel = cascade.kernel if isinstance(cascade.kernel, str) else repr(cascade.kernel)
        return cls(
            fitted,
            tuple(_per_reading(st) for st in cascade.stages),
            tuple(np.ones(st.x.size, np.int64) for st in cascade.stages),
            sources,
            unit,
            None if fitted.method == "lut" else kernel,
            _period(cascade, fitted.method),
            None if cascade.seed is None else int(cascade.seed),  # (NumPy's: not JSON)
            int(cascade.n_restarts),
        )

    def __post_init__(self) -> None:
        _check_unit(self.unit, InputError)

    @property
    def method(self) -> str:
        """``bayes``, ``homoscedastic`` or ``lut``."""
        return self.fitted.method

    @property
    def calibrated_range(self) -> tuple[float, float]:
        """Smallest and largest device reading the last stage was fitted on."""
        return self.fitted.calibrated_range

    @property
    def periodic(self) -> bool:
        """True for a periodic kernel: the model corrects every turn (less any arc its device
        readings left out: :func:`cascal.workflow.unmeasured_arc`)."""
        return self.period is not None


def _per_reading(stage: Stage) -> Stage:
    """``stage`` with its known noise as one variance per reading, as a model file keeps
    it (a number, a diagonal matrix or :class:`~cascal.noise.Diagonal`); InputError for a
    noise with correlations, which a model file cannot keep."""
    if stage.noise is None or np.ndim(stage.noise) == 1:
        return stage
    n = stage.x.size
    noise = as_noise(stage.noise, n)  # (not None: stage.noise is not)
    if not noise.is_diagonal:
        dense = noise.dense(n)
        if np.count_nonzero(dense - np.diag(np.diag(dense))):
            raise InputError(
                f"stage {stage.name!r}: its known noise has correlations between readings, "
                "which a model file cannot keep (one variance per reading): save a model of "
                "stages whose noise is a number or an (n,) vector of variances"
            )
    return Stage(stage.x, stage.y, np.array(noise.diagonal(n), dtype=float), stage.name)


def save_model(path: str | os.PathLike, model: CalibrationModel) -> Path:
    """Write ``model`` to ``path`` as JSON, atomically (a temporary file, then a rename)."""
    if not isinstance(model, CalibrationModel):
        hint = ""
        if isinstance(model, FittedCascade):
            hint = (
                ": make one of a fitted cascade with "
                "CalibrationModel.from_cascade(cascade, fitted, unit=...)"
            )
        raise InputError(f"model: expected a CalibrationModel, got {type(model).__name__}{hint}")
    doc = model_to_dict(model)
    texts = _number_texts(doc, {})  # each list of numbers formatted once, for both uses
    doc["checksum"] = {"algorithm": "sha256", "value": _checksum(doc, texts)}
    return write_text(path, _pretty(doc, texts=texts) + "\n")


def model_to_dict(model: CalibrationModel) -> dict[str, Any]:
    """The model file's content without the checksum, as JSON-ready Python values."""
    stages = []
    for k, (data, fitted, counts) in enumerate(
        zip(model.data, model.fitted.stages, model.counts, strict=True)
    ):
        m = model.fitted.models[k]
        stages.append(
            {
                "name": data.name,
                "x": _floats(data.x),
                "y": _floats(data.y),
                "noise": None
                if data.noise is None
                else _floats(np.broadcast_to(data.noise, data.x.shape)),
                "counts": [int(c) for c in counts],
                "model": _gp_dict(m) if isinstance(m, FittedGP) else _lut_dict(m, fitted.y),
            }
        )
    lo, hi = model.calibrated_range
    inputs = []
    for s in model.sources:
        entry = {"file": s.file, "sha256": s.sha256, "rows": s.rows, "columns": list(s.columns)}
        if s.excluded:
            entry["excluded_rows"] = [int(r) for r in s.excluded]
        inputs.append(entry)
    return {
        "schema_version": schema_version(model),
        "format": "cascal-model",
        "method": model.method,
        "unit": model.unit,
        "kernel": model.kernel,
        "period": None if model.period is None else float(model.period),
        "calibrated_range": [lo, hi],
        "stages": stages,
        "provenance": {
            "created": model.created or _now(),
            "cascal_version": model.cascal_version or _version(),
            "seed": model.seed,
            "n_restarts": int(model.n_restarts),
            "inputs": inputs,
        },
    }


def schema_version(model: CalibrationModel) -> int:
    """The schema version ``model`` is written in: 2 where rows of an input file were
    excluded (``provenance.inputs[].excluded_rows``), else 1."""
    return 2 if any(s.excluded for s in model.sources) else 1


def load_model(path: str | os.PathLike) -> CalibrationModel:
    """Read a model file, checking its version, checksum, schema and arrays.

    Raises:
        ModelFileError: The file is missing, not JSON (e.g. truncated), of another schema
            version (a newer one asks for a newer cascal), edited after it was written
            (checksum), or inconsistent.
    """
    return load_model_checksum(path)[0]


def load_model_checksum(path: str | os.PathLike) -> tuple[CalibrationModel, str]:
    """:func:`load_model`, and the checksum (sha256, hex) the file carries, verified: one
    read of the file (a pipe can be read once)."""
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8-sig")  # (an editor's byte-order mark)
    except OSError as exc:
        raise ModelFileError(f"{name}: cannot read the model file ({exc})") from None
    except UnicodeDecodeError:
        raise ModelFileError(
            f"{name}: not a valid model file: not UTF-8 text (cascal writes model files as "
            "UTF-8 JSON)"
        ) from None
    if "\x00" in text[:64]:  # (a fuzz review: UTF-16 without its mark was "truncated?")
        raise ModelFileError(
            f"{name}: not a valid model file: UTF-16 text (NUL bytes), not the UTF-8 JSON "
            "cascal writes: saved again by an editor?"
        )
    try:
        return _parse(text, name)
    except RecursionError:
        raise ModelFileError(f"{name}: not a valid model file: nested too deeply") from None


def _parse(text: str, name: str) -> tuple[CalibrationModel, str]:
    """The model in a model file's text and its checksum; ModelFileError naming ``name``
    if it is none."""
    start = text.lstrip("\ufeff \t\r\n")
    if start and not start.startswith("{"):  # a model file is one JSON object
        first = start.splitlines()[0]
        csv_like = Path(name).suffix.lower() in (".csv", ".tsv", ".txt") or (
            any(sep in first for sep in ",;\t") and not first.startswith(("[", '"'))
        )
        hint = (
            ": it reads like a CSV file; the model file comes first (MODEL.json READINGS.csv)?"
            if csv_like
            else ""
        )
        raise ModelFileError(
            f"{name}: not a valid model file: it starts with {first[:40]!r}, not with '{{' "
            f"as a cascal model (JSON) does{hint}"
        )
    try:
        doc = json.loads(text, parse_constant=_reject_constant, parse_float=_float, parse_int=_int)
    except json.JSONDecodeError as exc:
        body = text.rstrip()  # a model file is one object: cut short, it lacks its "}"
        short = exc.pos >= len(body) or not body.endswith("}")
        end = " (the file ends early: truncated?)" if short else ""
        if exc.msg == "Extra data":
            end = " (text after the model's closing '}': an edit, or two files joined?)"
        raise ModelFileError(
            f"{name}: not a valid model file: JSON error at line {exc.lineno} column "
            f"{exc.colno}: {exc.msg}{end}"
        ) from None
    except ValueError as exc:
        raise ModelFileError(f"{name}: not a valid model file: {exc}") from None
    if _lone_surrogate(doc):  # (a fuzz review: "\ud800" is valid JSON, and printing it
        # ended info, plan, compare and report with a traceback)
        raise ModelFileError(
            f"{name}: not a valid model file: a text holds a lone surrogate (\\ud800 to "
            "\\udfff), which cascal never writes (edited or damaged?)"
        )
    if not isinstance(doc, dict) or doc.get("format") != "cascal-model":
        raise ModelFileError(f'{name}: not a cascal model file (no "format": "cascal-model")')
    _check_version(doc.get("schema_version"), name)
    stored = doc.get("checksum")
    body = {k: v for k, v in doc.items() if k != "checksum"}
    value = stored.get("value") if isinstance(stored, dict) else None
    if value != _checksum(body):
        raise ModelFileError(
            f"{name}: checksum mismatch: the file was changed after cascal wrote it "
            "(edited or damaged); fit the model again"
        )
    version = doc["schema_version"]
    try:
        validate(doc, load_schema("model", version))
    except SchemaError as exc:
        raise ModelFileError(f"{name}: does not match model schema {version}: {exc}") from None
    try:
        return _from_dict(doc), value
    except (CascalError, ValueError, IndexError) as exc:
        raise ModelFileError(f"{name}: inconsistent model file: {exc}") from None
    except (OverflowError, TypeError) as exc:  # an integer too large for its array
        raise ModelFileError(
            f"{name}: inconsistent model file: a number out of range ({exc})"
        ) from None


def _lone_surrogate(obj: Any) -> bool:
    """Whether a text in the parsed JSON ``obj`` (its keys too) holds a lone surrogate of
    :data:`_LONE_SURROGATE`; lists of numbers are passed over (the schema checks that
    they hold numbers only)."""
    if isinstance(obj, str):
        return _LONE_SURROGATE.search(obj) is not None
    if isinstance(obj, dict):
        return any(_lone_surrogate(k) or _lone_surrogate(v) for k, v in obj.items())
    if isinstance(obj, list) and obj and not isinstance(obj[0], int | float):
        return any(_lone_surrogate(v) for v in obj)
    return False


def _check_version(version: Any, name: str) -> None:
    if type(version) is not int:
        raise ModelFileError(f"{name}: no integer schema_version; not a cascal model file")
    if version > SCHEMA_VERSION:
        raise ModelFileError(
            f"{name}: schema version {version} is newer than this cascal ({_version()}) can "
            f"read (version {SCHEMA_VERSION}); upgrade cascal to use this model"
        )
    if version < 1:
        raise ModelFileError(
            f"{name}: schema version {version} is not supported (this cascal reads versions "
            f"1 to {SCHEMA_VERSION}); fit the model again with this cascal"
        )


#: The first cascal whose search bounds are today's (the profiled noise ratio's upper
#: bound was 10 before): only its model files get their bounds back on loading. A kernel
#: with a product in it: 0.4.4 (a factor's variance was bounded by the data's before).
_BOUNDS_SINCE = (0, 4, 2)
_PRODUCT_BOUNDS_SINCE = (0, 4, 4)


def _same_bounds(version: object, kernel: Kernel) -> bool:
    """Whether a model file written by cascal ``version`` searched ``kernel``'s
    hyperparameters in today's bounds."""
    parts = str(version).split(".")[:3]
    try:
        v = tuple(int(p) for p in parts)
    except ValueError:  # a development version's suffix, or no version
        return False
    return v >= (_PRODUCT_BOUNDS_SINCE if _has_product(kernel) else _BOUNDS_SINCE)


def _has_product(kernel: Kernel) -> bool:
    if isinstance(kernel, Product):
        return True
    return isinstance(kernel, Sum) and (_has_product(kernel.left) or _has_product(kernel.right))


def _from_dict(doc: dict) -> CalibrationModel:
    models: list[FittedGP | OffsetTable] = []
    version = doc["provenance"].get("cascal_version")
    data, used, counts = [], [], []
    for k, st in enumerate(doc["stages"]):
        x, y = np.array(st["x"], float), np.array(st["y"], float)
        n = x.size
        noise = None if st["noise"] is None else np.array(st["noise"], float)
        c = np.array(st["counts"], np.int64)
        if y.size != n or c.size != n or (noise is not None and noise.size != n):
            raise ValueError(f"stage {k}: x, y, noise and counts differ in length")
        if noise is not None and np.any(noise < 0):
            raise ValueError(f"stage {k}: a noise variance below 0")
        if np.any(c < 1):
            raise ValueError(f"stage {k}: a point of fewer than 1 reading (counts)")
        m = st["model"]
        targets = np.array(m["targets"], float)
        if m["type"] == "gp":
            model = _gp_from(m, x, targets)
            model = restore_bounds(model) if _same_bounds(version, model.kernel) else model
        else:
            knots, offsets = np.array(m["knots"], float), np.array(m["offsets"], float)
            if knots.size != offsets.size or np.any(np.diff(knots) <= 0):
                raise ValueError(f"stage {k}: knots must increase and match the offsets")
            model = OffsetTable(knots, offsets)
        if targets.size != n:
            raise ValueError(f"stage {k}: {targets.size} targets for {n} points")
        if m["type"] != "gp":  # a table is its data's: an edited one would shift corrections
            expected = y if k == 0 or not isinstance(models[-1], OffsetTable) else models[-1](y)
            _check_table(k, model, x, targets, expected)
        else:  # so are a GP's targets (a review: targets and mean offset moved by 1 mm,
            # the checksum recomputed, moved every correction by 1 mm)
            above = models[-1] if k else None
            _check_targets(k, above if isinstance(above, FittedGP) else None, y, targets)
        models.append(model)
        data.append(Stage(x, y, noise, st["name"]))
        used.append(Stage(x, targets, noise, st["name"]))
        counts.append(c)
    method = doc["method"]
    _check_unit(doc["unit"], ValueError)
    name, period = doc["kernel"], doc["period"]
    if doc["method"] == "lut":  # lookup tables do not wrap (0.4.10 wrote some with a period)
        period = None
    if name in _NAMED and (name == "periodic") != (period is not None):
        raise ValueError(f"kernel {name!r} with period {period!r}")
    for k, m in enumerate(models):  # (a prefix's stages may have another kernel)
        if isinstance(m, FittedGP) and isinstance(m.kernel, Periodic) and m.kernel.period != period:
            raise ValueError(
                f"stage {k}: a periodic kernel of period {m.kernel.period!r}, "
                f"not the model's {period!r}"
            )
    last = models[-1] if models else None
    repeats = isinstance(last, FittedGP) and common_period(last.kernel) == period
    if period is not None and not repeats:
        raise ValueError(  # (a review: an edited "periodic" made a linear model's corrections
            # of other turns in range)
            f"a period of {period!r}, but the device stage's kernel does not repeat with it"
        )
    tables = [isinstance(m, OffsetTable) for m in models]
    if (method == "lut" and not all(tables)) or (method != "lut" and any(tables)):
        raise ValueError(f"method {method!r} does not match the stage models")
    for k, m in enumerate(models[1:], start=1):  # (a fuzz review: bayes relabelled
        # homoscedastic loaded, and plan then planned for another target)
        if not isinstance(m, FittedGP):
            continue
        if method == "bayes" and m.noise is None:
            raise ValueError(
                f"method 'bayes', but stage {k} does not carry the stage above's covariance "
                "as its noise (edited?)"
            )
        if method == "homoscedastic" and _correlated(m.noise, m.x.size):
            raise ValueError(
                f"method 'homoscedastic', but stage {k} carries correlated noise, as bayes "
                "does with the stage above's covariance (edited?)"
            )
    device = models[-1] if models else None
    if isinstance(device, FittedGP) and name in _NAMED:  # (the label, a kernel it is not)
        kinds = {"se": SquaredExp, "matern32": Matern32, "matern52": Matern52}
        want = kinds.get(name, Periodic)
        if not isinstance(device.kernel, want):
            raise ValueError(
                f"kernel {name!r}, but the device stage's is {type(device.kernel).__name__}"
            )
    fitted = FittedCascade(method, tuple(models), tuple(used))
    if list(fitted.calibrated_range) != doc["calibrated_range"]:
        raise ValueError("calibrated_range does not match the last stage's readings")
    prov = doc["provenance"]
    if len(prov["inputs"]) != len(models):
        raise ValueError(f"{len(prov['inputs'])} input files for {len(models)} stages")
    for i in prov["inputs"]:
        ex = i.get("excluded_rows", [])
        if ex != sorted(set(ex)):
            raise ValueError(f"excluded_rows of {i['file']} must increase")
    sources = tuple(
        Source(
            i["file"],
            i["sha256"],
            i["rows"],
            tuple(i["columns"]),
            tuple(i.get("excluded_rows", ())),
        )
        for i in prov["inputs"]
    )
    return CalibrationModel(
        fitted, tuple(data), tuple(counts), sources, doc["unit"], doc["kernel"],
        period, prov["seed"], prov["n_restarts"], prov["created"], prov["cascal_version"],
    )  # fmt: skip


def _gp_dict(gp: FittedGP) -> dict[str, Any]:
    opt = gp.optimization
    return {
        "type": "gp",
        "kernel": _kernel_dict(gp.kernel),
        "mean": {"slope": float(gp.mean.slope), "offset": float(gp.mean.offset)},
        "noise_variance": float(gp.noise_variance),
        "known_noise": None if gp.noise is None else _noise_dict(gp.noise, gp.x.size),
        "targets": _floats(gp.y),
        "alpha": _floats(gp.alpha),
        "cholesky": _lower(gp.L),
        "jitter": float(gp.jitter),
        "log_marginal_likelihood": _finite(gp.log_marginal_likelihood),
        "optimization": None if opt is None else _opt_dict(opt),
    }


def _gp_from(m: dict, x: np.ndarray, targets: np.ndarray) -> FittedGP:
    n = x.size
    rows = m["cholesky"]
    if len(rows) != n or any(len(r) != i + 1 for i, r in enumerate(rows)):
        raise ValueError(f"cholesky: expected {n} rows, row i holding i + 1 entries")
    L = np.zeros((n, n))
    for i, r in enumerate(rows):
        L[i, : i + 1] = r
    lml = m["log_marginal_likelihood"]
    gp = FittedGP.from_arrays(
        x,
        targets,
        kernel=_kernel_from(m["kernel"]),
        mean=Mean(m["mean"]["slope"], m["mean"]["offset"]),
        noise=None if m["known_noise"] is None else _noise_from(m["known_noise"]),
        noise_variance=float(m["noise_variance"]),  # (an integer of any size too)
        L=L,
        alpha=m["alpha"],
        jitter=float(m["jitter"]),
        log_marginal_likelihood=math.nan if lml is None else lml,
        optimization=None if m["optimization"] is None else _opt_from(m["optimization"]),
    )
    _check_weights(gp)
    _check_factor(gp)
    return gp


def _correlated(noise: Noise | None, n: int) -> bool:
    """Whether a known noise has a covariance off its diagonal (a diagonal matrix given as
    a dense noise has none: a review found such a homoscedastic model refused)."""
    if noise is None or noise.is_diagonal:
        return False
    M = noise.dense(n)
    return bool(np.any(M[~np.eye(n, dtype=bool)] != 0.0))


def _check_targets(k: int, above: FittedGP | None, y: np.ndarray, targets: np.ndarray) -> None:
    """ValueError unless GP stage ``k``'s ``targets`` (n,) are its data's: stage 0's
    readings ``y`` (n,) themselves, a later stage's the posterior mean of the GP ``above``
    at them, to its round-off (``1e3 n eps`` of the terms' magnitudes). O(n m)."""
    if above is None:
        if not np.array_equal(targets, y):
            raise ValueError(f"stage {k}: its targets are not its readings (edited?)")
        return
    with np.errstate(over="ignore", invalid="ignore"):
        K, prior = above.kernel(above._turn(y), above.x), above.mean(y)  # (as predict's)
        scale = np.abs(prior) + np.abs(K) @ np.abs(above.alpha)
        slack = 1e3 * above.x.size * np.finfo(float).eps * scale
        bad = ~(np.abs(prior + K @ above.alpha - targets) <= slack + 1e-300)
    if np.any(bad) or not np.all(np.isfinite(slack)):
        raise ValueError(
            f"stage {k}: its targets are not the stage above's correction of its readings (edited?)"
        )


def _check_factor(gp: FittedGP) -> None:
    """Refuse a Cholesky factor ``L`` that does not factorise the target covariance of
    the stored hyperparameters (kernel, known noise, noise variance and jitter) beyond
    the factorisation's round-off (``n eps |L| |L^T|``, bounded, with room to spare): a
    hyperparameter edited with the checksum recomputed (a review's case: a length scale
    tripled and the noise changed gave corrections 0.25 mm off and every u 0). Checked on
    the diagonal, the first, middle and last columns, and along two random directions
    ``z`` (``L L^T z`` against ``K z``, K built a block of rows at a time) drawn afresh at
    every load, so that no edit can aim past them (a fuzz review rotated a row of L out of
    sight of the columns): O(n^2) time, O(n) memory beyond a block of K and a dense known
    noise."""
    n = gp.x.size
    cols = np.unique([0, n // 2, n - 1])
    diag = gp.kernel.diag(gp.x) + gp.noise_variance + gp.jitter
    D = np.zeros((n, cols.size))
    D[cols, np.arange(cols.size)] = 1.0
    Z = np.hstack([D, np.random.default_rng().standard_normal((n, 2))])  # (n, 5)
    L = gp.L
    with np.errstate(over="ignore", invalid="ignore"):
        KZ = np.empty_like(Z)
        step = max(1, _BLOCK_ENTRIES // max(n, 1))
        for s in range(0, n, step):  # K z, a block of rows at a time
            KZ[s : s + step] = gp.kernel(gp.x[s : s + step], gp.x) @ Z
        KZ += (gp.noise_variance + gp.jitter) * Z
        if gp.noise is not None:
            diag = diag + gp.noise.diagonal(n)
            KZ += (
                gp.noise.diagonal(n)[:, None] * Z if gp.noise.is_diagonal else gp.noise.dense(n) @ Z
            )
        rows = np.einsum("ij,ij->i", L, L)  # diag(L L^T)
        got = np.concatenate([rows, (L @ (L.T @ Z)).ravel()])
        want = np.concatenate([diag, KZ.ravel()])
        # |L| |L^T| |z| bounded by Cauchy-Schwarz, sqrt(rows_i) sum_j sqrt(rows_j) |z_j|:
        # no copy of L
        root = np.sqrt(rows)
        bound = np.concatenate([rows, np.outer(root, root @ np.abs(Z)).ravel()])
        slack = 1e3 * n * np.finfo(float).eps * bound + 1e-12 * np.max(np.abs(want), initial=0.0)
        fits = np.abs(got - want) <= slack
    # (a review: one entry of 1e154 made the slack infinite, and any factor passed)
    if not (np.all(fits) and np.all(np.isfinite(slack))):
        raise ValueError(
            "cholesky does not factorise the covariance of the stored kernel, noise and "
            "jitter (a hyperparameter edited?)"
        )


def _check_weights(gp: FittedGP) -> None:
    """Refuse weights ``alpha`` that do not solve ``L L^T alpha = targets - mean(x)``
    beyond the solves' round-off (``n eps |L| |L^T| |alpha|``, with room to spare): the
    readings, targets, mean, factor and weights belong to one fit. O(n^2)."""
    L, a = gp.L, gp.alpha
    r = gp.y - gp.mean(gp.x)
    with np.errstate(over="ignore", invalid="ignore"):
        bound = np.abs(L) @ (np.abs(L.T) @ np.abs(a))
        slack = 1e3 * a.size * np.finfo(float).eps * bound + 1e-300
        fits = np.abs(L @ (L.T @ a) - r) <= slack + 1e-12 * np.max(np.abs(r), initial=0.0)
    if not (np.all(fits) and np.all(np.isfinite(slack))):  # (an infinite slack passed all)
        raise ValueError("alpha, cholesky, x and targets do not belong to one fit")


def _check_table(
    k: int, table: OffsetTable, x: np.ndarray, targets: np.ndarray, expected: np.ndarray
) -> None:
    """ValueError unless stage ``k``'s ``table`` is the one its readings ``x`` (n,) and
    ``targets`` (n,) give, and the targets are ``expected`` (n,): stage 0's reference
    readings, or a later stage's mapped through the table before."""
    fresh = fit_table(x, targets)
    same = np.array_equal(fresh.knots, table.knots) and np.array_equal(fresh.offsets, table.offsets)
    if not same:
        raise ValueError(f"stage {k}: its table's knots and offsets are not its data's (edited?)")
    if not np.array_equal(expected, targets):
        raise ValueError(f"stage {k}: its targets are not the readings above it mapped (edited?)")


def _lut_dict(table: OffsetTable, targets: np.ndarray) -> dict[str, Any]:
    return {
        "type": "lut",
        "targets": _floats(targets),
        "knots": _floats(table.knots),
        "offsets": _floats(table.offsets),
    }


def _kernel_dict(k: Kernel) -> dict[str, Any]:
    name = type(k).__name__
    if isinstance(k, Sum | Product):
        return {"type": name, "left": _kernel_dict(k.left), "right": _kernel_dict(k.right)}
    if isinstance(k, Constant):
        return {"type": name, "value": float(k.value)}
    if isinstance(k, Periodic):
        return {
            "type": name,
            "length_scale": float(k.length_scale),
            "variance": float(k.variance),
            "period": float(k.period),
        }
    if name in _SCALED:
        return {"type": name, "length_scale": float(k.length_scale), "variance": float(k.variance)}
    raise ValueError(f"kernel {name} cannot be stored in a model file")


#: The kernels that the command line names.
_NAMED = ("se", "matern32", "matern52", "periodic")


def _check_unit(unit: object, error: type[Exception]) -> None:
    """A unit label: 1 to 20 printable characters (it goes into messages and C comments)."""
    if not (isinstance(unit, str) and 1 <= len(unit) <= 20 and unit.isprintable()):
        raise error(f"unit: expected 1 to 20 printable characters, got {unit!r}")


def _kernel_from(d: dict) -> Kernel:
    t = d["type"]
    if t in ("Sum", "Product"):
        cls = Sum if t == "Sum" else Product
        return cls(_kernel_from(d["left"]), _kernel_from(d["right"]))
    if t == "Constant":
        return Constant(d["value"])
    if t == "Periodic":
        return Periodic(d["length_scale"], d["variance"], period=d["period"])
    return _SCALED[t](d["length_scale"], d["variance"])


def _noise_dict(noise: Noise, n: int) -> dict[str, Any]:
    if isinstance(noise, NoiseSum):
        return {"type": "sum", "parts": [_noise_dict(p, n) for p in noise.parts]}
    if isinstance(noise, Diagonal):
        v = noise.variance
        return {"type": "diagonal", "variance": float(v) if np.ndim(v) == 0 else _floats(v)}
    if isinstance(noise, Dense):
        return {
            "type": "dense",
            "lower": _lower(noise.cov),
            "tol": float(getattr(noise, "tol", 0.0)),
            "atol": float(getattr(noise, "atol", 0.0)),
        }
    raise ValueError(f"noise {type(noise).__name__} cannot be stored in a model file")


def _noise_from(d: dict) -> Noise:
    t = d["type"]
    if t == "sum":
        parts = [_noise_from(p) for p in d["parts"]]
        return NoiseSum(tuple(parts))
    if t == "diagonal":
        v = d["variance"]
        return Diagonal(v if isinstance(v, int | float) else np.array(v, float))
    rows = d["lower"]
    n = len(rows)
    if any(len(r) != i + 1 for i, r in enumerate(rows)):
        raise ValueError("known_noise: dense rows must hold i + 1 entries")
    C = np.zeros((n, n))
    for i, r in enumerate(rows):
        C[i, : i + 1] = r
    C = C + np.tril(C, -1).T
    return Dense.repaired(C, **{k: d[k] for k in ("tol", "atol") if k in d})  # (checksummed)


def _opt_dict(opt: OptimResult) -> dict[str, Any]:
    return {
        "theta": _floats(opt.theta),
        "value": _finite(opt.value),
        "n_candidates": int(opt.n_candidates),
        "n_probes": int(opt.n_probes),
        "starts": [
            {
                "theta0": _floats(s.theta0),
                "theta": _floats(s.theta),
                "value": _finite(s.value),
                "n_evals": int(s.n_evals),
                "converged": bool(s.converged),
            }
            for s in opt.starts
        ],
    }


def _opt_from(d: dict) -> OptimResult:
    def val(v: float | None) -> float:
        return -math.inf if v is None else float(v)

    starts = tuple(
        Start(np.array(s["theta0"], float), np.array(s["theta"], float), val(s["value"]),
              s["n_evals"], s["converged"])
        for s in d["starts"]
    )  # fmt: skip
    theta = np.array(d["theta"], float)
    return OptimResult(theta, val(d["value"]), starts, d["n_candidates"], d.get("n_probes", 0))


def _floats(a: Any) -> list[float]:
    return [float(v) for v in np.asarray(a, dtype=float).ravel()]


def _lower(M: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in M[i, : i + 1]] for i in range(M.shape[0])]


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _checksum(doc: dict, texts: dict[int, str] | None = None) -> str:
    """SHA-256 of ``doc``'s canonical JSON (sorted keys, no spaces, ASCII), the text
    ``json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=True)`` gives;
    ``texts`` holds lists of numbers already formatted (:func:`_number_texts`)."""
    return hashlib.sha256(_canonical(doc, texts or {}).encode("ascii")).hexdigest()


def _canonical(obj: Any, texts: dict[int, str]) -> str:
    if isinstance(obj, dict):
        items = (f"{json.dumps(k)}:{_canonical(obj[k], texts)}" for k in sorted(obj))
        return "{" + ",".join(items) + "}"
    if isinstance(obj, list) and obj and isinstance(obj[0], dict | list):
        return "[" + ",".join(_canonical(v, texts) for v in obj) + "]"
    text = texts.get(id(obj)) if isinstance(obj, list) else None
    if text is not None:  # numbers contain no ", ": only the separators change
        return text.replace(", ", ",")
    return json.dumps(
        obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False
    )


def _number_texts(obj: Any, out: dict[int, str]) -> dict[int, str]:
    """``json.dumps`` of every list of numbers (no strings) in ``obj``, by the list's id."""
    if isinstance(obj, dict):
        for v in obj.values():
            _number_texts(v, out)
    elif isinstance(obj, list) and obj and isinstance(obj[0], dict | list):
        for v in obj:
            _number_texts(v, out)
    elif isinstance(obj, list):
        text = json.dumps(obj, allow_nan=False)
        if '"' not in text:  # no strings (whose ", " would be no separator)
            out[id(obj)] = text
    return out


def _pretty(obj: Any, indent: int = 0, texts: dict[int, str] | None = None) -> str:
    """JSON with objects spread over lines and lists of numbers kept on one line."""
    pad = " " * (indent + 2)
    if isinstance(obj, dict) and obj:
        items = [f"{pad}{json.dumps(k)}: {_pretty(v, indent + 2, texts)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + "\n" + " " * indent + "}"
    if isinstance(obj, list) and obj and isinstance(obj[0], dict | list):
        items = [pad + _pretty(v, indent + 2, texts) for v in obj]
        return "[\n" + ",\n".join(items) + "\n" + " " * indent + "]"
    text = texts.get(id(obj)) if texts and isinstance(obj, list) else None
    return json.dumps(obj, allow_nan=False) if text is None else text


def _reject_constant(name: str) -> None:
    raise ValueError(f"{name} is not a number JSON allows")


def _float(text: str) -> float:
    """A JSON number as a finite float (``1e400`` is refused, not read as inf)."""
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"the number {_short(text)} is out of range (beyond 1.8e308)")
    return value


def _int(text: str) -> int:
    """A JSON integer, exact (a seed may have any number of digits); refused beyond 400
    digits, far past any float (where one is expected, a float's range is checked later)."""
    if len(text.lstrip("-")) > 400:
        raise ValueError(f"the integer {_short(text)} is out of range")
    return int(text)


def _short(text: str) -> str:
    return text if len(text) <= 24 else f"{text[:12]}...{text[-6:]} ({len(text)} characters)"


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _version() -> str:
    from .._version import __version__

    return __version__


def _period(cascade: Cascade, method: str) -> float | None:
    """The period of a cascade's GP stages: given as ``period=`` with the name ``periodic``,
    or that of a kernel object that repeats whole (a :class:`~cascal.kernels.Periodic`, with
    constants too; a review: such a model had been saved with none, and its file refused
    on loading); None for lookup tables, which do not wrap (as ``fit_model`` writes)."""
    if method == "lut":
        return None
    if cascade.period is not None or isinstance(cascade.kernel, str):
        return cascade.period
    period = common_period(cascade.kernel)
    return None if period is None else float(period)
