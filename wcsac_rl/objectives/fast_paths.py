"""The loss's fast paths, behind its one ``fast_paths`` keyword (:class:`FastPaths`).

Each computes what TorchRL's general path computes (tested against it:
``tests/test_fast_paths.py``), with fewer module calls:

* the networks read from a parameter tensordict: an MLP's layout and its evaluation with
  ``F.linear`` (:func:`mlp_layout`, :func:`evaluate_mlp`), the twin reward critic from
  its stacked parameters (:func:`evaluate_stacked_mlp`: bit for bit TorchRL's vmapped
  call), the kit's IQN critic (:class:`IQNReader`: bit for bit its module call);
* the actor's reparametrised draw ``a ~ π(·|s)`` and ``log π`` from its parameters
  (:class:`DirectSampling`), without building a ``TanhNormal``;
* the twin reward critic and the Gaussian safety critic as one batched ensemble
  (:class:`FusedCritics`: each layer one ``baddbmm`` over the stacked weights);
* the reward's TD(0) target without the estimator's tensordict round trip
  (:func:`td0_target`), and the target networks' Polyak step in one fused in-place
  operation (:class:`PolyakUpdate`, an updater of its own, not switched by the keyword).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn
from torch.nn import functional as F
from torchrl.modules import MLP
from torchrl.modules.distributions.utils import safetanh_noeps
from torchrl.objectives import SoftUpdate
from torchrl.objectives.value import TD0Estimator

from wcsac_rl.modules.actor import (
    TanhNormalActorPlan,
    clamped_normal_params,
    tanh_normal_actor_plan,
)
from wcsac_rl.modules.quantile_critic import IQNSafetyCritic, _cosines, _quantiles
from wcsac_rl.modules.safety_critic import GaussianSafetyCritic, softplus_variance

__all__ = [
    "ACTIVATIONS",
    "DirectSampling",
    "EnsembleMember",
    "FastPaths",
    "FusedCritics",
    "IQNReader",
    "Layers",
    "MLPLayout",
    "PolyakUpdate",
    "evaluate_ensemble",
    "evaluate_mlp",
    "evaluate_stacked_mlp",
    "mlp_layout",
    "stack_layers",
    "stacked_mlp_layout",
    "td0_target",
    "torchrl_mlp_layout",
]

_HALF_LOG_2PI = math.log(math.sqrt(2 * math.pi))
_LOG_2 = math.log(2.0)


class FastPaths:
    """Which fast paths a loss takes, from its ``fast_paths`` keyword.

    ``None`` (the default): each where the networks allow it; ``True``: the actor's
    direct sampling and the fused critics are required (a one-line ``ValueError`` says
    why one cannot be taken); ``False``: TorchRL's general path everywhere (the actor's
    distribution, the critics' module calls, the twin critic's vmapped call, the
    estimator's TD(0)). :meth:`report` names each path and why it is not taken.

    Args:
        wanted (bool, optional): the keyword.
        actor_network: the loss's actor.
        qvalue_network: the loss's reward critic (its stacked twins are read).
        head: the loss's safety head (``fusion_plan``, ``unfused_reason``,
            ``read_through_module``).
        action_key (NestedKey): the action entry the critics read.
        num_qvalue_nets (int): how many reward critics are stacked.
        vmap (bool): the loss calls the twin through ``vmap`` (TorchRL's
            ``deactivate_vmap=True`` loops over the critics, which rounds differently
            from a stacked read).
    """

    def __init__(
        self,
        wanted: bool | None,
        actor_network: nn.Module,
        qvalue_network: TensorDictModule,
        head,
        *,
        action_key: NestedKey,
        num_qvalue_nets: int,
        vmap: bool = True,
    ) -> None:
        if wanted not in (None, True, False):
            raise ValueError(f"fast_paths must be None, True or False, got {wanted!r}")
        self.head, self.off = head, wanted is False
        self.sampling = None if self.off else DirectSampling.of(actor_network)
        self.fused = None if self.off else head.fusion_plan(qvalue_network, num_qvalue_nets)
        self.stacked = None
        if vmap and not self.off and self.fused is None:
            self.stacked = stacked_mlp_layout(qvalue_network, action_key)
        self._not_stacked = (
            "not a plain TorchRL MLP reading [observation, action]"
            if vmap
            else "deactivate_vmap=True (a loop rounds unlike the vmapped call)"
        )
        if self.off:
            head.read_through_module()
        needs = None
        if self.sampling is None:
            needs = f"the actor sampled from its parameters, but {self._not_sampled}"
        elif self.fused is None:
            needs = f"the critics fused, but {head.unfused_reason()}"
        if wanted and needs:
            raise ValueError(
                f"fast_paths=True needs {needs}; use fast_paths=None to take each where possible"
            )

    _not_sampled = (
        "it is not built like wcsac_rl.modules.make_actor (an MLP with "
        "ClampedLogStdNormalParams and a TanhNormal)"
    )

    def read_through_modules(self) -> None:
        """Read every unfused critic through its module call (the twin through TorchRL's
        vmapped call): the same values, slower; the reference those reads are compared with."""
        self.stacked = None
        self._not_stacked = "read through the module (read_through_modules)"
        self.head.read_through_module()

    def report(self) -> dict[str, str]:
        """Each path, ``"taken"`` or ``"not taken: <why>"``: ``direct_sampling``,
        ``fused_critics``, ``stacked_qvalue`` (the unfused twin from its stacked
        parameters), ``safety_read`` (the safety critic from its parameters: fused, the
        kit's IQN critic, an ensemble's members in one product) and ``td0_target``
        (inline, where the batch allows)."""
        member = getattr(self.head, "member", self.head)  # (an ensemble's member)
        off = "fast_paths=False" if self.off else None
        safety = (
            self.fused is not None
            or getattr(self.head, "stacked", None) is not None
            or getattr(member, "_reader", None) is not None
        )
        why = {
            "direct_sampling": None if self.sampling else off or self._not_sampled,
            "fused_critics": None if self.fused else off or self.head.unfused_reason(),
            "stacked_qvalue": None
            if self.stacked
            else off or ("read in the fused critics" if self.fused else self._not_stacked),
            "safety_read": None if safety else off or "the module is called (not the kit's)",
            "td0_target": off,
        }
        return {name: f"not taken: {w}" if w else "taken" for name, w in why.items()}


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


def _reads_state_action(critic: TensorDictModule, action_key: NestedKey) -> bool:
    """Whether ``critic`` reads ``[observation, action]`` and writes one key."""
    in_keys = list(critic.in_keys)
    return len(in_keys) == 2 and in_keys[1] == action_key and len(critic.out_keys) == 1


def stacked_mlp_layout(qvalue_network: TensorDictModule, action_key: NestedKey) -> MLPLayout | None:
    """The layout of a reward critic that :func:`evaluate_stacked_mlp`
    reads exactly as its vmapped call computes: a TorchRL ``MLP`` (its own ``forward``,
    which concatenates its inputs; a flat output of one value) of plain ``Linear`` /
    activation layers reading ``[observation, action]`` and writing one key; else
    ``None`` (call the module)."""
    if not _reads_state_action(qvalue_network, action_key):
        return None
    layout = torchrl_mlp_layout(getattr(qvalue_network, "module", None), ("module",))
    if layout is None or layout.shapes[-1][0] != 1:
        return None
    return layout


@dataclass(frozen=True)
class DirectSampling:
    """A :func:`~wcsac_rl.modules.make_actor` actor sampled from its parameters: the
    actor's :class:`~wcsac_rl.modules.actor.TanhNormalActorPlan` and its MLP's layout.

    Every update draws ``a ~ π(·|s)`` and ``a' ~ π(·|s')``; through TorchRL that is the
    parameters swapped into the module, a ``TanhNormal`` built and the draw scored,
    which costs more than the actor's products. Build with :meth:`of`; draw with
    :meth:`sample`.
    """

    plan: TanhNormalActorPlan
    layout: MLPLayout

    @classmethod
    def of(cls, actor: nn.Module) -> DirectSampling | None:
        """The direct sampling of ``actor``, or ``None`` if it is not built like
        ``make_actor`` with a plain MLP."""
        plan = tanh_normal_actor_plan(actor)
        if plan is None:
            return None
        layout = mlp_layout(actor.module[0].module[0], ("module", "0", "module", "0"))
        return None if layout is None else cls(plan, layout)

    @property
    def observation_key(self) -> NestedKey:
        return self.plan.observation_key

    def sample(self, params: TensorDictBase, observation: Tensor) -> tuple[Tensor, Tensor]:
        """A reparametrised draw ``a = tanh(μ + σ ε)`` (mapped to ``[low, high]``) and
        ``log π(a|s)``, with the actor's parameters ``params``.

        Equal to TorchRL's ``TanhNormal(...).rsample_and_log_prob()`` at the same random
        state: the pre-tanh value is scored (not recovered by ``atanh``), the tanh is
        TorchRL's saturation-safe one.
        """
        plan = self.plan
        out = evaluate_mlp(observation, params, self.layout)
        loc, scale = clamped_normal_params(out, plan.log_std_min, plan.log_std_max)
        eps = torch.randn_like(loc)
        pre_tanh = loc + eps * scale
        # the Normal's log-density and the tanh's log-Jacobian, summed over the action
        # dimensions separately (the order TorchRL's distribution sums them in)
        normal_log_prob = -((pre_tanh - loc) ** 2) / (2 * scale**2) - scale.log() - _HALF_LOG_2PI
        log_det = 2.0 * (_LOG_2 - pre_tanh - F.softplus(-2.0 * pre_tanh))
        action, half_range = plan.to_bounds(safetanh_noeps(pre_tanh))
        if half_range is not None:
            log_det = log_det + half_range.abs().log()
        return action, normal_log_prob.sum(-1) - log_det.sum(-1)


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
        same_inputs = list(safety_network.in_keys) == list(qvalue_network.in_keys)
        if not (same_inputs and _reads_state_action(qvalue_network, action_key)):
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


@dataclass(frozen=True)
class IQNReader:
    """An :class:`IQNSafetyCritic` read from a parameter tensordict (how
    :class:`~wcsac_rl.WCSACLoss` reads it): the module's own operations in its order, so
    the same quantiles and gradients bit for bit, without the module call (swapping the
    parameters in and out of the module, the tensordict in and out).

    Build with :meth:`of` (``None`` when the module is not an unmodified
    ``IQNSafetyCritic``); call :meth:`quantiles`.
    """

    features: MLPLayout
    prefix: tuple[str, ...]
    num_cosines: int

    @classmethod
    def of(cls, module: nn.Module, prefix: tuple[str, ...] = ()) -> IQNReader | None:
        """The reader of ``module`` whose parameters sit under ``prefix`` (``("module",)``
        in a ``TensorDictModule``'s), or ``None``: not exactly an ``IQNSafetyCritic``
        (a subclass may compute otherwise), or features other than a TorchRL ``MLP`` of
        plain ``Linear`` / activation layers."""
        if type(module) is not IQNSafetyCritic:
            return None
        layout = torchrl_mlp_layout(module.features, (*prefix, "features"), activate_last=True)
        if layout is None:
            return None
        return cls(layout, tuple(prefix), module.num_cosines)

    def quantiles(
        self,
        params: TensorDictBase,
        observation: torch.Tensor,
        action: torch.Tensor,
        fractions: torch.Tensor,
    ) -> torch.Tensor:
        """``Z(s, a, τ)`` ``[*B, N]``: what the module returns for ``observation``,
        ``action`` and ``fractions`` ``[*B, N]`` with the parameters ``params``."""
        key = self.prefix
        features = evaluate_mlp(torch.cat([observation, action], dim=-1), params, self.features)
        weight = params.get((*key, "embedding", "weight"))
        bias = params.get((*key, "embedding", "bias"))

        def embed(tau: torch.Tensor) -> torch.Tensor:
            return torch.relu(nn.functional.linear(_cosines(tau, self.num_cosines), weight, bias))

        head_weight = params.get((*key, "head", "weight"))
        return _quantiles(
            features, head_weight, params.get((*key, "head", "bias")), fractions, embed
        )


def td0_target(
    estimator: TD0Estimator, tensordict: TensorDictBase, next_value: Tensor, inline: bool = True
) -> Tensor:
    """TorchRL's TD(0) estimate ``r + γ (1 − term) V(s')``, shaped like the reward.

    Computed here (``inline``) when the estimator has nothing beyond plain TD(0) to
    apply (no reward standardisation, no multi-step ``steps_to_next_obs``): the same
    elementwise operations in the same order, without the estimator's tensordict round
    trip. Otherwise, or when the shapes do not line up, the estimator does it (and
    reports errors).
    """
    keys = estimator.tensor_keys
    reward = tensordict.get(("next", keys.reward), None)
    terminated = tensordict.get(("next", keys.terminated), None)
    if terminated is None:
        terminated = tensordict.get(("next", keys.done), None)
    if (
        not inline
        or estimator.average_rewards
        or reward is None
        or terminated is None
        or tensordict.get(keys.steps_to_next_obs, None) is not None
        or not reward.shape == terminated.shape == next_value.shape
    ):
        td_value = tensordict.clone(False)
        td_value.set(("next", keys.value), next_value)
        return estimator.value_estimate(td_value)
    gamma = estimator.gamma.to(reward.device)
    return reward + gamma * (~terminated).int() * next_value


class PolyakUpdate(SoftUpdate):
    r"""TorchRL's :class:`~torchrl.objectives.SoftUpdate`, stepped with one ``_foreach_lerp_``.

    Same construction (``tau`` or ``eps``), same initialisation and same result,
    ``θ̄ ← θ̄ + τ (θ − θ̄)`` for every target parameter of the loss; ``step`` gathers
    all target and source tensors and updates them in one fused call instead of
    one tensordict ``lerp_`` per network (about 4× less time per step for
    WCSAC's six networks on one CPU core, see ``benchmarks/bench_update.py``).

    Example:
        >>> import torch
        >>> from torchrl.data import Bounded
        >>> from wcsac_rl import WCSACLoss
        >>> from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
        >>> from wcsac_rl.objectives import PolyakUpdate
        >>> loss = WCSACLoss(make_actor(4, Bounded(-1.0, 1.0, shape=(2,))),
        ...                  [make_qvalue(4, 2) for _ in range(2)], make_safety_critic(4, 2))
        >>> updater = PolyakUpdate(loss, tau=0.5)
        >>> with torch.no_grad():
        ...     _ = loss.safety_network_params["module", "mean_net", "0", "bias"].fill_(1.0)
        ...     _ = loss.target_safety_network_params["module", "mean_net", "0", "bias"].fill_(0.0)
        >>> updater.step()
        >>> loss.target_safety_network_params["module", "mean_net", "0", "bias"][0].item()
        0.5
    """

    def step(self, finite: torch.Tensor | None = None) -> None:
        """``θ̄ ← θ̄ + τ (θ − θ̄)``; where ``finite`` (a boolean tensor) is ``False``, the
        weight is 0 and the targets stay as they are (on the device: nothing is read)."""
        if not self.initialized:
            raise RuntimeError(
                f"{type(self).__name__} must be initialized (`.init_()`) before calling step()"
            )
        sources, targets = [], []
        for key, source in self._sources.items():
            target = self._targets.get(f"target_{key}")
            if not getattr(self, "_pairs_checked", False):
                # sources and targets are locked after init_, so once is enough
                source_keys = list(source.keys(True, True))
                if source_keys != list(target.keys(True, True)):
                    raise RuntimeError(
                        f"target_{key} and {key} hold different parameters: "
                        f"{list(target.keys(True, True))} vs {source_keys}"
                    )
            sources.extend(source.values(True, True))
            targets.extend(target.values(True, True))
        if not getattr(self, "_pairs_checked", False):
            if any(t.requires_grad for t in targets):
                raise RuntimeError("a target parameter is part of a graph")
            self._pairs_checked = True
        weight = 1.0 - self.eps
        if finite is not None:
            weight = torch.where(finite, weight, 0.0).to(targets[0].dtype)
        with torch.no_grad():
            torch._foreach_lerp_(targets, sources, weight)
