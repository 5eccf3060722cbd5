"""Plain MLPs read from a parameter tensordict: the layout of an ``nn.Sequential`` MLP
and its evaluation with ``F.linear``, for the fast paths that skip module calls
(the actor's direct sampling, the fused critics).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn
from torchrl.modules import MLP

__all__ = [
    "ACTIVATIONS",
    "MLPLayout",
    "evaluate_mlp",
    "evaluate_stacked_mlp",
    "mlp_layout",
    "torchrl_mlp_layout",
]


@dataclass(frozen=True)
class MLPLayout:
    """Where an MLP's layers are in a parameter tensordict, and their shapes.

    Attributes:
        prefixes: key prefix of each ``nn.Linear`` in order (``("module", "0")``...).
        shapes: ``(out_features, in_features)`` of each layer.
        activation: the activation class between layers.
        activate_last: the activation follows the last layer too (a feature extractor).
    """

    prefixes: tuple[tuple[str, ...], ...]
    shapes: tuple[tuple[int, int], ...]
    activation: type[nn.Module]
    activate_last: bool = False


def mlp_layout(
    module: nn.Module, prefix: tuple[str, ...] = (), *, activate_last: bool = False
) -> MLPLayout | None:
    """The :class:`MLPLayout` of ``module`` if it is ``Linear, act, Linear, act, ..., Linear``
    (with ``activate_last``: ``..., Linear, act``).

    Returns ``None`` for anything else (other layers, no bias, mixed activations),
    which makes the caller fall back to calling the modules one by one.
    """
    if not isinstance(module, nn.Sequential):
        return None
    children = list(module.named_children())
    linears = children[0::2]
    activations = children[1::2]
    if len(children) % 2 != (0 if activate_last else 1) or not linears:
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
        activate_last=activate_last,
    )


def torchrl_mlp_layout(
    module: nn.Module, prefix: tuple[str, ...] = (), *, activate_last: bool = False
) -> MLPLayout | None:
    """:func:`mlp_layout` of a TorchRL ``MLP`` that computes exactly what its layers do:
    its own ``forward`` (which concatenates several inputs), a flat output; else
    ``None`` (a subclass may compute otherwise: call the module)."""
    if (
        not isinstance(module, MLP)
        or type(module).forward is not MLP.forward
        or getattr(module, "_reshape_out", True)
    ):
        return None
    return mlp_layout(module, prefix, activate_last=activate_last)


ACTIVATIONS = {
    nn.ReLU: torch.relu,
    nn.Tanh: torch.tanh,
    nn.ELU: nn.functional.elu,
    nn.GELU: nn.functional.gelu,
}
"""The activations a fused or direct evaluation supports, as functions."""


def evaluate_mlp(x: Tensor, params: TensorDictBase, layout: MLPLayout) -> Tensor:
    """One MLP given by ``layout`` at ``x``, with its weights read from ``params``."""
    act = ACTIVATIONS[layout.activation]
    last = len(layout.prefixes) - 1
    for depth, prefix in enumerate(layout.prefixes):
        x = nn.functional.linear(x, params.get((*prefix, "weight")), params.get((*prefix, "bias")))
        if depth < last or layout.activate_last:
            x = act(x)
    return x


def evaluate_stacked_mlp(x: Tensor, params: TensorDictBase, layout: MLPLayout) -> Tensor:
    """``K`` MLPs of one ``layout`` with stacked parameters (weights ``[K, out, in]``, as
    TorchRL stacks a loss's twin critic) at a shared input ``x [*B, in]``: ``[K, *B, out]``.

    Bit for bit what ``torch.vmap`` over the module computes (TorchRL's vmapped call of
    the twin critic), values and gradients: the same kernels in the same order, each
    layer the product against the stacked weights and then the bias added (not one
    ``baddbmm``, which rounds differently), without vmap's per-call overhead.
    """
    act = ACTIVATIONS[layout.activation]
    batch_shape = x.shape[:-1]
    x = x.reshape(-1, x.shape[-1])
    last = len(layout.prefixes) - 1
    for depth, prefix in enumerate(layout.prefixes):
        weight, bias = params.get((*prefix, "weight")), params.get((*prefix, "bias"))
        x = torch.matmul(x, weight.transpose(-1, -2)) + bias.unsqueeze(-2)
        if depth < last or layout.activate_last:
            x = act(x)
    return x.reshape(x.shape[0], *batch_shape, x.shape[-1])
