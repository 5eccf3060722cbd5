"""TorchRL wrapping of the presets: ``make_env`` and its helpers.

The entries of ``make_env``'s tensordicts (the cost, the info entries, the episode
sums): docs/environments.md. With ``num_workers > 1`` the base envs run in a
``ParallelEnv`` (one process each), or with ``parallel=False`` in this process as one
:class:`~wcsac_rl.envs.BatchedGymEnv` (what training and evaluation use); for
TorchRL's multi-process collectors pass :func:`make_env_creator` (picklable). The
``info`` entries come from :mod:`wcsac_rl.envs.info`, the one reading rule both paths
share.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite
from torchrl.envs import (
    Compose,
    EnvBase,
    ParallelEnv,
    RewardSum,
    SerialEnv,
    StepCounter,
    Transform,
    TransformedEnv,
)
from torchrl.envs.libs.gym import GymWrapper

from wcsac_rl.envs.batched_gym import BatchedGymEnv
from wcsac_rl.envs.gymnasium_env import GYMNASIUM, env_facts, make_user_gym_env, user_env_info
from wcsac_rl.envs.info import COST_KEY, CostKeyError, InfoReader, step_info_spec
from wcsac_rl.envs.presets import get_preset, make_gym_env

__all__ = [
    "COST_KEY",
    "CostKeyError",
    "CostSum",
    "InfoReader",
    "NonFiniteStepError",
    "RejectNonFinite",
    "check_cost_key",
    "env_info",
    "env_transforms",
    "episode_transforms",
    "make_base_env",
    "make_env",
    "make_env_creator",
    "step_info_spec",
]


class NonFiniteStepError(ValueError):
    """An env step (or reset) gave a NaN or infinite reward, cost or observation."""


def _finite(value: Any) -> bool:
    if isinstance(value, (float, int)):  # the common case: a Python or NumPy float
        return math.isfinite(value)
    return bool(np.isfinite(np.asarray(value, dtype=np.float64)).all())


def _env_name(env: gym.Env) -> str:
    spec = getattr(env, "spec", None)
    return spec.id if spec is not None and spec.id else type(env.unwrapped).__name__


class RejectNonFinite(gym.Wrapper):
    """Raise :class:`NonFiniteStepError` when a step's reward, ``info["cost"]`` or
    observation is not finite (NaN or ±inf), naming the env (``name``, default its
    gymnasium id, else its class name) and the step: one non-finite cost in a replay buffer
    makes every loss that samples it NaN, and stopping at the env says where it came from.
    """

    def __init__(self, env: gym.Env, name: str | None = None) -> None:
        super().__init__(env)
        self.name = name or _env_name(env)
        self._steps = 0

    def _reject(self, what: str, value: Any) -> None:
        where = f"at step {self._steps} of an episode" if self._steps else "at reset"
        raise NonFiniteStepError(
            f"env {self.name} returned a non-finite {what} ({value}) {where}; "
            "rewards, costs and observations must be finite numbers"
        )

    def _check_observation(self, observation: Any) -> None:
        if isinstance(observation, np.ndarray) and not np.isfinite(observation).all():
            bad = observation[~np.isfinite(observation)].reshape(-1)[0]
            self._reject("observation", bad)

    def reset(self, **kwargs: Any):
        self._steps = 0
        observation, info = self.env.reset(**kwargs)
        self._check_observation(observation)
        return observation, info

    def step(self, action: Any):
        observation, reward, terminated, truncated, info = self.env.step(action)
        self._steps += 1
        if not _finite(reward):
            self._reject("reward", reward)
        cost = None if info is None else info.get(COST_KEY)
        if cost is not None and not _finite(cost):
            self._reject("cost", cost)
        self._check_observation(observation)
        return observation, reward, terminated, truncated, info


class CostSum(RewardSum):
    """``RewardSum`` for a cost stored as an observation entry (default ``"cost"`` into
    ``"episode_cost"``): TorchRL's ``RewardSum`` only accepts keys of the reward spec, while
    the cost read from ``info`` lives in the observation spec (``env.reward_key`` stays unique).
    """

    def __init__(
        self,
        in_keys: list | None = None,
        out_keys: list | None = None,
        reset_keys: list | None = None,
    ) -> None:
        in_keys = [COST_KEY] if in_keys is None else in_keys
        out_keys = ["episode_" + str(k) for k in in_keys] if out_keys is None else out_keys
        super().__init__(in_keys=in_keys, out_keys=out_keys, reset_keys=reset_keys)

    def _generate_episode_reward_spec(self) -> Composite:
        obs_spec = self.parent.full_observation_spec
        out = Composite()
        for in_key, out_key in zip(self.in_keys, self.out_keys, strict=True):
            if in_key not in obs_spec.keys(True, True):
                raise CostKeyError(
                    f"CostSum: the env has no {in_key!r} entry in its observation spec "
                    f"(keys: {sorted(map(str, obs_spec.keys(True, True)))})"
                )
            out[out_key] = obs_spec[in_key].clone()
        return out

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        for in_key, reset_key, out_key in zip(
            self.in_keys, self.reset_keys, self.out_keys, strict=True
        ):
            value = tensordict.get(out_key, default=None) if tensordict is not None else None
            if value is None:
                value = self.parent.full_observation_spec[in_key].zero()
            else:
                reset = tensordict.get(reset_key, default=None)
                if reset is None:
                    value = torch.zeros_like(value)
                else:
                    reset = reset.reshape(*reset.shape, *([1] * (value.ndim - reset.ndim)))
                    value = torch.where(reset, torch.zeros_like(value), value)
            tensordict_reset.set(out_key, value)
        return tensordict_reset


def episode_transforms() -> list[Transform]:
    """New instances of the transforms ``make_env`` puts on top of the base env(s).

    ``StepCounter`` (``"step_count"``), ``RewardSum`` (``"episode_reward"``) and
    :class:`CostSum` (``"episode_cost"``).
    """
    return [
        StepCounter(),
        RewardSum(in_keys=["reward"], out_keys=["episode_reward"]),
        CostSum(in_keys=[COST_KEY], out_keys=["episode_cost"]),
    ]


def env_transforms() -> Compose:
    """:func:`episode_transforms` as one ``Compose``."""
    return Compose(*episode_transforms())


class _PixelsAndObservation(gym.ObservationWrapper):
    """Dict observation ``{"observation": state, "pixels": render()}`` for ``from_pixels``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        env.reset(seed=0)
        frame = env.render()
        self.observation_space = gym.spaces.Dict(
            {
                "observation": env.observation_space,
                "pixels": gym.spaces.Box(0, 255, shape=frame.shape, dtype=np.uint8),
            }
        )

    def observation(self, observation: np.ndarray) -> dict[str, np.ndarray]:
        return {"observation": observation, "pixels": self.env.render()}


def make_base_env(
    name: str,
    *,
    device: torch.device | str = "cpu",
    max_episode_steps: int | None = None,
    from_pixels: bool = False,
    **kwargs: Any,
) -> EnvBase:
    """One untransformed TorchRL env of a preset: ``GymWrapper`` + :class:`InfoReader`
    over the gymnasium env in :class:`RejectNonFinite`. Arguments as :func:`make_env`'s
    (``from_pixels``: a uint8 ``H x W x 3`` ``"pixels"`` entry rendered with MuJoCo; set
    ``MUJOCO_GL=egl`` when headless).
    """
    if from_pixels:
        kwargs.setdefault("render_mode", "rgb_array")
    gym_env = _checked_gym_env(name, max_episode_steps=max_episode_steps, **kwargs)
    if from_pixels:
        gym_env = _PixelsAndObservation(gym_env)
    env = GymWrapper(gym_env, device=device)
    env.set_info_dict_reader(InfoReader(step_info_spec(device=env.device)))
    return env


def make_env(
    name: str,
    *,
    seed: int | None = None,
    num_workers: int = 1,
    parallel: bool = True,
    device: torch.device | str = "cpu",
    max_episode_steps: int | None = None,
    from_pixels: bool = False,
    **kwargs: Any,
) -> TransformedEnv:
    """Build a preset as a TorchRL env with cost, episode sums and step counts.

    Args:
        name: preset short name or gymnasium id; or ``"gymnasium"`` for your own env,
            named by ``env_id="<registered id | module:callable>"`` (with ``cost_key=``:
            :mod:`wcsac_rl.envs.gymnasium_env`).
        seed: seeds the env(s) (workers get ``seed``, ``seed + 1``, ...).
        num_workers: ``1`` for a single in-process env; more for a batch (``[num_workers]``).
        parallel: with ``num_workers > 1``, ``True`` runs one process per env
            (``ParallelEnv``), ``False`` steps them in turn in this process
            (:class:`~wcsac_rl.envs.BatchedGymEnv`, or ``SerialEnv`` with ``from_pixels``).
        device: device of the output tensordicts.
        max_episode_steps: episode length override (default: the preset's).
        from_pixels: also emit rendered ``"pixels"``.
        **kwargs: forwarded to the gymnasium env constructor (``hazards_num=5``).

    Raises:
        ValueError: unknown preset name, bad keyword, or ``num_workers < 1``.

    Examples:
        >>> from wcsac_rl.envs import make_env
        >>> env = make_env("tiny", seed=0)
        >>> td = env.rollout(5)
        >>> td["next", "cost"].shape
        torch.Size([5, 1])
    """
    _check_name(name)  # fail fast, in this process, on an unknown name
    if not isinstance(num_workers, int) or num_workers < 1:
        raise ValueError(f"num_workers must be a positive int, got {num_workers!r}")
    base_fn = functools.partial(
        make_base_env,
        name,
        device="cpu" if num_workers > 1 else device,
        max_episode_steps=max_episode_steps,
        from_pixels=from_pixels,
        **kwargs,
    )
    if num_workers == 1:
        base = base_fn()
    elif not parallel and not from_pixels:
        gym_fn = functools.partial(
            _checked_gym_env, name, max_episode_steps=max_episode_steps, **kwargs
        )
        base = BatchedGymEnv([gym_fn] * num_workers, info_spec=step_info_spec(), device=device)
    else:
        batched = ParallelEnv if parallel else SerialEnv
        base = batched(num_workers, base_fn, device=device)
    env = TransformedEnv(base, env_transforms())
    if seed is not None:
        env.set_seed(int(seed))
    return env


def _check_name(name: str) -> None:
    """Refuse an unknown env name (``"gymnasium"``: your own env, named by ``env_id``)."""
    if name != GYMNASIUM:
        get_preset(name)


def _checked_gym_env(name: str, **kwargs: Any) -> RejectNonFinite:
    """The preset's gymnasium env in :class:`RejectNonFinite`, named ``short (gym id)``;
    for ``name="gymnasium"``, your env (``env_id=...``, ``cost_key=...``: see
    :func:`~wcsac_rl.envs.gymnasium_env.make_user_gym_env`)."""
    if name == GYMNASIUM:
        env = make_user_gym_env(**kwargs)
        return RejectNonFinite(env, name=f"{GYMNASIUM} ({kwargs.get('env_id')})")
    preset = get_preset(name)
    env = make_gym_env(name, **kwargs)
    return RejectNonFinite(env, name=f"{preset.name} ({preset.gym_id})")


def make_env_creator(name: str, **kwargs: Any) -> Callable[[], TransformedEnv]:
    """A picklable zero-argument callable that builds ``make_env(name, **kwargs)``.

    Pass it as ``create_env_fn`` to TorchRL collectors, including the multi-process
    ones (``MultiSyncCollector([creator] * n, ...)``).
    """
    _check_name(name)
    return functools.partial(make_env, name, **kwargs)


def env_info(name: str, **kwargs: Any) -> dict[str, Any]:
    """Facts about a preset that a training loop needs, without building a TorchRL env:
    ``name``, ``gym_id``, ``max_episode_steps``, ``obs_dim``, ``action_dim``,
    ``action_low``, ``action_high``, ``cost_key`` (``("next", "cost")``),
    ``observation_slices`` (point-goal presets, else ``{}``) and ``description``.
    ``kwargs``: the overrides ``make_env`` would receive.
    """
    if name == GYMNASIUM:  # your own env: built and probed with one step
        return user_env_info(**kwargs)
    preset = get_preset(name)
    env = make_gym_env(preset.name, **kwargs)
    try:
        unwrapped = env.unwrapped
        slices = unwrapped.observation_slices() if hasattr(unwrapped, "observation_slices") else {}
        steps = unwrapped.max_episode_steps
        return env_facts(env, preset.name, preset.gym_id, steps, slices, preset.description)
    finally:
        env.close()


_HOW_TO_ADD_COST = (
    "wcsac_rl's safe-RL losses need a per-step cost. Build the env with "
    "wcsac_rl.envs.make_env(...), or, for your own gymnasium env that puts the cost in "
    "info['cost'], call GymWrapper(...).set_info_dict_reader("
    "wcsac_rl.envs.InfoReader(wcsac_rl.envs.step_info_spec())) — or point the loss at "
    "your key with set_keys(cost=...)."
)


def check_cost_key(obj: EnvBase | TensorDictBase, cost_key: str | tuple = COST_KEY) -> None:
    """Check that an env or a collected tensordict carries a usable per-step cost.

    For an env: ``cost_key`` must be in its observation or reward spec, floating point,
    shaped ``[*B, 1]`` or ``[*B]``. For a tensordict: ``("next", *cost_key)`` must be
    present, floating point, and shaped like ``("next", "reward")`` (``[*B, 1]``) or
    without its last dim (``[*B]``).

    Raises:
        CostKeyError: with a message that says what is missing and how to fix it.
    """
    key = (cost_key,) if isinstance(cost_key, str) else tuple(cost_key)
    if isinstance(obj, EnvBase):
        spec = None
        for container in (obj.full_observation_spec, obj.full_reward_spec):
            if key in container.keys(True, True):
                spec = container[key]
                break
        if spec is None:
            keys = sorted(
                map(str, list(obj.full_observation_spec.keys(True, True)) + list(obj.reward_keys))
            )
            raise CostKeyError(
                f"{type(obj).__name__} has no {cost_key!r} entry in its specs (entries: {keys}). "
                + _HOW_TO_ADD_COST
            )
        if not spec.dtype.is_floating_point:
            raise CostKeyError(f"the {cost_key!r} spec must be floating point, got {spec.dtype}")
        batch = tuple(obj.batch_size)
        shape = tuple(spec.shape)
        if shape not in ((*batch, 1), batch):
            raise CostKeyError(
                f"the {cost_key!r} spec must have shape {[*list(batch), 1]} (or {list(batch)}), "
                f"got {list(shape)}"
            )
        return
    if isinstance(obj, TensorDictBase):
        full_key = ("next", *key)
        cost = obj.get(full_key, default=None)
        if cost is None:
            raise CostKeyError(
                f"the tensordict has no {full_key!r} entry (entries: "
                f"{sorted(map(str, obj.keys(True, True)))}). " + _HOW_TO_ADD_COST
            )
        if not cost.dtype.is_floating_point:
            raise CostKeyError(f"{full_key!r} must be floating point, got {cost.dtype}")
        reward = obj.get(("next", "reward"), default=None)
        if reward is not None and tuple(cost.shape) not in (
            tuple(reward.shape),
            tuple(reward.shape[:-1]),
        ):
            raise CostKeyError(
                f"{full_key!r} has shape {list(cost.shape)}; expected the reward's shape "
                f"{list(reward.shape)} (or without its last dim)"
            )
        return
    raise TypeError(
        f"check_cost_key expects a TorchRL env or a TensorDict, got {type(obj).__name__}"
    )
