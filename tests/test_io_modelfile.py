"""Model files: exact round trip, checksum, schema versions, schema and consistency checks."""

from __future__ import annotations

import copy
import json
import re

import jsonschema
import numpy as np
import pytest

from cascal.errors import InputError, JitterWarning, ModelFileError
from cascal.gp import FittedGP, fit_gp
from cascal.io import modelfile as mf
from cascal.io.modelfile import load_model, model_to_dict, save_model
from cascal.io.schema import SchemaError, load_schema, validate
from cascal.kernels import Constant, Matern32, Periodic, SquaredExp
from cascal.noise import Dense, Diagonal
from cascal.workflow import fit_model
from utils import demo_stages


@pytest.fixture(scope="module")
def models():
    stages = demo_stages()
    return {m: fit_model(stages, method=m, n_restarts=1) for m in ("bayes", "homoscedastic", "lut")}


@pytest.fixture
def saved(models, tmp_path):
    return save_model(tmp_path / "model.json", models["bayes"])


def _rewrite(path, change):
    """Edit a model file and give it a valid checksum again (as a forger would)."""
    doc = json.loads(path.read_text())
    change(doc)
    body = {k: v for k, v in doc.items() if k != "checksum"}
    doc["checksum"]["value"] = mf._checksum(body)
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("method", ["bayes", "homoscedastic", "lut"])
def test_round_trip_is_exact(models, method, tmp_path):
    model = models[method]
    loaded = load_model(save_model(tmp_path / "m.json", model))
    a, b = model_to_dict(model), model_to_dict(loaded)
    a["provenance"].pop("created"), b["provenance"].pop("created")
    assert a == b  # the known noise too: a dense one is read back as written
    n_dense = 0
    for m0, m1 in zip(model.fitted.models, loaded.fitted.models, strict=True):
        if isinstance(m0, FittedGP):
            assert m0.kernel == m1.kernel and m0.mean == m1.mean
            np.testing.assert_array_equal(m0.L, m1.L)
            np.testing.assert_array_equal(m0.alpha, m1.alpha)
            assert (m0.noise is None) == (m1.noise is None)
            if m0.noise is not None:
                n = m0.x.size
                np.testing.assert_array_equal(m1.noise.dense(n), m0.noise.dense(n))
            if isinstance(m1.noise, Dense):  # its eigendecomposition waits until asked for
                assert m1.noise._factor is None
                C0, C1 = (U @ U.T for U in (m0.noise.factor(n), m1.noise.factor(n)))
                np.testing.assert_allclose(C1, C0, rtol=0, atol=1e-13 * np.abs(C0).max())
                n_dense += 1
            assert m0.optimization.value == m1.optimization.value
            assert len(m0.optimization.starts) == len(m1.optimization.starts)
            assert m0.optimization.n_evals == m1.optimization.n_evals  # probes included
    assert n_dense == (method == "bayes")
    assert loaded.sources == model.sources and loaded.unit == "m"
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["schema_version"] == 1 and doc["provenance"]["cascal_version"]
    assert doc["provenance"]["inputs"][0]["sha256"] == "ab" * 32


def test_file_layout_is_readable(saved):
    text = saved.read_text()
    assert text.startswith('{\n  "schema_version": 1,')
    assert '"cholesky": [\n' in text  # one row of L per line
    assert text.count("\n") < 1000


def test_composite_kernels_and_noise_round_trip():
    k = (SquaredExp(0.2, 1e-4) + Periodic(1.5, 2e-5, period=0.5)) * Constant(3.0) + Matern32(
        0.1, 1e-6
    )
    assert mf._kernel_from(json.loads(json.dumps(mf._kernel_dict(k)))) == k
    C = np.array([[2.0, 0.5, 0.1], [0.5, 1.0, 0.2], [0.1, 0.2, 3.0]])
    n = Dense(C) + Diagonal(np.array([0.1, 0.2, 0.3]))
    back = mf._noise_from(json.loads(json.dumps(mf._noise_dict(n, 3))))
    np.testing.assert_allclose(back.dense(3), n.dense(3), rtol=1e-15)


def test_fitted_gp_from_arrays_predicts_identically(rng):
    x = np.sort(rng.uniform(0, 1, 30))
    y = x + 0.01 * np.sin(6 * x) + rng.normal(0, 1e-4, 30)
    gp = fit_gp(x, y, n_restarts=1)
    back = FittedGP.from_arrays(
        gp.x.tolist(), gp.y, kernel=gp.kernel, mean=gp.mean, noise=None,
        noise_variance=gp.noise_variance, L=gp.L.tolist(), alpha=gp.alpha,
    )  # fmt: skip
    xs = np.linspace(-0.1, 1.1, 57)
    for a, b in zip(
        gp.predict(xs, return_std=True), back.predict(xs, return_std=True), strict=True
    ):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(InputError, match="expected L"):
        FittedGP.from_arrays(x, y, kernel=gp.kernel, mean=gp.mean, noise=None,
                             noise_variance=0.0, L=gp.L[:-1], alpha=gp.alpha)  # fmt: skip
    with pytest.raises(InputError, match="lower-triangular"):
        FittedGP.from_arrays(x, y, kernel=gp.kernel, mean=gp.mean, noise=None,
                             noise_variance=0.0, L=gp.L.T, alpha=gp.alpha)  # fmt: skip


def test_edited_file_fails_the_checksum(saved):
    text = saved.read_text()
    i = text.index('"alpha": [') + len('"alpha": [')
    j = text.index(".", i) + 1  # the first decimal of the first weight
    saved.write_text(text[:j] + str((int(text[j]) + 1) % 10) + text[j + 1 :])
    with pytest.raises(ModelFileError, match="checksum mismatch"):
        load_model(saved)


def test_checksum_is_of_the_canonical_json(models):
    """The checksum hashes the text json.dumps gives with sorted keys and no spaces, also
    when lists of numbers come formatted in advance (as save_model does), and with a
    column name holding ", " (a list of strings is formatted afresh)."""
    import hashlib

    doc = model_to_dict(models["bayes"])
    doc["provenance"]["inputs"][0]["columns"] = ["reading, mm", "reference"]
    canon = json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    expected = hashlib.sha256(canon.encode("ascii")).hexdigest()
    texts = mf._number_texts(doc, {})
    assert len(texts) > 10
    assert mf._checksum(doc, texts) == expected == mf._checksum(doc)
    assert json.loads(mf._pretty(doc, texts=texts)) == json.loads(canon)
    mixed = {"z": [1.5, {"b": [2.0, 3.0], "a": "x, y"}, [4, 5]], "a": [[], {}, None, True]}
    want = json.dumps(mixed, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    assert mf._canonical(mixed, mf._number_texts(mixed, {})) == want


@pytest.mark.parametrize("cut", ["end", "number"])
def test_truncated_file(saved, cut):
    """Cut anywhere, also within a number (a review's case: "...157e" at 5000 bytes read
    "Expecting ',' delimiter" without the hint, the error one character before the end)."""
    text = saved.read_text()
    if cut == "number":
        at = re.compile(r"\d\.\d+e-").search(text, len(text) // 3).end() - 1
        text = text[:at]  # just after a number's "e"
        assert re.search(r"\d\.\d+e$", text)
    saved.write_text(text if cut == "number" else text[:-40])
    with pytest.raises(ModelFileError, match=r"\(the file ends early: truncated\?\)"):
        load_model(saved)


@pytest.mark.parametrize(
    ("version", "words"), [(3, "newer than this cascal"), (0, "not supported"), ("1", "no integer")]
)
def test_other_schema_versions_are_refused(saved, version, words):
    _rewrite(saved, lambda d: d.__setitem__("schema_version", version))
    with pytest.raises(ModelFileError, match=words):
        load_model(saved)


def test_schema_violation_with_a_valid_checksum(saved):
    _rewrite(saved, lambda d: d["stages"][1]["model"]["kernel"].__setitem__("length_scale", -1))
    with pytest.raises(ModelFileError, match=r"schema 1: \$\.stages\[1\]\.model"):
        load_model(saved)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda d: d["stages"][0]["model"]["cholesky"][3].append(0.5), "cholesky"),
        (lambda d: d.__setitem__("calibrated_range", [0.0, 1.0]), "calibrated_range"),
        (lambda d: d["stages"][1]["model"]["alpha"].pop(), "alpha"),
        (lambda d: d.__setitem__("method", "lut"), "does not match the stage models"),
        (lambda d: d["provenance"]["inputs"].pop(), "input files for 2 stages"),
        # a review's forgeries, which had loaded (the first corrected readings wrongly)
        (lambda d: d["stages"][1]["x"].reverse(), "do not belong to one fit"),
        (lambda d: d["stages"][1]["model"]["targets"].__setitem__(3, 0.5), "one fit"),
        (lambda d: d["stages"][1]["model"]["alpha"].__setitem__(3, 1.0), "one fit"),
        (
            lambda d: d["stages"][0].__setitem__("noise", [-1e-8] * len(d["stages"][0]["x"])),
            "noise variance below 0",
        ),
        (lambda d: d.__setitem__("kernel", "periodic"), "kernel 'periodic' with period None"),
        (lambda d: d.__setitem__("unit", "m\nrm"), "printable characters"),
    ],
)
def test_inconsistent_arrays_with_a_valid_checksum(saved, change, words):
    _rewrite(saved, change)
    with pytest.raises(ModelFileError, match=f"inconsistent model file: .*{words}"):
        load_model(saved)


def test_nan_is_refused(saved):
    saved.write_text(saved.read_text().replace('"jitter": 0.0', '"jitter": NaN', 1))
    with pytest.raises(ModelFileError, match="NaN"):
        load_model(saved)


def test_numbers_beyond_a_float_are_refused_and_any_seed_is_kept(saved, models, tmp_path):
    """A review's cases: "jitter": 1e400 (read as inf) and an integer of 400 digits among
    the readings ended in tracebacks; a UTF-16 file named a codec. A seed of 24 digits
    (any seed is allowed) still loads, exactly."""
    text = saved.read_text()
    saved.write_text(text.replace('"jitter": 0.0', '"jitter": 1e400', 1))
    with pytest.raises(ModelFileError, match=r"the number 1e400 is out of range"):
        load_model(saved)
    saved.write_text(text)
    _rewrite(saved, lambda d: d["stages"][1]["x"].__setitem__(0, 10**350))
    with pytest.raises(ModelFileError, match=r"inconsistent .*a number out of range"):
        load_model(saved)
    saved.write_text(text)  # an integer where a float is due: read as one (1e20 here)
    _rewrite(
        saved, lambda d: d["stages"][1]["model"].__setitem__("log_marginal_likelihood", 10**20)
    )
    assert load_model(saved).fitted.models[1].log_marginal_likelihood == 1e20
    _rewrite(saved, lambda d: d["stages"][1].__setitem__("counts", [2**63] * 100))
    with pytest.raises(ModelFileError, match=r"inconsistent .*a number out of range \("):
        load_model(saved)  # an integer beyond int64 among the counts
    _rewrite(saved, lambda d: d["stages"][1]["x"].__setitem__(0, 10**500))
    with pytest.raises(ModelFileError, match=r"the integer 1000.* \(501 characters\) is out"):
        load_model(saved)
    saved.write_text(text, encoding="utf-16")
    with pytest.raises(ModelFileError, match="not UTF-8 text"):
        load_model(saved)
    big = fit_model(demo_stages(), method="lut", seed=123456789012345678901234)
    path = save_model(tmp_path / "big_seed.json", big)
    assert load_model(path).seed == 123456789012345678901234


@pytest.mark.parametrize(
    "stage, key, factor",
    [(1, "length_scale", 3.0), (1, "noise_variance", 100.0), (0, "variance", 1.001)],
)
def test_an_edited_hyperparameter_with_a_valid_checksum_is_refused(saved, stage, key, factor):
    """A review's case: stage 1's length scale tripled and its noise set to 1e-6, the
    checksum recomputed: the file loaded, its corrections moved by 0.25 mm and every u was
    0. The stored Cholesky factor must factorise the stored hyperparameters' covariance."""

    def edit(d) -> None:
        model = d["stages"][stage]["model"]
        where = model if key == "noise_variance" else model["kernel"]
        where[key] = where[key] * factor

    _rewrite(saved, edit)
    with pytest.raises(ModelFileError, match=r"cholesky does not factorise the covariance"):
        load_model(saved)


def test_a_factor_with_recorded_jitter_is_accepted_and_an_edited_jitter_is_not():
    """The factor check adds the recorded jitter to the diagonal: a fit that needed jitter
    (50 readings 1 mm apart, SE(0.2, 1e-4), no noise) passes, and its jitter raised a
    millionfold does not (the review's check had seen no fit with jitter)."""
    from dataclasses import replace

    x = np.linspace(0.0, 0.05, 50)
    hyper = {"length_scale": 0.2, "variance": 1e-4}
    with pytest.warns(JitterWarning, match="needed jitter"):
        fit = fit_gp(
            x, x + 1e-3 * np.sin(20 * x), noise=0.0, learn_noise=False, hyperparameters=hyper
        )
    assert fit.jitter > 0.0
    mf._check_factor(fit)
    with pytest.raises(ValueError, match=r"cholesky does not factorise the covariance"):
        mf._check_factor(replace(fit, jitter=1e6 * fit.jitter))
    with pytest.raises(ValueError, match=r"cholesky does not factorise the covariance"):
        mf._check_factor(replace(fit, kernel=SquaredExp(0.2, 1e-4 * (1 + 1e-6))))


def test_a_bad_period_is_named_as_such(saved):
    """A review's case: a period of -1.5 read "expected null, got number" (the first of
    the allowed forms), not what is wrong with it."""
    _rewrite(saved, lambda d: d.__setitem__("period", -1.5))
    with pytest.raises(ModelFileError, match=r"\$\.period: expected a number > 0, got -1\.5"):
        load_model(saved)


def test_schema_validator():
    schema = load_schema("model", 1)
    assert schema["properties"]["schema_version"] == {"const": 1}
    with pytest.raises(SchemaError, match=r"\$\.a: expected number, got string"):
        validate({"a": "x"}, {"type": "object", "properties": {"a": {"type": "number"}}})
    with pytest.raises(SchemaError, match="unexpected 'b'"):
        validate({"b": 1}, {"type": "object", "properties": {}, "additionalProperties": False})
    with pytest.raises(SchemaError, match=r"\$\[1\]"):
        validate([1, True], {"type": "array", "items": {"type": "number"}})
    with pytest.raises(ValueError, match="not supported"):
        validate(1, {"multipleOf": 2})
    validate(1, {"oneOf": [{"type": "null"}, {"type": "integer", "minimum": 1}]})


def _shortened(node, k: int = 2):
    """A copy of a JSON document with every list cut to its first ``k`` items."""
    if isinstance(node, dict):
        return {key: _shortened(v, k) for key, v in node.items()}
    if isinstance(node, list):
        return [_shortened(v, k) for v in node[:k]]
    return node


def _paths(node, prefix=()):
    """Paths to every value of a JSON document below its root."""
    if isinstance(node, dict):
        items = node.items()
    elif isinstance(node, list):
        items = enumerate(node)
    else:
        return
    for key, value in items:
        yield (*prefix, key)
        yield from _paths(value, (*prefix, key))


#: Replacement values of every JSON type, at the edges the schema's rules test.
_EDITS = [None, True, False, 0, -1, 1, 0.0, 2.5, [], [1.0], {}]
_EDITS += ["", "x", "bayes", "a" * 64, "0" * 64]


@pytest.mark.parametrize("method", ["bayes", "lut"])  # a GP stage (dense noise) and a table
def test_shipped_schema_agrees_with_jsonschema(models, method, tmp_path):
    """Our validator and the jsonschema library accept and refuse the same documents: each
    saved model (lists cut to 2 items), and each one edit away from it: any value replaced
    by any of ``_EDITS``, any key removed, an unknown key added to any object, an item
    appended to any list."""
    schema = load_schema("model", 1)
    peer = jsonschema.Draft202012Validator(schema)
    doc = _shortened(json.loads(save_model(tmp_path / "m.json", models[method]).read_text()))

    def ours(d) -> bool:
        try:
            validate(d, schema)
        except SchemaError:
            return False
        return True

    def edited(path, edit):
        d = copy.deepcopy(doc)
        parent = d
        for key in path[:-1]:
            parent = parent[key]
        edit(parent, path[-1])
        return d

    variants = [doc]
    for path in _paths(doc):
        variants += [edited(path, lambda p, k, v=v: p.__setitem__(k, v)) for v in _EDITS]
        variants.append(edited(path, lambda p, k: p.__delitem__(k)))
        variants.append(edited(path, lambda p, k: _grow(p[k])))
    verdicts = [(peer.is_valid(d), ours(d)) for d in variants]
    disagree = [d for d, (a, b) in zip(variants, verdicts, strict=True) if a != b]
    assert not disagree, disagree[0]
    refused = sum(not a for a, _ in verdicts)
    assert verdicts[0] == (True, True) and 0.5 * len(variants) < refused < len(variants)


def _grow(node) -> None:
    """Add an unknown key to an object or an item to a list (other values stay as they are)."""
    if isinstance(node, dict):
        node["unexpected"] = 1.0
    elif isinstance(node, list):
        node.append(node[0] if node else 1.0)


def test_atomic_write_gives_the_usual_permissions(tmp_path):
    from cascal.io import atomic

    path = atomic.write_text(tmp_path / "a.txt", "x")
    assert path.read_text() == "x"
    # what open() would give a new file under the process umask, not mkstemp's 0600
    assert (path.stat().st_mode & 0o777) == 0o666 & ~atomic._UMASK
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]  # no temporary left behind


def test_atomic_write_names_the_file_it_could_not_write(tmp_path):
    """A destination that is a folder, or under a file: the error names the destination
    (not the temporary file), and nothing is left behind."""
    from cascal.io import atomic

    (tmp_path / "taken").mkdir()
    (tmp_path / "plain").write_text("x")
    for dest in (tmp_path / "taken", tmp_path / "plain" / "under.txt"):
        with pytest.raises(OSError, match=f"cannot write {dest}: ") as info:
            atomic.write_text(dest, "y")
        assert info.value.errno is not None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plain", "taken"]
    assert not any((tmp_path / "taken").iterdir())


def test_atomic_write_names_the_file_on_a_full_disk(tmp_path):
    """A write that fails with no file named (a full disk's ENOSPC): the error names the
    destination, the file there keeps its content and no temporary is left."""
    import errno

    from cascal.io import atomic

    dest = tmp_path / "m.json"
    dest.write_text("good")

    def full(tmp: str) -> None:
        with open(tmp, "w") as fh:
            fh.write("partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match=f"cannot write {dest}: No space left on device"):
        atomic.atomic_write(dest, full)
    assert dest.read_text() == "good"
    assert [p.name for p in tmp_path.iterdir()] == ["m.json"]

    def encoder(tmp: str) -> None:  # an error with a message only keeps it
        raise OSError("PNG encoder failed")

    with pytest.raises(OSError, match=r"^PNG encoder failed$"):
        atomic.atomic_write(dest, encoder)


def test_atomic_write_keeps_links_and_writes_pipes_in_place(tmp_path):
    """A symbolic link keeps pointing at the (replaced) target; a named pipe is written
    through, not replaced by a regular file."""
    import os
    import threading

    from cascal.io import atomic

    target = tmp_path / "target.txt"
    target.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(target)
    atomic.write_text(link, "new")
    assert link.is_symlink() and target.read_text() == "new"
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    atomic.write_text(fifo, "through the pipe")
    reader.join(timeout=10)
    assert got == ["through the pipe"] and fifo.is_fifo()


def test_excluded_rows_are_kept_in_schema_version_2(models, tmp_path):
    import dataclasses

    model = models["bayes"]
    sources = (dataclasses.replace(model.sources[0], excluded=(7, 41)), *model.sources[1:])
    excluded = dataclasses.replace(model, sources=sources)
    path = save_model(tmp_path / "m.json", excluded)
    doc = json.loads(path.read_text())
    assert doc["schema_version"] == 2 == mf.schema_version(excluded)
    assert doc["provenance"]["inputs"][0]["excluded_rows"] == [7, 41]
    assert "excluded_rows" not in doc["provenance"]["inputs"][1]
    loaded = load_model(path)
    assert loaded.sources == excluded.sources
    inputs = [model_to_dict(m)["provenance"]["inputs"] for m in (loaded, excluded)]
    assert inputs[0] == inputs[1]
    # Version 1 has no place for them: a reader of version 1 could not take this file.
    with pytest.raises(SchemaError, match="unexpected 'excluded_rows'"):
        validate(dict(doc, schema_version=1), load_schema("model", 1))
    # Without exclusions, version 1 as before (older cascal versions read it).
    assert mf.schema_version(model) == 1
    _rewrite(path, lambda d: d["provenance"]["inputs"][0].__setitem__("excluded_rows", [41, 7]))
    with pytest.raises(ModelFileError, match=r"inconsistent model file: .*must increase"):
        load_model(path)


def test_schema_2_is_schema_1_with_the_excluded_rows():
    one, two = load_schema("model", 1), load_schema("model", 2)
    items = two["$defs"]["provenance"]["properties"]["inputs"]["items"]["properties"]
    assert items.pop("excluded_rows")["items"] == {"type": "integer", "minimum": 2}
    assert two["properties"].pop("schema_version") == {"const": 2}
    assert one["properties"].pop("schema_version") == {"const": 1}
    for s in (one, two):
        for key in ("$id", "title", "description"):
            s.pop(key)
        s["$defs"]["provenance"]["properties"]["inputs"]["items"]["properties"]["rows"].pop(
            "description", None
        )
    assert one == two


@pytest.mark.parametrize("method", ["bayes", "lut"])
def test_a_cascade_fitted_in_python_is_saved_and_predicts_alike(method, tmp_path):
    """CalibrationModel.from_cascade: no files, each stage named with the SHA-256 of its
    readings; the saved model predicts bit for bit what the fitted cascade does."""
    import hashlib

    from cascal import CalibrationModel, Cascade
    from cascal.simulation import simulate_trial

    trial = simulate_trial(np.random.default_rng(4))
    cascade = Cascade([trial.d2, trial.d1], method, n_restarts=2)
    fitted = cascade.fit()
    model = CalibrationModel.from_cascade(cascade, fitted, unit="mm")
    loaded = load_model(save_model(tmp_path / "py.json", model))
    r = np.linspace(*fitted.calibrated_range, 9)
    std = method != "lut"
    np.testing.assert_array_equal(
        np.asarray(loaded.fitted.correct(r, return_std=std)),
        np.asarray(fitted.correct(r, return_std=std)),
    )
    x, y = trial.d2
    src = loaded.sources[0]
    assert src.file == "<testbed>" and src.rows == 64 and loaded.unit == "mm"
    assert src.sha256 == hashlib.sha256(x.tobytes() + y.tobytes()).hexdigest()
    other = Cascade([trial.d2, (trial.d1[0] + 1e-3, trial.d1[1])], method, n_restarts=2)
    with pytest.raises(InputError, match="not a fit of this cascade"):
        CalibrationModel.from_cascade(other, fitted)


def test_a_prefix_of_another_kernel_loads_and_a_long_unit_is_refused_when_fitted(tmp_path):
    """A review's cases: a device stage fitted with another kernel on a saved test-bed model
    was written and then refused on load; a unit of over 20 characters was written and
    then refused. The first loads; the second is refused at the fit, before any file."""
    stages = demo_stages()
    tb = load_model(save_model(tmp_path / "tb.json", fit_model(stages[:1], n_restarts=1)))
    dev = fit_model(stages[1:], prefix=tb, kernel="matern52", n_restarts=1)
    loaded = load_model(save_model(tmp_path / "dev.json", dev))
    kernels = [type(m.kernel).__name__ for m in loaded.fitted.models]
    assert kernels == ["SquaredExp", "Matern52"]
    with pytest.raises(InputError, match="unit: expected 1 to 20 printable characters"):
        fit_model(stages[:1], n_restarts=1, unit="micrometre per metre (um/m)")


def test_atomic_write_keeps_a_replaced_files_mode_and_names_a_full_device(tmp_path):
    """A review's cases: replacing a 0600 file made it 0644 (a private model readable by
    all); a link to /dev/full ended with "No space left on device", naming no file."""
    import os
    import stat

    from cascal.io import atomic

    private = tmp_path / "private.h"
    private.write_text("old")
    os.chmod(private, 0o600)
    atomic.write_text(private, "new")
    assert private.read_text() == "new" and stat.S_IMODE(private.stat().st_mode) == 0o600
    fresh = atomic.write_text(tmp_path / "fresh.h", "x")
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(fresh.stat().st_mode) == 0o666 & ~umask
    if os.path.exists("/dev/full"):
        link = tmp_path / "full.h"
        link.symlink_to("/dev/full")
        with pytest.raises(OSError, match=f"cannot write {link}: No space left on device"):
            atomic.write_text(link, "x" * 100_000)


def test_writes_together_are_all_or_none(tmp_path):
    """A review's case: ``verify -o table --plot figure`` on a disk that filled up at the
    figure had replaced the table already. Inside ``together`` every write is finished
    first and the renames come last: a failure leaves every old file as it was, and no
    temporary behind."""
    import errno

    from cascal.io import atomic

    a, b = tmp_path / "a.csv", tmp_path / "b.png"
    a.write_text("old a")
    b.write_text("old b")

    def full(tmp: str) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(OSError, match=f"cannot write {b}"), atomic.together():
        atomic.write_text(a, "new a")
        assert a.read_text() == "old a"  # not renamed yet
        atomic.atomic_write(b, full)
    assert (a.read_text(), b.read_text()) == ("old a", "old b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.png"]
    with atomic.together():
        atomic.write_text(a, "new a")
        atomic.write_text(b, "new b")
    assert (a.read_text(), b.read_text()) == ("new a", "new b")
    atomic.write_text(a, "alone")  # outside a block: at once
    assert a.read_text() == "alone"
    full = tmp_path / "full.png"  # a device that fails: copied before any rename
    full.symlink_to("/dev/full")
    with pytest.raises(OSError, match=f"cannot write {full}"), atomic.together():
        atomic.write_text(a, "newer a")
        atomic.write_text(full, "figure")
    assert a.read_text() == "alone"
    with pytest.raises(RuntimeError), atomic.together():  # a block inside joins the outer
        with atomic.together():
            atomic.write_text(b, "inner b")
        raise RuntimeError("after the inner block")
    assert b.read_text() == "new b"
    with atomic.together():  # a failed inner block's writes are dropped, the outer's kept
        try:
            with atomic.together():
                atomic.write_text(a, "inner a")
                raise RuntimeError("inner")
        except RuntimeError:
            pass
        atomic.write_text(b, "outer b")
    assert (a.read_text(), b.read_text()) == ("alone", "outer b")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "b.png", "full.png"]


def test_stages_with_a_known_noise_of_any_diagonal_form_are_saved(tmp_path):
    """An API review's case: a Stage whose known noise was an (n, n) matrix or a Noise
    object fitted, then failed in save_model with NumPy's own error. A diagonal one is
    now kept as one variance per reading; one with correlations, which a model file
    cannot keep, is refused by name before anything is written."""
    from cascal import CalibrationModel, Cascade, Dense, Diagonal, Stage, load_model, save_model
    from cascal.simulation import simulate_trial

    trial = simulate_trial(np.random.default_rng(0))
    (tb, ref), (dev, tbd) = trial.d2, trial.d1
    n = tb.size
    r = np.linspace(dev.min(), dev.max(), 9)
    for noise in (np.eye(n) * 1e-12, Diagonal(1e-12), Dense(np.eye(n) * 1e-12)):
        cascade = Cascade([Stage(tb, ref, noise=noise, name="testbed"), (dev, tbd)])
        fitted = cascade.fit()
        model = CalibrationModel.from_cascade(cascade, fitted)
        back = load_model(save_model(tmp_path / "m.json", model))
        assert np.array_equal(back.data[0].noise, np.full(n, 1e-12))
        assert np.array_equal(back.fitted.correct(r), fitted.correct(r))
    corr = 1e-12 * np.exp(-(np.subtract.outer(tb, tb) ** 2) / 0.01)
    cascade = Cascade([Stage(tb, ref, noise=corr, name="testbed"), (dev, tbd)])
    with pytest.raises(InputError, match="stage 'testbed': its known noise has correlations"):
        CalibrationModel.from_cascade(cascade, cascade.fit())


def _shift_stage_1(doc: dict) -> None:
    """Stage 1's test-bed readings moved, its table and targets kept: they are no longer
    those readings mapped through stage 0's table."""
    y = doc["stages"][1]["y"]
    doc["stages"][1]["y"] = [v + 1e-4 for v in y]


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda d: d["stages"][0]["model"]["offsets"].__setitem__(2, 1.0), "stage 0: its table"),
        (lambda d: d["stages"][1]["model"]["targets"].__setitem__(4, 0.5), "stage 1: its table"),
        (_shift_stage_1, "stage 1: its targets are not the readings above it mapped"),
    ],
)
def test_an_edited_lookup_table_is_refused(models, tmp_path, change, words):
    """A fuzzing review's case: a lut model's offsets edited (the checksum made again)
    loaded, and every correction came out 1 m off; GP models refused such edits. A
    table is now checked against the data it was made from."""
    path = save_model(tmp_path / "lut.json", models["lut"])
    assert load_model(path).method == "lut"  # as written: fine
    _rewrite(path, change)
    with pytest.raises(ModelFileError, match=f"inconsistent model file: {words}"):
        load_model(path)


def test_a_byte_order_mark_loads_and_trailing_text_is_named(saved):
    """A fuzzing review's cases: a model file saved by an editor with a UTF-8 byte-order
    mark was refused with Python's JSON message, and one stray character after the model
    was called a truncated file."""
    text = saved.read_text()
    saved.write_text(text, encoding="utf-8-sig")
    assert load_model(saved).method == "bayes"
    saved.write_text(text + "x")
    with pytest.raises(ModelFileError, match=r"Extra data \(text after the model's closing"):
        load_model(saved)


def test_a_model_file_claiming_a_period_its_device_kernel_lacks_is_refused(saved):
    """A review's case: a linear model's file edited to say kernel "periodic", period 360
    (its checksum recomputed) was read, and readings of other turns corrected as in range."""
    _rewrite(saved, lambda doc: doc.update(kernel="periodic", period=360.0))
    with pytest.raises(ModelFileError, match=r"a period of 360\.0, but the device stage's kernel"):
        load_model(saved)


def test_edits_that_keep_the_sampled_checks_are_refused(saved):
    """A fuzz review's forgeries with the checksum recomputed, each of which loaded and
    moved corrections or u with exit 0: a GP stage's targets and prior mean moved by 1 mm
    together (every correction 1 mm off), one factor entry of 1e154 (the round-off
    allowance overflowed to infinity and passed anything), and a row of the factor rotated
    where neither the diagonal nor the first, middle and last columns once checked see it
    (the weights solved again for it)."""

    def targets(d) -> None:
        m = d["stages"][1]["model"]
        m["targets"] = [t + 1e-3 for t in m["targets"]]
        m["mean"]["offset"] += 1e-3

    _rewrite(saved, targets)
    with pytest.raises(ModelFileError, match=r"stage 1: its targets are not the stage above"):
        load_model(saved)


def _factor_edit(saved, tmp_path, edit):
    path = tmp_path / "edited.json"
    path.write_text(saved.read_text())

    def change(d) -> None:
        m = d["stages"][1]["model"]
        n = len(m["cholesky"])
        L = np.zeros((n, n))
        for i, r in enumerate(m["cholesky"]):
            L[i, : i + 1] = r
        edit(L)
        x = np.array(d["stages"][1]["x"])
        r = np.array(m["targets"]) - (m["mean"]["slope"] * x + m["mean"]["offset"])
        m["alpha"] = np.linalg.solve(L.T, np.linalg.solve(L, r)).tolist()
        m["cholesky"] = [L[i, : i + 1].tolist() for i in range(n)]

    _rewrite(path, change)
    return path


def test_a_factor_edited_out_of_sight_of_fixed_columns_is_refused(saved, tmp_path):
    def huge(L) -> None:
        L[5, 3] = 1e154

    with pytest.raises(ModelFileError, match=r"do not belong to one fit|does not factorise"):
        load_model(_factor_edit(saved, tmp_path, huge))

    def rotate(L) -> None:  # row i in a plane orthogonal to e_0, e_i and the rows 0, n/2, n-1
        n = L.shape[0]
        i = n - 3
        C = np.array([np.eye(i + 1)[0], np.eye(i + 1)[i], L[n // 2, : i + 1], L[n - 1, : i + 1]])
        free = np.linalg.qr(C.T, mode="complete")[0][:, 4:6]
        row = L[i, : i + 1]
        a, b = row @ free
        turned = row - a * free[:, 0] - b * free[:, 1] - b * free[:, 0] + a * free[:, 1]
        np.testing.assert_allclose(turned @ turned, row @ row, rtol=1e-12)
        L[i, : i + 1] = turned

    path = _factor_edit(saved, tmp_path, rotate)
    doc = json.loads(path.read_text())
    old = json.loads(saved.read_text())["stages"][1]["model"]["cholesky"]
    new = doc["stages"][1]["model"]["cholesky"][-3]
    assert max(abs(a - b) for a, b in zip(new, old[-3], strict=True)) > 0
    with pytest.raises(ModelFileError, match=r"cholesky does not factorise the covariance"):
        load_model(path)


def test_a_lone_surrogate_is_refused_and_other_names_are_kept(saved, tmp_path):
    """A fuzz review's case: a file name holding "\\ud800" (valid JSON) loaded, and info,
    plan, compare and report printed it with a traceback. A name with an emoji (a pair, as
    JSON escapes it) and one with a byte that is not UTF-8 (U+DC80 to U+DCFF, as Python
    reads such a file name) load."""
    for name, ok in (("a\ud800.csv", False), ("\U0001f600.csv", True), ("x\udcff.csv", True)):
        path = tmp_path / "named.json"
        path.write_text(saved.read_text())

        def rename(d, name=name) -> None:
            d["provenance"]["inputs"][0]["file"] = name

        _rewrite(path, rename)
        if ok:
            assert load_model(path).sources[0].file == name
        else:
            with pytest.raises(ModelFileError, match=r"a text holds a lone surrogate"):
                load_model(path)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda d: d.update(method="homoscedastic"), "'homoscedastic', but stage 1 carries corr"),
        (lambda d: d.update(kernel="matern52"), "kernel 'matern52', but the device stage's is"),
    ],
)
def test_labels_that_contradict_the_stages_are_refused(saved, edit, words):
    """A fuzz review: a bayes model relabelled homoscedastic loaded (plan then planned for
    another target), and so did a kernel label the stages do not have."""
    _rewrite(saved, edit)
    with pytest.raises(ModelFileError, match=re.escape(words)):
        load_model(saved)


def test_a_model_file_saved_as_utf16_is_named_so(saved):
    """A fuzz review: UTF-16 without a byte-order mark was called "truncated?"."""
    saved.write_bytes(saved.read_text().encode("utf-16-le"))
    with pytest.raises(ModelFileError, match=r"UTF-16 text \(NUL bytes\), not the UTF-8 JSON"):
        load_model(saved)


def test_a_known_noise_given_as_a_diagonal_matrix_loads_in_either_method(tmp_path):
    """A diff review: a homoscedastic model whose device stage's known noise was given as
    a diagonal (n, n) matrix (a dense noise object) was refused as bayes relabelled."""
    from cascal import CalibrationModel, Cascade, Stage

    rng = np.random.default_rng(5)
    x0 = np.sort(rng.uniform(0, 10, 50))
    x1 = np.sort(rng.uniform(0.5, 9.5, 40))
    s0 = Stage(x0 + 0.01 * np.sin(x0), x0, None, "tb")
    s1 = Stage(x1 + 0.003 * np.cos(x1), x1, np.diag(np.full(40, 1e-8)), "dev")
    for method in ("homoscedastic", "bayes"):
        cascade = Cascade([s0, s1], method, n_restarts=1)
        model = CalibrationModel.from_cascade(cascade, cascade.fit())
        loaded = load_model(save_model(tmp_path / f"{method}.json", model))
        assert loaded.method == method
