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
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn

from wcsac_rl.modules.mlp import ACTIVATIONS, MLPLayout, mlp_layout
from wcsac_rl.modules.safety_critic import GaussianSafetyCritic, softplus_variance

__all__ = [
    "EnsembleMember",
    "FusedCritics",
    "evaluate_ensemble",
    "stack_layers",
]


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


def evaluate_ensemble(
    x: Tensor,
    layers: list[tuple[Tensor, Tensor]],
    activation: type[nn.Module],
) -> Tensor:
    """Outputs ``[K, *B, out]`` of the K MLPs given by ``layers`` at the shared input
    ``x [*B, in]``."""
    act = ACTIVATIONS[activation]
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


Layers = list[tuple[Tensor, Tensor]]
"""Stacked ``(W [K, out, in], b [K, out])`` per layer of a fused evaluation."""


class FusedCritics:
    """A loss's twin reward critic and Gaussian safety critic evaluated as one ensemble.

    The members, in order: the ``num_qvalue_nets`` reward critics (TorchRL's stacked
    parameters), the safety critic's mean network and, with a variance head, its
    variance network. Build with :meth:`plan` (``None`` when the critics cannot be
    fused); gather parameters with :meth:`layers`; evaluate with :meth:`values`.

    Args:
        members: the ensemble's blocks, reward critics first.
        num_qvalue_nets: how many reward critics the first block holds.
        has_variance: whether the last block is the variance network.
    """

    def __init__(
        self, members: Sequence[EnsembleMember], num_qvalue_nets: int, has_variance: bool
    ) -> None:
        self.members = list(members)
        self.num_qvalue_nets = int(num_qvalue_nets)
        self.has_variance = bool(has_variance)
        self.activation = self.members[0].layout.activation

    @classmethod
    def plan(
        cls,
        qvalue_network: TensorDictModule,
        safety_network: TensorDictModule,
        *,
        action_key: NestedKey,
        num_qvalue_nets: int,
        has_variance: bool,
    ) -> FusedCritics | None:
        """The fused evaluation if every critic is a same-shaped MLP reading
        ``[observation, action]`` with one output, else ``None`` (call the modules)."""
        in_keys = list(qvalue_network.in_keys)
        if (
            len(in_keys) != 2
            or in_keys[1] != action_key
            or list(safety_network.in_keys) != in_keys
            or len(qvalue_network.out_keys) != 1
        ):
            return None
        members = [EnsembleMember("qvalue", mlp_layout(qvalue_network.module, ("module",)), True)]
        net = safety_network.module
        if isinstance(net, GaussianSafetyCritic) and has_variance:
            members.append(
                EnsembleMember("safety", mlp_layout(net.mean_net, ("module", "mean_net")), False)
            )
            members.append(
                EnsembleMember(
                    "safety", mlp_layout(net.variance_net, ("module", "variance_net")), False
                )
            )
        elif not has_variance and len(safety_network.out_keys) == 1:
            members.append(EnsembleMember("safety", mlp_layout(net, ("module",)), False))
        else:
            return None
        layouts = [m.layout for m in members]
        if any(layout is None for layout in layouts):
            return None
        first = layouts[0]
        if (
            any(
                layout.shapes != first.shapes or layout.activation is not first.activation
                for layout in layouts
            )
            or first.shapes[-1][0] != 1
        ):
            return None
        return cls(members, num_qvalue_nets, has_variance)

    def layers(self, qvalue_params: TensorDictBase, safety_params: TensorDictBase) -> Layers:
        """The stacked parameters of every member (gather once, evaluate several times)."""
        return stack_layers(self.members, {"qvalue": qvalue_params, "safety": safety_params})

    def values(
        self,
        observation: Tensor,
        action: Tensor,
        layers: Layers,
        *,
        qvalue: bool = True,
    ) -> tuple[Tensor | None, Tensor, Tensor | None]:
        """``(Q^r [num_qvalue_nets, *B], Q^c [*B], V^c [*B] or None)`` at ``(s, a)``.

        ``qvalue=False`` evaluates the safety members alone (``Q^r`` is ``None``; a
        mean-only safety critic with the last reward critic, so that its values are
        those of the whole ensemble's evaluation bit for bit).
        """
        n = self.num_qvalue_nets
        x = torch.cat([observation, action], dim=-1)
        if not qvalue:
            # the safety members, with the last reward critic when the safety critic is
            # a single network: a batched product of one member is another kernel and
            # rounds differently from the same member among others
            k = layers[0][0].shape[0]
            first = min(n, k - 2)
            members = [(weight[first:], bias[first:]) for weight, bias in layers]
            out = evaluate_ensemble(x, members, self.activation).squeeze(-1)[n - first :]
            variance = softplus_variance(out[1]) if self.has_variance else None
            return None, out[0], variance
        out = evaluate_ensemble(x, layers, self.activation).squeeze(-1)
        variance = softplus_variance(out[n + 1]) if self.has_variance else None
        return out[:n], out[n], variance
