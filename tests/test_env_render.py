"""Rendering (rgb_array through mujoco.Renderer; headless with MUJOCO_GL=egl)."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from wcsac_rl.envs import make_env, make_gym_env


@pytest.fixture(scope="module")
def render_env():
    env = make_gym_env("dynamic", render_mode="rgb_array", width=96, height=80)
    env.reset(seed=0)
    try:
        env.render()
    except Exception as err:  # no GL backend on this machine
        env.close()
        pytest.skip(f"MuJoCo rendering unavailable (set MUJOCO_GL=egl): {err}")
    yield env
    env.close()


def test_rgb_array_frames(render_env):
    layout = {"robot_xy": (-1.0, 0.0), "robot_heading": 0.0}
    render_env.reset(seed=0, options={"layout": layout})
    first = render_env.render()
    assert first.shape == (80, 96, 3) and first.dtype == np.uint8
    assert first.std() > 5  # not a blank image
    for _ in range(40):
        render_env.step(np.array([1.0, 0.0]))
    assert not np.array_equal(first, render_env.render())


def test_render_without_mode_returns_none():
    env = make_gym_env("dynamic")
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None


def test_hazards_and_goal_are_visual_only():
    env = make_gym_env("point_goal2")
    m = env.model
    for i in range(m.ngeom):
        name = m.geom(i).name
        if name.startswith("hazard") or name == "goal":
            assert m.geom_contype[i] == 0 and m.geom_conaffinity[i] == 0, name
    assert m.ntex == 0  # no skybox or textures


def test_make_env_from_pixels(render_env):
    env = make_env("dynamic", seed=0, from_pixels=True, width=64, height=48)
    td = env.rollout(3)
    assert td["next", "pixels"].shape == (3, 48, 64, 3)
    assert td["next", "pixels"].dtype == torch.uint8
    assert td["next", "observation"].shape == (3, 44)
    assert td["next", "cost"].shape == (3, 1)
    env.close()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the rule is Linux's")
@pytest.mark.parametrize(
    ("display", "preset", "expected"),
    [(None, None, "egl"), (None, "glfw", "glfw"), (":0", None, "unset")],
)
def test_importing_the_package_picks_egl_only_on_a_headless_machine(display, preset, expected):
    """``import wcsac_rl`` (before anything imports mujoco) sets ``MUJOCO_GL=egl`` when
    there is no display and the user chose nothing."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "MUJOCO_GL")}
    env.update({k: v for k, v in (("DISPLAY", display), ("MUJOCO_GL", preset)) if v})
    code = "import os, wcsac_rl; print(os.environ.get('MUJOCO_GL', 'unset'))"
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip().splitlines()[-1] == expected
