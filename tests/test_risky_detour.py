"""The tiny env's risky hazard, the risky-detour experiment's instruments, and the
paper's claim on it: WCSAC-0.1 takes the safe detour, SAC-Lag the risky shortcut."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _env_helpers import tiny_goal_seeker
from tensordict.nn import TensorDictModule

from paper.risky_detour import (
    COST_LIMIT,
    LEARNER,
    RISKY_HAZARD,
    RISKY_STEPS_INSIDE,
    detour_config,
    route_of,
    train_on_risky_detour,
)
from wcsac_rl.envs.tiny import TinyHazardEnv
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


def _route_cvar(steps_inside: int, alpha: float = 0.1) -> float:
    """Exact CVaR_α of a route's cost, ``hazard_cost · Binomial(steps inside, prob)``."""
    cost, prob = RISKY_HAZARD["hazard_cost"], RISKY_HAZARD["hazard_cost_prob"]
    outcomes = [
        (cost * n, math.comb(steps_inside, n) * prob**n * (1 - prob) ** (steps_inside - n))
        for n in range(steps_inside, -1, -1)  # worst first
    ]
    tail, mass = 0.0, 0.0
    for value, p in outcomes:
        take = min(p, alpha - mass)
        tail, mass = tail + take * value, mass + take
    return tail / alpha


def test_a_route_is_risky_beyond_three_steps_inside():
    # up to 3 steps inside the disc a route's own CVaR_0.1 is within d, from 4 on over it
    assert _route_cvar(RISKY_STEPS_INSIDE) <= COST_LIMIT < _route_cvar(RISKY_STEPS_INSIDE + 1)
    assert _route_cvar(3) == pytest.approx(3.0) and _route_cvar(14) > 6.0


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
    straight = route_of(tiny_goal_seeker(), episodes=10)
    assert straight.crossing == straight.risky == straight.goal == 1.0
    assert 11 <= straight.steps_inside <= 15 and straight.mean_return > 2.5
    around = route_of(_around_the_hazard(), episodes=10)
    assert around.crossing == around.risky == around.steps_inside == 0.0
    assert around.goal == 1.0 and around.mean_return > 2.5


def test_rows_compose_with_the_risky_hazard_and_the_limit():
    cfg = detour_config("wcsac_0.1", 3, "algo.kappa_statistic=tail")
    assert cfg.env.name == "tiny" and cfg.cost_limit == 3.0 and cfg.seed == 3
    assert dict(cfg.env.kwargs) == RISKY_HAZARD
    assert cfg.algo.name == "wcsac" and cfg.risk_level == 0.1
    assert cfg.algo.kappa_statistic == "tail"
    sac_lag = detour_config("sac_lag", 0)
    assert sac_lag.algo.name == "sac_lag"
    for algo in (cfg.algo, sac_lag.algo):  # both rows: the same safety critic and κ
        for option in LEARNER:
            key, value = option.removeprefix("algo.").split("=")
            assert str(algo[key]).lower() == value


@pytest.mark.slow
def test_wcsac_takes_the_safe_detour_and_sac_lag_the_risky_shortcut():
    """The paper's claim on a sequential task, through the project's Trainer.

    Seed 1 of each row in the measurement of ``paper.risky_detour``
    (module docstring, seeds 0-5): every SAC-Lag seed ends on the shortcut (14 steps
    inside the disc, κ → 0); WCSAC-0.1 ends off it on all six seeds and reaches the
    goal on four (seed 3: 70 % of the episodes, seed 5: none). Of those four, seed 1
    is the one whose route stayed on the detour from 3 000 frames on; the others were
    still switching in the last epochs (``results/risky_detour.md``). 1 min 54 s on
    an idle machine (both runs).
    """
    wcsac = train_on_risky_detour("wcsac_0.1", 1)
    sac_lag = train_on_risky_detour("sac_lag", 1)
    # WCSAC-0.1: around the disc (a route with ≤ 3 steps inside is within d by its
    # own CVaR_0.1), and on to the goal
    assert wcsac.risky_share <= 0.2 and wcsac.steps_inside <= 2.0, wcsac
    assert wcsac.goal_share >= 0.9, wcsac
    # SAC-Lag: straight through (expected cost ≈ 1.4 ≤ d), its constraint slack
    assert sac_lag.risky_share >= 0.8 and sac_lag.steps_inside >= 10.0, sac_lag
    assert sac_lag.goal_share >= 0.9 and sac_lag.kappa < 0.005, sac_lag
