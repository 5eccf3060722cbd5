"""The contract between a gymnasium env's ``info`` and the TorchRL tensordicts:
:func:`step_info_spec` (which entries are copied, with which dtype and shape) and
:func:`info_array`, the one reading rule (``None``, read as zero, when a step's ``info``
lacks the entry) that :class:`InfoReader` (for ``GymWrapper``) and
:class:`~wcsac_rl.envs.BatchedGymEnv` both apply.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.gym_like import BaseInfoDictReader

__all__ = ["COST_KEY", "CostKeyError", "InfoReader", "info_array", "numpy_dtype", "step_info_spec"]

COST_KEY = "cost"
"""Name of the per-step cost entry (``("next", "cost")`` after a step)."""


class CostKeyError(ValueError):
    """An env or a tensordict lacks a usable per-step cost entry."""


def numpy_dtype(dtype: torch.dtype) -> np.dtype | None:
    """The NumPy dtype of a torch dtype (``None`` where NumPy has none, e.g. bfloat16).

    >>> numpy_dtype(torch.float32), numpy_dtype(torch.bool), numpy_dtype(torch.bfloat16)
    (dtype('float32'), dtype('bool'), None)
    """
    try:
        return torch.empty((), dtype=dtype).numpy().dtype
    except TypeError:
        return None


def step_info_spec(device: torch.device | str | None = None) -> Composite:
    """Spec of the ``info`` entries copied into the tensordicts (by :class:`InfoReader`
    and :class:`~wcsac_rl.envs.BatchedGymEnv`)."""
    return Composite(
        {
            COST_KEY: Unbounded(shape=(1,), dtype=torch.float32, device=device),
            "goal_reached": Unbounded(shape=(1,), dtype=torch.bool, device=device),
            "numerical_failure": Unbounded(shape=(1,), dtype=torch.bool, device=device),
            "robot_xy": Unbounded(shape=(2,), dtype=torch.float32, device=device),
            "goal_xy": Unbounded(shape=(2,), dtype=torch.float32, device=device),
        },
        shape=(),
        device=device,
    )


def info_array(
    info: Mapping[str, Any] | None, key: str, dtype: np.dtype, shape: tuple[int, ...]
) -> np.ndarray | None:
    """``info[key]`` as a new array of ``dtype`` and ``shape``; ``None`` when it is
    missing (the entry then reads as zero).

    >>> info_array({"cost": 1}, "cost", np.float32, (1,))
    array([1.], dtype=float32)
    >>> info_array({}, "cost", np.float32, (1,)) is None
    True
    """
    value = None if info is None else info.get(key)
    if value is None:
        return None
    return np.array(value, dtype=dtype).reshape(shape)


class InfoReader(BaseInfoDictReader):
    """Copy selected ``info`` entries into the tensordict, cast and shaped to their spec.

    A missing entry is filled with the spec's zero, so env wrappers that drop ``info``
    on some steps do not break the tensordict layout. Use it with
    ``GymWrapper.set_info_dict_reader(InfoReader(spec))``.

    Args:
        spec: a :class:`~torchrl.data.Composite` of the entries to read.
    """

    def __init__(self, spec: Composite) -> None:
        self._spec = spec
        self._items = [
            (key, numpy_dtype(s.dtype), s.dtype, tuple(s.shape), s.device)
            for key, s in spec.items()
        ]

    def __call__(self, info_dict: Mapping[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        for key, np_dtype, dtype, shape, device in self._items:
            if np_dtype is None:  # no NumPy dtype: through torch
                value = None if info_dict is None else info_dict.get(key)
                tensor = None
                if value is not None:
                    tensor = torch.as_tensor(np.asarray(value), dtype=dtype, device=device)
                    tensor = tensor.reshape(shape)
            else:  # one NumPy copy, shared with torch
                array = info_array(info_dict, key, np_dtype, shape)
                tensor = None if array is None else torch.from_numpy(array)
                if tensor is not None and device is not None and device.type != "cpu":
                    tensor = tensor.to(device)
            tensordict.set(key, self._spec[key].zero() if tensor is None else tensor)
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._spec
