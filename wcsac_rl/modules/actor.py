"""The tanh-squashed Gaussian actor of SAC/WCSAC as a TorchRL ``ProbabilisticActor``."""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded, TensorSpec
from torchrl.envs.utils import ExplorationType
from torchrl.modules import ProbabilisticActor, TanhNormal

from wcsac_rl.modules._mlp import make_mlp

__all__ = ["ClampedLogStdNormalParams", "clamped_normal_params", "make_actor"]


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
        A ``ProbabilisticActor`` writing ``loc``, ``scale`` and ``action_key``.
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
        distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high},
        default_interaction_type=ExplorationType.RANDOM,
        return_log_prob=False,
    )
    return actor
