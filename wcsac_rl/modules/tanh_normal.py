"""Sample the kit's tanh-Normal actor without building a distribution object.

Every WCSAC update draws two reparametrised actions, ``a ~ π(·|s)`` for the actor
loss and ``a' ~ π(·|s')`` for the TD targets. Through TorchRL that means swapping
the parameters into the module, running it on a tensordict, building a
``TanhNormal`` (a ``TransformedDistribution`` over an ``Independent(Normal)``)
and scoring the draw, which costs more than the actor's matrix products. When
the actor is the one :func:`wcsac_rl.modules.make_actor` builds, the same draw
and score can be computed from the parameters directly: same noise stream, same
formulas, same gradients (tested against the TorchRL path).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import (
    InteractionType,
    ProbabilisticTensorDictSequential,
    TensorDictModule,
    TensorDictModuleBase,
)
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torch.nn import functional as F
from torchrl.envs.utils import exploration_type
from torchrl.modules import TanhNormal
from torchrl.modules.distributions.utils import safetanh_noeps

from wcsac_rl.modules.actor import (
    ClampedLogStdNormalParams,
    SyncFreeTanhNormal,
    clamped_normal_params,
)
from wcsac_rl.modules.mlp import MLPLayout, evaluate_mlp, mlp_layout

__all__ = [
    "TanhNormalActorPlan",
    "TanhNormalPolicy",
    "sample_tanh_normal",
    "tanh_normal_actor_plan",
]

_HALF_LOG_2PI = math.log(math.sqrt(2 * math.pi))
_LOG_2 = math.log(2.0)


@dataclass(frozen=True)
class TanhNormalActorPlan:
    """What :func:`sample_tanh_normal` needs to know about a ``make_actor`` actor.

    Attributes:
        observation_key: the key the actor reads.
        layout: its MLP (keys are relative to the actor's parameter tensordict).
        log_std_min, log_std_max: the clamp of the Gaussian's log-std.
        low, high: the action bounds, or ``None`` for ``[-1, 1]`` (no affine map).
    """

    observation_key: NestedKey
    layout: MLPLayout
    log_std_min: float
    log_std_max: float
    low: Tensor | None
    high: Tensor | None

    def to_bounds(self, squashed: Tensor) -> tuple[Tensor, Tensor | None]:
        """Map a tanh output in ``[-1, 1]`` to ``[low, high]`` (TorchRL's affine map).

        Returns the action and the half range ``(high − low) / 2`` (whose log is the
        map's log-Jacobian), or ``None`` for ``[-1, 1]`` (no map).
        """
        if self.low is None:
            return squashed, None
        low, high = self.low.to(squashed), self.high.to(squashed)
        half_range = (high - low) / 2
        return (high + low) / 2 + half_range * squashed, half_range


def tanh_normal_actor_plan(actor: nn.Module) -> TanhNormalActorPlan | None:
    """The plan for ``actor`` if it is built like :func:`~wcsac_rl.modules.make_actor`, else ``None``.

    Recognised: a ``ProbabilisticTensorDictSequential`` of (1) a ``TensorDictModule``
    reading one key and writing ``loc`` and ``scale`` through
    ``nn.Sequential(<plain MLP>, ClampedLogStdNormalParams)`` and (2) a
    ``TanhNormal`` (TorchRL's or :class:`~wcsac_rl.modules.actor.SyncFreeTanhNormal`)
    with default options apart from ``low``/``high``.
    """
    if not isinstance(actor, ProbabilisticTensorDictSequential) or len(actor.module) != 2:
        return None
    params_module, dist_module = actor.module
    if type(params_module) is not TensorDictModule or len(params_module.in_keys) != 1:
        return None
    net = params_module.module
    if not (
        isinstance(net, nn.Sequential)
        and len(net) == 2
        and type(net[1]) is ClampedLogStdNormalParams
    ):
        return None
    layout = mlp_layout(net[0], ("module", "0", "module", "0"))
    if layout is None:
        return None
    if getattr(dist_module, "distribution_class", None) not in (TanhNormal, SyncFreeTanhNormal):
        return None
    kwargs = dict(getattr(dist_module, "distribution_kwargs", {}) or {})
    if set(kwargs) - {"low", "high"}:
        return None
    dist_in = dist_module.in_keys
    if isinstance(dist_in, dict):
        dist_in = [dist_in.get("loc"), dist_in.get("scale")]
    if list(params_module.out_keys) != list(dist_in) or len(dist_in) != 2:
        return None
    low, high = kwargs.get("low", -1.0), kwargs.get("high", 1.0)
    low = torch.as_tensor(low, dtype=torch.get_default_dtype())
    high = torch.as_tensor(high, dtype=torch.get_default_dtype())
    trivial = bool((low == -1.0).all() and (high == 1.0).all())
    return TanhNormalActorPlan(
        observation_key=params_module.in_keys[0],
        layout=layout,
        log_std_min=net[1].log_std_min,
        log_std_max=net[1].log_std_max,
        low=None if trivial else low,
        high=None if trivial else high,
    )


def sample_tanh_normal(
    plan: TanhNormalActorPlan, params: TensorDictBase, observation: Tensor
) -> tuple[Tensor, Tensor]:
    """A reparametrised draw ``a = tanh(μ + σ ε)`` (mapped to ``[low, high]``) and ``log π(a|s)``.

    Equal to TorchRL's ``TanhNormal(...).rsample_and_log_prob()`` at the same
    random state: the pre-tanh value is scored (not recovered by ``atanh``), the
    tanh is TorchRL's saturation-safe one.
    """
    out = evaluate_mlp(observation, params, plan.layout)
    loc, scale = clamped_normal_params(out, plan.log_std_min, plan.log_std_max)
    eps = torch.randn_like(loc)
    pre_tanh = loc + eps * scale
    # the Normal's log-density and the tanh's log-Jacobian, summed over the action
    # dimensions separately (the order TorchRL's distribution sums them in)
    normal_log_prob = -((pre_tanh - loc) ** 2) / (2 * scale**2) - scale.log() - _HALF_LOG_2PI
    log_det = 2.0 * (_LOG_2 - pre_tanh - F.softplus(-2.0 * pre_tanh))
    action, half_range = plan.to_bounds(safetanh_noeps(pre_tanh))
    if half_range is not None:
        log_det = log_det + half_range.abs().log()
    return action, normal_log_prob.sum(-1) - log_det.sum(-1)


class TanhNormalPolicy(TensorDictModuleBase):
    """A :func:`~wcsac_rl.modules.make_actor` actor acting without distribution objects.

    For collection and test episodes: under ``ExplorationType.RANDOM`` (the actor's
    default) it writes ``loc``, ``scale`` and a sampled action, under
    ``DETERMINISTIC`` ``tanh(loc)`` (mapped to the action bounds), exactly what the
    wrapped ``ProbabilisticActor`` writes at the same random state (tested), for a
    fraction of its overhead per call; any other exploration type is handed to the
    actor itself. It reads the actor's current parameters at every call, so it
    follows training.

    Args:
        actor: an actor built like :func:`~wcsac_rl.modules.make_actor`.

    Raises:
        ValueError: ``actor`` is not built like ``make_actor``'s.
    """

    def __init__(self, actor: ProbabilisticTensorDictSequential) -> None:
        super().__init__()
        plan = tanh_normal_actor_plan(actor)
        if plan is None:
            raise ValueError(
                "TanhNormalPolicy needs an actor built like wcsac_rl.modules.make_actor"
            )
        self.actor = actor
        self._plan = plan
        self._net = actor.module[0].module  # Sequential(MLP, ClampedLogStdNormalParams)
        self._loc_key, self._scale_key = actor.module[0].out_keys
        self._action_key = actor.out_keys[-1]
        self.in_keys = [plan.observation_key]
        self.out_keys = [self._loc_key, self._scale_key, self._action_key]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        kind = exploration_type() or self.actor.module[-1].default_interaction_type
        if kind not in (InteractionType.RANDOM, InteractionType.DETERMINISTIC):
            return self.actor(tensordict)
        loc, scale = self._net(tensordict.get(self._plan.observation_key))
        pre_tanh = (
            loc if kind is InteractionType.DETERMINISTIC else loc + torch.randn_like(loc) * scale
        )
        action, _ = self._plan.to_bounds(safetanh_noeps(pre_tanh))
        tensordict.set(self._loc_key, loc)
        tensordict.set(self._scale_key, scale)
        tensordict.set(self._action_key, action)
        return tensordict

    @property
    def observation_key(self) -> NestedKey:
        """The key the actor reads."""
        return self._plan.observation_key

    @property
    def action_key(self) -> NestedKey:
        """The key the policy writes its action to."""
        return self._action_key

    def draw(self, tensordict: TensorDictBase, count: int) -> Tensor:
        """``count`` more actions ``a ~ π(·|s)`` (``[count, *B, A]``) from the ``loc`` and
        ``scale`` a call of this policy under ``ExplorationType.RANDOM`` wrote to
        ``tensordict`` (batch ``[*B]``): the distribution it sampled its action from."""
        loc, scale = tensordict.get(self._loc_key), tensordict.get(self._scale_key)
        noise = torch.randn((count, *loc.shape), dtype=loc.dtype, device=loc.device)
        return self._plan.to_bounds(safetanh_noeps(loc + noise * scale))[0]
