"""Environments: the point-goal MuJoCo task, its presets, a tiny env and TorchRL wrapping.

Importing this package registers the presets' gymnasium ids (idempotently; the table:
docs/environments.md). Main entry points: :func:`make_env` (a TorchRL env with
``("next", "cost")``), :func:`make_env_creator` (picklable, for multi-process
collectors), :func:`env_info`, :func:`check_cost_key`, the gymnasium envs
:class:`PointGoalEnv` and :class:`TinyHazardEnv`, :func:`make_safety_gymnasium_env`,
and ``make_env("gymnasium", env_id=...)`` for your own env
(:mod:`wcsac_rl.envs.gymnasium_env`, docs/own_environment.md).

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
