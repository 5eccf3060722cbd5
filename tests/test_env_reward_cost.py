"""Reward (progress, goal bonus, goal re-draw, termination, truncation) and cost.

Tolerances: rewards and distances are float64 sums of a few terms of size ≤ 2 (a few
× 2⁻⁵² × 2 ≈ 1e-15), so ``abs=1e-12`` and approx's default ``rel=1e-6`` hold on any CPU.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from wcsac_rl.envs import make_gym_env

FAR_HAZARDS_3 = [(-1.4, 1.4), (1.4, -1.4), (-1.4, -1.4)]


def _dyn_layout(robot_xy=(0.0, 0.0), heading=0.0, goal_xy=(1.0, 0.0), hazards=FAR_HAZARDS_3):
    return {
        "layout": {
            "robot_xy": robot_xy,
            "robot_heading": heading,
            "goal_xy": goal_xy,
            "hazards_xy": hazards,
        }
    }


def test_reward_is_progress_towards_goal():
    env = make_gym_env("dynamic")
    _, info = env.reset(seed=0, options=_dyn_layout(goal_xy=(1.2, 0.6)))
    rng = np.random.default_rng(0)
    prev = info["goal_dist"]
    for _ in range(100):
        _, reward, _terminated, _truncated, info = env.step(rng.uniform(-1, 1, size=2))
        assert not info["goal_reached"]
        expected = prev - info["goal_dist"]
        assert reward == pytest.approx(expected, abs=1e-12)
        xy = info["robot_xy"]
        assert info["goal_dist"] == pytest.approx(math.hypot(1.2 - xy[0], 0.6 - xy[1]))
        prev = info["goal_dist"]
    rewards_forward = [env.step(np.array([1.0, 0.0]))[1] for _ in range(1)]
    assert isinstance(rewards_forward[0], float)


def test_goal_bonus_and_redraw_in_dynamic_env():
    env = make_gym_env("dynamic")
    _, info = env.reset(seed=3, options=_dyn_layout(goal_xy=(0.6, 0.0)))
    old_goal = info["goal_xy"].copy()
    prev = info["goal_dist"]
    for _ in range(200):
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0]))
        if info["goal_reached"]:
            break
        prev = info["goal_dist"]
    else:
        pytest.fail("goal never reached")
    assert not terminated and not truncated  # DynamicEnv continues
    new_goal = info["goal_xy"]
    assert not np.allclose(new_goal, old_goal)
    xy = info["robot_xy"]
    dist_to_old = math.hypot(old_goal[0] - xy[0], old_goal[1] - xy[1])
    assert dist_to_old <= 0.3
    assert reward == pytest.approx(prev - dist_to_old + 1.0, abs=1e-12)
    # the new goal respects keepouts against the robot (0.4 + 0.305) and the hazards
    assert math.hypot(*(new_goal - xy)) >= 0.705
    for h in FAR_HAZARDS_3:
        assert math.hypot(*(new_goal - np.array(h))) >= 0.305 + 0.305
    assert info["goal_dist"] == pytest.approx(math.hypot(*(new_goal - xy)))
    # the progress term now measures distance to the new goal
    prev = info["goal_dist"]
    _, reward, *_, info = env.step(np.array([0.0, 0.0]))
    assert reward == pytest.approx(prev - info["goal_dist"], abs=1e-12)


def test_static_env_terminates_at_its_fixed_goal_with_offset():
    env = make_gym_env("static")
    # Start 0.5 m from the fixed goal (1.1, 1.1), facing it.
    layout = {"robot_xy": (0.75, 0.75), "robot_heading": math.pi / 4}
    _, info = env.reset(seed=0, options={"layout": layout})
    np.testing.assert_allclose(info["goal_xy"], [1.1, 1.1])
    prev = info["goal_dist"]
    for _ in range(200):
        _, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0]))
        if terminated:
            break
        assert reward == pytest.approx(prev - info["goal_dist"] - 0.02, abs=1e-12)
        prev = info["goal_dist"]
    else:
        pytest.fail("StaticEnv did not terminate at the goal")
    assert info["goal_reached"] and not truncated
    assert reward == pytest.approx(prev - info["goal_dist"] + 1.0 - 0.02, abs=1e-12)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(2))


def test_truncation_at_1000_steps():
    env = make_gym_env("dynamic")
    env.reset(seed=0, options=_dyn_layout())
    for t in range(1, 1001):
        *_, terminated, truncated, _ = env.step(np.zeros(2))
        assert not terminated
        assert truncated == (t == 1000)
    env = make_gym_env("dynamic", max_episode_steps=7)
    env.reset(seed=0)
    flags = [env.step(np.zeros(2))[3] for _ in range(7)]
    assert flags == [False] * 6 + [True]


def test_cost_inside_outside_and_exactly_on_the_boundary():
    env = make_gym_env("dynamic")
    hazards = [(0.0, 0.0), (1.4, -1.4), (-1.4, -1.4)]
    for robot_xy, expected in [
        ((0.1, 0.0), 1.0),
        ((0.0, -0.29), 1.0),
        ((0.3 - 1e-9, 0.0), 1.0),
        ((0.3, 0.0), 0.0),  # dist == hazards_size: not inside (strict <)
        ((0.0, 0.3), 0.0),
        ((0.5, 0.5), 0.0),
    ]:
        opts = _dyn_layout(robot_xy=robot_xy, goal_xy=(1.3, 1.3), hazards=hazards)
        _, info = env.reset(seed=0, options=opts)
        assert info["cost"] == expected, robot_xy
        _, _, _, _, info = env.step(np.zeros(2))  # at rest the robot does not move
        assert info["cost"] == expected, robot_xy
        assert isinstance(info["cost"], float)
        assert info["hazard_min_dist"] == pytest.approx(math.hypot(*robot_xy))
        assert info["hazard_dists"].shape == (3,)


def test_cost_when_driving_through_a_hazard():
    env = make_gym_env("dynamic")
    opts = _dyn_layout(
        robot_xy=(-1.0, 0.0), goal_xy=(1.3, 1.3), hazards=[(0, 0), *FAR_HAZARDS_3[1:]]
    )
    env.reset(seed=0, options=opts)
    costs, dists = [], []
    for _ in range(80):
        *_, info = env.step(np.array([1.0, 0.0]))
        costs.append(info["cost"])
        dists.append(info["hazard_min_dist"])
    costs, dists = np.array(costs), np.array(dists)
    assert costs.sum() > 0
    np.testing.assert_array_equal(costs, (dists < 0.3).astype(float))


@pytest.mark.parametrize("name", ["static", "dynamic", "point_goal1", "point_goal2"])
def test_starting_cost_is_zero_over_many_resets(name):
    env = make_gym_env(name)
    for seed in range(150):
        _, info = env.reset(seed=seed)
        assert info["cost"] == 0.0
        assert info["hazard_min_dist"] >= env.unwrapped.config.hazards_size


def test_untouched_vases_stay_still_and_cost_nothing():
    env = make_gym_env("point_goal2")
    for seed in range(5):
        env.reset(seed=seed)
        for _ in range(25):
            *_, info = env.step(np.zeros(2))
            assert info["cost"] == 0.0
            assert info["cost_vases_velocity"] == 0.0
            assert info["cost_vases_contact"] == 0.0


def _pg2_layout():
    corners = [(-1.8 + 0.4 * i, 1.8) for i in range(10)]
    vases = [(0.45, 0.0)] + [(-1.8 + 0.4 * i, -1.8) for i in range(9)]
    return {
        "robot_xy": (0.0, 0.0),
        "robot_heading": 0.0,
        "goal_xy": (-1.0, -1.0),
        "hazards_xy": corners,
        "vases_xy": vases,
    }


def test_pushing_a_vase_costs_in_point_goal2():
    env = make_gym_env("point_goal2")
    _, info = env.reset(seed=0, options={"layout": _pg2_layout()})
    assert info["cost"] == 0.0
    infos = []
    for _ in range(40):
        *_, info = env.step(np.array([1.0, 0.0]))
        infos.append(info)
    contact = [i["cost_vases_contact"] for i in infos]
    velocity = [i["cost_vases_velocity"] for i in infos]
    assert max(contact) >= 1.0
    assert max(velocity) > 0.0
    for i in infos:  # indicator of the total, as Safety Gym's constrain_indicator
        total = i["cost_hazards"] + i["cost_vases_contact"] + i["cost_vases_velocity"]
        assert i["cost"] == float(total > 0)
    assert env.vases_xy[0, 0] > 0.5  # the vase was pushed


def test_vases_do_not_cost_in_point_goal1():
    env = make_gym_env("point_goal1")
    layout = _pg2_layout()
    layout["hazards_xy"] = layout["hazards_xy"][:8]
    layout["vases_xy"] = layout["vases_xy"][:1]
    env.reset(seed=0, options={"layout": layout})
    costs = [env.step(np.array([1.0, 0.0]))[4]["cost"] for _ in range(40)]
    assert sum(costs) == 0.0
    assert env.vases_xy[0, 0] > 0.5  # physical: it was pushed


def test_raw_cost_sum_when_indicator_disabled():
    env = make_gym_env("point_goal2", constrain_indicator=False)
    env.reset(seed=0, options={"layout": _pg2_layout()})
    costs = [env.step(np.array([1.0, 0.0]))[4]["cost"] for _ in range(40)]
    assert max(costs) > 1.0


def test_numerical_failure_ends_the_episode_with_penalty():
    env = make_gym_env("dynamic")
    env.reset(seed=0)
    env.step(np.zeros(2))
    env.data.qvel[0] = np.nan  # simulate a blow-up
    obs, reward, terminated, _truncated, info = env.step(np.zeros(2))
    assert info["numerical_failure"] is True
    assert reward == -10.0
    assert info["cost"] == 1.0
    assert terminated
    assert np.all(np.isfinite(obs))
    # a fresh episode is clean again
    _, info = env.reset(seed=1)
    *_, info = env.step(np.zeros(2))
    assert info["numerical_failure"] is False


def test_numerical_failure_on_first_step_after_reset_is_detected():
    env = make_gym_env("dynamic")
    for _ in range(2):  # twice: MuJoCo's warning counters must not hide the second one
        env.reset(seed=0)
        env.data.qpos[0] = np.inf
        *_, terminated, _, info = env.step(np.zeros(2))
        assert info["numerical_failure"] and terminated
