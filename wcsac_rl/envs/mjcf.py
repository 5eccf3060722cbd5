"""MJCF (MuJoCo XML) of the point-goal world, generated in code.

Every physics fact it sets (timestep, floor, the robot body that glides on purpose, the
saturated actuators, the sensors' order) is described in docs/point_goal.md, "World and
robot". Hazards and the goal are mocap bodies with purely visual geoms
(``contype = conaffinity = 0``); vases are free boxes. Rendering assets are
deliberately light: no skybox, no textures, no shadows.
"""

from __future__ import annotations

import functools

__all__ = [
    "ROBOT_GEOMS",
    "SENSOR_SLICES",
    "build_point_goal_mjcf",
    "vase_rest_height",
]

ROBOT_GEOMS = ("robot", "robot_heading")
"""Names of the robot's collision geoms."""

SENSOR_SLICES = {
    "accelerometer": slice(0, 3),
    "velocimeter": slice(3, 6),
    "gyro": slice(6, 9),
    "magnetometer": slice(9, 12),
}
"""Where each robot sensor lives in ``MjData.sensordata``."""

_GOAL_RGBA = "0.2 0.9 0.2 0.35"
_HAZARD_RGBA = "0.25 0.25 1.0 0.45"
_VASE_RGBA = "0.0 0.9 0.9 1.0"
_ROBOT_RGBA = "0.741 0.043 0.184 1.0"


def build_point_goal_mjcf(
    *,
    hazards_num: int,
    hazards_size: float,
    goal_size: float,
    vases_num: int = 0,
    vases_size: float = 0.1,
    vases_density: float = 0.001,
    floor_half_size: float = 3.5,
    camera_distance: float = 1.5,
) -> str:
    """The MJCF string of a point-goal world: mocap bodies ``hazard{i}`` and ``goal`` (drawn
    only, of radius ``hazards_size`` / ``goal_size``), free bodies ``vase{i}`` (boxes of
    half-size ``vases_size``), a floor drawn ``floor_half_size`` each way and cameras framing
    ``camera_distance`` (the placement extents). Positions are not part of the model: the env
    sets them at every reset (robot joints, ``mocap_pos``, the vases' free joints).
    """
    d = camera_distance
    hazards = "\n".join(
        f'    <body name="hazard{i}" mocap="true" pos="0 0 0">\n'
        f'      <geom name="hazard{i}" type="cylinder" size="{hazards_size} 0.005" '
        f'pos="0 0 0.005" contype="0" conaffinity="0" group="1" rgba="{_HAZARD_RGBA}"/>\n'
        f"    </body>"
        for i in range(hazards_num)
    )
    vases = "\n".join(
        f'    <body name="vase{i}" pos="0 0 {vases_size}">\n'
        f'      <freejoint name="vase{i}"/>\n'
        f'      <geom name="vase{i}" type="box" size="{vases_size} {vases_size} {vases_size}" '
        f'density="{vases_density}" condim="6" rgba="{_VASE_RGBA}"/>\n'
        f"    </body>"
        for i in range(vases_num)
    )
    return f"""<mujoco model="point_goal">
  <compiler angle="radian"/>
  <option timestep="0.002" integrator="Euler" gravity="0 0 -9.81" magnetic="0 -0.5 0"/>
  <visual>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.6 0.6 0.6" specular="0 0 0"/>
    <quality shadowsize="0"/>
  </visual>
  <worldbody>
    <light name="top" pos="0 0 6" dir="0 0 -1" diffuse="0.4 0.4 0.4" castshadow="false"/>
    <geom name="floor" type="plane" size="{floor_half_size} {floor_half_size} 0.1"
          friction="1 0.005 0.0001" condim="6" rgba="0.93 0.93 0.93 1"/>
    <camera name="overview" pos="0 {-2.2 * d:.4f} {2.6 * d:.4f}" xyaxes="1 0 0 0 0.76 0.65" fovy="50"/>
    <camera name="top" pos="0 0 {2.9 * d:.4f}" xyaxes="1 0 0 0 1 0" fovy="45"/>
    <body name="robot" pos="0 0 0.1">
      <joint name="robot_x" type="slide" axis="1 0 0" damping="0.01" armature="0"/>
      <joint name="robot_y" type="slide" axis="0 1 0" damping="0.01" armature="0"/>
      <joint name="robot_z" type="hinge" axis="0 0 1" damping="0.005" armature="0"/>
      <geom name="robot" type="sphere" size="0.1" density="1" condim="6"
            friction="1 0.01 0.01" rgba="{_ROBOT_RGBA}"/>
      <geom name="robot_heading" type="box" size="0.05 0.05 0.05" pos="0.1 0 0" density="1"
            condim="6" rgba="{_ROBOT_RGBA}"/>
      <site name="robot" pos="0 0 0" size="0.03" rgba="1 0 0 0.1"/>
    </body>
    <body name="goal" mocap="true" pos="0 0 0">
      <geom name="goal" type="cylinder" size="{goal_size} 0.05" pos="0 0 0.05"
            contype="0" conaffinity="0" group="1" rgba="{_GOAL_RGBA}"/>
    </body>
{hazards}
{vases}
  </worldbody>
  <actuator>
    <motor name="forward" site="robot" gear="0.3 0 0 0 0 0" ctrllimited="true" ctrlrange="-1 1"
           forcelimited="true" forcerange="-0.05 0.05"/>
    <velocity name="turn" joint="robot_z" kv="1" gear="0.3" ctrllimited="true" ctrlrange="-1 1"
              forcelimited="true" forcerange="-0.05 0.05"/>
  </actuator>
  <sensor>
    <accelerometer name="accelerometer" site="robot"/>
    <velocimeter name="velocimeter" site="robot"/>
    <gyro name="gyro" site="robot"/>
    <magnetometer name="magnetometer" site="robot"/>
  </sensor>
</mujoco>
"""


@functools.lru_cache(maxsize=8)
def vase_rest_height(vases_size: float = 0.1, vases_density: float = 0.001) -> float:
    """Height of a vase's centre when it rests on the floor under gravity (MuJoCo's soft
    contacts let it sink about 4.4e-5; Safety Gym hard-coded 4e-5): placed there, an
    untouched vase stays still and never costs. Measured once per process by letting one
    vase settle in a minimal world with the same floor and options.
    """
    import mujoco  # local: this module stays importable without MuJoCo

    xml = f"""<mujoco>
  <option timestep="0.002" integrator="Euler" gravity="0 0 -9.81"/>
  <worldbody>
    <geom type="plane" size="1 1 0.1" friction="1 0.005 0.0001" condim="6"/>
    <body pos="0 0 {vases_size}"><freejoint/>
      <geom type="box" size="{vases_size} {vases_size} {vases_size}" density="{vases_density}"
            condim="6"/>
    </body>
  </worldbody>
</mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, nstep=2000)
    return float(data.qpos[2])
