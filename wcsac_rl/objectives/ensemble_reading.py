"""An ensemble of safety critics read together: one batched product, random priors and
the readings of its members' values.

:class:`~wcsac_rl.objectives.ensemble_head.EnsembleHead` holds ``E`` critics of one kind
with their parameters stacked ``[E, ...]``. This module gives it

* :class:`StackedMembers` — the ``E`` members of the kit's critics
  (:func:`~wcsac_rl.modules.make_safety_critic`: Gaussian, mean-only or IQN) evaluated
  from the stacked parameters in one batched product per layer (``baddbmm``, as
  :mod:`~wcsac_rl.objectives.fast_paths` fuses the reward critics): ``E = 8``
  costs one call per layer, not eight. An IQN ensemble reads every member at the same
  fractions τ (one draw per reading), so the members' spread is their disagreement,
  not the spread of their draws;
* :class:`RandomPrior` — Osband, Aslanides & Cassirer (NeurIPS 2018): a fixed random
  MLP per member whose output, times a fixed scale, is added to the member's cost
  value (to each quantile of an IQN member). Its weights are buffers: no optimizer
  sees them, no gradient reaches them, and the online and target readings add the same
  prior, so the target network is the member's trained part's Polyak average plus that
  prior. Members stay apart where no data has pinned them down;
* the readings: :func:`ucb` — ``mean_k Γ_k + k_ucb · std_k Γ_k`` (CAL, Wu et al.
  ICLR 2024; the sample standard deviation over the members, Bessel-corrected, as
  ``torch.std_mean`` in CAL's code) — and :func:`upper_tail_mean`, the mean of the
  upper ``α`` share of atoms (the merged-quantile, TQC reading of an IQN ensemble:
  COX-Q, Li, Spaan & Kooij ICLR 2026).

CAP's adaptive ``k_ucb`` (:class:`~wcsac_rl.objectives.ensemble_head.AdaptivePessimism`)
lives with the head that holds its options.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import Tensor, nn

from wcsac_rl.modules.quantile_critic import IQNSafetyCritic, _cosines
from wcsac_rl.modules.safety_critic import GaussianSafetyCritic, softplus_variance
from wcsac_rl.objectives.fast_paths import (
    ACTIVATIONS,
    EnsembleMember,
    MLPLayout,
    evaluate_ensemble,
    mlp_layout,
    stack_layers,
    torchrl_mlp_layout,
)
from wcsac_rl.objectives.risk import upper_tail_mean

__all__ = ["RandomPrior", "StackedMembers", "ucb", "upper_tail_mean"]


def ucb(values: Tensor, k_ucb: float) -> Tensor:
    """``mean + k_ucb · std`` over the leading (member) dimension of ``values``
    ``[E, *B]``: ``[*B]``. ``std`` is the sample standard deviation (divisor ``E − 1``),
    as ``torch.std_mean`` in CAL's code.

    >>> ucb(torch.tensor([[1.0, 0.0], [3.0, 0.0]]), 0.5)  # mean 2, std √2
    tensor([2.7071, 0.0000])
    """
    std, mean = torch.std_mean(values, dim=0, correction=1)
    return mean + k_ucb * std


class RandomPrior(nn.Module):
    """``E`` fixed random MLPs of the given layer shapes, ``p_k(s, a)``, stacked as
    buffers (``weight_<i>`` ``[E, out, in]``, ``bias_<i>`` ``[E, out]``), each layer
    initialised as ``nn.Linear`` initialises one; :meth:`forward` returns
    ``scale · p_k(x)`` for every member, ``[E, *B]``, in one batched product per layer.

    Args:
        members (int): ``E``.
        shapes: ``(out_features, in_features)`` per layer, the last ``out_features`` 1.
        activation (type): between the layers (a key of ``ACTIVATIONS``).
        scale (float): > 0, what the prior's output is multiplied by.
    """

    def __init__(
        self,
        members: int,
        shapes: tuple[tuple[int, int], ...],
        activation: type[nn.Module],
        scale: float,
    ) -> None:
        super().__init__()
        if shapes[-1][0] != 1:
            raise ValueError("a random prior's last layer gives one value")
        self.members, self.scale, self.activation = int(members), float(scale), activation
        self.depth = len(shapes)
        for i, (out_features, in_features) in enumerate(shapes):
            layers = [nn.Linear(in_features, out_features) for _ in range(self.members)]
            self.register_buffer(f"weight_{i}", torch.stack([m.weight.detach() for m in layers]))
            self.register_buffer(f"bias_{i}", torch.stack([m.bias.detach() for m in layers]))

    def layers(self) -> list[tuple[Tensor, Tensor]]:
        """``[(W [E, out, in], b [E, out]) per layer]`` (what ``evaluate_ensemble`` reads)."""
        return [
            (getattr(self, f"weight_{i}"), getattr(self, f"bias_{i}")) for i in range(self.depth)
        ]

    def forward(self, x: Tensor) -> Tensor:
        return self.scale * evaluate_ensemble(x, self.layers(), self.activation).squeeze(-1)

    def extra_repr(self) -> str:
        return f"members={self.members}, scale={self.scale}"


class StackedMembers:
    """The ``E`` members of a kit safety critic read from their stacked parameters.

    Build with :meth:`plan` (``None``: not a kit critic reading ``[observation,
    action]`` (and τ), so the members are called one by one). :meth:`gaussian` gives
    ``(Q^c [E, *B], V^c [E, *B] or None)``, :meth:`quantiles` ``Z [E, *B, N]`` at
    fractions ``[N]`` shared by the members and rows; both add the prior's
    ``scale · p_k(s, a)`` to the cost value (every quantile) when there is one.
    """

    def __init__(self, kind: str, layouts: dict, observation_key, action_key) -> None:
        self.kind, self.layouts = kind, layouts
        self.observation_key, self.action_key = observation_key, action_key
        self.prior: RandomPrior | None = None

    @classmethod
    def plan(cls, network, action_key, quantile_fractions_key) -> StackedMembers | None:
        in_keys = list(network.in_keys)
        module = getattr(network, "module", None)
        if len(in_keys) < 2 or in_keys[1] != action_key:
            return None
        if type(module) is IQNSafetyCritic:
            if in_keys[2:] != [quantile_fractions_key] or len(network.out_keys) != 1:
                return None
            features = torchrl_mlp_layout(
                module.features, ("module", "features"), activate_last=True
            )
            if features is None:
                return None
            layouts = {"features": features, "num_cosines": module.num_cosines}
            return cls("iqn", layouts, in_keys[0], action_key)
        if len(in_keys) != 2:
            return None
        if isinstance(module, GaussianSafetyCritic) and len(network.out_keys) == 2:
            mean = mlp_layout(module.mean_net, ("module", "mean_net"))
            variance = mlp_layout(module.variance_net, ("module", "variance_net"))
            if mean is None or variance is None or mean.shapes != variance.shapes:
                return None
            if mean.activation is not variance.activation:
                return None
            return cls("gaussian", {"mean": mean, "variance": variance}, in_keys[0], action_key)
        if len(network.out_keys) == 1:
            mean = mlp_layout(module, ("module",))
            if mean is None or mean.shapes[-1][0] != 1:
                return None
            return cls("mean", {"mean": mean}, in_keys[0], action_key)
        return None

    @property
    def value_layout(self) -> MLPLayout:
        """The shapes and activation a prior copies: the mean network's, or (IQN) the
        feature MLP followed by one output unit."""
        if self.kind != "iqn":
            return self.layouts["mean"]
        features = self.layouts["features"]
        width = features.shapes[-1][0]
        return MLPLayout(features.prefixes, (*features.shapes, (1, width)), features.activation)

    def add_prior(self, members: int, scale: float) -> RandomPrior:
        """Give the members a :class:`RandomPrior` of ``scale`` (returned, for the loss
        to hold as a sub-module: its buffers follow the loss's device and state dict)."""
        layout = self.value_layout
        self.prior = RandomPrior(members, layout.shapes, layout.activation, scale)
        return self.prior

    def _input(self, tensordict: TensorDictBase, action: Tensor | None) -> Tensor:
        observation = tensordict.get(self.observation_key)
        action = tensordict.get(self.action_key) if action is None else action
        return torch.cat([observation, action], dim=-1)

    def gaussian(
        self, tensordict: TensorDictBase, params: TensorDictBase, action: Tensor | None
    ) -> tuple[Tensor, Tensor | None]:
        """``Q^c`` (with the prior) and ``V^c`` (or ``None``), ``[E, *B]``: the mean, the
        variance and the prior networks of every member in one product per layer."""
        x = self._input(tensordict, action)
        blocks = [EnsembleMember("safety", self.layouts["mean"], True)]
        if self.kind == "gaussian":
            blocks.append(EnsembleMember("safety", self.layouts["variance"], True))
        layers = stack_layers(blocks, {"safety": params})
        members = layers[0][0].shape[0] // len(blocks)
        if self.prior is not None:
            layers = [
                (torch.cat([w, pw]), torch.cat([b, pb]))
                for (w, b), (pw, pb) in zip(layers, self.prior.layers())
            ]
        out = evaluate_ensemble(x, layers, self.layouts["mean"].activation).squeeze(-1)
        mean = out[:members]
        if self.prior is not None:
            mean = mean + self.prior.scale * out[len(blocks) * members :]
        if self.kind != "gaussian":
            return mean, None
        return mean, softplus_variance(out[members : 2 * members])

    def quantiles(
        self,
        tensordict: TensorDictBase,
        params: TensorDictBase,
        action: Tensor | None,
        fractions: Tensor,
    ) -> Tensor:
        """``Z_k(s, a, τ)`` ``[E, *B, N]`` of every member at the fractions ``[N]``:
        :class:`~wcsac_rl.modules.IQNSafetyCritic`'s computation with each product
        batched over the members (features, τ's embedding, the merge), plus the prior."""
        x = self._input(tensordict, action)
        batch_shape = x.shape[:-1]
        features_layout = self.layouts["features"]
        block = EnsembleMember("safety", features_layout, True)
        layers = stack_layers([block], {"safety": params})
        act = ACTIVATIONS[features_layout.activation]
        features = act(evaluate_ensemble(x, layers, features_layout.activation))  # [E, *B, W]
        members = features.shape[0]
        features = features.reshape(members, -1, features.shape[-1])  # [E, B, W]
        cosines = _cosines(fractions, self.layouts["num_cosines"])  # [N, C]
        weight = params.get(("module", "embedding", "weight"))  # [E, W, C]
        bias = params.get(("module", "embedding", "bias"))  # [E, W]
        embedded = torch.relu(
            torch.baddbmm(
                bias.unsqueeze(1), cosines.expand(members, *cosines.shape), weight.transpose(1, 2)
            )
        )  # [E, N, W]
        head_weight = params.get(("module", "head", "weight"))  # [E, 1, W]
        head_bias = params.get(("module", "head", "bias"))  # [E, 1]
        weighted = features * head_weight
        quantiles = torch.baddbmm(head_bias.unsqueeze(1), weighted, embedded.transpose(1, 2))
        quantiles = quantiles.reshape(members, *batch_shape, quantiles.shape[-1])
        if self.prior is not None:
            quantiles = quantiles + self.prior(x).unsqueeze(-1)
        return quantiles
