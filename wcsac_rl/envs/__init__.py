"""Environments: the point-goal MuJoCo task, its presets, a tiny env and TorchRL wrapping.

Importing this package registers the gymnasium ids (idempotently):

=====================  =========================  ========================================
short name             gymnasium id               env
=====================  =========================  ========================================
``"static"``           ``wcsac_rl/StaticEnv-v0``  WCSAC StaticEnv (44-dim obs)
``"dynamic"``          ``wcsac_rl/DynamicEnv-v0`` WCSAC DynamicEnv (44-dim obs)
``"point_goal1"``      ``wcsac_rl/PointGoal1-v0`` Safety Gym PointGoal1 (60-dim obs)
``"point_goal2"``      ``wcsac_rl/PointGoal2-v0`` Safety Gym PointGoal2 (60-dim obs)
``"tiny"``             ``wcsac_rl/TinyHazard-v0`` :class:`TinyHazardEnv` (6-dim obs)
=====================  =========================  ========================================

Main entry points:

* :func:`make_env` — a TorchRL env with ``("next", "cost")`` ``[*B, 1]`` float32,
  ``episode_reward`` / ``episode_cost`` / ``step_count``; ``num_workers > 1`` gives a
  ``ParallelEnv``.
* :func:`make_env_creator` — a picklable creator for multi-process collectors.
* :func:`env_info` — obs/action sizes and episode length of a preset.
* :func:`check_cost_key` — a clear error for envs/tensordicts without a cost.
* :class:`PointGoalEnv`, :class:`TinyHazardEnv` — the gymnasium envs.
* :func:`make_safety_gymnasium_env` — the same conventions on top of safety-gymnasium.
* ``make_env("gymnasium", env_id="<registered id | module:callable>", cost_key="cost")``
  — your own gymnasium env with a cost in ``info`` (or safety-gymnasium's 6-tuple step):
  :mod:`wcsac_rl.envs.gymnasium_env` (``env=gymnasium env.id=...`` on the command line).

On headless Linux (no ``DISPLAY``) importing this package sets ``MUJOCO_GL=egl``
unless ``MUJOCO_GL`` is already set, so rendering works on servers.
"""

from wcsac_rl import _headless  # noqa: F401  (before mujoco: headless GL default)
from wcsac_rl.envs.batched_gym import BatchedGymEnv
from wcsac_rl.envs.gymnasium_env import (
    GYMNASIUM,
    EnvSourceError,
    make_user_gym_env,
    user_env_info,
)
from wcsac_rl.envs.info import COST_KEY, InfoReader, step_info_spec
from wcsac_rl.envs.layout import LayoutError
from wcsac_rl.envs.point_goal import PointGoalConfig, PointGoalEnv
from wcsac_rl.envs.presets import (
    GYM_IDS,
    PRESET_NAMES,
    PRESETS,
    env_title,
    get_preset,
    make_gym_env,
    register_envs,
)
from wcsac_rl.envs.safety_gymnasium import make_safety_gymnasium_env, wrap_safety_gymnasium
from wcsac_rl.envs.tiny import TinyHazardEnv
from wcsac_rl.envs.torchrl_env import (
    CostKeyError,
    CostSum,
    NonFiniteStepError,
    RejectNonFinite,
    check_cost_key,
    env_info,
    make_base_env,
    make_env,
    make_env_creator,
)

register_envs()

__all__ = [
    "COST_KEY",
    "GYMNASIUM",
    "GYM_IDS",
    "PRESETS",
    "PRESET_NAMES",
    "BatchedGymEnv",
    "CostKeyError",
    "CostSum",
    "EnvSourceError",
    "InfoReader",
    "LayoutError",
    "NonFiniteStepError",
    "PointGoalConfig",
    "PointGoalEnv",
    "RejectNonFinite",
    "TinyHazardEnv",
    "check_cost_key",
    "env_info",
    "env_title",
    "get_preset",
    "make_base_env",
    "make_env",
    "make_env_creator",
    "make_gym_env",
    "make_safety_gymnasium_env",
    "make_user_gym_env",
    "register_envs",
    "step_info_spec",
    "user_env_info",
    "wrap_safety_gymnasium",
]
