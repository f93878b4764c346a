"""The report's words: a rotary axis's unreachable stretch is given on one turn."""

from __future__ import annotations

import html
import re

import numpy as np
import pytest

from cascal.demo import rotary_demo
from cascal.report import build_report
from cascal.workflow import fit_model
from utils import demo_stages


def test_a_rotary_stretch_across_zero_is_written_on_one_turn():
    """The rotary demo's reference cannot reach 335 to 25 degrees: the report says so
    (not [335, 385]); a linear stretch keeps its interval."""
    ref, dev = demo_stages(rotary_demo(0))
    model = fit_model([ref, dev], kernel="periodic", period=360.0, unit="deg", n_restarts=1)
    html = build_report(model, source="rotary.json")
    assert "could not measure (deg): 335 to 25 (across 0)." in html
    assert "385" not in html.split("could not measure (deg):")[1].split("</p>")[0]
    linear = fit_model(demo_stages(), n_restarts=1)  # (0.34395260854 to 0.52824241264:
    # rounded outward since a report review found such stretches printed shrunk)
    page = build_report(linear, source="l")
    assert "could not measure (m): [0.343952, 0.528243]." in page
    # the reach of the plan, rounded inward as ranges are (it had ended past the last point)
    from cascal.text import range_text
    from cascal.workflow import plan_measurements

    reach = plan_measurements(linear, 5).reach
    assert ", ".join(range_text(a, b) for a, b in reach) in page


def test_uncertainties_are_also_given_in_the_figures_unit():
    """The report's text gives u in the file's unit and in the unit its figures use (µm
    for metres, arcsec for small angles); the plan's table is in the figure's unit."""
    import re

    import numpy as np

    from cascal.report import correction_curve

    model = fit_model(demo_stages(), n_restarts=1)
    html = build_report(model, source="linear.json")
    u = float(np.max(correction_curve(model).u))
    assert f"Largest u over the calibrated range: {u:.6g} m ({u * 1e6:.3g} µm)." in html
    assert "RMS u after [µm]" in html and "largest u after [µm]" in html
    sd = re.search(r"\(standard deviation ([-+.e\d]+) m \(([.\d]+) µm\)\)", html)
    assert "each as precise as the average existing point, repeated readings" in html
    assert sd and float(sd[2]) == float(f"{float(sd[1]) * 1e6:.3g}")
    ref, dev = demo_stages(rotary_demo(0))
    rotary = fit_model([ref, dev], kernel="periodic", period=360.0, unit="deg", n_restarts=1)
    text = build_report(rotary, source="rotary.json")
    assert re.search(r"Largest u over the calibrated range: [-+.e\d]+ deg \([.\d]+ arcsec\)", text)


def test_the_report_repeats_what_fit_warned_of():
    """A review's cases: the report of a model from three reference points, or of a
    homoscedastic cascade, read as a clean bill of health while ``cascal fit`` had warned
    that u is likely too small. Its Cautions list the fit's findings (the search bounds
    restored on loading) and the homoscedastic caveat; a clean model has none."""
    from cascal.io.data import StageData
    from cascal.text import HOMOSCEDASTIC_U
    from cascal.workflow import fit_findings

    ref, dev = demo_stages()
    keep = np.array([0, ref.x.size // 3, ref.x.size - 1])
    three = StageData(ref.x[keep], ref.y[keep], None, ref.counts[keep], ref.rows[keep], ref.source)
    model = fit_model([three, dev], n_restarts=2)
    (finding,) = fit_findings(model)
    page = build_report(model)
    assert "Cautions" in page and "3 points cannot tell the readings" in page
    homo = build_report(fit_model([ref, dev], method="homoscedastic", n_restarts=2))
    assert "Cautions" in homo and html.escape(HOMOSCEDASTIC_U) in homo
    assert "(about 95 %)" not in homo and "(nominally 95 %; this method" in homo  # (a review)
    assert "(about 95 %)" in page
    assert "Cautions" not in build_report(fit_model([ref, dev], n_restarts=2))
    assert finding.stage == 0 and finding.points == 3


def test_the_correction_figure_marks_the_arc_a_rotary_device_left_out():
    """A user review's case: the report's correction figure drew +-U straight through the
    part of the turn the device readings left out, unmarked, while the text above named it
    as flagged. It is shaded now, in every turn drawn, and named in the legend."""

    from cascal.report import correction_curve, correction_figure
    from cascal.workflow import unmeasured_arc

    model = _partial_turn_model()
    curve = correction_curve(model)
    assert curve.arc == unmeasured_arc(model) is not None
    ax = correction_figure(curve, unit="deg", period=360.0).axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "device readings leave out (flagged)" in labels
    start = curve.arc[0]
    spans = [p.get_x() for p in ax.patches if p.get_label() != "reference could not measure"]
    assert any(abs(x - start) < 1e-9 for x in spans)
    full = fit_model(demo_stages(rotary_demo(0)), kernel="periodic", period=360.0, n_restarts=1)
    assert correction_curve(full).arc is None


def test_figures_of_a_partly_measured_turn_are_scaled_over_what_was_measured():
    """A review's case: U across the arc the device readings leave out (some 250 arcsec)
    set the scale of the report's U panel and of the device stage's residual panel, where
    U over the measured arc (about 1 arcsec), the residuals and the target noise's band
    were then hairlines on zero. Both are scaled over the measured arc now, the band
    beyond it running off the axis, and the stage figure shades the arc too."""
    from cascal.compensation import in_arc
    from cascal.report import correction_curve, correction_figure, stage_figure
    from cascal.reportdata import stage_views
    from cascal.workflow import arc_width

    model = _partial_turn_model()
    curve = correction_curve(model)
    outside = ~in_arc(curve.grid, arc_width(curve.arc, 360.0), 360.0)
    U = 2.0 * curve.u * 3600.0  # arcsec
    assert U.max() > 10.0 * U[outside].max()  # (24.5 against 1.36 arcsec)
    ux = correction_figure(curve, unit="deg", period=360.0).axes[1]
    assert ux.get_ylim() == pytest.approx((-1.15 * U[outside].max(), 1.15 * U[outside].max()))
    view = stage_views(model)[-1]
    assert view.arc == curve.arc and stage_views(model)[0].arc is None
    ax, rx = stage_figure(view, unit="deg", period=360.0).axes
    seen = ~in_arc(view.grid, arc_width(view.arc, 360.0), 360.0)
    top = 3600.0 * max(np.abs(view.residuals).max(), view.band[seen].max())
    top = max(top, 3600.0 * view.residual_band.max())  # (a second review: it had been cut)
    assert rx.get_ylim() == pytest.approx((-1.15 * top, 1.15 * top))
    (noise,) = [ln for ln in rx.get_lines() if ln.get_label() == "95 % of target noise"]
    assert np.max(noise.get_ydata()) < rx.get_ylim()[1]  # drawn whole
    assert 3600.0 * view.band.max() > 5.0 * rx.get_ylim()[1]  # the arc's band: off the axis
    assert "device readings leave out (flagged)" in [
        t.get_text() for t in ax.get_legend().get_texts()
    ]


def test_exclude_spec_writes_runs_of_rows_as_ranges():
    """A documentation review's case: 98 rows beyond the range were suggested to
    ``--exclude`` one by one (``104,105,...,201``); runs of three or more are ranges now,
    which ``--exclude`` reads back as the same rows."""
    from hypothesis import given
    from hypothesis import strategies as st

    from cascal.cli import _row_numbers
    from cascal.text import exclude_spec

    assert exclude_spec("d.csv", range(104, 202)) == "d.csv:104-201"
    assert exclude_spec("d.csv", [9, 5, 3, 4, 10, 12, 13, 14]) == "d.csv:3-5,9,10,12-14"
    assert exclude_spec("my d.csv", [7]) == "'my d.csv:7'"

    @given(st.sets(st.integers(2, 60), min_size=1))
    def round_trip(rows):
        spec = exclude_spec("f.csv", rows)
        assert _row_numbers(spec.split(":", 1)[1], spec) == rows

    round_trip()


def test_a_partial_turn_s_largest_u_is_over_the_measured_arc():
    """A review's case: for a rotary device measured over part of the turn, ``info`` and
    the report gave the largest u (and the RMS correction) over the whole turn, the
    unmeasured arc included: 0.0353 deg where the measured arc's was 0.000218 (the same
    report's plan table said so). Both are now over the measured arc."""

    from cascal.workflow import arc_width, correct, summarize_device, unmeasured_arc

    model = _partial_turn_model()
    start, width = arc_width(unmeasured_arc(model), 360.0)
    arc = np.linspace(start + width, start + 360.0, 1001)  # the measured arc, independently
    c = correct(model, arc)
    assert not c.out_of_range.any()
    s = summarize_device(model)
    assert s["max_u"] == float(c.u.max())
    assert s["rms_correction"] == float(np.sqrt(np.mean((c.corrected - arc) ** 2)))
    assert float(correct(model, np.linspace(0, 360, 1001)).u.max()) > 10 * s["max_u"]
    html = build_report(model)
    u = s["max_u"]
    assert f"Largest u over the calibrated range: {u:.6g} deg" in html


def _partial_turn_model():
    """The rotary demo with its device readings from 150 to 250 deg left out."""
    from dataclasses import replace

    case = rotary_demo(0)
    dev = case.stages[1]
    keep = (dev.x < 150.0) | (dev.x > 250.0)
    part = replace(case, stages=(case.stages[0], replace(dev, x=dev.x[keep], y=dev.y[keep])))
    return fit_model(demo_stages(part), kernel="periodic", period=360.0, unit="deg", n_restarts=1)


def test_a_measured_arc_is_printed_rounded_inward():
    """A CLI review's case: a swivel's measured arc from 6.8363821941 deg was printed from
    6.83638219 (plain 9 digits, rounded outward), and ``correct`` flagged a reading of the
    printed start. Its ends are now rounded inward, as a linear range's are; the arc left
    out, the same two numbers the other way round, so outward."""
    from cascal.text import measured_ends, turn_text

    arc = (199.115860006, 6.8363821941)  # left out from 199.1... round to 6.83...
    assert measured_ends(arc) == ("6.8363822", "199.11586")
    assert measured_ends((10.0, 350.0)) == ("350", "10")  # exact ends stay as they are
    text = turn_text(arc, "deg", 360.0)
    assert text.startswith("6.8363822 to 199.11586 deg of the turn (period 360;")
    assert "leave out 199.11586 to 6.8363822 deg" in text


def test_a_reading_named_in_a_range_is_printed_within_it():
    """A CLI review's case: compare printed its common range as ending at 0.940129142
    (rounded inward) and its largest change "at reading 0.940129143", the same end
    rounded up. A reading is now kept within the printed range."""
    from cascal.text import range_ends, range_text, reading_in_range

    lo, hi = 0.09807420485, 0.9401291429443
    assert range_text(lo, hi) == "[0.0980742049, 0.940129142]"
    assert range_ends(lo, hi) == ("0.0980742049", "0.940129142")
    assert f"{hi:.9g}" == "0.940129143"
    assert reading_in_range(hi, lo, hi) == "0.940129142"
    assert reading_in_range(lo, lo, hi) == "0.0980742049"
    assert reading_in_range(0.5, lo, hi) == "0.5"


def test_millimetres_and_radians_are_shown_with_a_smaller_prefix():
    """A review: only metres and degrees were rescaled, so a U of 6e-6 rad was drawn as
    ticks of 6 beside a detached "1e-6" (read as 6 rad), and a mm axis as 0.0001 mm or
    "3.43e-05 mm". Millimetres and radians now step down as metres do."""
    from cascal.report import display_scale

    assert display_scale("m", 3.43e-8) == (1e9, "nm")
    assert display_scale("mm", 3.43e-5) == (1e6, "nm")
    assert display_scale("mm", 2e-3) == (1e3, "µm")
    assert display_scale("mm", 0.5) == (1e3, "µm")
    assert display_scale("mm", 2.0) == (1.0, "mm")
    assert display_scale("rad", 6e-6) == (1e6, "µrad")
    assert display_scale("rad", 0.02) == (1e3, "mrad")
    assert display_scale("deg", 0.001) == (3600.0, "arcsec")
    assert display_scale("inch", 1e-4) == (1.0, "inch")  # no ladder: as it is


def test_a_rotary_stage_figure_shows_every_reading_whatever_the_other_stages_convention():
    """A report review's case: stage 0 read in [-180, 180) and the device in [0, 360): every
    stage was drawn on the window from -225 to 225 deg and the device readings beyond 225,
    a suspect among them, fell off the axis. Each stage now has its own window (the
    device's from -45 deg), and readings are drawn on the turn shown."""
    from dataclasses import replace

    from cascal.report import correction_curve, stage_figure
    from cascal.reportdata import seam, stage_views

    case = rotary_demo(0)
    ref = case.stages[0]
    shift = np.where(ref.x >= 180.0, 360.0, 0.0)  # the same angles, written -180 to 180
    signed = replace(ref, x=ref.x - shift, y=ref.y - shift)
    model = fit_model(
        demo_stages(replace(case, stages=(signed, case.stages[1]))),
        kernel="periodic", period=360.0, unit="deg", n_restarts=1,
    )  # fmt: skip
    assert [seam(model, k) for k in (0, 1)] == [-180.0, 0.0]
    assert correction_curve(model).grid[0] == pytest.approx(-45.0)
    for view in stage_views(model):
        ax, rx = stage_figure(view, unit="deg", period=360.0).axes
        lo, hi = ax.get_xlim()
        data = ax.containers[0].lines[0] if view.target_sd is not None else _line(ax, "data")
        for line in (data, _line(rx, "residual (target - fit)")):
            xs = np.asarray(line.get_xdata())
            assert np.all((xs >= lo) & (xs <= hi))
            # every reading, and those within an eighth of a turn of a seam again beyond it
            # (a review: the axis's margins had looked unmeasured)
            near = np.mod(view.x - (lo + 45.0), 360.0)
            assert xs.size == view.x.size + np.sum(near <= 45.0) + np.sum(near >= 315.0)
            drawn = np.unique(np.round(np.mod(xs, 360.0), 9))
            assert np.array_equal(drawn, np.unique(np.round(np.mod(view.x, 360.0), 9)))


def _line(ax, label: str):
    """The line of ``ax`` labelled ``label``."""
    (line,) = [ln for ln in ax.get_lines() if ln.get_label() == label]
    return line


def test_the_prior_mean_offset_carries_its_unit():
    """A report review's case: the report's hyperparameter table showed the prior mean
    offset as a bare number ("-100.021"), where ``cascal info`` gives "-100.021 m"."""
    from cascal.text import hyperparameter_unit

    assert hyperparameter_unit("prior mean offset", "mm", False) == " mm"
    assert hyperparameter_unit("prior mean offset", "deg", True) == " deg"
    assert hyperparameter_unit("length_scale", "deg", True) == ""
    case = rotary_demo(0)
    model = fit_model(demo_stages(case)[:1], mean="offset", unit="deg", n_restarts=1)
    page = build_report(model)
    assert re.search(r"prior mean offset</td><td>-?[0-9.e+-]+ deg</td>", page), page[:0]


def test_a_lookup_table_stage_says_it_was_not_screened():
    """A report review's case: a GP stage's section says what the outlier screening found,
    a lookup table's said nothing, though an outlier passes into its correction."""
    model = fit_model(demo_stages(rotary_demo(0))[:1], method="lut", unit="deg")
    page = build_report(model)
    assert "Outlier screening does not apply (no noise model)" in page
    assert "optimiser starts" not in page  # (a diff review: a table has no optimiser)


def test_a_suspect_is_shown_with_the_digits_its_discrepancy_needs():
    """A report review's case: readings near 1000 mm printed to 6 digits showed target and
    prediction alike ("1043.59") for a point 22 standard deviations out. The table gives
    10 digits and the difference itself, which with u recomputes z."""
    from cascal.io.data import StageData

    rng = np.random.default_rng(3)
    x = np.linspace(1000.0, 1100.0, 41)
    y = x + 1e-3 * np.sin(x / 15.0) + 1e-5 * rng.standard_normal(x.size)
    y[19] += 4e-4
    rows = np.arange(2, x.size + 2)
    stage = StageData(x, y, None, np.ones(x.size, int), rows, demo_stages()[0].source)
    model = fit_model([stage], unit="mm", n_restarts=2)
    page = build_report(model)
    cells = re.findall(r"<td>([^<]*)</td>", page.split("target - predicted [mm]")[1])[:6]
    reading, target, predicted, diff, u, z = cells
    assert float(reading) == pytest.approx(x[19], abs=1e-6)
    assert float(target) == pytest.approx(y[19], abs=1e-6)
    assert float(target) != float(predicted)
    assert float(diff) == pytest.approx(float(target) - float(predicted), rel=1e-3, abs=2e-9)
    assert float(z) == pytest.approx(float(diff) / float(u), rel=2e-3, abs=0.06)
    assert float(z) > 10.0


def test_the_plan_says_where_its_precision_is_the_planner_s_floor(tmp_path):
    """A diff review's case: with a test bed read to 1e-9 m, the plan's measurements were
    called as precise as the average existing point, while their standard deviation was
    the planner's floor (253 nm against 0.8 nm)."""
    from cascal.io.data import read_stage
    from cascal.planning import default_noise_variance

    rng = np.random.default_rng(0)
    x = np.linspace(0, 1, 30)
    y = x + 1e-3 * np.sin(5 * x) + 1e-9 * rng.standard_normal(30)
    d = np.linspace(0.05, 0.95, 25)
    t = d + 2e-3 * np.cos(4 * d) + 1e-6 * rng.standard_normal(25)
    for name, head, a, b in (("tb", "testbed,reference", x, y), ("d", "device,testbed", d, t)):
        rows = "".join(f"{float(u)!r},{float(v)!r}\n" for u, v in zip(a, b, strict=True))
        (tmp_path / f"{name}.csv").write_text(f"{head}\n{rows}")
    stages = [read_stage(tmp_path / "tb.csv"), read_stage(tmp_path / "d.csv")]
    model = fit_model(stages, n_restarts=1)
    page = build_report(model)
    average = float(np.sqrt(default_noise_variance(model.fitted.models[0])))
    assert average < 1e-8 and "as precise as the average existing point" not in page
    floor = "the planner's floor (1e-08 of stage 0's prior variance), above the average"
    assert html.escape(floor) in page
