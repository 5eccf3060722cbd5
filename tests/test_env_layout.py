"""Layout sampling: keepouts, fixed objects, seeding, explicit layouts.

Tolerances: positions are float64 (default ``assert_allclose`` rtol 1e-7 is 10⁸ ulps);
observations are float32 roundings of float64 values ≤ 10 (½ ulp ≤ 4.8e-7), so
``atol=1e-6`` allows one float32 rounding at the largest entry.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from wcsac_rl.envs import LayoutError, make_gym_env
from wcsac_rl.envs.layout import ObjectPlacement, draw_position, sample_layout


def _objects(env):
    """(name, start xy, keepout) of every object right after reset."""
    c = env.unwrapped.config
    lay = env.unwrapped.layout()
    out = [
        ("robot", lay["robot_start_xy"], c.robot_keepout),
        ("goal", lay["goal_xy"], c.goal_keepout),
    ]
    out += [(f"hazard{i}", xy, c.hazards_keepout) for i, xy in enumerate(lay["hazards_xy"])]
    out += [(f"vase{i}", xy, c.vases_keepout) for i, xy in enumerate(lay["vases_xy"])]
    return out


@pytest.mark.parametrize(
    ("name", "resets"),
    [("static", 100), ("dynamic", 150), ("point_goal1", 80), ("point_goal2", 40)],
)
def test_keepouts_and_extents_respected_over_many_resets(name, resets):
    env = make_gym_env(name)
    c = env.unwrapped.config
    xmin, ymin, xmax, ymax = c.placement_extents
    for seed in range(resets):
        env.reset(seed=seed)
        objs = _objects(env)
        for (na, a, ka), (nb, b, kb) in itertools.combinations(objs, 2):
            assert math.dist(a, b) >= ka + kb - 1e-12, (seed, na, nb)
        for n, xy, k in objs:
            assert xmin + k - 1e-12 <= xy[0] <= xmax - k + 1e-12, (seed, n)
            assert ymin + k - 1e-12 <= xy[1] <= ymax - k + 1e-12, (seed, n)


def test_static_env_goal_and_hazard_fixed_robot_random():
    env = make_gym_env("static")
    starts, headings = [], []
    for seed in range(50):
        _, _info = env.reset(seed=seed)
        lay = env.layout()
        np.testing.assert_array_equal(lay["goal_xy"], [1.1, 1.1])
        np.testing.assert_array_equal(lay["hazards_xy"], [[0.0, 0.0]])
        assert lay["hazards_size"] == 0.7 and lay["goal_size"] == 0.3
        assert math.hypot(*lay["robot_start_xy"]) >= 0.4 + 0.705
        starts.append(lay["robot_start_xy"])
        headings.append(lay["robot_start_heading"])
    assert len({tuple(s) for s in starts}) == 50
    assert 0.0 <= min(headings) and max(headings) < 2 * math.pi
    assert np.std(headings) > 1.0


def test_dynamic_env_redraws_everything():
    env = make_gym_env("dynamic")
    env.reset(seed=0)
    a = env.layout()
    env.reset()
    b = env.layout()
    for key in ("robot_start_xy", "goal_xy", "hazards_xy"):
        assert not np.allclose(a[key], b[key])


def _episode(env, seed, steps=150):
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = [(obs, 0.0, info["cost"])]
    for _ in range(steps):
        obs, r, term, trunc, info = env.step(rng.uniform(-1, 1, size=2))
        out.append((obs, r, info["cost"]))
        if term or trunc:
            obs, info = env.reset()
            out.append((obs, 0.0, info["cost"]))
    return out


@pytest.mark.parametrize("name", ["dynamic", "point_goal2", "tiny"])
def test_same_seed_same_episode(name):
    a = _episode(make_gym_env(name), seed=7)
    b = _episode(make_gym_env(name), seed=7)
    c = _episode(make_gym_env(name), seed=8)
    assert len(a) == len(b)
    for (oa, ra, ca), (ob, rb, cb) in zip(a, b):
        np.testing.assert_array_equal(oa, ob)
        assert ra == rb and ca == cb
    assert not np.array_equal(a[0][0], c[0][0])


def test_explicit_layout_is_honoured():
    env = make_gym_env("point_goal1")
    layout = {
        "robot_xy": (0.1, -0.2),
        "robot_heading": 1.0,
        "goal_xy": (1.0, 1.0),
        "hazards_xy": [(-1.0 + 0.25 * i, -1.2) for i in range(8)],
        "vases_xy": [(0.9, -0.9)],
    }
    _, info = env.reset(seed=0, options={"layout": layout})
    lay = env.layout()
    np.testing.assert_allclose(lay["robot_xy"], layout["robot_xy"])
    assert lay["robot_heading"] == pytest.approx(1.0)
    np.testing.assert_allclose(lay["goal_xy"], layout["goal_xy"])
    np.testing.assert_allclose(lay["hazards_xy"], layout["hazards_xy"])
    np.testing.assert_allclose(lay["vases_xy"], layout["vases_xy"], atol=1e-9)
    np.testing.assert_allclose(info["robot_xy"], layout["robot_xy"])
    # a partial layout: the rest is sampled, keeping clear of the explicit robot
    for seed in range(20):
        env.reset(seed=seed, options={"layout": {"robot_xy": (0.0, 0.0)}})
        lay = env.layout()
        np.testing.assert_allclose(lay["robot_xy"], [0.0, 0.0])
        assert math.hypot(*lay["goal_xy"]) >= 0.4 + 0.305
    # the layout option holds for one episode only
    env.reset(seed=1)
    assert not np.allclose(env.layout()["robot_xy"], [0.0, 0.0])


def test_a_drawn_robot_keeps_clear_of_explicit_objects_placed_after_it():
    """The robot is drawn first; a replayed goal and hazards (Figure 5's episodes) are
    explicit: the robot keeps clear of them as it does of drawn ones (keepout sums)."""
    env = make_gym_env("static")
    layout = {"goal_xy": (1.1, 1.1), "hazards_xy": [(0.0, 0.0)]}
    for seed in range(200):
        env.reset(seed=seed, options={"layout": layout})
        robot = env.layout()["robot_xy"]
        assert math.hypot(*robot) >= 0.4 + 0.705  # robot keepout + the hazard's
        assert math.hypot(robot[0] - 1.1, robot[1] - 1.1) >= 0.4 + 0.305


def test_layout_replays_from_layout_method():
    env = make_gym_env("dynamic")
    obs_a, _ = env.reset(seed=11)
    lay = env.layout()
    replay = {
        "robot_xy": lay["robot_start_xy"],
        "robot_heading": lay["robot_start_heading"],
        "goal_xy": lay["goal_xy"],
        "hazards_xy": lay["hazards_xy"],
    }
    obs_b, _ = env.reset(seed=99, options={"layout": replay})
    np.testing.assert_allclose(obs_a, obs_b, atol=1e-6)


def test_impossible_layout_fails_loudly():
    env = make_gym_env("dynamic", hazards_num=40, hazards_keepout=0.5, layout_max_restarts=20)
    with pytest.raises(LayoutError, match="after 20 layout restarts"):
        env.reset(seed=0)


def test_sample_layout_fixed_object_is_a_point_and_checked():
    rng = np.random.default_rng(0)
    extents = (-1.0, -1.0, 1.0, 1.0)
    objs = [ObjectPlacement("a", 0.2, (0.0, 0.0)), ObjectPlacement("b", 0.2)]
    for _ in range(50):
        lay = sample_layout(rng, extents, objs)
        np.testing.assert_array_equal(lay["a"], [0.0, 0.0])
        assert math.hypot(*lay["b"]) >= 0.4
        assert np.all(np.abs(lay["b"]) <= 0.8)
    # a fixed object that conflicts with the already placed ones is rejected
    pos = draw_position(
        rng, extents, ObjectPlacement("c", 0.3, (0.1, 0.0)), np.zeros((1, 2)), np.array([0.2]), 100
    )
    assert pos is None


def test_keepout_too_large_for_extents_is_reported():
    obj = ObjectPlacement("big", 2.0)
    with pytest.raises(ValueError, match="no room"):
        obj.rectangle((-1.0, -1.0, 1.0, 1.0))
