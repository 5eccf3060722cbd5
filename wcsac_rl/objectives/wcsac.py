"""Worst-Case Soft Actor Critic (Yang et al., AAAI 2021) as a TorchRL ``LossModule``.

``WCSACLoss`` is TorchRL's :class:`~torchrl.objectives.SACLoss` (v2: twin Q, no value
network) composed of parts, each in its own module: the safety head and its cost target
(:mod:`~wcsac_rl.objectives.safety_head`), the critics read together
(:mod:`~wcsac_rl.objectives.critics`) and the constraint, what κ reads and how it moves
(:mod:`~wcsac_rl.objectives.constraint`); ``docs/architecture.md`` maps them. The loss
itself is one method per term: ``qvalue_loss``, ``safety_loss``, ``actor_loss``
(``β log π − min Q^r + κ Γ``), ``alpha_loss`` (TorchRL's) and ``kappa_loss``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import SACLoss
from torchrl.objectives.sac import compute_rsample_log_prob
from torchrl.objectives.utils import ValueEstimators, _cache_values, distance_loss

from wcsac_rl.objectives.budget import (
    per_step_cost_threshold,
    validate_cost_limit,
    validate_max_episode_steps,
)
from wcsac_rl.objectives.checked_loss import CheckedLoss
from wcsac_rl.objectives.constraint import (
    ConstraintSignal,
    GradientLagrangian,
    HeldStatistic,
    PIDLagrangian,
    rename_kappa_raw,
)
from wcsac_rl.objectives.critics import CriticParams, Critics, CriticValues
from wcsac_rl.objectives.ensemble_head import make_safety_head
from wcsac_rl.objectives.fast_paths import FastPaths, Layers, td0_target
from wcsac_rl.objectives.inputs import (
    as_given,
    check_batch_entries,
    check_critic_inputs,
    check_finite_entries,
    check_finite_losses,
    check_nonempty_batch,
    check_td0,
    convert_safety_network,
    data_keys,
    finite_number,
    loss_out_keys,
    missing_inputs,
    parts_in_keys,
    refuse_multistep,
    refuse_unknown_keywords,
    sample_alive,
    state_keys,
    takes_tensordict,
    whole_count,
)
from wcsac_rl.objectives.loss_options import (
    PART_OF_OPTION,
    SafetyHeadOptions,
    SignalOptions,
    claim_constraint,
    default_parts,
)
from wcsac_rl.objectives.risk import gaussian_cvar_multiplier, validate_risk_level
from wcsac_rl.objectives.safety_head import CostTarget, SafetyValues
from wcsac_rl.options import SafetyOptions
from wcsac_rl.recipes import TRAINER_KEYS

__all__ = [
    "CriticValues",
    "WCSACLoss",
    "per_step_cost_threshold",
]


class WCSACLoss(CheckedLoss, SACLoss):
    r"""The WCSAC loss: SAC with a safety critic and a CVaR constraint.

    TorchRL-style: the networks, a handful of keywords, the parts as objects
    (``docs/architecture.md``). Not given, a part is the paper's (``PAPER_OPTIONS`` for
    the safety network's kind, β from 1 as SACLoss's): the published WCSAC, reading only
    what any TorchRL batch holds (observation, action, next reward / done / terminated /
    cost). ``**loss_parts(recipe)`` gives the parts of another recipe: the kit's
    (``KIT_OPTIONS``, what ``train.py algo=wcsac env=static`` runs, with an IQN critic;
    ``kit_options("dynamic")``), whose n-step cost, start states and episode window the
    kit's transforms write. ``benchmarks/plain_wcsac.py`` is the plain-PyTorch
    reference of the paper's update (``tests/test_plain_reference.py``).

    Args:
        actor_network (ProbabilisticTensorDictSequential): the stochastic (tanh-Normal) actor.
        qvalue_network (TensorDictModule or list of them): the reward critic ``Q^r(s, a)``
            (a list gives independently initialised twins; see
            :class:`~torchrl.objectives.SACLoss`).
        safety_network (TensorDictModule or list of them): the safety critic
            (:func:`wcsac_rl.modules.make_safety_critic`): Gaussian (``"cost_value"`` and
            ``"cost_variance"``; mean-only at ``risk_level=1``) or an implicit quantile
            network (``"quantile_fractions"`` → ``"cost_quantiles"``). A list of
            ``safety_head.num_safety_nets`` modules of one structure gives that many
            independently initialised critics; given one, the others are re-drawn from it.

    Keyword Args:
        risk_level (float): the paper's α ∈ (0, 1], the tail fraction whose mean cost
            (CVaR_α) is constrained; 1 is the expected cost (SAC-Lag).
        cost_limit (float): the episodic cost budget ``d``. Default ``15.0``.
        max_episode_steps (int): ``T`` in the per-step threshold
            ``d·(1−γ_c^T)/((1−γ_c)T)`` (κ at replay states). Default ``1000``.
        cost_threshold (float, optional): the threshold given directly (then
            ``cost_limit`` and ``max_episode_steps`` are not used). By default ``d``
            at start states, the per-step threshold at replay states.
        safety_head (SafetyHeadOptions, optional): the safety critic's head, its TD
            target and ensemble (:class:`~wcsac_rl.objectives.loss_options.SafetyHeadOptions`).
        signal (SignalOptions, optional): what κ holds under the threshold
            (:class:`~wcsac_rl.objectives.loss_options.SignalOptions`).
        constraint (GradientLagrangian or PIDLagrangian, optional): κ and its rule
            (:mod:`wcsac_rl.objectives.constraint`), owned by this loss from now on; the
            PID rule steps in :meth:`forward` while the loss is in training mode.
        alpha_init (float): the initial entropy weight β; SACLoss's 1 (the kit's recipe: 0.1).
        fast_paths (bool, optional): the critics as one batched ensemble, the actor's
            actions drawn from its parameters, ... (:mod:`~wcsac_rl.objectives.fast_paths`);
            ``None``: each when possible; ``True``: required; ``False``: TorchRL's general
            path. Same values either way; :attr:`fast_paths` reports the paths taken.
        check_finite (bool): run :meth:`check_inputs` on every call (not under
            ``torch.compile``). Default ``False``; an empty batch is refused either way.
        num_qvalue_nets, loss_function: SACLoss's (``loss_function`` default ``"l2"``).
        **sac_kwargs: :class:`~torchrl.objectives.SACLoss`'s other keywords
            (``target_entropy``, ``delay_qvalue``, ``separate_losses``, ``reduction``, ...),
            passed on. The loss's own keywords are the 12 above (``inspect.signature``'s
            keyword-only parameters; SACLoss's count as SACLoss's).

    Each option is defined once, in :class:`~wcsac_rl.options.SafetyOptions`; a bad value
    is refused in one line naming it. γ comes from the value estimator
    (``loss.make_value_estimator(gamma=0.99)``, any TD(0) form; default 0.99). A batch
    lacking what the parts read is refused with a one-line ``KeyError`` naming the
    transforms to add (:func:`~wcsac_rl.objectives.inputs.missing_inputs`; the TorchRL
    contract the loss keeps: ``docs/torchrl_contract.md``). ``forward`` returns the
    ``loss_*`` terms (``loss_kappa`` under the gradient rule) and detached diagnostics
    (:attr:`out_keys`); each term sends gradients only to its own parameters, so their
    sum can be back-propagated at once.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from torchrl.objectives import SoftUpdate
        >>> from wcsac_rl import WCSACLoss
        >>> from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
        >>> actor = make_actor(4, Bounded(-1.0, 1.0, shape=(2,)))
        >>> loss = WCSACLoss(  # the paper's WCSAC: a Gaussian safety critic
        ...     actor, [make_qvalue(4, 2) for _ in range(2)], make_safety_critic(4, 2),
        ...     risk_level=0.1, cost_limit=15.0, max_episode_steps=1000)
        >>> updater = SoftUpdate(loss, tau=0.005)
        >>> batch = TensorDict({  # a replay batch of any TorchRL collector
        ...     "observation": torch.randn(8, 4), "action": torch.rand(8, 2) * 2 - 1,
        ...     "next": {"observation": torch.randn(8, 4), "reward": torch.randn(8, 1),
        ...              "cost": torch.bernoulli(torch.full((8, 1), 0.1)),
        ...              "done": torch.zeros(8, 1, dtype=torch.bool),
        ...              "terminated": torch.zeros(8, 1, dtype=torch.bool)}}, [8])
        >>> out = loss(batch)
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_alpha', 'loss_cost_value', 'loss_cost_variance', 'loss_kappa', 'loss_qvalue']

    The kit's recipe, ``WCSACLoss(..., **loss_parts(KIT_OPTIONS))`` with an IQN critic,
    reads n-step cost entries, episode start states and a recent-episodes window
    (``NStepCost``, ``StartStateBuffer``, ``EpisodeCostWindow``: ``docs/loss.md``).
    """

    @dataclass
    class _AcceptedKeys(SACLoss._AcceptedKeys):
        """Tensordict keys the loss reads; change them with ``.set_keys(name=key)``.

        Those of :class:`~torchrl.objectives.SACLoss` (``action``,
        ``state_action_value``, ``priority``, ``reward``, ``done``, ``terminated``, ...)
        and:

        Attributes:
            cost (NestedKey): per-step cost, read under ``"next"``, ``[*B, 1]`` or ``[*B]``.
            cost_value, cost_variance (NestedKey): the Gaussian safety critic's Q^c and V^c.
            quantile_fractions, cost_quantiles (NestedKey): an IQN safety critic's input
                fractions τ (the loss writes them) and output quantiles.
            initial_states (NestedKey): with ``kappa_states="initial"``, a sub-tensordict
                shaped like the batch holding episode start states (the actor's and
                critics' state entries).
            episode_cvar (NestedKey): with ``kappa_signal`` ``"max"`` or ``"episodes"``,
                the empirical CVaR_α of recent episode costs, ``[*B, 1]`` (NaN: none yet).
            nstep (NestedKey): with ``cost_n_steps > 1``, the sub-tensordict of
                :class:`~wcsac_rl.objectives.NStepCost`.

            Each defaults to its own name, ``initial_states`` to ``"initial"``.
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
        safety_network: TensorDictModule | list[TensorDictModule],
        *,
        risk_level: float = SafetyOptions.risk_level,
        cost_limit: float = 15.0,
        max_episode_steps: int = 1000,
        cost_threshold: float | None = None,
        safety_head: SafetyHeadOptions | None = None,
        signal: SignalOptions | None = None,
        constraint: GradientLagrangian | PIDLagrangian | None = None,
        alpha_init: float = TRAINER_KEYS["alpha_init"],
        fast_paths: bool | None = None,
        num_qvalue_nets: int = 2,
        loss_function: str = "l2",
        check_finite: bool = False,
        **sac_kwargs,
    ) -> None:
        given = (safety_head, signal, constraint, alpha_init)
        head, signal, constraint = default_parts(safety_network, *given)
        refuse_unknown_keywords(WCSACLoss.__init__, sac_kwargs, PART_OF_OPTION)
        if sac_kwargs.pop("value_network", None) is not None:
            raise ValueError("WCSACLoss is SAC v2: it takes no value_network")
        self.risk_level = validate_risk_level(risk_level)
        self.cvar_multiplier = gaussian_cvar_multiplier(self.risk_level)
        validate_cost_limit(cost_limit)  # (NaN and inf too: one line naming it)
        if cost_threshold is not None:
            finite_number(cost_threshold, "cost_threshold", minimum=0.0)
        else:  # (what the threshold is made from, checked now whatever γ is later)
            validate_max_episode_steps(max_episode_steps)
        whole_count(num_qvalue_nets, "num_qvalue_nets")
        self.check_finite = bool(check_finite)
        self.cost_limit = float(cost_limit)
        self.max_episode_steps = int(max_episode_steps)
        self._explicit_cost_threshold = None if cost_threshold is None else float(cost_threshold)
        self.head_options, self.signal_options = head, signal  # (the parts' options as given)
        self.variance_loss = head.variance_loss  # (TorchRL wraps a class's "*loss" names)

        super().__init__(
            actor_network,
            qvalue_network,
            None,
            num_qvalue_nets=num_qvalue_nets,
            loss_function=loss_function,
            alpha_init=alpha_init,
            **sac_kwargs,
        )
        convert_safety_network(
            self, safety_network, sac_kwargs.get("separate_losses", False), head.num_safety_nets
        )
        self.cost_target = CostTarget(
            self.tensor_keys,
            gamma=head.cost_gamma,
            n_steps=head.cost_n_steps,
            bootstrap_truncated=head.cost_bootstrap_truncated,
        )
        self.safety_head = make_safety_head(
            self.safety_network, self.tensor_keys, risk_level=self.risk_level, options=head
        )
        device = self.log_alpha.device
        for name in ("prior", "pessimism"):  # (buffers, moved in place: no optimizer's)
            part = getattr(self.safety_head, name, None)
            setattr(self, f"safety_{name}", None if part is None else part.to(device))
        self.constraint_signal = ConstraintSignal(
            self.safety_head,
            self.tensor_keys,
            states=signal.kappa_states,
            actions=signal.kappa_actions,
            statistic=signal.kappa_statistic,
            signal=signal.kappa_signal,
        )
        self.constraint = claim_constraint(self, constraint).to(device)
        # the start-state tail held between reads (kappa_signal_every > 1 only: a loss
        # that reads it every update keeps the state dict it always had)
        every = signal.kappa_signal_every
        self.kappa_signal_hold = HeldStatistic(every).to(device) if every > 1 else None
        self.register_load_state_dict_pre_hook(rename_kappa_raw)
        self.register_buffer("cost_threshold", torch.zeros((), device=device))
        # derived from cost_gamma / the value estimator: not part of the state dict
        self.register_buffer("cost_discount", torch.zeros((), device=device), persistent=False)
        self.make_value_estimator(ValueEstimators.TD0)
        self._set_in_keys()
        self._paths = FastPaths(
            fast_paths,
            actor_network,
            self.qvalue_network,
            self.safety_head,
            action_key=self.tensor_keys.action,
            num_qvalue_nets=self.num_qvalue_nets,
            vmap=not self.deactivate_vmap,
        )
        self.critics = Critics(self.qvalue_network, self.safety_head, self.tensor_keys, self._paths)

    # the parts' options, by name (what the config calls them)
    num_safety_nets = property(lambda self: self.head_options.num_safety_nets)
    nonnegative_cost = property(lambda self: self.head_options.nonnegative_cost)
    variance_target_kind = property(lambda self: self.head_options.variance_target)
    num_quantiles = property(lambda self: self.head_options.num_quantiles)
    num_target_quantiles = property(lambda self: self.head_options.num_target_quantiles)
    huber_kappa = property(lambda self: self.head_options.huber_kappa)
    kappa_signal_every = property(lambda self: self.signal_options.kappa_signal_every)
    kappa_parametrization = property(lambda self: getattr(self.constraint, "parametrization", None))

    # ------------------------------------------------------------------ set-up
    @property
    def has_variance(self) -> bool:
        """Whether the safety critic has a variance network (WCSAC) or not (SAC-Lag, IQN)."""
        return self.safety_head.has_variance

    @property
    def safety_critic_kind(self) -> str:
        """``"iqn"`` (implicit quantile network), ``"gaussian"`` (mean and variance
        networks) or ``"mean"`` (mean only, SAC-Lag): the head's kind."""
        return self.safety_head.kind

    # what κ reads (:attr:`constraint_signal`)
    kappa_states = property(lambda self: self.constraint_signal.states)
    kappa_actions = property(lambda self: self.constraint_signal.actions)
    kappa_statistic = property(lambda self: self.constraint_signal.statistic_kind)
    kappa_signal = property(lambda self: self.constraint_signal.signal_kind)

    def make_value_estimator(self, value_type=None, **hyperparams):
        """Set the reward's TD(0) estimator and γ, and the per-step cost threshold that
        depends on it. Takes what :class:`~torchrl.objectives.SACLoss` takes for TD(0):
        ``ValueEstimators.TD0`` or ``"td0"`` with ``gamma=...``, the
        :class:`~torchrl.objectives.value.TD0Estimator` class with its arguments, or an
        instance; refuses the others in one line (the cost-variance target is a one-step
        recursion). Returns the loss."""
        check_td0(value_type, type(self).__name__)
        super().make_value_estimator(value_type, **hyperparams)
        if "gamma" in hyperparams:
            # γ as given (the estimator stores it in float32: 0.99 → 0.99000001, which
            # would move the per-step threshold by 1.4e-6)
            self._gamma = float(hyperparams["gamma"])
        else:  # the default's, or an instance's (its shortest float32 decimal)
            self._gamma = as_given(self.value_estimator.gamma)
        if "cost_threshold" in self._buffers:  # (the parts exist: not in SACLoss.__init__)
            self.cost_target.set_reward_gamma(self._gamma)
            gamma = self.cost_target.gamma
            threshold = self._explicit_cost_threshold
            if threshold is None:
                threshold = self.constraint_signal.threshold(
                    self.cost_limit, gamma, self.max_episode_steps
                )
            self.cost_threshold.fill_(threshold)
            self.cost_discount.fill_(gamma)
        return self

    @property
    def cost_gamma(self) -> float:
        """The safety critic's discount γ_c (``cost_gamma``, else the value estimator's γ)."""
        return self.cost_target.gamma

    @property
    def cost_n_steps(self) -> int:
        """The safety critic's lookahead ``n`` (:attr:`cost_target`)."""
        return self.cost_target.n_steps

    @property
    def cost_bootstrap_truncated(self) -> bool:
        """Whether the safety critic's target bootstraps across a time-limit truncation
        (``cost_bootstrap_truncated``, else ``γ_c < 1``)."""
        return self.cost_target.bootstrap_truncated

    def _set_in_keys(self):
        super()._set_in_keys()
        if "safety_head" in self.__dict__:  # (the parts exist: not in SACLoss.__init__)
            self._in_keys = parts_in_keys(self, self._in_keys)

    @property
    def out_keys(self):
        if self._out_keys is None:
            self._out_keys = loss_out_keys(self)
        return self._out_keys

    @out_keys.setter
    def out_keys(self, values):
        self._out_keys = values

    @property
    def initial_state_keys(self) -> list[NestedKey]:
        """What a start state (and an n-step state) must hold for the loss's networks:
        their inputs other than the action, without what they write in between
        (:func:`~wcsac_rl.objectives.inputs.state_keys`)."""
        return state_keys(self)

    # --------------------------------------------------------------- κ
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

    # ----------------------------------------------------------------- pieces
    @property
    @_cache_values
    def _cached_detached_safety_params(self):
        return self.safety_network_params.detach()

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

    @property
    def fast_paths(self) -> dict[str, str]:
        """Each fast path and whether it is taken, or why not (:meth:`FastPaths.report`)."""
        return self._paths.report()

    def _critic_values(
        self, tensordict, action, critics: CriticParams, layers=None, qvalue=True
    ) -> CriticValues:
        return self.critics.values(
            tensordict, action, critics, self._vmap_qnetworkN0, layers, qvalue=qvalue
        )

    def _online_values(
        self, tensordict: TensorDictBase, layers: Layers | None = None
    ) -> CriticValues:
        action = tensordict.get(self.tensor_keys.action)
        return self._critic_values(tensordict, action, self._online_critics(), layers)

    def _policy_values(self, states: TensorDictBase, layers: Layers | None = None) -> CriticValues:
        """The safety critic (detached) at ``a ~ π(·|s)`` for the ``states``, no gradient
        (the reward critics are not read: ``qvalue`` is ``None``)."""
        with torch.no_grad():
            action, _ = self._sample_policy(states)
            critics = self._detached_critics()  # (κ reads the safety critic alone)
            values = self._critic_values(states, action, critics, layers, qvalue=False)
            return values.detach()

    def _sample_policy(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor]:
        """A reparametrised action ``a ~ π(·|s)`` and its log-probability."""
        sampling = self._paths.sampling
        if sampling is not None:
            observation = tensordict.get(sampling.observation_key)
            return sampling.sample(self.actor_network_params, observation)
        tensordict = tensordict.copy()  # the actor writes its distribution parameters
        with (
            set_exploration_type(ExplorationType.RANDOM),
            self.actor_network_params.to_module(self.actor_network, preserve_module_state=False),
        ):
            dist = self.actor_network.get_dist(tensordict)
            return compute_rsample_log_prob(dist)

    def cvar(self, cost_value: Tensor, cost_variance: Tensor | None) -> Tensor:
        """Γ(s, a, α) = Q^c + α⁻¹ φ(Φ⁻¹(α)) √V^c (Eq. 9) of a Gaussian critic's values
        (the head's; Q^c at least 0 with ``nonnegative_cost``)."""
        return self.safety_head.cvar(SafetyValues(cost_value, cost_variance))

    def quantile_cvar(self, tail_quantiles: Tensor) -> Tensor:
        """Γ(s, a, α) of an IQN critic: the mean of its quantiles ``[*B, N]`` at
        fractions spread over [1 − α, 1] (each at least 0 with ``nonnegative_cost``)."""
        return self.safety_head.cvar(SafetyValues(tail=tail_quantiles))

    def variance_target(self, targets: dict[str, Tensor], cost_value: Tensor) -> Tensor:
        """The Gaussian head's TD target of V^c(s, a)
        (:meth:`~wcsac_rl.objectives.safety_head.GaussianHead.variance_target`)."""
        return self.safety_head.variance_target(targets, cost_value)

    def safety_estimates(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The safety critic at the state-actions of ``tensordict`` (online parameters,
        no gradient), shaped like the batch: ``cost_value`` (Q^c), ``cvar`` (Γ_α) and,
        with a variance network, ``cost_variance`` (V^c); an IQN critic is read at the
        midpoints of its strata and adds ``cost_quantiles`` ``[*B, N]``. For
        diagnostics such as :mod:`wcsac_rl.evaluation.run_calibration`."""
        with torch.no_grad():
            out = self.safety_head.estimates(tensordict, self.safety_network_params)
        return TensorDict(out, batch_size=tensordict.batch_size)

    def action_cvar(self, tensordict: TensorDictBase, action: Tensor) -> Tensor:
        """Γ(s, a, α) of the online safety critic at the states of ``tensordict`` and
        ``action`` (``[*B, A]`` for a batch ``[*B]``), shaped ``[*B]``, no gradient.

        The reading a collection-time shield compares with its threshold
        (:class:`~wcsac_rl.modules.CriticShield`): deterministic (an IQN critic is
        read at the midpoints of its tail strata) and, with several safety critics,
        the ensemble's reading (``ensemble_reading``), as the actor and κ read it."""
        return self.safety_head.action_cvar(tensordict, self.safety_network_params, action)

    # ---------------------------------------------------------------- targets
    def compute_targets(self, tensordict: TensorDictBase) -> dict[str, Tensor]:
        """TD targets (no gradient) from ``a' ~ π(·|s')`` scored by the target critics:
        ``reward_target`` (``r + γ(1−term)(min_i Q̄^r_i(s',a') − β log π(a'|s'))``) and
        the safety head's (``cost_target``, Eq. 7, and ``cost_second_moment``,
        ``cost_next_variance`` or ``cost_target_quantiles``) on the cost target's
        bootstrap (:class:`~wcsac_rl.objectives.safety_head.CostTarget`)."""
        if self.cost_n_steps == 1:
            refuse_multistep(
                type(self).__name__, tensordict, self.value_estimator.tensor_keys.steps_to_next_obs
            )
        with torch.no_grad():
            next_td = tensordict.get("next")
            next_action, next_log_prob = self._sample_alive(
                next_td, self.tensor_keys.done, tensordict
            )
            # the target critics read once: the reward critics at (s', a'), the safety
            # critic where its target bootstraps (s' or the n-step states, a ~ π there)
            ahead = self.cost_target.bootstrap_states(tensordict)
            next_values = self.critics.target_values(
                next_td,
                next_action,
                self._target_critics(),
                self._vmap_qnetworkN0,
                ahead,
                lambda states: self._sample_action(states, tensordict),
            )
            next_value = (next_values.qvalue - self._alpha * next_log_prob).min(0)[0]
            reward_target = self._reward_target(tensordict, next_value.unsqueeze(-1)).squeeze(-1)
            bootstrap = self.cost_target.bootstrap(
                tensordict, self.cost_discount, next_values.safety, next_values.safety
            )
            targets = self.safety_head.targets(*bootstrap)
        return {"reward_target": reward_target, **targets}

    def _sample_action(self, states: TensorDictBase, batch: TensorDictBase) -> Tensor:
        """``a ~ π(·|states)`` (the n-step bootstrap's action; ``skip_done_states``
        as for ``s'``)."""
        return self._sample_alive(states, "done", batch)[0]

    def _sample_alive(self, states: TensorDictBase, done_key: NestedKey, like: TensorDictBase):
        """:func:`~wcsac_rl.objectives.inputs.sample_alive` with this loss's
        actor (``skip_done_states``: the rows whose ``done_key`` is set are skipped)."""
        done = states.get(done_key, None) if self.skip_done_states else None
        return sample_alive(self._sample_policy, states, done, like.get(self.tensor_keys.action))

    def _reward_target(self, tensordict: TensorDictBase, next_value: Tensor) -> Tensor:
        """TorchRL's TD(0) estimate ``r + γ (1 − term) V(s')`` (:func:`td0_target`)."""
        return td0_target(self.value_estimator, tensordict, next_value, not self._paths.off)

    # ----------------------------------------------------------------- losses
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
    ) -> tuple[Tensor, Tensor | None, dict[str, Tensor | None]]:
        """The safety critic's TD loss (its head's): ``(first term, second term or None,
        metadata)`` — Gaussian: ``loss_cost_value`` (Eq. 7) and ``loss_cost_variance``
        (Eq. 8; ``None`` without a variance network); IQN: ``loss_cost_quantile`` and
        ``None``. ``metadata["cost_value"]`` / ``["cost_variance"]`` are the detached
        predictions at the replay actions (``None`` where there is no variance)."""
        if targets is None:
            targets = self.compute_targets(tensordict)
        if values is None:
            values = self._online_values(tensordict)
        weights = self._maybe_get_priority_weight(tensordict)
        terms = [
            self._reduce_loss(loss, tensordict=tensordict, weights=weights)
            for loss in self.safety_head.loss(values.safety, targets).values()
        ]
        metadata = self.safety_head.diagnostics(values.safety)
        return terms[0], (terms[1] if len(terms) > 1 else None), metadata

    def actor_loss(self, tensordict: TensorDictBase) -> tuple[Tensor, dict[str, Tensor]]:
        """``E[β log π(a|s) − min_i Q^r_i(s,a) + κ Γ(s,a,α)]``, ``a ~ π`` reparametrised.

        β, κ and all critic parameters are detached: only the actor gets gradients.
        """
        replay_values = None
        if self.constraint_signal.needs_replay_values:
            with torch.no_grad():
                replay_values = self._online_values(tensordict).detach()
        statistic = self._constraint_statistic(tensordict, replay_values)
        return self._actor_loss(tensordict, self.constraint_signal.signal(tensordict, statistic))

    def _actor_loss(self, tensordict, signal: Tensor | None, layers=None) -> tuple[Tensor, dict]:
        """The actor loss; ``signal`` is what κ holds under the threshold (``None``: the
        critic's statistic at the actor's own actions on the batch, computed here)."""
        weights = self._maybe_get_priority_weight(tensordict)
        action, log_prob = self._sample_policy(tensordict)
        values = self._critic_values(tensordict, action, self._detached_critics(), layers)
        min_q = values.qvalue.min(0)[0]
        cvar_pi = self.safety_head.cvar(values.safety)
        if signal is None:
            mask = self._row_mask(tensordict)
            signal = self.constraint_signal.statistic(values.safety.detach(), mask)
        penalty = self.constraint.penalty_weight(signal, self.cost_threshold)
        loss = self._alpha * log_prob - min_q + penalty * cvar_pi
        loss = self._reduce_loss(loss, tensordict=tensordict, weights=weights)
        return loss, {
            "log_prob": log_prob.detach(),
            "cvar_policy": cvar_pi.detach(),
            "cvar_constraint": signal,
        }

    def _constraint_statistic(self, tensordict, replay_values, layers=None) -> Tensor | None:
        """The critic's statistic κ reads, per row (:attr:`constraint_signal`), or
        ``None`` when it is taken at the actor's own actions (with the actor loss).
        With ``kappa_signal_every`` k > 1, a training update reads it once in k and
        the others take the held reading (evaluation mode reads it and holds nothing)."""
        hold = self.kappa_signal_hold if self.training else None
        if hold is not None:
            held = hold.take()
            if held is not None:
                return held.expand(tensordict.shape)
        values = self.constraint_signal.critic_values(
            tensordict, replay_values, lambda states: self._policy_values(states, layers)
        )
        if values is None:
            return None
        statistic = self.constraint_signal.statistic(values.safety, self._row_mask(tensordict))
        if hold is not None:
            hold.store(statistic.reshape(-1)[0])  # (the tail: one number, repeated per row)
        return statistic

    def _row_mask(self, tensordict: TensorDictBase) -> Tensor | None:
        """Which rows count, from the loss masks TorchRL's reduction reads
        (``("collector", "mask")``, ``"shifted_valid"``, or ``loss_mask_key``), shaped
        like the batch; ``None`` without any (keys only: no host synchronisation)."""
        mask = None
        for key in self._loss_mask_keys():
            value = tensordict.get(key, None)
            if value is not None:
                value = value.reshape(tensordict.shape)
                mask = value if mask is None else mask & value
        return mask

    def initial_state_cvar(self, tensordict: TensorDictBase, layers=None) -> Tensor:
        """Γ(s₀, a₀, α) with ``a₀ ~ π(·|s₀)`` at the start states the batch carries
        under the ``initial_states`` key (no gradient)."""
        states = self.constraint_signal.initial_states(tensordict)
        return self.safety_head.cvar(self._policy_values(states, layers).safety)

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

    def _data_keys(self) -> list[NestedKey]:
        """The entries of ``in_keys`` a batch must hold (:func:`~wcsac_rl.objectives.inputs.data_keys`)."""
        return data_keys(self)

    @takes_tensordict
    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        check_nonempty_batch(tensordict, type(self).__name__)  # (shapes only: no sync)
        missing = missing_inputs(self, tensordict)  # (keys only: no sync)
        if missing is not None:
            raise KeyError(missing)
        flags = [("next", self.tensor_keys.done), ("next", self.tensor_keys.terminated)]
        check_batch_entries(tensordict, self._data_keys(), flags, type(self).__name__)
        check_critic_inputs(tensordict, self, type(self).__name__)
        if self.check_finite:
            self.check_inputs(tensordict)
        targets = self.compute_targets(tensordict)
        # the fused critics' parameters, once: trainable for the critic losses, detached below
        layers = self.critics.layers(self._online_critics())
        values = self._online_values(tensordict, layers)  # shared by both critic losses
        loss_qvalue, q_metadata = self.qvalue_loss(tensordict, targets, values)
        *safety_terms, safety_metadata = self.safety_loss(tensordict, targets, values)
        detached = None if layers is None else [(w.detach(), b.detach()) for w, b in layers]
        statistic = self._constraint_statistic(tensordict, values.detach(), detached)
        signal = self.constraint_signal.signal(tensordict, statistic)
        loss_actor, actor_metadata = self._actor_loss(tensordict, signal, detached)
        log_prob, signal = actor_metadata["log_prob"], actor_metadata["cvar_constraint"]
        weights = self._maybe_get_priority_weight(tensordict)
        loss_alpha = self._reduce_loss(
            self._alpha_loss(log_prob=log_prob), tensordict=tensordict, weights=weights
        )
        if statistic is None:  # taken at the actor's own actions
            statistic = signal
        loss_kappa = self.kappa_loss(signal, tensordict)
        tensordict.set(self.tensor_keys.priority, q_metadata["td_error"])

        out = {"loss_actor": loss_actor, "loss_qvalue": loss_qvalue, "loss_alpha": loss_alpha}
        out.update(zip(self.safety_head.loss_names, safety_terms))  # (the first or both)
        if loss_kappa is not None:
            out["loss_kappa"] = loss_kappa
        if self.check_finite:
            check_finite_losses(out, tensordict, self.in_keys, type(self).__name__)
        scalars = {
            "alpha": self._alpha,
            "kappa": self.kappa,
            **self.constraint.diagnostics(),  # before this update's step, like κ
            "entropy": -log_prob.mean(),
            **{k: v.mean() for k, v in safety_metadata.items() if v is not None},
            "cvar": statistic.mean(),
            "cost_threshold": self.cost_threshold.clone(),
        }
        if self.kappa_signal != "critic":
            scalars["episode_cvar"] = self.constraint_signal.episode_cvar(tensordict).mean()
            scalars["constraint_cvar"] = signal.mean()
        if self.training:
            # a controller's update (the PID rule's; the gradient rule's does nothing),
            # after this batch's actor loss used the current κ
            self.constraint.step(signal.detach(), self.cost_threshold)
            self.safety_head.adapt(tensordict, self.cost_limit)  # (an adaptive k_ucb)
        if self.reduction == "none":
            td_out = TensorDict(out, batch_size=tensordict.batch_size)
            if self.scalar_output_mode == "non_tensor":
                for key, value in scalars.items():
                    td_out.set_non_tensor(key, value)
        else:
            td_out = TensorDict({**out, **scalars}, batch_size=[])
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
