"""The tanh-squashed Gaussian actor of SAC/WCSAC as a TorchRL ``ProbabilisticActor``
(:func:`make_actor`), recognised (:func:`tanh_normal_actor_plan`), and acting without
distribution objects (:class:`TanhNormalPolicy`, for collection and test episodes; the
loss's draw from the parameters is :mod:`wcsac_rl.objectives.fast_paths`')."""

from __future__ import annotations

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
from torch import distributions as D
from torchrl.data import Bounded, TensorSpec
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.modules.distributions.continuous import (
    SafeTanhTransform,
    _PatchedAffineTransform,
    _PatchedComposeTransform,
)
from torchrl.modules.distributions.utils import safetanh_noeps

from wcsac_rl.modules._mlp import make_mlp

__all__ = [
    "ClampedLogStdNormalParams",
    "SyncFreeTanhNormal",
    "TanhNormalActorPlan",
    "TanhNormalPolicy",
    "clamped_normal_params",
    "make_actor",
    "tanh_normal_actor_plan",
]


def clamped_normal_params(
    x: torch.Tensor, log_std_min: float, log_std_max: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(loc, scale)`` from the last dimension's halves, ``scale = exp(clamp(log_std))``
    (the one definition: the module below and the actor's fast path use it)."""
    loc, log_std = x.chunk(2, dim=-1)
    return loc, log_std.clamp(log_std_min, log_std_max).exp()


class ClampedLogStdNormalParams(nn.Module):
    """Split the last dimension into ``(loc, scale)`` with ``scale = exp(clamp(log_std))``.

    This is the parametrisation of the authors' code (log σ clamped to [−20, 2]);
    TorchRL's ``NormalParamExtractor`` maps the scale with a biased softplus instead.
    """

    def __init__(self, log_std_min: float = -20.0, log_std_max: float = 2.0) -> None:
        super().__init__()
        if not log_std_min < log_std_max:
            raise ValueError(
                f"log_std_min ({log_std_min}) must be smaller than log_std_max ({log_std_max})"
            )
        self.log_std_min = float(log_std_min)
        self.log_std_max = float(log_std_max)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return clamped_normal_params(x, self.log_std_min, self.log_std_max)


class SyncFreeTanhNormal(TanhNormal):
    """TorchRL's :class:`~torchrl.modules.TanhNormal` built without reading its bounds back.

    TorchRL's constructor checks ``high > low`` and whether the bounds are ``[-1, 1]``
    on the bounds' values at every construction, three host reads each (it skips them
    under ``torch.compile`` and CUDA-graph capture), so an eager SAC update built two
    of them and synchronised six times. This class is the one TorchRL builds while
    compiling: the same draws, log-probabilities and gradients, with the affine map to
    ``[low, high]`` always applied (for ``[-1, 1]`` it is ``0 + 1 · y`` and adds
    ``log 1 = 0`` to the log-Jacobian: the same numbers bit for bit). The bounds are
    checked once, where the actor is built (:func:`make_actor`), not here.

    Example:
        >>> import torch
        >>> from torchrl.modules import TanhNormal
        >>> loc, scale = torch.randn(3, 2), torch.rand(3, 2) + 0.1
        >>> _ = torch.manual_seed(0)
        >>> a, lp = SyncFreeTanhNormal(loc, scale).rsample_and_log_prob()
        >>> _ = torch.manual_seed(0)
        >>> b, lq = TanhNormal(loc, scale).rsample_and_log_prob()
        >>> bool(torch.equal(a, b) and torch.equal(lp, lq))
        True
    """

    def __init__(
        self,
        loc: torch.Tensor,
        scale: torch.Tensor,
        upscale: torch.Tensor | float = 5.0,
        low: torch.Tensor | float = -1.0,
        high: torch.Tensor | float = 1.0,
        event_dims: int | None = None,
        tanh_loc: bool = False,
        safe_tanh: bool = True,
    ) -> None:
        device = loc.device
        low = torch.as_tensor(low, device=device)
        high = torch.as_tensor(high, device=device)
        self.non_trivial_max = self.non_trivial_min = True  # (not read: always mapped)
        self.tanh_loc = tanh_loc
        self._event_dims = min(1, loc.ndim) if event_dims is None else event_dims
        self.device = device
        self.upscale = upscale.to(device) if isinstance(upscale, torch.Tensor) else upscale
        self.low, self.high = low, high
        tanh = SafeTanhTransform() if safe_tanh else D.TanhTransform()
        self._t = _PatchedComposeTransform(
            [tanh, _PatchedAffineTransform(loc=(high + low) / 2, scale=(high - low) / 2)]
        )
        self.update(loc, scale)


def make_actor(
    observation_dim: int,
    action_spec: TensorSpec,
    *,
    observation_key: NestedKey = "observation",
    action_key: NestedKey = "action",
    width: int = 256,
    depth: int = 2,
    activation: str = "relu",
    log_std_min: float = -20.0,
    log_std_max: float = 2.0,
) -> ProbabilisticActor:
    """Build the paper's actor: an MLP giving a tanh-Normal policy over a bounded action.

    Args:
        observation_dim: size of the (flat) observation.
        action_spec: a bounded continuous spec (``Bounded``); its low/high bound the tanh.
            The last dimension is the action size.

    Keyword Args:
        observation_key: key read by the policy.
        action_key: key the sampled action is written to.
        width, depth, activation: MLP shape (paper: 2 × 256, ReLU).
        log_std_min, log_std_max: clamp of the Gaussian's log-std (paper: [−20, 2]).

    Returns:
        A ``ProbabilisticActor`` writing ``loc``, ``scale`` and ``action_key``, its
        distribution a :class:`SyncFreeTanhNormal` (TorchRL's ``TanhNormal`` without
        its per-construction host reads of the bounds).
        Under ``ExplorationType.DETERMINISTIC`` it outputs ``tanh(loc)`` (the
        paper's mean action for test episodes), under ``RANDOM`` a sample.

    Example:
        >>> import torch
        >>> from torchrl.data import Bounded
        >>> from tensordict import TensorDict
        >>> actor = make_actor(44, Bounded(-1.0, 1.0, shape=(2,)))
        >>> td = actor(TensorDict({"observation": torch.randn(5, 44)}, [5]))
        >>> td["action"].shape
        torch.Size([5, 2])
    """
    if not isinstance(action_spec, Bounded):
        raise TypeError(
            f"make_actor needs a Bounded (continuous, box) action spec, got {type(action_spec).__name__}"
        )
    low, high = action_spec.space.low, action_spec.space.high
    if not bool((high > low).all()):  # (once: the distribution does not check them)
        raise ValueError(
            f"make_actor needs an action spec whose high is above its low in every "
            f"dimension, got low={low.tolist()} high={high.tolist()}"
        )
    action_dim = action_spec.shape[-1]
    net = nn.Sequential(
        make_mlp(observation_dim, 2 * action_dim, width=width, depth=depth, activation=activation),
        ClampedLogStdNormalParams(log_std_min, log_std_max),
    )
    module = TensorDictModule(net, in_keys=[observation_key], out_keys=["loc", "scale"])
    actor = ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=[action_key],
        spec=action_spec,
        distribution_class=SyncFreeTanhNormal,
        distribution_kwargs={"low": low, "high": high},
        default_interaction_type=ExplorationType.RANDOM,
        return_log_prob=False,
    )
    return actor


@dataclass(frozen=True)
class TanhNormalActorPlan:
    """What acting without the actor's distribution object needs to know about a
    ``make_actor`` actor (its MLP is ``actor.module[0].module[0]``).

    Attributes:
        observation_key: the key the actor reads.
        log_std_min, log_std_max: the clamp of the Gaussian's log-std.
        low, high: the action bounds, or ``None`` for ``[-1, 1]`` (no affine map).
    """

    observation_key: NestedKey
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
    ``nn.Sequential(<MLP>, ClampedLogStdNormalParams)`` and (2) a
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
        log_std_min=net[1].log_std_min,
        log_std_max=net[1].log_std_max,
        low=None if trivial else low,
        high=None if trivial else high,
    )


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
