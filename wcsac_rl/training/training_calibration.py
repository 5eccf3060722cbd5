"""The safety critic's reading on the training episodes, against what they then cost.

Every collected batch is read by the safety critic as it is collected (Γ_α at the state
and action taken), and once an episode ends its realised discounted cost-to-go
``G_t = Σ_{k≥t} γ_c^{k−t} c_k`` is set beside it; per epoch, the ``train_calib/*``
columns compare the two (docs/training.md, "The critic on the training episodes", has
the columns and how to read them). The realised sums stop where the episode ends (a
time limit too), as in :mod:`~wcsac_rl.rollouts.critic_calibration`; the readings
during the random warm-up are of the critic before any update.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from wcsac_rl.objectives.risk import empirical_cvar
from wcsac_rl.objectives.start_states import StartStateBuffer
from wcsac_rl.rollouts.critic_calibration import (
    _cost_key,
    calibration_keys,
    discounted_cost_to_go,
)

__all__ = ["TRAINING_CALIBRATION_KEYS", "TRAIN_PREFIX", "TrainingCalibration"]

TRAIN_PREFIX = "train_calib/"
TRAINING_CALIBRATION_KEYS: tuple[str, ...] = tuple(
    TRAIN_PREFIX + name
    for name in (
        *("episodes", "start_cvar", "start_cost_to_go", "start_realised_cvar", "start_ratio"),
        *("over_episodes", "over_cvar", "over_cost_to_go", "over_ratio"),
    )
)
"""The ``progress.csv`` columns of :meth:`TrainingCalibration.epoch_metrics`, in order
(docs/training.md, "The critic on the training episodes", says what each is)."""


def _ratio(numerator: float, denominator: float) -> float:
    if denominator == 0 or math.isnan(numerator) or math.isnan(denominator):
        return math.nan
    return numerator / denominator


class TrainingCalibration:
    """Reads each collected batch with a loss's safety critic and keeps, per epoch, the
    readings and realised cost-to-go of the training episodes (see the module).

    Args:
        loss: a loss with ``safety_estimates`` (``WCSACLoss``, ``SACLagLoss``): its
            ``cvar`` is the reading, its ``cost_gamma`` the discount of the realised sums
            and its ``risk_level`` that of ``start_realised_cvar``.
        cost_limit: ``d``, the episodic cost budget an episode is "over".

    :meth:`add` takes a collector batch, ``[time]`` or ``[num_envs, time]``, with
    ``("next", "done")``, the cost and ``step_count`` (or ``is_init``) beside what the
    critic reads; an episode running over several batches is joined across them.
    :meth:`epoch_metrics` returns the epoch's :data:`TRAINING_CALIBRATION_KEYS` and
    starts the next epoch; :meth:`state_dict` is the epoch's episodes so far (the
    episodes still running are not kept: a resumed run starts new ones).
    """

    def __init__(self, loss: Any, *, cost_limit: float) -> None:
        self.loss = loss
        self.cost_limit = float(cost_limit)
        self.gamma = float(loss.cost_gamma)
        self.risk_level = float(loss.risk_level)
        self.read_keys = [k for k in calibration_keys(loss) if k != _cost_key(loss)]
        self.cost_key = _cost_key(loss)
        self._running: dict[int, tuple[list[float], list[float]] | None] = {}
        self.reset_epoch()

    def reset_epoch(self) -> None:
        # Python floats (one per episode; sums over the over-d episodes' steps)
        self.start_readings: list[float] = []
        self.start_costs_to_go: list[float] = []
        self.over_episodes = 0
        self.over_steps = 0
        self.over_reading_sum = 0.0
        self.over_cost_to_go_sum = 0.0

    def add(self, batch: TensorDictBase) -> None:
        """Read ``batch`` with the critic and close the episodes that end in it."""
        if batch.ndim == 0:
            raise ValueError("TrainingCalibration.add expects a batch of steps, got a scalar")
        rows = batch.reshape(1, -1) if batch.ndim == 1 else batch.reshape(-1, batch.shape[-1])
        with torch.no_grad():
            flat = rows.reshape(-1).select(*self.read_keys)
            reading = self.loss.safety_estimates(flat).get("cvar")
        reading = reading.detach().to("cpu", torch.float64).reshape(rows.shape).numpy()
        cost = rows.get(self.cost_key).detach().to("cpu", torch.float64)
        cost = cost.reshape(rows.shape).numpy()
        done = rows.get(("next", "done")).reshape(rows.shape).cpu().numpy()
        starts = StartStateBuffer.start_mask(rows).reshape(rows.shape).cpu().numpy()
        for env in range(rows.shape[0]):
            for t in range(rows.shape[1]):
                if starts[env, t]:
                    self._running[env] = ([], [])
                episode = self._running.get(env)
                if episode is not None:
                    episode[0].append(float(reading[env, t]))
                    episode[1].append(float(cost[env, t]))
                if done[env, t]:
                    if episode is not None:
                        self._close(*episode)
                    self._running[env] = None

    def _close(self, readings: list[float], costs: list[float]) -> None:
        cost_to_go = discounted_cost_to_go(costs, self.gamma)
        self.start_readings.append(readings[0])
        self.start_costs_to_go.append(float(cost_to_go[0]))
        if math.fsum(costs) > self.cost_limit:
            self.over_episodes += 1
            self.over_steps += len(costs)
            self.over_reading_sum += math.fsum(readings)
            self.over_cost_to_go_sum += float(np.sum(cost_to_go))

    def epoch_metrics(self) -> dict[str, float]:
        """The epoch's :data:`TRAINING_CALIBRATION_KEYS` (then a new epoch begins)."""
        n = len(self.start_readings)
        metrics = dict.fromkeys(TRAINING_CALIBRATION_KEYS, math.nan)
        metrics[TRAIN_PREFIX + "episodes"] = n
        metrics[TRAIN_PREFIX + "over_episodes"] = self.over_episodes
        if n:
            start = {
                "start_cvar": math.fsum(self.start_readings) / n,
                "start_cost_to_go": math.fsum(self.start_costs_to_go) / n,
                "start_realised_cvar": empirical_cvar(self.start_costs_to_go, self.risk_level),
            }
            start["start_ratio"] = _ratio(start["start_cvar"], start["start_realised_cvar"])
            metrics.update({TRAIN_PREFIX + k: v for k, v in start.items()})
        if self.over_steps:
            over_cvar = self.over_reading_sum / self.over_steps
            over_cost_to_go = self.over_cost_to_go_sum / self.over_steps
            metrics[TRAIN_PREFIX + "over_cvar"] = over_cvar
            metrics[TRAIN_PREFIX + "over_cost_to_go"] = over_cost_to_go
            metrics[TRAIN_PREFIX + "over_ratio"] = _ratio(over_cvar, over_cost_to_go)
        self.reset_epoch()
        return metrics

    def state_dict(self) -> dict[str, Any]:
        return {
            "start_readings": list(self.start_readings),
            "start_costs_to_go": list(self.start_costs_to_go),
            "over_episodes": self.over_episodes,
            "over_steps": self.over_steps,
            "over_reading_sum": self.over_reading_sum,
            "over_cost_to_go_sum": self.over_cost_to_go_sum,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.start_readings = [float(x) for x in state["start_readings"]]
        self.start_costs_to_go = [float(x) for x in state["start_costs_to_go"]]
        self.over_episodes = int(state["over_episodes"])
        self.over_steps = int(state["over_steps"])
        self.over_reading_sum = float(state["over_reading_sum"])
        self.over_cost_to_go_sum = float(state["over_cost_to_go_sum"])
        self._running = {}
