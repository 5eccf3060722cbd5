"""Gymnasium registration of the presets."""

from __future__ import annotations

import importlib
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import wcsac_rl.envs
from wcsac_rl.envs import GYM_IDS, PRESET_NAMES, PointGoalEnv, TinyHazardEnv, register_envs


def test_ids_are_documented_and_registered():
    assert PRESET_NAMES == ("static", "dynamic", "point_goal1", "point_goal2", "tiny")
    assert GYM_IDS == {
        "static": "wcsac_rl/StaticEnv-v0",
        "dynamic": "wcsac_rl/DynamicEnv-v0",
        "point_goal1": "wcsac_rl/PointGoal1-v0",
        "point_goal2": "wcsac_rl/PointGoal2-v0",
        "tiny": "wcsac_rl/TinyHazard-v0",
    }
    for gym_id in GYM_IDS.values():
        assert gym_id in gym.registry


def test_registration_is_idempotent():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warns when overriding an id
        register_envs()
        register_envs()
        importlib.reload(wcsac_rl.envs)


@pytest.mark.parametrize("name", PRESET_NAMES)
def test_gym_make_and_gymnasium_env_checker(name):
    env = gym.make(GYM_IDS[name])
    expected = TinyHazardEnv if name == "tiny" else PointGoalEnv
    assert isinstance(env.unwrapped, expected)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        check_env(env.unwrapped, skip_render_check=True)
    obs, _info = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    env.close()


def test_gym_make_time_limit_kwarg_wraps():
    env = gym.make("wcsac_rl/DynamicEnv-v0", max_episode_steps=3)
    env.reset(seed=0)
    flags = [env.step(np.zeros(2, dtype=np.float32))[3] for _ in range(3)]
    assert flags == [False, False, True]


def test_gym_make_forwards_config_overrides():
    env = gym.make("wcsac_rl/DynamicEnv-v0", hazards_num=5)
    _obs, info = env.reset(seed=0)
    assert info["hazard_dists"].shape == (5,)
