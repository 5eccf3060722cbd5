"""The tiny env's risky hazard and the risky-detour experiment's instruments."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _env_helpers import tiny_goal_seeker
from tensordict.nn import TensorDictModule

from wcsac_rl.envs.tiny import TinyHazardEnv
from wcsac_rl.experiments.risky_detour import RISKY_HAZARD, detour_config, route_of
from wcsac_rl.objectives import empirical_cvar


def _straight_costs(episodes: int, **kwargs) -> np.ndarray:
    env = TinyHazardEnv(**kwargs)
    costs = []
    for seed in range(episodes):
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            obs, _, terminated, truncated, info = env.step(np.clip(10 * obs[2:4], -1, 1))
            total += info["cost"]
            done = terminated or truncated
        costs.append(total)
    return np.array(costs)


def test_risky_hazard_has_a_small_mean_and_a_heavy_tail():
    always = _straight_costs(300)  # every step inside the disc costs 1: steps inside
    risky = _straight_costs(300, **RISKY_HAZARD)
    assert set(np.unique(risky)) <= {5.0 * k for k in range(20)}
    # the straight route spends 11-15 steps inside; each costs 5 with probability 0.02
    expected_mean = 5.0 * 0.02 * always.mean()
    standard_error = 5.0 * np.sqrt(0.02 * 0.98 * always.mean() / 300)
    assert abs(risky.mean() - expected_mean) < 4 * standard_error
    assert risky.mean() < 3.0 < empirical_cvar(risky, 0.1)  # within d = 3 on average only
    with pytest.raises(ValueError, match="hazard_cost_prob"):
        TinyHazardEnv(hazard_cost_prob=1.5)
    # the default hazard charges every step and draws no random numbers for it
    assert np.array_equal(always, _straight_costs(300, hazard_cost_prob=1.0))


def _around_the_hazard() -> TensorDictModule:
    """Up above the disc (radius 0.35 at the origin), across, then down to the goal."""

    def act(obs):
        x, y = obs[..., 0], obs[..., 1]
        up = torch.stack([torch.zeros_like(x), torch.ones_like(y)], -1)
        right = torch.stack([torch.ones_like(x), torch.zeros_like(y)], -1)
        to_goal = (10 * obs[..., 2:4]).clamp(-1, 1)
        above = (y > 0.5).unsqueeze(-1)
        past = (x > 0.45).unsqueeze(-1)
        return torch.where(past, to_goal, torch.where(above, right, up))

    return TensorDictModule(act, in_keys=["observation"], out_keys=["action"])


def test_route_reads_crossings_and_goals_of_a_policy():
    crossing, goals, ret = route_of(tiny_goal_seeker(), episodes=10)
    assert crossing == 1.0 and goals == 1.0 and ret > 2.5
    crossing, goals, ret = route_of(_around_the_hazard(), episodes=10)
    assert crossing == 0.0 and goals == 1.0 and ret > 2.5


def test_rows_compose_with_the_risky_hazard_and_the_limit():
    cfg = detour_config("wcsac_0.1", 3, "algo.kappa_statistic=tail")
    assert cfg.env.name == "tiny" and cfg.cost_limit == 3.0 and cfg.seed == 3
    assert dict(cfg.env.kwargs) == RISKY_HAZARD
    assert cfg.algo.name == "wcsac" and cfg.risk_level == 0.1
    assert cfg.algo.kappa_statistic == "tail"
    assert detour_config("sac_lag", 0).algo.name == "sac_lag"
