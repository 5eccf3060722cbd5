"""Your own gymnasium env with a per-step cost: ``env=gymnasium env.id=<id>``.

``env.id`` is a registered gymnasium id (``"my_package:MyTask-v0"`` imports
``my_package`` first) or ``"module:callable"`` called with ``env.kwargs``. The cost
comes from ``info[cost_key]`` or safety-gymnasium's 6-tuple step (:class:`CostFromStep`);
observations are flattened to float32 (:class:`FlatFloat32Observation`). What the env
must provide, and the one-line :class:`EnvSourceError` for each mistake:
docs/own_environment.md.
"""

from __future__ import annotations

import importlib
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import load_env_creator
from gymnasium.wrappers import TimeLimit

from wcsac_rl._messages import first_line
from wcsac_rl.envs.info import COST_KEY, CostKeyError

__all__ = [
    "GYMNASIUM",
    "CostFromStep",
    "EnvSourceError",
    "FlatFloat32Observation",
    "env_facts",
    "make_user_gym_env",
    "user_env_info",
]

GYMNASIUM = "gymnasium"
"""``env.name`` of the config group ``env=gymnasium`` (your own env, named by ``env.id``)."""

HOW_TO_NAME = "env.id must be a registered gymnasium id or module:callable on your Python path"


class EnvSourceError(ValueError):
    """A user's env cannot be found, built or used (the message is one line)."""


def _import(module: str, env_id: str) -> Any:
    try:
        return importlib.import_module(module)
    except Exception as err:
        missing = isinstance(err, ModuleNotFoundError) and err.name
        if missing and module.split(".")[0] == err.name.split(".")[0]:
            raise EnvSourceError(
                f"env.id={env_id}: no module named {module!r} on the Python path (put its "
                f"directory on PYTHONPATH); {HOW_TO_NAME}"
            ) from None
        raise EnvSourceError(
            f"env.id={env_id}: importing {module!r} failed ({first_line(err, with_type=True)})"
        ) from None


def _registered(env_id: str, kwargs: dict[str, Any]) -> tuple[gym.Env, int | None]:
    """A registered id's env without gymnasium's wrappers (they expect 5-tuple steps),
    and its registration's ``max_episode_steps``."""
    try:
        spec = gym.spec(env_id)
    except gym.error.Error as err:
        raise EnvSourceError(
            f"env.id={env_id}: {first_line(err, with_type=True)}; {HOW_TO_NAME}"
        ) from None
    try:
        creator = (
            spec.entry_point if callable(spec.entry_point) else load_env_creator(spec.entry_point)
        )
    except Exception as err:
        raise EnvSourceError(
            f"env.id={env_id}: its entry point {spec.entry_point!r} does not load "
            f"({first_line(err, with_type=True)})"
        ) from None
    return _call(creator, env_id, {**spec.kwargs, **kwargs}), spec.max_episode_steps


def _call(creator: Any, env_id: str, kwargs: dict[str, Any]) -> gym.Env:
    try:
        env = creator(**kwargs)
    except Exception as err:
        raise EnvSourceError(
            f"env.id={env_id}: building the env raised {first_line(err, with_type=True)}"
        ) from None
    if not isinstance(env, gym.Env):
        raise EnvSourceError(
            f"env.id={env_id}: the callable returned {type(env).__name__}, not a gymnasium.Env"
        )
    return env


def _resolve(env_id: str, kwargs: dict[str, Any]) -> tuple[gym.Env, int | None]:
    """The env ``env_id`` names, built with ``kwargs``, and its registered episode length."""
    if not isinstance(env_id, str) or not env_id.strip():
        raise EnvSourceError(f"env=gymnasium needs env.id=<id>, got {env_id!r}; {HOW_TO_NAME}")
    module, sep, attr = env_id.partition(":")
    if not sep:
        return _registered(env_id, kwargs)
    if not module or not attr:
        raise EnvSourceError(f"env.id={env_id}: {HOW_TO_NAME}")
    mod = _import(module, env_id)
    target = getattr(mod, attr, None)
    if callable(target):
        return _call(target, env_id, kwargs), None
    if attr in gym.registry:  # "module:Id-v0": the module registered the id on import
        return _registered(attr, kwargs)
    raise EnvSourceError(
        f"env.id={env_id}: module {module!r} has no callable {attr!r} and registered no "
        f"gymnasium id {attr!r}; {HOW_TO_NAME}"
    )


def _own_limit(env: gym.Env) -> int | None:
    """The episode length an env enforces itself: a ``TimeLimit`` among its wrappers (or
    its ``spec``), else a ``max_episode_steps`` attribute of the unwrapped env."""
    layer: Any = env
    while isinstance(layer, gym.Wrapper):
        # gymnasium's TimeLimit, or one like it (safety-gymnasium has its own)
        steps = getattr(layer, "_max_episode_steps", None)
        if isinstance(layer, TimeLimit) or isinstance(steps, (int, np.integer)):
            return int(steps)
        layer = layer.env
    spec = getattr(env, "spec", None)
    if spec is not None and spec.max_episode_steps:
        return int(spec.max_episode_steps)
    own = getattr(env.unwrapped, "max_episode_steps", None)
    if isinstance(own, (int, np.integer)) and not isinstance(own, bool) and own > 0:
        return int(own)
    return None


def _check_spaces(env: gym.Env, env_id: str) -> None:
    action = env.action_space
    if not isinstance(action, gym.spaces.Box):
        raise EnvSourceError(
            f"env.id={env_id} has a {type(action).__name__} action space; the kit's "
            "algorithms (WCSAC, SAC-Lag, SAC, CPO) need a continuous Box action space"
        )
    if not (np.isfinite(action.low).all() and np.isfinite(action.high).all()):
        raise EnvSourceError(
            f"env.id={env_id}: the action space's bounds must be finite (the actor squashes "
            f"its actions into them), got low={action.low.tolist()} high={action.high.tolist()}"
        )
    obs = env.observation_space
    if not isinstance(obs, gym.spaces.Box):
        raise EnvSourceError(
            f"env.id={env_id} has a {type(obs).__name__} observation space; the kit's "
            "networks read one Box of numbers (flatten a Dict/Tuple space in your env)"
        )


class FlatFloat32Observation(gym.ObservationWrapper):
    """A ``Box`` observation flattened to one dimension and cast to float32 (the kit's
    MLPs read ``observation`` as ``[*B, n]`` float32)."""

    def __init__(self, env: gym.Env, name: str | None = None) -> None:
        super().__init__(env)
        self.name = name or type(env.unwrapped).__name__
        space = env.observation_space
        self.observation_space = gym.spaces.Box(
            low=np.asarray(space.low, dtype=np.float32).reshape(-1),
            high=np.asarray(space.high, dtype=np.float32).reshape(-1),
            dtype=np.float32,
        )

    def observation(self, observation: Any) -> np.ndarray:
        flat = np.asarray(observation, dtype=np.float32).reshape(-1)
        if flat.shape != self.observation_space.shape:
            raise EnvSourceError(
                f"env.id={self.name}: an observation has {flat.size} numbers (shape "
                f"{np.shape(observation)}), its observation space "
                f"{self.observation_space.shape[0]}; the kit's networks read a fixed-size one"
            )
        return flat


class CostFromStep(gym.Wrapper):
    """Put a step's cost into ``info["cost"]``: from ``info[cost_key]`` or from
    safety-gymnasium's 6-tuple step (then returned as gymnasium's 5-tuple). A step without
    a cost raises :class:`~wcsac_rl.envs.info.CostKeyError` naming the key and the keys
    ``info`` had (a cost silently read as zero would train an unconstrained policy);
    ``name`` (the ``env.id``) names the env in messages.
    """

    def __init__(self, env: gym.Env, cost_key: str = COST_KEY, name: str | None = None) -> None:
        super().__init__(env)
        self.cost_key = str(cost_key)
        self.name = name or type(env.unwrapped).__name__
        self._steps = 0

    def reset(self, **kwargs: Any):
        self._steps = 0
        try:
            return self.env.reset(**kwargs)
        except Exception as err:  # your env's own error: one line naming it and the call
            raise EnvSourceError(
                f"env.id={self.name}: reset() raised {first_line(err, with_type=True)}"
            ) from None

    def step(self, action: Any):
        try:
            result = self.env.step(action)
        except Exception as err:  # your env's own error: one line naming it and the call
            raise EnvSourceError(
                f"env.id={self.name}: step() raised {first_line(err, with_type=True)} at step "
                f"{self._steps + 1} of an episode"
            ) from None
        self._steps += 1
        if len(result) == 6:  # safety-gymnasium: (obs, reward, cost, terminated, truncated, info)
            observation, reward, cost, terminated, truncated, info = result
        elif len(result) == 5:
            observation, reward, terminated, truncated, info = result
            cost = None if not isinstance(info, dict) else info.get(self.cost_key)
            if cost is None and isinstance(info, dict) and self.cost_key in info:
                raise CostKeyError(
                    f"env.id={self.name}: the cost at step {self._steps} is None (its info's "
                    f"{self.cost_key!r} entry); put the step's cost there as a number"
                )
            if cost is None:
                keys = sorted(map(str, info)) if isinstance(info, dict) else []
                raise CostKeyError(
                    f"env.id={self.name} reported no cost at step {self._steps}: its info has "
                    f"no {self.cost_key!r} entry (info keys: {keys}); put the per-step cost "
                    "in info, name its key with env.cost_key=<key>, or return "
                    "(obs, reward, cost, terminated, truncated, info)"
                )
        else:
            raise EnvSourceError(
                f"env.id={self.name}: step() returned {len(result)} values; expected "
                "(obs, reward, terminated, truncated, info) or safety-gymnasium's "
                "(obs, reward, cost, terminated, truncated, info)"
            )
        info = dict(info or {})
        try:
            info[COST_KEY] = float(np.asarray(cost, dtype=np.float64).reshape(()))
        except (TypeError, ValueError):
            raise CostKeyError(
                f"env.id={self.name}: the cost at step {self._steps} is not one number: {cost!r}"
            ) from None
        return observation, reward, bool(terminated), bool(truncated), info


def make_user_gym_env(
    env_id: str,
    *,
    cost_key: str = COST_KEY,
    max_episode_steps: int | None = None,
    **kwargs: Any,
) -> gym.Env:
    """Your gymnasium env, ready for the kit's TorchRL wrapping: the cost in
    ``info["cost"]`` (:class:`CostFromStep`), float32 flat observations, and a
    ``TimeLimit`` of ``max_episode_steps`` (default: the env's own limit; required when it
    has none). ``kwargs`` go to the callable or the registered env's constructor.
    :class:`EnvSourceError` (one line): the id does not resolve, building the env raises,
    a space the kit cannot train on, or no episode length.
    """
    env, registered = _resolve(env_id, dict(kwargs))
    try:
        _check_spaces(env, env_id)
        own = _own_limit(env)
        limit = max_episode_steps if max_episode_steps is not None else (registered or own)
        if limit is None:
            raise EnvSourceError(
                f"env.id={env_id} has no episode length of its own (no TimeLimit, no "
                "max_episode_steps); set env.max_episode_steps=<steps>"
            )
        env = FlatFloat32Observation(CostFromStep(env, cost_key=cost_key, name=env_id), env_id)
        if max_episode_steps is not None or own is None or registered is not None:
            env = TimeLimit(env, max_episode_steps=int(limit))
    except BaseException:
        env.close()
        raise
    return env


def user_env_info(
    env_id: str,
    *,
    cost_key: str = COST_KEY,
    max_episode_steps: int | None = None,
    **kwargs: Any,
) -> dict[str, Any]:
    """:func:`~wcsac_rl.envs.env_info` for your env, after one probing reset and step
    (a random action): the step must report a cost (:class:`CostFromStep`).

    The episode length is the tightest limit on it (``max_episode_steps`` or the env's
    own, whichever ends episodes first)."""
    env = make_user_gym_env(
        env_id, cost_key=cost_key, max_episode_steps=max_episode_steps, **kwargs
    )
    try:
        limits = [limit for limit in (_own_limit(env), _inner_limit(env)) if limit]
        env.action_space.seed(0)
        try:
            env.reset(seed=0)
            env.step(env.action_space.sample())
        except (EnvSourceError, CostKeyError):
            raise
        except Exception as err:
            raise EnvSourceError(
                f"env.id={env_id}: a probing reset and step raised {first_line(err, with_type=True)}"
            ) from None
        description = f"your gymnasium env {env_id} (cost from info[{cost_key!r}])"
        return env_facts(env, GYMNASIUM, env_id, min(limits), {}, description)
    finally:
        env.close()


def env_facts(
    env: gym.Env,
    name: str,
    gym_id: str,
    max_episode_steps: int,
    observation_slices: dict[str, slice],
    description: str,
) -> dict[str, Any]:
    """:func:`~wcsac_rl.envs.env_info`'s dict: the given facts and ``env``'s spaces."""
    return {
        "name": name,
        "gym_id": gym_id,
        "max_episode_steps": int(max_episode_steps),
        "obs_dim": int(np.prod(env.observation_space.shape)),
        "action_dim": int(np.prod(env.action_space.shape)),
        "action_low": float(np.min(env.action_space.low)),
        "action_high": float(np.max(env.action_space.high)),
        "cost_key": ("next", COST_KEY),
        "observation_slices": observation_slices,
        "description": description,
    }


def _inner_limit(env: gym.Env) -> int | None:
    """The env's own limit below the kit's wrappers (a ``TimeLimit`` the user's env has)."""
    layer: Any = env
    while isinstance(layer, gym.Wrapper) and not isinstance(layer, CostFromStep):
        layer = layer.env
    return _own_limit(layer.env) if isinstance(layer, CostFromStep) else None
