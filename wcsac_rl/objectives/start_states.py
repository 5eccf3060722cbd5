"""Episode start states for a κ loss evaluated where episodes begin (``kappa_states="initial"``).

The cost limit is about whole episodes, and an episode's cost is the safety critic's
value at its start state. With ``kappa_states="initial"`` :class:`~wcsac_rl.objectives.WCSACLoss`
therefore reads start states from the batch (``batch["initial"]``, one per row) and
holds the CVaR there under the limit. :class:`StartStateBuffer` is what provides
them in a TorchRL loop: it keeps the start states met in collected data (the
transitions with ``step_count == 0``, from TorchRL's ``StepCounter``, or with
``is_init`` set, from ``InitTracker``) and attaches a uniform draw of them to each
sampled batch. The wcsac_rl trainer uses it the same way.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from wcsac_rl.objectives.inputs import state_keys
from wcsac_rl.objectives.loss_keys import LossKey, follow_loss_keys

__all__ = ["StartStateBuffer"]


class StartStateBuffer(TensorDictReplayBuffer):
    """Uniform replay of the episode start states seen in collected data.

    Args:
        state_keys: the entries a start state holds (the actor's and critics'
            inputs other than the action: ``loss.initial_state_keys``).

    Keyword Args:
        capacity: how many start states are kept (the most recent). Default 10 000.
        out_key: where :meth:`attach` puts them in a batch
            (``loss.tensor_keys.initial_states``). Default ``"initial"``.
        device: storage device (default CPU).

    A TorchRL ``TensorDictReplayBuffer`` otherwise (``len``, ``sample``, ``dumps`` /
    ``loads`` for checkpoints).

    Example:
        >>> buffer = StartStateBuffer.for_loss(loss)            # doctest: +SKIP
        >>> for data in collector:                              # doctest: +SKIP
        ...     replay.extend(data.reshape(-1))
        ...     buffer.add_starts(data)
        ...     out = loss(buffer.attach(replay.sample()))

    Built by :meth:`for_loss`, ``out_key`` is the loss's ``initial_states`` key, read at
    each call: a later ``loss.set_keys(initial_states=...)`` is followed.
    """

    out_key = LossKey("initial_states")

    def __init__(
        self,
        state_keys: Sequence[NestedKey] = ("observation",),
        *,
        capacity: int = 10_000,
        out_key: NestedKey = "initial",
        device: torch.device | str = "cpu",
    ) -> None:
        if int(capacity) != capacity or capacity < 1:
            raise ValueError(f"capacity must be an integer >= 1, got {capacity}")
        state_keys = list(state_keys)
        if not state_keys:
            raise ValueError("state_keys must name at least one entry (e.g. 'observation')")
        super().__init__(storage=LazyTensorStorage(int(capacity), device=device))
        self.state_keys = state_keys
        self.out_key = out_key

    @classmethod
    def for_loss(cls, loss, **kwargs) -> StartStateBuffer:
        """The buffer a loss with ``kappa_states="initial"`` reads (its out key, and the
        state entries its networks read from the env: not the keys a composite actor
        writes between its modules, see :func:`~wcsac_rl.objectives.inputs.state_keys`)."""
        if "out_key" in kwargs:
            return cls(state_keys(loss), **kwargs)
        return follow_loss_keys(cls(state_keys(loss), **kwargs), loss)

    @staticmethod
    def start_mask(batch: TensorDictBase) -> torch.Tensor:
        """Which transitions of ``batch`` (flattened) start an episode."""
        flat = batch.reshape(-1)
        is_init = flat.get("is_init", None)
        if is_init is not None:
            return is_init.reshape(-1).bool()
        step_count = flat.get("step_count", None)
        if step_count is None:
            raise KeyError(
                "cannot tell where episodes start: the batch has neither 'step_count' nor "
                "'is_init'; add torchrl.envs.StepCounter() or InitTracker() to the env"
            )
        return step_count.reshape(-1) == 0

    def add_starts(self, batch: TensorDictBase) -> int:
        """Store the start states of collected ``batch``; returns how many there were."""
        flat = batch.reshape(-1)
        starts = self.start_mask(flat)
        count = int(starts.sum())
        if count:
            missing = [key for key in self.state_keys if key not in flat.keys(True)]
            if missing:
                raise KeyError(f"the batch has no {missing}; a start state holds {self.state_keys}")
            self.extend(flat[starts].select(*self.state_keys))
        return count

    def attach(self, batch: TensorDictBase) -> TensorDictBase:
        """``batch`` with one uniformly drawn start state per row under ``out_key``."""
        if not len(self):
            raise RuntimeError(
                "no start states yet: call add_starts() on collected data (with the "
                "episodes' first steps) before sampling"
            )
        if batch.ndim != 1:
            raise ValueError(f"attach expects a flat batch of transitions, got shape {batch.shape}")
        initial = self.sample(batch.shape[0]).exclude("index")
        batch.set(self.out_key, initial.to(batch.device) if batch.device else initial)
        return batch
