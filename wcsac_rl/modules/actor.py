"""The tanh-squashed Gaussian actor of SAC/WCSAC as a TorchRL ``ProbabilisticActor``."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import distributions as D
from torch import nn
from torchrl.data import Bounded, TensorSpec
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.modules.distributions.continuous import (
    SafeTanhTransform,
    _PatchedAffineTransform,
    _PatchedComposeTransform,
)

from wcsac_rl.modules._mlp import make_mlp

__all__ = [
    "ClampedLogStdNormalParams",
    "SyncFreeTanhNormal",
    "clamped_normal_params",
    "make_actor",
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
