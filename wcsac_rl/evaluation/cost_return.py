"""The cost-return trade-off of a report's rows: ``fig_cost_return.png``.

One point per Table-1 row at (EC, ER), its mean episodic cost and return over the
row's test episodes, with the 95 % seed-stratified bootstrap interval of each as error
bars (``EC_lo``/``EC_hi``, ``ER_lo``/``ER_hi`` of :func:`~wcsac_rl.evaluation.reporting.table1_rows`),
in the row's colour and marker of the report (:func:`~wcsac_rl.evaluation.plots.row_styles`);
the budget d a dashed vertical line, the side of it within budget shaded. A row up and
to the left of d earns more at a cost within budget: the trade-off at a glance.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from wcsac_rl.evaluation import plots
from wcsac_rl.evaluation.plots import RowStyle

__all__ = ["COST_RETURN_SIZE", "plot_cost_return"]

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
    """``fig_cost_return.png`` (see the module docstring) of Table 1's ``rows``.

    Args:
        rows: Table-1 rows (``label``, ``algorithm``, ``EC``, ``ER`` and their
            ``_lo``/``_hi`` interval ends).
        out: PNG path (:data:`COST_RETURN_SIZE` × ``DPI`` pixels).
        cost_limit: the budget d, the dashed vertical line.
        title: the figure's title.
        styles: each row's colour and marker (default: :func:`~wcsac_rl.evaluation.plots.row_styles`
            of ``rows``).
        formats: the files written (:func:`~wcsac_rl.evaluation.plots.save_figure`).
    """
    if not rows:
        raise ValueError("plot_cost_return needs at least one row")
    styles = plots.styles_for([row["label"] for row in rows], styles)
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
    plots.draw_literally(ax.set_title(title, fontsize=10))  # (run data: "$" as written)
    plots.draw_literally(fig.legend(loc="outside right upper", fontsize=8))  # beside the axes
    plots.save_figure(fig, out, formats=formats)
    return Path(out)
