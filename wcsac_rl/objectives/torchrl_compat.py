"""What :class:`~wcsac_rl.objectives.WCSACLoss` does to keep TorchRL's ``LossModule``
contract where its safety critic makes it differ from :class:`~torchrl.objectives.SACLoss`
(``docs/torchrl_contract.md``): the TD(0) forms it accepts, the ``MultiStep`` batches it
refuses (n > 1 with one-step cost targets), ``skip_done_states``' row selection, γ as the
user wrote it."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives.utils import ValueEstimators, _coerce_value_type
from torchrl.objectives.value import TD0Estimator, ValueEstimatorBase

__all__ = [
    "as_given",
    "check_td0",
    "convert_safety_network",
    "refuse_multistep",
    "refuse_unknown_keywords",
    "sample_alive",
    "scatter_rows",
]


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
