"""Matplotlib figures of training runs and of a report's rows and runs.

Built with ``matplotlib.figure.Figure`` (no pyplot: headless, the caller's backend left
alone). A report draws each row in one style (:func:`row_styles` of all its rows, passed to
every figure as ``styles=``), every text from run data as written (:func:`draw_literally`),
env steps in whole steps (:func:`set_frames_axis`), an empty panel saying why
(:func:`mark_empty_panel`), and saves PNG and PDF with no timestamp (:func:`save_figure`;
docs/reproduce.md).
"""

from __future__ import annotations

import io
import math
import textwrap
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, NullLocator

from wcsac_rl.training.progress import read_progress
from wcsac_rl.training.training_safety import cumulative_cost

__all__ = [
    "COST_RETURN_SIZE",
    "DPI",
    "FIG4_SIZE",
    "FIG6_SIZE",
    "FIGURE_FORMATS",
    "NO_EPISODES",
    "NO_TRAINING_EPISODES",
    "NO_VALUES",
    "ROW_MARKERS",
    "ROW_PALETTE",
    "RUNS_PANEL_SIZE",
    "SCORE_SIZE",
    "RowStyle",
    "box_view",
    "curve_panels",
    "draw_literally",
    "figure_paths",
    "frames_formatter",
    "mark_empty_panel",
    "plot_cost_distribution",
    "plot_cost_return",
    "plot_run_curves",
    "plot_run_values",
    "plot_score_distribution",
    "plot_training_curves",
    "plot_trajectories",
    "row_color",
    "row_styles",
    "run_curves_figure",
    "save_figure",
    "set_frames_axis",
    "set_row_ticks",
    "styles_for",
    "trajectory_figure_size",
]

# ------------------------------------------------------------------- rows' styles
ROW_PALETTE: tuple[str, ...] = (
    # Okabe & Ito (2008), without black (the limit d) ...
    "#0072B2",  # blue
    "#E69F00",  # orange
    "#009E73",  # bluish green
    "#D55E00",  # vermillion
    "#CC79A7",  # reddish purple
    "#56B4E9",  # sky blue
    "#F0E442",  # yellow
    # ... then Paul Tol's muted scheme, without its pale grey
    "#332288",  # indigo
    "#CC6677",  # rose
    "#44AA99",  # teal
    "#882255",  # wine
    "#117733",  # green
    "#999933",  # olive
    "#88CCEE",  # cyan
    "#AA4499",  # purple
    "#DDCC77",  # sand
)
"""16 colour-blind-safe colours, one per row (black and grey stay for d and notes)."""
ROW_MARKERS: tuple[str, ...] = tuple("os^DvPX*<>hpdH8")  # one marker a character
"""15 markers: with 16 colours, 240 rows get distinct (colour, marker) pairs."""


@dataclass(frozen=True)
class RowStyle:
    """How a row is drawn in every figure of a report."""

    color: str
    marker: str


def row_styles(labels: Iterable[str]) -> dict[str, RowStyle]:
    """One style per row label: the labels in Table 1's order
    (:func:`~wcsac_rl.evaluation.runs.row_sort_key`), the i-th drawn in
    ``ROW_PALETTE[i % 16]`` with ``ROW_MARKERS[i % 15]`` (distinct pairs for up to 240
    rows)."""
    from wcsac_rl.evaluation.runs import row_sort_key

    ordered = sorted(set(labels), key=row_sort_key)
    return {
        label: RowStyle(ROW_PALETTE[i % len(ROW_PALETTE)], ROW_MARKERS[i % len(ROW_MARKERS)])
        for i, label in enumerate(ordered)
    }


def styles_for(labels: Iterable[str], styles: Mapping[str, RowStyle] | None) -> dict:
    """``styles`` where given (a report's), else :func:`row_styles` of ``labels``; a
    label ``styles`` lacks is refused (it would be drawn in another row's colour)."""
    labels = list(labels)
    if styles is None:
        return row_styles(labels)
    missing = [label for label in labels if label not in styles]
    if missing:
        raise ValueError(f"styles has no entry for row(s) {', '.join(missing)}")
    return dict(styles)


def draw_literally(texts: Iterable[Any] | Any) -> None:
    """Draw ``texts`` (matplotlib ``Text`` objects, or a ``Legend`` for its entries) as
    written: no mathtext, no TeX. For every text drawn from run data (a row label, an
    algorithm's or a run's name, a title naming them): a ``$`` in it is a character,
    not the start of a formula matplotlib would fail to parse while drawing."""
    from matplotlib.legend import Legend

    if isinstance(texts, Legend):
        texts = [*texts.get_texts(), texts.get_title()]
    elif not isinstance(texts, Iterable):
        texts = [texts]
    for text in texts:
        text.set(parse_math=False, usetex=False)


TICK_ROTATION = 45  # degrees: the x labels' tilt when a figure has many rows


def set_row_ticks(ax: Any, names: Sequence[str]) -> None:
    """Row names under their boxes or bars: up to 4 rows level, wrapped to 14
    characters a line; more rows tilted by :data:`TICK_ROTATION`, one line each
    (``tests/test_figures.py`` checks that no two overlap)."""
    if len(names) <= 4:
        wrapped = [textwrap.fill(name, width=14, break_on_hyphens=False) for name in names]
        ax.set_xticks(range(len(names)), wrapped)
        ax.tick_params(axis="x", labelsize=9)
        draw_literally(ax.get_xticklabels())  # (names from run data: drawn as written)
        return
    ax.set_xticks(range(len(names)), list(names))
    ax.tick_params(axis="x", labelsize=8)
    for label in ax.get_xticklabels():
        label.set(rotation=TICK_ROTATION, horizontalalignment="right", rotation_mode="anchor")
    draw_literally(ax.get_xticklabels())


def frames_formatter() -> Any:
    """Tick labels of env steps: whole numbers below 1 000 (``0``, ``200``), engineering
    units from there (``50 k``, ``1.5 M``), never a fraction of a step (no ``200 m``)."""
    from matplotlib.ticker import EngFormatter

    class _FramesFormatter(EngFormatter):
        def __call__(self, x: float, pos: int | None = None) -> str:
            steps = round(x) if math.isfinite(x) else x
            if abs(steps) < 1000:
                return self.fix_minus(f"{steps:d}")
            return super().__call__(steps, pos)

    return _FramesFormatter(sep=" ")


def set_frames_axis(ax: Any) -> None:
    """An x axis of env steps: at most 6 ticks, at whole steps, labelled by
    :func:`frames_formatter`."""
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(nbins=6, steps=[1, 2, 2.5, 5, 10], integer=True))
    ax.xaxis.set_major_formatter(frames_formatter())
    ax.set_xlabel("env steps")


NO_TRAINING_EPISODES = "no finished training episodes"
"""Written inside a panel of training-episode curves without one value: no training
episode of its runs ended (a run shorter than an episode, or stopped early)."""
NO_EPISODES = "no finished episodes"
"""Written inside a run's return or cost panel when neither a training nor a test
episode ended (where only test episodes did: :data:`NO_TRAINING_EPISODES`, under
their curve)."""
NO_VALUES = "no values logged"
"""Written inside a panel whose column no run logged a value of."""


def _panel_note(ax: Any, message: str, *, y: float, **style: Any) -> None:
    """``message`` centred across ``ax`` at height ``y`` (axes fraction), in the grey
    italics of the figures' notes about what a panel lacks."""
    ax.text(0.5, y, message, transform=ax.transAxes, ha="center", color="0.3",
            style="italic", **style)  # fmt: skip


def mark_empty_panel(
    ax: Any,
    message: str,
    frames: Sequence[float] = (),
    cost_limit: float | None = None,
) -> None:
    """Say ``message`` inside a panel that has nothing to draw (it is not left blank),
    over the env steps of ``frames`` (the x range the figure's other panels show); no y
    scale (there is none), except up to 1.5 × ``cost_limit`` where the panel draws the
    budget d."""
    _panel_note(ax, message, y=0.4, va="center", fontsize=10, zorder=5,
                bbox={"boxstyle": "round", "facecolor": "white", "edgecolor": "0.7"})  # fmt: skip
    finite = [float(f) for f in frames if math.isfinite(float(f))]
    if finite:
        low, high = min(finite), max(finite)
        pad = 0.05 * (high - low)  # matplotlib's default margins, as the other panels'
        if high > low:
            ax.set_xlim(low - pad, high + pad)
        else:  # one epoch: from the start
            ax.set_xlim(0.0, max(high, 1.0))
    if cost_limit is not None and cost_limit > 0:
        ax.set_ylim(0.0, 1.5 * cost_limit)
    else:
        ax.set_yticks([])


_PANELS = (
    ("episode return", ("train/episode_return", "eval/episode_return")),
    ("episode cost", ("train/episode_cost", "eval/episode_cost")),
    ("cost rate", ("train/cost_rate",)),
)
PANEL_SIZE = (4.0, 3.6)  # inches per panel of a run's curves
CURVE_COLUMNS = 4  # panels per row of a run's curves
# the multipliers' panels of a run's curves: (title, progress.csv column)
_WEIGHT_PANELS = (
    (r"safety weight $\kappa$", "loss/kappa"),
    (r"entropy weight $\beta$", "loss/alpha"),
)

# The safety critic at the test episodes' start states: (column, label, colour, style).
_CALIBRATION_LINES = (
    ("calib/start_cvar", r"predicted $\Gamma_\alpha(s_0, a_0)$", "C3", "-"),
    ("calib/start_realised_cvar", r"realised CVaR$_\alpha$ of $\sum_t \gamma_c^t c_t$", "C3", "--"),
    ("calib/start_cost_value", r"predicted $Q^c(s_0, a_0)$", "C0", "-"),
    ("calib/start_realised_cost_to_go", r"realised mean of $\sum_t \gamma_c^t c_t$", "C0", "--"),
)
CALIBRATION_PANEL = r"safety critic at $s_0$ (test episodes)"
SLACK_PANEL = r"$\kappa$-loss slack: threshold $-\ \Gamma$"
CUMULATIVE_PANEL = "cumulative training cost"


def _has_values(columns: dict[str, list[float]], key: str) -> bool:
    values = columns.get(key)
    return values is not None and not all(math.isnan(v) for v in values)


def _smoothed(values: Sequence[float], window: int) -> np.ndarray:
    """Trailing mean over the last ``window`` epochs, skipping NaN (NaN where all are)."""
    values = np.asarray(values, dtype=np.float64)
    if window <= 1:
        return values
    out = np.full_like(values, np.nan)
    for i in range(len(values)):
        chunk = values[max(0, i - window + 1) : i + 1]
        if not np.isnan(chunk).all():
            out[i] = np.nanmean(chunk)
    return out


def curve_panels(columns: dict[str, list[float]]) -> list[str]:
    """The panels of :func:`run_curves_figure` for these columns, in order: return,
    cost, cost rate; then each of the cumulative training cost, κ, the entropy weight
    β, the safety critic's calibration and the κ loss's slack the run logged."""
    panels: list[str] = [title for title, _ in _PANELS]
    if _has_values(columns, "train/cumulative_cost") or _has_values(columns, "train/cost_rate"):
        panels.append(CUMULATIVE_PANEL)
    for panel, key in _WEIGHT_PANELS:
        if _has_values(columns, key):
            panels.append(panel)
    if any(_has_values(columns, key) for key, *_ in _CALIBRATION_LINES):
        panels.append(CALIBRATION_PANEL)
    if _has_values(columns, "loss/constraint_slack"):
        panels.append(SLACK_PANEL)
    return panels


def run_curves_figure(
    columns: dict[str, list[float]],
    *,
    cost_limit: float | None = None,
    title: str = "",
    smooth: int = 1,
) -> Figure:
    """The figure of :func:`plot_run_curves` from ``read_progress`` columns: a grid of up
    to :data:`CURVE_COLUMNS` panels per row (:func:`curve_panels`; docs/training.md).
    ``smooth`` > 1: each curve is the trailing mean over that many epochs, the epochs'
    own values drawn faint beneath it.
    """
    if int(smooth) != smooth or smooth < 1:
        raise ValueError(f"smooth must be a whole number of epochs >= 1, got {smooth!r}")
    panels = curve_panels(columns)
    cols = min(CURVE_COLUMNS, len(panels))
    rows = math.ceil(len(panels) / cols)
    fig = Figure(figsize=(PANEL_SIZE[0] * cols, PANEL_SIZE[1] * rows), layout="constrained")
    grid = np.asarray(fig.subplots(rows, cols, squeeze=False)).reshape(-1)
    for ax in grid[len(panels) :]:
        ax.remove()
    for ax, panel in zip(grid, panels):
        _draw_run_panel(ax, panel, columns, cost_limit, int(smooth))
        ax.set_title(panel)
        set_frames_axis(ax)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    suffix = f" (trailing mean over {int(smooth)} epochs)" if smooth > 1 else ""
    draw_literally(fig.suptitle(f"{title}{suffix}", fontsize=10))  # (a run's name)
    return fig


def _curve(ax: Any, frames, values, smooth: int, **style) -> None:
    """One curve of a run's panel; smoothed, over its epochs' own values drawn faint."""
    if smooth > 1:
        ax.plot(frames, values, color=style.get("color"), alpha=0.25, linewidth=0.8)
        values = _smoothed(values, smooth)
    ax.plot(frames, values, marker="o", markersize=3, **style)


def _draw_run_panel(
    ax: Any, panel: str, columns: dict[str, list[float]], cost_limit: float | None, smooth: int
) -> None:
    """One panel of :func:`run_curves_figure`."""
    frames = columns["frames"]
    keys_of = dict(_PANELS)
    weights = dict(_WEIGHT_PANELS)
    if panel in keys_of:
        drawn = [key for key in keys_of[panel] if _has_values(columns, key)]
        for key, color in zip(keys_of[panel], ("C0", "C1")):
            if key in drawn:
                label = "test (deterministic)" if key.startswith("eval/") else "training"
                _curve(ax, frames, columns[key], smooth, color=color, label=label)
        if not drawn:
            limit = cost_limit if panel == "episode cost" else None
            mark_empty_panel(ax, NO_EPISODES if panel != "cost rate" else NO_VALUES, frames, limit)
        elif keys_of[panel][0] not in drawn:  # the test episodes' curve only
            _panel_note(ax, NO_TRAINING_EPISODES, y=0.03, va="bottom", fontsize=8)
        if panel == "episode cost" and cost_limit is not None:
            ax.axhline(
                cost_limit,
                color="k",
                linestyle="--",
                linewidth=1,
                label=f"limit d = {cost_limit:g}",
            )
    elif panel == CUMULATIVE_PANEL:
        ax.plot(frames, cumulative_cost(columns), color="C3", marker="o", markersize=3)
    elif panel in weights:
        _curve(ax, frames, columns[weights[panel]], smooth, color="C4")
    elif panel == CALIBRATION_PANEL:
        for key, label, color, style in _CALIBRATION_LINES:
            if _has_values(columns, key):
                _curve(ax, frames, columns[key], smooth, color=color, linestyle=style, label=label)
    else:
        _curve(ax, frames, columns["loss/constraint_slack"], smooth, color="C2")
        ax.axhline(0.0, color="k", linestyle="--", linewidth=1)


def plot_run_curves(
    progress_csv: Path,
    out: Path,
    *,
    cost_limit: float | None = None,
    smooth: int = 1,
    formats: Sequence[str] = ("png",),
) -> Path:
    """The curves of one run against env steps (``progress.csv`` → PNG; ``formats``:
    the files written, :func:`save_figure`).

    Training curves are means over the episodes that ended in each epoch; test
    curves are the deterministic test episodes. A dashed line marks ``cost_limit``.
    The panels and ``smooth``: :func:`run_curves_figure`.
    """
    columns = read_progress(progress_csv)
    if not columns:
        raise ValueError(f"{progress_csv} has no rows yet")
    from wcsac_rl.evaluation.runs import display_text

    title = display_text(Path(progress_csv).parent.name)  # (a name that is not UTF-8 too)
    fig = run_curves_figure(columns, cost_limit=cost_limit, title=title, smooth=smooth)
    paths = save_figure(fig, out, formats=formats)
    return Path(out) if Path(out) in paths else paths[0]


# ---------------------------------------------------------------- the paper's figures
DPI = 100
"""Resolution of every report figure: pixel size = figure size (inches) × DPI."""
FIG4_SIZE = (15.0, 4.5)  # inches: 1500 × 450 px
FIG6_SIZE = (13.0, 4.8)  # inches: 1300 × 480 px
TRAJECTORY_PANEL = 5.5  # inches per trajectory panel (square)
TRAJECTORY_COLUMNS = 3  # panels per row of the trajectory figure

_CURVE_PANELS = (
    ("(a) Average episodic return", "train/episode_return", "episodic return"),
    ("(b) Average episodic cost", "train/episode_cost", "episodic cost"),
    ("(c) Cost rate", "train/cost_rate", "cumulative cost / env steps"),
)
_COST_COLUMNS = ("train/episode_cost", "train/cost_rate")  # >= 0: their bands end at 0
_STEP_COLUMNS = ("train/cost_rate",)  # per env step, not per finished episode


def row_color(label: str) -> str:
    """The colour of ``label`` among Table 1's rows (:data:`~wcsac_rl.evaluation.runs.ROW_ORDER`
    and ``label``): the same in every figure. A report with other rows draws them in
    the colours of :func:`row_styles` of its own rows."""
    from wcsac_rl.evaluation.runs import ROW_ORDER

    return row_styles([*ROW_ORDER, label])[label].color


FIGURE_FORMATS: tuple[str, ...] = ("png", "pdf")
"""The formats :func:`save_figure` writes by default: a PNG to view, a PDF to print."""


def figure_paths(out: Path, formats: Sequence[str] = FIGURE_FORMATS) -> list[Path]:
    """The files :func:`save_figure` writes for ``out``: ``out`` with each format's suffix."""
    return [Path(out).with_suffix(f".{fmt}") for fmt in formats]


def save_figure(fig: Figure, out: Path, *, formats: Sequence[str] = FIGURE_FORMATS) -> list[Path]:
    """Write ``fig`` as each of ``formats`` (``"png"``, ``"pdf"``, ``"svg"``) beside
    ``out`` (its suffix replaced); returns the paths (:func:`figure_paths`).

    PNG: a 256-colour palette image at :data:`DPI` (line, box and scatter plots on
    white: visually the same at about a third of the RGBA file's size, what makes a
    report's figures viewable in a repository). PDF and SVG: vector, with the fonts
    embedded as TrueType (editable text) and no creation date, so the same figure
    gives the same bytes."""
    unknown = sorted(set(formats) - {"png", "pdf", "svg"})
    if unknown or not formats:
        raise ValueError(f"formats must be among png, pdf, svg, got {list(formats)!r}")
    paths = figure_paths(out, formats)
    paths[0].parent.mkdir(parents=True, exist_ok=True)
    for fmt, path in zip(formats, paths, strict=True):
        if fmt == "png":
            _save_palette_png(fig, path)
            continue
        metadata = {"CreationDate": None} if fmt == "pdf" else {"Date": None}
        with matplotlib.rc_context({"pdf.fonttype": 42, "svg.hashsalt": "wcsac_rl"}):
            fig.savefig(path, dpi=DPI, format=fmt, metadata=metadata)
    return paths


def _save_palette_png(fig: Figure, out: Path) -> None:
    from PIL import Image

    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=DPI, format="png")
    buffer.seek(0)
    with Image.open(buffer) as image:
        palette = image.convert("RGB").quantize(
            colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
        )
    palette.save(out, format="png", optimize=True)


def _save(fig: Figure, out: Path, formats: Sequence[str] = ("png",)) -> Path:
    """:func:`save_figure`, returning ``out`` (a report figure's own path)."""
    save_figure(fig, out, formats=formats)
    return Path(out)


def plot_training_curves(
    rows: dict[str, list[dict[str, list[float]]]],
    out: Path,
    *,
    cost_limit: float | None = None,
    title: str = "Training curves",
    styles: Mapping[str, RowStyle] | None = None,
    formats: Sequence[str] = ("png",),
) -> Path:
    """Figure 4: episodic return, episodic cost and cost rate against env steps.

    Args:
        rows: Table-1 row label → the ``read_progress`` columns of each seed's run.
            Each row is drawn as the mean over its seeds (line) ± one standard
            deviation (shaded, cut at 0 on the cost panels: a cost is never
            negative), on the training-episode columns as in the paper. A panel
            without a value (no training episode of any run ended: a run shorter
            than an episode) says so inside it (:data:`NO_TRAINING_EPISODES`).
        out: PNG path (``FIG4_SIZE`` × ``DPI`` pixels).
        cost_limit: the budget d, a dashed line on the cost panel.
        title: the figure's title.
        styles: each row's colour and marker (:func:`row_styles` of the report's rows;
            default: of ``rows``).
        formats: the files written (:func:`save_figure`), e.g. :data:`FIGURE_FORMATS`.
    """
    from wcsac_rl.evaluation.metrics import curve_mean_std
    from wcsac_rl.evaluation.runs import row_name

    styles = styles_for(rows, styles)
    fig = Figure(figsize=FIG4_SIZE, layout="constrained")
    axes = fig.subplots(1, len(_CURVE_PANELS))
    handles: dict[str, Any] = {}
    frames = [f for runs in rows.values() for run in runs for f in run.get("frames", ())]
    for ax, (panel_title, key, ylabel) in zip(axes, _CURVE_PANELS):
        drawn = False
        for label, runs in rows.items():
            curves = [(run["frames"], run[key]) for run in runs if key in run and "frames" in run]
            if not curves:
                continue
            x, mean, std, _ = curve_mean_std(curves)
            ok = ~np.isnan(mean)
            if not ok.any():
                continue
            drawn = True
            style = styles[label]
            seeds = f"{len(curves)} seed{'s' if len(curves) != 1 else ''}"
            (line,) = ax.plot(
                x[ok],
                mean[ok],
                color=style.color,
                marker=style.marker,
                markersize=3.5,
                markevery=max(1, int(ok.sum()) // 12),
                label=f"{row_name(label)} ({seeds})",
            )
            handles.setdefault(line.get_label(), line)
            low = mean - std
            if key in _COST_COLUMNS:  # a cost is >= 0: so is the band's lower edge
                low = np.maximum(low, 0.0)
            ax.fill_between(x[ok], low[ok], (mean + std)[ok], color=style.color, alpha=0.15)
        if not drawn:
            # (the cost rate is per step: it needs no finished episode)
            message = NO_VALUES if key in _STEP_COLUMNS else NO_TRAINING_EPISODES
            limit = cost_limit if key == "train/episode_cost" else None
            mark_empty_panel(ax, message, frames, limit)
        if key == "train/episode_cost" and cost_limit is not None:
            line = ax.axhline(cost_limit, color="k", linestyle="--", linewidth=1.2)
            handles.setdefault(f"budget d = {cost_limit:g}", line)
        ax.set_title(panel_title)
        set_frames_axis(ax)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    if handles:  # one legend for the three panels, under them (never over a curve)
        legend = fig.legend(
            list(handles.values()),
            list(handles),
            loc="outside lower center",
            ncol=min(len(handles), 6),
            fontsize=8,
        )
        draw_literally(legend)  # (the rows' names)
    draw_literally(fig.suptitle(f"{title} — mean ± std over seeds (training episodes)"))
    return _save(fig, out, formats)


def box_view(
    costs: Sequence[Sequence[float]], cost_limit: float, ymax: float | None = None
) -> tuple[float, float]:
    """Figure 6(a)'s y-range: every row's interquartile box and d in view. All the data
    when it fits within 3 × the highest box top (or d), else up to 2 × that (the
    episodes above are marked with their count); ``ymax`` (the paper clips its view so
    d stays readable) where it still shows every box."""
    rows = [np.asarray(c, dtype=np.float64) for c in costs if len(c)]
    if not rows:
        return (0.0, max(1.0, 1.1 * cost_limit))
    need = max(max(float(np.percentile(c, 75)) for c in rows), float(cost_limit))
    full = max(float(c.max()) for c in rows)
    need = need if need > 0 else max(full, 1.0)
    top = 1.05 * max(full, need) if full <= 3 * need else 2 * need
    if ymax is not None:
        top = max(float(ymax), 1.05 * need)
    low = min(0.0, min(float(np.percentile(c, 25)) for c in rows))
    return (low - 0.03 * (top - low), top)


def plot_cost_distribution(
    costs: dict[str, list[float]],
    out: Path,
    *,
    cost_limit: float,
    title: str = "Evaluation after training",
    ymax: float | None = None,
    styles: Mapping[str, RowStyle] | None = None,
    formats: Sequence[str] = ("png",),
) -> Path:
    """Figure 6: (a) box plots of episodic cost, (b) proportion of episodes over budget.

    Args:
        costs: row label → the episodic costs of its test episodes (seeds pooled).
        out: PNG path (``FIG6_SIZE`` × ``DPI`` pixels).
        cost_limit: the budget d: dashed line in (a); (b) counts costs strictly above it.
        title: the figure's title.
        ymax: upper view limit of (a), kept where it shows every box (:func:`box_view`);
            ``None``: the view :func:`box_view` chooses.
        styles: each row's colour and marker (:func:`row_styles` of the report's rows).
        formats: the files written (:func:`save_figure`), e.g. :data:`FIGURE_FORMATS`.

    Boxes span the quartiles, whiskers the 1st and 99th percentiles (the paper's);
    episodes above the view are counted over their row (``↑ n``).
    """
    from wcsac_rl.evaluation.metrics import exceedance_proportion
    from wcsac_rl.evaluation.runs import row_name

    labels = list(costs)
    styles = styles_for(labels, styles)
    names = [row_name(label) for label in labels]
    colors = [styles[label].color for label in labels]
    data = [np.asarray(costs[label], dtype=np.float64) for label in labels]
    fig = Figure(figsize=FIG6_SIZE, layout="constrained")
    ax_box, ax_bar = fig.subplots(1, 2)
    bottom, top = box_view(data, cost_limit, ymax)
    handles, legend_labels = [], []
    if labels:
        box = ax_box.boxplot(
            data,
            positions=range(len(labels)),
            whis=(1, 99),
            showmeans=True,
            patch_artist=True,
            flierprops={"marker": ".", "markersize": 3, "alpha": 0.5},
            meanprops={"marker": "^", "markerfacecolor": "white", "markeredgecolor": "k"},
            medianprops={"color": "k"},
        )
        for patch, color in zip(box["boxes"], colors):
            patch.set_facecolor(color)
            patch.set_alpha(0.6)
        for i, values in enumerate(data):
            above = int((values > top).sum())
            if above:
                ax_box.annotate(
                    f"↑ {above}",
                    (i, top),
                    xytext=(3, -3),  # (beside the whisker running up to the edge)
                    textcoords="offset points",
                    ha="left",
                    va="top",
                    fontsize=9,
                    fontweight="bold",
                    color="0.2",
                )
        handles, legend_labels = [box["medians"][0], box["means"][0]], ["median", "mean"]
    line = ax_box.axhline(cost_limit, color="k", linestyle="--", linewidth=1.2)
    fig.legend(  # under the panels: never over a box, a bar or a count
        [*handles, line],
        [*legend_labels, f"budget d = {cost_limit:g}"],
        loc="outside lower center",
        ncol=3,
        fontsize=8,
        title="(a) box: quartiles; whiskers: 1st and 99th percentiles; ↑ n: n episodes "
        "above the view",
        title_fontsize=8,
    )
    ax_box.set_ylim(bottom, top)
    ax_box.set_title("(a) Episodic cost of the test episodes")
    ax_box.set_ylabel("episodic cost")
    ax_box.grid(axis="y", alpha=0.3)

    shares = [100.0 * exceedance_proportion(costs[label], cost_limit) for label in labels]
    bars = ax_bar.bar(range(len(labels)), shares, color=colors, alpha=0.8)
    ax_bar.bar_label(bars, labels=[f"{s:.1f}%" for s in shares], fontsize=8)
    ax_bar.set_ylim(0, max([*shares, 1.0]) * 1.15)
    ax_bar.set_title(f"(b) Budget exceedance: episodes with cost > d = {cost_limit:g}")
    ax_bar.set_ylabel("episodes over budget (%)")
    ax_bar.grid(axis="y", alpha=0.3)
    for ax in (ax_box, ax_bar):
        set_row_ticks(ax, names)
    draw_literally(fig.suptitle(title))
    return _save(fig, out, formats)


def trajectory_figure_size(panels: int, columns: int = TRAJECTORY_COLUMNS) -> tuple[float, float]:
    """Size in inches of a trajectory figure with ``panels`` panels, ``columns`` per row."""
    cols = min(panels, columns)
    rows = math.ceil(panels / cols)
    return (TRAJECTORY_PANEL * cols, TRAJECTORY_PANEL * rows)


def _draw_layout(ax: Any, layout: dict[str, Any]) -> list[Any]:
    from matplotlib.patches import Circle, Rectangle

    handles = []
    xmin, ymin, xmax, ymax = layout["placement_extents"]
    handles.append(
        ax.add_patch(
            Rectangle(
                (xmin, ymin),
                xmax - xmin,
                ymax - ymin,
                fill=False,
                linestyle=":",
                edgecolor="0.5",
                label="placement area",
            )
        )
    )
    r = float(layout["hazards_size"])
    for i, (hx, hy) in enumerate(np.asarray(layout["hazards_xy"]).reshape(-1, 2)):
        patch = Circle(
            (hx, hy),
            r,
            facecolor="tab:red",
            edgecolor="darkred",
            alpha=0.25,
            label=f"hazard (r = {r:g})" if i == 0 else None,
        )
        ax.add_patch(patch)
        if i == 0:
            handles.append(patch)
    vr = float(layout.get("vases_size", 0.0))
    for i, (vx, vy) in enumerate(np.asarray(layout.get("vases_xy", np.zeros((0, 2))))):
        patch = Rectangle(
            (vx - vr, vy - vr),
            2 * vr,
            2 * vr,
            facecolor="tab:cyan",
            edgecolor="teal",
            alpha=0.5,
            label="vase" if i == 0 else None,
        )
        ax.add_patch(patch)
        if i == 0:
            handles.append(patch)
    gx, gy = np.asarray(layout["goal_xy"], dtype=np.float64)
    g = float(layout["goal_size"])
    goal = Circle(
        (gx, gy),
        g,
        facecolor="tab:green",
        edgecolor="darkgreen",
        alpha=0.35,
        label=f"goal (r = {g:g})",
    )
    handles.append(ax.add_patch(goal))
    return handles


def _draw_trajectories(
    ax: Any, layout: dict[str, Any], trajectories: list[Any], title: str
) -> None:
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle

    handles = _draw_layout(ax, layout)
    cmap = matplotlib.colormaps["viridis"]
    points = [layout["placement_extents"][:2], layout["placement_extents"][2:]]
    redrawn = False
    g = float(layout["goal_size"])
    for i, traj in enumerate(trajectories):
        color = cmap(0.9 * i / max(1, len(trajectories) - 1))
        xy = np.asarray(traj.xy)
        (line,) = ax.plot(
            xy[:, 0],
            xy[:, 1],
            color=color,
            linewidth=1.4,
            label=f"ep {i + 1}: cost {traj.cost:g}, return {traj.ret:.2f}",
        )
        handles.append(line)
        ax.plot(*xy[0], marker="o", color=color, markeredgecolor="k", markersize=6)
        ax.plot(*xy[-1], marker="X", color=color, markeredgecolor="k", markersize=7)
        for gx, gy in np.asarray(traj.goals)[1:]:
            ax.add_patch(Circle((gx, gy), g, fill=False, edgecolor="tab:green", linestyle="--"))
            redrawn = True
        points.extend([xy.min(0), xy.max(0)])
    handles.append(Line2D([], [], marker="o", color="w", markeredgecolor="k", label="start"))
    handles.append(Line2D([], [], marker="X", color="w", markeredgecolor="k", label="end"))
    if redrawn:
        handles.append(
            Line2D(
                [],
                [],
                marker="o",
                color="w",
                markeredgecolor="tab:green",
                linestyle="--",
                label="re-drawn goal",
            )
        )
    lo = np.min(points, axis=0) - 0.2
    hi = np.max(points, axis=0) + 0.2
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    draw_literally(ax.set_title(title, fontsize=10))  # (a row's name)
    ax.grid(alpha=0.2)
    ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2)


def plot_trajectories(
    panels: list[tuple[str, dict[str, Any], list[Any]] | None],
    out: Path,
    *,
    title: str = "Trajectories of deterministic test episodes",
    columns: int = TRAJECTORY_COLUMNS,
    rows: Sequence[str | None] | None = None,
    styles: Mapping[str, RowStyle] | None = None,
    formats: Sequence[str] = ("png",),
) -> Path:
    """Figure 5: top-down robot paths, one panel per ``(title, layout, trajectories)``.

    Each panel draws the layout (placement area, hazards with their radius, goal,
    vases) and every trajectory (start ``o``, end ``X``, legend with its cost and
    return), from :func:`~wcsac_rl.evaluation.trajectories.collect_trajectories`.
    Panels fill rows of ``columns``; a ``None`` panel is left blank. ``rows``: each
    panel's row label (``None``: no row): its frame and title are drawn in the row's
    colour (``styles``, as in the report's other figures; default: :func:`row_styles`
    of ``rows``), the episodes in a sequential palette. Size:
    :func:`trajectory_figure_size` × ``DPI``; ``formats``: the files written
    (:func:`save_figure`).
    """
    if not any(panel is not None for panel in panels):
        raise ValueError("plot_trajectories needs at least one panel")
    if columns < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    rows = list(rows) if rows is not None else [None] * len(panels)
    if len(rows) != len(panels):
        raise ValueError(f"rows has {len(rows)} labels for {len(panels)} panels")
    styles = styles_for(dict.fromkeys(r for r in rows if r is not None), styles)
    fig = Figure(figsize=trajectory_figure_size(len(panels), columns), layout="constrained")
    cols = min(len(panels), columns)
    grid_rows = math.ceil(len(panels) / cols)
    axes = np.asarray(fig.subplots(grid_rows, cols, squeeze=False)).reshape(-1)
    for ax, panel, row in zip(axes, panels, rows):
        if panel is None:
            ax.set_axis_off()
            continue
        panel_title, layout, trajectories = panel
        _draw_trajectories(ax, layout, trajectories, panel_title)
        if row is not None:  # the row's colour, as in the report's other figures
            ax.title.set_color(styles[row].color)
            for spine in ax.spines.values():
                spine.set(edgecolor=styles[row].color, linewidth=2.5)
    for ax in axes[len(panels) :]:
        ax.set_axis_off()
    draw_literally(fig.suptitle(title))
    return _save(fig, out, formats)


# ------------------------------------------------- the cost-return trade-off
COST_RETURN_SIZE = (8.0, 5.0)  # inches: 800 × 500 px


def _error(row: Mapping[str, Any], metric: str) -> tuple[float, float]:
    """The distances from the row's value down and up to its interval's ends (0 where
    there is no interval: one episode of one seed)."""
    value, lo, hi = row[metric], row[f"{metric}_lo"], row[f"{metric}_hi"]
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return (0.0, 0.0)
    return (max(0.0, value - lo), max(0.0, hi - value))


def plot_cost_return(
    rows: Sequence[Mapping[str, Any]],
    out: Path,
    *,
    cost_limit: float,
    title: str = "Cost and return",
    styles: Mapping[str, RowStyle] | None = None,
    formats: Sequence[str] = ("png",),
) -> Path:
    """``fig_cost_return.png``: one point per Table-1 row at (EC, ER) with the 95 %
    seed-stratified bootstrap interval of each as error bars, in the row's colour and
    marker; the budget d a dashed vertical line, the side of it within budget shaded.

    Args:
        rows: Table-1 rows (``label``, ``algorithm``, ``EC``, ``ER`` and their
            ``_lo``/``_hi`` interval ends).
        out: PNG path (:data:`COST_RETURN_SIZE` × ``DPI`` pixels).
        cost_limit: the budget d, the dashed vertical line.
        title: the figure's title.
        styles: each row's colour and marker (default: :func:`row_styles`
            of ``rows``).
        formats: the files written (:func:`save_figure`).
    """
    if not rows:
        raise ValueError("plot_cost_return needs at least one row")
    styles = styles_for([row["label"] for row in rows], styles)
    fig = Figure(figsize=COST_RETURN_SIZE, layout="constrained")
    ax = fig.subplots()
    for row in rows:
        style = styles[row["label"]]
        (low_x, high_x), (low_y, high_y) = _error(row, "EC"), _error(row, "ER")
        ax.errorbar(
            row["EC"],
            row["ER"],
            xerr=[[low_x], [high_x]],
            yerr=[[low_y], [high_y]],
            fmt=style.marker,
            color=style.color,
            markersize=8,
            markeredgecolor="k",
            markeredgewidth=0.6,
            capsize=4,
            linewidth=1.4,
            label=row["algorithm"],
        )
    ax.axvline(
        cost_limit, color="k", linestyle="--", linewidth=1.2, label=f"budget d = {cost_limit:g}"
    )
    low = min(0.0, *(row["EC"] - _error(row, "EC")[0] for row in rows))
    high = max(cost_limit, *(row["EC"] + _error(row, "EC")[1] for row in rows))
    left = low - 0.04 * (high - low or 1.0)  # (a row at EC = 0 stays whole in view)
    ax.axvspan(left, cost_limit, color="0.5", alpha=0.08, linewidth=0, label="within budget")
    ax.set_xlim(left, high + 0.04 * (high - low or 1.0))
    ax.set_xlabel("EC: mean episodic cost (95 % interval)")
    ax.set_ylabel("ER: mean episodic return (95 % interval)")
    ax.grid(alpha=0.3)
    draw_literally(ax.set_title(title, fontsize=10))  # (run data: "$" as written)
    draw_literally(fig.legend(loc="outside right upper", fontsize=8))  # beside the axes
    return _save(fig, out, formats)


# ------------------------------------------------------ the runs one by one
RUNS_PANEL_SIZE = (5.5, 5.0)  # inches per panel of fig_runs.png
SCORE_SIZE = (9.0, 4.5)  # inches: 900 × 450 px
_RUN_PANELS = (
    ("EC", "EC: mean episode cost"),
    ("C0.1", "C0.1: CVaR$_{0.1}$ of episode cost"),
    ("ER", "ER: mean episode return"),
)
_SPREAD = 0.25  # half the width over which a row's dots are spread


def _stat_rows(stats: Any) -> list[str]:
    return list(dict.fromkeys(run["label"] for run in stats.runs))


def plot_run_values(
    stats: Any,
    out: Path,
    *,
    title: str = "",
    styles: Mapping[str, RowStyle] | None = None,
    formats: Sequence[str] = ("png",),
) -> Path:
    """``fig_runs.png`` (see the module docstring) from a
    :class:`~wcsac_rl.evaluation.run_report.RunStatistics`; ``styles``: each row's
    colour and marker (default: :func:`~wcsac_rl.evaluation.row_styles` of its
    rows); ``formats``: the files written."""
    labels = _stat_rows(stats)
    by_label = {row["label"]: row for row in stats.rows}
    names = {run["label"]: run["algorithm"] for run in stats.runs}
    styles = styles_for(labels, styles)
    fig = Figure(
        figsize=(RUNS_PANEL_SIZE[0] * len(_RUN_PANELS), RUNS_PANEL_SIZE[1]), layout="constrained"
    )
    axes = fig.subplots(1, len(_RUN_PANELS))
    for ax, (metric, panel_title) in zip(axes, _RUN_PANELS):
        for x, label in enumerate(labels):
            runs = [run for run in stats.runs if run["label"] == label]
            offsets = np.linspace(-_SPREAD, _SPREAD, len(runs)) if len(runs) > 1 else [0.0]
            color, marker = styles[label].color, styles[label].marker
            for offset, run in zip(offsets, runs):
                held = run["split"] == "held-out"
                ax.plot(
                    x + offset,
                    run[metric],
                    marker=marker,
                    linestyle="none",
                    markersize=6,
                    markeredgecolor=color,
                    markerfacecolor=color if held else "none",
                    alpha=0.85,
                )
            row = by_label.get(label)
            if row is not None:
                point = row[f"{metric}_iqm"]
                ax.errorbar(
                    x,
                    point,
                    yerr=[[point - row[f"{metric}_lo"]], [row[f"{metric}_hi"] - point]],
                    fmt="D",
                    color="k",
                    markersize=6,
                    capsize=5,
                    linewidth=1.5,
                    zorder=3,
                )
        if metric != "ER":
            ax.axhline(stats.cost_limit, color="k", linestyle="--", linewidth=1)
        set_row_ticks(ax, [names[label] for label in labels])
        ax.set_xlim(-0.6, len(labels) - 0.4)
        ax.set_title(panel_title)
        ax.grid(axis="y", alpha=0.3)
    _run_values_legend(fig, stats.cost_limit)
    draw_literally(fig.suptitle(f"Runs one by one — {title}"))  # (names from run data)
    return _save(fig, out, formats)


def _run_values_legend(fig: Figure, cost_limit: float) -> None:
    from matplotlib.lines import Line2D

    handles = [
        Line2D([], [], marker="o", linestyle="none", color="0.4", label="run, held-out seed"),
        Line2D(
            [],
            [],
            marker="o",
            linestyle="none",
            color="0.4",
            markerfacecolor="none",
            label="run, in-sample seed",
        ),
        Line2D([], [], marker="D", color="k", label="IQM over runs, 95 % interval"),
        Line2D([], [], color="k", linestyle="--", label=f"budget d = {cost_limit:g}"),
    ]
    fig.legend(handles=handles, fontsize=9, loc="outside lower center", ncol=len(handles))


def plot_score_distribution(
    stats: Any,
    out: Path,
    *,
    title: str = "",
    styles: Mapping[str, RowStyle] | None = None,
    formats: Sequence[str] = ("png",),
) -> Path:
    """``fig_score_distribution.png``: the fraction of a row's runs with C0.1 <= x against
    x, one step curve per row marked at each of its runs, with a 95 % bootstrap band over
    runs (rliable's score distribution); x linear up to d, logarithmic above it."""
    from wcsac_rl.evaluation.run_statistics import cdf_band

    values = np.array([run["C0.1"] for run in stats.runs], dtype=np.float64)
    right = max(float(values.max()), float(stats.cost_limit)) * 1.05 or 1.0
    grid = np.unique(np.concatenate([[0.0, right], values, [float(stats.cost_limit)]]))
    fig = Figure(figsize=SCORE_SIZE, layout="constrained")
    ax = fig.subplots()
    styles = styles_for(_stat_rows(stats), styles)
    for label in _stat_rows(stats):
        runs = [run["C0.1"] for run in stats.runs if run["label"] == label]
        name = next(run["algorithm"] for run in stats.runs if run["label"] == label)
        color = styles[label].color
        if len(runs) > 1:
            share, low, high = cdf_band(runs, grid)
            ax.fill_between(grid, low, high, step="post", color=color, alpha=0.12, linewidth=0)
        else:
            share = (np.asarray(runs)[:, None] <= grid).mean(axis=0)
        ax.step(
            grid,
            share,
            where="post",
            color=color,
            linewidth=1.8,
            marker=styles[label].marker,
            markevery=[int(i) for i in np.searchsorted(grid, np.unique(runs))],
            markersize=5,
            label=f"{name} ({len(runs)} run{'s' if len(runs) != 1 else ''})",
        )
    ax.axvline(
        stats.cost_limit,
        color="k",
        linestyle="--",
        linewidth=1,
        label=f"budget d = {stats.cost_limit:g}",
    )
    # linear up to d, logarithmic above it: the runs near the budget stay apart however
    # far the worst run lies
    limit = max(float(stats.cost_limit), 1.0)
    ax.set_xscale("symlog", linthresh=limit, linscale=1.5)
    above = [v * 10**e for e in range(6) for v in (1, 2, 5) if 1.5 * limit < v * 10**e <= right]
    ax.set_xticks([0.0, limit / 3, 2 * limit / 3, limit, *above])
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.3g}" if v < 1000 else f"{v:.0f}"))
    ax.xaxis.set_minor_locator(NullLocator())
    ax.set_xlim(0.0, right)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("x: C0.1 of a run (mean cost of its worst 10 % of test episodes)")
    ax.set_ylabel("fraction of runs with C0.1 <= x")
    ax.grid(alpha=0.3)
    draw_literally(fig.legend(fontsize=8, loc="outside right upper"))  # (rows' names)
    draw_literally(ax.set_title(f"Score distribution over runs — {title}", fontsize=10))
    return _save(fig, out, formats)
