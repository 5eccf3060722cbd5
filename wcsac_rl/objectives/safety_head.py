"""The safety critic's head: how a loss reads, trains and takes the CVaR of its safety critic.

:class:`~wcsac_rl.objectives.WCSACLoss` never asks which safety critic it holds; it
calls the head that :func:`make_safety_head` picked for it (the one place that decides
the kind) through a small interface:

* :meth:`~SafetyHead.values` — the critic at a batch of state-actions
  (a :class:`SafetyValues`), with given parameters (online, target or detached);
* :meth:`~SafetyHead.targets` — its TD targets from the cost, the discount and the
  target critic's values where the sum is bootstrapped (:class:`CostTarget` reads
  them from the batch);
* :meth:`~SafetyHead.loss` — its TD loss terms per batch row (named as the loss
  reports them);
* :meth:`~SafetyHead.cvar` — Γ(s, a, α) per row, and :meth:`~SafetyHead.mixture_cvar`,
  the CVaR_α of the critic's distribution mixed over the rows;
* :meth:`~SafetyHead.estimates` — its outputs for diagnostics (calibration).

Two heads, and an ensemble of either
(:class:`~wcsac_rl.objectives.ensemble_head.EnsembleHead`, in its own module):

* :class:`GaussianHead` — the paper's ``C(s, a) ~ N(Q^c, V^c)`` (a mean and a variance
  network; Eq. 7–9), or the mean alone (SAC-Lagrangian, where Γ = Q^c);
* :class:`IQNHead` — an implicit quantile network (the journal version): quantile
  Huber TD loss (:func:`quantile_huber_loss`) on fractions drawn one per stratum
  (:func:`stratified_fractions`), Γ the mean of its quantiles over ``τ ∈ [1 − α, 1]``.

A head holds no parameters: the loss owns the network's functional parameters (and
their targets, which ``SoftUpdate`` finds by name) and hands them to every call.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor

from wcsac_rl.modules.quantile_critic import IQNSafetyCritic
from wcsac_rl.modules.safety_critic import VARIANCE_MAX, VARIANCE_MIN
from wcsac_rl.objectives.fast_paths import FusedCritics, IQNReader
from wcsac_rl.objectives.inputs import nested_key, required_entry
from wcsac_rl.objectives.risk import (
    gaussian_cvar_multiplier,
    gaussian_mixture_cvar,
    quantile_mixture_cvar,
)
from wcsac_rl.objectives.variance import variance_regression_loss
from wcsac_rl.options import (
    VARIANCE_TARGETS,
    IQNOptions,
    SafetyOptions,
    check_options,
)

__all__ = [
    "VARIANCE_TARGETS",
    "CostTarget",
    "GaussianHead",
    "IQNHead",
    "SafetyHead",
    "SafetyValues",
    "is_iqn_critic",
    "midpoint_fractions",
    "quantile_huber_loss",
    "stratified_fractions",
]


class SafetyValues(NamedTuple):
    """The safety critic at a batch of state-actions, squeezed to the batch shape ``*B``.

    ``mean`` is Q^c and ``variance`` V^c (``None`` for a mean-only critic). An IQN
    critic also gives ``quantiles`` ``[*B, N]`` at ``fractions`` ``[N]`` (one draw
    over [0, 1], shared by the rows; ``mean`` and ``variance`` are theirs) and
    ``tail`` ``[*B, N]``, its quantiles over ``[1 − α, 1]`` (whose mean is Γ), or
    ``None`` where not needed (target values).
    """

    mean: Tensor | None = None
    variance: Tensor | None = None
    quantiles: Tensor | None = None
    fractions: Tensor | None = None
    tail: Tensor | None = None

    def detach(self) -> SafetyValues:
        """The same values without gradient."""
        return SafetyValues(*(None if v is None else v.detach() for v in self))


class CostTarget:
    """What the safety critic's TD target is made of: the cost summed, its discount, where
    it stops.

    The target of every safety head has the form
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
        check_options({"cost_gamma": gamma, "cost_n_steps": n_steps})
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


class SafetyHead:
    """What every head shares: the network, the loss's key names and the options of Γ.

    Args:
        network (TensorDictModule): the safety critic (its functional parameters are
            the loss's; the module is only called with them).
        keys: the loss's ``tensor_keys`` (read at every call, so ``set_keys`` applies).
        risk_level (float): α ∈ (0, 1], the tail fraction of Γ.
        nonnegative_cost (bool): costs are never negative: use ``max(Q^c, 0)`` (each
            quantile at least 0) wherever the critic's value is *used* (targets, Γ).
    """

    kind: str
    loss_names: tuple[str, ...]

    def __init__(
        self, network: TensorDictModule, keys, *, risk_level: float, nonnegative_cost: bool
    ) -> None:
        self.network = network
        self.keys = keys
        self.risk_level = float(risk_level)
        self.nonnegative_cost = bool(nonnegative_cost)

    @property
    def has_variance(self) -> bool:
        """Whether the critic has a variance network (only the Gaussian head's)."""
        return False

    def skip_reading(
        self, params: TensorDictBase, *, target: bool = False, stratified: bool = True
    ) -> None:
        """Draw the random numbers a :meth:`values` call with these arguments would (an
        IQN head's fractions; none here) without evaluating the critic: a reading whose
        result is not needed keeps the random stream, and every result after it, as they
        were when it was made."""

    def action_cvar(
        self, tensordict: TensorDictBase, params: TensorDictBase, action: Tensor
    ) -> Tensor:
        """Γ at the states of ``tensordict`` and ``action`` ``[*B, A]``, shaped ``[*B]``,
        no gradient, deterministic (an IQN head's midpoints): what a shield reads."""
        batch, flat = tensordict.batch_size, tensordict.reshape(-1)
        with torch.no_grad():
            action = action.reshape(flat.numel(), action.shape[-1])
            values = self.values(flat, params.detach(), action, stratified=False)
            return self.cvar(values).reshape(batch)

    @property
    def in_keys(self) -> list:
        """What the critic reads from a batch (the entries the loss does not write)."""
        return list(self.network.in_keys)

    def _inputs(self, tensordict: TensorDictBase, action: Tensor | None) -> TensorDictBase:
        td = tensordict.select(*self.in_keys, strict=False)
        if action is not None:
            td.set(self.keys.action, action)
        return td

    def fusion_plan(self, qvalue_network: TensorDictModule, num_qvalue_nets: int):
        """A :class:`~wcsac_rl.objectives.fast_paths.FusedCritics` evaluating the
        reward critics and this one at once, or ``None`` (call the modules)."""
        return None

    reads_episode_costs = False
    """Whether :meth:`adapt` reads the recent episodes' cost (an ensemble's adaptive
    ``k_ucb``)."""

    def adapt(self, tensordict: TensorDictBase, cost_limit: float) -> None:
        """Adapt the head's reading to the batch's episode costs (none here)."""

    def read_through_module(self) -> None:
        """Evaluate the network through its module call from now on (a head that reads
        it from its parameters instead: the same values; see ``Critics.read_through_modules``)."""

    def unfused_reason(self) -> str:
        """Why the critics are not fused (``fast_paths=True``'s refusal says it)."""
        return (
            "the reward and safety critics are not MLPs of one shape (Linear/activation "
            "stacks) reading [observation, action], as wcsac_rl.modules builds them"
        )

    @property
    def diagnostic_names(self) -> tuple[str, ...]:
        """What :meth:`diagnostics` reports (the loss's outputs ``cost_value``, ...)."""
        return ("cost_value", "cost_variance") if self.has_variance else ("cost_value",)

    def diagnostics(self, values: SafetyValues) -> dict[str, Tensor | None]:
        """The detached ``cost_value`` and ``cost_variance`` (``None`` where there is none)."""
        variance = None if values.variance is None else values.variance.detach()
        return {"cost_value": values.mean.detach(), "cost_variance": variance}

    def row_shape(self, values: SafetyValues) -> torch.Size:
        """The batch shape ``*B`` of ``values`` (what :meth:`cvar` returns)."""
        return values.mean.shape


class GaussianHead(SafetyHead):
    """The paper's Gaussian safety critic ``C(s, a) ~ N(Q^c, V^c)``, or its mean alone.

    The network writes the cost mean ``Q^c`` at ``keys.cost_value`` and, with a
    variance network, ``V^c > 0`` at ``keys.cost_variance`` (if its out_keys are
    named otherwise, the first is taken as the mean and the second as the variance).

    * mean TD loss (Eq. 7): ``½ (c + γ_c(1−term) Q̄^c(s', a') − Q^c(s, a))²``;
    * variance TD loss (Eq. 8) with ``variance_loss`` (:mod:`wcsac_rl.objectives.variance`:
      ``"w2"`` the paper's 2-Wasserstein term, ``"mse"``, ``"glm"``) against the
      target of ``variance_target`` (:meth:`variance_target`: ``"moment"``, Eq. 8's
      second moment minus the squared mean; ``"td"``, the squared TD error plus the
      discounted next variance, never negative);
    * ``Γ = Q^c + α⁻¹ φ(Φ⁻¹(α)) √V^c`` (Eq. 9). A mean-only critic is allowed at α = 1
      only (SAC-Lagrangian: Γ = Q^c).

    Example:
        >>> import torch
        >>> from wcsac_rl.modules import make_safety_critic
        >>> from wcsac_rl.objectives import WCSACLoss
        >>> head = GaussianHead(make_safety_critic(3, 1), WCSACLoss.default_keys(),
        ...                     risk_level=0.5, nonnegative_cost=False)
        >>> head.cvar(SafetyValues(torch.tensor([1.0]), torch.tensor([4.0])))  # 1 + 0.7979·2
        tensor([2.5958])
    """

    def __init__(
        self,
        network: TensorDictModule,
        keys,
        *,
        risk_level: float,
        nonnegative_cost: bool,
        variance_loss: str = SafetyOptions.variance_loss,
        variance_target: str = SafetyOptions.variance_target,
    ) -> None:
        super().__init__(network, keys, risk_level=risk_level, nonnegative_cost=nonnegative_cost)
        check_options({"variance_loss": variance_loss, "variance_target": variance_target})
        self.variance_loss = variance_loss
        self.variance_target_kind = variance_target
        self.cvar_multiplier = gaussian_cvar_multiplier(self.risk_level)
        self._adopt_keys()
        if self.cvar_multiplier != 0.0 and not self.has_variance:
            raise ValueError(
                f"risk_level={self.risk_level} needs a safety critic with a variance head "
                f"(out_keys {keys.cost_value!r} and {keys.cost_variance!r}); "
                f"this one writes only {list(network.out_keys)}. A mean-only critic "
                "is SAC-Lagrangian: use risk_level=1 (or SACLagLoss)."
            )

    def _adopt_keys(self) -> None:
        out_keys, keys = list(self.network.out_keys), self.keys
        if not any(k in out_keys for k in (keys.cost_value, keys.cost_variance)):
            if len(out_keys) > 2:
                raise ValueError(
                    f"cannot tell the cost mean and variance apart among the safety "
                    f"critic's out_keys {out_keys}; call set_keys(cost_value=..., cost_variance=...)"
                )
            keys.cost_value = out_keys[0]
            if len(out_keys) == 2:
                keys.cost_variance = out_keys[1]
        if keys.cost_value not in out_keys:
            raise ValueError(
                f"the safety critic writes {out_keys} but the loss reads the cost mean "
                f"from {keys.cost_value!r}"
            )

    @property
    def kind(self) -> str:
        return "gaussian" if self.has_variance else "mean"

    @property
    def has_variance(self) -> bool:
        return self.keys.cost_variance in self.network.out_keys

    @property
    def loss_names(self) -> tuple[str, ...]:
        if self.has_variance:
            return ("loss_cost_value", "loss_cost_variance")
        return ("loss_cost_value",)

    def fusion_plan(self, qvalue_network: TensorDictModule, num_qvalue_nets: int):
        return FusedCritics.plan(
            qvalue_network,
            self.network,
            action_key=self.keys.action,
            num_qvalue_nets=num_qvalue_nets,
            has_variance=self.has_variance,
        )

    def values(
        self,
        tensordict: TensorDictBase,
        params: TensorDictBase,
        action: Tensor | None = None,
        *,
        target: bool = False,
        stratified: bool = True,
    ) -> SafetyValues:
        """Q^c and V^c (clamped to [1e-8, 1e8]) at the state and ``action`` (else the
        batch's own) with the parameters ``params``. ``target`` and ``stratified``
        are the IQN head's (no effect here)."""
        td = self._inputs(tensordict, action)
        with params.to_module(self.network, preserve_module_state=False):
            td = self.network(td)
        mean = td.get(self.keys.cost_value).squeeze(-1)
        if not self.has_variance:
            return SafetyValues(mean)
        variance = td.get(self.keys.cost_variance).squeeze(-1)
        return SafetyValues(mean, variance.clamp(VARIANCE_MIN, VARIANCE_MAX))

    def targets(
        self, cost: Tensor, gamma: Tensor, alive: Tensor, ahead: SafetyValues
    ) -> dict[str, Tensor | None]:
        """``cost_target`` ``c + γ_c·alive·Q̄^c`` (Eq. 7), and with a variance network
        ``cost_second_moment`` (``c² + alive(2γ_c c Q̄^c + γ_c² Q̄^c²) + γ_c² alive V̄^c``:
        Eq. 8's target is this minus ``Q^c(s, a)²``) and ``cost_next_variance``
        (``γ_c² alive V̄^c``); ``None`` otherwise. ``ahead``: the target critic where
        the sum is bootstrapped; ``alive``: 1 where it is (0 at a termination)."""
        mean = ahead.mean.clamp(min=0.0) if self.nonnegative_cost else ahead.mean
        second_moment = next_variance = None
        if ahead.variance is not None:
            next_variance = alive * gamma.pow(2) * ahead.variance
            second_moment = (
                cost.pow(2)
                + alive * (2 * gamma * cost * mean + gamma.pow(2) * mean.pow(2))
                + next_variance
            )
        return {
            "cost_target": cost + gamma * alive * mean,
            "cost_second_moment": second_moment,
            "cost_next_variance": next_variance,
        }

    def variance_target(self, targets: dict[str, Tensor], cost_value: Tensor) -> Tensor:
        """The TD target of V^c(s, a) from :meth:`targets`' ``targets``.

        ``"moment"`` (Eq. 8): ``y_v = sampled C² − Q^c(s, a)²``; ``"td"``:
        ``y_v = (y_c − Q^c(s, a))² + γ_c²(1−term) V̄^c(s', a')`` with ``y_c`` the mean
        target. ``Q^c(s, a)`` is detached in both. For ``"w2"`` the target is clamped
        to [1e-8, 1e8] (its square root needs it positive, as in the paper); for the
        regression losses only to [−1e8, 1e8]: a single sampled moment-form target
        may legitimately be negative, and clamping it at 0 would bias the fit upwards.
        """
        cost_value = cost_value.detach()
        if self.variance_target_kind == "td":
            target = (targets["cost_target"] - cost_value).pow(2) + targets["cost_next_variance"]
        else:
            target = targets["cost_second_moment"] - cost_value.pow(2)
        if self.variance_loss == "w2":
            return target.clamp(VARIANCE_MIN, VARIANCE_MAX)
        return target.clamp(-VARIANCE_MAX, VARIANCE_MAX)

    def loss(self, values: SafetyValues, targets: dict[str, Tensor]) -> dict[str, Tensor]:
        """Per row: ``loss_cost_value`` (Eq. 7) and, with a variance network,
        ``loss_cost_variance`` (Eq. 8 with ``variance_loss``)."""
        out = {"loss_cost_value": 0.5 * (targets["cost_target"] - values.mean).pow(2)}
        if values.variance is not None:
            target = self.variance_target(targets, values.mean)
            out["loss_cost_variance"] = variance_regression_loss(
                values.variance, target, self.variance_loss
            )
        return out

    def cvar(self, values: SafetyValues) -> Tensor:
        """Γ(s, a, α) = Q^c + α⁻¹ φ(Φ⁻¹(α)) √V^c (Eq. 9), Q^c at least 0 with
        ``nonnegative_cost``."""
        if values.mean is None:
            raise TypeError(
                "the Gaussian critic's Γ is cvar(cost_value, cost_variance); "
                "quantile_cvar(tail_quantiles) is an IQN critic's"
            )
        mean = values.mean.clamp(min=0.0) if self.nonnegative_cost else values.mean
        if self.cvar_multiplier == 0.0 or values.variance is None:
            return mean
        return mean + self.cvar_multiplier * values.variance.sqrt()

    def mixture_cvar(self, values: SafetyValues, weights: Tensor | None = None) -> Tensor:
        """The CVaR_α of the Gaussians of every row mixed with equal weights (0-dim;
        :func:`~wcsac_rl.objectives.risk.gaussian_mixture_cvar`; ``weights``: per row,
        0 for a row that does not count)."""
        mean = values.mean.clamp(min=0.0) if self.nonnegative_cost else values.mean
        return gaussian_mixture_cvar(mean, values.variance, self.risk_level, weights=weights)

    def estimates(self, tensordict: TensorDictBase, params: TensorDictBase) -> dict[str, Tensor]:
        """``cost_value`` (Q^c), ``cvar`` (Γ) and, with a variance network,
        ``cost_variance`` (V^c) at the state-actions of ``tensordict``."""
        values = self.values(tensordict, params)
        out = {"cost_value": values.mean, "cvar": self.cvar(values)}
        if values.variance is not None:
            out["cost_variance"] = values.variance
        return out


# ------------------------------------------- the IQN head's fractions and TD loss
def stratified_fractions(
    count: int,
    low: float = 0.0,
    high: float = 1.0,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """``count`` fractions in ``[low, high]``, one uniform draw in each of ``count`` equal strata.

    Each τ_k is uniform on its stratum, so an average over them is an unbiased
    estimate of the average over ``τ ~ U[low, high]`` (as with ``count`` independent
    draws) with the variance of stratified sampling: a step in the quantile function
    (a rare large cost) moves the estimate by at most one stratum's share. Sorted
    ascending. Uses torch's global generator.

    >>> tau = stratified_fractions(4, 0.9, 1.0)
    >>> bool(((tau - 0.9) * 40).floor().eq(torch.arange(4.0)).all())  # one per stratum
    True
    """
    offsets = torch.arange(count, device=device, dtype=dtype)
    offsets = offsets + torch.rand(count, device=device, dtype=dtype)
    return low + (high - low) * offsets / count


def midpoint_fractions(
    count: int,
    low: float = 0.0,
    high: float = 1.0,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """The midpoints of ``count`` equal strata of ``[low, high]`` (deterministic fractions).

    >>> midpoint_fractions(4).tolist()
    [0.125, 0.375, 0.625, 0.875]
    """
    offsets = torch.arange(count, device=device, dtype=dtype) + 0.5
    return low + (high - low) * offsets / count


def quantile_huber_loss(
    quantiles: Tensor, fractions: Tensor, targets: Tensor, kappa: float = 1.0
) -> Tensor:
    r"""IQN's quantile Huber loss, per batch row.

    ``Σ_i (1/N') Σ_j |τ_i − 1{δ_ij < 0}| · L_κ(δ_ij) / κ`` with ``δ_ij = y_j − Z_i``,
    ``L_κ`` the Huber loss (``½δ²`` for ``|δ| ≤ κ``, ``κ(|δ| − ½κ)`` beyond), summed
    over the ``N`` predicted quantiles and averaged over the ``N'`` target samples
    (Dabney et al. 2018, Eq. 4). As ``κ → 0`` it becomes the plain quantile
    (pinball) loss.

    Args:
        quantiles: ``Z_i = Z(s, a, τ_i)``, ``[*B, N]``.
        fractions: their τ_i, ``[N]`` (shared by the batch) or ``[*B, N]``.
        targets: target samples ``y_j``, ``[*B, N']`` (no gradient is taken through them).
        kappa: the Huber threshold κ_H > 0.

    Returns:
        ``[*B]``.

    >>> q = torch.tensor([[0.0, 0.0]]); tau = torch.tensor([0.25, 0.75])
    >>> quantile_huber_loss(q, tau, torch.tensor([[2.0]]))  # δ = 2 > κ: τ_i (2 − ½), summed
    tensor([1.5000])
    """
    predicted = quantiles.unsqueeze(-1)  # [*B, N, 1]
    target = targets.detach().unsqueeze(-2)  # [*B, 1, N']
    # L_κ(δ_ij) in one kernel (and one backward) over [*B, N, N']: the same values and
    # gradients, to the bit, as ½δ² / κ(|δ| − ½κ) written out, at a third less time
    huber = F.huber_loss(*torch.broadcast_tensors(predicted, target), reduction="none", delta=kappa)
    # |τ_i − 1{δ_ij < 0}|: 1 − τ_i where the target is below the quantile, else τ_i
    tau = fractions.unsqueeze(-1)
    weight = torch.where(target < predicted.detach(), 1.0 - tau, tau)
    return (weight * huber).mean(-1).sum(-1) / kappa


class IQNHead(SafetyHead):
    """An implicit quantile network: the τ-quantiles ``Z(s, a, τ)`` of the cost return.

    The network reads state, action and fractions τ ``[*B, N]`` (at
    ``keys.quantile_fractions``; the head writes them) and writes the quantiles
    ``[*B, N]`` at ``keys.cost_quantiles`` (or its single out key).

    * each evaluation draws ``num_quantiles`` fractions over [0, 1], one per equal
      stratum and shared by the rows (:func:`stratified_fractions`),
      and as many over ``[1 − α, 1]`` for Γ; the targets ``num_target_quantiles``;
    * TD loss: ``Σ_i (1/N') Σ_j ρ^κ_{τ_i}(y_j − Z(s, a, τ_i))`` with
      ``y_j = c + γ_c(1−term) Z̄(s', a', τ'_j)`` and κ_H = ``huber_kappa``
      (:func:`quantile_huber_loss`), reported as
      ``loss_cost_quantile``;
    * Γ = the mean of its quantiles over ``[1 − α, 1]``; the mixture's CVaR is that of
      the quantiles of every row pooled
      (:func:`~wcsac_rl.objectives.risk.quantile_mixture_cvar`).

    Example:
        >>> import torch
        >>> from wcsac_rl.modules import make_safety_critic
        >>> from wcsac_rl.objectives import WCSACLoss
        >>> head = IQNHead(make_safety_critic(3, 1, kind="iqn"), WCSACLoss.default_keys(),
        ...                risk_level=0.5, nonnegative_cost=False)
        >>> head.cvar(SafetyValues(tail=torch.tensor([[1.0, 2.0, 6.0]])))  # the tail's mean
        tensor([3.])
    """

    kind = "iqn"
    loss_names = ("loss_cost_quantile",)
    diagnostic_names = ("cost_value", "cost_variance")  # of the quantiles

    def __init__(
        self,
        network: TensorDictModule,
        keys,
        *,
        risk_level: float,
        nonnegative_cost: bool,
        num_quantiles: int = IQNOptions.num_quantiles,
        num_target_quantiles: int = IQNOptions.num_target_quantiles,
        huber_kappa: float = IQNOptions.huber_kappa,
    ) -> None:
        super().__init__(network, keys, risk_level=risk_level, nonnegative_cost=nonnegative_cost)
        self.num_quantiles = int(num_quantiles)
        self.num_target_quantiles = int(num_target_quantiles)
        self.huber_kappa = float(huber_kappa)
        in_keys, out_keys = list(network.in_keys), list(network.out_keys)
        if keys.quantile_fractions not in in_keys:
            # an IQNSafetyCritic reads (observation, action, fractions) in that order
            keys.quantile_fractions = in_keys[-1]
        if keys.cost_quantiles not in out_keys:
            if len(out_keys) != 1:
                raise ValueError(
                    f"cannot tell which of the IQN safety critic's out_keys {out_keys} holds "
                    "the quantiles; call set_keys(cost_quantiles=...)"
                )
            keys.cost_quantiles = out_keys[0]
        # a parameter (or buffer): the fractions are drawn on its device and dtype
        leaves = list(TensorDict.from_module(network).keys(True, True))
        if not leaves:
            raise ValueError("the IQN safety critic has no parameters to learn its quantiles with")
        self._like_key = leaves[0]
        # the kit's IQNSafetyCritic is read from its parameters (the same values, no
        # module call) when it reads (observation, action, fractions) in that order
        self._reader = (
            IQNReader.of(network.module, ("module",))
            if len(in_keys) == 3
            and in_keys[2] == keys.quantile_fractions
            and keys.cost_quantiles in out_keys
            and len(out_keys) == 1
            else None
        )

    @property
    def in_keys(self) -> list:
        return [k for k in self.network.in_keys if k != self.keys.quantile_fractions]

    def read_through_module(self) -> None:
        self._reader = None

    def unfused_reason(self) -> str:
        return (
            "an IQN safety critic is not fused with the reward critics (it also reads "
            "quantile fractions)"
        )

    def fractions(self, count: int, like: Tensor, tail: bool = False, stratified: bool = True):
        """``count`` fractions over [0, 1] (``tail``: over [1 − α, 1]), one per stratum,
        drawn (``stratified``) or at the strata's midpoints, on ``like``'s device and dtype."""
        draw = stratified_fractions if stratified else midpoint_fractions
        low = 1.0 - self.risk_level if tail else 0.0
        return draw(count, low, 1.0, device=like.device, dtype=like.dtype)

    def quantiles(
        self, tensordict: TensorDictBase, params: TensorDictBase, fractions: Tensor
    ) -> Tensor:
        """The quantiles ``[*B, N]`` at the state-action in ``tensordict`` and the
        fractions ``[N]`` (given expanded over the batch: one embedding of τ serves
        every row)."""
        expanded = fractions.expand(*tensordict.batch_size, fractions.shape[-1])
        if self._reader is not None:
            observation, action = (tensordict.get(key) for key in self.network.in_keys[:2])
            return self._reader.quantiles(params, observation, action, expanded)
        td = tensordict.select(*self.in_keys, strict=False)
        td.set(self.keys.quantile_fractions, expanded)
        with params.to_module(self.network, preserve_module_state=False):
            td = self.network(td)
        return td.get(self.keys.cost_quantiles)

    def values(
        self,
        tensordict: TensorDictBase,
        params: TensorDictBase,
        action: Tensor | None = None,
        *,
        target: bool = False,
        stratified: bool = True,
    ) -> SafetyValues:
        """The quantiles over [0, 1] (``num_target_quantiles`` of them for the
        ``target``, else ``num_quantiles``), their mean and variance, and (not for the
        ``target``) the quantiles over [1 − α, 1], from one call of the network.
        ``stratified=False`` reads them at the strata's midpoints."""
        td = self._inputs(tensordict, action)
        like = params.get(self._like_key)
        count = self.num_target_quantiles if target else self.num_quantiles
        fractions = self.fractions(count, like, stratified=stratified)
        if target:
            quantiles, tail = self.quantiles(td, params, fractions), None
        else:
            tail_fractions = self.fractions(self.num_quantiles, like, True, stratified)
            both = torch.cat([fractions, tail_fractions])
            quantiles, tail = self.quantiles(td, params, both).split(
                [count, self.num_quantiles], dim=-1
            )
        mean = quantiles.mean(-1)
        variance = (quantiles - mean.unsqueeze(-1)).pow(2).mean(-1)
        return SafetyValues(mean, variance, quantiles, fractions, tail)

    def skip_reading(
        self, params: TensorDictBase, *, target: bool = False, stratified: bool = True
    ) -> None:
        like = params.get(self._like_key)
        count = self.num_target_quantiles if target else self.num_quantiles
        self.fractions(count, like, stratified=stratified)
        if not target:
            self.fractions(self.num_quantiles, like, True, stratified)

    def targets(
        self, cost: Tensor, gamma: Tensor, alive: Tensor, ahead: SafetyValues
    ) -> dict[str, Tensor | None]:
        """``cost_target_quantiles`` ``[*B, N']``: ``c + γ_c·alive·Z̄(τ'_j)`` per target
        quantile of ``ahead``, and ``cost_target`` their mean."""
        quantiles = ahead.quantiles.clamp(min=0.0) if self.nonnegative_cost else ahead.quantiles
        discount = (gamma * alive).unsqueeze(-1)
        target_quantiles = cost.unsqueeze(-1) + discount * quantiles
        return {
            "cost_target": target_quantiles.mean(-1),
            "cost_target_quantiles": target_quantiles,
            "cost_second_moment": None,
            "cost_next_variance": None,
        }

    def loss(self, values: SafetyValues, targets: dict[str, Tensor]) -> dict[str, Tensor]:
        """Per row: ``loss_cost_quantile``, the quantile Huber TD loss."""
        loss = quantile_huber_loss(
            values.quantiles, values.fractions, targets["cost_target_quantiles"], self.huber_kappa
        )
        return {"loss_cost_quantile": loss}

    def cvar(self, values: SafetyValues) -> Tensor:
        """Γ(s, a, α): the mean of the quantiles ``values.tail`` over [1 − α, 1] (each
        at least 0 with ``nonnegative_cost``)."""
        if values.tail is None:
            raise TypeError(
                "an IQN critic's Γ is the mean of its tail quantiles: "
                "quantile_cvar(tail_quantiles) (or safety_estimates()['cvar']); "
                "cvar(cost_value, cost_variance) is the Gaussian critic's"
            )
        tail = values.tail.clamp(min=0.0) if self.nonnegative_cost else values.tail
        return tail.mean(-1)

    def mixture_cvar(self, values: SafetyValues, weights: Tensor | None = None) -> Tensor:
        """The CVaR_α of the quantiles of every row pooled (0-dim; ``weights``: per row,
        0 for a row that does not count)."""
        quantiles = values.quantiles
        if self.nonnegative_cost:
            quantiles = quantiles.clamp(min=0.0)
        return quantile_mixture_cvar(quantiles, self.risk_level, weights=weights)

    def estimates(self, tensordict: TensorDictBase, params: TensorDictBase) -> dict[str, Tensor]:
        """At deterministic fractions, the midpoints of ``num_quantiles`` equal strata:
        ``cost_quantiles`` ``[*B, N]`` over [0, 1], ``cost_value`` and ``cost_variance``
        their mean and variance, and ``cvar`` the mean of the quantiles at the midpoints
        of [1 − α, 1]."""
        values = self.values(tensordict, params, stratified=False)
        return {
            "cost_value": values.mean,
            "cost_variance": values.variance,
            "cvar": self.cvar(values),
            "cost_quantiles": values.quantiles,
        }


def is_iqn_critic(network: Any, quantile_fractions: Any = "quantile_fractions") -> bool:
    """Whether ``network`` (a safety critic module) is an implicit quantile network: the
    kit's :class:`~wcsac_rl.modules.IQNSafetyCritic`, or any module reading the quantile
    fractions τ (``quantile_fractions``, the loss's key)."""
    return isinstance(getattr(network, "module", None), IQNSafetyCritic) or (
        quantile_fractions in list(getattr(network, "in_keys", ()))
    )


def _make_member_head(network, keys, *, risk_level, options) -> GaussianHead | IQNHead:
    """The head of one critic of ``network``'s kind, as ``options`` (a checked
    ``SafetyHeadOptions``) say; the Gaussian head's variance options are refused for an
    IQN critic unless left at their defaults."""
    common = {"risk_level": risk_level, "nonnegative_cost": options.nonnegative_cost}
    variance_loss, variance_target = options.variance_loss, options.variance_target
    if not is_iqn_critic(network, keys.quantile_fractions):
        return GaussianHead(
            network, keys, variance_loss=variance_loss, variance_target=variance_target, **common
        )
    defaults = (SafetyOptions.variance_loss, SafetyOptions.variance_target)
    if (variance_loss, variance_target) != defaults:
        raise ValueError(
            f"variance_loss={variance_loss!r} and variance_target={variance_target!r} "
            "configure the Gaussian critic's variance head; an IQN safety critic has "
            "none (it learns quantiles with the quantile Huber loss): leave them at "
            f"their defaults {defaults}"
        )
    return IQNHead(
        network,
        keys,
        num_quantiles=options.num_quantiles,
        num_target_quantiles=options.num_target_quantiles,
        huber_kappa=options.huber_kappa,
        **common,
    )
