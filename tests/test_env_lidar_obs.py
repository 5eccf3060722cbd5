"""Pseudo-lidar against hand-computed bins, and the observation layout.

Tolerances: ``pseudo_lidar`` is float64 (``atol=1e-12`` on values ≤ 1 is 10⁴ ulps of
a few trigonometric roundings); the env's observation is float32, one rounding of a
float64 value (≤ 2⁻²⁴ of values ≤ 1 for lidar, ≤ 9.81 for the accelerometer), so
``atol=1e-6`` (lidar, compass) and ``1e-5`` (accelerometer, vases: also the vase's
settling under gravity after reset) and ``abs=1e-4`` on a vase bin.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from wcsac_rl.envs import make_gym_env
from wcsac_rl.envs.lidar import heading_to_rotation, pseudo_lidar, pseudo_lidar_groups

BIN = 2 * math.pi / 16


def reference_lidar(points, robot_xy, heading, num_bins=16, max_dist=3.0):
    """Step-by-step transcription of docs/point_goal.md, "Lidar" (a scalar loop)."""
    obs = [0.0] * num_bins
    binsize = 2 * math.pi / num_bins
    c, s = math.cos(heading), math.sin(heading)
    for px, py in points:
        dx, dy = px - robot_xy[0], py - robot_xy[1]
        ex, ey = c * dx + s * dy, -s * dx + c * dy  # Rᵀ (p - robot)
        dist = math.hypot(ex, ey)
        angle = math.atan2(ey, ex) % (2 * math.pi)
        k = int(angle // binsize)
        sensor = max(0.0, max_dist - dist) / max_dist
        obs[k] = max(obs[k], sensor)
        a = angle / binsize - k
        obs[(k + 1) % num_bins] = max(obs[(k + 1) % num_bins], a * sensor)
        obs[(k - 1) % num_bins] = max(obs[(k - 1) % num_bins], (1 - a) * sensor)
    return np.array(obs)


def test_object_straight_ahead():
    out = pseudo_lidar(np.array([[1.0, 0.0]]), np.zeros(2), heading_to_rotation(0.0))
    expected = np.zeros(16)
    expected[0] = 2 / 3  # s = (3 - 1) / 3, bin 0
    expected[15] = 2 / 3  # alias a = 0 -> the previous bin gets (1 - a) s
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_object_inside_a_bin_aliases_into_both_neighbours():
    # 30° at distance 2: bin 1 (22.5°..45°), a = (30 - 22.5) / 22.5 = 1/3, s = 1/3
    p = 2.0 * np.array([[math.cos(math.radians(30)), math.sin(math.radians(30))]])
    out = pseudo_lidar(p, np.zeros(2), heading_to_rotation(0.0))
    expected = np.zeros(16)
    expected[1] = 1 / 3
    expected[2] = 1 / 3 * 1 / 3
    expected[0] = 2 / 3 * 1 / 3
    np.testing.assert_allclose(out, expected, atol=1e-12)


def test_robot_frame_rotation_and_translation():
    # Robot at (1, 1) facing +y; an object at world (1, 2) is straight ahead,
    # one at world (0, 1) is at 90° (to its left), one at (2, 1) at 270°.
    rot = heading_to_rotation(math.pi / 2)
    ahead = pseudo_lidar(np.array([[1.0, 2.0]]), np.array([1.0, 1.0]), rot)
    left = pseudo_lidar(np.array([[0.0, 1.0]]), np.array([1.0, 1.0]), rot)
    right = pseudo_lidar(np.array([[2.0, 1.0]]), np.array([1.0, 1.0]), rot)
    assert ahead[0] == pytest.approx(2 / 3) and ahead[15] == pytest.approx(2 / 3)
    assert left[4] == pytest.approx(2 / 3) and left[3] == pytest.approx(2 / 3)
    assert right[12] == pytest.approx(2 / 3) and right[11] == pytest.approx(2 / 3)
    for out in (ahead, left, right):
        assert np.count_nonzero(out > 1e-9) == 2


def test_bins_keep_the_max_and_far_objects_vanish():
    pts = np.array([[0.5, 0.05], [2.0, 0.1], [5.0, 0.0]])  # same bin; last beyond 3 m
    out = pseudo_lidar(pts, np.zeros(2), heading_to_rotation(0.0))
    near = pseudo_lidar(pts[:1], np.zeros(2), heading_to_rotation(0.0))
    np.testing.assert_allclose(out, near, atol=1e-12)
    assert pseudo_lidar(pts[2:], np.zeros(2), np.eye(2)).sum() == 0.0
    assert pseudo_lidar(np.zeros((0, 2)), np.zeros(2), np.eye(2)).shape == (16,)


def test_vectorised_lidar_equals_spec_pseudo_code():
    rng = np.random.default_rng(0)
    for _ in range(200):
        n = int(rng.integers(1, 12))
        pts = rng.uniform(-3.5, 3.5, size=(n, 2))
        robot = rng.uniform(-1, 1, size=2)
        heading = float(rng.uniform(0, 2 * math.pi))
        out = pseudo_lidar(pts, robot, heading_to_rotation(heading))
        np.testing.assert_allclose(out, reference_lidar(pts, robot, heading), atol=1e-12)


def test_grouped_lidar_equals_per_group():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-2, 2, size=(9, 2))
    groups = np.array([0, 1, 1, 1, 2, 2, 2, 2, 2])
    rot = heading_to_rotation(1.3)
    out = pseudo_lidar_groups(pts, groups, 3, np.zeros(2), rot)
    for g in range(3):
        np.testing.assert_allclose(out[g], pseudo_lidar(pts[groups == g], np.zeros(2), rot))


def test_lidar_rejects_too_few_bins():
    with pytest.raises(ValueError, match="num_bins >= 3"):
        pseudo_lidar(np.ones((1, 2)), np.zeros(2), np.eye(2), num_bins=2)


def test_observation_slices_44_dims():
    env = make_gym_env("dynamic")
    s = env.observation_slices()
    assert env.observation_space.shape == (44,)
    assert [(k, v.start, v.stop) for k, v in s.items()] == [
        ("accelerometer", 0, 3),
        ("goal_lidar", 3, 19),
        ("gyro", 19, 22),
        ("hazards_lidar", 22, 38),
        ("magnetometer", 38, 41),
        ("velocimeter", 41, 44),
    ]


@pytest.mark.parametrize("name", ["point_goal1", "point_goal2"])
def test_observation_slices_60_dims(name):
    env = make_gym_env(name)
    s = env.observation_slices()
    assert env.observation_space.shape == (60,)
    assert [(k, v.start, v.stop) for k, v in s.items()] == [
        ("accelerometer", 0, 3),
        ("goal_lidar", 3, 19),
        ("gyro", 19, 22),
        ("hazards_lidar", 22, 38),
        ("magnetometer", 38, 41),
        ("vases_lidar", 41, 57),
        ("velocimeter", 57, 60),
    ]


def test_env_observation_contents_in_sorted_key_order():
    env = make_gym_env("dynamic")
    heading = 0.4
    layout = {
        "robot_xy": (0.2, -0.1),
        "robot_heading": heading,
        "goal_xy": (1.0, 1.2),
        "hazards_xy": [(-1.0, 0.5), (0.8, -1.1), (-0.2, -1.3)],
    }
    obs, _info = env.reset(seed=0, options={"layout": layout})
    assert obs.dtype == np.float32 and obs.shape == (44,)
    np.testing.assert_allclose(obs[0:3], [0, 0, 9.81], atol=1e-5)  # accelerometer
    np.testing.assert_allclose(
        obs[3:19], reference_lidar([layout["goal_xy"]], layout["robot_xy"], heading), atol=1e-6
    )
    np.testing.assert_allclose(obs[19:22], 0.0)  # gyro at rest
    np.testing.assert_allclose(
        obs[22:38], reference_lidar(layout["hazards_xy"], layout["robot_xy"], heading), atol=1e-6
    )
    np.testing.assert_allclose(
        obs[38:41], [-0.5 * math.sin(heading), -0.5 * math.cos(heading), 0], atol=1e-6
    )
    np.testing.assert_allclose(obs[41:44], 0.0)  # velocimeter at rest
    for _ in range(20):
        obs, *_ = env.step(np.array([1.0, 0.0]))
    assert obs[41] > 0.3  # forward velocity in the robot frame, last slot
    assert abs(obs[42]) < 0.05 * obs[41]  # mostly forward


def test_vases_lidar_sees_vases_and_moves_with_them():
    env = make_gym_env("point_goal1")
    layout = {
        "robot_xy": (0.0, 0.0),
        "robot_heading": 0.0,
        "goal_xy": (1.3, 1.3),
        "hazards_xy": [(-1.3, 1.3 - 0.35 * i) for i in range(8)],
        "vases_xy": [(1.0, 0.0)],
    }
    obs, _ = env.reset(seed=0, options={"layout": layout})
    s = env.observation_slices()
    vases = obs[s["vases_lidar"]]
    expected = reference_lidar(env.vases_xy, (0.0, 0.0), 0.0)
    np.testing.assert_allclose(vases, expected, atol=1e-5)
    assert vases[0] == pytest.approx(2 / 3, abs=1e-4)


def test_lidar_in_env_for_placed_heading_matches_hand_values():
    env = make_gym_env("dynamic")
    # Robot at the origin facing +y; goal 1 m to its left (world (-1, 0)): bin 4.
    layout = {
        "robot_xy": (0.0, 0.0),
        "robot_heading": math.pi / 2,
        "goal_xy": (-1.0, 0.0),
        "hazards_xy": [(0.0, 2.0), (1.4, -1.4), (-1.4, -1.4)],
    }
    obs, _ = env.reset(seed=0, options={"layout": layout})
    goal = obs[env.observation_slices()["goal_lidar"]]
    expected = np.zeros(16)
    expected[4] = expected[3] = 2 / 3
    np.testing.assert_allclose(goal, expected, atol=1e-6)
    hazards = obs[env.observation_slices()["hazards_lidar"]]
    assert hazards[0] == pytest.approx(1 / 3, abs=1e-6)  # (0, 2) is straight ahead, 2 m
    assert hazards[15] == pytest.approx(1 / 3, abs=1e-6)
