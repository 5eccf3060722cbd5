"""Calibration of the safety critic on the states the policy visits: predicted vs realised cost.

Whether the critic's Q^c, Γ_α and √V^c mean anything is measured on deterministic test
episodes of the current policy (docs/training.md, "Safety-critic calibration", defines the
measures and their ``calib/*`` columns):

* :func:`record_calibration_episodes` runs the test episodes (the very episodes
  :func:`~wcsac_rl.rollouts.episodes.run_episodes` gives) and keeps, per step, the entries
  the loss's actor and safety critic read, the action taken and the cost;
* :func:`compare_episodes` asks the loss for its estimates at every recorded state-action
  (``loss.safety_estimates``) beside the Monte-Carlo discounted cost-to-go
  (:func:`discounted_cost_to_go`, γ_c = ``loss.cost_gamma``);
* :func:`summarize_calibration` / :func:`calibration_metrics` reduce that to
  :data:`CALIBRATION_KEYS` (logged per epoch by the trainer, written to
  ``calibration.json`` by :mod:`wcsac_rl.evaluation.run_calibration`).

The realised cost-to-go is the sum of the costs seen until the episode ends: a critic
that bootstraps across the time limit (γ_c < 1) counts costs beyond it, so near the end
of a truncated episode the realised value is low (the start-state numbers least). The
test episodes act with the mean action, the critic is trained for the stochastic policy:
the comparison is the one the constraint relies on, not a test of the TD fixed point.
Losses without ``safety_estimates`` (SAC, CPO): :func:`supports_calibration` is ``False``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs import EnvBase

from wcsac_rl.objectives.risk import (
    empirical_cvar,
    gaussian_mixture_cvar,
    quantile_mixture_cvar,
)
from wcsac_rl.rollouts.episodes import EpisodeResult, RecordedEpisode, record_episodes

__all__ = [
    "CALIBRATION_KEYS",
    "PREFIX",
    "EpisodeCalibration",
    "calibration_keys",
    "calibration_metrics",
    "compare_episodes",
    "discounted_cost_to_go",
    "record_calibration_episodes",
    "summarize_calibration",
    "supports_calibration",
]

PREFIX = "calib/"
CALIBRATION_KEYS: tuple[str, ...] = tuple(
    PREFIX + name
    for name in (
        # start state s0 (first step of each episode), averaged over episodes
        "start_cost_value",  # predicted Q^c(s0, a0)
        "start_cvar",  # predicted Γ_α(s0, a0), the CVaR the loss uses
        "start_std",  # predicted √V^c(s0, a0) (IQN: std of its quantiles; NaN for a mean-only critic)
        "start_realised_cost_to_go",  # realised Σ_t γ_c^t c_t from s0
        "start_realised_cvar",  # empirical CVaR_α over episodes of that sum
        "start_cvar_ratio",  # start_cvar / start_realised_cvar
        "start_tail_cvar",  # CVaR_α of the predicted start-state distributions, mixed
        "start_tail_ratio",  # start_tail_cvar / start_realised_cvar
        "realised_spread",  # std over episodes of the realised sum from s0
        # every visited state, pooled over episodes (each step counts once)
        "mean_cost_value",  # Q^c
        "mean_cvar",  # Γ_α
        "mean_std",  # √V^c (NaN for a mean-only critic)
        "mean_realised_cost_to_go",  # Σ_{k≥t} γ_c^{k−t} c_k
        "correlation",  # Pearson correlation of Q^c and the realised cost-to-go
        "negative_share",  # share of states with Q^c < 0
        # undiscounted episodic cost
        "episode_cost",  # mean over episodes
        "episode_cvar",  # empirical CVaR_α over episodes
    )
)
"""The names :func:`summarize_calibration` returns, in a fixed order."""


def supports_calibration(loss: Any) -> bool:
    """Whether ``loss`` has a safety critic to calibrate (``WCSACLoss``, ``SACLagLoss``)."""
    return loss is not None and callable(getattr(loss, "safety_estimates", None))


def _cost_key(loss: Any) -> tuple[str, ...]:
    """Where the loss reads the per-step cost, under ``"next"``."""
    key = getattr(loss.tensor_keys, "cost", "cost")
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def calibration_keys(loss: Any) -> list[NestedKey]:
    """The per-step entries calibration records: the observation entries the loss's
    safety critic and actor read, the action, and the cost under ``"next"``."""
    action = loss.tensor_keys.action
    # an IQN critic's quantile fractions are drawn by the loss, not recorded
    fractions = getattr(loss.tensor_keys, "quantile_fractions", None)
    keys: list[NestedKey] = []
    for name in ("safety_network", "actor_network"):
        network = getattr(loss, name, None)
        if network is not None:
            keys += [key for key in network.in_keys if key not in (action, fractions)]
    keys += [action, _cost_key(loss)]
    return list(dict.fromkeys(keys))


def record_calibration_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None,
    loss: Any,
    num_episodes: int,
    *,
    max_steps: int = 100_000,
    on_episode: Callable[[EpisodeResult], None] | None = None,
) -> list[RecordedEpisode]:
    """``num_episodes`` deterministic test episodes with what :func:`compare_episodes` needs.

    Same episodes (and :class:`~wcsac_rl.rollouts.episodes.EpisodeResult`) as
    ``run_episodes(env, policy, num_episodes, deterministic=True, max_steps=...)``.
    """
    return record_episodes(
        env,
        policy,
        num_episodes,
        calibration_keys(loss),
        deterministic=True,
        max_steps=max_steps,
        on_episode=on_episode,
    )


def discounted_cost_to_go(costs: Sequence[float] | np.ndarray, gamma: float) -> np.ndarray:
    """Monte-Carlo cost-to-go ``G_t = Σ_{k≥t} γ^{k−t} c_k`` of one episode (float64).

    Computed backwards (``G_t = c_t + γ G_{t+1}``, ``G_T = 0``) over the costs of
    the episode as it happened: for an episode cut by a time limit this is the
    truncated sum (see the module docstring).

    >>> discounted_cost_to_go([1.0, 0.0, 2.0], 0.5).tolist()
    [1.5, 1.0, 2.0]
    """
    costs = np.asarray(costs, dtype=np.float64).reshape(-1)
    out = np.empty_like(costs)
    running = 0.0
    for t in range(costs.size - 1, -1, -1):
        running = costs[t] + gamma * running
        out[t] = running
    return out


@dataclass(frozen=True)
class EpisodeCalibration:
    """One episode's per-step predictions and realised costs (float64 arrays of length T).

    Attributes:
        cost: the per-step cost ``c_t``.
        cost_to_go: the realised discounted cost-to-go ``Σ_{k≥t} γ_c^{k−t} c_k``.
        cost_value: predicted Q^c(s_t, a_t).
        cvar: predicted Γ_α(s_t, a_t).
        std: predicted √V^c(s_t, a_t) (IQN: the standard deviation of its quantiles),
            all NaN for a mean-only critic.
        quantiles: an IQN critic's quantiles ``[T, N]`` at ``N`` evenly spread
            fractions of [0, 1] (``None`` for the other critics).
    """

    cost: np.ndarray
    cost_to_go: np.ndarray
    cost_value: np.ndarray
    cvar: np.ndarray
    std: np.ndarray
    quantiles: np.ndarray | None = None

    def as_dict(self) -> dict[str, float]:
        """The episode's start-state numbers and its totals (for ``calibration.json``)."""
        return {
            "length": int(self.cost.size),
            "cost": float(self.cost.sum()),
            "start_cost_value": float(self.cost_value[0]),
            "start_cvar": float(self.cvar[0]),
            "start_std": float(self.std[0]),
            "start_realised_cost_to_go": float(self.cost_to_go[0]),
            "mean_cost_value": float(self.cost_value.mean()),
            "mean_realised_cost_to_go": float(self.cost_to_go.mean()),
        }


def _as_float64(value: torch.Tensor) -> np.ndarray:
    return value.detach().to("cpu", torch.float64).reshape(-1).numpy()


def compare_episodes(episodes: Sequence[RecordedEpisode], loss: Any) -> list[EpisodeCalibration]:
    """The loss's safety estimates and the realised cost-to-go at every recorded step.

    All steps go through ``loss.safety_estimates`` in one batch (no gradient). Each
    episode's ``steps`` must hold the entries of :func:`calibration_keys`.
    """
    if not episodes:
        return []
    cost_key = _cost_key(loss)
    lengths = [episode.steps.shape[0] for episode in episodes]
    inputs = torch.cat([episode.steps.exclude("next") for episode in episodes])
    with torch.no_grad():
        estimates = loss.safety_estimates(inputs)
    split = np.cumsum(lengths)[:-1]
    cost_value = np.split(_as_float64(estimates.get("cost_value")), split)
    cvar = np.split(_as_float64(estimates.get("cvar")), split)
    variance = estimates.get("cost_variance", None)
    if variance is None:
        std = [np.full(n, np.nan) for n in lengths]
    else:
        std = np.split(np.sqrt(np.clip(_as_float64(variance), 0.0, None)), split)
    quantiles = estimates.get("cost_quantiles", None)
    if quantiles is None:
        quantiles = [None] * len(episodes)
    else:
        quantiles = np.split(quantiles.detach().to("cpu", torch.float64).numpy(), split)
    gamma = float(loss.cost_gamma)
    out = []
    for i, episode in enumerate(episodes):
        cost = _as_float64(episode.steps.get(cost_key))
        out.append(
            EpisodeCalibration(
                cost=cost,
                cost_to_go=discounted_cost_to_go(cost, gamma),
                cost_value=cost_value[i],
                cvar=cvar[i],
                std=std[i],
                quantiles=quantiles[i],
            )
        )
    return out


def _ratio(numerator: float, denominator: float) -> float:
    if denominator == 0 or math.isnan(numerator) or math.isnan(denominator):
        return math.nan
    return numerator / denominator


def _correlation(x: np.ndarray, y: np.ndarray) -> float:
    """Pearson correlation; NaN for fewer than two points or a constant array."""
    # constant: checked on the values themselves, not on a rounded x − mean(x)
    if x.size < 2 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return math.nan
    dx, dy = x - x.mean(), y - y.mean()
    return float(dx @ dy) / math.sqrt(float(dx @ dx) * float(dy @ dy))


def summarize_calibration(
    episodes: Sequence[EpisodeCalibration], risk_level: float, *, nonnegative: bool = False
) -> dict[str, float]:
    """The :data:`CALIBRATION_KEYS` of a set of episodes (NaN where undefined; all NaN
    for no episodes): docs/training.md's table says what each is.

    ``start_*`` are at each episode's first state-action, averaged over episodes; the
    realised CVaRs are empirical over episodes
    (:func:`~wcsac_rl.objectives.risk.empirical_cvar`). ``start_tail_cvar`` is the CVaR_α
    of the predicted start-state distributions mixed over the episodes
    (:func:`~wcsac_rl.objectives.risk.gaussian_mixture_cvar`; an IQN critic's quantiles
    pooled, :func:`~wcsac_rl.objectives.risk.quantile_mixture_cvar`), the critic's own
    estimate of ``start_realised_cvar``, whose tail is made of episodes with different
    start states; with ``nonnegative`` the predictions are clamped at 0 first.
    """
    metrics = dict.fromkeys(CALIBRATION_KEYS, math.nan)
    if not episodes:
        return metrics
    start_realised = np.array([e.cost_to_go[0] for e in episodes])
    episode_cost = np.array([e.cost.sum() for e in episodes])
    pooled = {
        name: np.concatenate([getattr(e, name) for e in episodes])
        for name in ("cost_value", "cvar", "std", "cost_to_go")
    }
    values = {
        "start_cost_value": float(np.mean([e.cost_value[0] for e in episodes])),
        "start_cvar": float(np.mean([e.cvar[0] for e in episodes])),
        "start_std": float(np.mean([e.std[0] for e in episodes])),
        "start_realised_cost_to_go": float(start_realised.mean()),
        "start_realised_cvar": empirical_cvar(start_realised, risk_level),
        "realised_spread": float(start_realised.std(ddof=1)) if len(episodes) > 1 else math.nan,
        "mean_cost_value": float(pooled["cost_value"].mean()),
        "mean_cvar": float(pooled["cvar"].mean()),
        "mean_std": float(pooled["std"].mean()),
        "mean_realised_cost_to_go": float(pooled["cost_to_go"].mean()),
        "correlation": _correlation(pooled["cost_value"], pooled["cost_to_go"]),
        "negative_share": float(np.mean(pooled["cost_value"] < 0)),
        "episode_cost": float(episode_cost.mean()),
        "episode_cvar": empirical_cvar(episode_cost, risk_level),
    }
    values["start_cvar_ratio"] = _ratio(values["start_cvar"], values["start_realised_cvar"])
    if all(e.quantiles is not None for e in episodes):
        start_quantiles = torch.from_numpy(np.stack([e.quantiles[0] for e in episodes]))
        if nonnegative:
            start_quantiles = start_quantiles.clamp(min=0.0)
        tail = quantile_mixture_cvar(start_quantiles, risk_level)
    else:
        start_mean = torch.tensor([float(e.cost_value[0]) for e in episodes], dtype=torch.float64)
        if nonnegative:
            start_mean = start_mean.clamp(min=0.0)
        start_std = torch.tensor([float(e.std[0]) for e in episodes], dtype=torch.float64)
        start_variance = None if torch.isnan(start_std).any() else start_std.pow(2)
        tail = gaussian_mixture_cvar(start_mean, start_variance, risk_level)
    values["start_tail_cvar"] = float(tail)
    values["start_tail_ratio"] = _ratio(values["start_tail_cvar"], values["start_realised_cvar"])
    metrics.update({PREFIX + name: value for name, value in values.items()})
    return metrics


def calibration_metrics(episodes: Sequence[RecordedEpisode], loss: Any) -> dict[str, float]:
    """:func:`summarize_calibration` of :func:`compare_episodes` at ``loss.risk_level``."""
    return summarize_calibration(
        compare_episodes(episodes, loss),
        float(loss.risk_level),
        nonnegative=bool(getattr(loss, "nonnegative_cost", False)),
    )


# ----------------------------------------------------------------- a saved run
