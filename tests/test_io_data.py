"""CSV input: parsing, row numbers and columns in messages, repeated readings."""

from __future__ import annotations

import hashlib
import os
import re
import warnings

import numpy as np
import pytest

from cascal.errors import DataWarning, InputError
from cascal.io import data as data_mod
from cascal.io.csvout import write_columns
from cascal.io.data import read_readings, read_stage, read_table
from cascal.validation import aggregate_repeats


def _write(tmp_path, text, name="s.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_stage_in_column_order_with_provenance(tmp_path):
    p = _write(tmp_path, "tb,ref\n3,3.5\n1,1.2\n2,2.1\n")
    s = read_stage(p)
    np.testing.assert_array_equal(s.x, [1, 2, 3])
    np.testing.assert_array_equal(s.y, [1.2, 2.1, 3.5])
    np.testing.assert_array_equal(s.rows, [3, 4, 2])
    assert s.noise is None and list(s.counts) == [1, 1, 1]
    assert s.source.columns == ("tb", "ref") and s.source.rows == 3
    assert s.source.sha256 == hashlib.sha256(p.read_bytes()).hexdigest()


def test_repeats_are_averaged_and_their_spread_is_known_noise(tmp_path):
    p = _write(tmp_path, "x,y\n1,1.0\n2,2.0\n1,1.2\n3,3.0\n1,1.4\n2,2.2\n")
    s = read_stage(p)
    np.testing.assert_array_equal(s.x, [1, 2, 3])
    np.testing.assert_allclose(s.y, [1.2, 2.1, 3.0])
    # variance of the mean: sample variance (ddof 1) / count; 0 for a single reading
    np.testing.assert_allclose(s.noise, [np.var([1.0, 1.2, 1.4], ddof=1) / 3, 0.02 / 2, 0.0])
    assert list(s.counts) == [3, 2, 1] and list(s.rows) == [2, 3, 5]


def test_aggregate_repeats_against_a_loop(rng):
    x = rng.integers(0, 20, 200).astype(float)
    y = x + rng.normal(0, 0.1, x.size)
    rep = aggregate_repeats(x, y)
    for k, v in enumerate(rep.x):
        grp = y[x == v]
        assert rep.counts[k] == grp.size and rep.first[k] == np.flatnonzero(x == v)[0]
        np.testing.assert_allclose(rep.y[k], grp.mean(), rtol=1e-14)
        want = grp.var(ddof=1) / grp.size if grp.size > 1 else 0.0
        np.testing.assert_allclose(rep.noise[k], want, rtol=1e-12, atol=1e-300)


def test_repeat_means_do_not_depend_on_the_rows_order(rng):
    """A review's case: the rows of a file with repeats reordered moved a mean by an ulp
    (sums in file order), and compare took one test-bed calibration for two. Every
    permutation gives the same means and variances to the last bit; the first rows follow
    the file."""
    x = rng.integers(0, 15, 300).astype(float)
    y = x + rng.normal(0, 0.1, x.size)
    ref = aggregate_repeats(x, y)
    unequal = 0
    for _ in range(5):
        p = rng.permutation(x.size)
        rep = aggregate_repeats(x[p], y[p])
        np.testing.assert_array_equal(rep.x, ref.x)
        np.testing.assert_array_equal(rep.y, ref.y)
        np.testing.assert_array_equal(rep.noise, ref.noise)
        np.testing.assert_array_equal(rep.counts, ref.counts)
        np.testing.assert_array_equal(rep.first, [np.flatnonzero(x[p] == v)[0] for v in ref.x])
        sums = np.bincount(np.unique(x[p], return_inverse=True)[1], weights=y[p])
        unequal += int(np.any(sums / rep.counts != ref.y))  # (file-order sums would differ)
    assert unequal > 0


def test_a_file_cut_short_in_its_last_number_is_warned_of(tmp_path):
    """A fuzz review: a file cut within its last number (``0.486`` of
    ``0.4861985463790``) was read with no word. Ending without a line break, with fewer
    decimals than every row before (3 or more), it is warned of; a file that ends with one,
    or whose numbers are written shortest (Python's repr), is not."""
    rows = [(0.1 * k + 1e-7 * k * k, 0.1 * k) for k in range(1, 9)]
    body = "".join(f"{a:.13f},{b:.13f}\n" for a, b in rows)
    cut = _write(tmp_path, "tb,ref\n" + body + "0.9000000000000,0.9", "cut.csv")
    with pytest.warns(DataWarning, match=r"cut.csv: the file ends without a line break, and the "
                      r"last row's ref '0.9' has 1 decimal where the rows before have 13 or "
                      r"more: the file cut short in that number\? \(row 10\)"):  # fmt: skip
        read_stage(cut)
    whole = _write(tmp_path, "tb,ref\n" + body + "0.9000000000000,0.9\n", "whole.csv")
    # (set points written shortest: 0.1, 0.2, 0.30000000000000004, ...; the last, 0.9)
    short = "".join(f"{b!r},{a!r}\n" for a, b in rows) + "0.9,0.9000081"
    shortest = _write(tmp_path, "tb,ref\n" + short, "repr.csv")
    # (a second review: fixed significant digits, 100 after 99.4737, and trailing zeros
    # dropped, 0.1234 of 0.123400, had been warned of)
    points = np.linspace(0.0, 100.0, 20)
    sig = "".join(f"{v:g},{v + 0.1234567:g}\n" for v in points[:-1]) + "99.9,100"
    fixed = _write(tmp_path, "tb,ref\n" + sig, "fixed.csv")
    zeros = "".join(f"{a:.6f},{b:.6f}\n" for a, b in rows) + "0.9000001,0.9123"
    dropped = _write(tmp_path, "tb,ref\n" + zeros, "dropped.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for quiet in (whole, shortest, fixed, dropped):
            read_stage(quiet)


def test_columns_by_name_semicolons_bom_crlf_and_blank_lines(tmp_path):
    p = tmp_path / "s.csv"
    p.write_bytes("\ufefftime;ref;tb\r\n0;1.1;1\r\n\r\n1;2.2;2\r\n2;3.1;3\r\n".encode())
    s = read_stage(p, x_column="tb", y_column="ref")
    np.testing.assert_allclose(s.y, [1.1, 2.2, 3.1])
    assert list(s.rows) == [2, 4, 5]
    with pytest.raises(InputError, match="extra columns"):
        read_stage(p)


def test_a_quoted_empty_reading_is_named_where_blank_lines_are_skipped(tmp_path):
    blank = _write(tmp_path, "pos\n1.0\n\n  \n3.0\n")
    assert list(read_readings(blank).rows) == [2, 5]
    quoted = tmp_path / "q.csv"
    quoted.write_text('pos\n1.0\n\n""\n3.0\n')
    with pytest.raises(InputError, match=r"q\.csv, row 4, column 'pos': .*empty cell"):
        read_readings(quoted)
    rows = tmp_path / "rows.csv"  # two columns: an empty row stays a blank line
    rows.write_text('a,b\n1.0,2\n"",""\n,\n3.0,4\n')
    assert list(read_table(rows, (None, None)).rows) == [2, 5]


def test_only_x_column_named_takes_the_other(tmp_path):
    p = _write(tmp_path, "ref,tb\n1.1,1\n2.2,2\n3.1,3\n")
    s = read_stage(p, x_column="tb")
    np.testing.assert_allclose(s.y, [1.1, 2.2, 3.1])
    assert s.source.columns == ("tb", "ref")


def test_periodic_stage_is_unwrapped_to_the_reading(tmp_path):
    p = _write(tmp_path, "enc,ref\n0.5,0.6\n180,180.1\n359.9,0.05\n")
    s = read_stage(p, period=360.0)
    np.testing.assert_allclose(s.y, [0.6, 180.1, 360.05])


@pytest.mark.parametrize(
    ("text", "row", "words"),
    [
        ("a,b\n1,1\n2,2\n3,x\n", 4, "expected a number, got 'x'"),
        ("a,b\n1,1\n2,2\n3\n", 4, "missing cells"),
        ("a,b\n1,1\n2,1\n3,3\n", 3, "not above"),
        ("a,b\n1,1\n2,2\n", 3, "at least 3 data rows"),
        ("a,b\n1,1\n2,2\n3,1e999\n", 4, "finite"),
        # Python's float() reads these; a CSV cell with them is mistyped
        ("a,b\n1,1\n2,2\n3,3_5\n", 4, "expected a number, got '3_5'"),
        ("a,b\n1,1\n2,2\n\uff13,3\n", 4, "expected a number, got '\uff13'"),
        ("a,b\n1,1\n\u0662.\u0661,2\n3,3\n", 3, "expected a number"),
    ],
)
def test_errors_name_file_and_row(tmp_path, text, row, words):
    p = _write(tmp_path, text)
    with pytest.raises(InputError, match=words) as exc:
        read_stage(p)
    assert exc.value.row == row and exc.value.file == str(p)
    assert str(exc.value).startswith(f"{p}, row {row}")


def test_fast_path_and_exact_path_agree(tmp_path, monkeypatch):
    v = np.random.default_rng(0).normal(size=6000)
    p = tmp_path / "r.csv"
    write_columns(p, {"reading": v}, decimals=15)
    fast = read_readings(p)
    monkeypatch.setattr(data_mod, "_FAST_LINES", 10**9)
    slow = read_readings(p)
    np.testing.assert_array_equal(fast.columns[0], slow.columns[0])
    np.testing.assert_array_equal(fast.rows, slow.rows)
    np.testing.assert_allclose(fast.columns[0], v, rtol=0, atol=1e-15)


def test_fast_path_errors_are_located_exactly(tmp_path):
    lines = ["reading", *[f"{i / 7:.6f}" for i in range(6000)]]
    lines[4321] = "1.5e"
    p = _write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"'1\.5e'") as exc:
        read_readings(p)
    assert exc.value.row == 4322
    lines[4321] = "nan"
    p = _write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(InputError, match="finite") as exc:
        read_readings(p)
    assert exc.value.row == 4322


def test_many_readings_from_a_pipe_take_the_fast_path_quietly(tmp_path):
    """A review's case: over 5000 readings from a pipe (``<(cat big.csv)``) printed NumPy's
    "input contained no data" warning: the fast path opened the path again, which a pipe
    cannot give twice. It now parses the bytes read once."""
    import threading

    v = np.round(np.random.default_rng(1).normal(size=6000), 6)
    text = "reading\n" + "\n".join(f"{x:.6f}" for x in v) + "\n"
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    writer = threading.Thread(target=lambda: fifo.write_text(text))
    writer.start()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = read_readings(fifo)
    writer.join()
    np.testing.assert_array_equal(got.columns[0], v)


def test_a_long_bad_cell_is_shortened_in_the_message(tmp_path):
    p = _write(tmp_path, "reading\n0.5\n1" + "0" * 5000 + "x\n")
    with pytest.raises(InputError, match=r"got '10+'\.\.\.'0+x' \(5002 characters\)") as exc:
        read_readings(p)
    assert len(str(exc.value)) < 200


def test_read_table_reports_unreadable_file(tmp_path):
    with pytest.raises(InputError, match="cannot read"):
        read_table(tmp_path / "missing.csv", (None,))


def test_cr_line_ends_are_read(tmp_path):
    """Files with CR alone as line end (old Mac) read like LF and CRLF files."""
    rows = "a,b\n1,1.1\n2,2.05\n3,3.2\n"
    tables = []
    for name, end in (("lf", "\n"), ("crlf", "\r\n"), ("cr", "\r")):
        path = tmp_path / f"{name}.csv"
        path.write_bytes(rows.replace("\n", end).encode())
        tables.append(read_table(path, (None, None)))
    for t in tables[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(t.columns, tables[0].columns, strict=True))
        assert np.array_equal(t.rows, tables[0].rows)


def test_a_mean_of_repeats_is_named_as_such(tmp_path):
    """Where a value in the message is the mean of repeated readings, the message says so
    (the file holds no cell with that value)."""
    path = tmp_path / "rep.csv"
    path.write_text("a,b\n1,1\n2,2.6\n2,2.4\n3,2.45\n4,4\n")
    with pytest.raises(
        InputError, match=r"b 2\.5 at a 2\.0 \(the mean of its 2 readings, rows 3 a"
    ):
        read_stage(path)


@pytest.mark.parametrize(
    ("text", "names"),
    [
        ("pos (mm; raw),ref (mm; raw)\n1,1.1\n2,2.05\n3,3.2\n", ["pos (mm; raw)", "ref (mm; raw)"]),
        ("pos, mm\tref, mm\n1\t1.1\n2\t2.05\n3\t3.2\n", ["pos, mm", "ref, mm"]),
        ("a;b\n1;1.1\n2;2.05\n3;3.2\n", ["a", "b"]),
        ("a,b\n\n1,1.1\n2,2.05\n3,3.2\n", ["a", "b"]),
    ],
    ids=["semicolons_in_names", "commas_in_tab_names", "semicolons", "blank_line_first"],
)
def test_separator_fits_the_data_rows(tmp_path, text, names):
    """The separator is the one that splits the first data row like the header, so column
    names may contain the other separators."""
    path = tmp_path / "s.csv"
    path.write_text(text)
    table = read_table(path, (None, None))
    assert list(table.source.columns) == names
    assert np.array_equal(table.columns[1], [1.1, 2.05, 3.2])


def test_values_too_large_are_named_when_a_bound_is_given(tmp_path):
    p = tmp_path / "big.csv"
    p.write_text("a,b\n1,2\n3,-1e200\n")
    assert read_table(p, (None, None)).columns[1][1] == -1e200  # no bound: accepted
    with pytest.raises(InputError, match=r"big.csv, row 3, column 'b': -1e\+200 is too large"):
        read_table(p, (None, None), max_abs=1e150)
    assert read_table(p, ("a",), max_abs=1e150).columns[0][1] == 3.0  # b not wanted


_FAST = data_mod._fast


def _stage_lines(n: int, seed: int = 0) -> list[str]:
    """A stage file's lines (header first): n readings, every third position read twice."""
    rng = np.random.default_rng(seed)
    x = np.repeat(np.linspace(0.0, 1.0, n), np.where(np.arange(n) % 3 == 0, 2, 1))
    y = x + 0.01 * np.sin(4 * x) + rng.normal(0.0, 1e-5, x.size)
    return ["reading,reference", *[f"{float(a)!r},{float(b)!r}" for a, b in zip(x, y, strict=True)]]


@pytest.mark.parametrize("n", [40, 6000])  # the exact path, and NumPy's fast one
def test_excluded_rows_read_as_the_file_without_them(tmp_path, n, monkeypatch):
    fast = []
    monkeypatch.setattr(data_mod, "_fast", lambda *a: fast.append(1) or _FAST(*a))
    lines = _stage_lines(n)
    drop = {2, 3, 17, len(lines)}  # both readings of a repeated position, one, the last
    full = _write(tmp_path, "\n".join(lines) + "\n", "full.csv")
    cut = [line for r, line in enumerate(lines, start=1) if r not in drop]
    without = _write(tmp_path, "\n".join(cut) + "\n", "cut.csv")
    a, b = read_stage(full, exclude=drop), read_stage(without)
    for name in ("x", "y", "noise", "counts", "raw_x", "raw_y"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    kept = [r for r in range(2, len(lines) + 1) if r not in drop]
    np.testing.assert_array_equal(a.raw_rows, kept)  # the file's own row numbers
    assert a.source.excluded == tuple(sorted(drop)) and a.source.rows == len(kept)
    assert (
        b.source.excluded == () and a.source.sha256 == hashlib.sha256(full.read_bytes()).hexdigest()
    )
    assert len(fast) == (2 if n > data_mod._FAST_LINES else 0)
    if fast:  # a row past the end, refused on the fast path too
        with pytest.raises(InputError, match=f"past the last, row {len(lines)}"):
            read_stage(full, exclude={len(lines) + 1})


def test_an_excluded_row_is_not_read(tmp_path):
    lines = _stage_lines(20)
    lines[5] = "0.3,oops"  # file row 6
    p = _write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(InputError, match="'oops'"):
        read_stage(p)
    assert read_stage(p, exclude={6}).source.excluded == (6,)


@pytest.mark.parametrize(
    ("row", "words"),
    [(1, "the header"), (0, "rows count from 1"), (4, "blank"), (99, "past the last, row 22")],
)
def test_excluding_a_row_that_holds_no_data_is_refused(tmp_path, row, words):
    lines = _stage_lines(15)
    lines.insert(3, "")  # file row 4 is blank
    p = _write(tmp_path, "\n".join(lines) + "\n")
    with pytest.raises(InputError, match=f"row {row} is to be excluded.*{words}") as exc:
        read_stage(p, exclude={row, 5})
    assert exc.value.row == row


@pytest.mark.parametrize(("eol", "bom"), [(b"\n", b""), (b"\r\n", b"\xef\xbb\xbf"), (b"\r", b"")])
def test_windows_1252_text_is_named_with_its_row(tmp_path, eol, bom):
    """A review's case: a non-breaking space after a number in row 4 (Windows-1252, as a
    spreadsheet saves plain CSV) was named by its byte offset alone."""
    p = tmp_path / "cp1252.csv"
    rows = ["a,b", "1,1", "2,2", "3\u00a0,3", "4,4"]
    p.write_bytes(bom + eol.join(r.encode("cp1252") for r in rows) + eol)
    with pytest.raises(
        InputError, match=r"not UTF-8 text \(byte 0xa0, .*save it as CSV UTF-8"
    ) as exc:
        read_stage(p)
    assert exc.value.row == 4 and "row 4" in str(exc.value)


def test_utf16_files_are_named_as_such(tmp_path):
    p = tmp_path / "unicode.txt"
    p.write_bytes("a,b\n1,1\n2,2\n3,3\n".encode("utf-16"))  # with its byte-order mark
    with pytest.raises(InputError, match="UTF-16 text, not UTF-8: save it as CSV"):
        read_stage(p)


@pytest.mark.parametrize(
    ("text", "row", "rows"),
    [  # a review's cases: the row named held a correct value
        (
            "a,b\n1,1\n2,2\n2,2.1\n2,-5\n3,3\n4,4\n",
            5,
            "the mean of its 3 readings, rows 3, 4 and 5",
        ),
        ("a,b\n1,1\n2,2\n3,9\n4,4\n5,5\n", 4, "b 4.0 at a 4.0 (row 5) is not above b 9.0"),
        ("a,b\n1,1\n2,2\n3,-1\n4,4\n5,5\n", 4, "b -1.0 at a 3.0 (row 4) is not above b 2.0"),
        ("a,b\n1,1\n2,2\n3,3\n4,9\n5,5\n", 5, "b 5.0 at a 5.0 (row 6) is not above b 9.0"),
        ("a,b\n1,1\n2,2\n3,3\n4,4\n5,0\n", 6, "b 0.0 at a 5.0 (row 6) is not above b 4.0"),
    ],
)
def test_a_point_out_of_step_is_named_by_its_rows(tmp_path, text, row, rows):
    """A mean of repeats names all its rows, and the error's row is the reading out of
    step: a spike (too high) before the step back, a dip (too low) after it, and within a
    mean its reading furthest that way."""
    p = _write(tmp_path, text)
    with pytest.raises(InputError, match=re.escape(rows)) as exc:
        read_stage(p)
    assert exc.value.row == row


def test_a_quote_never_closed_is_named_where_it_opens(tmp_path):
    """A review's case: a stray quote at the start of row 5 took the rest of the file into
    one cell, and the message named the last row as "missing cells". A quoted cell that
    spans lines and closes is still read."""
    rows = "".join(f"{k},{k}.5\n" for k in range(1, 30))
    p = _write(tmp_path, "a,b\n" + rows.replace("4,4.5", '"4,4.5'))
    with pytest.raises(InputError, match="a quoted cell opens in this row and is never") as exc:
        read_stage(p)
    assert exc.value.row == 5
    closed_later = rows.replace("4,4.5", '"4,4.5').replace("9,9.5", '9,"9.5"')
    with pytest.raises(InputError, match="runs on to row 10, which leaves 1 cell for") as exc:
        read_stage(_write(tmp_path, "a,b\n" + closed_later))
    assert exc.value.row == 5
    p = _write(tmp_path, 'a,b\n1,1\n"2\n",2\n3,3\n4,4\n')
    with pytest.warns(DataWarning, match=r"s\.csv, rows 3 to 4: read as one record"):
        assert read_stage(p).x.tolist() == [1.0, 2.0, 3.0, 4.0]
    with pytest.warns(DataWarning):
        assert read_stage(p).rows.tolist() == [2, 3, 5, 6]  # a record named by its first line
    p = _write(tmp_path, 'a,b,note\n1,1,x\n2,0,"line1\nline2\nline3"\n3,3,y\n4,4,z\n')
    with pytest.raises(InputError) as exc, pytest.warns(DataWarning):
        read_stage(p, x_column="a", y_column="b")
    assert exc.value.row == 3  # (a review's case: it was named row 5, its last line)
    with warnings.catch_warnings():  # the record left out: no warning of it (a review)
        warnings.simplefilter("error")
        assert read_stage(p, x_column="a", y_column="b", exclude=[3]).x.tolist() == [1, 3, 4]


def test_a_stray_quote_that_swallows_rows_of_a_note_column_is_warned_of(tmp_path):
    """A review's case: a quote opened in a text column that is not read and closed rows
    later leaves the right number of cells, so the rows between vanish into one note. They
    are read as CSV says, with a warning naming the rows; a file without such a record
    gives none."""
    rows = [f"{k / 10},{k / 10 + 0.001 * (k % 3)},ok" for k in range(12)]
    rows[2] = rows[2].replace(",ok", ',"stray')
    rows[5] = rows[5].replace(",ok", ',x"')
    rows[8] = rows[8].replace(",ok", ',"a\nb"')
    p = _write(tmp_path, "x,y,note\n" + "\n".join(rows) + "\n")
    with pytest.warns(DataWarning, match=r"rows 4 to 7: .* \(and 1 more record like it\)"):
        s = read_stage(p, x_column="x", y_column="y")
    assert s.rows.tolist() == [2, 3, 4, 8, 9, 10, 12, 13, 14]
    clean = _write(tmp_path, "x,y,note\n" + "\n".join(r.replace('"', "") for r in rows[:8]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_stage(clean, x_column="x", y_column="y").rows.size == 8


def test_columns_in_different_units_are_warned_of(tmp_path):
    """A user review's case: a reference column in mm beside test-bed readings in m was
    fitted silently (corrections of 575 'm' on a 1 m axis). Spans 1000 times apart are
    named; a scale error of a few per cent and an offset between the zeros are not."""
    x = np.linspace(0.0, 1.0, 12)
    mm = _write(tmp_path, "testbed,reference\n" + "".join(f"{a},{a * 1000}\n" for a in x))
    with pytest.warns(DataWarning, match=r"'reference' span 1000 times .* \(mm and m\)"):
        read_stage(mm)
    fine = x * 1.03 + 10.0
    text = "".join(f"{a},{b}\n" for a, b in zip(x, fine, strict=True))
    ok = _write(tmp_path, "testbed,reference\n" + text)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_stage(ok)


def test_a_step_back_names_both_columns_as_possible_culprits(tmp_path):
    """A user review's case: a device reading mistyped (divided by 10) moved its point,
    and the message blamed the other column. Either may be wrong: both are named."""
    rows = "".join(f"{k / 10},{k / 10 + 0.01}\n" for k in range(1, 10))
    p = _write(tmp_path, "device,testbed\n" + rows.replace("0.6,0.61", "0.06,0.61"))
    with pytest.raises(InputError, match=r"mistyped cell \(of testbed or of device\)") as exc:
        read_stage(p)
    assert exc.value.column is None


@pytest.mark.parametrize(
    "text, hint",
    [
        ("testbed;reference\n-0,0451;-0,0000436\n0,5;0,5001\n0,9;0,9\n", "a decimal comma"),
        ("reading\n0,5\n0,6\n", "decimal commas? Write numbers with a decimal point"),
        ("testbed,reference\nm,m\n0.1,0.1\n0.5,0.5\n0.9,0.9\n", "a row of units under the"),
        # a review's case: a German Excel file's units row was called a column of text
        (
            "testbed;reference\nmm;mm\n0,1;0,1\n0,5;0,5\n0,9;0,9\n",
            "Delete it; and the rows below write decimal commas: use a point",
        ),
        ("testbed,reference\n\nm,m\n0.1,0.1\n0.5,0.5\n0.9,0.9\n", "row 3: expected numbers"),
        ("testbed,reference\n0.1,0.1O01\n0.5,0.5\n0.9,0.9\n", "got '0.1O01'\n"),
        # a review's case: a column of text taken as the readings was called a units row
        ("reading\nx\ny\nz\n", "column 'reading' holds no readings (the wrong column?)"),
        ("testbed,reference\nA1,B1\nA2,B2\nA3,\n", "columns 'testbed', 'reference' hold no"),
        # a user review's cases: lines above the header, from Excel and from instruments
        ("sep=;\ntestbed;reference\n0,1;0,1\n0,5;0,5\n", "row 1: 'sep=;' is a spreadsheet's"),
        ("# run 7\ntestbed,reference\n0.1,0.1\n0.5,0.5\n", "the header looks like row 2"),
        (
            "LabVIEW Measurement\t\nWriter_Version\t2\n***End_of_Header***\t\n\n"
            "X_Value\ttestbed\treference\n0\t0.1\t0.1\n1\t0.5\t0.5\n2\t0.9\t0.9\n",
            "header looks like row 5 ('X_Value\\ttestbed\\treference'): delete the lines above",
        ),
        # a documentation review's cases: one-column files and blocks of two-cell lines
        ("# instrument XYZ\nreading\n0.1\n0.2\n", "header looks like row 2 ('reading')"),
        (
            "Instrument,XL80\nDate,2024-01-01\nOperator,Smith\ntestbed,reference\n0.1,0.1\n",
            "'Instrument,XL80' is not the header: the header looks like row 4",
        ),
        ("Instrument XL80\nreading\n0.1\n0.2\n", "if row 2 is the header, delete row 1"),
        ("reading\n[mm]\n0.1\n0.2\n", "row 2: expected numbers, got '[mm]': a row of units"),
        ("# run 7\ntestbed,reference\nmm,mm\n0.1,0.1\n", "row 2 ('testbed,reference'): de"),
        ("reading\n0.1_16\n0.2\n", "column 'reading': expected a number, got '0.1_16'\n"),
        # a README review's cases: an instrument's word beside a number in the first row
        # was taken for a second header row (row 1 named, "delete row 2" advised)
        ("testbed,reference\n0.098,ERR\n0.5,0.5\n", "row 2, column 'reference': expected a"),
        ("testbed,reference\nn/a,0.1\n0.5,0.5\n", "row 2, column 'testbed': expected a num"),
        # a diff review's cases: a header with a number for a column's name under a comment,
        # and a comment above a header above such a first data row, are still named
        ("# laser run 7\ntestbed,1\n0.1,0.1\n0.5,0.5\n", "the header looks like row 2"),
        ("Calibration 2024-05-01\ntestbed,2024\n0.1,0.1\n", "the header looks like row 2"),
        ("# run 7\ntestbed,reference\n0.098,ERR\n0.5,0.5\n", "the header looks like row 2"),
    ],
    ids=[
        "decimal_comma",
        "decimal_comma_splits_cells",
        "units_row",
        "units_row_decimal_commas",
        "units_row_3",
        "typo",
        "text_column",
        "text_column_of_two",
        "excel_separator_line",
        "comment_line",
        "instrument_header_block",
        "comment_above_one_column",
        "block_of_two_cell_lines",
        "line_or_units_above_one_column",
        "units_row_of_one_column",
        "comment_then_units_row",
        "typo_in_first_row_of_one_column",
        "word_beside_a_number_in_the_first_row",
        "word_then_a_number_in_the_first_row",
        "comment_above_a_header_with_a_number",
        "title_above_a_header_with_a_year",
        "comment_above_a_header_above_a_word_in_the_first_row",
    ],
)
def test_spreadsheet_habits_get_a_hint(tmp_path, text, hint):
    """A user review's cases: the message named the cell but not the likely cause."""
    p = _write(tmp_path, text)
    reader = read_stage if "testbed" in text else read_readings
    with pytest.raises(InputError) as exc:
        reader(p)
    assert hint.rstrip("\n") in str(exc.value)
    if hint.endswith("\n"):  # a typo in the first row is not called a units row
        assert str(exc.value).endswith(hint.rstrip("\n"))


def test_unnamed_empty_columns_are_ignored_and_a_value_in_one_is_named(tmp_path):
    """A user review's case: a spreadsheet's trailing empty columns (``a,b,,``) made the
    file one of four columns. Columns the header leaves unnamed are ignored while empty."""
    rows = "".join(f"{k / 10},{k / 10 + 0.001},,\n" for k in range(1, 6))
    s = read_stage(_write(tmp_path, "testbed,reference,,\n" + rows))
    assert s.x.tolist() == [0.1, 0.2, 0.3, 0.4, 0.5]
    assert s.source.columns == ("testbed", "reference")
    bad = rows.replace("0.3,0.301,,", "0.3,0.301,,7")
    with pytest.raises(InputError, match=r"row 4: '7' in column 4, which the header row leaves"):
        read_stage(_write(tmp_path, "testbed,reference,,\n" + bad))
    named = read_stage(
        _write(tmp_path, "testbed,reference,,\n" + bad), x_column="testbed", y_column="reference"
    )
    assert named.x.tolist() == s.x.tolist()  # both by name: the others are not read


def test_unnamed_columns_in_every_place(tmp_path):
    """A review's cases: a header ``testbed,`` over two columns of numbers is read by place
    as before; a pandas index column (``,testbed,reference``) is named with the hint to
    pick columns by name; a value in an unnamed column is found in a large file too (the
    fast parser would have read it); trailing unnamed cells may be left out; a lone
    quoted empty reading under ``reading,`` is named."""
    rows = "".join(f"{k / 100},{k / 100 + 0.0001}\n" for k in range(1, 20))
    assert read_stage(_write(tmp_path, "testbed,\n" + rows)).x.size == 19
    index = "".join(f"{i},{k / 100},{k / 100 + 0.0001}\n" for i, k in enumerate(range(1, 20)))
    with pytest.raises(InputError, match=r"'0' in column 1, .*choose two by name with --x-col"):
        read_stage(_write(tmp_path, ",testbed,reference\n" + index))
    big = "".join(f"{k / 10000},,{k / 10000 + 0.00001}\n" for k in range(1, 6001))
    big = big.replace("0.3,,0.30001", "0.3,7,0.30001")
    assert big.count("\n") > data_mod._FAST_LINES
    with pytest.raises(InputError, match=r"row 3001: '7' in column 2"):
        read_stage(_write(tmp_path, "testbed,,reference\n" + big))
    assert read_stage(_write(tmp_path, "testbed,reference,,\n" + rows)).x.size == 19
    with pytest.raises(InputError, match="row 3, column 'reading': expected a number, got an"):
        read_readings(_write(tmp_path, 'reading,\n0.5,\n""\n0.7,\n'))


def test_the_unit_check_ignores_one_mistyped_cell_and_sees_rotary_columns(tmp_path):
    """A review's cases: one reading typed 10.0001 for 1.0001 made the span ten times
    larger and the unit warning fired; degrees against radians in a rotary stage went
    unwarned, the check running after the unwrapping by whole turns."""
    x = np.linspace(0.0, 1.0, 40)
    y = x + 1e-4
    y[-1] += 9.0  # 10.0001: a mistyped cell, for the screening to name
    typo = _write(
        tmp_path, "testbed,reference\n" + "".join(f"{a},{b}\n" for a, b in zip(x, y, strict=True))
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_stage(typo)
    deg = np.linspace(5.0, 355.0, 30)
    rad = _write(tmp_path, "encoder,table\n" + "".join(f"{d},{np.radians(d)}\n" for d in deg))
    with pytest.warns(DataWarning, match="different units"):
        read_stage(rad, period=360.0)


@pytest.mark.parametrize(
    ("scale", "words"),
    [(1e76, "is too large (|value| < 1e+75 expected)"), (1e-200, "span only")],
)
def test_a_stage_at_a_scale_float64_cannot_fit_is_refused_by_row(tmp_path, scale, words):
    """A fuzzing review's cases: a stage file of values near 1e308 fitted (method lut),
    then broke info and report; scaled by 1e100 or 1e-200 it failed inside the fit with
    messages naming no file or row. Now the file and row are named."""
    rows = "".join(f"{k / 10 * scale!r},{(k / 10 + 0.001) * scale!r}\n" for k in range(1, 8))
    p = _write(tmp_path, "testbed,reference\n" + rows)
    with pytest.raises(InputError, match=r"s\.csv, row \d+.*" + re.escape(words)):
        read_stage(p)
    ok = "".join(f"{k / 10 * 1e70!r},{(k / 10 + 0.001) * 1e70!r}\n" for k in range(1, 8))
    assert read_stage(_write(tmp_path, "testbed,reference\n" + ok, "ok.csv")).x.size == 7


def test_utf16_without_a_byte_order_mark_is_named(tmp_path):
    """A fuzzing review's case: UTF-16 text without its byte-order mark was called a row of
    units under the header."""
    p = tmp_path / "u.csv"
    p.write_bytes("testbed,reference\n0.1,0.1\n0.5,0.5\n0.9,0.9\n".encode("utf-16-le"))
    with pytest.raises(InputError, match=r"u\.csv: UTF-16 text, not UTF-8"):
        read_stage(p)
    p.write_bytes(bytes(range(256)) * 16)  # zeros at every 256th byte: binary, not UTF-16
    with pytest.raises(InputError) as exc:
        read_stage(p)
    assert "UTF-16" not in str(exc.value)


def test_repeats_read_with_jitter_are_named_as_such(tmp_path):
    """A user review's case: three readings per set point, the calibrated sensor's varying
    by 2 µm of jitter, were refused as not one-to-one with the advice to measure at fewer,
    wider-spaced positions (they were 10 mm apart). The message names the near-equal
    readings as likely repeats and says how repeats are averaged."""
    rng = np.random.default_rng(0)
    sp = np.repeat(np.arange(20.0, 281.0, 10.0), 3)
    x = sp + 2e-3 * rng.standard_normal(sp.size)
    y = sp + 0.3 * np.sin(sp / 50) + 5e-4 * rng.standard_normal(sp.size)
    rows = "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(x, y, strict=True))
    with pytest.raises(InputError) as exc:
        read_stage(_write(tmp_path, "stage,laser\n" + rows))
    text = str(exc.value)
    assert "under a twentieth of the usual spacing (10): repeated readings of one position?" in text
    assert "write each repeat's set point in stage, or average them first" in text
    assert "wider-spaced" not in text
