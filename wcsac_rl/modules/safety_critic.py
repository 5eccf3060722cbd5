"""The safety critics of WCSAC: the Gaussian C(s, a) ~ N(Q^c(s, a), V^c(s, a)) of the
paper, its mean-only ablation (SAC-Lagrangian), and the implicit-quantile critic of the
journal version (:class:`~wcsac_rl.modules.quantile_critic.IQNSafetyCritic`).

Mean and variance are two *separate* MLPs, as the paper requires: removing the
variance network leaves exactly the cost critic of SAC-Lagrangian.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torch.nn import functional as F

from wcsac_rl.modules._mlp import make_mlp
from wcsac_rl.modules.quantile_critic import IQNSafetyCritic
from wcsac_rl.options import SAFETY_CRITIC_KINDS

__all__ = [
    "SAFETY_CRITIC_KINDS",
    "VARIANCE_MAX",
    "VARIANCE_MIN",
    "GaussianSafetyCritic",
    "make_safety_critic",
    "softplus_variance",
]


#: V^c is clamped to this range wherever it is produced or used (spec, authors' code).
VARIANCE_MIN = 1e-8
VARIANCE_MAX = 1e8


def softplus_variance(raw: torch.Tensor) -> torch.Tensor:
    """The variance head's output transform: ``clamp(softplus(raw), 1e-8, 1e8)``.

    The one definition used by :class:`GaussianSafetyCritic` and by the fused critic
    evaluation of :class:`~wcsac_rl.objectives.WCSACLoss` (the two must agree).
    """
    return F.softplus(raw).clamp(VARIANCE_MIN, VARIANCE_MAX)


class GaussianSafetyCritic(nn.Module):
    """Two MLPs over ``cat(s, a)``: the cost mean ``Q^c`` and the cost variance ``V^c``.

    ``V^c = clamp(softplus(η(s, a)), 1e-8, 1e8)`` is positive by construction.
    ``forward(observation, action)`` returns ``(mean, variance)``, each ``[*B, 1]``.
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        width: int = 256,
        depth: int = 2,
        activation: str = "relu",
    ) -> None:
        super().__init__()
        in_features = observation_dim + action_dim
        self.mean_net = make_mlp(in_features, 1, width=width, depth=depth, activation=activation)
        self.variance_net = make_mlp(
            in_features, 1, width=width, depth=depth, activation=activation
        )

    def forward(
        self, observation: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([observation, action], dim=-1)
        mean = self.mean_net(x)
        return mean, softplus_variance(self.variance_net(x))


def make_safety_critic(
    observation_dim: int,
    action_dim: int,
    *,
    kind: str = "gaussian",
    variance: bool = True,
    observation_key: NestedKey = "observation",
    action_key: NestedKey = "action",
    cost_value_key: NestedKey = "cost_value",
    cost_variance_key: NestedKey = "cost_variance",
    quantile_fractions_key: NestedKey = "quantile_fractions",
    cost_quantiles_key: NestedKey = "cost_quantiles",
    width: int = 256,
    depth: int = 2,
    activation: str = "relu",
    num_cosines: int = 64,
) -> TensorDictModule:
    """The safety critic as a ``TensorDictModule`` reading observation and action.

    Args:
        observation_dim: size of the flat observation.
        action_dim: size of the action.

    Keyword Args:
        kind: ``"gaussian"`` (the paper's critic, or its mean-only ablation, see
            ``variance``) or ``"iqn"``: an implicit quantile network
            (:class:`~wcsac_rl.modules.quantile_critic.IQNSafetyCritic`) that also
            reads quantile fractions τ ``[*B, N]`` at ``quantile_fractions_key`` and
            writes the τ-quantiles of the cost return ``[*B, N]`` at
            ``cost_quantiles_key`` (``WCSACLoss`` samples τ itself).
        variance: Gaussian only. ``True`` (WCSAC) writes ``cost_value`` (Q^c) and
            ``cost_variance`` (V^c > 0) from two separate MLPs; ``False`` (SAC-Lag)
            writes only ``cost_value``.
        observation_key, action_key: input keys.
        cost_value_key, cost_variance_key: output keys of the Gaussian critic
            (``WCSACLoss`` reads them in this order: mean first, variance second).
        quantile_fractions_key, cost_quantiles_key: input τ and output quantiles of
            the IQN critic.
        width, depth, activation: MLP shape (paper: 2 × 256, ReLU); for the IQN
            critic, the hidden layers before the merge with the τ embedding.
        num_cosines: IQN only: cosines of τ in its embedding (64, as IQN).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> critic = make_safety_critic(44, 2)
        >>> td = TensorDict({"observation": torch.randn(4, 44), "action": torch.rand(4, 2)}, [4])
        >>> td = critic(td)
        >>> td["cost_value"].shape, bool((td["cost_variance"] > 0).all())
        (torch.Size([4, 1]), True)
        >>> iqn = make_safety_critic(44, 2, kind="iqn")
        >>> td["quantile_fractions"] = torch.rand(4, 20)
        >>> iqn(td)["cost_quantiles"].shape
        torch.Size([4, 20])
    """
    if kind not in SAFETY_CRITIC_KINDS:
        raise ValueError(f"kind must be one of {SAFETY_CRITIC_KINDS}, got {kind!r}")
    in_keys = [observation_key, action_key]
    if kind == "iqn":
        if not variance:
            raise ValueError(
                "variance=False is the Gaussian critic's mean-only ablation; an IQN "
                "critic learns the whole distribution (leave variance at its default)"
            )
        net = IQNSafetyCritic(
            observation_dim,
            action_dim,
            width=width,
            depth=depth,
            activation=activation,
            num_cosines=num_cosines,
        )
        return TensorDictModule(
            net, in_keys=[*in_keys, quantile_fractions_key], out_keys=[cost_quantiles_key]
        )
    if variance:
        net = GaussianSafetyCritic(
            observation_dim, action_dim, width=width, depth=depth, activation=activation
        )
        return TensorDictModule(net, in_keys=in_keys, out_keys=[cost_value_key, cost_variance_key])
    net = make_mlp(observation_dim + action_dim, 1, width=width, depth=depth, activation=activation)
    return TensorDictModule(net, in_keys=in_keys, out_keys=[cost_value_key])
