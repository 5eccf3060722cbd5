"""Matplotlib figures of training runs.

Figures are built with ``matplotlib.figure.Figure`` (no pyplot), so they render
headless and never change the caller's matplotlib backend.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from wcsac_rl.training.progress import read_progress
from wcsac_rl.training.training_safety import cumulative_cost

__all__ = [
    "DPI",
    "FIG4_SIZE",
    "FIG6_SIZE",
    "plot_cost_distribution",
    "plot_run_curves",
    "plot_training_curves",
    "plot_trajectories",
    "row_color",
    "run_curves_figure",
    "trajectory_figure_size",
]

_PANELS = (
    ("episode return", ("train/episode_return", "eval/episode_return")),
    ("episode cost", ("train/episode_cost", "eval/episode_cost")),
    ("cost rate", ("train/cost_rate",)),
)
PANEL_SIZE = (4.0, 3.6)  # inches per panel of a run's curves

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


def run_curves_figure(
    columns: dict[str, list[float]], *, cost_limit: float | None = None, title: str = ""
) -> Figure:
    """The figure of :func:`plot_run_curves` from ``read_progress`` columns.

    Panels: return, cost (training and test, the limit d dashed), cost rate, the
    cumulative training cost (:mod:`~wcsac_rl.training.training_safety`); then, when
    the run logged them, the safety critic's calibration at the test episodes' start
    states (predicted Γ_α and Q^c against the realised CVaR_α and mean of the
    discounted cost-to-go, ``calib/*``) and the constraint slack the κ loss sees
    (``loss/constraint_slack``).
    """
    panels: list[str] = [title for title, _ in _PANELS]
    if _has_values(columns, "train/cumulative_cost") or _has_values(columns, "train/cost_rate"):
        panels.append(CUMULATIVE_PANEL)
    if any(_has_values(columns, key) for key, *_ in _CALIBRATION_LINES):
        panels.append(CALIBRATION_PANEL)
    if _has_values(columns, "loss/constraint_slack"):
        panels.append(SLACK_PANEL)
    fig = Figure(figsize=(PANEL_SIZE[0] * len(panels), PANEL_SIZE[1]), layout="constrained")
    axes = fig.subplots(1, len(panels))
    for ax, panel in zip(axes, panels):
        _draw_run_panel(ax, panel, columns, cost_limit)
        ax.set_title(panel)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    return fig


def _draw_run_panel(
    ax: Any, panel: str, columns: dict[str, list[float]], cost_limit: float | None
) -> None:
    """One panel of :func:`run_curves_figure`."""
    frames = columns["frames"]
    keys_of = dict(_PANELS)
    if panel in keys_of:
        for key in keys_of[panel]:
            if _has_values(columns, key):
                label = "test (deterministic)" if key.startswith("eval/") else "training"
                ax.plot(frames, columns[key], marker="o", markersize=3, label=label)
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
    elif panel == CALIBRATION_PANEL:
        for key, label, color, style in _CALIBRATION_LINES:
            if _has_values(columns, key):
                ax.plot(
                    frames,
                    columns[key],
                    color=color,
                    linestyle=style,
                    marker="o",
                    markersize=3,
                    label=label,
                )
    else:
        ax.plot(frames, columns["loss/constraint_slack"], color="C2", marker="o", markersize=3)
        ax.axhline(0.0, color="k", linestyle="--", linewidth=1)


def plot_run_curves(progress_csv: Path, out: Path, *, cost_limit: float | None = None) -> Path:
    """Return, cost, cost rate and cumulative training cost of one run against env steps
    (``progress.csv`` → PNG).

    Training curves are means over the episodes that ended in each epoch; test
    curves are the deterministic test episodes. A dashed line marks ``cost_limit``.
    Runs with a safety critic get two more panels (:func:`run_curves_figure`).
    """
    columns = read_progress(progress_csv)
    if not columns:
        raise ValueError(f"{progress_csv} has no rows yet")
    from wcsac_rl.evaluation.runs import display_text

    title = display_text(Path(progress_csv).parent.name)  # (a name that is not UTF-8 too)
    fig = run_curves_figure(columns, cost_limit=cost_limit, title=title)
    out = Path(out)
    fig.savefig(out, dpi=100)
    return out


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


def row_color(label: str) -> str:
    """A fixed colour per Table-1 row, the same in every figure."""
    from wcsac_rl.evaluation.runs import ROW_ORDER

    palette = ("C0", "C1", "C2", "C3", "C4", "C5", "C7", "C6", "C8", "C9")
    if label in ROW_ORDER:
        return palette[ROW_ORDER.index(label)]
    return palette[len(ROW_ORDER) + sum(map(ord, label)) % (len(palette) - len(ROW_ORDER))]


def _save(fig: Figure, out: Path) -> Path:
    """Write ``fig`` as a 256-colour palette PNG: these are line, box and scatter plots
    on white, so the palette keeps them visually the same at about a third of the
    RGBA file's size (what makes a report's figures viewable in a repository)."""
    from PIL import Image

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=DPI, format="png")
    buffer.seek(0)
    with Image.open(buffer) as image:
        palette = image.convert("RGB").quantize(
            colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
        )
    palette.save(out, format="png", optimize=True)
    return out


def plot_training_curves(
    rows: dict[str, list[dict[str, list[float]]]],
    out: Path,
    *,
    cost_limit: float | None = None,
    title: str = "Training curves",
) -> Path:
    """Figure 4: episodic return, episodic cost and cost rate against env steps.

    Args:
        rows: Table-1 row label → the ``read_progress`` columns of each seed's run.
            Each row is drawn as the mean over its seeds (line) ± one standard
            deviation (shaded), on the training-episode columns as in the paper.
        out: PNG path (``FIG4_SIZE`` × ``DPI`` pixels).
        cost_limit: the budget d, a dashed line on the cost panel.
        title: the figure's title.
    """
    from wcsac_rl.evaluation.metrics import curve_mean_std
    from wcsac_rl.evaluation.runs import row_name

    fig = Figure(figsize=FIG4_SIZE, layout="constrained")
    axes = fig.subplots(1, len(_CURVE_PANELS))
    for ax, (panel_title, key, ylabel) in zip(axes, _CURVE_PANELS):
        for label, runs in rows.items():
            curves = [(run["frames"], run[key]) for run in runs if key in run and "frames" in run]
            if not curves:
                continue
            x, mean, std, _ = curve_mean_std(curves)
            ok = ~np.isnan(mean)
            if not ok.any():
                continue
            color = row_color(label)
            seeds = f"{len(curves)} seed{'s' if len(curves) != 1 else ''}"
            ax.plot(
                x[ok],
                mean[ok],
                color=color,
                marker="o",
                markersize=2.5,
                label=f"{row_name(label)} ({seeds})",
            )
            ax.fill_between(x[ok], (mean - std)[ok], (mean + std)[ok], color=color, alpha=0.2)
        if key == "train/episode_cost" and cost_limit is not None:
            ax.axhline(
                cost_limit,
                color="k",
                linestyle="--",
                linewidth=1.2,
                label=f"budget d = {cost_limit:g}",
            )
        ax.set_title(panel_title)
        ax.set_xlabel("env steps")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.suptitle(f"{title} — mean ± std over seeds (training episodes)")
    return _save(fig, out)


def plot_cost_distribution(
    costs: dict[str, list[float]],
    out: Path,
    *,
    cost_limit: float,
    title: str = "Evaluation after training",
    ymax: float | None = None,
) -> Path:
    """Figure 6: (a) box plots of episodic cost, (b) proportion of episodes over budget.

    Args:
        costs: row label → the episodic costs of its test episodes (seeds pooled).
        out: PNG path (``FIG6_SIZE`` × ``DPI`` pixels).
        cost_limit: the budget d: dashed line in (a); (b) counts costs strictly above it.
        title: the figure's title.
        ymax: upper view limit of (a) (the paper clips it so d stays readable);
            ``None`` shows all the data.
    """
    from wcsac_rl.evaluation.metrics import exceedance_proportion
    from wcsac_rl.evaluation.runs import row_name

    labels = list(costs)
    names = [row_name(label) for label in labels]
    colors = [row_color(label) for label in labels]
    fig = Figure(figsize=FIG6_SIZE, layout="constrained")
    ax_box, ax_bar = fig.subplots(1, 2)
    if labels:
        box = ax_box.boxplot(
            [np.asarray(costs[label], dtype=np.float64) for label in labels],
            whis=(1, 99),
            showmeans=True,
            patch_artist=True,
            flierprops={"marker": ".", "markersize": 3, "alpha": 0.5},
            meanprops={"marker": "^", "markerfacecolor": "white", "markeredgecolor": "k"},
            medianprops={"color": "k"},
        )
        ax_box.set_xticks(range(1, len(labels) + 1), names)
        for patch, color in zip(box["boxes"], colors):
            patch.set_facecolor(color)
            patch.set_alpha(0.6)
        handles = [box["medians"][0], box["means"][0]]
        legend_labels = ["median", "mean"]
    else:
        handles, legend_labels = [], []
    line = ax_box.axhline(cost_limit, color="k", linestyle="--", linewidth=1.2)
    ax_box.legend(
        [*handles, line],
        [*legend_labels, f"budget d = {cost_limit:g}"],
        fontsize=8,
        title="box: quartiles; whiskers: 1st/99th pct.",
        title_fontsize=8,
    )
    if ymax is not None:
        ax_box.set_ylim(top=ymax)
    ax_box.set_title("(a) Episodic cost of the test episodes")
    ax_box.set_ylabel("episodic cost")
    ax_box.grid(axis="y", alpha=0.3)

    shares = [100.0 * exceedance_proportion(costs[label], cost_limit) for label in labels]
    bars = ax_bar.bar(range(len(labels)), shares, color=colors, alpha=0.8)
    ax_bar.bar_label(bars, labels=[f"{s:.1f}%" for s in shares], fontsize=8)
    ax_bar.set_xticks(range(len(labels)), names)
    ax_bar.set_ylim(0, max([*shares, 1.0]) * 1.15)
    ax_bar.set_title(f"(b) Budget exceedance: episodes with cost > d = {cost_limit:g}")
    ax_bar.set_ylabel("episodes over budget (%)")
    ax_bar.grid(axis="y", alpha=0.3)
    for ax in (ax_box, ax_bar):
        ax.tick_params(axis="x", labelrotation=15)
    fig.suptitle(title)
    return _save(fig, out)


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
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.2)
    ax.legend(handles=handles, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2)


def plot_trajectories(
    panels: list[tuple[str, dict[str, Any], list[Any]] | None],
    out: Path,
    *,
    title: str = "Trajectories of deterministic test episodes",
    columns: int = TRAJECTORY_COLUMNS,
) -> Path:
    """Figure 5: top-down robot paths, one panel per ``(title, layout, trajectories)``.

    Each panel draws the layout (placement area, hazards with their radius, goal,
    vases) and every trajectory (start ``o``, end ``X``, legend with its cost and
    return), from :func:`~wcsac_rl.evaluation.trajectories.collect_trajectories`.
    Panels fill rows of ``columns``; a ``None`` panel is left blank. Size: :func:`trajectory_figure_size` × ``DPI``.
    """
    if not any(panel is not None for panel in panels):
        raise ValueError("plot_trajectories needs at least one panel")
    if columns < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    fig = Figure(figsize=trajectory_figure_size(len(panels), columns), layout="constrained")
    cols = min(len(panels), columns)
    rows = math.ceil(len(panels) / cols)
    axes = np.asarray(fig.subplots(rows, cols, squeeze=False)).reshape(-1)
    for ax, panel in zip(axes, panels):
        if panel is None:
            ax.set_axis_off()
        else:
            panel_title, layout, trajectories = panel
            _draw_trajectories(ax, layout, trajectories, panel_title)
    for ax in axes[len(panels) :]:
        ax.set_axis_off()
    fig.suptitle(title)
    return _save(fig, out)
