"""The tiny numpy env: dynamics, reward, cost, episode length, explicit layout.

Tolerances: the dynamics are float64; the observation rounds each float64 entry to
float32 once (≤ 2⁻²⁴ ≈ 6e-8 relative), within ``rtol=1e-6``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from wcsac_rl.envs import TinyHazardEnv, make_gym_env


def test_spaces_and_observation():
    env = TinyHazardEnv()
    obs, info = env.reset(seed=0)
    assert env.observation_space.shape == (6,) and obs.dtype == np.float32
    assert env.action_space.shape == (2,)
    x, y = info["robot_xy"]
    assert abs(x + 1.0) <= 0.2 and abs(y) <= 0.2
    np.testing.assert_allclose(obs, [x, y, 1 - x, -y, -x, -y], rtol=1e-6)
    assert info["cost"] == 0.0 and info["goal_reached"] is False


def test_motion_reward_and_clipping():
    env = TinyHazardEnv()
    _, info = env.reset(seed=0, options={"layout": {"robot_xy": (-1.0, 0.5)}})
    prev = info["goal_dist"]
    _obs, reward, terminated, truncated, info = env.step(np.array([3.0, -0.5]))  # x clipped to 1
    np.testing.assert_allclose(info["robot_xy"], [-0.95, 0.475])
    assert reward == pytest.approx(prev - info["goal_dist"])
    assert not terminated and not truncated


def test_greedy_path_costs_and_reaches_the_goal():
    env = TinyHazardEnv()
    env.reset(seed=0, options={"layout": {"robot_xy": (-1.0, 0.0)}})
    total_cost, steps = 0.0, 0
    while True:
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0]))
        total_cost += info["cost"]
        steps += 1
        if terminated or truncated:
            break
    assert terminated and info["goal_reached"] and reward > 1.0  # progress + bonus
    assert steps == 38  # 2 m - 0.1 goal radius at 0.05 m per step
    assert total_cost == 14  # |x| < 0.35 for the steps inside the hazard disc


def test_detour_is_safe_and_still_reaches_the_goal():
    env = TinyHazardEnv()
    env.reset(seed=0, options={"layout": {"robot_xy": (-1.0, 0.0)}})
    waypoints = [(-0.3, 0.5), (0.3, 0.5), (1.0, 0.0)]
    total_cost, done, info = 0.0, False, {}
    for wx, wy in waypoints:
        for _ in range(100):
            x, y = env.layout()["robot_xy"]
            d = math.hypot(wx - x, wy - y)
            if d < 0.06:
                break
            _, _, terminated, truncated, info = env.step(np.array([wx - x, wy - y]) / max(d, 0.05))
            total_cost += info["cost"]
            done = terminated or truncated
            if done:
                break
        if done:
            break
    assert info["goal_reached"] and total_cost == 0.0


def test_cost_strictly_inside_and_truncation():
    env = TinyHazardEnv(max_episode_steps=5)
    for xy, expected in [((0.1, 0.0), 1.0), ((0.35, 0.0), 0.0), ((0.0, -0.3499), 1.0)]:
        _, info = env.reset(options={"layout": {"robot_xy": xy}})
        assert info["cost"] == expected
    env.reset(seed=0, options={"layout": {"robot_xy": (-1.0, 1.0)}})
    flags = [env.step(np.zeros(2))[3] for _ in range(5)]
    assert flags == [False] * 4 + [True]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2))


def test_explicit_layout_and_errors():
    env = TinyHazardEnv()
    _, _info = env.reset(
        options={"layout": {"robot_xy": (0, 1), "goal_xy": (0, -1), "hazards_xy": [(0.5, 0.5)]}}
    )
    lay = env.layout()
    np.testing.assert_allclose(lay["goal_xy"], [0, -1])
    np.testing.assert_allclose(lay["hazards_xy"], [[0.5, 0.5]])
    with pytest.raises(ValueError, match="no robot heading"):
        env.reset(options={"layout": {"robot_heading": 1.0}})
    with pytest.raises(ValueError, match="unknown layout key"):
        env.reset(options={"layout": {"robot": (0, 0)}})
    with pytest.raises(ValueError, match="does not render"):
        TinyHazardEnv(render_mode="rgb_array")


def test_registered_and_fast_enough():
    env = make_gym_env("tiny")
    assert isinstance(env, TinyHazardEnv)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(2000, 2))
    import time

    t0 = time.perf_counter()
    for a in actions:
        *_, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    rate = len(actions) / (time.perf_counter() - t0)
    assert rate > 2000  # loose bound for a loaded CI box; typically tens of thousands
