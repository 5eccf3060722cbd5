"""The run's own record: ``progress.csv`` (one row per epoch) and per-epoch accumulators."""

from __future__ import annotations

import csv
import io
import math
import sys
from collections.abc import Mapping
from pathlib import Path

import torch
from tensordict import TensorDictBase

from wcsac_rl.training.run_dir import replace_text

__all__ = ["EpisodeTracker", "LossMeans", "ProgressWriter", "read_progress"]


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
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=self.fieldnames, restval="")
        writer.writeheader()
        writer.writerows(rows)
        replace_text(self.path, buf.getvalue())


def _float(text: str | None) -> float:
    """A cell's number (NaN for an empty cell); ``ValueError`` for anything else."""
    return float(text) if text not in ("", None) else math.nan


def read_progress(path: Path, *, warn: bool = True) -> dict[str, list[float]]:
    """Columns of a ``progress.csv`` as lists of floats (NaN for empty cells).

    Only whole rows are read. A row a killed process left half-written — the file's
    last line without its line end (a number cut short), fewer or more cells than the
    header, a cell that is not a number — is skipped, with one warning line on stderr
    (``warn=False``: silently).
    """
    path = Path(path)
    with path.open(newline="", errors="replace") as f:
        text = f.read()
    lines = list(csv.reader(io.StringIO(text)))
    if len(lines) < 2:
        return {}
    header, body = lines[0], lines[1:]
    if not text.endswith(("\n", "\r")):  # the last row was being written when it stopped
        body = body[:-1]
    kept: list[list[float]] = []
    for row in body:
        try:
            if len(row) == len(header):
                kept.append([_float(cell) for cell in row])
        except ValueError:
            pass
    skipped = len(lines) - 1 - len(kept)
    if skipped and warn:
        print(
            f"warning: {path}: skipped {skipped} incomplete row(s) (a process stopped while "
            "writing it); the whole rows are read",
            file=sys.stderr,
        )
    return {key: [row[i] for row in kept] for i, key in enumerate(header)} if kept else {}


class LossMeans:
    """Epoch means of the loss outputs, summed batch by batch (float64, on their device):
    each batch's outputs are summed at once and dropped, never kept for the epoch (their
    tiny tensors would pin the heap: docs/performance.md, "Memory per run").
    """

    def __init__(self, keys: list[str]) -> None:
        self.keys = list(keys)
        self.reset()

    def reset(self) -> None:
        self.total: TensorDictBase | None = None
        self.count = 0

    def add(self, outputs: list[TensorDictBase]) -> None:
        if not outputs or not self.keys:
            return
        summed = torch.stack([td.select(*self.keys) for td in outputs]).double().sum(0)
        self.total = summed if self.total is None else self.total + summed
        self.count += len(outputs)

    def means(self) -> dict[str, float]:
        """``loss/<key>`` → the mean over the outputs added since :meth:`reset` (NaN: none)."""
        if self.total is None:
            return {f"loss/{key}": math.nan for key in self.keys}
        return {f"loss/{key}": float(self.total[key]) / self.count for key in self.keys}


class EpisodeTracker:
    """Training-episode statistics from collector batches (``RewardSum``/``CostSum`` keys).

    Per epoch: returns, costs and lengths of the episodes that finished, and which of
    them reached a goal (``goals``: an env with goals that writes ``goal_reached``;
    ``train/goal_rate``, the per-epoch sign that the task is being learned, NaN
    otherwise); over the whole run: frames and total cost, for the paper's cost rate. A
    batch's last dimension is time (TorchRL's collectors), the ones before it the envs.
    """

    def __init__(self, frames: int = 0, total_cost: float = 0.0, goals: bool = True) -> None:
        self.frames = frames
        self.total_cost = total_cost
        self.goals = goals
        self._goal_seen: torch.Tensor | None = None  # per env: a goal in its current episode
        self.reset_epoch()

    def reset_epoch(self) -> None:
        # Python numbers, not tensors: small tensors kept alive for a whole epoch sit
        # between the update's activations on the heap and keep it from being reused
        self.returns: list[float] = []
        self.costs: list[float] = []
        self.lengths: list[int] = []
        self.reached: list[bool] = []  # per finished episode (an env with goals)
        self.failures = 0

    def add(self, batch: TensorDictBase) -> None:
        nxt = batch.get("next")
        done = nxt.get("done").squeeze(-1)
        self.returns += nxt.get("episode_reward").squeeze(-1)[done].tolist()
        self.costs += nxt.get("episode_cost").squeeze(-1)[done].tolist()
        self.lengths += nxt.get("step_count").squeeze(-1)[done].tolist()
        goal = nxt.get("goal_reached", None) if self.goals else None
        if goal is not None:
            self._add_goals(goal.reshape(done.shape).bool().cpu(), done.cpu())
        failure = nxt.get("numerical_failure", None)
        if failure is not None:
            self.failures += int(failure.sum())
        self.frames += batch.numel()
        self.total_cost += float(nxt.get("cost").sum())

    def _add_goals(self, goal: torch.Tensor, done: torch.Tensor) -> None:
        """Whether each episode that finished in the batch reached a goal at any of its
        steps, those before the batch included (``goal``, ``done``: ``[*envs, time]``)."""
        if goal.dim() == 0 or goal.numel() == 0:
            return
        seen = self._goal_seen
        if seen is None or seen.shape != goal.shape[:-1]:
            seen = torch.zeros(goal.shape[:-1], dtype=torch.bool)
        seen = seen.clone()
        for t in range(goal.shape[-1]):
            seen |= goal[..., t]
            ended = done[..., t]
            if ended.any():
                self.reached += seen[ended].tolist()
                seen[ended] = False
        self._goal_seen = seen

    def epoch_metrics(self) -> dict[str, float]:
        # float32 means, as the sums were (the same numbers as when these were tensors)
        returns = torch.tensor(self.returns, dtype=torch.float32)
        costs = torch.tensor(self.costs, dtype=torch.float32)
        lengths = torch.tensor(self.lengths, dtype=torch.int64)
        n = len(self.returns)

        def mean(x: torch.Tensor) -> float:
            return float(x.float().mean()) if n else math.nan

        return {
            "train/episodes": n,
            "train/episode_return": mean(returns),
            "train/episode_cost": mean(costs),
            "train/episode_length": mean(lengths),
            "train/cost_rate": self.total_cost / self.frames if self.frames else math.nan,
            "train/numerical_failures": self.failures,
            "train/goal_rate": sum(self.reached) / len(self.reached) if self.reached else math.nan,
        }
