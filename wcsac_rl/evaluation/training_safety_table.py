"""The report's training-safety table (``training_safety.md``, ``.csv``, ``.tex``).

How safely each Table-1 row *trained* (Table 1 judges its final policy): per row, each
seed's and the mean over seeds of the numbers :mod:`~wcsac_rl.training.training_safety`
defines from the run's ``progress.csv`` (docs/reproduce.md lists them).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from wcsac_rl.evaluation.latex import (
    csv_text,
    latex_path,
    markdown_cell,
    markdown_table,
    markdown_text,
    markdown_to_latex,
)
from wcsac_rl.evaluation.runs import env_title, row_name, row_sort_key
from wcsac_rl.training.training_safety import WARMUP_FRAMES, training_safety

__all__ = [
    "TRAINING_SAFETY_CSV",
    "TRAINING_SAFETY_FILES",
    "TRAINING_SAFETY_MD",
    "TRAINING_SAFETY_TEX",
    "training_safety_csv",
    "training_safety_files",
    "training_safety_markdown",
    "training_safety_rows",
]

TRAINING_SAFETY_MD = "training_safety.md"
TRAINING_SAFETY_CSV = "training_safety.csv"
TRAINING_SAFETY_TEX = latex_path(TRAINING_SAFETY_MD)
TRAINING_SAFETY_FILES = (TRAINING_SAFETY_MD, TRAINING_SAFETY_CSV, TRAINING_SAFETY_TEX)

METRICS = (
    "cumulative_cost",
    "epochs_over_limit",
    "epochs_over_limit_after_warmup",
    "peak_epoch_cost",
    "safe_from_frames",
    "frames",
    "epochs",
)
"""Per run, from its :class:`~wcsac_rl.training.training_safety.TrainingSafety`."""

CSV_COLUMNS = (
    "label",
    "algorithm",
    "env",
    "cost_limit",
    "warmup_frames",
    "seeds",
    "seed_list",
    *METRICS,
    *(f"{key}_per_seed" for key in METRICS),
)


@dataclass
class _Run:
    seed: int
    values: dict[str, float]


def _run_values(progress: dict[str, list[float]], cost_limit: float, warmup: int) -> dict:
    safety = training_safety(progress, cost_limit, warmup_frames=warmup)
    return {key: getattr(safety, key) for key in METRICS}  # counts as ints, the rest floats


def training_safety_rows(
    runs: Sequence[Any],
    cost_limit: float,
    *,
    env: str | None = None,
    warmup_frames: int = WARMUP_FRAMES,
    warn: Callable[[str], None] = print,
) -> list[dict[str, Any]]:
    """One row per ``algo.label`` in Table 1's order: the mean over seeds of each of
    :data:`METRICS` (NaN if one seed's is NaN: a seed that ended over d has no "≤ d for
    good from") and ``<metric>_per_seed``, the seeds' values in seed order.

    ``runs`` are the report's run records (``label``, ``seed``, ``progress``: the
    ``read_progress`` columns, ``directory``); a run whose ``progress.csv`` lacks the
    cost columns is left out with a ``warn``.
    """
    by_label: dict[str, list[_Run]] = defaultdict(list)
    for run in runs:
        try:
            values = _run_values(run.progress, cost_limit, warmup_frames)
        except ValueError as err:
            warn(f"training safety: skipped {run.directory}: {err}")
            continue
        by_label[run.label].append(_Run(int(run.seed), values))
    rows = []
    for label in sorted(by_label, key=row_sort_key):
        seeds = sorted(by_label[label], key=lambda r: r.seed)
        row: dict[str, Any] = {
            "label": label,
            "algorithm": row_name(label),
            "env": env,
            "cost_limit": cost_limit,
            "warmup_frames": warmup_frames,
            "seeds": len(seeds),
            "seed_list": " ".join(str(r.seed) for r in seeds),
        }
        for key in METRICS:
            per_seed = [r.values[key] for r in seeds]
            row[key] = sum(per_seed) / len(per_seed)
            row[f"{key}_per_seed"] = per_seed
        rows.append(row)
    return rows


def training_safety_csv(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as CSV: full float reprs, per-seed values space-separated."""
    per_seed = [f"{key}_per_seed" for key in METRICS]
    cells = ({**row, **{k: " ".join(map(repr, row[k])) for k in per_seed}} for row in rows)
    return csv_text(cells, CSV_COLUMNS, lineterminator="\r\n")


def _cell(row: dict[str, Any], key: str, text: Callable[[float], str]) -> str:
    """``mean (seed / seed ...)``, or the one seed's value."""
    per_seed = row[f"{key}_per_seed"]
    if len(per_seed) == 1:
        return text(per_seed[0])
    return f"{text(row[key])} ({' / '.join(text(v) for v in per_seed)})"


def _safe_from_cell(row: dict[str, Any]) -> str:
    """:func:`_cell` of ``safe_from_frames``: "–" for a seed in which no training episode
    finished (its peak is NaN: nothing was measured), "never" where the last epoch was
    over d."""
    peaks = row["peak_epoch_cost_per_seed"]
    texts = [
        "–" if math.isnan(peak) else _frames_text(frames)
        for frames, peak in zip(row["safe_from_frames_per_seed"], peaks, strict=True)
    ]
    if len(texts) == 1:
        return texts[0]
    mean = "–" if all(math.isnan(p) for p in peaks) else _frames_text(row["safe_from_frames"])
    return f"{mean} ({' / '.join(texts)})"


def _frames_text(frames: float) -> str:
    return "never" if math.isnan(frames) else f"{_count_text(frames / 1000)} k"


def _count_text(value: float) -> str:
    return f"{value:g}" if value == int(value) else f"{value:.1f}"


def training_safety_markdown(
    rows: Sequence[dict[str, Any]], env: str | None, cost_limit: float
) -> str:
    """The table as Markdown, each cell the mean over seeds (the seeds' values, in seed
    order, in brackets), with a legend of the columns below it."""
    warmup = _frames_text(rows[0]["warmup_frames"]) if rows else _frames_text(WARMUP_FRAMES)
    header = ["Algorithm", "cumulative cost", "epochs > d", f"after {warmup}", "peak epoch"]
    header += ["≤ d for good from", "frames (seeds)"]
    lines = [
        f"# Training safety — {markdown_text(env_title(env)) if env else '?'}, budget "
        f"d = {cost_limit:g}",
        "",
    ]
    body = [
        [
            markdown_cell(row["algorithm"]),
            _cell(row, "cumulative_cost", lambda v: f"{v:.0f}"),
            _cell(row, "epochs_over_limit", _count_text),
            _cell(row, "epochs_over_limit_after_warmup", _count_text),
            _cell(row, "peak_epoch_cost", lambda v: "–" if math.isnan(v) else f"{v:.2f}"),
            _safe_from_cell(row),
            f"{_frames_text(max(row['frames_per_seed']))} ({row['seeds']})",
        ]
        for row in rows
    ]
    lines += markdown_table(header, "l" + "r" * (len(header) - 1), body)
    legend = _LEGEND.format(d=f"{cost_limit:g}", warmup=warmup)
    if any(math.isnan(p) for row in rows for p in row["peak_epoch_cost_per_seed"]):
        legend += " –: no training episode finished in the run (nothing was measured)."
    lines += ["", legend, ""]
    return "\n".join(lines)


_LEGEND = (
    "Training episodes, from each run's progress.csv (one epoch per row); each cell is the "
    "mean over seeds, the seeds' own values in brackets (in the order of "
    "training_safety.csv's seed_list). Cumulative cost: the sum of every per-step training cost "
    "(all envs, all frames). Epochs > d: epochs whose mean training-episode cost is "
    "strictly above d = {d} (an epoch in which no episode finished is not counted); "
    "after {warmup}: those ending after the first {warmup} frames. Peak epoch: the "
    "highest mean training-episode cost of an epoch. ≤ d for good from: the frames "
    "after which every epoch stayed ≤ d (never: the last epoch was over d; the mean is "
    "then never too). Definitions: wcsac_rl/training/training_safety.py."
)


def training_safety_files(
    runs: Sequence[Any], env: str | None, cost_limit: float, warn: Callable[[str], None]
) -> dict[str, str]:
    """What the report writes: file name → text of :data:`TRAINING_SAFETY_FILES`."""
    rows = training_safety_rows(runs, cost_limit, env=env, warn=warn)
    markdown = training_safety_markdown(rows, env, cost_limit)
    return {
        TRAINING_SAFETY_MD: markdown,
        TRAINING_SAFETY_CSV: training_safety_csv(rows),
        TRAINING_SAFETY_TEX: markdown_to_latex(markdown),
    }
