"""The safety-gymnasium adapter: clear ImportError here, project conventions on top of
TorchRL's own ``SafetyGymnasiumWrapper`` (exercised with a stand-in 6-tuple env)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs.libs.safety_gymnasium import SafetyGymnasiumWrapper
from torchrl.envs.utils import check_env_specs

from wcsac_rl.envs import CostKeyError, make_safety_gymnasium_env, wrap_safety_gymnasium
from wcsac_rl.envs.safety_gymnasium import safety_gymnasium_available


@pytest.mark.skipif(safety_gymnasium_available(), reason="safety_gymnasium is installed")
def test_missing_safety_gymnasium_gives_a_clear_import_error():
    with pytest.raises(ImportError, match="safety_gymnasium is not installed") as err:
        make_safety_gymnasium_env("SafetyPointGoal1-v0")
    msg = str(err.value)
    assert "SafetyPointGoal1-v0" in msg
    assert "pip install safety-gymnasium" in msg
    assert "make_env('static' | 'dynamic' | 'point_goal1' | 'point_goal2')" in msg


class SixTupleEnv(gym.Env):
    """Mimics safety-gymnasium's API: step returns (obs, reward, cost, term, trunc, info)."""

    def __init__(self):
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (5,), np.float64)
        self.action_space = gym.spaces.Box(-1, 1, (2,), np.float32)
        self.t = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return np.zeros(5), {}

    def step(self, action):
        self.t += 1
        cost = float(self.t % 2)
        return np.full(5, float(self.t)), 1.0, cost, False, self.t >= 10, {}


def test_torchrl_safety_wrapper_emits_flat_float64_cost():
    base = SafetyGymnasiumWrapper(env=SixTupleEnv())
    td = base.rollout(3)
    # TorchRL's convention, which the adapter converts:
    assert td["next", "cost"].shape == (3,)
    assert td["next", "cost"].dtype == torch.float64


def test_wrap_safety_gymnasium_applies_project_conventions():
    env = wrap_safety_gymnasium(SafetyGymnasiumWrapper(env=SixTupleEnv()))
    check_env_specs(env, seed=0)
    td = env.rollout(20)
    assert td.shape == (10,)
    assert td["next", "cost"].shape == (10, 1)
    assert td["next", "cost"].dtype == torch.float32
    assert td["observation"].dtype == torch.float32
    assert td["next", "episode_cost"][-1].item() == 5.0
    assert td["next", "episode_reward"][-1].item() == 10.0
    assert td["next", "step_count"][-1].item() == 10


def test_wrap_safety_gymnasium_needs_a_cost():
    from torchrl.envs.libs.gym import GymWrapper

    with pytest.raises(CostKeyError, match="no 'cost' entry"):
        wrap_safety_gymnasium(GymWrapper(gym.make("Pendulum-v1")))
