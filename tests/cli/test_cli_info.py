"""``cascal info``: a model file's summary and its input files' checksums."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
from cli_helpers import run_cascal

from cascal.cli_info import input_status
from cascal.io.modelfile import load_model
from cascal.workflow import correct


def test_info_prints_what_the_model_holds(linear_model):
    res = run_cascal("info", linear_model)
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""
    lines = res.stdout.splitlines()
    model = load_model(linear_model)
    assert lines[0] == f"{linear_model}: cascal model file, schema 1, checksum verified"
    digest = hashlib.sha256(linear_model.read_bytes()).hexdigest()  # as sha256sum prints it
    content = json.loads(linear_model.read_text())["checksum"]["value"]
    assert lines[1] == f"SHA-256 of the file {digest}; content checksum (sha256) {content}"
    lines.pop(1)
    assert f"Fitted {model.created} with cascal {model.cascal_version} (seed 0, 5 " in lines[1]
    assert lines[2] == "Method bayes, kernel se, unit m, 2 stages"
    for k, gp in enumerate(model.fitted.models):
        head = [i for i, t in enumerate(lines) if t.startswith(f"Stage {k} (")]
        (i,) = head
        ls = gp.hyperparameters["length_scale"]
        assert f"length_scale {ls:.4g} m," in lines[i]
        assert f"noise_variance {gp.hyperparameters['noise_variance']:.4g} m²" in lines[i]
        lml = gp.log_marginal_likelihood
        assert lines[i + 1] == f"  log marginal likelihood {lml:.6g}, no jitter"
        src = model.sources[k]
        assert lines[i + 2] == f"  input {src.file} (columns {', '.join(src.columns)}): unchanged"
        assert (
            lines[i + 3] == f"    SHA-256 {hashlib.sha256(Path(src.file).read_bytes()).hexdigest()}"
        )
    # The correction's size, computed here on a grid of the calibrated range.
    lo, hi = model.calibrated_range
    grid = np.linspace(lo, hi, 1001)
    c = correct(model, grid)
    rms = np.sqrt(np.mean((c.corrected - grid) ** 2))
    assert lines[-1] == f"Correction over it: RMS {rms:.3g} m, largest u {c.u.max():.3g} m"


def test_info_says_when_an_input_changed_or_is_gone(linear_files, tmp_path):
    files, _ = linear_files
    ref, dev = (shutil.copy(f, tmp_path / f.name) for f in files)
    model = tmp_path / "m.json"
    assert run_cascal("fit", ref, dev, "-o", model, "--method", "lut").returncode == 0
    with open(dev, "a") as fh:
        fh.write("0.5,0.5\n")
    (tmp_path / ref.name).unlink()
    res = run_cascal("info", model)
    assert res.returncode == 3, res.stderr  # (a user review: 0, no use to a script)
    assert f"  input {ref} (columns testbed, reference): not found" in res.stdout
    assert f"  input {dev} (columns device, testbed): changed since the fit" in res.stdout
    then, now = (load_model(model).sources[1].sha256, hashlib.sha256(dev.read_bytes()).hexdigest())
    assert f"    SHA-256 {then} at the fit, {now} now\n" in res.stdout and then != now
    assert res.stderr == (
        f"cascal info: warning: {dev} is not the file this model was fitted from (its "
        "SHA-256 differs)\n"
    )
    assert "log marginal likelihood" not in res.stdout  # lookup tables
    assert "Stage 0 (" in res.stdout and ": lookup table" in res.stdout
    assert res.stdout.splitlines()[-1].endswith(", no uncertainty (lookup tables)")
    dev.write_text(dev.read_text().removesuffix("0.5,0.5\n"))  # as fitted: only one not found
    assert run_cascal("info", model).returncode == 0


def test_input_status_looks_beside_the_model(tmp_path):
    import hashlib

    folder = tmp_path / "moved"
    folder.mkdir()
    f = folder / "stage.csv"
    f.write_text("a,b\n1,2\n")
    digest = hashlib.sha256(f.read_bytes()).hexdigest()
    assert input_status(f, digest) == ("unchanged", f)
    assert input_status(f, "0" * 64) == ("changed since the fit", f)
    # A relative path from the fit's folder: found by its name beside the model.
    assert input_status("elsewhere/stage.csv", digest) == ("not found", None)
    assert input_status("elsewhere/stage.csv", digest, base=folder) == ("unchanged", f)


def test_info_takes_the_unchanged_file_beside_the_model(linear_files, tmp_path, monkeypatch):
    files, _ = linear_files
    fitted, other = tmp_path / "fitted", tmp_path / "other"
    fitted.mkdir(), other.mkdir()
    for f in files:
        shutil.copy(f, fitted / f.name)
        (other / f.name).write_text(f.read_text() + "0.5,0.5\n")  # same names, other files
    monkeypatch.chdir(fitted)
    names = [f.name for f in files]
    assert run_cascal("fit", *names, "-o", "m.json", "--method", "lut").returncode == 0
    monkeypatch.chdir(other)  # relative paths from here name the other files
    res = run_cascal("info", "../fitted/m.json")
    assert res.returncode == 0 and res.stderr == ""
    for name in names:
        assert f"  input {name} " in res.stdout
        assert f"unchanged (as ../fitted/{name})" in res.stdout


def test_info_refuses_a_damaged_model(linear_model, tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(linear_model.read_text().replace('"seed": 0', '"seed": 1'))
    res = run_cascal("info", bad)
    assert res.returncode == 2 and "checksum mismatch" in res.stderr
    assert "Traceback" not in res.stderr and res.stdout == ""
    res = run_cascal("info", tmp_path / "missing.json")
    assert res.returncode == 2 and "cannot read the model file" in res.stderr


def test_info_repeats_what_fit_warned_of(linear_files, tmp_path):
    """A review's case: ``info`` of a homoscedastic cascade said nothing of its u, which
    ``fit`` had warned of; it now warns the same, and of a loaded model's findings."""
    files, _ = linear_files
    model = tmp_path / "h.json"
    fit = run_cascal("fit", *files, "-o", model, "--method", "homoscedastic")
    assert fit.returncode == 0, fit.stderr
    res = run_cascal("info", model)
    assert res.returncode == 0, res.stderr
    warned = [line for line in fit.stderr.splitlines() if "homoscedastic" in line]
    assert warned and res.stderr.splitlines() == [w.replace("fit:", "info:") for w in warned]


def test_outputs_never_overwrite_the_models_input_files(linear_files, tmp_path):
    """A review's case: ``cascal report m.json -o ref.csv`` replaced the reference file the
    model was fitted from (which ``info`` checks) with HTML. Every command that reads a
    model refuses to write over its input files, found as ``info`` finds them."""
    (ref, dev), readings = linear_files
    ref, dev = (shutil.copy(f, tmp_path / f.name) for f in (ref, dev))
    model = tmp_path / "m.json"
    assert run_cascal("fit", ref, dev, "-o", model).returncode == 0
    before = {p: p.read_bytes() for p in (ref, dev)}
    cases = [
        ("report", model, "-o", ref),
        ("correct", model, readings, "-o", dev),
        ("export", model, "-o", ref.with_suffix(".csv")),
        ("plan", model, "-n", "2", "-o", dev),
        ("verify", model, ref, "-o", dev),
        ("compare", model, model, "-o", ref),
    ]
    for args in cases:
        res = run_cascal(*args)
        assert res.returncode == 2, (args, res.stderr)
        assert "is the input file" in res.stderr and "Traceback" not in res.stderr
    assert {p: p.read_bytes() for p in (ref, dev)} == before


def test_outputs_never_overwrite_an_input_file_fitted_from_another_folder(
    linear_files, tmp_path, monkeypatch, capsys
):
    """A review's case: ``fit data/ref.csv data/dev.csv -o models/m.json`` run from the
    project folder, then ``report m.json -o ../data/ref.csv`` from ``models/``: the
    recorded paths (relative to the project) were not found from there, and the reference
    data were replaced by HTML with exit 0. An existing file with an input's recorded
    SHA-256 is refused wherever it lies; and a report is written to .html names only."""
    from cascal.cli import main

    (ref, dev), _ = linear_files
    (tmp_path / "data").mkdir()
    (tmp_path / "models").mkdir()
    ref, dev = (shutil.copy(f, tmp_path / "data" / f.name) for f in (ref, dev))
    before = {p: p.read_bytes() for p in (ref, dev)}
    monkeypatch.chdir(tmp_path)
    assert main(["fit", f"data/{ref.name}", f"data/{dev.name}", "-o", "models/m.json"]) == 0
    monkeypatch.chdir(tmp_path / "models")
    capsys.readouterr()
    for args in (
        ["report", "m.json", "-o", f"../data/{ref.name}"],
        ["export", "m.json", "-o", f"../data/{dev.name}"],
        ["correct", "m.json", f"../data/{dev.name}", "-o", f"../data/{ref.name}"],
    ):
        assert main(args) == 2, args
        err = capsys.readouterr().err
        assert "holds the input file data/" in err and "(the same SHA-256)" in err, err
    assert {p: p.read_bytes() for p in (ref, dev)} == before
    assert main(["report", "m.json", "-o", "report.csv"]) == 2
    assert "expected an .html file name" in capsys.readouterr().err
    assert not (tmp_path / "models" / "report.csv").exists()
    assert main(["report", "m.json", "-o", "report.HTML"]) == 0
