"""Worst-Case Soft Actor Critic (Yang et al., AAAI 2021) as a TorchRL ``LossModule``.

``WCSACLoss`` is TorchRL's :class:`~torchrl.objectives.SACLoss` (v2: twin Q, no value
network) plus

* a Gaussian safety critic ``C(s, a) ~ N(Q^c, V^c)`` (mean and variance networks),
  trained with a TD loss on the mean (Eq. 7) and a TD loss on the variance (Eq. 8:
  the paper's 2-Wasserstein loss, ``variance_loss="w2"``, or the regression losses
  ``"glm"``, the default, and ``"mse"``), each with its own target network updated
  by ``SoftUpdate``;
* the CVaR of the cost, ``Γ(s, a, α) = Q^c + α⁻¹ φ(Φ⁻¹(α)) √V^c`` (Eq. 9);
* a CVaR-penalised actor loss ``β log π − min Q^r + κ Γ``;
* a Lagrange multiplier ``κ`` trained to keep ``Γ`` under the threshold (the paper:
  Γ over replay states under a per-step threshold; by default the CVaR of the
  critic at episode start states under the episodic limit ``d``, see
  ``kappa_states``).

``SACLagLoss`` is the same loss at ``α = 1`` with a mean-only safety critic.

Beyond the paper, the safety critic may be an implicit quantile network (the
journal version of WCSAC): quantile-Huber TD loss instead of the mean and variance
losses, ``Γ`` = the mean of its quantiles over ``τ ∈ [1 − α, 1]``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, NamedTuple

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import SACLoss
from torchrl.objectives.sac import compute_rsample_log_prob
from torchrl.objectives.utils import (
    ValueEstimators,
    _cache_values,
    default_value_kwargs,
    distance_loss,
)

from wcsac_rl.modules.quantile_critic import IQNSafetyCritic
from wcsac_rl.modules.safety_critic import (
    VARIANCE_MAX,
    VARIANCE_MIN,
)
from wcsac_rl.modules.tanh_normal import sample_tanh_normal, tanh_normal_actor_plan
from wcsac_rl.objectives.budget import (
    per_step_cost_threshold,
    validate_cost_limit,
    validate_max_episode_steps,
)
from wcsac_rl.objectives.constraint import (
    PIDGains,
    make_constraint,
)
from wcsac_rl.objectives.critic_ensemble import FusedCritics, Layers
from wcsac_rl.objectives.inputs import check_finite_entries, check_nonempty_batch, finite_number
from wcsac_rl.objectives.quantile import (
    midpoint_fractions,
    quantile_huber_loss,
    stratified_fractions,
)
from wcsac_rl.objectives.risk import (
    gaussian_cvar_multiplier,
    gaussian_mixture_cvar,
    quantile_mixture_cvar,
    validate_risk_level,
)
from wcsac_rl.objectives.variance import VARIANCE_LOSSES, variance_regression_loss

__all__ = ["PAPER_OPTIONS", "CriticValues", "SACLagLoss", "WCSACLoss", "per_step_cost_threshold"]

KAPPA_ACTIONS = ("replay", "policy")
KAPPA_STATES = ("replay", "initial")
KAPPA_STATISTICS = ("mean", "tail")
KAPPA_SIGNALS = ("critic", "max", "episodes")
VARIANCE_TARGETS = ("moment", "td")

PAPER_OPTIONS: Mapping[str, Any] = MappingProxyType(
    {
        "variance_target": "moment",
        "cost_gamma": None,
        "cost_n_steps": 1,
        "nonnegative_cost": False,
        "kappa_states": "replay",
        "kappa_statistic": "mean",
        "kappa_signal": "critic",
        "kappa_rule": "gradient",
    }
)
"""The safety critic and κ as the paper writes them (Eq. 7–8, one-step targets with the
reward's γ, κ on the mean Γ over replay states against the per-step threshold):
``WCSACLoss(..., **PAPER_OPTIONS)``. The defaults differ, on StaticEnv evidence (README,
"Defaults chosen on evidence"); ``algo=wcsac_paper`` is the same in the config."""


def _nested(*keys: NestedKey) -> tuple[str, ...]:
    """One nested key from several (``_nested("nstep", ("a", "b")) == ("nstep", "a", "b")``)."""
    return tuple(part for key in keys for part in ((key,) if isinstance(key, str) else key))


class CriticParams(NamedTuple):
    """The reward critics' and the safety critic's parameters for one evaluation;
    ``target`` marks the target networks (an IQN critic then draws N' fractions)."""

    qvalue: TensorDictBase
    safety: TensorDictBase
    target: bool = False


class CriticValues(NamedTuple):
    """Every critic at one batch of state-actions, squeezed to the batch shape.

    ``qvalue`` is ``[num_qvalue_nets, *B]``; ``cost_variance`` is ``None`` for a
    mean-only safety critic. For an IQN safety critic, ``cost_quantiles`` ``[*B, N]``
    are its quantiles at ``quantile_fractions`` ``[N]`` (one stratified draw over
    [0, 1], shared by the batch), ``cost_value`` and ``cost_variance`` their mean and
    variance, and ``tail_quantiles`` ``[*B, N]`` the quantiles at a stratified draw
    over ``[1 − α, 1]`` (whose mean is Γ), or ``None`` where not needed.
    """

    qvalue: Tensor
    cost_value: Tensor
    cost_variance: Tensor | None
    cost_quantiles: Tensor | None = None
    quantile_fractions: Tensor | None = None
    tail_quantiles: Tensor | None = None

    def detach(self) -> CriticValues:
        """The same values without gradient."""
        return CriticValues(*(None if v is None else v.detach() for v in self))


class WCSACLoss(SACLoss):
    r"""The WCSAC loss: SAC with a Gaussian safety critic and a CVaR constraint.

    ``benchmarks/plain_wcsac.py`` is the plain-PyTorch reference of the paper's update
    (this loss with ``**PAPER_OPTIONS, variance_loss="mse"``), tested equal to it in
    ``tests/test_plain_reference.py``.

    Args:
        actor_network (ProbabilisticTensorDictSequential): the stochastic (tanh-Normal) actor.
        qvalue_network (TensorDictModule or list of them): the reward critic ``Q^r(s, a)``
            writing ``"state_action_value"``; a list gives independently initialised twins
            (see :class:`~torchrl.objectives.SACLoss`).
        safety_network (TensorDictModule): the safety critic reading state and action
            and writing the cost mean ``Q^c`` and, for WCSAC, the cost variance
            ``V^c > 0`` (keys ``"cost_value"`` and ``"cost_variance"``; if its out_keys
            are named otherwise, the first is taken as the mean and the second as the
            variance). A mean-only critic (one out key) is allowed at ``risk_level=1``.
            Or an implicit quantile network (``make_safety_critic(..., kind="iqn")``,
            detected by its :class:`~wcsac_rl.modules.IQNSafetyCritic` or by its
            reading the ``quantile_fractions`` key): it reads state, action and
            quantile fractions τ ``[*B, N]`` and writes the τ-quantiles of the cost
            return ``[*B, N]`` (``"cost_quantiles"``, or its single out key); the
            loss draws τ. See :func:`wcsac_rl.modules.make_safety_critic`.

    Keyword Args:
        risk_level (float): the paper's α ∈ (0, 1], the tail fraction whose mean cost
            (CVaR_α) is constrained. 0.1 is risk-averse, 1 is the expected cost (SAC-Lag).
            Default ``0.5``.
        cost_limit (float): the episodic cost budget ``d`` (undiscounted sum over an
            episode). Default ``15.0``.
        max_episode_steps (int): episode length ``T`` used to convert ``d`` into the
            per-step threshold ``d·(1−γ^T)/((1−γ)T)`` for the discounted critic
            (γ from the value estimator). Default ``1000``.
        cost_threshold (float, optional): give the threshold Γ is held under directly;
            when set, ``cost_limit`` and ``max_episode_steps`` are not used. By default
            it is the per-step threshold ``d·(1−γ_c^T)/((1−γ_c)T)`` when κ sees replay
            states, and ``d`` itself when κ sees initial states (``kappa_states``).
        cost_gamma (float, optional): discount γ_c of the safety critic. ``None``
            uses the value estimator's γ, as the paper does. Default ``1.0``: the
            critic's value at a start state is then the expected episode cost itself,
            which the limit ``d`` is about (with γ_c = γ = 0.99 a cost met 60 steps
            into an episode counts 0.55 times). With γ_c = 1 the safety critic's sum
            stops where the episode stops, time limits included
            (``cost_bootstrap_truncated``).
        cost_bootstrap_truncated (bool, optional): whether the safety critic's target
            bootstraps across a time-limit truncation (``done`` but not
            ``terminated``), as the reward critic's does. ``None`` (default): only when
            γ_c < 1. Undiscounted, bootstrapping across the time limit makes Q^c the
            cost of an endless episode, which grows without bound on a task whose
            episodes end only by the time limit; stopping there makes it the cost
            until the episode's end (for a critic that does not see the time, an
            average over the times the state is met).
        cost_n_steps (int): ``1`` (the paper): one-step safety-critic
            targets. ``n > 1`` (default ``10``): the safety critic bootstraps from the n-step entries
            :class:`~wcsac_rl.objectives.NStepCost` adds to collected data
            (``Σ_{k<m} γ_c^k c_{t+k} + γ_c^m (1−term) Q̄^c(s_{t+m}, a')``, m ≤ n), so
            sparse costs reach the states that lead to them n times faster. The
            reward critic keeps its one-step target.
        nonnegative_cost (bool): costs are never negative, so neither is their value:
            use ``max(Q^c, 0)`` wherever Q^c is *used* (the bootstrapped targets and Γ
            in the actor and κ losses; the regression itself is unchanged). Stops the
            actor from steering into actions where the safety critic extrapolates
            below zero, and those values from spreading through the targets.
            Default ``True`` (the paper: ``False``).
        kappa_init (float): initial safety weight κ > 0. Default ``softplus(0) ≈ 0.693``
            (the authors' code).
        kappa_parametrization (str): ``"softplus"`` (κ = softplus(raw), the authors'
            code) or ``"log"`` (κ = exp(raw)). Default ``"softplus"``.
        kappa_states (str): the states at which the κ loss evaluates Γ: ``"replay"``
            (the sampled batch, as the paper and the authors' code) or ``"initial"``
            (episode start states, read from the sub-tensordict at the
            ``initial_states`` key, one start state per batch row, with ``a ~ π``):
            Γ(s₀, a₀) estimates the CVaR of the episode's discounted cost, so it is
            held under the episodic limit ``d`` itself. Default ``"initial"``: the
            batch must then carry start states
            (:class:`~wcsac_rl.objectives.StartStateBuffer` provides them).
        kappa_statistic (str): what of the critic at those states the κ loss holds
            under the threshold. ``"mean"`` (the paper): the mean of the per-state
            Γ(s, a, α). ``"tail"``: the CVaR_α of the critic's cost distribution
            *mixed over the states* (:func:`~wcsac_rl.objectives.risk.gaussian_mixture_cvar`)
            — at initial states, the CVaR_α of an episode's discounted cost when the
            start state is random too, which is what the worst-α share of test
            episodes measures; the mean of per-state CVaRs is never larger and
            misses a tail made of a few risky start states. Equal at α = 1.
            Default ``"tail"``.
        kappa_signal (str): what the κ loss (and the damping term) holds under the
            threshold. ``"critic"`` (the paper): the critic's Γ as set by
            ``kappa_states`` / ``kappa_statistic`` / ``kappa_actions``. ``"max"``: the
            larger of that and what recent finished episodes cost, read from the batch
            at the ``episode_cvar`` key (:class:`~wcsac_rl.objectives.EpisodeCostWindow`
            provides it: their empirical CVaR_α, or their mean cost, a lower bound of
            every CVaR_α), so κ rises as soon as
            the collected episodes exceed the limit even while the critic's
            start-state value still lags the policy. ``"episodes"``: that episode
            statistic alone (OmniSafe's SAC-Lag at α = 1). Where no episode has
            finished yet (NaN) both fall back to the critic. Needs
            ``kappa_states="initial"`` (the threshold is then the episodic ``d`` the
            costs are measured against). Default ``"critic"``. The actor's cost term is
            always the critic's Γ.
        kappa_actions (str): the actions at which the κ loss evaluates Γ: ``"replay"``
            (the stored actions, the authors' code) or ``"policy"`` (``a ~ π``, as the
            paper writes). Default ``"policy"`` (see README for the evidence).
        damp_scale (float): MDMM damping in the actor's penalty,
            ``(κ − damp_scale · mean(threshold − Γ)) · Γ_π``. Default ``0`` (none).
            Gradient rule only.
        kappa_rule (str): how κ moves (:mod:`wcsac_rl.objectives.constraint`, held by
            the loss as :attr:`constraint`): ``"gradient"`` (the paper: κ is trained
            on ``loss_kappa``) or ``"pid"`` (a PID Lagrangian, Stooke et al. 2020: κ
            is set from the error ``signal − threshold``; no ``loss_kappa``). Like
            batch norm's running statistics, the controller steps in :meth:`forward`
            while the loss is in training mode (``loss.train()``, the default), once
            per call, with that batch's signal and after the actor loss has used the
            current κ; ``loss.eval()`` freezes it. Default ``"gradient"``.
        pid (PIDGains or dict, optional): the PID rule's gains
            (:class:`~wcsac_rl.objectives.constraint.PIDGains`: ``kp``, ``ki``, ``kd``,
            ``d_delay``, ``p_ema``, ``d_ema``, ``max_kappa``); ``kappa_rule="pid"`` only.
            ``None``: ``PIDGains()`` (``kp=0.05``, ``ki=1e-6``, ``p_ema=0.99``, no
            derivative term).
        num_quantiles (int): IQN critic only: ``N``, the fractions τ drawn per
            evaluation of the online critic (quantile loss, Γ, diagnostics), one per
            equal stratum of [0, 1] (of [1 − α, 1] for Γ) and shared by the batch
            rows. Default ``20`` (the journal version).
        num_target_quantiles (int): IQN critic only: ``N'``, the target fractions τ'
            per update. Default ``20``.
        huber_kappa (float): IQN critic only: the threshold κ_H > 0 of the quantile
            Huber loss. Default ``1.0`` (IQN).
        variance_loss (str): ``"w2"`` — the paper's 2-Wasserstein variance loss
            ``V + y − 2√(V y)``; ``"mse"`` — ``½ (V − y)²``, a consistent estimator of
            the variance when the TD target ``y`` is noisy (W2 on sampled targets
            converges to ``(E√y)²`` instead of ``E y``); ``"glm"`` — the MSE's fixed
            point with the gradient ``V − y`` on the head's pre-softplus output, so
            small variances are not silenced by ``softplus' ≈ V``
            (:mod:`wcsac_rl.objectives.variance`). Default ``"glm"`` (see README).
        variance_target (str): ``"moment"`` — Eq. 8,
            ``c² + γ_c(1−term)(2c Q̄' + γ_c(V̄' + Q̄'²)) − Q²``, the second moment minus the
            squared mean; ``"td"`` — ``(c + γ_c(1−term) Q̄' − Q)² + γ_c²(1−term) V̄'``,
            the squared TD error plus the discounted next variance. Both have the same
            expectation when Q is the mean of its target, but ``"td"`` is never
            negative (the moment form is negative wherever ``Q > γ_c Q̄'``, which
            drives the variance head to its floor when costs are rare). Default
            ``"td"``. ``variance_loss`` and ``variance_target`` configure the
            Gaussian critic's variance head: with an IQN critic any other value than
            their defaults is a ``ValueError``.
        fuse_critics (bool, optional): evaluate the reward and safety critics as one
            batched ensemble (one matrix product per layer for all four networks).
            Needs plain MLP critics of one shape reading ``[observation, action]``, as
            :mod:`wcsac_rl.modules` builds them; ``None`` (default) fuses when
            possible, ``False`` calls the modules one by one. Same values and
            gradients either way. An IQN safety critic is never fused (``True`` is
            a ``ValueError``).
        direct_sampling (bool, optional): draw the actor's reparametrised actions
            straight from its parameters instead of building TorchRL's
            ``TanhNormal`` each time. Needs an actor built like
            :func:`wcsac_rl.modules.make_actor`; ``None`` (default) does it when
            possible, ``False`` never. Same draws, log-probabilities and gradients
            either way.
        check_finite (bool): run :meth:`check_inputs` on every call: a NaN or ±inf in
            an entry the loss reads is a ``ValueError`` naming it instead of NaN losses
            (one host synchronisation per entry: not under ``torch.compile``). Default
            ``False``; an empty batch is refused either way.
        num_qvalue_nets, loss_function, alpha_init, min_alpha, max_alpha, action_spec,
        fixed_alpha, target_entropy, delay_actor, delay_qvalue, separate_losses,
        reduction, skip_done_states, deactivate_vmap, scalar_output_mode: as in
        :class:`~torchrl.objectives.SACLoss`. ``loss_function`` defaults to ``"l2"``
        (the paper's squared TD error) instead of TorchRL's ``"smooth_l1"``.

    The discount γ comes from the value estimator, as for every TorchRL loss:
    ``loss.make_value_estimator(gamma=0.99)`` (TD(0) only: the cost-variance target
    is a one-step recursion). The default is 0.99, the paper's value.

    ``forward`` returns ``loss_actor``, ``loss_qvalue``, ``loss_alpha``,
    ``loss_cost_value``, ``loss_cost_variance`` (only with a variance head) and
    ``loss_kappa``, plus the detached diagnostics ``alpha`` (entropy weight β),
    ``kappa``, ``entropy``, ``cost_value`` (mean Q^c), ``cost_variance`` (mean V^c),
    ``cvar`` (what the κ loss holds under the threshold, see ``kappa_statistic``) and
    ``cost_threshold``. Each loss term sends gradients only to its own parameters, so
    their sum can be back-propagated at once.

    With an IQN safety critic ``loss_cost_quantile`` (the quantile Huber TD loss)
    replaces ``loss_cost_value`` and ``loss_cost_variance``: with ``N`` fractions τ_i
    over [0, 1] and ``N'`` fractions τ'_j, the targets are
    ``y_j = c + γ_c(1−term) Z̄(s', a', τ'_j)`` (``a' ~ π(s')``, target critic; the
    n-step form with ``cost_n_steps > 1``; ``max(Z̄, 0)`` with ``nonnegative_cost``)
    and the loss is ``Σ_i (1/N') Σ_j ρ^κ_{τ_i}(y_j − Z(s, a, τ_i))``. Γ is the mean
    of ``Z(s, a, τ)`` over ``N`` fractions in ``[1 − α, 1]`` (``max(Z, 0)`` with
    ``nonnegative_cost``); ``cost_value`` and ``cost_variance`` are the mean and
    variance of the quantiles over [0, 1], and ``kappa_statistic="tail"`` is the
    CVaR_α of the quantiles of all states pooled
    (:func:`~wcsac_rl.objectives.risk.quantile_mixture_cvar`).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl.objectives import SoftUpdate
        >>> from wcsac_rl import WCSACLoss
        >>> from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
        >>> from wcsac_rl.objectives import NStepCost, StartStateBuffer
        >>> actor = make_actor(4, Bounded(-1.0, 1.0, shape=(2,)))
        >>> loss = WCSACLoss(
        ...     actor, [make_qvalue(4, 2) for _ in range(2)], make_safety_critic(4, 2),
        ...     risk_level=0.1, cost_limit=15.0, max_episode_steps=1000)
        >>> updater = SoftUpdate(loss, tau=0.005)
        >>> traj = TensorDict({  # one env's first 8 steps, as a collector hands them over
        ...     "observation": torch.randn(1, 8, 4), "action": torch.rand(1, 8, 2) * 2 - 1,
        ...     "step_count": torch.arange(8).reshape(1, 8, 1),
        ...     "next": {"observation": torch.randn(1, 8, 4), "reward": torch.randn(1, 8, 1),
        ...              "cost": torch.bernoulli(torch.full((1, 8, 1), 0.1)),
        ...              "done": torch.zeros(1, 8, 1, dtype=torch.bool),
        ...              "terminated": torch.zeros(1, 8, 1, dtype=torch.bool)}}, [1, 8])
        >>> traj = NStepCost(loss.cost_n_steps, loss.cost_gamma)(traj)  # n-step cost targets
        >>> starts = StartStateBuffer.for_loss(loss)  # κ looks at episode start states
        >>> starts.add_starts(traj)
        1
        >>> out = loss(starts.attach(traj.reshape(-1)))
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_alpha', 'loss_cost_value', 'loss_cost_variance', 'loss_kappa', 'loss_qvalue']
    """

    @dataclass
    class _AcceptedKeys(SACLoss._AcceptedKeys):
        """Tensordict keys the loss reads; change them with ``.set_keys(name=key)``.

        Attributes:
            action (NestedKey): the action. Defaults to ``"action"``.
            state_action_value (NestedKey): output of the reward critic.
                Defaults to ``"state_action_value"``.
            log_prob (NestedKey): log-probability of the sampled action.
            priority (NestedKey): where the reward-critic TD error is written.
                Defaults to ``"td_error"``.
            reward (NestedKey): reward, read under ``"next"``. Defaults to ``"reward"``.
            done (NestedKey): done flag, read under ``"next"``. Defaults to ``"done"``.
            terminated (NestedKey): termination flag (no bootstrap), read under
                ``"next"``. Defaults to ``"terminated"``.
            cost (NestedKey): per-step cost, read under ``"next"``, shaped like the
                reward (``[*B, 1]``) or ``[*B]``. Defaults to ``"cost"``.
            cost_value (NestedKey): safety critic's cost mean Q^c. Defaults to
                ``"cost_value"``.
            cost_variance (NestedKey): safety critic's cost variance V^c. Defaults to
                ``"cost_variance"``.
            quantile_fractions (NestedKey): where an IQN safety critic reads its
                fractions τ (the loss writes them). Defaults to ``"quantile_fractions"``.
            cost_quantiles (NestedKey): the IQN safety critic's quantiles.
                Defaults to ``"cost_quantiles"``.
            initial_states (NestedKey): with ``kappa_states="initial"``, a
                sub-tensordict shaped like the batch holding episode start states (the
                actor's and critics' observation entries), where the κ loss evaluates
                Γ. Defaults to ``"initial"``.
            episode_cvar (NestedKey): with ``kappa_signal`` ``"max"`` or ``"episodes"``,
                the empirical CVaR_α of recent episode costs, ``[*B, 1]`` (NaN: none
                yet). Defaults to ``"episode_cvar"``.
            nstep (NestedKey): with ``cost_n_steps > 1``, the sub-tensordict written
                by :class:`~wcsac_rl.objectives.NStepCost` (discounted cost of the
                next ``m`` steps, ``m``, termination and the state after them).
                Defaults to ``"nstep"``.
        """

        cost: NestedKey = "cost"
        cost_value: NestedKey = "cost_value"
        cost_variance: NestedKey = "cost_variance"
        quantile_fractions: NestedKey = "quantile_fractions"
        cost_quantiles: NestedKey = "cost_quantiles"
        initial_states: NestedKey = "initial"
        episode_cvar: NestedKey = "episode_cvar"
        nstep: NestedKey = "nstep"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    SUPPORTED_VALUE_ESTIMATORS = (ValueEstimators.TD0,)

    safety_network: TensorDictModule
    safety_network_params: TensorDictParams
    target_safety_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        qvalue_network: TensorDictModule | list[TensorDictModule],
        safety_network: TensorDictModule,
        *,
        risk_level: float = 0.5,
        cost_limit: float = 15.0,
        max_episode_steps: int = 1000,
        cost_threshold: float | None = None,
        cost_gamma: float | None = 1.0,
        cost_bootstrap_truncated: bool | None = None,
        cost_n_steps: int = 10,
        nonnegative_cost: bool = True,
        kappa_statistic: str = "tail",
        kappa_init: float = math.log(2.0),
        kappa_parametrization: str = "softplus",
        kappa_actions: str = "policy",
        kappa_states: str = "initial",
        kappa_signal: str = "critic",
        damp_scale: float = 0.0,
        kappa_rule: str = "gradient",
        pid: PIDGains | Mapping[str, Any] | None = None,
        num_quantiles: int = 20,
        num_target_quantiles: int = 20,
        huber_kappa: float = 1.0,
        variance_loss: str = "glm",
        variance_target: str = "td",
        fuse_critics: bool | None = None,
        direct_sampling: bool | None = None,
        num_qvalue_nets: int = 2,
        loss_function: str = "l2",
        check_finite: bool = False,
        **sac_kwargs,
    ) -> None:
        if "value_network" in sac_kwargs and sac_kwargs["value_network"] is not None:
            raise ValueError("WCSACLoss is SAC v2: it takes no value_network")
        sac_kwargs.pop("value_network", None)
        self.risk_level = validate_risk_level(risk_level)
        self.cvar_multiplier = gaussian_cvar_multiplier(self.risk_level)
        validate_cost_limit(cost_limit)  # (NaN and inf too: one line naming it)
        if cost_threshold is not None:
            finite_number(cost_threshold, "cost_threshold", minimum=0.0)
        else:  # (what the threshold is made from, checked now whatever γ is later)
            validate_max_episode_steps(max_episode_steps)
        constraint = make_constraint(
            kappa_rule,
            kappa_init=kappa_init,
            parametrization=kappa_parametrization,
            damp_scale=damp_scale,
            pid=pid,
        )
        if kappa_actions not in KAPPA_ACTIONS:
            raise ValueError(f"kappa_actions must be one of {KAPPA_ACTIONS}, got {kappa_actions!r}")
        if kappa_states not in KAPPA_STATES:
            raise ValueError(f"kappa_states must be one of {KAPPA_STATES}, got {kappa_states!r}")
        if kappa_signal not in KAPPA_SIGNALS:
            raise ValueError(f"kappa_signal must be one of {KAPPA_SIGNALS}, got {kappa_signal!r}")
        if kappa_signal != "critic" and kappa_states != "initial":
            raise ValueError(
                f"kappa_signal={kappa_signal!r} compares episode costs with the episodic limit "
                "d, which is the threshold only with kappa_states='initial' (with 'replay' "
                "it is a per-step threshold)"
            )
        if variance_target not in VARIANCE_TARGETS:
            raise ValueError(
                f"variance_target must be one of {VARIANCE_TARGETS}, got {variance_target!r}"
            )
        if cost_gamma is not None and not 0.0 <= cost_gamma <= 1.0:
            raise ValueError(f"cost_gamma must be in [0, 1], got {cost_gamma}")
        if int(cost_n_steps) != cost_n_steps or cost_n_steps < 1:
            raise ValueError(f"cost_n_steps must be an integer >= 1, got {cost_n_steps}")
        self.cost_n_steps = int(cost_n_steps)
        self.check_finite = bool(check_finite)
        self.nonnegative_cost = bool(nonnegative_cost)
        if kappa_statistic not in KAPPA_STATISTICS:
            raise ValueError(
                f"kappa_statistic must be one of {KAPPA_STATISTICS}, got {kappa_statistic!r}"
            )
        self.kappa_statistic = kappa_statistic
        if variance_loss not in VARIANCE_LOSSES:
            raise ValueError(
                f"variance_loss must be one of {VARIANCE_LOSSES}, got {variance_loss!r}"
            )
        for name, count in (
            ("num_quantiles", num_quantiles),
            ("num_target_quantiles", num_target_quantiles),
        ):
            if int(count) != count or count < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {count}")
        if not huber_kappa > 0:
            raise ValueError(f"huber_kappa must be > 0 (the Huber threshold), got {huber_kappa}")
        self.num_quantiles = int(num_quantiles)
        self.num_target_quantiles = int(num_target_quantiles)
        self.huber_kappa = float(huber_kappa)
        self.cost_limit = float(cost_limit)
        self.max_episode_steps = int(max_episode_steps)
        self._explicit_cost_threshold = None if cost_threshold is None else float(cost_threshold)
        self.kappa_parametrization = kappa_parametrization
        self.kappa_actions = kappa_actions
        self.kappa_states = kappa_states
        self.kappa_signal = kappa_signal
        self.variance_loss = variance_loss
        self.variance_target_kind = variance_target
        self._explicit_cost_gamma = None if cost_gamma is None else float(cost_gamma)
        self._cost_bootstrap_truncated = (
            None if cost_bootstrap_truncated is None else bool(cost_bootstrap_truncated)
        )

        super().__init__(
            actor_network,
            qvalue_network,
            None,
            num_qvalue_nets=num_qvalue_nets,
            loss_function=loss_function,
            **sac_kwargs,
        )
        self.convert_to_functional(safety_network, "safety_network", create_target_params=True)
        self._quantile_critic = self._reads_quantile_fractions(safety_network)
        self._adopt_safety_keys(safety_network)
        if self._quantile_critic and (variance_loss, variance_target) != ("glm", "td"):
            raise ValueError(
                f"variance_loss={variance_loss!r} and variance_target={variance_target!r} "
                "configure the Gaussian critic's variance head; an IQN safety critic has "
                "none (it learns quantiles with the quantile Huber loss): leave them at "
                "their defaults ('glm', 'td')"
            )
        if self.cvar_multiplier != 0.0 and not self.has_variance and not self._quantile_critic:
            raise ValueError(
                f"risk_level={self.risk_level} needs a safety critic with a variance head "
                f"(out_keys {self.tensor_keys.cost_value!r} and {self.tensor_keys.cost_variance!r}); "
                f"this one writes only {list(safety_network.out_keys)}. A mean-only critic "
                "is SAC-Lagrangian: use risk_level=1 (or SACLagLoss)."
            )

        device = self.log_alpha.device
        self.constraint = constraint.to(device)
        self.register_load_state_dict_pre_hook(_rename_kappa_raw)
        self.register_buffer("cost_threshold", torch.zeros((), device=device))
        # derived from cost_gamma / the value estimator: not part of the state dict
        self.register_buffer("cost_discount", torch.zeros((), device=device), persistent=False)
        self.make_value_estimator(ValueEstimators.TD0)
        self._set_in_keys()
        self._fused = (
            FusedCritics.plan(
                self.qvalue_network,
                safety_network,
                action_key=self.tensor_keys.action,
                num_qvalue_nets=self.num_qvalue_nets,
                has_variance=self.has_variance,
            )
            if fuse_critics is not False
            else None
        )
        if fuse_critics and self._quantile_critic:
            raise ValueError(
                "fuse_critics=True: an IQN safety critic is not fused with the reward "
                "critics (it also reads quantile fractions); use fuse_critics=None, which "
                "evaluates it as a module and still fuses nothing else"
            )
        if fuse_critics and self._fused is None:
            raise ValueError(
                "fuse_critics=True needs the reward and safety critics to be MLPs of one "
                "shape (Linear/activation stacks) reading [observation, action], e.g. "
                "from wcsac_rl.modules; use fuse_critics=None to fall back automatically"
            )
        self._actor_plan = (
            tanh_normal_actor_plan(actor_network) if direct_sampling is not False else None
        )
        if direct_sampling and self._actor_plan is None:
            raise ValueError(
                "direct_sampling=True needs an actor built like wcsac_rl.modules.make_actor "
                "(an MLP with ClampedLogStdNormalParams and a TanhNormal); use "
                "direct_sampling=None to fall back automatically"
            )

    # ------------------------------------------------------------------ set-up
    def _reads_quantile_fractions(self, safety_network: TensorDictModule) -> bool:
        """Whether the safety critic is an implicit quantile network."""
        return isinstance(
            getattr(safety_network, "module", None), IQNSafetyCritic
        ) or self.tensor_keys.quantile_fractions in list(safety_network.in_keys)

    def _adopt_safety_keys(self, safety_network: TensorDictModule) -> None:
        if self._quantile_critic:
            self._adopt_quantile_keys(safety_network)
            return
        out_keys = list(safety_network.out_keys)
        defaults = (self.tensor_keys.cost_value, self.tensor_keys.cost_variance)
        if not any(k in out_keys for k in defaults):
            if len(out_keys) > 2:
                raise ValueError(
                    f"cannot tell the cost mean and variance apart among the safety "
                    f"critic's out_keys {out_keys}; call set_keys(cost_value=..., cost_variance=...)"
                )
            self.tensor_keys.cost_value = out_keys[0]
            if len(out_keys) == 2:
                self.tensor_keys.cost_variance = out_keys[1]
        if self.tensor_keys.cost_value not in out_keys:
            raise ValueError(
                f"the safety critic writes {out_keys} but the loss reads the cost mean "
                f"from {self.tensor_keys.cost_value!r}"
            )

    def _adopt_quantile_keys(self, safety_network: TensorDictModule) -> None:
        in_keys, out_keys = list(safety_network.in_keys), list(safety_network.out_keys)
        keys = self.tensor_keys
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

    @property
    def has_variance(self) -> bool:
        """Whether the safety critic has a variance head (WCSAC) or not (SAC-Lag, IQN)."""
        return self.tensor_keys.cost_variance in self.safety_network.out_keys

    @property
    def safety_critic_kind(self) -> str:
        """``"iqn"`` (implicit quantile network), ``"gaussian"`` (mean and variance
        heads) or ``"mean"`` (mean only, SAC-Lag)."""
        if self._quantile_critic:
            return "iqn"
        return "gaussian" if self.has_variance else "mean"

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        """Set γ (TD(0) only), and the per-step cost threshold that depends on it."""
        if value_type not in (None, ValueEstimators.TD0):
            raise NotImplementedError(
                f"WCSACLoss supports only the TD(0) value estimator (its cost-variance target "
                f"is a one-step recursion), got {value_type}"
            )
        super().make_value_estimator(value_type, **hyperparams)
        # γ as given (the estimator stores it in float32: 0.99 → 0.99000001, which
        # would move the per-step threshold by 1.4e-6)
        self._gamma = float(
            hyperparams.get("gamma", default_value_kwargs(ValueEstimators.TD0)["gamma"])
        )
        gamma = self.cost_gamma
        if self._explicit_cost_threshold is not None:
            threshold = self._explicit_cost_threshold
        elif self.kappa_states == "initial":
            threshold = self.cost_limit
        else:
            threshold = per_step_cost_threshold(self.cost_limit, gamma, self.max_episode_steps)
        if "cost_threshold" in self._buffers:
            self.cost_threshold.fill_(threshold)
            self.cost_discount.fill_(gamma)
        # a Python bool, fixed with γ_c, so compiled code does not branch on a tensor
        self._bootstrap_truncated = (
            gamma < 1.0
            if self._cost_bootstrap_truncated is None
            else self._cost_bootstrap_truncated
        )
        return self

    @property
    def cost_gamma(self) -> float:
        """The safety critic's discount γ_c (``cost_gamma``, else the value estimator's γ)."""
        if self._explicit_cost_gamma is not None:
            return self._explicit_cost_gamma
        return self._gamma

    @property
    def cost_bootstrap_truncated(self) -> bool:
        """Whether the safety critic's target bootstraps across a time-limit truncation
        (``cost_bootstrap_truncated``, else ``γ_c < 1``)."""
        return self._bootstrap_truncated

    def _set_in_keys(self):
        super()._set_in_keys()
        safety = self.__dict__.get("safety_network")
        if safety is not None:
            keys = set(self._in_keys)
            keys.add(("next", self.tensor_keys.cost))
            fractions = self.tensor_keys.quantile_fractions  # written by the loss
            inputs = [k for k in safety.in_keys if k != fractions]
            keys.update(inputs)
            keys.update(("next", k) for k in inputs if k != self.tensor_keys.action)
            if self.__dict__.get("cost_n_steps", 1) > 1:
                for key in ("cost", "steps", "terminated", "done", *self.initial_state_keys):
                    keys.add(_nested(self.tensor_keys.nstep, key))
            self._in_keys = list(keys)

    @property
    def out_keys(self):
        if self._out_keys is None:
            keys = ["loss_actor", "loss_qvalue", "loss_alpha"]
            quantile = self.__dict__.get("_quantile_critic", False)
            if quantile:
                keys.append("loss_cost_quantile")
            else:
                keys.append("loss_cost_value")
            if self.has_variance:
                keys.append("loss_cost_variance")
            constraint = self.__dict__.get("_modules", {}).get("constraint")
            if constraint is None or constraint.rule == "gradient":
                keys.append("loss_kappa")
            keys += ["alpha", "kappa", "entropy", "cost_value"]
            if self.has_variance or quantile:
                keys.append("cost_variance")
            keys += ["cvar", "cost_threshold"]
            if self.__dict__.get("kappa_signal", "critic") != "critic":
                keys += ["episode_cvar", "constraint_cvar"]
            self._out_keys = keys
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values

    # --------------------------------------------------------------- parameters
    @property
    def kappa(self) -> Tensor:
        """The current safety weight κ (detached)."""
        return self.constraint.kappa

    @property
    def kappa_rule(self) -> str:
        """How κ is updated: ``"gradient"`` (the paper) or ``"pid"`` (:attr:`constraint`)."""
        return self.constraint.rule

    @property
    def kappa_raw(self) -> torch.nn.Parameter:
        """The gradient rule's raw parameter (``constraint.kappa_raw``)."""
        if self.constraint.rule != "gradient":
            raise AttributeError(f"kappa_rule={self.constraint.rule!r} has no kappa_raw parameter")
        return self.constraint.kappa_raw

    @property
    def damp_scale(self) -> float:
        return getattr(self.constraint, "damp_scale", 0.0)

    @property
    @_cache_values
    def _cached_detached_safety_params(self):
        return self.safety_network_params.detach()

    # ----------------------------------------------------------------- pieces
    def _get_cost(self, tensordict: TensorDictBase) -> Tensor:
        key = ("next", self.tensor_keys.cost)
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
        return cost.to(self.cost_threshold.dtype)

    @staticmethod
    def _required_entry(tensordict: TensorDictBase, key: NestedKey, what: str, how: str):
        """``tensordict[key]``, or a ``KeyError`` saying what it is and how to provide it."""
        value = tensordict.get(key, None)
        if value is None:
            raise KeyError(f"{what} at {key!r} of the batch; the batch has none. {how}")
        return value

    def _get_nstep(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._required_entry(
            tensordict,
            self.tensor_keys.nstep,
            f"cost_n_steps={self.cost_n_steps} needs the n-step cost entries (cost, steps, "
            f"terminated and the state after them)",
            f"Add them to collected data with "
            f"wcsac_rl.objectives.NStepCost({self.cost_n_steps}, gamma=loss.cost_gamma).",
        )

    def _safety_forward(
        self, tensordict: TensorDictBase, params: TensorDictBase
    ) -> tuple[Tensor, Tensor | None]:
        """Q^c and V^c (squeezed to the batch shape) at the state-action in ``tensordict``."""
        td = tensordict.select(*self.safety_network.in_keys, strict=False)
        with params.to_module(self.safety_network, preserve_module_state=False):
            td = self.safety_network(td)
        mean = td.get(self.tensor_keys.cost_value).squeeze(-1)
        if not self.has_variance:
            return mean, None
        variance = td.get(self.tensor_keys.cost_variance).squeeze(-1)
        return mean, variance.clamp(VARIANCE_MIN, VARIANCE_MAX)

    def _quantile_forward(
        self, tensordict: TensorDictBase, params: TensorDictBase, fractions: Tensor
    ) -> Tensor:
        """The IQN critic's quantiles ``[*B, N]`` at the state-action in ``tensordict``
        and the fractions ``[N]`` (given to it expanded over the batch: one embedding
        of τ serves every row)."""
        key = self.tensor_keys.quantile_fractions
        inputs = [k for k in self.safety_network.in_keys if k != key]
        td = tensordict.select(*inputs, strict=False)
        td.set(key, fractions.expand(*td.batch_size, fractions.shape[-1]))
        with params.to_module(self.safety_network, preserve_module_state=False):
            td = self.safety_network(td)
        return td.get(self.tensor_keys.cost_quantiles)

    def _fractions(self, count: int, tail: bool = False, *, stratified: bool = True) -> Tensor:
        """``count`` fractions over [0, 1] (``tail``: over [1 − α, 1]), one per stratum,
        drawn (``stratified``) or at the strata's midpoints."""
        draw = stratified_fractions if stratified else midpoint_fractions
        low = 1.0 - self.risk_level if tail else 0.0
        device, dtype = self.cost_threshold.device, self.cost_threshold.dtype
        return draw(count, low, 1.0, device=device, dtype=dtype)

    def _quantile_values(
        self,
        tensordict: TensorDictBase,
        params: TensorDictBase,
        *,
        target: bool = False,
        stratified: bool = True,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None]:
        """The IQN critic at the state-action in ``tensordict``: the mean and variance of
        its quantiles over [0, 1], those quantiles, their fractions and (not for the
        ``target``) the quantiles over [1 − α, 1], from one call of the network."""
        count = self.num_target_quantiles if target else self.num_quantiles
        fractions = self._fractions(count, stratified=stratified)
        if target:
            quantiles, tail = self._quantile_forward(tensordict, params, fractions), None
        else:
            both = torch.cat(
                [fractions, self._fractions(self.num_quantiles, True, stratified=stratified)]
            )
            quantiles, tail = self._quantile_forward(tensordict, params, both).split(
                [count, self.num_quantiles], dim=-1
            )
        mean = quantiles.mean(-1)
        variance = (quantiles - mean.unsqueeze(-1)).pow(2).mean(-1)
        return mean, variance, quantiles, fractions, tail

    # The critics' parameters, by role: trainable (the critic losses), target (the TD
    # targets) and detached (the actor's and κ's view: gradients reach only the action).
    def _online_critics(self) -> CriticParams:
        return CriticParams(self.qvalue_network_params, self.safety_network_params)

    def _target_critics(self) -> CriticParams:
        return CriticParams(
            self.target_qvalue_network_params, self.target_safety_network_params, target=True
        )

    def _detached_critics(self) -> CriticParams:
        return CriticParams(
            self._cached_detached_qvalue_params, self._cached_detached_safety_params
        )

    def _fused_layers(self, critics: CriticParams) -> Layers | None:
        """The fused critics' stacked parameters (``None`` when not fused)."""
        if self._fused is None:
            return None
        return self._fused.layers(critics.qvalue, critics.safety)

    def _critic_values(
        self,
        tensordict: TensorDictBase,
        action: Tensor,
        critics: CriticParams,
        layers: Layers | None = None,
    ) -> CriticValues:
        """The reward and safety critics with parameters ``critics`` at
        ``(observation, action)``: one fused evaluation when possible (``layers``, if
        already gathered from ``critics``), else the modules one by one."""
        if self._fused is not None:
            observation = tensordict.get(self.qvalue_network.in_keys[0])
            layers = self._fused_layers(critics) if layers is None else layers
            return CriticValues(*self._fused.values(observation, action, layers))
        td_q = tensordict.select(*self.qvalue_network.in_keys, strict=False)
        td_q.set(self.tensor_keys.action, action)
        qvalue = self._vmap_qnetworkN0(td_q, critics.qvalue).get(
            self.tensor_keys.state_action_value
        )
        td_s = tensordict.select(*self.safety_network.in_keys, strict=False)
        td_s.set(self.tensor_keys.action, action)
        if self._quantile_critic:
            values = self._quantile_values(td_s, critics.safety, target=critics.target)
            return CriticValues(qvalue.squeeze(-1), *values)
        return CriticValues(qvalue.squeeze(-1), *self._safety_forward(td_s, critics.safety))

    def cvar(self, cost_value: Tensor, cost_variance: Tensor | None) -> Tensor:
        """Γ(s, a, α) = Q^c + α⁻¹ φ(Φ⁻¹(α)) √V^c (Eq. 9) of the Gaussian critic; Q^c at
        least 0 with ``nonnegative_cost``. (An IQN critic's Γ is :meth:`quantile_cvar`.)"""
        if self._quantile_critic:
            raise TypeError(
                "cvar(cost_value, cost_variance) is the Gaussian critic's Γ; an IQN "
                "critic's is quantile_cvar(tail_quantiles) (or safety_estimates()['cvar'])"
            )
        if self.nonnegative_cost:
            cost_value = cost_value.clamp(min=0.0)
        if self.cvar_multiplier == 0.0 or cost_variance is None:
            return cost_value
        return cost_value + self.cvar_multiplier * cost_variance.sqrt()

    def quantile_cvar(self, tail_quantiles: Tensor) -> Tensor:
        """Γ(s, a, α) of the IQN critic: the mean of its quantiles ``[*B, N]`` at
        fractions spread over [1 − α, 1] (each at least 0 with ``nonnegative_cost``)."""
        if self.nonnegative_cost:
            tail_quantiles = tail_quantiles.clamp(min=0.0)
        return tail_quantiles.mean(-1)

    def _cvar_of(self, values: CriticValues) -> Tensor:
        """Γ(s, a, α) per row from the critic's values, whichever the critic."""
        if self._quantile_critic:
            return self.quantile_cvar(values.tail_quantiles)
        return self.cvar(values.cost_value, values.cost_variance)

    def _sample_policy(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor]:
        """A reparametrised action ``a ~ π(·|s)`` and its log-probability."""
        if self._actor_plan is not None:
            observation = tensordict.get(self._actor_plan.observation_key)
            return sample_tanh_normal(self._actor_plan, self.actor_network_params, observation)
        tensordict = tensordict.copy()  # the actor writes its distribution parameters
        with (
            set_exploration_type(ExplorationType.RANDOM),
            self.actor_network_params.to_module(self.actor_network, preserve_module_state=False),
        ):
            dist = self.actor_network.get_dist(tensordict)
            return compute_rsample_log_prob(dist)

    def compute_targets(self, tensordict: TensorDictBase) -> dict[str, Tensor]:
        """TD targets from one next action ``a' ~ π(·|s')`` scored by the target critics.

        Returns a dict (each entry shaped like the batch, no gradient) with
        ``reward_target`` (``r + γ(1−term)(min_i Q̄^r_i(s',a') − β log π(a'|s'))``,
        computed by TorchRL's TD(0) estimator), ``cost_target`` (Eq. 7:
        ``c + γ_c(1−term) Q̄^c(s',a')``), and with a variance head
        ``cost_second_moment`` (``c² + (1−term)(2γ_c c Q̄^c' + γ_c² V̄^c' + γ_c² Q̄^c'²)``;
        the variance target of Eq. 8 is this minus ``Q^c(s, a)²``) and
        ``cost_next_variance`` (``γ_c² (1−term) V̄^c(s',a')``); otherwise these are
        ``None``. See :meth:`variance_target`.

        With an IQN critic, ``cost_target_quantiles`` ``[*B, N']`` holds the target
        samples ``c + γ_c(1−term) Z̄(s', a', τ'_j)`` (``num_target_quantiles`` fractions
        τ' over [0, 1]), and ``cost_target`` is their mean.
        """
        with torch.no_grad():
            next_td = tensordict.get("next")
            next_action, next_log_prob = self._sample_policy(next_td)
            next_values = self._critic_values(next_td, next_action, self._target_critics())
            q_next, vc_next = next_values.qvalue, next_values.cost_variance
            # an IQN critic's next "value" is its quantiles [*B, N']
            qc_next = (
                next_values.cost_quantiles if self._quantile_critic else next_values.cost_value
            )
            next_value = (q_next - self._alpha * next_log_prob).min(0)[0].unsqueeze(-1)
            reward_target = self._reward_target(tensordict, next_value).squeeze(-1)

            cost = self._get_cost(tensordict)
            gamma = self.cost_discount.to(cost.dtype)
            if self.cost_n_steps > 1:
                # bootstrap m ≤ n steps ahead from the batch's n-step entries
                nstep = self._get_nstep(tensordict)
                nstep_action, _ = self._sample_policy(nstep)
                # only the safety critic is needed at s_{t+m}
                nstep_sa = nstep.clone(False).set(self.tensor_keys.action, nstep_action)
                target_params = self.target_safety_network_params
                if self._quantile_critic:
                    fractions = self._fractions(self.num_target_quantiles)
                    qc_next = self._quantile_forward(nstep_sa, target_params, fractions)
                else:
                    qc_next, vc_next = self._safety_forward(nstep_sa, target_params)
                cost = nstep.get("cost").reshape(cost.shape).to(cost.dtype)
                gamma = gamma.pow(nstep.get("steps").reshape(cost.shape).to(cost.dtype))
                if self._bootstrap_truncated:
                    terminated = nstep.get("terminated")
                else:
                    terminated = self._required_entry(
                        nstep,
                        "done",
                        "Stopping the safety critic's sum at time limits needs the n-step "
                        "entries' done flag",
                        "Recompute them with this version's wcsac_rl.objectives.NStepCost, "
                        "or pass cost_bootstrap_truncated=True.",
                    )
            elif self._bootstrap_truncated:
                terminated = tensordict.get(("next", self.tensor_keys.terminated))
            else:
                # a batch without done flags has no truncations to tell apart
                terminated = tensordict.get(("next", self.tensor_keys.done), None)
                if terminated is None:
                    terminated = tensordict.get(("next", self.tensor_keys.terminated))
            not_terminated = (~terminated.reshape(cost.shape)).to(cost.dtype)
            if self.nonnegative_cost:
                qc_next = qc_next.clamp(min=0.0)
            if self._quantile_critic:
                discount = (gamma * not_terminated).unsqueeze(-1)
                target_quantiles = cost.unsqueeze(-1) + discount * qc_next
                return {
                    "reward_target": reward_target,
                    "cost_target": target_quantiles.mean(-1),
                    "cost_target_quantiles": target_quantiles,
                    "cost_second_moment": None,
                    "cost_next_variance": None,
                }
            cost_target = cost + gamma * not_terminated * qc_next
            if vc_next is None:
                second_moment = next_variance = None
            else:
                next_variance = not_terminated * gamma.pow(2) * vc_next
                second_moment = (
                    cost.pow(2)
                    + not_terminated * (2 * gamma * cost * qc_next + gamma.pow(2) * qc_next.pow(2))
                    + next_variance
                )
        return {
            "reward_target": reward_target,
            "cost_target": cost_target,
            "cost_second_moment": second_moment,
            "cost_next_variance": next_variance,
        }

    def _reward_target(self, tensordict: TensorDictBase, next_value: Tensor) -> Tensor:
        """TorchRL's TD(0) estimate ``r + γ (1 − term) V(s')``, shaped like the reward.

        Computed here when the estimator has nothing beyond plain TD(0) to apply (no
        reward standardisation, no multi-step ``steps_to_next_obs``); otherwise, or
        when the shapes do not line up, the estimator does it (and reports errors).
        """
        estimator = self.value_estimator
        keys = estimator.tensor_keys
        reward = tensordict.get(("next", keys.reward), None)
        terminated = tensordict.get(("next", keys.terminated), None)
        if terminated is None:
            terminated = tensordict.get(("next", keys.done), None)
        if (
            estimator.average_rewards
            or reward is None
            or terminated is None
            or tensordict.get(keys.steps_to_next_obs, None) is not None
            or not reward.shape == terminated.shape == next_value.shape
        ):
            td_value = tensordict.clone(False)
            td_value.set(("next", keys.value), next_value)
            return estimator.value_estimate(td_value)
        gamma = estimator.gamma.to(reward.device)
        return reward + gamma * (~terminated).int() * next_value

    # ----------------------------------------------------------------- losses
    def _online_values(
        self, tensordict: TensorDictBase, layers: Layers | None = None
    ) -> CriticValues:
        action = tensordict.get(self.tensor_keys.action)
        return self._critic_values(tensordict, action, self._online_critics(), layers)

    def qvalue_loss(
        self,
        tensordict: TensorDictBase,
        targets: dict[str, Tensor] | None = None,
        values: CriticValues | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """Twin reward-critic TD loss (TorchRL's SAC v2 critic loss).

        ``targets`` (from :meth:`compute_targets`) and ``values`` (the online critics
        at the replay actions) are computed if not given.
        """
        if targets is None:
            targets = self.compute_targets(tensordict)
        if values is None:
            values = self._online_values(tensordict)
        weights = self._maybe_get_priority_weight(tensordict)
        target_value = targets["reward_target"]
        pred = values.qvalue
        loss = distance_loss(
            pred, target_value.expand_as(pred), loss_function=self.loss_function
        ).sum(0)
        loss = self._reduce_loss(loss, tensordict=tensordict, weights=weights)
        return loss, {"td_error": (pred - target_value).abs().detach().max(0)[0]}

    def safety_loss(
        self,
        tensordict: TensorDictBase,
        targets: dict[str, Tensor] | None = None,
        values: CriticValues | None = None,
    ) -> tuple[Tensor, Tensor | None, dict[str, Tensor]]:
        """Mean TD loss (Eq. 7) and variance TD loss (Eq. 8; W2, MSE or GLM) of the safety critic.

        Returns ``(loss_cost_value, loss_cost_variance or None, metadata)`` with
        ``metadata["cost_value"]`` / ``["cost_variance"]`` the detached predictions at
        the replay actions. For an IQN critic: ``(loss_cost_quantile, None, metadata)``
        (:meth:`quantile_loss`).
        """
        if targets is None:
            targets = self.compute_targets(tensordict)
        if values is None:
            values = self._online_values(tensordict)
        if self._quantile_critic:
            loss, metadata = self.quantile_loss(tensordict, targets, values)
            return loss, None, metadata
        weights = self._maybe_get_priority_weight(tensordict)
        qc, vc = values.cost_value, values.cost_variance
        loss_mean = 0.5 * (targets["cost_target"] - qc).pow(2)
        loss_mean = self._reduce_loss(loss_mean, tensordict=tensordict, weights=weights)
        metadata = {"cost_value": qc.detach(), "cost_variance": None}
        if vc is None:
            return loss_mean, None, metadata
        variance_target = self.variance_target(targets, qc)
        loss_var = variance_regression_loss(vc, variance_target, self.variance_loss)
        loss_var = self._reduce_loss(loss_var, tensordict=tensordict, weights=weights)
        metadata["cost_variance"] = vc.detach()
        return loss_mean, loss_var, metadata

    def quantile_loss(
        self,
        tensordict: TensorDictBase,
        targets: dict[str, Tensor] | None = None,
        values: CriticValues | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """The IQN critic's quantile Huber TD loss (κ_H = ``huber_kappa``).

        ``Σ_i (1/N') Σ_j ρ^κ_{τ_i}(y_j − Z(s, a, τ_i))`` per row
        (:func:`~wcsac_rl.objectives.quantile.quantile_huber_loss`), with the targets
        ``y_j`` of :meth:`compute_targets` and the online quantiles at the replay
        actions; reduced over the batch like every term. ``metadata`` holds the
        detached mean and variance of the quantiles (``"cost_value"``,
        ``"cost_variance"``).
        """
        if not self._quantile_critic:
            raise TypeError("quantile_loss needs an IQN safety critic; use safety_loss")
        if targets is None:
            targets = self.compute_targets(tensordict)
        if values is None:
            values = self._online_values(tensordict)
        weights = self._maybe_get_priority_weight(tensordict)
        loss = quantile_huber_loss(
            values.cost_quantiles,
            values.quantile_fractions,
            targets["cost_target_quantiles"],
            self.huber_kappa,
        )
        loss = self._reduce_loss(loss, tensordict=tensordict, weights=weights)
        return loss, {
            "cost_value": values.cost_value.detach(),
            "cost_variance": values.cost_variance.detach(),
        }

    def variance_target(self, targets: dict[str, Tensor], cost_value: Tensor) -> Tensor:
        """The TD target of V^c(s, a) from :meth:`compute_targets`' ``targets``.

        ``variance_target="moment"`` (Eq. 8): ``y_v = sampled C² − Q^c(s, a)²``;
        ``"td"``: ``y_v = (y_c − Q^c(s, a))² + γ_c²(1−term) V̄^c(s', a')`` with ``y_c``
        the mean target. ``Q^c(s, a)`` is detached in both.

        For the ``"w2"`` loss the target is clamped to [1e-8, 1e8] (the square root
        needs it positive), as in the paper. For ``"mse"`` it is only clamped to
        [−1e8, 1e8]: a single sampled moment-form target may legitimately be
        negative, and clamping it at 0 would bias the fit upwards (e.g. a cost of 10
        with probability 0.1 would give 9.9 instead of the true variance 9).
        """
        cost_value = cost_value.detach()
        if self.variance_target_kind == "td":
            target = (targets["cost_target"] - cost_value).pow(2) + targets["cost_next_variance"]
        else:
            target = targets["cost_second_moment"] - cost_value.pow(2)
        if self.variance_loss == "w2":
            return target.clamp(VARIANCE_MIN, VARIANCE_MAX)
        return target.clamp(-VARIANCE_MAX, VARIANCE_MAX)

    def _penalty_weight(self, cvar_constraint: Tensor) -> Tensor:
        """The weight of Γ in the actor loss (the constraint's: κ, minus MDMM damping)."""
        return self.constraint.penalty_weight(cvar_constraint, self.cost_threshold)

    def _actor_loss(
        self,
        tensordict: TensorDictBase,
        cvar_constraint: Tensor | None,
        layers: Layers | None = None,
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """The actor loss; ``cvar_constraint`` is the Γ the κ loss sees (``None``: Γ at
        the actor's own actions on the batch)."""
        weights = self._maybe_get_priority_weight(tensordict)
        action, log_prob = self._sample_policy(tensordict)
        values = self._critic_values(tensordict, action, self._detached_critics(), layers)
        min_q = values.qvalue.min(0)[0]
        cvar_pi = self._cvar_of(values)
        if cvar_constraint is None:
            cvar_constraint = self._constraint_statistic(values.detach())
        penalty = self._penalty_weight(cvar_constraint)
        loss = self._alpha * log_prob - min_q + penalty * cvar_pi
        loss = self._reduce_loss(loss, tensordict=tensordict, weights=weights)
        return loss, {
            "log_prob": log_prob.detach(),
            "cvar_policy": cvar_pi.detach(),
            "cvar_constraint": cvar_constraint,
        }

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """``E[β log π(a|s) − min_i Q^r_i(s,a) + κ Γ(s,a,α)]``, ``a ~ π`` reparametrised.

        β, κ and all critic parameters are detached: only the actor gets gradients.
        """
        replay_values = None
        if self.kappa_actions == "replay" and self.kappa_states == "replay":
            with torch.no_grad():
                replay_values = self._online_values(tensordict).detach()
        cvar = self._constraint_cvar(tensordict, replay_values)
        return self._actor_loss(tensordict, self._kappa_signal(tensordict, cvar))

    def _episode_cvar(self, tensordict: TensorDictBase) -> Tensor:
        key = self.tensor_keys.episode_cvar
        return self._required_entry(
            tensordict,
            key,
            f"kappa_signal={self.kappa_signal!r} needs the empirical CVaR_α of recent "
            "episode costs ([*B, 1], NaN while no episode has ended)",
            f"The wcsac_rl trainer attaches it; in your own loop keep an "
            f"EpisodeCostWindow.for_loss(loss) and set batch[{key!r}] with its attach().",
        )

    def _kappa_signal(self, tensordict: TensorDictBase, cvar: Tensor | None) -> Tensor | None:
        """What the κ loss holds under the threshold (``kappa_signal``): the critic's
        statistic ``cvar``, or the episodes' empirical CVaR, or the larger of them;
        the critic's where the episodes give NaN (none finished yet)."""
        if self.kappa_signal == "critic" or cvar is None:
            return cvar
        episodes = self._episode_cvar(tensordict).to(cvar.dtype).reshape(cvar.shape)
        if self.kappa_signal == "max":
            return torch.fmax(cvar, episodes)  # fmax: NaN loses
        return torch.where(episodes.isnan(), cvar, episodes)

    def _constraint_cvar(
        self,
        tensordict: TensorDictBase,
        replay_values: CriticValues | None,
        layers: Layers | None = None,
    ) -> Tensor | None:
        """What the κ loss holds under the threshold, per batch row: the statistic
        (``kappa_statistic``) of the safety critic at the initial states (``a ~ π``)
        or at the replay actions; ``None`` when it is taken at the actor's own
        actions on the batch (computed with the actor loss)."""
        if self.kappa_states == "initial":
            return self._constraint_statistic(self._initial_state_values(tensordict, layers))
        if self.kappa_actions == "replay":
            return self._constraint_statistic(replay_values)
        return None

    def _constraint_statistic(self, values: CriticValues) -> Tensor:
        """Per-state Γ (``"mean"``: the κ loss averages it) or, for ``"tail"``, the
        CVaR_α of the critic's cost distribution mixed over the states, repeated per
        row: of the Gaussians (:func:`~wcsac_rl.objectives.risk.gaussian_mixture_cvar`)
        or of the IQN critic's quantiles over [0, 1] of every state pooled
        (:func:`~wcsac_rl.objectives.risk.quantile_mixture_cvar`)."""
        if self.kappa_statistic == "mean":
            return self._cvar_of(values)
        cost_value = values.cost_value
        if self._quantile_critic:
            quantiles = values.cost_quantiles
            if self.nonnegative_cost:
                quantiles = quantiles.clamp(min=0.0)
            tail = quantile_mixture_cvar(quantiles, self.risk_level)
        else:
            if self.nonnegative_cost:
                cost_value = cost_value.clamp(min=0.0)
            tail = gaussian_mixture_cvar(cost_value, values.cost_variance, self.risk_level)
        return tail.detach().expand(cost_value.shape)

    def initial_state_cvar(
        self, tensordict: TensorDictBase, layers: Layers | None = None
    ) -> Tensor:
        """Γ(s₀, a₀, α) with ``a₀ ~ π(·|s₀)`` at the start states the batch carries
        under the ``initial_states`` key (no gradient)."""
        return self._cvar_of(self._initial_state_values(tensordict, layers))

    def _initial_state_values(
        self, tensordict: TensorDictBase, layers: Layers | None = None
    ) -> CriticValues:
        key = self.tensor_keys.initial_states
        initial = self._required_entry(
            tensordict,
            key,
            "kappa_states='initial' needs episode start states (a sub-tensordict shaped like "
            "the batch with the actor's observation entries)",
            f"The wcsac_rl trainer attaches them; in your own loop sample start states and "
            f"set batch[{key!r}] = them.",
        )
        with torch.no_grad():
            action, _ = self._sample_policy(initial)
            return self._critic_values(initial, action, self._detached_critics(), layers).detach()

    @property
    def initial_state_keys(self) -> list[NestedKey]:
        """What a start state must hold for :meth:`initial_state_cvar` (the actor's and
        critics' inputs other than the action)."""
        keys = list(self.actor_network.in_keys)
        loss_inputs = (self.tensor_keys.action, self.tensor_keys.quantile_fractions)
        for key in (*self.qvalue_network.in_keys, *self.safety_network.in_keys):
            if key not in loss_inputs and key not in keys:
                keys.append(key)
        return keys

    def safety_estimates(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The safety critic at the state-actions of ``tensordict`` (online parameters,
        no gradient): ``cost_value`` (Q^c), ``cvar`` (Γ_α) and, with a variance head,
        ``cost_variance`` (V^c), each shaped like the batch. For diagnostics such as
        :mod:`wcsac_rl.evaluation.calibration`.

        An IQN critic is read at deterministic fractions, the midpoints of
        ``num_quantiles`` equal strata: ``cost_quantiles`` ``[*B, N]`` over [0, 1],
        ``cost_value`` and ``cost_variance`` their mean and variance, and ``cvar`` the
        mean of the quantiles at the midpoints of [1 − α, 1]."""
        if self._quantile_critic:
            with torch.no_grad():
                mean, variance, quantiles, _, tail = self._quantile_values(
                    tensordict, self.safety_network_params, stratified=False
                )
                out = {
                    "cost_value": mean,
                    "cost_variance": variance,
                    "cvar": self.quantile_cvar(tail),
                    "cost_quantiles": quantiles,
                }
            return TensorDict(out, batch_size=tensordict.batch_size)
        with torch.no_grad():
            cost_value, cost_variance = self._safety_forward(tensordict, self.safety_network_params)
            out = {"cost_value": cost_value, "cvar": self.cvar(cost_value, cost_variance)}
            if cost_variance is not None:
                out["cost_variance"] = cost_variance
        return TensorDict(out, batch_size=tensordict.batch_size)

    def kappa_loss(self, cvar: Tensor, tensordict: TensorDictBase | None = None) -> Tensor | None:
        """The constraint's loss term: ``κ · (threshold − Γ)`` with Γ detached (κ grows
        while Γ exceeds the threshold) under the gradient rule; ``None`` under the PID
        rule, whose κ the forward pass sets (see ``kappa_rule``)."""
        loss = self.constraint.loss(cvar, self.cost_threshold)
        if loss is None:
            return None
        weights = None if tensordict is None else self._maybe_get_priority_weight(tensordict)
        return self._reduce_loss(loss, tensordict=tensordict, weights=weights)

    # ---------------------------------------------------------------- forward
    def check_inputs(self, tensordict: TensorDictBase) -> None:
        """Raise a ``ValueError`` naming the first entry the loss reads (``in_keys``) that
        holds a NaN or ±inf, or an empty batch. Reads the values (a host
        synchronisation): call it before :meth:`forward` where that is affordable, or
        construct the loss with ``check_finite=True`` to run it on every call (not
        under ``torch.compile``)."""
        check_nonempty_batch(tensordict, type(self).__name__)
        check_finite_entries(tensordict, self.in_keys, type(self).__name__)

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        check_nonempty_batch(tensordict, type(self).__name__)  # (shapes only: no sync)
        if self.check_finite:
            self.check_inputs(tensordict)
        targets = self.compute_targets(tensordict)
        # the fused critics' parameters are gathered once: trainable for the critic
        # losses, detached for the actor's
        layers = self._fused_layers(self._online_critics())
        values = self._online_values(tensordict, layers)  # shared by both critic losses
        loss_qvalue, q_metadata = self.qvalue_loss(tensordict, targets, values)
        loss_cost_value, loss_cost_variance, safety_metadata = self.safety_loss(
            tensordict, targets, values
        )
        replay_values = values.detach()
        detached = None if layers is None else [(w.detach(), b.detach()) for w, b in layers]
        cvar_constraint = self._constraint_cvar(tensordict, replay_values, detached)
        kappa_signal = self._kappa_signal(tensordict, cvar_constraint)
        loss_actor, actor_metadata = self._actor_loss(tensordict, kappa_signal, detached)
        log_prob = actor_metadata["log_prob"]
        weights = self._maybe_get_priority_weight(tensordict)
        loss_alpha = self._reduce_loss(
            self._alpha_loss(log_prob=log_prob), tensordict=tensordict, weights=weights
        )
        if cvar_constraint is None:  # Γ at the actor's own actions
            cvar_constraint = actor_metadata["cvar_constraint"]
        loss_kappa = self.kappa_loss(actor_metadata["cvar_constraint"], tensordict)
        tensordict.set(self.tensor_keys.priority, q_metadata["td_error"])

        out = {
            "loss_actor": loss_actor,
            "loss_qvalue": loss_qvalue,
            "loss_alpha": loss_alpha,
            "loss_cost_quantile" if self._quantile_critic else "loss_cost_value": loss_cost_value,
        }
        if loss_cost_variance is not None:
            out["loss_cost_variance"] = loss_cost_variance
        if loss_kappa is not None:
            out["loss_kappa"] = loss_kappa
        scalars = {
            "alpha": self._alpha,
            "kappa": self.kappa,
            "entropy": -log_prob.mean(),
            "cost_value": safety_metadata["cost_value"].mean(),
            "cvar": cvar_constraint.mean(),
            "cost_threshold": self.cost_threshold.clone(),
        }
        if self.kappa_signal != "critic":
            scalars["episode_cvar"] = self._episode_cvar(tensordict).mean()
            scalars["constraint_cvar"] = actor_metadata["cvar_constraint"].mean()
        if safety_metadata["cost_variance"] is not None:
            scalars["cost_variance"] = safety_metadata["cost_variance"].mean()
        if self.training and self.constraint.rule != "gradient":
            # the controller's update, after this batch's actor loss used the current κ
            self.constraint.step(actor_metadata["cvar_constraint"].detach(), self.cost_threshold)
        if self.reduction == "none":
            td_out = TensorDict(out, batch_size=tensordict.batch_size)
            if self.scalar_output_mode == "non_tensor":
                for key, value in scalars.items():
                    td_out.set_non_tensor(key, value)
        else:
            out.update(scalars)
            td_out = TensorDict(out, batch_size=[])
        self._clear_weakrefs(
            tensordict,
            td_out,
            "actor_network_params",
            "qvalue_network_params",
            "safety_network_params",
            "target_actor_network_params",
            "target_qvalue_network_params",
            "target_safety_network_params",
        )
        return td_out


def _rename_kappa_raw(module, state_dict, prefix, *args) -> None:
    """Load a state dict saved before κ moved into :attr:`WCSACLoss.constraint`."""
    old, new = f"{prefix}kappa_raw", f"{prefix}constraint.kappa_raw"
    if old in state_dict and new not in state_dict:
        state_dict[new] = state_dict.pop(old)


class SACLagLoss(WCSACLoss):
    """SAC-Lagrangian: :class:`WCSACLoss` with ``risk_level=1`` (Γ = Q^c, the expected cost).

    Use a mean-only safety critic (``make_safety_critic(..., variance=False)``): no
    variance network exists or is trained, which is the paper's ablation. With a
    Gaussian critic the variance is still learned (a diagnostic) but never used; with
    an IQN critic (``kind="iqn"``) Γ is the mean of its quantiles over [0, 1].

    Example:
        >>> from torchrl.data import Bounded
        >>> from wcsac_rl import SACLagLoss
        >>> from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
        >>> loss = SACLagLoss(make_actor(4, Bounded(-1.0, 1.0, shape=(2,))),
        ...                   [make_qvalue(4, 2) for _ in range(2)],
        ...                   make_safety_critic(4, 2, variance=False), cost_limit=25.0)
        >>> loss.has_variance, loss.risk_level
        (False, 1.0)
    """

    def __init__(self, actor_network, qvalue_network, safety_network, **kwargs) -> None:
        if kwargs.get("risk_level", 1.0) != 1.0:
            raise ValueError(
                "SACLagLoss is the risk-neutral case (risk_level=1); for risk_level < 1 use WCSACLoss"
            )
        kwargs["risk_level"] = 1.0
        super().__init__(actor_network, qvalue_network, safety_network, **kwargs)
