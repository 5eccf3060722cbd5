"""Several gymnasium envs stepped in turn in this process, as one batched TorchRL env:
one tensordict per batched step, with the same entries, specs and reset semantics as
``SerialEnv(n, make_base_env)`` without its per-env tensordict bookkeeping (both read
``info`` by :func:`~wcsac_rl.envs.info.info_array`; docs/environments.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Composite
from torchrl.envs import EnvBase
from torchrl.envs.libs.gym import GymWrapper

from wcsac_rl.envs.info import InfoReader, info_array, numpy_dtype

__all__ = ["BatchedGymEnv"]

_DONE_KEYS = ("done", "terminated", "truncated")


class BatchedGymEnv(EnvBase):
    """``n`` gymnasium envs with flat ``Box`` observations as one TorchRL env of batch ``[n]``.

    Args:
        env_fns: one zero-argument constructor per sub-env (called here).
        info_spec: ``info`` entries to copy into the tensordicts (as
            :class:`~wcsac_rl.envs.InfoReader` does); a missing entry reads as zero.
            ``None``: none.
        device: device of the output tensordicts.

    Seeding: ``set_seed(s)`` resets sub-env ``i`` with seed ``s + i``. Partial
    resets (``"_reset"`` masks, as TorchRL's collectors send) reset only the masked
    sub-envs; partial steps (``"_step"`` masks, from
    ``rollout(break_when_all_done=True)``) step only the masked ones.

    Example:
        >>> from wcsac_rl.envs.presets import make_gym_env
        >>> from wcsac_rl.envs.info import step_info_spec
        >>> env = BatchedGymEnv([lambda: make_gym_env("tiny")] * 3, info_spec=step_info_spec())
        >>> td = env.rollout(4)
        >>> td.batch_size, td["next", "cost"].shape
        (torch.Size([3, 4]), torch.Size([3, 4, 1]))
    """

    def __init__(
        self,
        env_fns: Sequence[Callable[[], gym.Env]],
        *,
        info_spec: Composite | None = None,
        device: torch.device | str = "cpu",
    ) -> None:
        if len(env_fns) == 0:
            raise ValueError("BatchedGymEnv needs at least one env constructor")
        n = len(env_fns)
        super().__init__(batch_size=torch.Size([n]), device=device)
        self._envs: list[gym.Env] = []
        try:
            for fn in env_fns:
                self._envs.append(fn())
            self._set_specs_from(env_fns[0], info_spec)
        except Exception:
            for env in self._envs:
                env.close()
            raise
        obs_spec = self.full_observation_spec
        self._obs_dtype = _required_numpy_dtype(obs_spec["observation"].dtype, "observation")
        self._info = [
            (key, _required_numpy_dtype(spec.dtype, key), tuple(spec.shape))
            for key, spec in (info_spec.items() if info_spec is not None else ())
        ]
        obs_shape = tuple(obs_spec["observation"].shape[1:])
        self._observation = np.zeros((n, *obs_shape), self._obs_dtype)
        self._info_values = {key: np.zeros((n, *shape), dtype) for key, dtype, shape in self._info}

    def _set_specs_from(self, env_fn, info_spec: Composite | None) -> None:
        probe = GymWrapper(env_fn(), device=self.device)
        try:
            if list(probe.full_observation_spec.keys()) != ["observation"]:
                raise ValueError(
                    "BatchedGymEnv takes envs with one flat Box observation, got entries "
                    f"{list(probe.full_observation_spec.keys())}"
                )
            if info_spec is not None:
                probe.set_info_dict_reader(InfoReader(info_spec))
            n = self.batch_size[0]

            def batched(spec):
                return spec.expand(n, *spec.shape).clone()

            self.full_observation_spec = batched(probe.full_observation_spec)
            self.full_action_spec = batched(probe.full_action_spec)
            self.full_reward_spec = batched(probe.full_reward_spec)
            self.full_done_spec = batched(probe.full_done_spec)
        finally:
            probe.close()

    # ------------------------------------------------------------------ stepping
    def _read_info(self, i: int, info: dict | None) -> None:
        for key, dtype, shape in self._info:
            value = info_array(info, key, dtype, shape)
            self._info_values[key][i] = 0 if value is None else value

    def _entries(self) -> dict[str, torch.Tensor]:
        out = {"observation": torch.from_numpy(self._observation.copy())}
        for key, values in self._info_values.items():
            out[key] = torch.from_numpy(values.copy())
        return out

    def _to_device(self, td: TensorDictBase) -> TensorDictBase:
        return td if self.device is None or self.device.type == "cpu" else td.to(self.device)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get(self.action_key).detach().cpu().numpy()
        n = len(self._envs)
        # partial steps (``rollout(break_when_all_done=True)``): the sub-envs outside
        # the mask are not stepped; TorchRL keeps their previous entries
        active = tensordict.get("_step", None)
        active = None if active is None else active.reshape(n).cpu().numpy()
        reward = np.zeros((n, 1), np.float32)
        terminated = np.zeros((n, 1), bool)
        truncated = np.zeros((n, 1), bool)
        for i, env in enumerate(self._envs):
            if active is not None and not active[i]:
                continue
            obs, r, term, trunc, info = env.step(actions[i])
            self._observation[i] = obs
            reward[i] = r
            terminated[i] = term
            truncated[i] = trunc
            self._read_info(i, info)
        out = self._entries()
        out["reward"] = torch.from_numpy(reward)
        out["terminated"] = torch.from_numpy(terminated)
        out["truncated"] = torch.from_numpy(truncated)
        out["done"] = torch.from_numpy(terminated | truncated)
        return self._to_device(TensorDict(out, batch_size=self.batch_size))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        n = len(self._envs)
        mask = None
        if tensordict is not None:
            reset = tensordict.get("_reset", None)
            if reset is not None:
                mask = reset.reshape(n).cpu().numpy()
        for i, env in enumerate(self._envs):
            if mask is None or mask[i]:
                self._reset_one(i, env, **kwargs)
        out = self._entries()
        for key in _DONE_KEYS:
            out[key] = torch.zeros((n, 1), dtype=torch.bool)
        return self._to_device(TensorDict(out, batch_size=self.batch_size))

    def _reset_one(self, i: int, env: gym.Env, seed: int | None = None) -> None:
        obs, info = env.reset(seed=seed)
        self._observation[i] = obs
        self._read_info(i, info)

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            return
        for i, env in enumerate(self._envs):
            self._reset_one(i, env, seed=int(seed) + i)

    # ------------------------------------------------------------------ helpers
    @property
    def envs(self) -> list[gym.Env]:
        """The gymnasium sub-envs (read-only use: stepping them desynchronises the batch)."""
        return list(self._envs)

    def close(self, *, raise_if_closed: bool = True) -> None:
        for env in self._envs:
            env.close()
        super().close(raise_if_closed=raise_if_closed)


def _required_numpy_dtype(dtype: torch.dtype, what: str) -> np.dtype:
    result = numpy_dtype(dtype)
    if result is None:
        raise ValueError(f"BatchedGymEnv keeps {what!r} in NumPy, which has no {dtype}")
    return result
