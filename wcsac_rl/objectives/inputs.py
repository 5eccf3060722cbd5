"""What a loss is given, checked, and where it keeps TorchRL's ``LossModule`` contract.

Its constructor's numbers and keywords, its batch (the entries its parts read), and
where the safety critic makes :class:`~wcsac_rl.objectives.WCSACLoss` differ from
:class:`~torchrl.objectives.SACLoss` (``docs/torchrl_contract.md``): the TD(0) forms it
accepts, the ``MultiStep`` batches it refuses (n > 1 with one-step cost targets),
``skip_done_states``' row selection, γ as the user wrote it, the safety critic's
functional parameters.

One NaN or infinite cost, reward or observation in a batch makes every loss term NaN,
and one optimizer step on them makes every parameter NaN for good. Checking a batch's
values needs the host to read them (a synchronisation), which a compiled update
(``torch.compile(fullgraph=True)``) must not do on every step: so the loss checks only
what its shapes say (an empty batch) on its own, and :func:`check_finite_entries` is
what :meth:`WCSACLoss.check_inputs <wcsac_rl.objectives.WCSACLoss.check_inputs>` (and
``WCSACLoss(..., check_finite=True)``) runs. The trainers check every collected batch
once instead, before it reaches the replay buffer.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable, Mapping
from numbers import Real

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives.utils import ValueEstimators, _coerce_value_type
from torchrl.objectives.value import TD0Estimator, ValueEstimatorBase

__all__ = [
    "as_given",
    "check_batch_entries",
    "check_finite_entries",
    "check_finite_losses",
    "check_nonempty_batch",
    "check_td0",
    "collected_keys",
    "convert_safety_network",
    "data_keys",
    "finite_number",
    "loss_out_keys",
    "missing_inputs",
    "nested_key",
    "network_state_keys",
    "nonfinite_entry",
    "parts_in_keys",
    "produced_keys",
    "refuse_multistep",
    "refuse_unknown_keywords",
    "required_entry",
    "sample_alive",
    "scatter_rows",
    "state_keys",
]


def finite_number(value: object, name: str, *, minimum: float | None = None) -> float:
    """``value`` as a float, or a ``ValueError`` naming ``name`` when it is not a finite
    number (NaN, ±inf, a bool, a string) at least ``minimum``."""
    ok = isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (minimum is None or value >= minimum)
    if not ok:
        what = "a finite number" if minimum is None else f">= {minimum:g} (a finite number)"
        raise ValueError(f"{name} must be {what}, got {value!r}")
    return float(value)


def takes_tensordict(forward):
    """``forward`` (under TorchRL's ``dispatch``) refusing a positional batch that is not
    a TensorDict in one ``TypeError`` line (``dispatch`` would read it as keywords)."""

    @functools.wraps(forward)
    def checked(self, *args, **kwargs):
        if args and not isinstance(args[0], TensorDictBase):
            raise TypeError(
                f"{type(self).__name__} takes a TensorDict batch, got {type(args[0]).__name__} "
                "(wrap it: TensorDict(batch, batch_size=[n]))"
            )
        return forward(self, *args, **kwargs)

    return checked


def whole_count(value: object, name: str) -> int:
    """``value`` as a count >= 1, or a ``ValueError`` naming ``name`` (a bool is no count)."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return value


def required_entry(tensordict: TensorDictBase, key: NestedKey, what: str, how: str):
    """``tensordict[key]``, or a ``KeyError`` saying what it is and how to provide it."""
    value = tensordict.get(key, None)
    if value is None:
        raise KeyError(f"{what} at {key!r} of the batch; the batch has none. {how}")
    return value


def check_nonempty_batch(tensordict: TensorDictBase, what: str) -> None:
    """A ``TypeError`` for a batch that is not a TensorDict, a ``ValueError`` naming the
    batch size when ``tensordict`` holds no sample (its shape is known without reading
    any value: no host synchronisation)."""
    if not isinstance(tensordict, TensorDictBase):
        raise TypeError(
            f"{what} takes a TensorDict batch, got {type(tensordict).__name__} (wrap it: "
            "TensorDict(batch, batch_size=[n]))"
        )
    if tensordict.batch_size.numel() == 0 and tensordict.batch_dims:
        raise ValueError(
            f"{what} got an empty batch (batch_size={list(tensordict.batch_size)}); it needs "
            "at least one transition (e.g. sample the replay buffer once it holds some)"
        )


def check_batch_entries(
    tensordict: TensorDictBase,
    keys: Iterable[NestedKey],
    flags: Iterable[NestedKey],
    what: str,
) -> None:
    """A ``KeyError`` naming the first of ``keys`` the batch lacks, or a ``TypeError``
    naming an entry of ``flags`` (done, terminated) that is not boolean. Looks at keys
    and dtypes only (no host synchronisation; the same under ``torch.compile``)."""
    for key in keys:
        if tensordict.get(key, None) is None:
            raise KeyError(
                f"{what}: the batch has no {key!r} entry, which the loss reads (its "
                "in_keys); add it, or name your entry with loss.set_keys(...)"
            )
    for key in flags:
        value = tensordict.get(key, None)
        if isinstance(value, torch.Tensor) and value.dtype != torch.bool:
            raise TypeError(
                f"{what}: batch entry {key!r} must be boolean (torch.bool), got {value.dtype}; "
                "convert it with .bool() (TorchRL's envs write done and terminated as bool)"
            )


def check_critic_inputs(tensordict: TensorDictBase, loss, what: str) -> None:
    """A ``TypeError`` when a batch entry the reward critics read is not of the networks'
    floating dtype, a ``ValueError`` when it is on another device or the reward's shape
    is not the done flag's (:func:`check_reward_shape`), and, for a critic that is one module over its entries (the kit's),
    a ``ValueError`` when those entries do not add up to the inputs its first layer
    takes; each naming the entries. Looks at shapes and dtypes only (no host
    synchronisation; not under ``torch.compile``)."""
    from tensordict.nn import TensorDictSequential

    if torch.compiler.is_compiling():  # (a graph runs what eager mode checked)
        return
    network = loss.qvalue_network
    params = loss.qvalue_network_params.values(True, True)
    first_param = next(iter(params), torch.empty(0))
    dtype, device = first_param.dtype, first_param.device
    check_reward_shape(tensordict, loss.tensor_keys, what)
    cached = loss.__dict__.get("_critic_inputs_cache")  # (the network's structure, once)
    if (
        cached is None
        or cached[0] is not network
        or cached[1] != list(map(nested_key, network.in_keys))
    ):
        first = None
        if not isinstance(network, TensorDictSequential):  # (a trunk's features: not the batch's)
            leaves = (m for m in network.modules() if not list(m.children()))
            first = next((m for m in leaves if list(m.parameters(recurse=False))), None)
            first = first if type(first) is torch.nn.Linear else None  # (an MLP on the entries)
        cached = (network, [nested_key(key) for key in network.in_keys], first)
        loss.__dict__["_critic_inputs_cache"] = cached
    _, keys, first = cached
    entries = [(key, tensordict.get(key, None)) for key in keys]
    entries = [(key, value) for key, value in entries if isinstance(value, torch.Tensor)]
    for key, value in entries:
        if value.device != device:
            shown = key[0] if isinstance(key, tuple) and len(key) == 1 else key
            raise ValueError(
                f"{what}: batch entry {shown!r} is on {value.device}, the networks' parameters "
                f"on {device}; move the batch (.to({str(device)!r})) or the loss"
            )
        if value.is_floating_point() and value.dtype != dtype:
            raise TypeError(
                f"{what}: batch entry {key!r} is {value.dtype}, the networks' parameters "
                f"{dtype}; convert the batch (.to({dtype})) or the loss"
            )
    if first is None or len(entries) != len(keys):
        return
    widths = {key: value.shape[-1] if value.ndim else 1 for key, value in entries}
    if sum(widths.values()) != first.in_features:
        shown = ", ".join(f"{key!r} {width}" for key, width in widths.items())
        raise ValueError(
            f"{what}: the batch's entries ({shown} numbers) make {sum(widths.values())} "
            f"critic inputs; the critics take {first.in_features}"
        )


def check_reward_shape(tensordict: TensorDictBase, keys, what: str) -> None:
    """A ``ValueError`` when ``("next", reward)`` and ``("next", done)`` differ in shape
    (TorchRL's value estimators need them equal: ``[B, 1]`` for a TorchRL env)."""
    reward = tensordict.get(("next", keys.reward), None)
    done = tensordict.get(("next", keys.done), None)
    if isinstance(reward, torch.Tensor) and isinstance(done, torch.Tensor):
        if reward.shape != done.shape:
            raise ValueError(
                f"{what}: batch entry ('next', {keys.reward!r}) has shape "
                f"{list(reward.shape)}, ('next', {keys.done!r}) {list(done.shape)}; they "
                "must be equal (a TorchRL env writes both [B, 1]: reward.unsqueeze(-1))"
            )


def nonfinite_entry(
    tensordict: TensorDictBase, keys: Iterable[NestedKey]
) -> tuple[NestedKey, int, int, float] | None:
    """The first of ``keys`` whose floating-point entry in ``tensordict`` holds a NaN or
    ±inf: ``(key, how many, of how many, the first such value)``; ``None`` if all are
    finite (absent and non-float entries are skipped). Reads the values: a host
    synchronisation per entry."""
    for key in keys:
        value = tensordict.get(key, None)
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            continue
        bad = ~torch.isfinite(value)
        if bool(bad.any()):
            first = float(value[bad].reshape(-1)[0])
            return key, int(bad.sum()), value.numel(), first
    return None


def check_finite_entries(tensordict: TensorDictBase, keys: Iterable[NestedKey], what: str) -> None:
    """A ``ValueError`` naming the first entry of ``keys`` that is not finite, how many of
    its values are not, and one of them (see :func:`nonfinite_entry`)."""
    found = nonfinite_entry(tensordict, keys)
    if found is not None:
        key, count, total, first = found
        raise ValueError(
            f"{what}: batch entry {key!r} holds {count} non-finite value(s) of {total} "
            f"(e.g. {first}); a NaN or infinite cost, reward or observation makes every "
            "loss term NaN and, after one optimizer step, every parameter. Drop or fix "
            "those transitions before they reach the replay buffer"
        )


def check_finite_losses(
    losses: dict[str, torch.Tensor],
    tensordict: TensorDictBase,
    keys: Iterable[NestedKey],
    what: str,
) -> None:
    """A ``ValueError`` naming the first loss term that is not finite although its batch
    is (:func:`check_finite_entries` ran first), and the largest magnitude of each
    floating-point entry the loss read: finite inputs too large for float32 (a cost of
    1e30) overflow in the targets and losses. Reads the values (a host synchronisation)."""
    for name, value in losses.items():
        if bool(torch.isfinite(value).all()):
            continue
        sizes = []
        for key in keys:
            entry = tensordict.get(key, None)
            if isinstance(entry, torch.Tensor) and entry.is_floating_point() and entry.numel():
                sizes.append(f"{key!r} {float(entry.detach().abs().max()):.3g}")
        raise ValueError(
            f"{what}: {name} is {float(value.detach().reshape(-1)[0])} although the batch is "
            f"finite; its largest magnitudes: {', '.join(sizes)}. Values this large overflow "
            "float32 in the targets and losses: scale the rewards, costs or observations down"
        )


def produced_keys(*modules) -> set[NestedKey]:
    """Every key some sub-module of ``modules`` writes (``out_keys`` of each
    ``TensorDictModule`` inside), as tuples."""
    out: set[tuple[str, ...]] = set()
    for module in modules:
        for sub in module.modules() if isinstance(module, torch.nn.Module) else ():
            for key in getattr(sub, "out_keys", None) or ():
                out.add((key,) if isinstance(key, str) else tuple(key))
    return out


def _is_produced(key: NestedKey, produced: set[tuple[str, ...]]) -> bool:
    key = (key,) if isinstance(key, str) else tuple(key)
    # a key whose sub-entries a module writes is written too: ``"params"`` for an actor
    # writing ``("params", "action1", "loc")`` (a TorchRL composite distribution)
    return any(out[: len(key)] == key for out in produced)


def network_state_keys(loss) -> list[NestedKey]:
    """Every entry ``loss``'s networks read other than the action: the actor's
    ``in_keys``, then the reward critic's and the safety head's (in that order, once
    each). Includes the keys its own networks write in between (see :func:`state_keys`)."""
    keys = list(loss.actor_network.in_keys)
    for key in (*loss.qvalue_network.in_keys, *loss.safety_head.in_keys):
        if key != loss.tensor_keys.action and key not in keys:
            keys.append(key)
    return keys


def state_keys(loss) -> list[NestedKey]:
    """The entries an environment state must hold for ``loss``'s networks (its
    ``initial_state_keys``): what they read other than the action
    (:func:`network_state_keys`), without the keys its own networks write in between (a
    composite actor lists the ``"params"`` its first module writes among its
    ``in_keys``; a start state or an n-step state holds only what the env wrote)."""
    networks = [loss.actor_network, loss.qvalue_network, loss.safety_network]
    produced = produced_keys(*networks)
    return [key for key in network_state_keys(loss) if not _is_produced(key, produced)]


def collected_keys(loss) -> list[NestedKey]:
    """``loss.in_keys`` without the entries attached to each *sampled* batch (the start
    states under ``initial_states``, the episodes' ``episode_cvar``): what collected
    data holds, and what a replay buffer stores (``data.select(*collected_keys(loss))``).
    Any TorchRL loss: a loss without those keys gives its ``in_keys``."""
    keys = getattr(loss, "tensor_keys", None)
    attached = [
        nested_key(getattr(keys, name))
        for name in ("initial_states", "episode_cvar")
        if getattr(keys, name, None) is not None
    ]
    return [
        key
        for key in loss.in_keys
        if not any(nested_key(key)[: len(prefix)] == prefix for prefix in attached)
    ]


def nested_key(*keys: NestedKey) -> tuple[str, ...]:
    """One nested key from several: ``nested_key("initial", ("a", "b"))`` is
    ``("initial", "a", "b")``."""
    return tuple(part for key in keys for part in ((key,) if isinstance(key, str) else key))


class _Present:
    """``key in _Present(td)``: whether ``td`` has an entry (a tensor or a
    sub-tensordict) at the nested ``key``, without listing its keys."""

    def __init__(self, tensordict: TensorDictBase) -> None:
        self.tensordict = tensordict

    def __contains__(self, key: NestedKey) -> bool:
        return self.tensordict.get(key, None) is not None


def parts_in_keys(loss, in_keys: Iterable[NestedKey]) -> list[NestedKey]:
    """``in_keys`` (SACLoss's) and what ``loss``'s parts read: the safety head's inputs
    at ``s`` and ``s'``, the cost target's, the start states with
    ``kappa_states="initial"``, the episodes' cost where the signal or the head reads it."""
    head, tensor_keys = loss.safety_head, loss.tensor_keys
    keys = set(in_keys)
    keys.update(head.in_keys)
    keys.update(("next", k) for k in head.in_keys if k != tensor_keys.action)
    states = state_keys(loss)
    keys.update(loss.cost_target.in_keys(states))
    if loss.kappa_states == "initial":
        keys.update(nested_key(tensor_keys.initial_states, key) for key in states)
    if loss.kappa_signal != "critic" or head.reads_episode_costs:
        keys.add(tensor_keys.episode_cvar)
    return list(keys)


def loss_out_keys(loss) -> list[str]:
    """What ``loss.forward`` returns: the loss terms (the head's; ``loss_kappa`` under the
    gradient rule), then the diagnostics (the constraint's and the head's among them)."""
    head, constraint = loss.safety_head, loss.constraint
    keys = ["loss_actor", "loss_qvalue", "loss_alpha", *head.loss_names]
    if constraint.rule == "gradient":
        keys.append("loss_kappa")
    keys += ["alpha", "kappa", *constraint.diagnostic_names, "entropy"]
    keys += [*head.diagnostic_names, "cvar", "cost_threshold"]
    if loss.kappa_signal != "critic":
        keys += ["episode_cvar", "constraint_cvar"]
    return keys


def data_keys(loss) -> list[NestedKey]:
    """The entries of ``loss.in_keys`` a batch must hold: not those the loss's own networks
    write (a composite actor's ``params``, a shared trunk's features), not the end
    flags (``terminated`` falls back to ``done``; the n-step entries' flag the cost
    target reads, naming it, is the one its bootstrap needs), not the cost (its own
    message). Cached on the loss until its ``in_keys`` change (``set_keys``)."""
    in_keys = tuple(loss.in_keys)
    cached = loss.__dict__.get("_data_keys_cache")
    if cached is not None and cached[0] == in_keys:
        return cached[1]
    produced = produced_keys(loss.actor_network, loss.qvalue_network, loss.safety_network)
    tensor_keys = loss.tensor_keys
    optional = {
        nested_key(outer, getattr(tensor_keys, name))
        for outer, names in (("next", ("done", "terminated", "cost")),
                             (tensor_keys.nstep, ("done", "terminated")))
        for name in names
    }  # fmt: skip
    keys = []
    action = nested_key(tensor_keys.action)  # (the actor writes one, the critics read the batch's)
    for key in in_keys:
        key = nested_key(key)
        inner = key[1:] if key[0] == "next" else key
        written = key != action and any(out[: len(inner)] == inner for out in produced)
        if key not in optional and not written:
            keys.append(key)
    loss.__dict__["_data_keys_cache"] = (in_keys, keys)
    return keys


def missing_inputs(loss, tensordict: TensorDictBase) -> str | None:
    """One line naming what ``tensordict`` lacks for ``loss``'s options and the kit's
    transform that writes it, or ``None`` if nothing is missing. Looks at keys only (no
    host synchronisation; the same under ``torch.compile``).

    A TorchRL replay batch (observation, action, ``next`` reward / done / cost) lacks
    the entries the defaults read: the n-step cost entries (``cost_n_steps > 1``:
    :class:`~wcsac_rl.objectives.NStepCost`), the episode start states
    (``kappa_states="initial"``: :class:`~wcsac_rl.objectives.StartStateBuffer`) and
    the recent episodes' cost (``kappa_signal != "critic"``:
    :class:`~wcsac_rl.objectives.EpisodeCostWindow`).
    """
    keys = _Present(tensordict)
    name = type(loss).__name__
    wanted = []
    nstep = loss.tensor_keys.nstep
    if loss.cost_n_steps > 1 and nstep not in keys:
        wanted.append(
            (
                f"cost_n_steps={loss.cost_n_steps}",
                "the n-step cost entries",
                nstep,
                "NStepCost.for_loss(loss) as the collector's postproc (before the replay buffer)",
            )
        )
    initial = loss.tensor_keys.initial_states
    if loss.kappa_states == "initial" and initial not in keys:
        wanted.append(
            (
                "kappa_states='initial'",
                "episode start states",
                initial,
                "starts = StartStateBuffer.for_loss(loss); starts.add_starts(data) per "
                "collected batch; loss(starts.attach(sample))",
            )
        )
    signal = loss.tensor_keys.episode_cvar
    adaptive = getattr(getattr(loss, "safety_head", None), "reads_episode_costs", False)
    if (getattr(loss, "kappa_signal", "critic") != "critic" or adaptive) and signal not in keys:
        wanted.append(
            (
                "an adaptive k_ucb" if adaptive else f"kappa_signal={loss.kappa_signal!r}",
                "the recent episodes' cost",
                signal,
                "window = EpisodeCostWindow.for_loss(loss); window.add_episodes(data); "
                "window.attach(sample)",
            )
        )
    if not wanted:
        return None
    parts = "; ".join(
        f"{option} reads {what} at {key!r}: add {how}" for option, what, key, how in wanted
    )
    return (
        f"{name}: the batch lacks entries its options read ({parts}; from "
        "wcsac_rl.objectives). Or construct the loss with **loss_parts(PAPER_OPTIONS), which reads "
        "only observation, action and next reward / done / terminated / cost."
    )


# ------------------------------------- where the loss differs from SACLoss
def scatter_rows(rows, keep: Tensor):
    """``rows`` (one per set entry of ``keep``) back in ``keep``'s shape, zeros elsewhere
    (a tensor or a tensordict of them: a composite action).

    >>> scatter_rows(torch.tensor([1.0, 2.0]), torch.tensor([True, False, True])).tolist()
    [1.0, 0.0, 2.0]
    """
    if isinstance(rows, TensorDictBase):
        return rows.apply(lambda value: scatter_rows(value, keep), batch_size=keep.shape)
    full = rows.new_zeros((*keep.shape, *rows.shape[1:]))
    full[keep] = rows
    return full


def check_td0(value_type, owner: str = "WCSACLoss") -> None:
    """A ``NotImplementedError`` in one line unless ``value_type`` is a TD(0) estimator
    (``None``, ``ValueEstimators.TD0``, ``"td0"``, the ``TD0Estimator`` class or an
    instance)."""
    if value_type is None:
        return
    if isinstance(value_type, ValueEstimatorBase):
        ok = isinstance(value_type, TD0Estimator)
    elif isinstance(value_type, type) and issubclass(value_type, ValueEstimatorBase):
        ok = issubclass(value_type, TD0Estimator)
    else:
        try:
            ok = _coerce_value_type(value_type) == ValueEstimators.TD0
        except KeyError:
            ok = False
    if not ok:
        raise NotImplementedError(
            f"{owner} supports only the TD(0) value estimator (ValueEstimators.TD0, 'td0', "
            f"TD0Estimator; its cost-variance target is a one-step recursion), got {value_type!r}"
        )


def as_given(gamma) -> float:
    """γ as a user wrote it: a float32 tensor's shortest decimal (``0.99``, not
    ``0.9900000095``), any other's value.

    >>> as_given(torch.tensor(0.99))
    0.99
    """
    if isinstance(gamma, Tensor) and gamma.dtype == torch.float32:
        return float(str(np.float32(gamma.item())))
    return float(gamma)


def refuse_multistep(owner: str, tensordict: TensorDictBase, key: NestedKey) -> None:
    """A one-step cost target on a batch from TorchRL's ``MultiStep`` (``key``: its
    ``steps_to_next_obs`` entry) with ``n > 1`` would pair one step's cost with the state
    n steps on: refused in one line. ``MultiStep(n_steps=1)`` is a no-op (every entry 1,
    ``"next"`` and the reward unchanged): accepted, as :class:`~torchrl.objectives.SACLoss`
    accepts it. Reading the entry costs one host sync, only for batches that have it;
    under ``torch.compile`` its values cannot be read, and any such batch is refused."""
    steps = tensordict.get(key, None)
    if steps is None:
        return
    compiling = torch.compiler.is_compiling()
    if not compiling and not bool((steps > 1).any()):
        return
    where = " (under torch.compile the loss cannot read n: even n=1 is refused)"
    raise ValueError(
        f"{owner}: the batch has {key!r}, written by TorchRL's "
        "MultiStep: its reward target is n-step but the cost target with "
        "cost_n_steps=1 is one step's, which would bootstrap from the state n steps "
        f"on{where if compiling else ''}; drop MultiStep, or construct the loss with "
        "safety_head=SafetyHeadOptions(cost_n_steps=n) and add NStepCost.for_loss(loss) to "
        "the collector's postproc before MultiStep"
    )


def sample_alive(
    sample_policy: Callable[[TensorDictBase], tuple],
    states: TensorDictBase,
    done: Tensor | None,
    like_action,
) -> tuple:
    """``a ~ π(·|states)`` and its log-probability; given ``done`` (``skip_done_states``,
    as :class:`~torchrl.objectives.SACLoss`) the actor is run only on the states not
    done, and the others get the action 0 and log-probability 0 (their target is cut by
    ``done``; TorchRL's rule). ``like_action``: an action batch shaped like those (the
    replay batch's). Eager only: the rows kept are read on the host."""
    if done is None:
        return sample_policy(states)
    alive = ~done.reshape(states.shape)
    if not alive.any():  # (nothing to run the actor on)
        action = torch.zeros_like(like_action)  # (a tensordict too)
        return action, torch.zeros(states.shape, device=done.device)
    action, log_prob = sample_policy(states[alive])
    return scatter_rows(action, alive), scatter_rows(log_prob, alive)


def convert_safety_network(
    loss, safety_network, separate_losses: bool, num_safety_nets: int = 1
) -> None:
    """``loss``'s safety critic's functional parameters, as
    :class:`~torchrl.objectives.SACLoss` makes the reward critic's where it shares
    tensors with the actor (a common trunk): with ``separate_losses`` it reads the
    actor's tensors without training them (only the actor loss does); without, it gets
    its own trainable copy of them (its loss trains that copy, never the actor's).

    ``num_safety_nets`` > 1: that many critics, their parameters stacked along a
    leading dimension (as TorchRL stacks the reward critics): from a list of that many
    modules of one structure (each keeps its own initialisation), or from one module
    re-drawn per member (TorchRL's ``expand_dim``)."""
    if isinstance(safety_network, (list, tuple)):
        if len(safety_network) != num_safety_nets:
            raise ValueError(
                f"num_safety_nets={num_safety_nets} but {len(safety_network)} safety "
                f"critics were given: pass num_safety_nets={len(safety_network)}"
            )
        if num_safety_nets == 1:
            safety_network = safety_network[0]
        else:
            check_same_structure(safety_network)
            loss.convert_to_functional(
                list(safety_network), "safety_network", num_safety_nets, create_target_params=True
            )
            return
    actor_params = list(loss.actor_network_params.values(True, True))
    loss.convert_to_functional(
        safety_network,
        "safety_network",
        num_safety_nets if num_safety_nets > 1 else None,
        create_target_params=True,
        compare_against=actor_params if separate_losses else None,
    )
    if separate_losses:
        return
    shared = {id(p) for p in actor_params}
    for key, value in list(loss.safety_network_params.items(True, True)):
        if id(value) in shared:
            copy = torch.nn.Parameter(value.detach().clone(), value.requires_grad)
            loss.safety_network_params.set(key, copy)


def check_same_structure(critics) -> None:
    """A ``ValueError`` naming the first member of an ensemble of safety critics whose
    class or parameter shapes differ from the first member's: the members' parameters
    are stacked, so they must be one network drawn several times."""
    first = critics[0]
    shapes = {name: tuple(p.shape) for name, p in first.named_parameters()}
    for i, critic in enumerate(critics[1:], start=1):
        other = {name: tuple(p.shape) for name, p in critic.named_parameters()}
        if type(getattr(critic, "module", critic)) is not type(getattr(first, "module", first)) or (
            other.keys() != shapes.keys()
        ):
            raise ValueError(
                f"safety critic {i} of the ensemble is not the same network as critic 0 "
                "(other layers); an ensemble's members must be one structure (e.g. "
                "make_safety_critic(...) with the same kind and width, called per member)"
            )
        for name, shape in shapes.items():
            if other[name] != shape:
                raise ValueError(
                    f"safety critic {i} of the ensemble has {name} of shape "
                    f"{list(other[name])}, critic 0 {list(shape)}; an ensemble's members "
                    "must be one structure (the same kind and width)"
                )


def refuse_unknown_keywords(
    init: Callable, kwargs: dict, parts: Mapping[str, str] | None = None
) -> None:
    """Refuse a keyword neither ``init`` (the loss's ``__init__``) nor
    :class:`~torchrl.objectives.SACLoss` takes, in one line naming the part that takes
    it (``parts``: ``kappa_init`` → ``constraint=GradientLagrangian(kappa_init=...)``)
    or the closest keyword (``alpha_int`` → ``alpha_init``), before ``SACLoss`` says
    only that it is unexpected."""
    import difflib
    import inspect

    from torchrl.objectives import SACLoss

    known = {*inspect.signature(init).parameters, *inspect.signature(SACLoss.__init__).parameters}
    known -= {"self", "sac_kwargs", "kwargs"}
    parts = parts or {}
    for name in kwargs:
        if name in parts:
            raise TypeError(f"{name!r} is an option of a part of the loss: give {parts[name]}")
        if name not in known:
            close = difflib.get_close_matches(name, sorted({*known, *parts}), n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]}?)" if close else ""
            if close and close[0] in parts:
                hint = f" (did you mean {close[0]}? give {parts[close[0]]})"
            raise TypeError(f"unknown keyword argument {name!r}{hint}")
