"""Safety during training: what a run's training episodes cost, epoch by epoch.

The one definition of the training-safety numbers, used by the trainer (its running
``progress.csv`` columns) and by the report (``training_safety.md``). An *epoch* is
one ``progress.csv`` row; its cost is ``train/episode_cost``, the mean cost of the
training episodes that finished in it. With ``d`` the cost limit:

* **cumulative training cost**: the sum of every per-step training cost so far
  (all envs, all frames), ``train/cumulative_cost`` — for runs logged before that
  column, ``train/cost_rate × frames``, the same number. It is the per-step sum, not
  the sum of finished episodes' costs: it includes the episodes still running at the
  last frame. On the committed 200 k-frame StaticEnv runs the two differ by 0–104
  (≤ 0.3 %), on the DynamicEnv runs by 0;
* **epochs over d**: epochs whose mean training-episode cost is strictly above ``d``
  (as Table 1's "over budget"); and the same count over the epochs that end after
  ``warmup_frames`` (default 50 k: with 10 k-frame epochs, the first one counted is
  the one ending at 60 k frames);
* **peak epoch cost**: the highest epoch cost;
* **≤ d for good from**: the frames at the end of the last epoch over ``d`` (0 if
  none was): from there on every epoch stayed ≤ ``d``. NaN when the last epoch is
  over ``d`` (the run ended unsafe).

An epoch in which no training episode finished (``train/episodes`` 0, cost NaN) is
neither over ``d`` nor a peak. A run none of whose epochs had a finished episode has
a NaN peak and NaN "≤ d for good from" (nothing is known).

Example:
    >>> columns = {"frames": [100, 200, 300], "train/episode_cost": [30.0, float("nan"), 5.0],
    ...            "train/episodes": [2, 0, 2], "train/cost_rate": [0.5, 0.4, 0.3]}
    >>> s = training_safety(columns, cost_limit=15.0, warmup_frames=150)
    >>> s.cumulative_cost, s.epochs_over_limit, s.epochs_over_limit_after_warmup
    (90.0, 1, 0)
    >>> s.peak_epoch_cost, s.safe_from_frames
    (30.0, 100.0)
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

from wcsac_rl.objectives.budget import validate_cost_limit

__all__ = ["WARMUP_FRAMES", "TrainingSafety", "cumulative_cost", "training_safety"]

WARMUP_FRAMES = 50_000
"""Frames at the start of a run whose epochs :attr:`TrainingSafety.epochs_over_limit_after_warmup`
does not count (the random warm-up and first learning)."""

REQUIRED_COLUMNS = ("frames", "train/episode_cost")


@dataclass
class TrainingSafety:
    """The training-safety numbers of the epochs seen so far (:meth:`add_epoch`).

    The trainer keeps one per run (in its checkpoint: :meth:`state_dict`) and logs
    :meth:`columns` each epoch; :func:`training_safety` folds a finished run's
    ``progress.csv`` columns through one.
    """

    cost_limit: float
    warmup_frames: int = WARMUP_FRAMES
    epochs: int = 0
    frames: float = 0.0
    cumulative_cost: float = 0.0
    epochs_over_limit: int = 0
    epochs_over_limit_after_warmup: int = 0
    peak_epoch_cost: float = math.nan
    last_over_frames: float = 0.0  # end of the last epoch over d (0: none yet)
    last_epoch_over: bool = False

    def __post_init__(self) -> None:
        self.cost_limit = validate_cost_limit(self.cost_limit)

    def add_epoch(self, frames: float, episode_cost: float, cumulative: float) -> None:
        """One epoch that ended at ``frames``: its mean training-episode cost (NaN when no
        episode finished) and the cumulative training cost at its end."""
        self.epochs += 1
        self.frames = float(frames)
        self.cumulative_cost = float(cumulative)
        over = math.isfinite(episode_cost) and episode_cost > self.cost_limit
        self.last_epoch_over = over
        if math.isfinite(episode_cost) and not episode_cost <= self.peak_epoch_cost:
            self.peak_epoch_cost = float(episode_cost)  # (NaN peak: the first one)
        if over:
            self.epochs_over_limit += 1
            self.epochs_over_limit_after_warmup += int(frames > self.warmup_frames)
            self.last_over_frames = float(frames)

    @property
    def safe_from_frames(self) -> float:
        """Frames from which every epoch stayed ≤ d (see the module's docstring)."""
        if self.last_epoch_over or math.isnan(self.peak_epoch_cost):
            return math.nan
        return self.last_over_frames

    def columns(self) -> dict[str, float]:
        """The running ``progress.csv`` columns: cumulative cost, epochs over d, peak."""
        return {
            "train/cumulative_cost": self.cumulative_cost,
            "train/epochs_over_limit": self.epochs_over_limit,
            "train/peak_epoch_cost": self.peak_epoch_cost,
        }

    def state_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> TrainingSafety:
        return cls(**state)


def cumulative_cost(columns: Mapping[str, Sequence[float]]) -> list[float]:
    """Per row, the cumulative training cost: ``train/cumulative_cost`` where logged, else
    ``train/cost_rate × frames`` (runs, or rows, from before that column)."""
    frames = columns["frames"]
    logged = columns.get("train/cumulative_cost", [math.nan] * len(frames))
    rates = columns.get("train/cost_rate", [math.nan] * len(frames))
    return [c if math.isfinite(c) else r * f for c, r, f in zip(logged, rates, frames)]


def _check_columns(columns: Mapping[str, Sequence[float]]) -> None:
    missing = [key for key in REQUIRED_COLUMNS if key not in columns]
    if not ("train/cumulative_cost" in columns or "train/cost_rate" in columns):
        missing.append("train/cumulative_cost or train/cost_rate")
    if missing:
        raise ValueError(f"progress columns lack {', '.join(missing)} (got {sorted(columns)})")
    lengths = {key: len(values) for key, values in columns.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"progress columns differ in length: {lengths}")


def training_safety(
    columns: Mapping[str, Sequence[float]],
    cost_limit: float,
    *,
    warmup_frames: int = WARMUP_FRAMES,
) -> TrainingSafety:
    """The training-safety numbers of a run from its ``read_progress`` columns (one entry
    per epoch): ``frames``, ``train/episode_cost``, ``train/episodes`` (optional: a NaN
    cost already marks an epoch without episodes) and ``train/cumulative_cost`` or
    ``train/cost_rate``.

    Raises:
        ValueError: a negative or non-finite ``cost_limit``, a missing column, or
            columns of different lengths.
    """
    safety = TrainingSafety(cost_limit, warmup_frames=int(warmup_frames))
    _check_columns(columns)
    episodes = columns.get("train/episodes", [math.nan] * len(columns["frames"]))
    for frames, cost, n, total in zip(
        columns["frames"], columns["train/episode_cost"], episodes, cumulative_cost(columns)
    ):
        safety.add_epoch(frames, cost if n != 0 else math.nan, total)
    return safety
