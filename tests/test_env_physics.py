"""Physics facts of the point robot (docs/point_goal.md, "World and robot").

Tolerances: MuJoCo integrates in float64 (ε = 2⁻⁵²), so rounding is 10⁸ times below
every tolerance here; ``rel=1e-9`` and the ``1e-6`` on sensors at rest are float64 sums
of a few terms and float32 observations (2⁻²⁴ ≈ 6e-8 relative); the percent-level ones
(``rel=0.01``–``0.03``) bound the gap between the closed-form physics and the
integrated dynamics (discretisation, contact), not rounding.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from wcsac_rl.envs import make_gym_env

# Far-away objects so that nothing interferes with the robot near the origin.
FAR_GOAL = (1.4, 1.4)
FAR_HAZARDS = [(-1.4, 1.4), (1.4, -1.4), (-1.4, -1.4)]
FORCE = 0.05 * 0.3  # forcerange x gear: saturated forward force (N)
SLIDE_DAMPING = 0.01
HINGE_DAMPING = 0.005


def _reset(env, heading=0.0, robot_xy=(0.0, 0.0)):
    layout = {
        "robot_xy": robot_xy,
        "robot_heading": heading,
        "goal_xy": FAR_GOAL,
        "hazards_xy": FAR_HAZARDS,
    }
    return env.reset(seed=0, options={"layout": layout})


@pytest.fixture
def env():
    e = make_gym_env("dynamic")
    yield e
    e.close()


def _robot_mass(env) -> float:
    return float(env.model.body_mass[env.model.body("robot").id])


def test_mass_matches_density_one_geoms(env):
    sphere = 4.0 / 3.0 * math.pi * 0.1**3
    box = 0.1**3
    assert _robot_mass(env) == pytest.approx(sphere + box, rel=1e-9)
    assert _robot_mass(env) == pytest.approx(0.0051888, rel=1e-4)


def test_model_options(env):
    opt = env.model.opt
    assert opt.timestep == 0.002
    assert opt.integrator == mujoco.mjtIntegrator.mjINT_EULER
    np.testing.assert_allclose(opt.gravity, [0, 0, -9.81])
    np.testing.assert_allclose(opt.magnetic, [0, -0.5, 0])
    assert env.dt == pytest.approx(0.02)
    # robot body exactly at z = 0.1, no z translation joint
    assert env.model.body("robot").pos[2] == 0.1
    assert env.model.nq == 3 and env.model.nv == 3  # dynamic preset: robot only


def test_forward_speed_after_one_second_and_top_speed(env):
    obs, _ = _reset(env)
    vel = env.observation_slices()["velocimeter"]
    for _ in range(50):  # 50 env steps = 1 s
        obs, *_ = env.step(np.array([1.0, 0.0]))
    m = _robot_mass(env)
    expected = FORCE / SLIDE_DAMPING * (1.0 - math.exp(-SLIDE_DAMPING / m * 1.0))
    assert expected == pytest.approx(1.28, abs=0.005)
    assert obs[vel][0] == pytest.approx(expected, rel=0.02)
    assert obs[vel][0] == pytest.approx(1.28, rel=0.03)
    for _ in range(450):  # 10 s in total: terminal velocity F / c
        obs, *_ = env.step(np.array([1.0, 0.0]))
    assert obs[vel][0] == pytest.approx(FORCE / SLIDE_DAMPING, rel=0.01)
    assert obs[vel][0] == pytest.approx(1.5, rel=0.01)


def test_forward_force_saturates_at_005(env):
    trajectories = {}
    for a in (0.05, 1.0, 0.02):
        _reset(env)
        qpos = []
        for _ in range(30):
            env.step(np.array([a, 0.0]))
            qpos.append(env.data.qpos.copy())
        trajectories[a] = np.array(qpos)
    np.testing.assert_array_equal(trajectories[0.05], trajectories[1.0])
    assert trajectories[0.02][-1, 0] < 0.5 * trajectories[1.0][-1, 0]


def test_action_is_clipped(env):
    _reset(env)
    out_big = [env.step(np.array([5.0, -7.0]))[0] for _ in range(5)]
    _reset(env)
    out_one = [env.step(np.array([1.0, -1.0]))[0] for _ in range(5)]
    np.testing.assert_array_equal(np.array(out_big), np.array(out_one))


def test_max_turn_rate_is_about_3(env):
    obs, _ = _reset(env)
    gyro = env.observation_slices()["gyro"]
    for _ in range(50):
        obs, *_ = env.step(np.array([0.0, 1.0]))
    w_max = FORCE / HINGE_DAMPING  # saturated servo torque balanced by damping
    assert w_max == pytest.approx(3.0)
    assert obs[gyro][2] == pytest.approx(w_max, rel=0.02)
    for _ in range(50):
        obs, *_ = env.step(np.array([0.0, -1.0]))
    assert obs[gyro][2] == pytest.approx(-w_max, rel=0.02)


def test_robot_glides_slowed_only_by_joint_damping(env):
    _obs, _ = _reset(env)
    for _ in range(50):
        env.step(np.array([1.0, 0.0]))
    v0 = float(env.data.qvel[0])
    coast_steps = 25  # 0.5 s without forward force
    for _ in range(coast_steps):
        env.step(np.array([0.0, 0.0]))
    v1 = float(env.data.qvel[0])
    m = _robot_mass(env)
    # MuJoCo's Euler integrator treats joint damping implicitly: per substep
    # v <- v / (1 + h c / m); the continuous solution is v0 exp(-c t / m).
    h = env.model.opt.timestep
    discrete = v0 / (1.0 + h * SLIDE_DAMPING / m) ** (coast_steps * 10)
    continuous = v0 * math.exp(-SLIDE_DAMPING / m * coast_steps * env.dt)
    assert v1 == pytest.approx(discrete, rel=1e-3)
    assert v1 == pytest.approx(continuous, rel=0.01)
    # With floor friction (mu = 1) it would stop within ~0.15 s.
    assert v1 > 0.3 * v0


def test_lowering_the_body_kills_the_glide(env):
    """The glide depends on z = 0.1 exactly: 1e-4 lower, the sphere rubs the floor."""
    xml = env.mjcf.replace(
        '<body name="robot" pos="0 0 0.1">', '<body name="robot" pos="0 0 0.0999">'
    )
    assert xml != env.mjcf
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    data.ctrl[:] = [1.0, 0.0]
    mujoco.mj_step(model, data, nstep=500)
    assert abs(data.qvel[0]) < 0.05


def test_accelerometer_reads_gravity(env):
    obs, _ = _reset(env, heading=1.0)
    acc = obs[env.observation_slices()["accelerometer"]]
    np.testing.assert_allclose(acc, [0.0, 0.0, 9.81], atol=1e-6)
    obs, *_ = env.step(np.array([0.0, 0.0]))
    np.testing.assert_allclose(
        obs[env.observation_slices()["accelerometer"]], [0, 0, 9.81], atol=1e-6
    )


@pytest.mark.parametrize("heading", [0.0, 0.7, math.pi / 2, 2.5, math.pi, 4.0, 5.9])
def test_magnetometer_is_a_compass(env, heading):
    obs, _ = _reset(env, heading=heading)
    mag = obs[env.observation_slices()["magnetometer"]]
    expected = [-0.5 * math.sin(heading), -0.5 * math.cos(heading), 0.0]
    np.testing.assert_allclose(mag, expected, atol=1e-6)


def test_turn_servo_chatters_with_zero_command(env):
    """Reproduced on purpose: the saturated turn servo oscillates at this timestep."""
    obs, _ = _reset(env)
    gyro = env.observation_slices()["gyro"]
    for _ in range(10):
        env.step(np.array([0.0, 1.0]))
    headings, readings = [], []
    for _ in range(20):
        obs, *_, info = env.step(np.array([0.0, 0.0]))
        readings.append(obs[gyro][2])
        headings.append(info["robot_heading"])
    readings = np.abs(np.array(readings))
    assert np.all(readings > 0.4), readings  # ≈ 0.48 rad/s although the command is 0
    assert np.all(readings < 0.55)
    # ... while the heading itself barely moves: it is an oscillation, not a turn.
    assert np.max(np.abs(np.diff(headings))) < 1e-3


def test_no_chatter_from_rest(env):
    obs, _ = _reset(env)
    for _ in range(10):
        obs, *_ = env.step(np.array([0.0, 0.0]))
    np.testing.assert_array_equal(obs[env.observation_slices()["gyro"]], 0.0)
