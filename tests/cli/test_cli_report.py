"""``cascal report``: one self-contained HTML page, rendered in headless Chromium."""

from __future__ import annotations

import base64
import io
import re
import shutil
import subprocess

import numpy as np
import pytest
from cli_helpers import run_cascal
from PIL import Image

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def report(linear_model, tmp_path_factory):
    out = tmp_path_factory.mktemp("report") / "report.html"
    res = run_cascal("report", linear_model, "-o", out)
    assert res.returncode == 0, res.stderr
    return out


def test_report_is_self_contained(report):
    text = report.read_text()
    srcs = re.findall(r'src="([^"]*)"', text)
    assert len(srcs) == 4  # two stages, the final correction and the plan
    assert all(s.startswith("data:image/png;base64,") for s in srcs)
    assert not re.search(r'(src|href)="(https?:|file:|/)', text)
    for s in srcs:
        img = Image.open(io.BytesIO(base64.b64decode(s.split(",", 1)[1])))
        assert img.size[0] > 500 and img.size[1] > 300
    for words in ("Stage 0", "Stage 1", "length_scale", "noise_variance", "SHA-256",
                  "Stretches where the reference could not measure", "U = 2u",
                  "Where to measure next with the reference"):  # fmt: skip
        assert words in text


def test_report_names_the_model_file_it_describes(report, linear_model):
    """A report review: a report named its model file by its base name alone, so two fits'
    reports could not be told apart by an auditor. It shows the content checksum and the
    file's SHA-256 that ``cascal info`` prints, the optimiser starts and the RMS
    correction."""
    import hashlib

    text = report.read_text()
    info = run_cascal("info", linear_model).stdout
    checksum = re.search(r"content checksum \(sha256\) ([0-9a-f]{64})", info).group(1)
    assert f"<td>content checksum (sha256)</td><td>{checksum}</td>" in text
    digest = hashlib.sha256(linear_model.read_bytes()).hexdigest()
    assert f"<td>SHA-256 of the file</td><td>{digest}</td>" in text
    assert "up to 5 optimiser starts per stage" in text
    rms = re.search(r"RMS ([0-9.e+-]+) m", info).group(1)  # (info: 3 digits)
    shown = re.search(r"RMS correction over the calibrated range: ([0-9.e+-]+) m", text)
    assert f"{float(shown.group(1)):.3g}" == rms


def test_report_plan_is_the_commands(report, linear_model):
    """The report's plan is ``cascal plan``'s default one; a lut model's report has none."""
    from cascal.io.modelfile import load_model
    from cascal.report import build_report
    from cascal.workflow import fit_model, plan_measurements
    from utils import demo_stages

    plan = plan_measurements(load_model(linear_model), 5).plan
    text = report.read_text()
    section = text[text.index("Where to measure next") :]
    for p in plan.positions:
        assert f"<td>{p:.6g}</td>" in section
    lut = build_report(fit_model(demo_stages(), method="lut"))
    assert "Where to measure next" not in lut


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_report_renders_with_figures_in_chromium(report, tmp_path):
    shot = tmp_path / "shot.png"
    subprocess.run(
        [
            CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
            "--no-first-run", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}",
            "--window-size=1200,2000", report.resolve().as_uri(),
        ],
        capture_output=True, timeout=120, check=False,
    )  # fmt: skip
    assert shot.exists(), "chromium wrote no screenshot"
    rgb = np.asarray(Image.open(shot).convert("RGB"), dtype=float)
    assert rgb.shape[:2] == (2000, 1200)
    gray = rgb.mean(axis=2)
    assert gray.std() > 20  # not blank
    assert np.mean(gray < 200) > 0.02  # text, lines and figures, not a white page
    # The figures: matplotlib's blue fit lines and 95 % bands.
    r, b = rgb[..., 0], rgb[..., 2]
    blue = (b - r > 25) & (b > 150)
    assert blue.sum() > 20000, "no figure (blue fit line or band) in the screenshot"
    rows = np.flatnonzero(blue.any(axis=1))
    assert rows.max() - rows.min() > 600  # more than one figure down the page
