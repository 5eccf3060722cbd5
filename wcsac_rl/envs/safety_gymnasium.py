"""Adapter for users who have ``safety_gymnasium`` installed.

TorchRL's :class:`torchrl.envs.libs.safety_gymnasium.SafetyGymnasiumEnv` folds
safety-gymnasium's 6-tuple ``step`` into a root ``"cost"`` shaped ``[*B]``, ``float64``;
:func:`wrap_safety_gymnasium` puts the project's conventions on top (those of
:func:`~wcsac_rl.envs.make_env`). Where safety-gymnasium does not install or import (it
does not with gymnasium 1.x), :func:`make_safety_gymnasium_env` raises an
``ImportError`` that says so and points at the built-in presets.
"""

from __future__ import annotations

import importlib.util
from typing import Any

import torch
from torchrl.envs import (
    Compose,
    DoubleToFloat,
    EnvBase,
    TransformedEnv,
    UnsqueezeTransform,
)

from wcsac_rl.envs.info import COST_KEY
from wcsac_rl.envs.torchrl_env import check_cost_key, episode_transforms

__all__ = [
    "SAFETY_GYMNASIUM_MISSING",
    "make_safety_gymnasium_env",
    "safety_gymnasium_available",
    "wrap_safety_gymnasium",
]

SAFETY_GYMNASIUM_MISSING = (
    "safety_gymnasium is not installed (or failed to import), so "
    "make_safety_gymnasium_env() cannot build {name!r}. Install it with "
    "`pip install safety-gymnasium` in an environment where it is supported (it needs "
    "an older gymnasium/Python than this project's), or use the built-in equivalent "
    "tasks: wcsac_rl.envs.make_env('static' | 'dynamic' | 'point_goal1' | 'point_goal2')."
)
"""Message of the ``ImportError`` raised when safety-gymnasium is unavailable."""


def safety_gymnasium_available() -> bool:
    """Whether ``import safety_gymnasium`` succeeds."""
    if importlib.util.find_spec("safety_gymnasium") is None:
        return False
    try:
        import safety_gymnasium  # noqa: F401
    except Exception:  # it may be installed but break on import (gymnasium 1.x)
        return False
    return True


def wrap_safety_gymnasium(env: EnvBase) -> TransformedEnv:
    """Put the project's conventions on a TorchRL safety-gymnasium env (a root ``"cost"``
        entry shaped ``[*B]`` or ``[*B, 1]``): ``("next", "cost")`` shaped ``[*B, 1]``
        ``float32``, ``float64`` observations cast to ``float32``, and ``step_count`` /
        ``episode_reward`` / ``episode_cost``; :class:`~wcsac_rl.envs.info.CostKeyError` without
    a ``"cost"`` entry.
    """
    check_cost_key(env)
    transforms = []
    obs_spec = env.full_observation_spec
    if tuple(obs_spec[COST_KEY].shape) == tuple(env.batch_size):
        transforms.append(UnsqueezeTransform(-1, in_keys=[COST_KEY]))
    doubles = [key for key, spec in obs_spec.items(True, True) if spec.dtype == torch.float64]
    if doubles or env.full_reward_spec["reward"].dtype == torch.float64:
        reward_keys = ["reward"] if env.full_reward_spec["reward"].dtype == torch.float64 else []
        transforms.append(DoubleToFloat(in_keys=doubles + reward_keys))
    transforms.extend(episode_transforms())
    return TransformedEnv(env, Compose(*transforms))


def make_safety_gymnasium_env(
    env_name: str,
    *,
    seed: int | None = None,
    device: torch.device | str = "cpu",
    **kwargs: Any,
) -> TransformedEnv:
    """A safety-gymnasium task (e.g. ``"SafetyPointGoal1-v0"``) with the project's keys,
    seeded ``seed``; ``kwargs`` go to TorchRL's ``SafetyGymnasiumEnv``. ``ImportError``
    (:data:`SAFETY_GYMNASIUM_MISSING`) where safety-gymnasium is not available.
    """
    if not safety_gymnasium_available():
        raise ImportError(SAFETY_GYMNASIUM_MISSING.format(name=env_name))
    from torchrl.envs.libs.safety_gymnasium import SafetyGymnasiumEnv

    env = wrap_safety_gymnasium(SafetyGymnasiumEnv(env_name=env_name, device=device, **kwargs))
    if seed is not None:
        env.set_seed(int(seed))
    return env
