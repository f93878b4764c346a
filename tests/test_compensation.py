"""Compensation tables: error against the exact correction, the grid chosen, wrap-around,
the generated C against the library's arithmetic (compiled with the machine's C compiler)."""

from __future__ import annotations

import shutil
import subprocess
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cascal.compensation import compensation_table
from cascal.errors import InputError
from cascal.io.ctable import c_header, c_identifier, table_csv
from cascal.workflow import compensation, correct, fit_model
from utils import demo_stages


def _smooth(a: float, w: float):
    return lambda x: x + a * np.sin(w * x) + 0.3 * a * np.cos(2.7 * w * x)


@settings(max_examples=40, deadline=None)
@given(st.floats(1e-4, 1e-1), st.floats(0.5, 30.0), st.integers(4, 14), st.floats(0.2, 1.0))
def test_error_within_tolerance_and_grid_is_the_coarsest(a, w, k, q):
    """Against the exact map on 20 000 random readings the table is within 1.2 times the
    tolerance (it is checked at 3 points an interval, where a smooth map's linear
    interpolation error peaks near the middle), and the grid with half the intervals is
    not within the tolerance at its own check points. The tolerance is a fraction ``q`` of
    the error bound ``max|f''| h^2 / 8`` of 2^k intervals, so at most 2^(k+1) are needed."""
    f = _smooth(a, w)
    tol = q * a * (w**2 + 0.3 * (2.7 * w) ** 2) / 8.0 / 4.0**k
    table = compensation_table(f, 0.0, 1.0, tol)
    assert table is not None and table.error <= tol
    r = np.random.default_rng(0).uniform(0.0, 1.0, 20000)
    got, outside = table(r)
    assert not outside.any()
    assert np.max(np.abs(got - f(r))) <= 1.2 * tol
    assert np.array_equal(table(table.nodes())[0], table.nodes() + table.correction)
    if table.n > 17:
        coarse = compensation_table(f, 0.0, 1.0, tol, max_nodes=(table.n - 1) // 2 + 1)
        assert coarse is None


def test_kinks_are_checked():
    """A piecewise-linear map's interpolation error is largest at its kinks; with the kinks
    as extra check points, no reading is off by more than the tolerance."""
    knots = np.sort(np.random.default_rng(1).uniform(0.0, 1.0, 40))
    offsets = np.random.default_rng(2).normal(0.0, 1e-5, 40)

    def f(x):
        return x + np.interp(x, knots, offsets)

    table = compensation_table(f, 0.0, 1.0, 1e-6, extra=knots)
    r = np.concatenate([np.random.default_rng(3).uniform(0.0, 1.0, 50000), knots])
    assert np.max(np.abs(table(r)[0] - f(r))) <= 1e-6
    assert table.checked == 4 * (table.n - 1) + knots.size


def test_errors_at_the_grid_frequency_are_seen():
    """A periodic error whose period divides the node spacing vanishes at the quarter,
    half and three-quarter points of every interval, not at the golden-ratio points."""
    f = lambda x: x + 1e-3 * np.sin(2 * np.pi * 32 * x)  # noqa: E731
    table = compensation_table(f, 0.0, 1.0, 1e-6)
    assert table.n > 257
    r = np.random.default_rng(0).uniform(0.0, 1.0, 20000)
    assert np.max(np.abs(table(r)[0] - f(r))) <= 1.2e-6


def test_range_flag_uses_the_exact_ends():
    """The last node may round past the range's end; the flag uses the end itself."""
    table = compensation_table(lambda x: x + 1e-3 * np.sin(x / 100), -1000.3, 0.1, 1e-3)
    assert table.hi == 0.1 and table.lo + table.step * (table.n - 1) > 0.1
    assert table(np.array([0.1, np.nextafter(0.1, 1.0)]))[1].tolist() == [False, True]


def test_outside_and_periodic_readings():
    f = _smooth(1e-3, 3.0)
    table = compensation_table(f, 0.0, 1.0, 1e-7)
    got, outside = table(np.array([-0.5, 0.0, 1.0, 1.5, np.nan]))
    assert outside.tolist() == [True, False, False, True, True]
    c = table.correction
    assert got[0] == -0.5 + c[0] and got[3] == 1.5 + c[-1]  # the end corrections held
    deg = compensation_table(
        lambda x: x + 0.01 * np.sin(np.deg2rad(x)), 0.0, 360.0, 1e-7, period=360.0
    )
    x = np.array([10.0, 200.0, 359.9])
    for turns in (-2, 1, 3):
        wrapped, outside = deg(x + 360.0 * turns)
        assert not outside.any()
        np.testing.assert_allclose(wrapped - 360.0 * turns, deg(x)[0], rtol=0, atol=1e-9)


def test_model_tables():
    """The bayes model's table against exact correction (default tolerance: a tenth of the
    smallest u); the lut model's needs a tolerance and meets it everywhere (its kinks are
    checked)."""
    stages = demo_stages()
    bayes, lut = (fit_model(stages, method=m, n_restarts=1) for m in ("bayes", "lut"))
    table = compensation(bayes)
    lo, hi = bayes.calibrated_range
    r = np.random.default_rng(0).uniform(lo, hi, 20000)
    exact = correct(bayes, r)
    assert table.tolerance == pytest.approx(0.1 * np.min(exact.u), rel=0.05)
    assert np.max(np.abs(table(r)[0] - exact.corrected)) <= 1.2 * table.tolerance
    np.testing.assert_allclose(table.u, correct(bayes, table.nodes()).u, rtol=1e-12)
    with pytest.raises(InputError, match="lookup-table"):
        compensation(lut)
    lt = compensation(lut, 1e-5)
    r = np.concatenate([r, lut.fitted.device.knots])
    assert np.max(np.abs(lt(r)[0] - correct(lut, r).corrected)) <= 1e-5
    with pytest.raises(InputError, match="more than"):
        compensation(lut, 1e-13)
    lines = table_csv(lt).splitlines()
    assert lines[0] == "reading,correction,corrected" and len(lines) == lt.n + 1
    assert [float(v) for v in lines[1].split(",")][1] == lt.correction[0]  # exact round trip


def test_c_identifiers():
    assert c_identifier("device_7") == "device_7"
    for bad in ("7device", "dev-ice", "", "dé", "_x", "__x"):
        with pytest.raises(InputError, match="C identifier"):
            c_identifier(bad)
    # a review: these made macro names the C library (or C++) reserves; "is", "to", "str"
    # and "mem" beginnings are reserved with external linkage only (the names are static)
    for bad in ("ENC1", "EX", "SIGX", "SIG_X", "LC_X", "FE_X", "PRId"):
        with pytest.raises(InputError, match="reserved by the C standard library"):
            c_identifier(bad)
    for bad in ("x_", "a__b"):
        with pytest.raises(InputError, match="two underscores"):
            c_identifier(bad)
    for good in ("E", "Encoder", "isaxis", "tool", "strain", "axis_x", "sig", "LC", "int16"):
        assert c_identifier(good) == good


def test_a_table_is_within_its_tolerance_between_its_check_points():
    """A review's case: a Matern 3/2 model's table, with the tolerance just above its error
    at the check points of 17 nodes, was 0.11 % over it between them (2.4985e-4 against
    2.4963e-4, 53 of 2 million readings). A table is now taken within 0.95 of the
    tolerance at its check points."""
    model = fit_model(demo_stages(), kernel="matern32", n_restarts=2)
    table = compensation(model, 2.4963e-4)
    x = np.linspace(table.lo, table.hi, 400_001)
    assert table.n == 33 and table.error <= 0.95 * 2.4963e-4
    assert np.max(np.abs(table(x)[0] - model.fitted.correct(x))) <= 2.4963e-4


def test_a_periodic_table_checks_the_data_readings_of_every_turn():
    """A review's case: device readings of -180 to 0 degrees lay outside the table's turn
    [0, 360] and were not check points; they are now, as their angles."""
    f = _smooth(1e-3, 0.05)
    extra = np.linspace(-179.0, 179.0, 180)
    table = compensation_table(f, 0.0, 360.0, 1e-4, period=360.0, extra=extra)
    assert table.checked == 4 * (table.n - 1) + 180


_MAIN = """
#include <stdio.h>
#include "table.h"
int main(void)
{
    double r, c;
    while (scanf("%lf", &r) == 1) {
        int status = NAME_correct(r, &c);
        printf("%d %.17g\\n", status, c);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler")
@pytest.mark.parametrize("periodic", [False, True, "arc"])
def test_generated_c_matches_the_library(tmp_path, periodic):
    """The header compiles warning-free as C99 and corrects every reading (inside, at the
    ends, outside, huge, infinite, NaN) to the same double as the library's table, with the
    same flag; a periodic table with an arc its device readings left out flags that arc,
    in every turn, and not its ends."""
    if periodic:
        period = 360.0
        table = compensation_table(
            lambda x: x + 0.02 * np.sin(np.deg2rad(x)),
            0.0,
            period,
            1e-7,
            period=period,
            std=None if periodic == "arc" else lambda x: 3e-5 + 1e-5 * np.cos(np.deg2rad(x)),
        )
        r = np.array([0.0, 0.1, 359.99, 360.0, 725.3, -10.0, 1e300, np.nan, np.inf, -np.inf])
        if periodic is True:  # u on the nodes: flagged from the limit on (2^37 here)
            assert table.limit == 2.0**37 and np.spacing(2.0**37) > table.u.min() >= 2.0**-16
            edge = table.limit * np.array([1.0 - 2.0**-53, 1.0, 1.0 + 2.0**-52])
            r = np.concatenate([r, edge, -edge, [360e9 + 10.0, 1.7976931348623157e308]])
            assert table(edge)[1].tolist() == [False, True, True]
        else:  # no u: only infinite and NaN readings are too large
            assert table.limit == np.inf and table(r)[1].tolist() == 7 * [False] + 3 * [True]
        if periodic == "arc":
            table = replace(table, arc=(199.8, 165.3))
            arc = np.array([199.8, 199.81, 250.0, 365.09, 365.11, 5.0, 5.2, -160.0, 919.9])
            r = np.concatenate([r, arc, arc + 720.0])
            flagged = table(arc)[1].tolist()
            assert flagged == [False, True, True, True, False, True, False, True, True]
    else:
        table = compensation_table(_smooth(1e-3, 4.0), 0.1, 0.9, 1e-8)
        ends = [0.1, 0.9, np.nan, np.inf, -np.inf, 1e300, -1e300]
        r = np.concatenate([np.random.default_rng(0).uniform(0.0, 1.0, 500), ends])
    (tmp_path / "table.h").write_text(c_header(table, "NAME", ["unit */ int x = 1; /*"]))
    (tmp_path / "main.c").write_text(_MAIN)
    exe = tmp_path / "main"
    cmd = ["cc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-o", exe, "main.c", "-lm"]
    subprocess.run(cmd, cwd=tmp_path, check=True, capture_output=True)
    text = "\n".join("nan" if np.isnan(v) else repr(float(v)) for v in r)
    out = subprocess.run([exe], input=text, capture_output=True, text=True, check=True).stdout
    status, corrected = zip(*(line.split() for line in out.splitlines()), strict=True)
    want, outside = table(r)
    assert [int(s) for s in status] == outside.astype(int).tolist()
    got = np.array([float(v) for v in corrected])
    assert np.array_equal(got, want, equal_nan=True)


_TRAPS = """
#include <fenv.h>
#include <stdio.h>
#include "table.h"
int main(void)
{
    double r, c;
    int raised = 0, flagged = 0;
    feclearexcept(FE_ALL_EXCEPT);
    while (scanf("%lf", &r) == 1) {
        flagged += NAME_correct(r, &c);
        raised |= fetestexcept(FE_INVALID | FE_OVERFLOW) != 0;
    }
    printf("%d %d\\n", raised, flagged);
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler")
@pytest.mark.parametrize("periodic", [False, True])
def test_generated_c_raises_no_invalid_operation_for_nan_or_infinity(tmp_path, periodic):
    """A review's case: a NaN reading (and an infinite one on a rotary table) raised the
    invalid-operation exception (an ordered comparison with NaN, fmod of an infinity), which
    a controller that traps it (a Cortex-M fault handler, feenableexcept) turns into a crash
    instead of status 1. The function now compares quietly and flags them all."""
    if periodic:
        table = compensation_table(
            lambda x: x + 0.02 * np.sin(np.deg2rad(x)), 0.0, 360.0, 1e-6, period=360.0
        )
    else:
        table = compensation_table(_smooth(1e-3, 4.0), 0.1, 0.9, 1e-7)
    (tmp_path / "table.h").write_text(c_header(table, "NAME", ["traps"]))
    (tmp_path / "main.c").write_text(_TRAPS)
    exe = tmp_path / "main"
    cmd = ["cc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-o", exe, "main.c", "-lm"]
    subprocess.run(cmd, cwd=tmp_path, check=True, capture_output=True)
    # a review: the largest finite readings overflowed the linear table's division
    text = "nan\n-nan\ninf\n-inf\n1.7976931348623157e308\n-1.7976931348623157e308\n0.5\n"
    out = subprocess.run([exe], input=text, capture_output=True, text=True, check=True).stdout
    assert out.split() == ["0", "4" if periodic else "6"]  # (no u: no limit on a rotary one)


@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler")
def test_the_header_refuses_to_compile_where_double_is_not_binary64(tmp_path):
    """A review's case: with a 32-bit double (TI C2000, avr-gcc before 10) the header
    compiled and lost whole corrections with status 0; it now stops the build."""
    table = compensation_table(_smooth(1e-3, 4.0), 0.1, 0.9, 1e-7)
    header = c_header(table, "NAME", ["float"])
    assert "#include <float.h>" in header
    # a linear table calls no function of the maths library (a README review: its comment
    # asked for -lm): it links without
    assert "(macros: no -lm needed)" in header and "-lm" not in header.replace("no -lm", "")
    (tmp_path / "main.c").write_text(_MAIN)
    as_float = "#define DBL_MANT_DIG 24\n#define DBL_MAX_EXP 128"
    for text, ok in ((header, True), (header.replace("#include <float.h>", as_float), False)):
        (tmp_path / "table.h").write_text(text)
        cmd = ["cc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-o", "main", "main.c"]
        res = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True)
        assert (res.returncode == 0) == ok, res.stderr
        assert ok or "needs IEEE 754 binary64 doubles" in res.stderr


@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler")
def test_the_functions_names_do_not_shadow_the_firmwares(tmp_path):
    """A review's case: a firmware's own globals ``status`` and ``t`` were shadowed by the
    function's locals, an error with -Wshadow -Werror; they carry the prefix now."""
    table = compensation_table(
        lambda x: x + 0.02 * np.sin(np.deg2rad(x)), 0.0, 360.0, 1e-6, period=360.0
    )
    table = replace(table, arc=(199.8, 165.3))
    (tmp_path / "table.h").write_text(c_header(table, "NAME", ["shadow"]))
    main = (  # (and a typedef NAME_t, as firmware names its types: a second review)
        "double t, i, a, status, reading, corrected;\n"
        "typedef struct { double x; } NAME_t;\n"
        '#include "table.h"\n'
        "int main(void) { double c = 0.0; return NAME_correct(0.5, &c); }\n"
    )
    (tmp_path / "main.c").write_text(main)
    cmd = ["cc", "-std=c99", "-Wall", "-Wextra", "-Wshadow", "-Werror", "-c", "main.c"]
    res = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def test_a_rotary_table_flags_every_reading_that_correct_flags_as_too_large():
    """A review's case: readings of 1e12 to 1e18 degrees, whose correction a double no longer
    holds, got status 0 from the C function while ``correct`` flagged them. The table now
    flags from the magnitude where a double's step exceeds the smallest u on its nodes;
    ``correct`` flags by each reading's own u, never below that: every reading it flags,
    the table flags too, and neither flags one a million turns away."""
    from cascal.demo import rotary_demo

    model = fit_model(demo_stages(rotary_demo(0)), kernel="periodic", period=360.0,
                      unit="deg", n_restarts=2)  # fmt: skip
    table = compensation(model)
    angles = np.linspace(0.0, 359.0, 37)
    both = 0
    for turns in (10**6, 10**9, 10**10, 10**11, 10**12, 10**15):
        r = np.concatenate([angles + 360.0 * turns, -angles - 360.0 * turns])
        lib, tab = correct(model, r).out_of_range, table(r)[1]
        assert not np.any(lib & ~tab), turns
        both += int(lib.all())
        if turns == 10**6:
            assert not tab.any()
    assert both >= 2 and table(np.array([1e18, -1e18, 2.0**1000]))[1].all()


@pytest.mark.skipif(shutil.which("cc") is None, reason="needs a C compiler")
def test_two_tables_of_one_name_do_not_hide_each_other(tmp_path):
    """A review's case: axes exported to ``ax1/comp.h`` and ``ax2/comp.h`` had one include
    guard, so the second header was skipped in silence and ax2 used ax1's table. The guard
    now names the content: the same header twice compiles, two different ones do not."""
    first = c_header(compensation_table(_smooth(1e-3, 4.0), 0.1, 0.9, 1e-8), "comp", ["a"])
    second = c_header(compensation_table(_smooth(2e-3, 3.0), 0.1, 0.9, 1e-8), "comp", ["b"])
    for folder, text in (("ax1", first), ("ax2", second), ("again", first)):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "comp.h").write_text(text)

    def compiles(*headers: str) -> subprocess.CompletedProcess:
        includes = "".join(f'#include "{h}/comp.h"\n' for h in headers)
        (tmp_path / "main.c").write_text(
            f"{includes}int main(void) {{ return comp_N > 0 ? 0 : 1; }}\n"
        )
        cmd = ["cc", "-std=c99", "-Wall", "-Werror", "-c", "main.c", "-o", "main.o"]
        return subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True)

    assert compiles("ax1", "again").returncode == 0  # one table, included twice
    clash = compiles("ax1", "ax2")
    assert clash.returncode != 0 and "comp_CORRECTION" in clash.stderr


def test_a_rotary_device_measured_over_part_of_the_turn_flags_the_rest():
    """A review's case: a rotary device measured from 5 to 200 degrees only was reported as
    calibrated over the full turn; readings at 250 and 300 degrees (u 110 times that inside)
    were corrected unflagged, and the C table returned 0 there. The arc the device readings
    leave out is now flagged by ``correct`` and by the table, alike; a full turn is not."""
    from dataclasses import replace as replaced

    from cascal.demo import rotary_demo
    from cascal.workflow import unmeasured_arc
    from utils import demo_stages

    case = rotary_demo(0)
    full = fit_model(demo_stages(case), kernel="periodic", period=360.0, n_restarts=1)
    assert unmeasured_arc(full) is None
    dev = case.stages[1]
    keep = (dev.x > 5.0) & (dev.x < 200.0)
    part = replaced(case, stages=(case.stages[0], replaced(dev, x=dev.x[keep], y=dev.y[keep])))
    model = fit_model(demo_stages(part), kernel="periodic", period=360.0, n_restarts=1)
    start, end = unmeasured_arc(model)
    assert start == dev.x[keep].max() and end == dev.x[keep].min()
    r = np.array([100.0, 250.0, 300.0, end - 1.0, end, start, start + 1.0, 100.0 - 720.0])
    c = correct(model, r)
    assert c.out_of_range.tolist() == [False, True, True, True, False, False, True, False]
    assert np.min(c.u[1:3]) > 10.0 * np.max(c.u[~c.out_of_range])  # deep in the arc
    table = compensation(model)
    assert table.arc == (start, (end - start) % 360.0)
    assert table(r)[1].tolist() == c.out_of_range.tolist()
    assert not correct(full, r).out_of_range.any() and compensation(full).arc is None
