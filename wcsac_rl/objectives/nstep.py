"""n-step cost returns for the safety critic, computed on collected trajectories.

One-step TD moves a cost back by one state per target refresh; a cost met ~100
steps after the start then needs many thousand updates to reach the start state's
estimate, and the policy changes faster than that. :class:`NStepCost` adds to each
transition of a collector batch the discounted cost of the next ``m ≤ n`` steps and
the state reached after them, so the safety critic bootstraps ``m`` steps ahead:

``y_c = Σ_{k<m} γ_c^k c_{t+k} + γ_c^m (1 − term) Q̄^c(s_{t+m}, a'),  a' ~ π(·|s_{t+m})``.

``m`` is ``n`` unless the episode ends first (the steps up to and including the
last one count) or the batch ends first (the collector hands over trajectories in
pieces; the lookahead stops at the piece's end, which is still an exact target; in a
piece padded by TorchRL's ``split_trajs``, at its last step ``("collector", "mask")``
keeps).
The reward critic keeps its one-step target.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import nn

from wcsac_rl.objectives.inputs import state_keys
from wcsac_rl.objectives.loss_keys import LossKey, follow_loss_keys
from wcsac_rl.options import SafetyOptions, check_value, option_spec

__all__ = ["NStepCost"]

NSTEP_GAMMA = replace(option_spec(SafetyOptions, "cost_gamma"), nullable=False)
"""What ``NStepCost``'s ``gamma`` may be: ``cost_gamma``'s range, resolved (no null)."""


class NStepCost(nn.Module):
    """Collector postproc adding n-step cost returns under ``out_key`` (default ``"nstep"``).

    Args:
        n_steps: lookahead ``n ≥ 1`` (1 reproduces the one-step target exactly).
        gamma: the safety critic's discount γ_c.

    Keyword Args:
        observation_keys: the state entries to carry from ``s_{t+m}`` (read under
            ``"next"``). Default ``("observation",)``.
        cost_key, done_key, terminated_key: read under ``"next"`` (without a terminated
            entry, done is read in its place, as TorchRL does).
        out_key: where the sub-tensordict goes. It holds the state entries of
            ``s_{t+m}``, ``"cost"`` (the discounted sum, shaped like the cost),
            ``"steps"`` (``m``, int64), and ``"terminated"`` and ``"done"`` (at step
            ``t+m−1``; ``done`` also marks a time-limit truncation there).

    The batch's last dimension must be time (TorchRL collectors' layout, e.g.
    ``[num_envs, frames_per_env]``). With TorchRL's ``MultiStep`` postproc too, put
    ``NStepCost`` first: it reads each step's own cost and flags, which ``MultiStep``
    replaces by those n steps on (a batch it has seen with ``n > 1`` is refused;
    ``MultiStep(n_steps=1)`` changes nothing).

    Built by :meth:`for_loss`, the cost / done / terminated and out keys are the loss's,
    read at each call: a later ``loss.set_keys(cost=...)`` is followed.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> cost = torch.tensor([[0.0, 1.0, 0.0, 1.0]]).unsqueeze(-1)
        >>> done = torch.tensor([[False, False, True, False]]).unsqueeze(-1)
        >>> td = TensorDict({"next": {"observation": torch.arange(4.0).reshape(1, 4, 1),
        ...                           "cost": cost, "done": done, "terminated": done.clone()}},
        ...                 [1, 4])
        >>> out = NStepCost(3, gamma=0.5)(td)["nstep"]
        >>> out["cost"].squeeze(-1), out["steps"], out["observation"].squeeze(-1)
        (tensor([[0.5000, 1.0000, 0.0000, 1.0000]]), tensor([[3, 2, 1, 1]]), tensor([[2., 2., 2., 3.]]))
    """

    cost_key = LossKey("cost")
    done_key = LossKey("done")
    terminated_key = LossKey("terminated")
    out_key = LossKey("nstep")

    def __init__(
        self,
        n_steps: int,
        gamma: float,
        *,
        observation_keys: tuple[NestedKey, ...] = ("observation",),
        cost_key: NestedKey = "cost",
        done_key: NestedKey = "done",
        terminated_key: NestedKey = "terminated",
        out_key: NestedKey = "nstep",
    ) -> None:
        super().__init__()
        check_value("n_steps", n_steps, "cost_n_steps")
        check_value("gamma", gamma, NSTEP_GAMMA)
        self.n_steps = int(n_steps)
        self.gamma = float(gamma)
        self.observation_keys = tuple(observation_keys)
        self.cost_key, self.done_key, self.terminated_key = cost_key, done_key, terminated_key
        self.out_key = out_key

    @classmethod
    def for_loss(cls, loss) -> NStepCost:
        """The postproc a loss with ``cost_n_steps > 1`` reads: its ``n`` and γ_c, the
        state entries its networks read from the env
        (:func:`~wcsac_rl.objectives.inputs.state_keys`), and its cost / done /
        terminated and n-step keys, which follow ``loss.set_keys`` made after this call
        (the postproc reads them from ``loss.tensor_keys`` each time it runs)."""
        nstep = cls(loss.cost_n_steps, loss.cost_gamma, observation_keys=tuple(state_keys(loss)))
        return follow_loss_keys(nstep, loss)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if tensordict.ndim == 0:
            raise ValueError("NStepCost needs a batch whose last dimension is time")
        time_dim = _named_time_dim(tensordict)
        if time_dim is not None and time_dim != tensordict.ndim - 1:
            # a batch whose dimension named "time" is not the last (TorchRL's names)
            moved = tensordict.transpose(time_dim, tensordict.ndim - 1)
            self.forward(moved)
            tensordict.set(self.out_key, moved.get(self.out_key).transpose(time_dim, -1))
            return tensordict
        steps_ahead = tensordict.get("steps_to_next_obs", None)
        if steps_ahead is not None and bool((steps_ahead > 1).any()):
            raise ValueError(
                "NStepCost got a batch from TorchRL's MultiStep (it has 'steps_to_next_obs'), "
                "whose 'next' entries are n steps on; put NStepCost before MultiStep"
            )
        for key in (self.cost_key, self.done_key):
            if tensordict.get(("next", *_tuple(key)), None) is None:
                raise KeyError(
                    f"NStepCost: the batch has no {('next', *_tuple(key))!r} entry, which the "
                    "n-step cost reads (name yours with cost_key= / done_key=, or "
                    "NStepCost.for_loss(loss) after loss.set_keys(...))"
                )
        nxt = tensordict.get("next")
        shape = tensordict.shape
        cost = nxt.get(self.cost_key)
        flat_cost = cost.reshape(shape).to(torch.float64)
        done = nxt.get(self.done_key).reshape(shape)
        _check_time_is_last(tensordict, done)
        horizon = shape[-1]
        time = torch.arange(horizon, device=flat_cost.device)

        # a padded piece (TorchRL's split_trajs) ends at its last kept step
        kept = tensordict.get(("collector", "mask"), None)
        kept = None if kept is None else kept.reshape(shape).bool()

        total = torch.zeros_like(flat_cost)
        steps = torch.zeros(shape, dtype=torch.int64, device=flat_cost.device)
        alive = torch.ones(shape, dtype=torch.bool, device=flat_cost.device)
        for k in range(self.n_steps):
            index = time + k
            inside = index < horizon
            index = index.clamp(max=horizon - 1)
            if kept is not None and k > 0:
                inside = inside & kept[..., index]
            valid = alive & inside  # broadcast over the leading (env) dimensions
            total += torch.where(valid, self.gamma**k * flat_cost[..., index], 0.0)
            steps += valid.long()
            alive = valid & ~done[..., index]
        last = (time + steps - 1).clamp(min=0)  # index of step t+m−1 (m ≥ 1 always)

        def at_last(value: torch.Tensor) -> torch.Tensor:
            gather_index = last.reshape(*shape, *([1] * (value.ndim - len(shape))))
            gather_index = gather_index.expand(*shape, *value.shape[len(shape) :])
            return value.gather(len(shape) - 1, gather_index)

        out = {key: at_last(nxt.get(key)) for key in self.observation_keys}
        out["cost"] = total.to(cost.dtype).reshape(cost.shape)
        out["steps"] = steps
        terminated = nxt.get(self.terminated_key, None)  # (TorchRL: done where absent)
        out["terminated"] = at_last(nxt.get(self.done_key) if terminated is None else terminated)
        out["done"] = at_last(nxt.get(self.done_key))
        tensordict.set(self.out_key, TensorDict(out, batch_size=shape))
        return tensordict


def _named_time_dim(tensordict: TensorDictBase) -> int | None:
    """The dimension TorchRL named ``"time"`` (its collectors name the last one), if any."""
    try:
        names = tensordict.names
    except (RuntimeError, ValueError):  # (a lazy stack or a batch that cannot hold names)
        return None
    return names.index("time") if "time" in names else None


def _check_time_is_last(tensordict: TensorDictBase, done: torch.Tensor) -> None:
    """Refuse a batch whose ``step_count`` shows its last dimension is not time: along
    time, each step's count is the one before it plus one, unless an episode ended (or
    was reset) in between. One ``ValueError`` line; nothing to check without the entry.
    (A host synchronisation per call: this runs in the collector's postproc.)"""
    count = tensordict.get("step_count", None)
    if count is None or tensordict.shape[-1] < 2:
        return
    count = count.reshape(tensordict.shape)
    advanced = count[..., 1:] == count[..., :-1] + 1
    restarted = done[..., :-1] | (count[..., 1:] == 0)
    if not bool((advanced | restarted).all()):
        raise ValueError(
            f"NStepCost: the batch's last dimension is not time (its step_count does not "
            f"advance by one along it; batch shape {list(tensordict.shape)}): give "
            "[envs, time] as TorchRL's collectors do, or name the time dimension 'time' "
            "(tensordict.refine_names(..., 'time'))"
        )


def _tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)
