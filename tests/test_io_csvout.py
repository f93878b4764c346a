"""CSV output: fixed-decimal text of whole columns against Python's own formatting."""

from __future__ import annotations

import warnings

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cascal.io import csvout
from cascal.io.csvout import auto_decimals, exact_decimals, format_columns, write_columns


def _float_lists(bound: float, max_size: int):
    """Lists of 1 to ``max_size`` finite floats in [-bound, bound]."""
    finite = st.floats(min_value=-bound, max_value=bound, allow_nan=False, allow_infinity=False)
    return st.lists(finite, min_size=1, max_size=max_size)


@settings(max_examples=60, deadline=None)
@given(_float_lists(1e6, 30), st.integers(min_value=0, max_value=9))
def test_format_columns_matches_python_formatting(values, decimals):
    v = np.array(values)
    text = format_columns([v, v > 0], decimals)
    assert text is not None
    for line, x in zip(text.decode().splitlines(), values, strict=True):
        cell, flag = line.split(",")
        want = f"{x:.{decimals}f}"
        if float(want) == 0.0:
            want = want.lstrip("-")
        # within one unit in the last place of Python's correctly rounded text, plus the
        # float64 spacing of x (both texts are parsed back into doubles)
        tol = 10.0**-decimals + 4 * np.spacing(abs(x))
        assert abs(float(cell) - float(want)) <= tol, (cell, want)
        assert flag == str(int(x > 0))
        assert ("." in cell) == (decimals > 0)


def test_format_columns_exact_on_random_values_and_threads(monkeypatch):
    rng = np.random.default_rng(3)
    v = rng.uniform(-2, 2, 300_000) * 10.0 ** rng.integers(-4, 3, 300_000)
    threaded = format_columns([v], 9)
    monkeypatch.setattr(csvout, "_THREADED_ROWS", 10**9)
    single = format_columns([v], 9)
    assert threaded == single
    sample = single.decode().splitlines()[:5000]
    want = [f"{x:.9f}" for x in v[:5000]]
    want = [w.lstrip("-") if float(w) == 0 else w for w in want]
    assert sample == want


@settings(max_examples=80, deadline=None)
@given(
    st.lists(st.integers(-(10**12), 10**12), min_size=1, max_size=40),
    st.integers(min_value=1, max_value=9),
)
def test_format_columns_rounds_decimal_half_way_values_as_python(digits, decimals):
    # x = (d + 1/2) 10^-decimals as the nearest double: the product by 10^decimals can round
    # onto the half-way point from either side, where Python's format rounds the exact value
    v = (np.array(digits, dtype=float) + np.copysign(0.5, digits)) / 10.0**decimals
    text = format_columns([v], decimals).decode().splitlines()
    want = [f"{x:.{decimals}f}" for x in v.tolist()]
    assert text == [w.lstrip("-") if float(w) == 0 else w for w in want]


def test_nan_is_an_empty_cell_and_huge_values_fall_back(tmp_path):
    p = tmp_path / "o.csv"
    write_columns(p, {"a": np.array([1.5, np.nan]), "b": np.array([True, False])}, decimals=2)
    assert p.read_text() == "a,b\n1.50,1\n,0\n"
    write_columns(p, {"a": np.array([1e300, -2.0])}, decimals=3)
    assert p.read_text() == "a\n1e+300\n-2.000\n"  # the decimals kept where they fit
    write_columns(p, {"a": np.array([3.6e14 + 10.25, 1.0])}, decimals=7)  # a review's case
    assert p.read_text() == "a\n360000000000010.2500000\n1.0000000\n"
    with warnings.catch_warnings():  # (a review's case: an overflow warning was printed)
        warnings.simplefilter("error")
        write_columns(p, {"a": np.array([1e307, -1e-9, -0.0, -0.002])}, decimals=3)
    assert p.read_text() == "a\n1e+307\n0.000\n0.000\n-0.002\n"  # no -0.000, as the fast path
    flags = np.ma.masked_array([True, False, True], [False, False, True])
    write_columns(p, {"a": np.array([1.5, np.nan, 2.0]), "ok": flags}, decimals=1)
    assert p.read_text() == "a,ok\n1.5,1\n,0\n2.0,\n"
    write_columns(p, {"a": np.array([1e300, 1.0, 2.0]), "ok": flags}, decimals=1)  # slow path
    assert p.read_text() == "a,ok\n1e+300,1\n1.0,0\n2.0,\n"  # (one decimal: as repr)


def test_auto_decimals():
    assert auto_decimals([np.array([0.5, 0.9])]) == 13
    assert auto_decimals([np.array([359.0])]) == 10
    assert auto_decimals([np.array([0.5])], np.array([1e-12, np.nan])) == 15
    assert auto_decimals([np.array([np.nan])]) == 12


@given(
    st.floats(-1e6, 1e6, allow_nan=False),
    st.floats(1e-6, 1e6, allow_nan=False),
    st.integers(3, 12),
)
@settings(max_examples=300, deadline=None)
def test_a_range_is_printed_rounded_inward(lo, width, digits):
    """A review's case: a report printed the range ending at 0.949381593 as ending at
    0.949382, which holds readings that ``correct`` flags as outside."""
    from cascal.text import range_text

    hi = lo + width
    a, b = (float(v) for v in range_text(lo, hi, digits).strip("[]").split(", "))
    assert lo <= a and b <= hi  # inside
    tol = 10.0 ** (1 - digits)
    assert a - lo <= tol * abs(lo) and hi - b <= tol * abs(hi)  # by one digit at most
    assert range_text(0.0980742049123, 0.9493815934) == "[0.098074205, 0.949381593]"


def test_a_range_text_keeps_exact_ends_and_order():
    """A review's cases: ends that nine digits give exactly had printed as 0.100000001 and
    0.699999999 (their doubles lie a little off the decimal), narrow ranges inverted
    ([1000.00001, 1000]) and -0.0 as -0."""
    from cascal.text import range_text

    assert range_text(0.1, 0.7) == "[0.1, 0.7]"
    assert range_text(-0.0, 360.0) == "[0, 360]"
    for lo, hi in [(1000.0000001, 1000.0000004), (123456789012.5, 123456789987.0), (1.5, 1.5)]:
        a, b = (float(v) for v in range_text(lo, hi).strip("[]").split(", "))
        assert lo <= a <= b <= hi


def test_many_cells_near_half_way_are_left_to_python(tmp_path):
    """Beyond 2^51 every scaled value is within its rounding of a half-way point: the block
    is formatted in Python, with the same text."""
    v = 7e14 + np.arange(2000) * 0.25  # 7.0e15 after one decimal: beyond 2^51
    assert format_columns([v], 1) is None
    assert format_columns([v[:10]], 1) is not None  # a few: rounded one by one
    write_columns(tmp_path / "o.csv", {"a": v}, decimals=1)
    assert (tmp_path / "o.csv").read_text().splitlines()[1:] == [f"{x:.1f}" for x in v]


def test_readings_with_one_decimal_more_stay_on_the_fast_path():
    """A review's case: 10^6 readings with one decimal more than the output keeps (a tenth
    of them half-way) were formatted cell by cell in Python, 3 times slower. The fast path
    now rounds those cells exactly itself, as Python's format does."""
    v = np.round(np.random.default_rng(3).uniform(0.0, 360.0, 20_000), 11)
    text = format_columns([v], 10)
    assert text is not None  # not left to the caller's Python formatting
    assert text.decode().splitlines() == [f"{x:.10f}" for x in v.tolist()]


@settings(max_examples=80, deadline=None)
@given(_float_lists(1e5, 20), st.integers(0, 12), st.integers(0, 6))
def test_exact_decimals_write_readings_back_exactly(values, digits, least):
    """Values of ``digits`` decimals come back from their text as the same floats, with no
    more decimals than they need (and never fewer than ``least``), where the fast path
    can write them so; else it says so."""
    v = np.round(np.array(values), digits)
    k, exact = exact_decimals(v, least)
    assert k >= least
    text = format_columns([v], k)
    fits = float(np.max(np.abs(v))) * 10.0 ** max(least, digits) < 2.0**50
    assert exact or not fits  # (16 significant digits and more: not promised)
    if exact:
        assert text is not None
        assert [float(c) for c in text.decode().splitlines()] == v.tolist()
        if k > max(least, digits):  # then digits decimals must not have been enough
            assert [float(f"{x:.{digits}f}") for x in v.tolist()] != v.tolist()


def test_exact_decimals_stop_where_the_fast_path_does():
    """A review's case: 10^6 readings of 16 and 17 significant digits (as ``repr`` writes
    them) were echoed with decimals beyond 2^51, where every cell is formatted in Python
    (4 times slower), and still not exactly; the summary said "as read". Now such values
    get the decimals that keep the fast path (below 2^46), and are not called exact."""
    v = np.array([123.45678901234567, np.nan, -1.5])  # 17 significant digits
    k, exact = exact_decimals(v, 3)
    assert (k, exact) == (11, False) and format_columns([v], k) is not None
    assert exact_decimals(np.array([1e300]), 4) == (4, False)  # beyond already: as asked
    assert exact_decimals(np.array([0.25, -3.5, 1e-3]), 1) == (3, True)
    reprs = np.random.default_rng(5).uniform(0, 1, 20_000)  # 16 and 17 digits
    k, exact = exact_decimals(reprs, 13)
    assert (k, exact) == (13, False) and format_columns([reprs], k) is not None


def test_decimals_per_column():
    a, b = np.array([0.123456789, 2.0]), np.array([1.0, -0.25])
    text = format_columns([a, b, np.array([1, 0])], [9, 2, 0])
    assert text == b"0.123456789,1.00,1\n2.000000000,-0.25,0\n"
    big = np.array([1e17, 0.5])  # beyond 2^53: Python's formatting, the same decimals
    assert format_columns([big, b], [1, 3]) is None


def test_write_columns_slow_path_keeps_decimals_per_column(tmp_path):
    big, b = np.array([1e15, 0.5]), np.array([1.0, -0.25])
    write_columns(tmp_path / "o.csv", {"a": big, "b": b}, decimals=[2, 3])
    assert (tmp_path / "o.csv").read_text() == ("a,b\n1000000000000000.00,1.000\n0.50,-0.250\n")
