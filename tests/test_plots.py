"""Figures carry what their captions say: checked on the artists, not on pixels."""

from __future__ import annotations

import numpy as np
import pytest

from cascal.plots import plot_change, plot_cost_distribution, plot_verification
from cascal.verification import compare, verify


def _lines(ax, label):
    return [ln for ln in ax.get_lines() if ln.get_label() == label]


def test_verification_draws_the_acceptance_limits_inside_the_mpe():
    """ISO 14253-1: a point conforms when |error| + k u_reference <= MPE, so the limits
    that decide are drawn at +-(MPE - k u_reference), inside the +-MPE lines."""
    r = np.linspace(0.0, 1.0, 80)
    err = 1e-6 * np.sin(9 * r)
    v = verify(r, r, r + err, np.full(80, 1e-6), u_reference=1e-6, mpe=5e-6)
    ax = plot_verification(v, scale=1e6, unit="µm").axes[0]
    (limit,) = _lines(ax, "acceptance limit")
    assert limit.get_ydata()[0] == pytest.approx(3.0)  # (5 - 2 * 1) µm
    assert _lines(ax, "±MPE")[0].get_ydata()[0] == pytest.approx(5.0)
    assert ax.get_title().endswith("all conform to the MPE")
    bad = verify(r, r, r + 10 * err, np.full(80, 1e-6), u_reference=1e-6, mpe=5e-6)
    title = plot_verification(bad, scale=1e6, unit="µm").axes[0].get_title()
    n = int(np.count_nonzero(~bad.conforms[bad.inside]))
    assert n > 0 and title.endswith(f"\n{n} not shown to conform to the MPE")


def test_verification_counts_the_points_it_leaves_out_in_its_verdict():
    """A review: with one check point outside the calibrated range, ``verify --mpe`` failed
    (exit 3) while its figure said "all conform to the MPE", and never named its files."""
    r = np.linspace(0.0, 1.0, 80)
    err = 1e-6 * np.sin(6 * r)
    v = verify(r, r, r + err, np.full(80, 1e-6), inside=r < 0.99, u_reference=1e-6, mpe=5e-6)
    ax = plot_verification(v, scale=1e6, unit="µm", names=("m.json", "check.csv")).axes[0]
    rms = float(np.sqrt(np.mean(err[r < 0.99] ** 2))) * 1e6
    assert ax.get_title() == (
        f"check.csv against m.json\n79 check points: RMS error {rms:.3g} µm, 100.0 % within ±U\n"
        "1 outside the calibrated range left out, not judged: not all shown to conform to the MPE"
    )
    plain = verify(r, r, r + err, np.full(80, 1e-6), inside=r < 0.99)
    title = plot_verification(plain, scale=1e6, unit="µm").axes[0].get_title()
    assert title.endswith("within ±U\n1 outside the calibrated range left out")


def test_change_names_its_quantity_and_the_files_in_the_title():
    r = np.linspace(0.0, 1.0, 50)
    u = np.full(50, 1e-6)
    c = compare(r, r, u, r + 1e-7, u)
    ax = plot_change(c, scale=1e6, unit="µm", names=("old.json", "new.json")).axes[0]
    assert ax.get_ylabel() == "change of correction [µm]"
    assert ax.get_title().startswith("new.json - old.json\n")


def test_change_draws_the_max_change_and_breaks_between_two_stretches():
    """A review: the figure of ``compare --max-change`` did not draw the limit it judged
    against (verify draws its MPE). Two stretches of a turn (arcs that overlap at both
    ends) are drawn apart, with no line across the part left out."""
    r = np.r_[np.linspace(300.0, 330.0, 30), np.linspace(410.0, 460.0, 50)]
    u = np.full(r.size, 1e-4)
    c = compare(r, r, u, r + 2e-4, u, period=360.0)
    ax = plot_change(c, scale=3600.0, unit="arcsec", limit=1e-4).axes[0]
    (line,) = _lines(ax, "±max change 0.36 arcsec")
    assert line.get_ydata()[0] == pytest.approx(0.36)
    title = " ".join(ax.get_title().split("\n"))  # (wrapped to the figure's width)
    # (2e-4 deg against 1e-4 is not beyond it by more than the band, 3.2 u: not shown within)
    assert title.endswith(
        "not shown within the max change; beyond the band over 0.0 % of the range"
    )
    (change,) = _lines(ax, "change of the correction")
    x = np.asarray(change.get_xdata())
    assert np.isnan(x[30]) and x.size == 81 and np.all(np.isfinite(np.delete(x, 30)))
    # a report review: the stretches beyond the band were labelled "beyond it", beside the
    # max change's line
    far = compare(r, r, u, r + 2e-3 * np.sin(r / 20.0), u, period=360.0)
    ax = plot_change(far, scale=3600.0, unit="arcsec", limit=1e-4).axes[0]
    assert len(_lines(ax, "beyond the band")) == 1 and not _lines(ax, "beyond it")
    assert "; beyond the max change;" in " ".join(ax.get_title().split("\n"))
    ok = plot_change(c, scale=3600.0, unit="arcsec", limit=1e-3).axes[0]
    assert "within the max change" in ok.get_title()
    far = plot_change(c, scale=3600.0, unit="arcsec", limit=1.0).axes[0]  # 3600 arcsec
    (line,) = _lines(far, "±max change 3.6e+03 arcsec, off the axis")
    top = max(0.72, c.k_band * c.u.max() * 3600.0)  # the change, 2e-4 deg, or the band
    assert far.get_ylim() == pytest.approx((-1.15 * top, 1.15 * top))


def test_cost_medians_are_written_without_exponents():
    costs = {"bayes": np.full(5, 80e-6), "lut": np.full(5, 1.53e-3)}
    ax = plot_cost_distribution(costs).axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["bayes (median 80 µm)", "lut (median 1530 µm)"]


def test_file_names_and_units_are_drawn_as_written_and_ticks_carry_no_offset():
    """A review's cases: ``dev$^$.csv`` (or a unit ``$^$``) ended the drawing with a
    mathtext parse error, and ``a$x$b`` was drawn as maths; a correction of -100 m had
    tick labels 0.04 ... -0.08 under a small "-1e2"."""
    import io

    r = np.linspace(0.0, 1.0, 50)
    u = np.full(50, 1e-6)
    c = compare(r, r, u, r - 100.0 + 1e-7 * r, u)
    fig = plot_change(c, scale=1.0, unit="$^$", names=("a$x$b.csv", "dev$^$.csv"))
    fig.savefig(io.BytesIO(), format="png")  # drawn: no parse error
    ax = fig.axes[0]
    assert ax.get_ylabel() == "change of correction [$^$]"
    assert ax.title.get_parse_math() is False and ax.yaxis.label.get_parse_math() is False
    assert ax.yaxis.get_major_formatter().get_useOffset() is False
    texts = [t.get_text().replace("\N{MINUS SIGN}", "-") for t in ax.get_yticklabels()]
    ticks = [float(t) for t in texts if t]
    assert ticks and min(ticks) < -99.0  # the values themselves, no offset to add


def test_vector_figures_carry_no_date_and_fixed_ids(tmp_path):
    """A review's case: two runs of one study gave SVG files that differed (a date and
    random clip-path ids). The same figure now gives the same bytes as SVG, PDF and PNG."""
    import matplotlib.pyplot as plt

    from cascal.io.atomic import save_figure

    for k in (1, 2):
        fig, ax = plt.subplots()
        ax.plot([1, 2, 3], [1, 4, 9], "o-")
        ax.set_yscale("log")
        for fmt in ("svg", "pdf", "png"):
            save_figure(fig, tmp_path / f"f{k}.{fmt}")
        plt.close(fig)
    for fmt in ("svg", "pdf", "png"):
        assert (tmp_path / f"f1.{fmt}").read_bytes() == (tmp_path / f"f2.{fmt}").read_bytes()
    assert b"<dc:date>" not in (tmp_path / "f1.svg").read_bytes()
    assert b"CreationDate" not in (tmp_path / "f1.pdf").read_bytes()


def _left_edge_blank(fig, dpi: int = 130) -> bool:
    """Whether the figure, written as PNG at ``dpi`` (as the commands write it), has its
    three leftmost pixel columns blank: no label cut off at the edge."""
    import io

    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    im = Image.open(io.BytesIO(buf.getvalue())).convert("L")
    return min(im.getpixel((x, y)) for x in range(3) for y in range(im.size[1])) == 255


def test_no_axis_label_is_cut_off_at_the_figure_edge():
    """A review's case: a recalibration's change of +-0.02 mm (tick labels of three
    decimals) drew its y label half outside the PNG: the legend below the axes, placed as
    part of them, kept the layout from settling. The legends lie outside the axes now."""
    r = np.linspace(25.0, 275.0, 400)
    d = 0.02 * np.sin((r - 25.0) / 40.0)
    u = np.full(r.size, 0.0012)
    c = compare(r, r, u, r + d, u)
    assert _left_edge_blank(plot_change(c, unit="mm", xunit="mm", names=("a.json", "b.json")))
    v = verify(r, r + d, r + 0.9 * d, u, u_reading=0.0)
    assert _left_edge_blank(plot_verification(v, unit="mm", xunit="mm"))


def test_plan_order_labels_do_not_run_into_each_other():
    """A user review's case: proposals 1, 2, 3 at 155.4 mm and 5 at 167.9 mm on a 265 mm
    axis were labelled on one line, reading "1, 2, 35". A label that reaches the next one's
    place now puts that one a line higher."""
    from cascal import fit_gp
    from cascal.planning import Plan
    from cascal.plots import plot_plan

    x = np.linspace(20.0, 285.0, 40)
    gp = fit_gp(x, x + 1e-3 * np.sin(x / 30.0), n_restarts=1)
    pos = np.array([155.415, 155.415, 155.945, 40.935, 167.87])
    where = np.linspace(20.0, 285.0, 5)
    plan = Plan(pos, np.ones(6), np.ones(6), 1e-8, where, np.ones(5), np.ones(5))
    ax = plot_plan(plan, gp, [(20.0, 285.0)], unit="mm", xunit="mm").axes[0]
    labels = {t.get_text(): t.xy for t in ax.texts}
    assert set(labels) == {"1, 2, 3", "4", "5"}
    assert labels["5"][1] > labels["1, 2, 3"][1]  # a line higher
    assert labels["4"][1] == labels["1, 2, 3"][1]  # far apart: the same line


def test_plan_labels_group_only_close_proposals_and_wrap_reference_points():
    """A review's cases: seven proposals from 4.4 to 21.9 deg, each within 1.5 % of the
    turn of the next, were chained into one label "1, 2, 3, 4, 5, 6, 8" over 18 degrees;
    a group now spans at most that 1.5 %, its orders left to right. And a rotary test
    bed read from -180 to 180 drew its reference points below 0 off the turn drawn."""
    from cascal import fit_gp
    from cascal.planning import Plan
    from cascal.plots import plot_plan

    x = np.linspace(-175.0, 175.0, 36)
    gp = fit_gp(x, x + 1e-3 * np.sin(np.deg2rad(x)), kernel="periodic", period=360.0)
    pos = np.array([6.3, 9.3, 11.8, 4.4, 14.7, 16.8, 30.0, 21.9])
    where = np.linspace(0.0, 350.0, 5)
    plan = Plan(pos, np.ones(9), np.ones(9), 1e-8, where, np.ones(5), np.ones(5))
    ax = plot_plan(plan, gp, [(-180.0, 180.0)], unit="deg", xunit="deg", period=360.0).axes[0]
    labels = sorted(t.get_text() for t in ax.texts)
    assert labels == ["3, 5, 6", "4, 1, 2", "7", "8"]  # groups of 5.4 deg at most
    (ticks,) = [ln for ln in ax.get_lines() if ln.get_label() == "reference points"]
    drawn = np.sort(ticks.get_xdata())
    np.testing.assert_allclose(drawn, np.sort(np.mod(x, 360.0)))


def test_the_cascade_figure_draws_stage_0_wherever_stage_1_reads_it():
    """A review: stage 0 was drawn over its own readings only, so the ends the reference
    could not reach, where stage 1's targets come from its extrapolation (their error bars
    widest), were off the figure. It spans stage 1's test-bed readings now, with the
    stretches the reference could not measure hatched."""
    from cascal import Cascade
    from cascal.plots import plot_cascade
    from cascal.simulation import simulate_trial

    trial = simulate_trial(np.random.default_rng(0))
    fitted = Cascade([trial.d2, trial.d1], "bayes", n_restarts=1).fit()
    ax0, ax1 = plot_cascade(fitted, upper=[trial.d1[1]]).axes
    (mean,) = _lines(ax0, "stage 0: mean")
    x = np.asarray(mean.get_xdata())
    testbed = np.r_[trial.d2[0], trial.d1[1]]
    assert x.min() == testbed.min() and x.max() == testbed.max()
    assert testbed.min() < trial.d2[0].min() and testbed.max() > trial.d2[0].max()
    hatched = [p for p in ax0.patches if p.get_hatch() == "//"]
    assert len(hatched) == 3  # below, across the centre, above
    (mean1,) = _lines(ax1, "stage 1: mean")
    assert np.min(mean1.get_xdata()) == trial.d1[0].min()
    (own,) = _lines(plot_cascade(fitted).axes[0], "stage 0: mean")  # without: its readings
    assert np.min(own.get_xdata()) == trial.d2[0].min()


def test_a_long_file_name_in_a_title_is_wrapped():
    """A report review's case: a stage file of 200 characters ran off both sides of its
    figure's title. Titles wrap to the figure's width, a long name broken; measured as
    drawn (a diff review: a count of characters had let 110 of them overflow)."""
    from matplotlib.figure import Figure

    from cascal.plots import set_title

    for width, letter in ((7.5, "M"), (8.0, "a"), (8.0, "W")):
        fig = Figure(figsize=(width, 3.0), dpi=100)
        ax = fig.subplots()
        name = "run_" + letter * 196 + ".csv"
        set_title(ax, f"{name}: more accurate reading minus reading\nsecond line")
        fig.canvas.draw()
        box = ax.title.get_window_extent()
        assert box.x0 >= 0.0 and box.x1 <= width * 100.0, (letter, box)
        lines = ax.get_title().split("\n")
        assert "".join(lines[:-1]).replace(" ", "") == f"{name}:moreaccuratereadingminusreading"
        assert lines[-1] == "second line"
