"""Evaluate several same-shaped MLP critics at once with batched matrix products.

WCSAC evaluates four critics — the twin reward critic ``Q^r_1, Q^r_2`` and the
safety critic's mean ``Q^c`` and variance ``V^c`` networks — on the same
``cat(s, a)`` three times per update (target nets at ``(s', a')``, online nets at
``(s, a)``, detached online nets at ``(s, a~π)``). When all of them are plain MLPs
of the same shape (what :mod:`wcsac_rl.modules` builds), one call here replaces
four module calls: each layer becomes one ``baddbmm`` over the stacked weights.
Gradients reach each network's own parameters exactly as with separate calls.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

__all__ = [
    "EnsembleMember",
    "MLPLayout",
    "evaluate_ensemble",
    "evaluate_mlp",
    "mlp_layout",
    "stack_layers",
]


@dataclass(frozen=True)
class MLPLayout:
    """Where an MLP's layers are in a parameter tensordict, and their shapes.

    Attributes:
        prefixes: key prefix of each ``nn.Linear`` in order (``("module", "0")``...).
        shapes: ``(out_features, in_features)`` of each layer.
        activation: the activation class between layers.
    """

    prefixes: tuple[tuple[str, ...], ...]
    shapes: tuple[tuple[int, int], ...]
    activation: type[nn.Module]


def mlp_layout(module: nn.Module, prefix: tuple[str, ...] = ()) -> MLPLayout | None:
    """The :class:`MLPLayout` of ``module`` if it is ``Linear, act, Linear, act, ..., Linear``.

    Returns ``None`` for anything else (other layers, no bias, mixed activations),
    which makes the caller fall back to calling the modules one by one.
    """
    if not isinstance(module, nn.Sequential):
        return None
    children = list(module.named_children())
    linears = children[0::2]
    activations = children[1::2]
    if len(children) % 2 != 1 or not linears:
        return None
    if not all(type(m) is nn.Linear and m.bias is not None for _, m in linears):
        return None
    kinds = {type(m) for _, m in activations}
    if len(kinds) > 1 or not all(
        isinstance(m, (nn.ReLU, nn.Tanh, nn.ELU, nn.GELU)) for _, m in activations
    ):
        return None
    activation = kinds.pop() if kinds else nn.ReLU
    if activation is nn.ELU and any(m.alpha != 1.0 for _, m in activations):
        return None
    if activation is nn.GELU and any(m.approximate != "none" for _, m in activations):
        return None
    return MLPLayout(
        prefixes=tuple((*prefix, name) for name, _ in linears),
        shapes=tuple((m.out_features, m.in_features) for _, m in linears),
        activation=activation,
    )


@dataclass(frozen=True)
class EnsembleMember:
    """One block of critics in the ensemble.

    Attributes:
        source: which parameter set it reads (a key of the dict given to
            :func:`stack_layers`, e.g. ``"qvalue"`` or ``"safety"``).
        layout: where its layers are in that parameter tensordict.
        stacked: the parameters carry a leading ensemble dimension (TorchRL's twin
            critic); otherwise the block is a single network.
    """

    source: str
    layout: MLPLayout
    stacked: bool


def stack_layers(
    members: Sequence[EnsembleMember], params: dict[str, TensorDictBase]
) -> list[tuple[Tensor, Tensor]]:
    """``[(W [K, out, in], b [K, out]) per layer]`` gathered from every member's parameters."""
    layers = []
    for depth in range(len(members[0].layout.prefixes)):
        weights, biases = [], []
        for member in members:
            source = params[member.source]
            prefix = member.layout.prefixes[depth]
            weight, bias = source.get((*prefix, "weight")), source.get((*prefix, "bias"))
            if not member.stacked:
                weight, bias = weight.unsqueeze(0), bias.unsqueeze(0)
            weights.append(weight)
            biases.append(bias)
        layers.append((torch.cat(weights), torch.cat(biases)))
    return layers


_ACTIVATIONS = {
    nn.ReLU: torch.relu,
    nn.Tanh: torch.tanh,
    nn.ELU: nn.functional.elu,
    nn.GELU: nn.functional.gelu,
}


def evaluate_ensemble(
    x: Tensor, layers: list[tuple[Tensor, Tensor]], activation: type[nn.Module]
) -> Tensor:
    """Outputs ``[K, *B, out]`` of the K MLPs given by ``layers`` at the shared input ``x [*B, in]``."""
    act = _ACTIVATIONS[activation]
    batch_shape = x.shape[:-1]
    x = x.reshape(-1, x.shape[-1])
    # the shared input is broadcast (not copied) to the K members, so every layer,
    # the first included, is one batched product on contiguous [K, B, features]
    # activations (a first layer against the side-by-side weights would leave
    # them transposed, and cost a strided copy per layer forward and backward)
    h = x.expand(layers[0][0].shape[0], *x.shape)
    for depth, (weight, bias) in enumerate(layers):
        h = torch.baddbmm(bias.unsqueeze(1), h if depth == 0 else act(h), weight.transpose(1, 2))
    return h.reshape(h.shape[0], *batch_shape, h.shape[-1])


def evaluate_mlp(x: Tensor, params: TensorDictBase, layout: MLPLayout) -> Tensor:
    """One MLP given by ``layout`` at ``x``, with its weights read from ``params``."""
    act = _ACTIVATIONS[layout.activation]
    last = len(layout.prefixes) - 1
    for depth, prefix in enumerate(layout.prefixes):
        x = nn.functional.linear(x, params.get((*prefix, "weight")), params.get((*prefix, "bias")))
        if depth < last:
            x = act(x)
    return x
