"""What the safety critic's TD target is made of: the cost summed, its discount, where it stops.

The target of every safety head (:mod:`wcsac_rl.objectives.safety_head`) has the form
``C + γ_c^m · alive · (target critic at the bootstrap state)``. :class:`CostTarget`
reads ``C``, ``γ_c^m`` and ``alive`` from the batch, and names the bootstrap state:

* ``n_steps=1`` (the paper): ``C = c_t``, ``m = 1``, bootstrapped at ``s_{t+1}``;
* ``n_steps=n > 1``: the entries :class:`~wcsac_rl.objectives.NStepCost` adds to
  collected data, ``C = Σ_{k<m} γ_c^k c_{t+k}``, bootstrapped at ``s_{t+m}`` (m ≤ n:
  sparse costs reach the states that lead to them n times faster);
* ``alive`` is 0 where the sum stops: at a termination, and (unless
  ``bootstrap_truncated``) at a time-limit truncation too — undiscounted, bootstrapping
  across the time limit makes Q^c the cost of an endless episode, which grows without
  bound on a task whose episodes end only by the time limit; stopping there makes it
  the cost until the episode's end.

``gamma=None`` takes the reward's γ (the paper); the default ``1.0`` makes the critic's
value at a start state the expected episode cost itself, which the limit ``d`` is about.
"""

from __future__ import annotations

from collections.abc import Callable

from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

from wcsac_rl.objectives.inputs import nested_key, required_entry

__all__ = ["CostTarget"]


class CostTarget:
    """The data of the safety critic's TD target (see the module doc).

    Args:
        keys: the loss's ``tensor_keys`` (``cost``, ``done``, ``terminated``, ``nstep``).
        gamma (float, optional): γ_c in [0, 1]; ``None``: the reward's γ.
        n_steps (int): the lookahead ``n >= 1``.
        bootstrap_truncated (bool, optional): bootstrap across time-limit truncations
            (``done`` but not ``terminated``); ``None``: only when γ_c < 1.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from wcsac_rl.objectives import WCSACLoss
        >>> target = CostTarget(WCSACLoss.default_keys(), gamma=0.5, n_steps=1)
        >>> target.set_reward_gamma(0.99)
        >>> batch = TensorDict({"next": {"cost": torch.tensor([[1.0], [2.0]]),
        ...                              "done": torch.tensor([[False], [True]]),
        ...                              "terminated": torch.tensor([[False], [True]])}}, [2])
        >>> cost, gamma, alive, _ = target.bootstrap(batch, torch.tensor(0.5), None, None)
        >>> cost, gamma, alive
        (tensor([1., 2.]), tensor(0.5000), tensor([1., 0.]))
    """

    def __init__(
        self,
        keys,
        *,
        gamma: float | None = 1.0,
        n_steps: int = 10,
        bootstrap_truncated: bool | None = None,
    ) -> None:
        if gamma is not None and not 0.0 <= gamma <= 1.0:
            raise ValueError(f"cost_gamma must be in [0, 1], got {gamma}")
        if int(n_steps) != n_steps or n_steps < 1:
            raise ValueError(f"cost_n_steps must be an integer >= 1, got {n_steps}")
        self.keys = keys
        self.n_steps = int(n_steps)
        self._explicit_gamma = None if gamma is None else float(gamma)
        self._explicit_truncated = (
            None if bootstrap_truncated is None else bool(bootstrap_truncated)
        )
        self.set_reward_gamma(0.99)

    def set_reward_gamma(self, gamma: float) -> None:
        """The reward's γ (γ_c when ``gamma=None``); fixes :attr:`bootstrap_truncated`
        as a Python bool, so compiled code does not branch on a tensor."""
        self._reward_gamma = float(gamma)
        truncated = self._explicit_truncated
        self.bootstrap_truncated = self.gamma < 1.0 if truncated is None else truncated

    @property
    def gamma(self) -> float:
        """γ_c: the one given, else the reward's."""
        if self._explicit_gamma is not None:
            return self._explicit_gamma
        return self._reward_gamma

    def in_keys(self, state_keys: list[NestedKey]) -> list[NestedKey]:
        """The batch entries read beyond the reward critic's (``state_keys``: the
        critics' state inputs, carried by the n-step entries)."""
        keys = [("next", self.keys.cost)]
        if self.n_steps > 1:
            for key in ("cost", "steps", "terminated", "done", *state_keys):
                keys.append(nested_key(self.keys.nstep, key))
        return keys

    def cost(self, tensordict: TensorDictBase, dtype) -> Tensor:
        """The per-step cost ``[*B]`` (``[*B, 1]`` accepted), in ``dtype``."""
        key = ("next", self.keys.cost)
        cost = tensordict.get(key, None)
        if cost is None:
            raise KeyError(
                f"WCSACLoss needs the per-step cost at {key} of the batch, which has no such "
                f"entry. Use an env that reports a cost (wcsac_rl.envs.make_env) or point the "
                f"loss at your key with loss.set_keys(cost=...)."
            )
        batch_shape = tensordict.shape
        if cost.shape == (*batch_shape, 1):
            cost = cost.squeeze(-1)
        elif cost.shape != batch_shape:
            raise ValueError(
                f"cost at {key} has shape {tuple(cost.shape)}; expected {tuple(batch_shape)} "
                f"or {(*batch_shape, 1)} for a batch of shape {tuple(batch_shape)}"
            )
        return cost.to(dtype)

    def bootstrap_states(self, tensordict: TensorDictBase) -> TensorDictBase | None:
        """The states where the target bootstraps when they are not ``s_{t+1}``: the
        n-step entries (a ``KeyError`` saying how to add them if the batch has none),
        or ``None`` for one step."""
        if self.n_steps == 1:
            return None
        return required_entry(
            tensordict,
            self.keys.nstep,
            f"cost_n_steps={self.n_steps} needs the n-step cost entries (cost, steps, "
            f"terminated and the state after them)",
            "Add them to collected data with wcsac_rl.objectives.NStepCost.for_loss(loss).",
        )

    def bootstrap(
        self, tensordict: TensorDictBase, discount: Tensor, at_next, ahead: Callable | object = None
    ):
        """``(C, γ_c^m, alive, values)``, each ``[*B]`` but the last: the target
        critic's values where the sum is bootstrapped — ``at_next`` (at ``s_{t+1}``)
        for one step, else at the n-step entries' ``s_{t+m}``: ``ahead(states)`` for a
        callable ``ahead``, or ``ahead`` itself when the values there were read
        already (:meth:`bootstrap_states` names those states). ``discount`` is γ_c as
        a tensor."""
        cost = self.cost(tensordict, discount.dtype)
        gamma = discount.to(cost.dtype)
        if self.n_steps == 1:
            first, second = self.keys.terminated, self.keys.done
            if not self.bootstrap_truncated:
                first, second = second, first
            # a batch with one of the flags has no truncations to tell apart (TorchRL's
            # TD(0) reads done where terminated is absent)
            terminated = tensordict.get(("next", first), None)
            if terminated is None:
                terminated = tensordict.get(("next", second))
            return cost, gamma, self._alive(terminated, cost), at_next
        nstep = self.bootstrap_states(tensordict)
        values = ahead(nstep) if callable(ahead) else ahead
        cost = nstep.get("cost").reshape(cost.shape).to(cost.dtype)
        gamma = gamma.pow(nstep.get("steps").reshape(cost.shape).to(cost.dtype))
        if self.bootstrap_truncated:
            terminated = nstep.get("terminated")
        else:
            terminated = required_entry(
                nstep,
                "done",
                "Stopping the safety critic's sum at time limits needs the n-step "
                "entries' done flag",
                "Recompute them with this version's wcsac_rl.objectives.NStepCost, "
                "or pass cost_bootstrap_truncated=True.",
            )
        return cost, gamma, self._alive(terminated, cost), values

    @staticmethod
    def _alive(terminated: Tensor, cost: Tensor) -> Tensor:
        return (~terminated.reshape(cost.shape)).to(cost.dtype)
