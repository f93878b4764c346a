"""``cascal export``: compensation tables through the installed command."""

from __future__ import annotations

import hashlib
import json
import re

import numpy as np
from cli_helpers import run_cascal

from cascal.io.modelfile import load_model
from cascal.workflow import compensation


def test_header_and_csv_hold_the_library_table(linear_model, tmp_path):
    """The CSV's nodes and corrections are the library's table to the last bit; the header
    carries the same numbers, its provenance and the error found; the command says where
    the table went and how good it is."""
    table = compensation(load_model(linear_model))
    res = run_cascal("export", linear_model, "-o", tmp_path / "axis-1.csv")
    assert res.returncode == 0, res.stderr
    assert f"{table.n} nodes" in res.stdout and "largest interpolation error" in res.stdout
    rows = np.loadtxt(tmp_path / "axis-1.csv", delimiter=",", skiprows=1)
    assert np.array_equal(rows[:, 0], table.nodes())
    assert np.array_equal(rows[:, 1], table.correction)
    assert np.array_equal(rows[:, 3], table.u)
    res = run_cascal("export", linear_model, "-o", tmp_path / "axis-1.h")
    assert res.returncode == 0, res.stderr
    text = (tmp_path / "axis-1.h").read_text()
    assert "int axis_1_correct(double reading, double *corrected)" in text  # name from file
    assert f"#define axis_1_N {table.n}" in text and linear_model.name in text
    assert repr(float(table.correction[7])) in text and f"{table.error:.3g}" in text
    # a review's case: the header named the content checksum inside the model file as "the
    # model file's checksum", which neither sha256sum nor cascal info showed
    digest = hashlib.sha256(linear_model.read_bytes()).hexdigest()
    content = json.loads(linear_model.read_text())["checksum"]["value"]
    assert f" * {digest};\n" in text and f" * {content}.\n" in text
    info = run_cascal("info", linear_model).stdout
    assert digest in info and content in info
    model_text = linear_model.read_text()
    piped = run_cascal("export", "/dev/stdin", "-o", "-", "--format", "h", stdin=model_text)
    assert piped.returncode == 0, piped.stderr
    assert "read from a pipe" in piped.stdout and digest not in piped.stdout
    res = run_cascal("export", linear_model, "-o", tmp_path / "t.h", "--tolerance", "1e-4")
    assert res.returncode == 0, res.stderr
    loose = re.search(r"#define t_N (\d+)\n", (tmp_path / "t.h").read_text())
    assert int(loose.group(1)) < table.n  # a looser tolerance, a smaller table


def test_standard_output_takes_the_format_from_the_option(linear_model, tmp_path):
    """``-o -`` writes the table to standard output, the messages to standard error; the
    format comes from ``--format`` there and must agree with a file's suffix."""
    res = run_cascal("export", linear_model, "-o", "-", "--format", "csv")
    assert res.returncode == 0, res.stderr
    assert run_cascal("export", linear_model, "-o", tmp_path / "t.csv").returncode == 0
    assert res.stdout == (tmp_path / "t.csv").read_text()
    assert "Compensation table written to /dev/stdout: " in res.stderr  # as correct says
    res = run_cascal("export", linear_model, "-o", "-", "--format", "h", "--name", "x1")
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith("/*") and "int x1_correct(double reading" in res.stdout
    res = run_cascal("export", linear_model, "-o", "-")
    assert res.returncode == 2 and "add --format h or --format csv" in res.stderr
    res = run_cascal("export", linear_model, "-o", tmp_path / "t.csv", "--format", "h")
    assert res.returncode == 2 and "a .csv file name, but --format h" in res.stderr
    assert "Traceback" not in res.stderr
    res = run_cascal("export", linear_model, "-o", tmp_path / "T.H")  # any case, as .csv
    assert res.returncode == 0 and "#define T_N " in (tmp_path / "T.H").read_text()
