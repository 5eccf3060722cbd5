"""Filter the actions a policy collects with through its safety critic (a shield).

A Lagrangian policy learns its route before κ has grown: in the kit's StaticEnv runs the
epochs over the limit come while the policy first finds a way to the goal, and every
κ rule screened (its size, its rate, the signal it reads) left some of them
(``results/training_safety/``). κ reads the critic at the episodes' *start* states; near
a hazard the critic's own reading of an action, Γ(s, a), rises steps before the cost is
paid. :class:`CriticShield` reads it there: at each collection step it draws
``candidates − 1`` more actions from the policy's distribution beside the one the policy
sampled, keeps the policy's action when its Γ is at most the threshold, else the first
candidate whose Γ is, else the candidate with the lowest Γ. This is the action rule of
Conservative Safety Critics (Bharadhwaj et al., ICLR 2021: sample from π until
``Q_C(s, a) <= ε``, else the least unsafe sample), on the kit's CVaR reading.

It acts only under ``ExplorationType.RANDOM`` (collection): deterministic test episodes,
and the evaluation of a saved run, play the policy alone, so what Table 1 measures is
the policy, not the shield. The replay buffer stores the action taken (the learner is
off-policy), and ``"shielded"`` marks the steps where the shield replaced it.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import InteractionType, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.envs.utils import exploration_type

from wcsac_rl.modules.actor import TanhNormalPolicy

__all__ = ["CriticShield"]


class CriticShield(TensorDictModuleBase):
    """A :class:`~wcsac_rl.modules.TanhNormalPolicy` whose sampled actions pass a
    safety critic's check.

    Args:
        policy (TanhNormalPolicy): the policy that acts.
        cvar (callable): ``cvar(states, actions) -> Γ`` for a tensordict of states with
            batch ``[K, *B]`` and actions ``[K, *B, A]``, shaped ``[K, *B]``
            (:meth:`~wcsac_rl.objectives.WCSACLoss.action_cvar`).
        threshold (float or callable): the largest Γ an action may read, or a function
            returning it at each call (it follows a loss's buffer).
        candidates (int): actions read per step, the policy's own included (>= 2).
        shielded_key (NestedKey): where each step's flag goes (``[*B, 1]``, ``True``
            where the shield replaced the policy's action). Default ``"shielded"``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from wcsac_rl.modules import CriticShield, TanhNormalPolicy, make_actor
        >>> policy = TanhNormalPolicy(make_actor(3, Bounded(-1.0, 1.0, shape=(2,))))
        >>> # a toy critic: Γ is the first action coordinate, so the shield keeps it <= 0
        >>> shield = CriticShield(policy, lambda s, a: a[..., 0], threshold=0.0, candidates=64)
        >>> out = shield(TensorDict({"observation": torch.randn(5, 3)}, [5]))
        >>> bool((out["action"][:, 0] <= 0).all()), out["shielded"].shape
        (True, torch.Size([5, 1]))
    """

    def __init__(
        self,
        policy: TanhNormalPolicy,
        cvar: Callable[[TensorDictBase, Tensor], Tensor],
        threshold: float | Callable[[], float],
        candidates: int,
        shielded_key: NestedKey = "shielded",
    ) -> None:
        super().__init__()
        if not isinstance(policy, TanhNormalPolicy):
            raise TypeError(
                f"CriticShield filters a TanhNormalPolicy's actions, got {type(policy).__name__}"
            )
        if isinstance(candidates, bool) or not isinstance(candidates, int) or candidates < 2:
            raise ValueError(
                "candidates must be an integer >= 2 (the policy's action and at least one "
                f"other), got {candidates!r}"
            )
        if not callable(threshold):
            value = float(threshold)
            if value != value:
                raise ValueError("threshold must be a number, got nan")
            threshold = _Constant(value)
        self.policy = policy
        self.cvar = cvar
        self.threshold = threshold
        self.candidates = candidates
        self.shielded_key = shielded_key
        self.in_keys = list(policy.in_keys)
        self.out_keys = [*policy.out_keys, shielded_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self.policy(tensordict)
        # (outside any exploration context the actor samples: make_actor's default)
        if exploration_type() not in (None, InteractionType.RANDOM):
            return tensordict  # test episodes: the policy alone
        action_key = self.policy.action_key
        with torch.no_grad():
            action = tensordict.get(action_key)
            actions = torch.cat(
                [action.unsqueeze(0), self.policy.draw(tensordict, self.candidates - 1)]
            )
            states = tensordict.select(self.policy.observation_key).expand(
                self.candidates, *tensordict.batch_size
            )
            cvar = self.cvar(states, actions)
            safe = cvar <= float(self.threshold())
            # the first safe candidate (the policy's own is the first), else the least unsafe
            pick = torch.where(safe.any(0), safe.to(torch.uint8).argmax(0), cvar.argmin(0))
            index = pick.reshape(1, *pick.shape, 1).expand(1, *action.shape)
            chosen = actions.gather(0, index).squeeze(0)
        tensordict.set(action_key, chosen)
        tensordict.set(self.shielded_key, (pick != 0).unsqueeze(-1))
        return tensordict


class _Constant:
    """A fixed threshold as the callable :class:`CriticShield` reads."""

    def __init__(self, value: float) -> None:
        self.value = value

    def __call__(self) -> float:
        return self.value
