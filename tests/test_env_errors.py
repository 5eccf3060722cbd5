"""Bad input gets one clear error: names, layouts, actions, options, configs."""

from __future__ import annotations

import numpy as np
import pytest

from wcsac_rl.envs import PointGoalConfig, env_title, get_preset, make_gym_env


@pytest.fixture(scope="module")
def env():
    e = make_gym_env("dynamic")
    yield e
    e.close()


def test_unknown_preset_lists_valid_names():
    with pytest.raises(ValueError) as err:
        get_preset("StaticEnv-v1")
    msg = str(err.value)
    for name in ("static", "dynamic", "point_goal1", "point_goal2", "tiny"):
        assert f"'{name}'" in msg
    assert "wcsac_rl/StaticEnv-v0" in msg
    with pytest.raises(ValueError, match="valid names"):
        make_gym_env(None)
    # short names are case-insensitive, gym ids work too
    assert get_preset("Static").name == "static"
    assert get_preset("wcsac_rl/PointGoal2-v0").name == "point_goal2"


def test_env_title_names_a_preset_by_its_gymnasium_id_and_leaves_other_names_alone():
    """The title reports and resume hints print: the gym id's name without its version."""
    assert env_title("static") == "StaticEnv"
    assert env_title("dynamic") == "DynamicEnv"
    assert env_title("wcsac_rl/PointGoal2-v0") == "PointGoal2"
    assert env_title("my_own_env") == "my_own_env"  # a user's env: its own name


@pytest.mark.parametrize(
    ("layout", "match"),
    [
        ([(0, 0)], "must be a dict"),
        ({"robot": (0, 0)}, r"unknown layout key\(s\) \['robot'\]; valid keys"),
        ({"robot_xy": (0, 0, 0)}, r"robot_xy.*\(x, y\) pair.*shape \(3,\)"),
        ({"robot_xy": ("a", 0)}, r"robot_xy.*\(x, y\) pair of numbers"),
        ({"robot_xy": (np.nan, 0)}, "robot_xy.*finite"),
        ({"goal_xy": 1.0}, r"goal_xy.*\(x, y\) pair"),
        ({"robot_heading": "north"}, "robot_heading.*number"),
        ({"robot_heading": np.inf}, "robot_heading.*finite"),
        ({"hazards_xy": [(0, 0), (1, 1)]}, r"hazards_xy.*3 \(x, y\) pairs \(this env has 3\)"),
        ({"hazards_xy": [(0, 0), (1, 1), (1, None)]}, "hazards_xy.*finite|hazards_xy.*pairs"),
        ({"vases_xy": [(0, 0)]}, r"vases_xy.*0 \(x, y\) pairs"),
    ],
)
def test_malformed_layouts(env, layout, match):
    with pytest.raises(ValueError, match=match):
        env.reset(seed=0, options={"layout": layout})


def test_bad_reset_options(env):
    with pytest.raises(ValueError, match="options must be a dict"):
        env.reset(options=[("layout", {})])
    with pytest.raises(ValueError, match=r"unknown reset option\(s\) \['layot'\]"):
        env.reset(options={"layot": {}})
    env.reset(options={"layout": None})  # None means "no explicit layout"


@pytest.mark.parametrize(
    ("action", "match"),
    [
        (np.zeros(3), r"shape \(2,\), got shape \(3,\)"),
        (np.zeros((1, 2)), r"shape \(2,\), got shape \(1, 2\)"),
        (0.5, r"shape \(2,\), got shape \(\)"),
        (["a", "b"], "numeric"),
        (np.array([True, False]), "numeric"),
        (np.array([object(), 1], dtype=object), "numeric"),
        (np.array([np.nan, 0.0]), "finite"),
        (np.array([np.inf, 0.0]), "finite"),
    ],
)
def test_bad_actions(env, action, match):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(action)


def test_good_action_types(env):
    env.reset(seed=0)
    for action in ([0.1, -0.2], (1, 0), np.array([0.5, 0.5], dtype=np.float32), np.array([2, -3])):
        env.step(action)


def test_step_before_reset():
    fresh = make_gym_env("static")
    with pytest.raises(RuntimeError, match=r"before reset\(\)"):
        fresh.step(np.zeros(2))


def test_bad_constructor_arguments():
    with pytest.raises(ValueError, match=r"unknown PointGoalEnv option.*hazard_size"):
        make_gym_env("dynamic", hazard_size=0.3)
    with pytest.raises(ValueError, match="render_mode"):
        make_gym_env("dynamic", render_mode="human")
    with pytest.raises(ValueError, match="hazards_locations has 1 entries for hazards_num=2"):
        PointGoalConfig(hazards_num=2, hazards_locations=((0.0, 0.0),))
    with pytest.raises(ValueError, match="hazards_num must be a non-negative int"):
        PointGoalConfig(hazards_num=-1)
    with pytest.raises(ValueError, match="placement_extents"):
        PointGoalConfig(placement_extents=(1.0, -1.0, -1.0, 1.0))
