"""The run's own record: ``progress.csv`` (one row per epoch) and per-epoch accumulators."""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping
from pathlib import Path

import torch
from tensordict import TensorDictBase

__all__ = ["EpisodeTracker", "ProgressWriter", "read_progress"]


class ProgressWriter:
    """Append one row per epoch to a CSV file.

    Appends to an existing file (a resumed run). A row with a column the file does not
    have yet (a timer that first ran in a later epoch) rewrites the file once with the
    wider header, earlier rows getting empty cells there.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.fieldnames: list[str] | None = None
        if self.path.exists() and self.path.stat().st_size > 0:
            with self.path.open(newline="") as f:
                self.fieldnames = next(csv.reader(f))

    def write(self, row: Mapping[str, float | int | str]) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.fieldnames is None:
            self.fieldnames = list(row)
            with self.path.open("w", newline="") as f:
                csv.DictWriter(f, fieldnames=self.fieldnames).writeheader()
        new_columns = [key for key in row if key not in self.fieldnames]
        if new_columns:
            self._widen(new_columns)
        with self.path.open("a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fieldnames)
            writer.writerow({k: row.get(k, float("nan")) for k in self.fieldnames})

    def _widen(self, new_columns: list[str]) -> None:
        with self.path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        self.fieldnames = [*self.fieldnames, *new_columns]
        tmp = self.path.with_suffix(".csv.tmp")
        with tmp.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fieldnames, restval="")
            writer.writeheader()
            writer.writerows(rows)
        tmp.replace(self.path)


def read_progress(path: Path) -> dict[str, list[float]]:
    """Columns of a ``progress.csv`` as lists of floats (NaN for empty cells)."""
    with Path(path).open(newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    columns: dict[str, list[float]] = {key: [] for key in rows[0]}
    for row in rows:
        for key in columns:
            value = row.get(key, "")
            columns[key].append(float(value) if value not in ("", None) else math.nan)
    return columns


class EpisodeTracker:
    """Training-episode statistics from collector batches (``RewardSum``/``CostSum`` keys).

    Per epoch: returns, costs and lengths of the episodes that finished; over the
    whole run: frames and total cost, for the paper's cost rate.
    """

    def __init__(self, frames: int = 0, total_cost: float = 0.0) -> None:
        self.frames = frames
        self.total_cost = total_cost
        self.reset_epoch()

    def reset_epoch(self) -> None:
        self.returns: list[torch.Tensor] = []
        self.costs: list[torch.Tensor] = []
        self.lengths: list[torch.Tensor] = []
        self.failures = 0

    def add(self, batch: TensorDictBase) -> None:
        nxt = batch.get("next")
        done = nxt.get("done").squeeze(-1)
        self.returns.append(nxt.get("episode_reward").squeeze(-1)[done])
        self.costs.append(nxt.get("episode_cost").squeeze(-1)[done])
        self.lengths.append(nxt.get("step_count").squeeze(-1)[done])
        failure = nxt.get("numerical_failure", None)
        if failure is not None:
            self.failures += int(failure.sum())
        self.frames += batch.numel()
        self.total_cost += float(nxt.get("cost").sum())

    def epoch_metrics(self) -> dict[str, float]:
        returns = torch.cat(self.returns) if self.returns else torch.zeros(0)
        costs = torch.cat(self.costs) if self.costs else torch.zeros(0)
        lengths = torch.cat(self.lengths) if self.lengths else torch.zeros(0)
        n = int(returns.numel())

        def mean(x: torch.Tensor) -> float:
            return float(x.float().mean()) if n else math.nan

        return {
            "train/episodes": n,
            "train/episode_return": mean(returns),
            "train/episode_cost": mean(costs),
            "train/episode_length": mean(lengths),
            "train/cost_rate": self.total_cost / self.frames if self.frames else math.nan,
            "train/numerical_failures": self.failures,
        }
