"""The MLP used by every network of the paper: ``depth`` hidden layers of ``width`` units."""

from __future__ import annotations

from torch import nn
from torchrl.modules import MLP

_ACTIVATIONS = {"relu": nn.ReLU, "tanh": nn.Tanh, "elu": nn.ELU, "gelu": nn.GELU}
ACTIVATION_NAMES = tuple(_ACTIVATIONS)
"""What ``algo.network.activation`` may be."""


def make_mlp(
    in_features: int,
    out_features: int,
    *,
    width: int = 256,
    depth: int = 2,
    activation: str = "relu",
    activate_last_layer: bool = False,
) -> MLP:
    """An MLP with ``depth`` hidden layers of ``width`` units (paper: 2 × 256, ReLU).

    TorchRL's :class:`~torchrl.modules.MLP` concatenates several inputs along the
    last dimension, so the same network serves ``Q(s, a)`` (two inputs) and ``π(s)``.
    ``activate_last_layer`` applies the activation to the output too (a feature
    extractor, as in the IQN safety critic).
    """
    if in_features <= 0 or out_features <= 0:
        raise ValueError(
            f"MLP needs positive sizes, got in_features={in_features}, out_features={out_features}"
        )
    if width <= 0 or depth < 0:
        raise ValueError(f"MLP needs width > 0 and depth >= 0, got width={width}, depth={depth}")
    try:
        activation_class = _ACTIVATIONS[activation]
    except KeyError:
        raise ValueError(
            f"unknown activation {activation!r}; choose one of {sorted(_ACTIVATIONS)}"
        ) from None
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=[width] * depth,
        activation_class=activation_class,
        activate_last_layer=activate_last_layer,
    )
