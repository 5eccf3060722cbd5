"""Several safety critics of one kind read as one: :class:`EnsembleHead`.

``num_safety_nets`` > 1 gives the loss this head over the member head
:func:`~wcsac_rl.objectives.ensemble_head.make_safety_head` picks for the critic's kind;
how the members are evaluated together, their random priors and the readings' maths
are in :mod:`~wcsac_rl.objectives.ensemble_reading`; CAP's adaptive ``k_ucb`` is
:class:`AdaptivePessimism`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import Tensor, nn

from wcsac_rl.objectives.ensemble_reading import StackedMembers, ucb, upper_tail_mean
from wcsac_rl.objectives.loss_options import SafetyHeadOptions
from wcsac_rl.objectives.risk import quantile_mixture_cvar
from wcsac_rl.objectives.safety_head import (
    GaussianHead,
    IQNHead,
    SafetyHead,
    SafetyValues,
    _make_member_head,
)
from wcsac_rl.options import check_options

__all__ = ["AdaptivePessimism", "EnsembleHead", "make_safety_head"]


class AdaptivePessimism(nn.Module):
    """``k_ucb`` adapted from the realised episode cost (CAP, Ma et al. AAAI 2022).

    At every :meth:`step` with the recent training episodes' cost ``C`` (the episode
    window's statistic, :class:`~wcsac_rl.objectives.EpisodeCostWindow`) and the limit
    ``d``: ``k ← clip(k + lr · (C − d), 0, k_max)`` — more pessimism while the episodes
    cost more than the limit, less while they cost less; no change while ``C`` is NaN
    (no episode has finished). ``k`` is a buffer: it is checkpointed with the loss, and
    the step reads no value on the host (``torch.compile`` keeps one graph).

    Example:
        >>> cap = AdaptivePessimism(0.5, lr=0.01, k_max=1.0)
        >>> for cost in (float("nan"), 45.0, 45.0, 0.0):
        ...     cap.step(torch.tensor(cost), torch.tensor(15.0))
        >>> cap.k  # 0.5, then + 0.3 twice (capped at 1), then − 0.15
        tensor(0.8500)
    """

    def __init__(self, k_ucb: float, *, lr: float, k_max: float) -> None:
        super().__init__()
        check_options({"k_ucb": k_ucb, "k_ucb_lr": lr, "k_ucb_max": k_max})
        self.lr, self.k_max = float(lr), float(k_max)
        self.register_buffer("k", torch.tensor(float(k_ucb)))

    @torch.no_grad()
    def step(self, cost: Tensor, limit: Tensor) -> None:
        cost = cost.reshape(-1)[0].to(self.k.dtype)
        moved = (self.k + self.lr * (cost - limit)).clamp(0.0, self.k_max)
        self.k.copy_(torch.where(cost.isnan(), self.k, moved))

    def extra_repr(self) -> str:
        return f"lr={self.lr}, k_max={self.k_max}"


class EnsembleHead(SafetyHead):
    """``options.num_safety_nets`` safety critics of one kind (``members``), read as
    ``options.ensemble_reading`` says (``reading``; the options:
    :class:`~wcsac_rl.objectives.loss_options.SafetyHeadOptions`, checked there).

    Each member is an independent critic of the ``member`` head's kind (its own
    initialisation, its own target network, its own TD loss against its own targets);
    the loss holds their parameters stacked along a leading dimension of size
    ``members`` (TorchRL's convention for the twin reward critics). Every reading
    returns the members' :class:`SafetyValues` stacked the same way, ``[members, *B]``.

    * :meth:`targets`, by ``options.ensemble_target`` (``target``): ``"own"``: each
      member's from its own target critic;
      ``"max"``: per row, every member's from the target critic of the member whose
      target value (Q̄^c, the mean) is largest there — TD3's clipped double-Q, which
      bootstraps from the smaller reward value, turned pessimistic for a cost, so
      that an under-estimate the actor has found in one member is not copied back
      through the bootstrap; ``"merged"`` (IQN members): every member's from all the
      members' target quantiles pooled (TQC's target, COX-Q's);
    * :meth:`loss`: each member's TD loss, summed over the members (TorchRL's SAC
      sums its reward critics' losses the same way), so with ``target="own"`` each
      member's gradient is exactly its own single-critic gradient;
    * :meth:`cvar`, the actor's, κ's and the shield's Γ(s, a, α), by ``reading``:
      ``"max"``, ``max_k Γ_k`` (where the members disagree, e.g. on a route the policy
      has just found, the most pessimistic one counts); ``"ucb"``,
      ``mean_k Γ_k + k_ucb · std_k Γ_k`` (CAL; the sample standard deviation,
      :func:`~wcsac_rl.objectives.ensemble_reading.ucb`); ``"tqc"`` (IQN members),
      the CVaR_α of every member's quantiles merged into one pool of ``members · N``
      atoms (:func:`~wcsac_rl.objectives.ensemble_reading.upper_tail_mean`);
    * :meth:`mixture_cvar`: the members' CVaRs of their mixtures over the rows read
      the same way (``"tqc"``: the CVaR of every member's quantiles at every row);
    * :meth:`diagnostics` and :meth:`estimates`: with ``"max"``, per row, the member
      whose Γ is the largest (so ``cost_value``, ``cost_variance`` and ``cvar``
      belong together); otherwise the members' mean ``cost_value`` and
      ``cost_variance``, ``cvar`` the reading's and (IQN) ``cost_quantiles`` the
      members' merged and sorted.

    The kit's critics (:func:`~wcsac_rl.modules.make_safety_critic`) are read in one
    batched product over the members under ``"ucb"``, ``"tqc"`` or with a prior
    (:class:`~wcsac_rl.objectives.ensemble_reading.StackedMembers`; an IQN ensemble
    then reads every member at the same fractions); ``"max"`` without a prior calls
    the members one after the other, as it always has. ``prior_scale`` > 0 adds a
    fixed random network per member (:class:`~wcsac_rl.objectives.ensemble_reading.RandomPrior`,
    :attr:`prior`) to every reading, online and target alike.

    Example:
        >>> import torch
        >>> from wcsac_rl.modules import make_safety_critic
        >>> from wcsac_rl.objectives import WCSACLoss
        >>> from wcsac_rl.objectives.safety_head import GaussianHead
        >>> member = GaussianHead(make_safety_critic(3, 1), WCSACLoss.default_keys(),
        ...                       risk_level=0.5, nonnegative_cost=False)
        >>> head = EnsembleHead(member, SafetyHeadOptions(num_safety_nets=2))
        >>> mean, variance = torch.tensor([[1.0, 5.0], [3.0, 0.0]]), torch.ones(2, 2)
        >>> head.cvar(SafetyValues(mean, variance))  # max(1.80, 3.80), max(5.80, 0.80)
        tensor([3.7979, 5.7979])
    """

    def __init__(self, member: SafetyHead, options: SafetyHeadOptions) -> None:
        members = options.num_safety_nets
        if members < 2:
            raise ValueError(f"an ensemble needs num_safety_nets >= 2, got {members}")
        check_options(options, safety_critic=member.kind)  # (the kind: its networks')
        super().__init__(
            member.network,
            member.keys,
            risk_level=member.risk_level,
            nonnegative_cost=member.nonnegative_cost,
        )
        self.member, self.members, self.target = member, int(members), options.ensemble_target
        self.reading, self.k_ucb = options.ensemble_reading, float(options.k_ucb)
        self.pessimism = (
            AdaptivePessimism(options.k_ucb, lr=options.k_ucb_lr, k_max=options.k_ucb_max)
            if options.k_ucb_lr > 0
            else None
        )
        self.stacked = None
        if self.reading != "max" or options.prior_scale > 0:
            keys = member.keys
            self.stacked = StackedMembers.plan(member.network, keys.action, keys.quantile_fractions)
        self.prior = None
        if options.prior_scale > 0:
            if self.stacked is None:
                raise ValueError(
                    "prior_scale > 0 adds a random network of the members' shape: it needs "
                    "the kit's safety critics (wcsac_rl.modules.make_safety_critic)"
                )
            self.prior = self.stacked.add_prior(self.members, options.prior_scale)

    kind = property(lambda self: self.member.kind)
    has_variance = property(lambda self: self.member.has_variance)
    loss_names = property(lambda self: self.member.loss_names)
    diagnostic_names = property(lambda self: self.member.diagnostic_names)
    in_keys = property(lambda self: self.member.in_keys)

    def unfused_reason(self) -> str:
        return (
            f"{self.members} safety critics (num_safety_nets) are read apart from the "
            "reward critics"
        )

    @property
    def reads_episode_costs(self) -> bool:
        """Whether :meth:`adapt` reads the recent episodes' cost (``k_ucb_lr`` > 0)."""
        return self.pessimism is not None

    def adapt(self, tensordict: TensorDictBase, cost_limit: float) -> None:
        """One step of the adaptive ``k_ucb`` (:attr:`pessimism`, if any) on the episode
        window's cost the batch carries (``keys.episode_cvar``) against ``cost_limit``."""
        if self.pessimism is not None:
            self.pessimism.step(tensordict.get(self.keys.episode_cvar), cost_limit)

    def _k(self):
        # (a copy: the adaptive k moves in place after the actor loss has read it)
        return self.k_ucb if self.pessimism is None else self.pessimism.k.clone()

    def read_through_module(self) -> None:
        self.member.read_through_module()
        if self.prior is None:  # (a prior is read from the stacked parameters only)
            self.stacked = None

    def _each(self, values: SafetyValues) -> list[SafetyValues]:
        return [
            SafetyValues(*(None if v is None else v[k] for v in values))
            for k in range(self.members)
        ]

    @staticmethod
    def _stack(readings: list) -> SafetyValues:
        return SafetyValues(*(None if v[0] is None else torch.stack(v) for v in zip(*readings)))

    @staticmethod
    def _stack_dicts(each: list[dict]) -> dict:
        """The members' dicts of tensors (``None`` where a head has none) stacked per key."""
        return {
            key: None if each[0][key] is None else torch.stack([d[key] for d in each])
            for key in each[0]
        }

    def values(
        self,
        tensordict: TensorDictBase,
        params: TensorDictBase,
        action: Tensor | None = None,
        *,
        target: bool = False,
        stratified: bool = True,
    ) -> SafetyValues:
        """Every member's values (``params``: stacked ``[members, ...]``), ``[members, *B]``."""
        if self.stacked is not None:
            return self._stacked_values(tensordict, params, action, target, stratified)
        return self._stack(
            [
                self.member.values(
                    tensordict, params[k], action, target=target, stratified=stratified
                )
                for k in range(self.members)
            ]
        )

    def _stacked_values(self, tensordict, params, action, target, stratified) -> SafetyValues:
        """:meth:`values` in one batched product over the members (and the prior)."""
        if self.stacked.kind != "iqn":
            mean, variance = self.stacked.gaussian(tensordict, params, action)
            return SafetyValues(mean, variance)
        member = self.member
        like = params.get(member._like_key)
        count = member.num_target_quantiles if target else member.num_quantiles
        fractions = member.fractions(count, like, stratified=stratified)
        tail = None
        if target:
            quantiles = self.stacked.quantiles(tensordict, params, action, fractions)
        else:
            tail_fractions = member.fractions(member.num_quantiles, like, True, stratified)
            both = torch.cat([fractions, tail_fractions])
            quantiles, tail = self.stacked.quantiles(tensordict, params, action, both).split(
                [count, member.num_quantiles], dim=-1
            )
        mean = quantiles.mean(-1)
        variance = (quantiles - mean.unsqueeze(-1)).pow(2).mean(-1)
        fractions = fractions.expand(self.members, fractions.shape[-1])  # (one draw for all)
        return SafetyValues(mean, variance, quantiles, fractions, tail)

    def skip_reading(
        self, params: TensorDictBase, *, target: bool = False, stratified: bool = True
    ) -> None:
        draws = 1 if self.stacked is not None else self.members  # (members share one draw)
        for k in range(draws):
            self.member.skip_reading(params[k], target=target, stratified=stratified)

    def targets(
        self, cost: Tensor, gamma: Tensor, alive: Tensor, ahead: SafetyValues
    ) -> dict[str, Tensor | None]:
        """Each member's targets, stacked ``[members, *B, ...]``: from its own target
        critic (``target="own"``), all from the member whose target value is the
        largest, row by row (``"max"``; the rows' picks among ``ahead``'s members), or
        (IQN members) all from every member's target quantiles pooled and sorted, ``[*B,
        members · N']`` (``"merged"``: TQC's target, COX-Q's)."""
        if self.target == "own":
            return self._stack_dicts(
                [self.member.targets(cost, gamma, alive, v) for v in self._each(ahead)]
            )
        if self.target == "merged":
            pooled = self._pool(ahead.quantiles).sort(-1).values
            shared = self.member.targets(cost, gamma, alive, SafetyValues(quantiles=pooled))
        else:
            rows = {"mean": ahead.mean, "variance": ahead.variance, "quantiles": ahead.quantiles}
            pessimistic = SafetyValues(**self._pick(ahead.mean.argmax(0), rows))
            shared = self.member.targets(cost, gamma, alive, pessimistic)
        return {
            key: None if value is None else value.expand(self.members, *value.shape)
            for key, value in shared.items()
        }

    def loss(self, values: SafetyValues, targets: dict[str, Tensor]) -> dict[str, Tensor]:
        """Per row: each term summed over the members."""
        each = [
            self.member.loss(v, {k: None if t is None else t[m] for k, t in targets.items()})
            for m, v in enumerate(self._each(values))
        ]
        return {name: sum(terms[name] for terms in each) for name in each[0]}

    def variance_target(self, targets: dict[str, Tensor], cost_value: Tensor) -> Tensor:
        """The member head's variance target, member by member (stacked in, stacked out)."""
        return self.member.variance_target(targets, cost_value)

    def member_cvars(self, values: SafetyValues) -> Tensor:
        """Each member's Γ, ``[members, *B]``."""
        return torch.stack([self.member.cvar(v) for v in self._each(values)])

    @staticmethod
    def _pool(quantiles: Tensor) -> Tensor:
        """``[members, *B, N]`` as one pool per row, ``[*B, members · N]``."""
        quantiles = quantiles.movedim(0, -2)
        return quantiles.reshape(*quantiles.shape[:-2], -1)

    def merged_quantiles(self, values: SafetyValues) -> Tensor:
        """Every member's quantiles of a row in one pool, ``[*B, members · N]`` (each
        at least 0 with ``nonnegative_cost``)."""
        quantiles = self._pool(values.quantiles)
        return quantiles.clamp(min=0.0) if self.nonnegative_cost else quantiles

    def cvar(self, values: SafetyValues) -> Tensor:
        """Γ per row, ``[*B]``, as ``reading`` says: the largest member's, the members'
        upper confidence bound, or the CVaR_α of their merged quantiles."""
        if self.reading == "tqc":
            return upper_tail_mean(self.merged_quantiles(values), self.risk_level)
        if self.reading == "ucb":
            return ucb(self.member_cvars(values), self._k())
        return self.member_cvars(values).max(0)[0]

    def mixture_cvar(self, values: SafetyValues, weights: Tensor | None = None) -> Tensor:
        """The members' mixture CVaRs read as ``reading`` says (0-dim)."""
        if self.reading == "tqc":
            return quantile_mixture_cvar(
                self.merged_quantiles(values), self.risk_level, weights=weights
            )
        each = torch.stack([self.member.mixture_cvar(v, weights) for v in self._each(values)])
        return ucb(each, self._k()) if self.reading == "ucb" else each.max()

    def row_shape(self, values: SafetyValues) -> torch.Size:
        return values.mean.shape[1:]

    @staticmethod
    def _pick(pick: Tensor, readings: dict) -> dict:
        """``readings`` (each ``[members, *B, ...]``) of member ``pick`` (``[*B]``) per row."""
        out = {}
        for name, value in readings.items():
            if value is None:
                out[name] = None
                continue
            index = pick.reshape(1, *pick.shape, *([1] * (value.dim() - 1 - pick.dim())))
            out[name] = value.gather(0, index.expand(1, *value.shape[1:])).squeeze(0)
        return out

    def diagnostics(self, values: SafetyValues) -> dict[str, Tensor | None]:
        """The detached ``cost_value`` and ``cost_variance``: ``"max"``, of the member
        with the largest Γ, per row; otherwise the members' mean."""
        values = values.detach()
        each = self.member.diagnostics(values)
        if self.reading != "max":
            return {key: None if v is None else v.mean(0) for key, v in each.items()}
        return self._pick(self.member_cvars(values).argmax(0), each)

    def estimates(self, tensordict: TensorDictBase, params: TensorDictBase) -> dict[str, Tensor]:
        """The member head's estimates (an IQN's at the strata's midpoints): ``cvar``
        is :meth:`cvar`; ``cost_value``, ``cost_variance`` and (IQN) ``cost_quantiles``
        are those of the member with the largest Γ per row (``"max"``), otherwise the
        members' mean value and variance and their quantiles merged and sorted."""
        values = self.values(tensordict, params, stratified=False)
        rows = {"cost_value": values.mean, "cost_variance": values.variance}
        if self.reading == "max":
            rows["cost_quantiles"] = values.quantiles
            out = self._pick(self.member_cvars(values).argmax(0), rows)
        else:
            out = {key: None if v is None else v.mean(0) for key, v in rows.items()}
            if values.quantiles is not None:
                out["cost_quantiles"] = self.merged_quantiles(values).sort(-1).values
        out["cvar"] = self.cvar(values)
        return {key: value for key, value in out.items() if value is not None}


def make_safety_head(
    network: TensorDictModule,
    keys,
    *,
    risk_level: float,
    options: SafetyHeadOptions | None = None,
) -> GaussianHead | IQNHead | EnsembleHead:
    """The head for ``network``: the one place that decides the safety critic's kind.

    An implicit quantile network (an :class:`~wcsac_rl.modules.IQNSafetyCritic`, or a
    module reading ``keys.quantile_fractions``) gets an :class:`IQNHead`, anything
    else a :class:`GaussianHead`, built as ``options`` say
    (:class:`~wcsac_rl.objectives.loss_options.SafetyHeadOptions`; ``None``: its
    defaults); the Gaussian head's ``variance_loss`` / ``variance_target`` are refused
    for an IQN critic unless left at their defaults. ``num_safety_nets`` > 1: that
    many critics of the kind, read by an :class:`EnsembleHead`.
    """
    options = SafetyHeadOptions() if options is None else options
    head = _make_member_head(network, keys, risk_level=risk_level, options=options)
    if options.num_safety_nets == 1:
        return head
    return EnsembleHead(head, options)
