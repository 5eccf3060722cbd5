"""Figures of the runs one by one (:mod:`~wcsac_rl.evaluation.run_report`).

* :func:`plot_run_values` — ``fig_runs.png``: one panel each for EC, C0.1 and ER, one dot
  per run (filled: held-out seed; hollow: in-sample), the row's IQM over runs (black
  diamond) with its 95 % bootstrap interval, the budget d dashed on the cost panels;
* :func:`plot_score_distribution` — ``fig_score_distribution.png``: the fraction of a row's
  runs with C0.1 <= x against x, one step curve per row marked at each of its runs, with a
  95 % bootstrap band over runs (rliable's score distribution, for a cost: higher is
  better); x is linear up to the budget d and logarithmic above it.

Built on ``matplotlib.figure.Figure`` (no pyplot), each row in its colour and marker of the
report (``styles``: :func:`~wcsac_rl.evaluation.plots.row_styles`), the names and titles
from run data drawn as written (:func:`~wcsac_rl.evaluation.plots.draw_literally`: a ``$``
in them is no formula), and written by :func:`~wcsac_rl.evaluation.plots.save_figure` (PNG
and PDF, no time stamp): the same runs give the same bytes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, NullLocator

from wcsac_rl.evaluation import plots
from wcsac_rl.evaluation.plots import RowStyle
from wcsac_rl.evaluation.run_statistics import cdf_band

__all__ = ["RUNS_PANEL_SIZE", "SCORE_SIZE", "plot_run_values", "plot_score_distribution"]

RUNS_PANEL_SIZE = (5.5, 5.0)  # inches per panel of fig_runs.png
SCORE_SIZE = (9.0, 4.5)  # inches: 900 × 450 px
_PANELS = (
    ("EC", "EC: mean episode cost"),
    ("C0.1", "C0.1: CVaR$_{0.1}$ of episode cost"),
    ("ER", "ER: mean episode return"),
)
_SPREAD = 0.25  # half the width over which a row's dots are spread


def _rows(stats: Any) -> list[str]:
    return list(dict.fromkeys(run["label"] for run in stats.runs))


def _write(fig: Figure, out: Path, formats: Sequence[str]) -> Path:
    """:func:`~wcsac_rl.evaluation.plots.save_figure`, returning ``out``."""
    plots.save_figure(fig, out, formats=formats)
    return Path(out)


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
    colour and marker (default: :func:`~wcsac_rl.evaluation.plots.row_styles` of its
    rows); ``formats``: the files written."""
    labels = _rows(stats)
    by_label = {row["label"]: row for row in stats.rows}
    names = {run["label"]: run["algorithm"] for run in stats.runs}
    styles = plots.styles_for(labels, styles)
    fig = Figure(
        figsize=(RUNS_PANEL_SIZE[0] * len(_PANELS), RUNS_PANEL_SIZE[1]), layout="constrained"
    )
    axes = fig.subplots(1, len(_PANELS))
    for ax, (metric, panel_title) in zip(axes, _PANELS):
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
        plots.set_row_ticks(ax, [names[label] for label in labels])
        ax.set_xlim(-0.6, len(labels) - 0.4)
        ax.set_title(panel_title)
        ax.grid(axis="y", alpha=0.3)
    _legend(fig, stats.cost_limit)
    plots.draw_literally(fig.suptitle(f"Runs one by one — {title}"))  # (names from run data)
    return _write(fig, out, formats)


def _legend(fig: Figure, cost_limit: float) -> None:
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
    """``fig_score_distribution.png`` (see the module docstring); ``styles`` and
    ``formats`` as for :func:`plot_run_values`."""
    values = np.array([run["C0.1"] for run in stats.runs], dtype=np.float64)
    right = max(float(values.max()), float(stats.cost_limit)) * 1.05 or 1.0
    grid = np.unique(np.concatenate([[0.0, right], values, [float(stats.cost_limit)]]))
    fig = Figure(figsize=SCORE_SIZE, layout="constrained")
    ax = fig.subplots()
    styles = plots.styles_for(_rows(stats), styles)
    for label in _rows(stats):
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
    plots.draw_literally(fig.legend(fontsize=8, loc="outside right upper"))  # (rows' names)
    plots.draw_literally(ax.set_title(f"Score distribution over runs — {title}", fontsize=10))
    return _write(fig, out, formats)
