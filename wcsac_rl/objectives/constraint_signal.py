"""What the Lagrange multiplier κ holds under which threshold: the constraint's signal.

:mod:`wcsac_rl.objectives.constraint` says how κ moves (gradient or PID); this module
says what it reads. Four options, each with the paper's choice first:

* ``kappa_states`` — where the critic is read: ``"replay"`` (the sampled batch, the
  paper and the authors' code; Γ then estimates a discounted per-step cost, held under
  the per-step threshold ``d·(1−γ_c^T)/((1−γ_c)T)``) or ``"initial"`` (episode start
  states, one per batch row under the ``initial_states`` key, with ``a ~ π``:
  Γ(s₀, a₀) estimates the CVaR of the episode's cost, held under the episodic limit
  ``d`` itself; :class:`~wcsac_rl.objectives.StartStateBuffer` provides them).
* ``kappa_actions`` — at replay states, the actions: ``"replay"`` (the stored ones, the
  authors' code) or ``"policy"`` (``a ~ π``, as the paper writes; Γ at the actor's own
  actions, computed with the actor loss).
* ``kappa_statistic`` — ``"mean"`` (the paper): the mean of the per-state Γ(s, a, α);
  ``"tail"``: the CVaR_α of the critic's cost distribution *mixed over the states*
  (the head's :meth:`~wcsac_rl.objectives.safety_head.SafetyHead.mixture_cvar`), which
  at start states is the CVaR of an episode's cost when the start state is random too;
  the mean of per-state CVaRs is never larger and misses a tail made of a few risky
  start states. Equal at α = 1.
* ``kappa_signal`` — ``"critic"`` (the paper): that statistic. ``"episodes"``: the
  recent finished episodes' empirical CVaR_α (or mean cost), read from the batch at the
  ``episode_cvar`` key (:class:`~wcsac_rl.objectives.EpisodeCostWindow`); ``"max"``:
  the larger of the two, so κ rises as soon as collected episodes exceed the limit
  while the critic still lags. Where no episode has finished (NaN) both fall back to
  the critic. Needs ``kappa_states="initial"`` (the threshold is then the episodic
  ``d`` the costs are measured against).

The actor's cost term is always the critic's Γ at its own actions; the signal only sets
κ (and the MDMM damping).

``kappa_signal_every`` (k): at the start states with the tail statistic, the critic's
reading is one number per batch that nothing else uses, so it may be read every k
training updates and held in between (:class:`HeldStatistic`): the actor draws at the
start states and the critic's evaluation there happen once in k updates. The episodes'
half of the signal is still read at every update. k = 1 (the default) reads it every
update, as before.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

from wcsac_rl.objectives.budget import per_step_cost_threshold
from wcsac_rl.objectives.inputs import required_entry
from wcsac_rl.options import (
    KAPPA_ACTIONS,
    KAPPA_SIGNALS,
    KAPPA_STATES,
    KAPPA_STATISTICS,
)

__all__ = [
    "KAPPA_ACTIONS",
    "KAPPA_SIGNALS",
    "KAPPA_STATES",
    "KAPPA_STATISTICS",
    "ConstraintSignal",
    "HeldStatistic",
    "check_signal_states",
]


def check_signal_states(states: str, signal: str) -> None:
    """An episode signal (``kappa_signal`` other than ``"critic"``) needs
    ``kappa_states="initial"``: one ``ValueError`` line naming both."""
    if signal != "critic" and states != "initial":
        raise ValueError(
            f"kappa_signal={signal!r} compares episode costs with the episodic limit "
            "d, which is the threshold only with kappa_states='initial' (with 'replay' "
            "it is a per-step threshold)"
        )


class ConstraintSignal:
    """The signal κ holds under its threshold, per batch row (see the module doc).

    Args:
        head: the loss's safety head (:mod:`wcsac_rl.objectives.safety_head`): its
            :meth:`cvar` and :meth:`mixture_cvar` give the statistics.
        keys: the loss's ``tensor_keys`` (``initial_states``, ``episode_cvar``).
        states, actions, statistic, signal: ``kappa_states``, ``kappa_actions``,
            ``kappa_statistic``, ``kappa_signal``.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from wcsac_rl.modules import make_safety_critic
        >>> from wcsac_rl.objectives import WCSACLoss
        >>> from wcsac_rl.objectives.safety_head import GaussianHead
        >>> keys = WCSACLoss.default_keys()
        >>> head = GaussianHead(make_safety_critic(3, 1), keys, risk_level=1.0,
        ...                     nonnegative_cost=False)
        >>> signal = ConstraintSignal(head, keys, states="initial", signal="max")
        >>> batch = TensorDict({"episode_cvar": torch.tensor([[20.0], [float("nan")]])}, [2])
        >>> signal.signal(batch, torch.tensor([12.0, 12.0]))  # NaN: the critic's
        tensor([20., 12.])
    """

    def __init__(
        self,
        head,
        keys,
        *,
        states: str = "initial",
        actions: str = "policy",
        statistic: str = "tail",
        signal: str = "critic",
    ) -> None:
        for name, value, allowed in (
            ("kappa_actions", actions, KAPPA_ACTIONS),
            ("kappa_states", states, KAPPA_STATES),
            ("kappa_signal", signal, KAPPA_SIGNALS),
            ("kappa_statistic", statistic, KAPPA_STATISTICS),
        ):
            if value not in allowed:
                raise ValueError(f"{name} must be one of {allowed}, got {value!r}")
        check_signal_states(states, signal)
        self.head = head
        self.keys = keys
        self.states, self.actions = states, actions
        self.statistic_kind, self.signal_kind = statistic, signal

    @property
    def needs_replay_values(self) -> bool:
        """Whether the signal is read at the batch's own state-actions."""
        return self.states == "replay" and self.actions == "replay"

    def threshold(self, cost_limit: float, cost_gamma: float, max_episode_steps: int) -> float:
        """The threshold for the episodic limit ``d``: ``d`` at start states, the
        per-step ``d·(1−γ_c^T)/((1−γ_c)T)`` at replay states."""
        if self.states == "initial":
            return cost_limit
        return per_step_cost_threshold(cost_limit, cost_gamma, max_episode_steps)

    def initial_states(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The start states the batch carries (one per row), shaped like the batch."""
        key = self.keys.initial_states
        states = required_entry(
            tensordict,
            key,
            "kappa_states='initial' needs episode start states (a sub-tensordict shaped like "
            "the batch with the actor's observation entries)",
            f"The wcsac_rl trainer attaches them; in your own loop sample start states and "
            f"set batch[{key!r}] = them.",
        )
        if states.batch_dims > tensordict.batch_dims:
            # (rebuilt from flat entries, e.g. TorchRL's keyword call, a sub-tensordict
            # takes every leading dimension its entries share: the observation's too)
            states = states.copy()
            states.batch_size = tensordict.batch_size
        return states

    def critic_values(self, tensordict: TensorDictBase, replay_values, at_policy: Callable):
        """The critics' values where the statistic is taken: ``at_policy(states)`` (the
        critics at ``a ~ π(states)``, no gradient) at the start states, ``replay_values``
        at the replay state-actions, or ``None`` for the actor's own actions on the
        batch (they come with the actor loss)."""
        if self.states == "initial":
            return at_policy(self.initial_states(tensordict))
        if self.actions == "replay":
            return replay_values
        return None

    def statistic(self, values, mask: Tensor | None = None) -> Tensor:
        """Per row: Γ (``"mean"``: the κ loss averages it), or for ``"tail"`` the CVaR_α
        of the critic's distribution mixed over the rows, repeated per row (detached).
        ``mask`` (per row, ``False``: a padded or invalid row, TorchRL's loss masks)
        keeps those rows out of the mixture; the κ loss's reduction drops them from the
        mean."""
        if self.statistic_kind == "mean":
            return self.head.cvar(values)
        return self.head.mixture_cvar(values, mask).detach().expand(self.head.row_shape(values))

    def episode_cvar(self, tensordict: TensorDictBase) -> Tensor:
        """The recent episodes' empirical CVaR_α from the batch (NaN: none finished)."""
        key = self.keys.episode_cvar
        return required_entry(
            tensordict,
            key,
            f"kappa_signal={self.signal_kind!r} needs the empirical CVaR_α of recent "
            "episode costs ([*B, 1], NaN while no episode has ended)",
            f"The wcsac_rl trainer attaches it; in your own loop keep an "
            f"EpisodeCostWindow.for_loss(loss) and set batch[{key!r}] with its attach().",
        )

    def signal(self, tensordict: TensorDictBase, statistic: Tensor | None) -> Tensor | None:
        """What κ holds under the threshold: the critic's ``statistic``, or the
        episodes' empirical CVaR, or the larger of them; the critic's where the episodes
        give NaN (none finished yet)."""
        if self.signal_kind == "critic" or statistic is None:
            return statistic
        episodes = self.episode_cvar(tensordict).to(statistic.dtype).reshape(statistic.shape)
        if self.signal_kind == "max":
            return torch.fmax(statistic, episodes)  # fmax: NaN loses
        return torch.where(episodes.isnan(), statistic, episodes)


class HeldStatistic(nn.Module):
    """The critic's statistic read every ``every`` training updates and held in between.

    Two buffers, so that a checkpoint carries them and a resumed run reads the critic
    when the uninterrupted one would: ``value`` (the last reading, 0-dim) and ``age``
    (updates since it was read, counting the one that read it; 0: none yet).

    Example:
        >>> hold = HeldStatistic(3)
        >>> hold.take() is None          # nothing held yet: read the critic
        True
        >>> hold.store(torch.tensor(4.0))
        >>> hold.take(), hold.take()     # the next two updates hold it
        (tensor(4.), tensor(4.))
        >>> hold.take() is None          # the third reads it again
        True
    """

    def __init__(self, every: int) -> None:
        super().__init__()
        if isinstance(every, bool) or not isinstance(every, int) or every < 2:
            raise ValueError(f"HeldStatistic holds for every >= 2 updates, got {every!r}")
        self.every = every
        self.register_buffer("value", torch.full((), float("nan")))
        self.register_buffer("age", torch.zeros((), dtype=torch.long))
        self._age: int | None = 0  # the buffer's value in Python (None: not read yet)

    def take(self) -> Tensor | None:
        """The held value for this update (and count it), or ``None`` when the critic is
        to be read: nothing held yet, or held for ``every`` updates already. The age is
        kept in Python beside its buffer: read from the buffer once (after a load), not
        at every update."""
        if self._age is None:
            self._age = int(self.age)  # (a host read: once, not per update)
        if self._age == 0 or self._age >= self.every:
            return None
        self._age += 1
        self.age += 1
        return self.value.clone()

    def store(self, value: Tensor) -> None:
        """Hold ``value`` (0-dim, detached) from this update on."""
        self.value.copy_(value.detach().reshape(()))
        self.age.fill_(1)
        self._age = 1

    def _load_from_state_dict(self, *args, **kwargs) -> None:
        super()._load_from_state_dict(*args, **kwargs)
        self._age = None  # (the loaded buffer is read again at the next update)

    def extra_repr(self) -> str:
        return f"every={self.every}"
