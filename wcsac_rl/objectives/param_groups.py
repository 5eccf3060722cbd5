"""The loss's parameters as optimizer groups with the kit's learning rates.

``torch.optim.Adam(loss.parameters(), lr)`` — the TorchRL habit — trains everything a
:class:`~wcsac_rl.objectives.WCSACLoss` holds at one rate: the actor, the reward and
safety critics, the entropy weight β and the Lagrange multiplier κ (``kappa_raw``). The
kit trains κ at its own rate (``lr × kappa_lr_scale``: 0.3 in ``conf/algo/wcsac.yaml``)
and the actor at ``actor_lr`` when set (3e-4 there). :func:`param_groups`
gives those groups for one optimizer::

    optim = torch.optim.Adam(param_groups(loss, lr=3e-4, kappa_lr_scale=5.0))

and, so that the habit is not a silent trap, the first ``step()`` of any optimizer that
holds κ's parameter in one group with other parameters warns once, in one line
(:class:`SingleGroupWarning`; silence it with
``warnings.filterwarnings("ignore", category=SingleGroupWarning)`` when one rate is meant).
"""

from __future__ import annotations

import warnings
import weakref

import torch
from torch.optim.optimizer import register_optimizer_step_pre_hook

__all__ = ["PARAM_GROUP_NAMES", "SingleGroupWarning", "param_groups", "watch_multiplier"]

PARAM_GROUP_NAMES = ("actor", "critic", "alpha", "kappa")
"""The groups of :func:`param_groups`, in order (``"kappa"`` only under the gradient rule;
``"critic"`` holds the reward critics, then the safety critic)."""


class SingleGroupWarning(UserWarning):
    """An optimizer trains κ in one group with other parameters (one learning rate)."""


def param_groups(
    loss,
    lr: float,
    *,
    actor_lr: float | None = None,
    kappa_lr_scale: float = 1.0,
) -> list[dict]:
    """The loss's trainable parameters as ``torch.optim`` parameter groups.

    Args:
        loss: a ``WCSACLoss`` / ``SACLagLoss`` (or TorchRL's ``SACLoss``: no safety
            critic, no κ).
        lr: the critics' and the entropy weight's learning rate (``algo.lr``).

    Keyword Args:
        actor_lr: the actor's (``algo.actor_lr``); ``None``: ``lr``.
        kappa_lr_scale: κ's rate is ``lr × kappa_lr_scale`` (``algo.kappa_lr_scale``).

    Returns:
        ``[{"name": "actor", "params": [...], "lr": ...}, {"name": "critic", ...},
        {"name": "alpha", ...}, {"name": "kappa", ...}]``, each parameter once. Pass
        the list to one optimizer, or one group each to separate optimizers (what
        ``train.py`` does).

    Example:
        >>> import torch
        >>> from torchrl.data import Bounded
        >>> from wcsac_rl import WCSACLoss, make_actor, make_qvalue, make_safety_critic
        >>> loss = WCSACLoss(make_actor(4, Bounded(-1.0, 1.0, shape=(2,))),
        ...                  [make_qvalue(4, 2) for _ in range(2)], make_safety_critic(4, 2))
        >>> groups = param_groups(loss, lr=1e-3, kappa_lr_scale=5.0)
        >>> [(g["name"], g["lr"]) for g in groups]
        [('actor', 0.001), ('critic', 0.001), ('alpha', 0.001), ('kappa', 0.005)]
        >>> optim = torch.optim.Adam(groups)
    """
    for name, value in (("lr", lr), ("actor_lr", actor_lr), ("kappa_lr_scale", kappa_lr_scale)):
        if value is None and name == "actor_lr":
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
            raise ValueError(f"{name} must be a number > 0, got {value!r}")
    critics = list(loss.qvalue_network_params.values(True, True))
    safety = getattr(loss, "safety_network_params", None)
    if safety is not None:
        critics += list(safety.values(True, True))
    groups = [
        {
            "name": "actor",
            "params": list(loss.actor_network_params.values(True, True)),
            "lr": float(lr if actor_lr is None else actor_lr),
        },
        {"name": "critic", "params": critics, "lr": float(lr)},
    ]
    if isinstance(loss.log_alpha, torch.nn.Parameter):  # (a buffer with fixed_alpha=True)
        groups.append({"name": "alpha", "params": [loss.log_alpha], "lr": float(lr)})
    constraint = getattr(loss, "constraint", None)
    if constraint is not None and constraint.rule == "gradient":
        groups.append(
            {"name": "kappa", "params": [constraint.kappa_raw], "lr": float(lr * kappa_lr_scale)}
        )
    # only what trains: a parameter shared with the actor (separate_losses) is one
    # already listed, a detached copy is none
    seen: set[int] = set()
    for group in groups:
        params = []
        for p in group["params"]:
            if isinstance(p, torch.nn.Parameter) and p.requires_grad and id(p) not in seen:
                seen.add(id(p))
                params.append(p)
        group["params"] = params
    return [g for g in groups if g["params"]]


# κ's parameters alive in this process, by id (weak: a dropped loss leaves no trace)
_MULTIPLIERS: dict[int, weakref.ref] = {}
# optimizers already looked at (each is checked at its first step only)
_CHECKED: weakref.WeakSet = weakref.WeakSet()
_HOOK = None


def watch_multiplier(parameter: torch.nn.Parameter) -> None:
    """Mark ``parameter`` as a Lagrange multiplier's: an optimizer that trains it in one
    group with other parameters warns at its first step (:class:`SingleGroupWarning`)."""
    global _HOOK
    key = id(parameter)
    _MULTIPLIERS[key] = weakref.ref(parameter, lambda _ref, key=key: _MULTIPLIERS.pop(key, None))
    if _HOOK is None:
        _HOOK = register_optimizer_step_pre_hook(_check_groups)


def _is_multiplier(parameter) -> bool:
    ref = _MULTIPLIERS.get(id(parameter))
    return ref is not None and ref() is parameter


def _check_groups(optimizer, args, kwargs) -> None:
    if optimizer in _CHECKED:
        return None
    _CHECKED.add(optimizer)
    for group in optimizer.param_groups:
        params = group["params"]
        if len(params) > 1 and any(_is_multiplier(p) for p in params):
            warnings.warn(
                f"{type(optimizer).__name__} trains κ (the loss's constraint.kappa_raw) in one "
                f"group with {len(params) - 1} other parameters at lr={group.get('lr')}; the "
                "kit trains κ at its own rate (lr × kappa_lr_scale): build the optimizer from "
                "wcsac_rl.objectives.param_groups(loss, lr=..., kappa_lr_scale=...), or filter "
                "SingleGroupWarning if one rate is meant",
                SingleGroupWarning,
                stacklevel=3,
            )
            break
    return None
