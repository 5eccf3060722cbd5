"""Matplotlib figures of training runs.

Figures are built with ``matplotlib.figure.Figure`` (no pyplot), so they render
headless and never change the caller's matplotlib backend.
"""

from __future__ import annotations

import math
from pathlib import Path

from matplotlib.figure import Figure

from wcsac_rl.training.progress import read_progress

__all__ = ["plot_run_curves"]

_PANELS = (
    ("episode return", ("train/episode_return", "eval/episode_return")),
    ("episode cost", ("train/episode_cost", "eval/episode_cost")),
    ("cost rate", ("train/cost_rate",)),
)


def plot_run_curves(progress_csv: Path, out: Path, *, cost_limit: float | None = None) -> Path:
    """Return, cost and cost rate of one run against env steps (``progress.csv`` → PNG).

    Training curves are means over the episodes that ended in each epoch; test
    curves are the deterministic test episodes. A dashed line marks ``cost_limit``.
    """
    columns = read_progress(progress_csv)
    if not columns:
        raise ValueError(f"{progress_csv} has no rows yet")
    frames = columns["frames"]
    fig = Figure(figsize=(12, 3.6), layout="constrained")
    axes = fig.subplots(1, len(_PANELS))
    for ax, (title, keys) in zip(axes, _PANELS):
        for key in keys:
            values = columns.get(key)
            if values is None or all(math.isnan(v) for v in values):
                continue
            label = "test (deterministic)" if key.startswith("eval/") else "training"
            ax.plot(frames, values, marker="o", markersize=3, label=label)
        if title == "episode cost" and cost_limit is not None:
            ax.axhline(
                cost_limit,
                color="k",
                linestyle="--",
                linewidth=1,
                label=f"limit d = {cost_limit:g}",
            )
        ax.set_title(title)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.suptitle(Path(progress_csv).parent.name, fontsize=10)
    out = Path(out)
    fig.savefig(out, dpi=100)
    return out
