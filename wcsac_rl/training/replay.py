"""The trainer's replay buffer with n-step cost entries: the state after the n steps is
read from the row that holds it, not stored twice.

:class:`~wcsac_rl.objectives.NStepCost` gives transition ``t`` of a collected piece the
state ``s_{t+m}`` its safety-critic target bootstraps at; that is the next observation
of transition ``t+m−1`` of the same piece (``m ≥ 1``; the lookahead stops at the
piece's end). The trainer writes a collected piece into the buffer whole and in order
(``[envs, time]`` flattened: one env's steps in time order after another's), and the
ring buffer overwrites its oldest rows first, so transition ``t+m−1`` is in the buffer
whenever transition ``t`` is, at ``(index(t) + m − 1) mod capacity``.
:class:`NStepReplayBuffer` stores every entry but the n-step state and, at sampling,
reads that state from there: the same batches, ``obs_dim × 4`` bytes per row fewer
(168 MiB of the default 10⁶-row buffer with StaticEnv's 44 observations).

That holds as long as every piece fits the buffer (``frames_per_batch ≤ buffer_size``);
:func:`~wcsac_rl.training.builders.make_replay_buffer` stores the state otherwise. A
buffer saved by an earlier version (with the state stored) loads too: the stored copy is
then not read.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import TensorDictReplayBuffer

__all__ = ["NStepReplayBuffer", "draw_indices", "nested_key", "sample_at"]


def nested_key(*parts: NestedKey) -> tuple[str, ...]:
    """One flat tuple key from (nested) key parts: ``nested_key("next", ("a", "b"))``
    is ``("next", "a", "b")``."""
    return tuple(p for part in parts for p in ((part,) if isinstance(part, str) else part))


class NStepReplayBuffer(TensorDictReplayBuffer):
    """A ``TensorDictReplayBuffer`` that fills in each sampled row's n-step state from
    the row holding it (see the module doc).

    Args:
        nstep_key: where the n-step entries are (``NStepCost``'s ``out_key``); its
            ``steps`` entry (``m``) must be stored.
        state_keys: the state entries of ``s_{t+m}`` (``NStepCost``'s
            ``observation_keys``), read from the stored ``("next", key)``.
        **kwargs: ``TensorDictReplayBuffer``'s (``storage`` with a ``max_size``,
            ``batch_size``, ...).
    """

    def __init__(self, *, nstep_key: NestedKey, state_keys: Sequence[NestedKey], **kwargs) -> None:
        super().__init__(**kwargs)
        self.nstep_key = nested_key(nstep_key)
        self.state_keys = [nested_key(key) for key in state_keys]
        if not self.state_keys:
            raise ValueError("NStepReplayBuffer needs the state entries of s_{t+m}")

    @property
    def gathered_keys(self) -> list[tuple[str, ...]]:
        """The entries read from other rows at sampling (not to be stored)."""
        return [(*self.nstep_key, *key) for key in self.state_keys]

    def sample(
        self, batch_size: int | None = None, return_info: bool = False, include_info=None
    ) -> TensorDictBase:
        data, info = super().sample(batch_size, return_info=True, include_info=include_info)
        index = torch.as_tensor(info["index"], device=self.storage.device)
        self.gather_states(data, index)
        return (data, info) if return_info else data

    def gather_states(self, data: TensorDictBase, index: torch.Tensor) -> None:
        """Fill in ``data`` (the rows at ``index``) with each row's n-step state."""
        nstep = data.get(self.nstep_key)
        steps = nstep.get("steps").reshape(index.shape).to(index.device)
        rows = (index + steps - 1) % self.storage.max_size
        ahead = self.storage.get(rows)
        for key in self.state_keys:
            value = ahead.get(("next", *key))
            nstep.set(key, value.to(data.device) if data.device is not None else value)


def draw_indices(buffer: TensorDictReplayBuffer, count: int) -> torch.Tensor:
    """``count`` batches' row indices at once, ``[count, batch_size]``, uniform over the
    filled rows, drawn on the storage's device (where ``buffer.sample()`` draws one
    batch's: ``count`` draws in one call, not ``count`` calls)."""
    storage = buffer.storage
    if not len(storage):
        raise RuntimeError("the replay buffer is empty: nothing to draw")
    return torch.randint(
        0, len(storage), (count, buffer.batch_size), device=getattr(storage, "device", None)
    )


def sample_at(buffer: TensorDictReplayBuffer, index: torch.Tensor) -> TensorDictBase:
    """The batch ``buffer.sample()`` returns when it draws ``index``: the rows, their
    ``"index"`` and, from an :class:`NStepReplayBuffer`, their n-step states."""
    data = buffer.storage.get(index)
    data.set("index", index.to(data.device) if data.device is not None else index)
    if isinstance(buffer, NStepReplayBuffer):
        buffer.gather_states(data, index)
    return data
