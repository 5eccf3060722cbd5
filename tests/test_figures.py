"""The report's figure style (wcsac_rl/evaluation/plots.py): a colour and marker per row
shared by every figure, labels that do not overlap, box plots whose view shows every
row's box, PNG and PDF files, a run's curves as a grid."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb

from wcsac_rl.evaluation import plots
from wcsac_rl.evaluation.runs import row_sort_key

# a sweep's rows: Table 1's, SAC-Lag at other limits, the IQN and paper variants
ROWS = [
    "random",
    "sac",
    "sac_lag",
    "sac_lag_d13.5",
    "sac_lag_d7.5",
    "sac_lag_d1.5",
    "sac_lag_paper",
    "wcsac_0.9",
    "wcsac_0.5",
    "wcsac_0.1",
    "wcsac_iqn_0.5",
    "wcsac_iqn_0.1",
    "wcsac_paper_0.1",
    "cpo",
]


def _costs(labels, seed=0):
    rng = np.random.default_rng(seed)
    costs = {label: list(rng.exponential(3.0 + i, 120)) for i, label in enumerate(labels)}
    costs[labels[0]] = [*rng.normal(30.0, 4.0, 120).clip(0), *[800.0] * 7]  # a heavy tail
    return costs


def _progress(seed):
    rng = np.random.default_rng(seed)
    return {
        "frames": [1000.0 * i for i in range(1, 9)],
        "train/episode_return": list(rng.normal(0, 1, 8)),
        "train/episode_cost": list(rng.normal(20, 5, 8)),
        "train/cost_rate": list(rng.uniform(0, 0.1, 8)),
    }


def _drawn(fig):
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def test_every_row_of_a_sweep_gets_its_own_colour_and_marker():
    styles = plots.row_styles(ROWS)
    assert list(styles) == sorted(ROWS, key=row_sort_key)  # Table 1's order
    colors = {to_rgb(style.color) for style in styles.values()}
    assert len(colors) == len(ROWS)  # 14 rows, 14 colours
    assert len({style.marker for style in styles.values()}) == len(ROWS)
    assert len(set(plots.ROW_PALETTE)) == 16 and len(set(plots.ROW_MARKERS)) == 15
    # beyond 16 rows the colours repeat, never a (colour, marker) pair
    many = plots.row_styles([f"wcsac_0.{i:03d}" for i in range(1, 200)])
    assert len({(s.color, s.marker) for s in many.values()}) == 199
    # a row's style depends on the report's rows, not on a figure's subset of them
    assert plots.row_styles(ROWS)["sac_lag_d7.5"] == styles["sac_lag_d7.5"]


def _line_colors(ax):
    # ("<row name> (<n> seeds)")
    return {
        line.get_label().rsplit(" (", 1)[0]: to_rgb(line.get_color()) for line in ax.get_lines()
    }


def test_a_row_has_the_same_colour_in_every_figure_of_a_report(tmp_path):
    from wcsac_rl.evaluation.runs import row_name

    styles = plots.row_styles(ROWS)
    captured = {}

    def keep(fig, out, formats=("png",)):
        captured[out.name] = fig
        return out

    original = plots._save
    plots._save = keep
    try:
        plots.plot_training_curves(
            {label: [_progress(i)] for i, label in enumerate(ROWS)},
            tmp_path / "fig4.png",
            cost_limit=15,
            styles=styles,
        )
        subset = [label for label in ROWS if label != "random"]  # Figure 6's default rows
        plots.plot_cost_distribution(
            {label: _costs(subset)[label] for label in subset},
            tmp_path / "fig6.png",
            cost_limit=15,
            styles=styles,
        )
    finally:
        plots._save = original
    curves = captured["fig4.png"].axes[0]
    by_name = {row_name(label): to_rgb(styles[label].color) for label in ROWS}
    drawn = {name: color for name, color in _line_colors(curves).items() if name in by_name}
    assert drawn == by_name and len(set(drawn.values())) == len(ROWS)
    box_ax, bar_ax = captured["fig6.png"].axes
    bars = [to_rgb(patch.get_facecolor()) for patch in bar_ax.patches]
    boxes = [to_rgb(patch.get_facecolor()) for patch in box_ax.patches]
    assert bars == boxes == [to_rgb(styles[label].color) for label in subset]
    with pytest.raises(ValueError, match=r"styles has no entry for row\(s\) wcsac_0\.3"):
        plots.plot_cost_distribution(
            {"wcsac_0.3": [1.0]}, tmp_path / "x.png", cost_limit=1, styles=styles
        )


@pytest.mark.parametrize("rows", [ROWS[:3], ROWS])
def test_the_box_view_shows_every_row_s_box_and_counts_what_is_above_it(tmp_path, rows):
    costs = _costs(rows)
    captured = {}
    original = plots._save
    plots._save = lambda fig, out, formats=("png",): captured.setdefault("fig", fig) and out
    try:
        plots.plot_cost_distribution(costs, tmp_path / "f6.png", cost_limit=15)
    finally:
        plots._save = original
    fig = captured["fig"]
    box_ax, bar_ax = fig.axes
    low, high = box_ax.get_ylim()
    for label in rows:
        q1, q3 = np.percentile(costs[label], [25, 75])
        assert low <= q1 and q3 <= high, label  # the whole interquartile box in view
    assert low <= 0 and high >= 15  # and d
    assert high < 800  # the 7 episodes at 800 do not squash every box to a line
    above = [sum(v > high for v in costs[label]) for label in rows]
    assert [text.get_text() for text in box_ax.texts] == [f"↑ {n}" for n in above if n]
    assert above[0] == 7  # the heavy tail's episodes, counted over their row
    # the paper's whiskers: to the data within the 1st and 99th percentiles of a row
    ends = set()
    for line in box_ax.lines:
        x, y = line.get_xdata(), line.get_ydata()
        if len(x) == 2 and x[0] == x[1] == 0:  # row 0's vertical segments (the whiskers)
            ends.update(float(v) for v in y)
    values = np.asarray(costs[rows[0]])
    q01, q99 = np.percentile(values, [1, 99])
    assert values[values >= q01].min() in ends and values[values <= q99].max() in ends
    # no two row names overlap, on either panel
    renderer = _drawn(fig)
    for ax in (box_ax, bar_ax):
        _assert_labels_apart(ax.get_xticklabels(), renderer)


def _assert_labels_apart(labels, renderer):
    """Level labels: their boxes do not intersect. Tilted ones (parallel strips, all at
    one angle): the distance between neighbouring baselines exceeds a label's height."""
    labels = [label for label in labels if label.get_text()]
    for a, b in itertools.pairwise(labels):
        angle = a.get_rotation()
        if angle == 0:
            assert not a.get_window_extent(renderer).overlaps(b.get_window_extent(renderer))
            continue
        (xa, _), (xb, _) = (
            a.get_transform().transform(a.get_position()),
            b.get_transform().transform(b.get_position()),
        )
        a.set_rotation(0)
        height = a.get_window_extent(renderer).height
        a.set_rotation(angle)
        assert abs(xb - xa) * math.sin(math.radians(angle)) > height


def test_box_view_keeps_the_whole_data_when_it_fits_and_a_user_limit_that_shows_the_boxes():
    assert plots.box_view([[1.0, 2.0, 3.0, 4.0]], cost_limit=5.0) == pytest.approx(
        (-0.03 * 5.25, 5.25)
    )  # all the data (4 ≤ 3 × 5): up to the largest, +5 %
    high = plots.box_view([[1.0, 2.0, 3.0, 3.0, 3.0, 40.0]], cost_limit=5.0)[1]
    assert high == pytest.approx(2 * 5.0)  # 40 > 3 × max(Q3, d): clipped at 2 × that
    assert plots.box_view([[0.0, 10.0]], cost_limit=1.0, ymax=60.0)[1] == 60.0
    # a limit under a box is raised to show it
    assert plots.box_view([[0.0, 10.0, 20.0, 30.0]], 1.0, ymax=5.0)[1] == pytest.approx(23.625)


def test_every_figure_is_written_as_png_and_pdf_the_same_bytes_each_time(tmp_path):
    costs = _costs(ROWS[:3])
    first = plots.plot_cost_distribution(
        costs, tmp_path / "a" / "f6.png", cost_limit=15, formats=plots.FIGURE_FORMATS
    )
    again = plots.plot_cost_distribution(
        costs, tmp_path / "b" / "f6.png", cost_limit=15, formats=plots.FIGURE_FORMATS
    )
    for out in (first, again):
        assert plots.figure_paths(out) == [out, out.with_suffix(".pdf")]
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert out.with_suffix(".pdf").read_bytes()[:5] == b"%PDF-"
    for suffix in (".png", ".pdf"):
        assert first.with_suffix(suffix).read_bytes() == again.with_suffix(suffix).read_bytes()
    pdf = first.with_suffix(".pdf").read_bytes()
    assert b"/CreationDate" not in pdf and b"/FontFile2" in pdf  # TrueType: editable text
    out = plots.plot_training_curves(
        {"sac": [_progress(0)]}, tmp_path / "f4.png", formats=("png", "svg")
    )
    assert out.with_suffix(".svg").read_text().lstrip().startswith("<?xml")
    assert not out.with_suffix(".pdf").exists()
    with pytest.raises(ValueError, match="formats must be among png, pdf, svg"):
        plots.save_figure(
            plots.run_curves_figure(_progress(0)), tmp_path / "c.png", formats=["jpg"]
        )


def _run_columns():
    rng = np.random.default_rng(3)
    columns = {
        **_progress(1),
        "eval/episode_return": list(rng.normal(0, 1, 8)),
        "eval/episode_cost": list(rng.normal(20, 5, 8)),
        "train/cumulative_cost": list(np.cumsum(rng.uniform(0, 100, 8))),
        "loss/kappa": list(np.cumsum(rng.uniform(0, 0.1, 8))),
        "loss/alpha": list(np.exp(-np.arange(8) / 3)),
        "loss/constraint_slack": list(rng.normal(0, 1, 8)),
    }
    for key, *_ in plots._CALIBRATION_LINES:
        columns[key] = list(rng.uniform(0, 10, 8))
    return columns


def test_a_run_s_curves_are_a_grid_with_kappa_and_the_entropy_weight():
    columns = _run_columns()
    fig = plots.run_curves_figure(columns, cost_limit=15)
    titles = [ax.get_title() for ax in fig.axes]
    assert titles == [
        "episode return",
        "episode cost",
        "cost rate",
        plots.CUMULATIVE_PANEL,
        r"safety weight $\kappa$",
        r"entropy weight $\beta$",
        plots.CALIBRATION_PANEL,
        plots.SLACK_PANEL,
    ]
    width, height = fig.get_size_inches()
    assert (width, height) == (4 * plots.PANEL_SIZE[0], 2 * plots.PANEL_SIZE[1])  # 4 × 2
    kappa, beta = fig.axes[4], fig.axes[5]
    assert kappa.get_lines()[0].get_ydata().tolist() == columns["loss/kappa"]
    assert beta.get_lines()[0].get_ydata().tolist() == columns["loss/alpha"]
    # the critic's reading against the realised cost: four lines, two of them realised
    labels = [line.get_label() for line in fig.axes[6].get_lines()]
    assert sum("realised" in label for label in labels) == 2 and len(labels) == 4
    # a run without κ (SAC): no κ panel; five panels fill a 4-wide grid's two rows
    sac = {k: v for k, v in columns.items() if not k.startswith(("calib/", "loss/kappa"))}
    sac.pop("loss/constraint_slack")
    fig = plots.run_curves_figure(sac)
    assert len(fig.axes) == 5 and r"entropy weight $\beta$" in [a.get_title() for a in fig.axes]


def test_smoothing_draws_the_trailing_mean_over_the_epochs_own_values():
    columns = _run_columns()
    values = columns["train/episode_return"]
    fig = plots.run_curves_figure(columns, smooth=3)
    faint, smooth = fig.axes[0].get_lines()[:2]
    assert faint.get_ydata().tolist() == values and faint.get_alpha() == 0.25
    expected = [np.mean(values[max(0, i - 2) : i + 1]) for i in range(len(values))]
    assert smooth.get_ydata() == pytest.approx(expected, rel=1e-12)
    assert "trailing mean over 3 epochs" in fig.get_suptitle()
    assert plots._smoothed([math.nan, 1.0, math.nan, 3.0], 2)[1:].tolist() == [1.0, 1.0, 3.0]
    with pytest.raises(ValueError, match="smooth must be a whole number of epochs >= 1"):
        plots.run_curves_figure(columns, smooth=0)


def _statistics(labels):
    from wcsac_rl.evaluation.run_report import RunStatistics
    from wcsac_rl.evaluation.runs import row_name

    rng = np.random.default_rng(5)
    runs, rows = [], []
    for i, label in enumerate(labels):
        for seed in (100, 101, 7):
            values = {"EC": rng.uniform(0, 30), "C0.1": rng.uniform(0, 90), "ER": rng.normal()}
            split = "held-out" if seed >= 100 else "in-sample"
            runs.append({"label": label, "algorithm": row_name(label), "seed": seed,
                         "split": split, **values})  # fmt: skip
        row = {"label": label, "algorithm": row_name(label)}
        for metric in ("EC", "C0.1", "ER"):
            row |= {f"{metric}_iqm": i, f"{metric}_lo": i - 0.5, f"{metric}_hi": i + 1.0}
        rows.append(row)
    return RunStatistics("static", 15.0, runs, rows)


def _table1_rows(labels):
    from wcsac_rl.evaluation.runs import row_name

    return [
        {"label": label, "algorithm": row_name(label), "EC": 2.0 * i, "EC_lo": 2.0 * i - 1,
         "EC_hi": 2.0 * i + 1.5, "ER": -0.1 * i, "ER_lo": -0.1 * i - 0.2, "ER_hi": -0.1 * i + 0.3}
        for i, label in enumerate(labels)
    ]  # fmt: skip


def test_the_runs_score_and_cost_return_figures_draw_each_row_in_its_style(tmp_path):
    """14 rows: fig_runs' dots, the score distribution's curves and the cost-return points
    (read from the artists) are in each row's colour and marker of the report, and
    fig_runs' row names do not overlap."""
    from matplotlib.colors import to_hex

    from wcsac_rl.evaluation.plots import plot_cost_return, plot_run_values, plot_score_distribution
    from wcsac_rl.evaluation.runs import row_name

    styles = plots.row_styles(ROWS)
    expected = {row_name(label): (to_hex(s.color), s.marker) for label, s in styles.items()}
    captured = {}
    original = plots.save_figure
    plots.save_figure = lambda fig, out, formats=("png",): captured.setdefault(out.name, fig)
    try:
        stats = _statistics(ROWS)
        plot_run_values(stats, tmp_path / "runs.png", styles=styles)
        plot_score_distribution(stats, tmp_path / "score.png", styles=styles)
        plot_cost_return(_table1_rows(ROWS), tmp_path / "cr.png", cost_limit=15, styles=styles)
    finally:
        plots.save_figure = original
    ax = captured["runs.png"].axes[0]
    names = [t.get_text() for t in ax.get_xticklabels()]
    dots: dict[str, set] = {}
    for line in ax.get_lines():  # (in black: the IQM and its interval's caps)
        if line.get_linestyle() == "None" and to_hex(line.get_markeredgecolor()) != "#000000":
            name = names[round(line.get_xdata()[0])]
            dots.setdefault(name, set()).add(
                (to_hex(line.get_markeredgecolor()), line.get_marker())
            )
    assert dots == {name: {style} for name, style in expected.items()}
    _assert_labels_apart(ax.get_xticklabels(), _drawn(captured["runs.png"]))
    ax = captured["score.png"].axes[0]
    curves = {
        line.get_label().rsplit(" (", 1)[0]: (to_hex(line.get_color()), line.get_marker())
        for line in ax.get_lines()
        if not line.get_label().startswith("budget")
    }
    assert curves == expected
    # each curve is marked exactly at its own row's runs, at the share of runs <= each;
    # x is linear up to d = 15 and logarithmic above it
    for line in ax.get_lines():
        if line.get_label().startswith("budget"):
            continue
        name = line.get_label().rsplit(" (", 1)[0]
        runs = sorted(run["C0.1"] for run in stats.runs if run["algorithm"] == name)
        x, y = line.get_xydata()[line.get_markevery()].T
        assert x.tolist() == runs and y.tolist() == pytest.approx([1 / 3, 2 / 3, 1.0])
    assert ax.get_xscale() == "symlog" and ax.xaxis.get_transform().linthresh == 15.0
    ax = captured["cr.png"].axes[0]
    points = {
        c.get_label(): (to_hex(c.lines[0].get_color()), c.lines[0].get_marker())
        for c in ax.containers
    }
    assert points == expected and len({color for color, _ in points.values()}) == len(ROWS)
    # each point at (EC, ER) with its interval as error bars; d drawn
    first = ax.containers[1]
    assert first.lines[0].get_xydata().tolist() == [[2.0, -0.1]]
    segments = [seg for col in first.lines[2] for seg in col.get_segments()]
    assert [[1.0, -0.1], [3.5, -0.1]] in [s.tolist() for s in segments]
    assert any(
        list(line.get_xdata()) == [15, 15] and line.get_linestyle() == "--"
        for line in ax.get_lines()
    )


def test_the_env_step_labels_do_not_overlap_up_to_millions_of_frames(tmp_path):
    """Figure 4 and a run's curves over 3 M frames: the x labels in engineering units
    (``1 M``), none running into the next."""
    progress = _progress(0)
    progress["frames"] = [375_000.0 * i for i in range(1, 9)]
    captured = {}
    original = plots._save
    plots._save = lambda fig, out, formats=("png",): captured.setdefault(out.name, fig) and out
    try:
        plots.plot_training_curves({"sac": [progress]}, tmp_path / "f4.png")
    finally:
        plots._save = original
    for fig in (captured["f4.png"], plots.run_curves_figure(progress)):
        renderer = _drawn(fig)
        for ax in fig.axes:
            labels = [t for t in ax.get_xticklabels() if t.get_text()]
            assert "3 M" in [t.get_text() for t in labels] and len(labels) <= 8
            _assert_labels_apart(labels, renderer)
