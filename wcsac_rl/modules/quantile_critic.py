"""The implicit-quantile (IQN) safety critic: quantiles Z(s, a, τ) of the discounted cost.

The journal version of WCSAC (Yang et al., Machine Learning 2022) replaces the Gaussian
safety critic with an implicit quantile network (Dabney et al., 2018): the network
reads a state-action and quantile fractions ``τ ∈ [0, 1]`` and returns the
τ-quantiles of the cost return, so the tail of the distribution is learned directly
(quantile regression) instead of through a mean and a variance.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from wcsac_rl.modules._mlp import make_mlp

__all__ = ["IQNSafetyCritic"]


def _shared_over_batch(fractions: torch.Tensor) -> bool:
    """Whether ``fractions`` ``[*B, N]`` holds one row of τ for the whole batch (an
    expanded tensor: zero strides over the batch dimensions)."""
    return fractions.dim() > 1 and all(stride == 0 for stride in fractions.stride()[:-1])


class IQNSafetyCritic(nn.Module):
    r"""Quantiles of the cost return: ``Z(s, a, τ) = w · (ψ(s, a) ⊙ φ(τ)) + b``.

    * ``ψ(s, a)``: an MLP over ``cat(s, a)`` with ``depth`` activated hidden layers of
      ``width`` units (the paper's 2 × 256 ReLU, the size of each Gaussian network);
    * ``φ(τ) = ReLU(Σ_{i<n} cos(π i τ) W_i + b)``: IQN's cosine embedding of τ with
      ``n = num_cosines`` (64, as IQN) into ``width`` units;
    * the multiplicative merge ``ψ ⊙ φ`` and a linear output ``w · (·) + b``.

    The merge sits after the last hidden layer, so for a τ shared by the whole batch
    (an expanded ``[*B, N]`` tensor, as :class:`~wcsac_rl.WCSACLoss` passes it) the
    quantiles are one ``[*B, W] × [W, N]`` product and cost about one MLP evaluation;
    τ given per row costs an embedding per (row, τ) (``[*B, N, W]``). Both give the
    same values.

    ``forward(observation, action, quantile_fractions)`` returns ``[*B, N]`` for
    fractions ``[*B, N]`` (or ``[N]`` for an unbatched state-action).

    Example:
        >>> critic = IQNSafetyCritic(4, 2, width=32)
        >>> tau = torch.rand(5).expand(3, 5)  # one set of τ for the batch
        >>> critic(torch.randn(3, 4), torch.rand(3, 2), tau).shape
        torch.Size([3, 5])
    """

    def __init__(
        self,
        observation_dim: int,
        action_dim: int,
        *,
        width: int = 256,
        depth: int = 2,
        activation: str = "relu",
        num_cosines: int = 64,
    ) -> None:
        super().__init__()
        if depth < 1:
            raise ValueError(f"the IQN safety critic needs depth >= 1 hidden layers, got {depth}")
        if int(num_cosines) != num_cosines or num_cosines < 1:
            raise ValueError(f"num_cosines must be an integer >= 1, got {num_cosines}")
        self.num_cosines = int(num_cosines)
        self.features = make_mlp(
            observation_dim + action_dim,
            width,
            width=width,
            depth=depth - 1,
            activation=activation,
            activate_last_layer=True,
        )
        self.embedding = nn.Linear(self.num_cosines, width)
        self.head = nn.Linear(width, 1)

    def embed(self, fractions: torch.Tensor) -> torch.Tensor:
        """``φ(τ)``: ``[..., N]`` fractions to ``[..., N, width]`` embeddings."""
        return torch.relu(self.embedding(_cosines(fractions, self.num_cosines)))

    def forward(
        self, observation: torch.Tensor, action: torch.Tensor, quantile_fractions: torch.Tensor
    ) -> torch.Tensor:
        features = self.features(torch.cat([observation, action], dim=-1))  # [*B, W]
        return _quantiles(
            features, self.head.weight, self.head.bias, quantile_fractions, self.embed
        )


def _cosines(fractions: torch.Tensor, num_cosines: int) -> torch.Tensor:
    """``cos(π i τ)`` for ``i < num_cosines``: ``[..., N]`` to ``[..., N, num_cosines]``."""
    frequencies = math.pi * torch.arange(
        num_cosines, device=fractions.device, dtype=fractions.dtype
    )
    return torch.cos(fractions.unsqueeze(-1) * frequencies)


def _quantiles(features, head_weight, head_bias, fractions, embed) -> torch.Tensor:
    """``w · (ψ ⊙ φ(τ)) + b`` from the features ``ψ`` ``[*B, W]``, the output layer and
    ``embed`` (``φ``): one embedding for a row of τ shared by the batch (an expanded
    ``[*B, N]`` tensor), else one per (row, τ)."""
    weighted = features * head_weight[0]
    if _shared_over_batch(fractions):
        row = fractions[(0,) * (fractions.dim() - 1)]  # [N]
        quantiles = weighted @ embed(row).transpose(-1, -2)
    else:
        embedded = embed(fractions)  # [*B, N, W]
        quantiles = (embedded @ weighted.unsqueeze(-1)).squeeze(-1)
    return quantiles + head_bias
