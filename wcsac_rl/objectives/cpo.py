r"""Constrained Policy Optimization (Achiam et al., ICML 2017) as a TorchRL ``LossModule``.

CPO is a trust-region policy update with a cost constraint. From one on-policy batch:

* reward and cost advantages ``A^r``, ``A^c`` by TorchRL's
  :class:`~torchrl.objectives.value.GAE`, once on ``("next", "reward")`` with
  ``V^r`` and once on ``("next", "cost")`` with ``V^c``;
* the surrogates ``L_r(θ) = E[ρ_θ A^r]`` and ``L_c(θ) = E[ρ_θ A^c]``
  (``ρ_θ = π_θ(a|s) / π_old(a|s)``), their gradients ``g`` and ``b`` at ``θ_old``;
* the Fisher matrix ``H`` (the Hessian of the mean KL(π_old ‖ π_θ) at ``θ_old``)
  only through Fisher-vector products, and ``H⁻¹g``, ``H⁻¹b`` by conjugate gradient;
* the step ``x`` solving the linearised, trust-region problem

  .. math::

     \max_x\; g^\top x \quad\text{s.t.}\quad b^\top x + c \le 0,\quad
     \tfrac12 x^\top H x \le \delta

  by its dual (Achiam et al. 2017, Appendix 10.2), or — when no point of the trust
  region satisfies the linearised constraint — the recovery step
  ``x = −√(2δ / bᵀH⁻¹b) · H⁻¹b`` that reduces the cost as much as the trust region
  allows;
* a backtracking line search on ``θ_old + βʲ x`` accepting the first point whose
  KL is within ``δ``, whose reward surrogate did not decrease (feasible cases
  only) and whose cost surrogate satisfies the constraint
  (``L_c(θ) − L_c(θ_old) ≤ max(−c, 0)``); when none does, ``θ_old`` is kept.

**The cost constraint.** The limit ``d`` is the same episodic, *undiscounted* budget
as for the other algorithms of this kit (``cost_limit``, 15 in the paper). Following
OpenAI's safety-starter-agents (Ray, Achiam & Amodei 2019 — the CPO implementation
of the Safety Gym benchmark, on which the WCSAC authors' code is built):

* ``J_C`` is the mean undiscounted cost of the episodes that *ended in the batch*
  (``("next", "episode_cost")`` where ``("next", "done")``);
* the linearised change of the episodic cost is ``T̄ · (L_c(θ) − L_c(θ_old))``
  with ``T̄`` the mean length of those episodes (the batch-mean surrogate is a
  per-step quantity; ``T̄`` of them make an episode), so the constraint
  ``J_C + T̄ bᵀx ≤ d`` reads ``bᵀx + c ≤ 0`` with ``c = (J_C − d) / T̄``;
* the cost advantage itself is GAE with its own ``(γ_c, λ_c)`` (0.99 / 0.97 there):
  discounting there is variance reduction of the advantage, not a change of the
  constraint; ``cost_gamma=1`` gives the undiscounted advantage.

If no episode ended in the batch, ``J_C`` falls back to the batch's mean per-step cost
× ``max_episode_steps`` and ``T̄`` to ``max_episode_steps``.

**Advantages.** As in safety-starter-agents (and OmniSafe): the reward advantage is
standardised over the batch, the cost advantage is only centred (its scale carries
the constraint's units). Value targets are GAE's λ-returns (TorchRL's convention;
safety-starter-agents regresses on discounted reward-to-go).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators, _reduce, distance_loss
from torchrl.objectives.value import GAE

from wcsac_rl.objectives.budget import validate_cost_limit, validate_max_episode_steps
from wcsac_rl.objectives.checked_loss import CheckedLoss

__all__ = ["CPODirection", "CPOLoss", "conjugate_gradient", "cpo_direction"]

# Numbering of the step's geometry, as in safety-starter-agents (logged as `optim_case`).
CASE_INFEASIBLE_RECOVERY = 0  # θ_old infeasible, no feasible point in the trust region
CASE_INFEASIBLE_DUAL = 1  # θ_old infeasible, the constraint cuts the trust region
CASE_FEASIBLE_DUAL = 2  # θ_old feasible, the constraint cuts the trust region
CASE_FEASIBLE_TRPO = 3  # the whole trust region is feasible: a TRPO step
CASE_NO_COST_GRADIENT = 4  # feasible and b ≈ 0: a TRPO step

_EPS = 1e-8


def conjugate_gradient(
    matvec: Callable[[Tensor], Tensor],
    b: Tensor,
    iters: int = 10,
    residual_tol: float = 1e-10,
) -> Tensor:
    """Approximately solve ``A x = b`` for a symmetric positive-definite ``A``.

    Args:
        matvec: ``v ↦ A v`` (``A`` itself is never formed).
        b: the right-hand side (a flat vector).
        iters: at most this many iterations (exact after ``len(b)`` in exact arithmetic).
        residual_tol: stop once ``‖b − A x‖²`` falls below this.

    >>> A = torch.tensor([[4.0, 1.0], [1.0, 3.0]])
    >>> conjugate_gradient(lambda v: A @ v, torch.tensor([1.0, 2.0]))
    tensor([0.0909, 0.6364])
    """
    x = torch.zeros_like(b)
    residual = b.clone()
    direction = b.clone()
    residual_sq = residual @ residual
    for _ in range(int(iters)):
        if residual_sq <= residual_tol:
            break
        a_dir = matvec(direction)
        curvature = direction @ a_dir
        if curvature <= 0:  # not positive definite along this direction: stop here
            break
        alpha = residual_sq / curvature
        x = x + alpha * direction
        residual = residual - alpha * a_dir
        new_residual_sq = residual @ residual
        direction = residual + (new_residual_sq / residual_sq) * direction
        residual_sq = new_residual_sq
    return x


@dataclass
class CPODirection:
    """The CPO step before the line search: ``θ_new = θ_old + step``.

    Attributes:
        step: the full step ``x``.
        case: the geometry (``0``: infeasible recovery, ``1``: infeasible with a
            feasible part of the trust region, ``2``: feasible with the constraint
            cutting the trust region, ``3``: whole trust region feasible, ``4``:
            feasible and no cost gradient) — safety-starter-agents' numbering.
        lam: the dual variable λ of the trust region (``0`` for the recovery step
            and in the limit of parallel reward and cost gradients).
        nu: the dual variable ν of the cost constraint.
        q, r, s: ``gᵀH⁻¹g``, ``gᵀH⁻¹b``, ``bᵀH⁻¹b``.
        c: the constraint value ``(J_C − d) / T̄`` the step was computed for.
    """

    step: Tensor
    case: int
    lam: float
    nu: float
    q: float
    r: float
    s: float
    c: float

    @property
    def infeasible(self) -> bool:
        """``θ_old`` violates the (linearised) constraint."""
        return self.case in (CASE_INFEASIBLE_RECOVERY, CASE_INFEASIBLE_DUAL)

    @property
    def recovery(self) -> bool:
        """The step is the pure cost-decrease recovery step (reward ignored)."""
        return self.case == CASE_INFEASIBLE_RECOVERY


def cpo_direction(
    reward_grad: Tensor,
    cost_grad: Tensor,
    constraint: float,
    max_kl: float,
    solve: Callable[[Tensor], Tensor],
) -> CPODirection:
    r"""Solve CPO's linearised, trust-region problem for the step ``x``.

    Maximise ``gᵀx`` subject to ``bᵀx + c ≤ 0`` and ``½ xᵀHx ≤ δ``, where
    ``g = reward_grad``, ``b = cost_grad``, ``c = constraint``, ``δ = max_kl`` and
    ``solve(v) ≈ H⁻¹v``. With ``q = gᵀH⁻¹g``, ``r = gᵀH⁻¹b``, ``s = bᵀH⁻¹b``,
    ``A = q − r²/s`` and ``B = 2δ − c²/s``, the dual is
    ``min_{λ>0, ν≥0} (q − 2νr + ν²s)/(2λ) − νc + λδ``; for a given λ the best
    ``ν = max(0, (λc + r)/s)``, and the dual in λ is ``A/(2λ) + λB/2 − rc/s`` where
    ``ν > 0`` and ``q/(2λ) + λδ`` where ``ν = 0``. Its minimiser over each piece
    (``√(A/B)``, ``√(q/2δ)``), projected onto the piece's interval, and the better
    of the two give ``λ*, ν*`` and ``x = H⁻¹(g − ν*b)/λ*``. ``B < 0`` means the
    constraint's boundary misses the trust region: with ``c < 0`` every point is
    feasible (a TRPO step), with ``c ≥ 0`` none is, and the step is
    ``x = −√(2δ/s) H⁻¹b`` (infeasible recovery).

    >>> g, b = torch.tensor([1.0, 0.0]), torch.tensor([0.0, 1.0])
    >>> d = cpo_direction(g, b, -2.0, 0.5, solve=lambda v: v)  # H = I
    >>> d.case, d.step  # the constraint is far: the trust-region (TRPO) step along g
    (3, tensor([1., 0.]))
    """
    g, b, c, delta = reward_grad, cost_grad, float(constraint), float(max_kl)
    v = solve(g)  # H⁻¹ g
    q = max(float(g @ v), 0.0)
    w = solve(b)  # H⁻¹ b
    r = float(g @ w)
    s = float(b @ w)
    if float(b @ b) <= _EPS or s <= _EPS:  # no (measurable) cost gradient
        if c < 0:  # feasible: the constraint plays no part, a TRPO step
            lam = math.sqrt(q / (2 * delta))
            step = v / (lam + _EPS)
            return CPODirection(step, CASE_NO_COST_GRADIENT, lam, 0.0, q, r, s, c)
        # infeasible, and no direction lowers the linearised cost: stay
        return CPODirection(torch.zeros_like(g), CASE_INFEASIBLE_RECOVERY, 0.0, 0.0, q, r, s, c)
    A = max(q - r * r / s, 0.0)  # ≥ 0 by Cauchy-Schwarz
    B = 2 * delta - c * c / s
    if B < 0 and c < 0:
        lam = math.sqrt(q / (2 * delta))
        return CPODirection(v / (lam + _EPS), CASE_FEASIBLE_TRPO, lam, 0.0, q, r, s, c)
    if B < 0:
        nu = math.sqrt(2 * delta / s)
        return CPODirection(-nu * w, CASE_INFEASIBLE_RECOVERY, 0.0, nu, q, r, s, c)

    # ν > 0 exactly where λc + r > 0: split λ > 0 at λ₀ = −r/c.
    if c < 0:
        nu_positive = (0.0, -r / c) if r > 0 else None
        nu_zero = (max(0.0, -r / c), math.inf)
    elif c > 0:
        nu_positive = (max(0.0, -r / c), math.inf)
        nu_zero = (0.0, -r / c) if r < 0 else None
    else:
        nu_positive, nu_zero = ((0.0, math.inf), None) if r > 0 else (None, (0.0, math.inf))

    def clip(x: float, interval: tuple[float, float]) -> float:
        return min(max(x, interval[0]), interval[1])

    # (dual value, λ, piece); the dual is convex in λ, so the better projected
    # minimiser of the two pieces is the global one.
    candidates: list[tuple[float, float, str]] = []
    if nu_positive is not None:
        lam_a = clip(math.sqrt(A / B) if B > 0 else math.inf, nu_positive)
        if 0 < lam_a < math.inf:
            candidates.append((A / (2 * lam_a) + lam_a * B / 2 - r * c / s, lam_a, "a"))
        elif lam_a == 0 and A == 0:  # g ∥ b: the dual's infimum is its λ → 0 limit
            candidates.append((-r * c / s, 0.0, "a"))
    if nu_zero is not None:
        lam_b = clip(math.sqrt(q / (2 * delta)), nu_zero)
        if 0 < lam_b < math.inf:
            candidates.append((q / (2 * lam_b) + lam_b * delta, lam_b, "b"))
    case = CASE_FEASIBLE_DUAL if c < 0 else CASE_INFEASIBLE_DUAL
    if not candidates:  # degenerate (g ≈ 0 and c = 0): nothing to gain
        return CPODirection(torch.zeros_like(g), case, 0.0, 0.0, q, r, s, c)
    _, lam, piece = min(candidates)
    if piece == "b":
        return CPODirection(v / lam, case, lam, 0.0, q, r, s, c)
    nu = (lam * c + r) / s
    # x = H⁻¹(g − νb)/λ = u/λ − (c/s) H⁻¹b with u = H⁻¹g − (r/s) H⁻¹b (‖u‖²_H = A):
    # at A = 0 (reward and cost gradients parallel) only the second term remains —
    # the point of the constraint's boundary nearest to θ_old.
    u = v - (r / s) * w
    step = -(c / s) * w if lam == 0 else u / lam - (c / s) * w
    return CPODirection(step, case, lam, nu, q, r, s, c)


class CPOLoss(CheckedLoss, LossModule):
    r"""Constrained Policy Optimization: surrogates, value losses and the CPO policy step.

    CPO's policy update is not a gradient step, so this loss has two faces:

    * :meth:`forward` returns the TorchRL-style differentiable terms at the current
      parameters (taken as ``θ_old``): ``loss_objective`` (``−L_r``; its gradient is
      ``−g``), ``loss_cost_objective`` (``L_c``; gradient ``b``), ``loss_value`` and
      ``loss_cost_value`` (squared errors of ``V^r`` and ``V^c`` to their GAE
      λ-returns), plus ``entropy``. Back-propagate only the value losses (the policy
      is changed by :meth:`policy_step`).
    * :meth:`policy_step` performs the CPO update of the actor's parameters in place
      (conjugate gradient on the Fisher-vector product, the dual solution of the
      constrained trust-region step, the backtracking line search) and returns its
      diagnostics.

    Call :meth:`compute_advantages` first on the (time-ordered, ``[*B, T]``) batch:
    it runs the reward and cost GAE and writes ``advantage``, ``value_target``,
    ``cost_advantage`` and ``cost_value_target``.

    Args:
        actor_network (ProbabilisticTensorDictSequential): a diagonal-Gaussian policy
            (``get_dist`` returns a ``Normal`` or an ``Independent(Normal)``, e.g.
            :func:`wcsac_rl.modules.gaussian_actor.make_gaussian_actor`). Its
            parameters are updated in place, so a collector holding it sees the new
            policy. The stored action must be the sampled one (unclipped: the env
            clips), or the likelihood ratios are wrong.
        value_network (TensorDictModule): ``V^r(s)`` writing ``"state_value"``.
        cost_value_network (TensorDictModule): ``V^c(s)`` writing ``"state_cost_value"``.

    Keyword Args:
        cost_limit (float): the episodic, undiscounted cost budget ``d``. Default 15.
        max_episode_steps (int, optional): the episode length, used only when no
            episode ended in a batch (see the module docstring).
        max_kl (float): the trust region ``δ`` on the mean KL(π_old ‖ π). Default 0.01.
        damping (float): ``H + damping·I`` in the conjugate gradient. Default 0.1.
        cg_iters (int): conjugate-gradient iterations. Default 10.
        backtrack_iters (int): line-search points tried. Default 10.
        backtrack_coeff (float): the line search's shrink factor β. Default 0.8.
        entropy_coeff (float): entropy bonus added to the reward surrogate. Default 0.
        normalize_advantage (bool): standardise ``A^r`` over the batch. Default True.
        center_cost_advantage (bool): subtract the batch mean of ``A^c``. Default True.
        reduction (str): ``"mean"`` (default), ``"sum"`` or ``"none"`` for
            :meth:`forward`'s terms.

    The defaults (and the GAE defaults γ = γ_c = 0.99, λ = λ_c = 0.97) are those of
    safety-starter-agents. Change the GAE with :meth:`make_value_estimator`.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from torchrl.data import Bounded
        >>> from wcsac_rl.modules.gaussian_actor import make_gaussian_actor, make_state_value
        >>> _ = torch.manual_seed(0)
        >>> actor = make_gaussian_actor(3, Bounded(-1.0, 1.0, shape=(2,)), width=16)
        >>> loss = CPOLoss(actor, make_state_value(3, width=16),
        ...                make_state_value(3, out_key="state_cost_value", width=16),
        ...                cost_limit=5.0, max_episode_steps=10)
        >>> T = 10
        >>> done = torch.zeros(4, T, 1, dtype=torch.bool)
        >>> done[:, -1] = True
        >>> batch = TensorDict({
        ...     "observation": torch.randn(4, T, 3), "action": torch.randn(4, T, 2),
        ...     "next": {"observation": torch.randn(4, T, 3), "reward": torch.randn(4, T, 1),
        ...              "cost": torch.ones(4, T, 1), "done": done, "terminated": done,
        ...              "episode_cost": torch.full((4, T, 1), 10.0),
        ...              "step_count": torch.full((4, T, 1), T)}}, [4, T])
        >>> _ = loss.compute_advantages(batch)
        >>> info = loss.policy_step(batch)  # J_C = 10 > d = 5: the step lowers the cost
        >>> bool(info["infeasible"]), float(info["constraint"])
        (True, 5.0)
        >>> bool(info["cost_surrogate_change"] <= 0) and bool(info["kl"] <= 0.01)
        True
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys the loss reads and writes (change them with ``set_keys``).

        Attributes:
            advantage: reward advantage written by the reward GAE. ``"advantage"``.
            value_target: λ-return target of ``V^r``. ``"value_target"``.
            value: ``V^r`` output key. ``"state_value"``.
            cost_advantage: cost advantage written by the cost GAE. ``"cost_advantage"``.
            cost_value_target: λ-return target of ``V^c``. ``"cost_value_target"``.
            cost_value: ``V^c`` output key. ``"state_cost_value"``.
            action: the taken (unclipped) action. ``"action"``.
            reward: per-step reward, read at ``("next", reward)``. ``"reward"``.
            cost: per-step cost, read at ``("next", cost)``. ``"cost"``.
            done: episode end, read at ``("next", done)``. ``"done"``.
            terminated: true termination, read at ``("next", terminated)``. ``"terminated"``.
            episode_cost: running undiscounted episode cost (``CostSum``), read at
                ``("next", episode_cost)`` where done. ``"episode_cost"``.
            step_count: episode step counter (``StepCounter``), read at
                ``("next", step_count)`` where done. ``"step_count"``.
        """

        advantage: NestedKey = "advantage"
        value_target: NestedKey = "value_target"
        value: NestedKey = "state_value"
        cost_advantage: NestedKey = "cost_advantage"
        cost_value_target: NestedKey = "cost_value_target"
        cost_value: NestedKey = "state_cost_value"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        cost: NestedKey = "cost"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        episode_cost: NestedKey = "episode_cost"
        step_count: NestedKey = "step_count"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.GAE

    actor_network: ProbabilisticTensorDictSequential
    value_network: TensorDictModule
    cost_value_network: TensorDictModule

    #: keys of :meth:`policy_step`'s diagnostics
    STEP_KEYS = (
        "kl",
        "surrogate_improvement",
        "cost_surrogate_change",
        "constraint",
        "episode_cost_estimate",
        "step_fraction",
        "line_search_steps",
        "accepted",
        "infeasible",
        "recovery",
        "optim_case",
        "lagrange_lambda",
        "lagrange_nu",
        "entropy",
    )

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        value_network: TensorDictModule,
        cost_value_network: TensorDictModule,
        *,
        cost_limit: float = 15.0,
        max_episode_steps: int | None = None,
        max_kl: float = 0.01,
        damping: float = 0.1,
        cg_iters: int = 10,
        backtrack_iters: int = 10,
        backtrack_coeff: float = 0.8,
        entropy_coeff: float = 0.0,
        normalize_advantage: bool = True,
        center_cost_advantage: bool = True,
        reduction: str = "mean",
    ) -> None:
        super().__init__()
        validate_cost_limit(cost_limit)
        if not max_kl > 0:
            raise ValueError(f"max_kl (the trust region δ) must be > 0, got {max_kl}")
        if damping < 0:
            raise ValueError(f"damping must be >= 0, got {damping}")
        if int(cg_iters) < 1 or int(backtrack_iters) < 1:
            raise ValueError(
                f"cg_iters and backtrack_iters must be >= 1, got {cg_iters} and {backtrack_iters}"
            )
        if not 0 < backtrack_coeff < 1:
            raise ValueError(f"backtrack_coeff must be in (0, 1), got {backtrack_coeff}")
        if max_episode_steps is not None:
            validate_max_episode_steps(max_episode_steps)
        if reduction not in ("mean", "sum", "none"):
            raise ValueError(f"reduction must be 'mean', 'sum' or 'none', got {reduction!r}")
        # No target networks: the networks are plain submodules, and the actor's
        # parameters are the collector's policy parameters.
        self.actor_network = actor_network
        self.value_network = value_network
        self.cost_value_network = cost_value_network
        self.cost_limit = float(cost_limit)
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self.max_kl = float(max_kl)
        self.damping = float(damping)
        self.cg_iters = int(cg_iters)
        self.backtrack_iters = int(backtrack_iters)
        self.backtrack_coeff = float(backtrack_coeff)
        self.entropy_coeff = float(entropy_coeff)
        self.normalize_advantage = bool(normalize_advantage)
        self.center_cost_advantage = bool(center_cost_advantage)
        self.reduction = reduction
        self._cost_value_estimator: GAE | None = None
        self.make_value_estimator()

    # ------------------------------------------------------------ keys / GAE
    @property
    def in_keys(self) -> list[NestedKey]:
        keys = {*self.actor_network.in_keys, *self.value_network.in_keys}
        keys |= {*self.cost_value_network.in_keys, self.tensor_keys.action}
        for key in ("reward", "cost", "done", "terminated"):
            keys.add(("next", getattr(self.tensor_keys, key)))
        return sorted(keys, key=str)

    @property
    def out_keys(self) -> list[str]:
        return [
            "loss_objective",
            "loss_cost_objective",
            "loss_value",
            "loss_cost_value",
            "entropy",
        ]

    def make_value_estimator(
        self,
        value_type: ValueEstimators | None = None,
        *,
        gamma: float = 0.99,
        lmbda: float = 0.97,
        cost_gamma: float | None = None,
        cost_lmbda: float | None = None,
        **hyperparams,
    ) -> CPOLoss:
        """Build the reward and cost GAE estimators (only ``ValueEstimators.GAE``).

        Args:
            value_type: ``None`` or ``ValueEstimators.GAE``.
            gamma, lmbda: the reward GAE's discount and λ.
            cost_gamma, cost_lmbda: the cost GAE's (default: ``gamma`` / ``lmbda``).
            **hyperparams: passed to both :class:`~torchrl.objectives.value.GAE`.
        """
        if value_type not in (None, ValueEstimators.GAE):
            raise NotImplementedError(
                f"CPOLoss supports ValueEstimators.GAE only, got {value_type}"
            )
        for name, value in (("gamma", gamma), ("lmbda", lmbda)):
            if not 0.0 <= float(value) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        cost_gamma = gamma if cost_gamma is None else cost_gamma
        cost_lmbda = lmbda if cost_lmbda is None else cost_lmbda
        for name, value in (("cost_gamma", cost_gamma), ("cost_lmbda", cost_lmbda)):
            if not 0.0 <= float(value) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        self.value_type = ValueEstimators.GAE
        reward_gae = GAE(
            gamma=float(gamma), lmbda=float(lmbda), value_network=self.value_network, **hyperparams
        )
        cost_gae = GAE(
            gamma=float(cost_gamma),
            lmbda=float(cost_lmbda),
            value_network=self.cost_value_network,
            **hyperparams,
        )
        # Kept out of the module registry: the estimators hold no learned state, and a
        # checkpoint must not override the configured γ/λ on resume.
        self.__dict__["_value_estimator"] = reward_gae
        self.__dict__["_cost_value_estimator"] = cost_gae
        self._forward_value_estimator_keys()
        return self

    @property
    def cost_value_estimator(self) -> GAE:
        """The GAE on ``("next", cost)`` with ``V^c``."""
        return self._cost_value_estimator

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        keys = self.tensor_keys
        if getattr(self, "_value_estimator", None) is not None:
            self._value_estimator.set_keys(
                advantage=keys.advantage,
                value_target=keys.value_target,
                value=keys.value,
                reward=keys.reward,
                done=keys.done,
                terminated=keys.terminated,
            )
        if getattr(self, "_cost_value_estimator", None) is not None:
            self._cost_value_estimator.set_keys(
                advantage=keys.cost_advantage,
                value_target=keys.cost_value_target,
                value=keys.cost_value,
                reward=keys.cost,
                done=keys.done,
                terminated=keys.terminated,
            )

    @torch.no_grad()
    def compute_advantages(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Run the reward and cost GAE on a ``[*B, T]`` batch (in place); returns it.

        Writes ``advantage``, ``value_target``, ``cost_advantage``,
        ``cost_value_target`` (and the value estimates). Values already in the batch
        are recomputed with the current networks.
        """
        keys = self.tensor_keys
        if tensordict.get(("next", keys.cost), None) is None:
            raise KeyError(
                f"CPOLoss needs a per-step cost at {('next', keys.cost)!r}; build the env with "
                "wcsac_rl.envs.make_env or point the loss at your key with set_keys(cost=...)"
            )
        for key in (keys.value, keys.cost_value):
            for nested in (key, ("next", key)):
                if tensordict.get(nested, None) is not None:
                    del tensordict[nested]
        self.value_estimator(tensordict)
        self.cost_value_estimator(tensordict)
        return tensordict

    # ------------------------------------------------------------ surrogates
    def _check_advantages(self, tensordict: TensorDictBase) -> None:
        keys = self.tensor_keys
        if (
            tensordict.get(keys.advantage, None) is None
            or tensordict.get(keys.cost_advantage, None) is None
        ):
            raise KeyError(
                f"{keys.advantage!r} / {keys.cost_advantage!r} missing: call "
                "loss.compute_advantages(batch) on the time-ordered batch first"
            )

    def _advantages(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor]:
        """Reward advantage (standardised) and cost advantage (centred), detached."""
        self._check_advantages(tensordict)
        adv = tensordict.get(self.tensor_keys.advantage).detach().squeeze(-1)
        cadv = tensordict.get(self.tensor_keys.cost_advantage).detach().squeeze(-1)
        if self.normalize_advantage and adv.numel() > 1:
            adv = (adv - adv.mean()) / adv.std().clamp_min(1e-8)
        if self.center_cost_advantage:
            cadv = cadv - cadv.mean()
        return adv, cadv

    def _dist(self, tensordict: TensorDictBase) -> torch.distributions.Distribution:
        return self.actor_network.get_dist(tensordict.select(*self.actor_network.in_keys))

    def _surrogates(
        self,
        dist: torch.distributions.Distribution,
        action: Tensor,
        old_log_prob: Tensor,
        adv: Tensor,
        cadv: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Per-sample ``ρ A^r + entropy bonus``, ``ρ A^c`` and entropy."""
        ratio = (dist.log_prob(action) - old_log_prob).exp()
        entropy = dist.entropy()
        return ratio * adv + self.entropy_coeff * entropy, ratio * cadv, entropy

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The differentiable terms at the current parameters (see the class docstring)."""
        keys = self.tensor_keys
        adv, cadv = self._advantages(tensordict)
        dist = self._dist(tensordict)
        action = tensordict.get(keys.action)
        log_prob = dist.log_prob(action)
        reward_sur, cost_sur, entropy = self._surrogates(dist, action, log_prob.detach(), adv, cadv)
        loss_value, loss_cost_value = self.value_loss(tensordict, reduction=self.reduction)
        return TensorDict(
            {
                "loss_objective": _reduce(-reward_sur, self.reduction),
                "loss_cost_objective": _reduce(cost_sur, self.reduction),
                "loss_value": loss_value,
                "loss_cost_value": loss_cost_value,
                "entropy": _reduce(entropy.detach(), self.reduction),
            },
            batch_size=[] if self.reduction != "none" else tensordict.batch_size,
        )

    def value_loss(
        self, tensordict: TensorDictBase, *, reduction: str = "mean"
    ) -> tuple[Tensor, Tensor]:
        """Squared errors of ``V^r`` and ``V^c`` to their λ-return targets."""
        keys = self.tensor_keys
        if tensordict.get(keys.value_target, None) is None:
            self._check_advantages(tensordict)
        losses = []
        for net, target_key, value_key in (
            (self.value_network, keys.value_target, keys.value),
            (self.cost_value_network, keys.cost_value_target, keys.cost_value),
        ):
            value = net(tensordict.select(*net.in_keys)).get(value_key)
            target = tensordict.get(target_key).detach()
            losses.append(_reduce(distance_loss(value, target, "l2").squeeze(-1), reduction))
        return losses[0], losses[1]

    # ------------------------------------------------------------ parameters
    def _actor_params(self) -> list[Tensor]:
        return [p for p in self.actor_network.parameters() if p.requires_grad]

    def _flat_params(self) -> Tensor:
        return torch.cat([p.detach().reshape(-1) for p in self._actor_params()])

    @torch.no_grad()
    def _set_flat_params(self, flat: Tensor) -> None:
        offset = 0
        for p in self._actor_params():
            n = p.numel()
            p.copy_(flat[offset : offset + n].view_as(p))
            offset += n

    def _flat_grad(self, scalar: Tensor, **kwargs) -> Tensor:
        grads = torch.autograd.grad(scalar, self._actor_params(), **kwargs)
        return torch.cat([g.reshape(-1) for g in grads])

    @staticmethod
    def _detached_dist(dist: torch.distributions.Distribution) -> torch.distributions.Distribution:
        base = dist.base_dist if isinstance(dist, torch.distributions.Independent) else dist
        if not isinstance(base, torch.distributions.Normal):
            raise TypeError(
                f"CPOLoss's KL needs a (diagonal) Normal policy, got {type(dist).__name__}"
            )
        normal = torch.distributions.Normal(base.loc.detach(), base.scale.detach())
        if isinstance(dist, torch.distributions.Independent):
            return torch.distributions.Independent(normal, dist.reinterpreted_batch_ndims)
        return normal

    def mean_kl(
        self,
        tensordict: TensorDictBase,
        old_dist: torch.distributions.Distribution,
    ) -> Tensor:
        """Mean over the batch of ``KL(old_dist ‖ π_θ)`` at the current parameters."""
        return torch.distributions.kl_divergence(old_dist, self._dist(tensordict)).mean()

    def _fisher_operator(
        self, tensordict: TensorDictBase, old_dist: torch.distributions.Distribution
    ) -> Callable[[Tensor], Tensor]:
        """``v ↦ (H + damping·I) v`` with ``H`` the Hessian of the mean KL at ``θ_old``.

        The KL's gradient graph is built once and reused for every product
        (double backward: ``∇_θ ((∇_θ KL)ᵀ v)``).
        """
        kl_grad = self._flat_grad(self.mean_kl(tensordict, old_dist), create_graph=True)

        def fvp(vector: Tensor) -> Tensor:
            hv = self._flat_grad(kl_grad @ vector, retain_graph=True)
            return hv + self.damping * vector

        return fvp

    def fisher_vector_product(self, tensordict: TensorDictBase, vector: Tensor) -> Tensor:
        """``(H + damping·I) v``: ``H`` is the Hessian of the mean KL(π_θ ‖ π_θ') at θ' = θ.

        ``vector`` is flat, ordered like ``actor_network.parameters()``.
        """
        old_dist = self._detached_dist(self._dist(tensordict))
        return self._fisher_operator(tensordict, old_dist)(vector)

    # ------------------------------------------------------------ CPO step
    def episode_cost_estimate(self, tensordict: TensorDictBase) -> tuple[float, float, int]:
        """``(J_C, T̄, episodes)``: mean undiscounted cost and length of the batch's episodes.

        Reads ``("next", episode_cost)`` and ``("next", step_count)`` where
        ``("next", done)``. With no finished episode: the mean per-step cost ×
        ``max_episode_steps`` and ``T̄ = max_episode_steps``.
        """
        keys = self.tensor_keys
        nxt = tensordict.get("next")
        done = nxt.get(keys.done).reshape(-1)
        if bool(done.any()):
            costs = nxt.get(keys.episode_cost, None)
            lengths = nxt.get(keys.step_count, None)
            if costs is None or lengths is None:
                raise KeyError(
                    f"CPOLoss estimates J_C from {('next', keys.episode_cost)!r} and "
                    f"{('next', keys.step_count)!r} (TorchRL's CostSum/StepCounter, as in "
                    "wcsac_rl.envs.make_env); pass episode_cost= and episode_length= to "
                    "policy_step instead"
                )
            costs = costs.reshape(-1)[done].float()
            lengths = lengths.reshape(-1)[done].float()
            return float(costs.mean()), float(lengths.mean()), int(done.sum())
        if self.max_episode_steps is None:
            raise ValueError(
                "no episode ended in this batch and max_episode_steps is unknown: pass "
                "max_episode_steps to CPOLoss (or episode_cost= / episode_length= to policy_step)"
            )
        per_step = float(nxt.get(keys.cost).float().mean())
        return per_step * self.max_episode_steps, float(self.max_episode_steps), 0

    def policy_step(
        self,
        tensordict: TensorDictBase,
        *,
        episode_cost: float | None = None,
        episode_length: float | None = None,
    ) -> TensorDictBase:
        """One CPO update of the actor, in place; returns its diagnostics.

        Args:
            tensordict: the on-policy batch, after :meth:`compute_advantages`.
            episode_cost: ``J_C`` (default: :meth:`episode_cost_estimate`).
            episode_length: ``T̄`` (default: :meth:`episode_cost_estimate`).

        Returns:
            A TensorDict of scalars (:attr:`STEP_KEYS`): ``kl`` (of the accepted step),
            ``surrogate_improvement`` (``L_r`` new − old), ``cost_surrogate_change``
            (``L_c`` new − old), ``constraint`` (``J_C − d``, episodic),
            ``episode_cost_estimate`` (``J_C``), ``step_fraction`` (``βʲ`` of the
            accepted point, 0 if none), ``line_search_steps`` (``j``; ``backtrack_iters``
            if none was accepted), ``accepted``, ``infeasible`` (θ_old violates the
            constraint), ``recovery`` (the pure cost-decrease step was taken),
            ``optim_case`` (see :class:`CPODirection`), ``lagrange_lambda``,
            ``lagrange_nu`` and ``entropy`` (before the step).
        """
        td = tensordict.reshape(-1)
        adv, cadv = self._advantages(td)
        action = td.get(self.tensor_keys.action)
        if episode_cost is None or episode_length is None:
            est_cost, est_length, _ = self.episode_cost_estimate(td)
            episode_cost = est_cost if episode_cost is None else episode_cost
            episode_length = est_length if episode_length is None else episode_length
        if not episode_length > 0:
            raise ValueError(f"episode_length must be > 0, got {episode_length}")
        constraint = float(episode_cost) - self.cost_limit
        c = constraint / float(episode_length)

        dist = self._dist(td)
        old_dist = self._detached_dist(dist)
        old_log_prob = old_dist.log_prob(action)
        reward_sur, cost_sur, entropy = self._surrogates(dist, action, old_log_prob, adv, cadv)
        reward_old, cost_old = reward_sur.mean(), cost_sur.mean()
        g = self._flat_grad(reward_old, retain_graph=True)
        b = self._flat_grad(cost_old)
        fvp = self._fisher_operator(td, old_dist)
        direction = cpo_direction(
            g,
            b,
            c,
            self.max_kl,
            lambda vec: conjugate_gradient(fvp, vec, self.cg_iters),
        )

        old_params = self._flat_params()
        accepted, steps, kl = False, self.backtrack_iters, torch.zeros(())
        reward_new, cost_new = reward_old.detach(), cost_old.detach()
        with torch.no_grad():
            for j in range(self.backtrack_iters):
                self._set_flat_params(old_params + self.backtrack_coeff**j * direction.step)
                new_dist = self._dist(td)
                kl = torch.distributions.kl_divergence(old_dist, new_dist).mean()
                r_sur, c_sur, _ = self._surrogates(new_dist, action, old_log_prob, adv, cadv)
                reward_new, cost_new = r_sur.mean(), c_sur.mean()
                improves = direction.infeasible or bool(reward_new >= reward_old)
                within_cost = bool(cost_new - cost_old <= max(-c, 0.0))
                if bool(kl <= self.max_kl) and improves and within_cost:
                    accepted, steps = True, j
                    break
            if not accepted:
                self._set_flat_params(old_params)
                kl = torch.zeros(())
                reward_new, cost_new = reward_old.detach(), cost_old.detach()

        return TensorDict(
            {
                "kl": kl.detach(),
                "surrogate_improvement": (reward_new - reward_old).detach(),
                "cost_surrogate_change": (cost_new - cost_old).detach(),
                "constraint": torch.tensor(constraint),
                "episode_cost_estimate": torch.tensor(float(episode_cost)),
                "step_fraction": torch.tensor(self.backtrack_coeff**steps if accepted else 0.0),
                "line_search_steps": torch.tensor(float(steps)),
                "accepted": torch.tensor(float(accepted)),
                "infeasible": torch.tensor(float(direction.infeasible)),
                "recovery": torch.tensor(float(direction.recovery)),
                "optim_case": torch.tensor(float(direction.case)),
                "lagrange_lambda": torch.tensor(direction.lam),
                "lagrange_nu": torch.tensor(direction.nu),
                "entropy": entropy.mean().detach(),
            },
            batch_size=[],
        )
