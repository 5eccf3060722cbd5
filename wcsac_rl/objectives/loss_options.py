"""The parts :class:`~wcsac_rl.objectives.WCSACLoss` takes as arguments, and a recipe's parts.

The loss is TorchRL-style: the networks first, then a handful of keywords, and each part
an object a user builds, reads and swaps on its own:

* ``safety_head=SafetyHeadOptions(...)``: the safety critic's head — its TD target
  (γ_c, n steps, time limits), the Gaussian head's variance loss and target, the IQN
  head's quantiles, an ensemble of critics and how it is read, ``max(Q^c, 0)``;
* ``signal=SignalOptions(...)``: what κ holds under the threshold (which states and
  actions the critic is read at, which statistic, the critic or the recent episodes);
* ``constraint=GradientLagrangian(...)`` or ``PIDLagrangian(...)``: κ and the rule that
  moves it (:mod:`wcsac_rl.objectives.constraint`).

Each field of the two options classes *is* the field of the same name of
:class:`~wcsac_rl.options.SafetyOptions` (its default, what it may be and its doc:
defined once); a bad value is refused in one ``ValueError`` line naming it.
:func:`loss_parts` gives the loss's keywords for a whole recipe (``PAPER_OPTIONS``,
``kit_options("dynamic")``, a config's ``SafetyOptions``).
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

from wcsac_rl.objectives.constraint import GradientLagrangian, PIDLagrangian, make_constraint
from wcsac_rl.objectives.safety_head import is_iqn_critic
from wcsac_rl.options import (
    ALPHA_INIT,
    PAPER_OPTIONS,
    IQNOptions,
    PIDGains,
    SafetyOptions,
    ShieldOptions,
    check_options,
    check_value,
)
from wcsac_rl.recipes import TRAINER_KEYS

__all__ = [
    "PART_OF_OPTION",
    "SafetyHeadOptions",
    "SignalOptions",
    "claim_constraint",
    "default_parts",
    "loss_parts",
    "options_constraint",
]


def _same(cls: type, name: str) -> Any:
    """``cls``'s field ``name`` (its default and its option metadata), for another class."""
    source = cls.__dataclass_fields__[name]
    return field(default=source.default, metadata=source.metadata)


@dataclass(frozen=True)
class SafetyHeadOptions:
    """The safety critic's head (:func:`~wcsac_rl.objectives.ensemble_head.make_safety_head`)
    and its TD target (:class:`~wcsac_rl.objectives.safety_head.CostTarget`).

    ``cost_gamma`` (γ_c; ``None``: the value estimator's γ, the paper),
    ``cost_bootstrap_truncated`` (``None``: only when γ_c < 1) and ``cost_n_steps`` (``1``:
    the paper; ``n > 1`` reads :class:`~wcsac_rl.objectives.NStepCost`'s entries);
    ``nonnegative_cost`` (``max(Q^c, 0)`` where Q^c is used); the Gaussian head's
    ``variance_loss`` and ``variance_target``; the IQN head's ``num_quantiles``,
    ``num_target_quantiles`` and ``huber_kappa``; with ``num_safety_nets`` > 1, where the
    critics bootstrap (``ensemble_target``), how the actor, κ and a shield read them
    (``ensemble_reading``, ``k_ucb`` adapted by ``k_ucb_lr`` up to ``k_ucb_max``) and
    their random priors (``prior_scale``). Each field is ``SafetyOptions``' (or
    ``IQNOptions``') of that name. The Gaussian head's options are refused for an IQN
    critic unless left at their defaults.

    Example:
        >>> SafetyHeadOptions(cost_n_steps=1).cost_n_steps
        1
        >>> SafetyHeadOptions(num_quantiles=0)
        Traceback (most recent call last):
        ...
        ValueError: num_quantiles must be an integer >= 1, got 0
    """

    cost_gamma: float | None = _same(SafetyOptions, "cost_gamma")
    cost_bootstrap_truncated: bool | None = _same(SafetyOptions, "cost_bootstrap_truncated")
    cost_n_steps: int = _same(SafetyOptions, "cost_n_steps")
    nonnegative_cost: bool = _same(SafetyOptions, "nonnegative_cost")
    variance_loss: str = _same(SafetyOptions, "variance_loss")
    variance_target: str = _same(SafetyOptions, "variance_target")
    num_quantiles: int = _same(IQNOptions, "num_quantiles")
    num_target_quantiles: int = _same(IQNOptions, "num_target_quantiles")
    huber_kappa: float = _same(IQNOptions, "huber_kappa")
    num_safety_nets: int = _same(SafetyOptions, "num_safety_nets")
    ensemble_target: str = _same(SafetyOptions, "ensemble_target")
    ensemble_reading: str = _same(SafetyOptions, "ensemble_reading")
    k_ucb: float = _same(SafetyOptions, "k_ucb")
    k_ucb_lr: float = _same(SafetyOptions, "k_ucb_lr")
    k_ucb_max: float = _same(SafetyOptions, "k_ucb_max")
    prior_scale: float = _same(SafetyOptions, "prior_scale")

    def __post_init__(self) -> None:
        check_options(self)


@dataclass(frozen=True)
class SignalOptions:
    """What κ holds under the threshold (:class:`~wcsac_rl.objectives.constraint.ConstraintSignal`).

    ``kappa_states`` (``"initial"``: episode start states, from
    :class:`~wcsac_rl.objectives.StartStateBuffer`, against ``d``; ``"replay"``: the
    batch, against the per-step threshold), ``kappa_actions``, ``kappa_statistic``,
    ``kappa_signal`` (``"critic"``, or ``"max"`` / ``"episodes"`` reading
    :class:`~wcsac_rl.objectives.EpisodeCostWindow`'s ``episode_cvar``) and
    ``kappa_signal_every`` (hold the start-state tail between reads). Each field is
    ``SafetyOptions``' of that name.

    Example:
        >>> SignalOptions(kappa_states="replay", kappa_statistic="mean").kappa_signal
        'critic'
    """

    kappa_states: str = _same(SafetyOptions, "kappa_states")
    kappa_actions: str = _same(SafetyOptions, "kappa_actions")
    kappa_statistic: str = _same(SafetyOptions, "kappa_statistic")
    kappa_signal: str = _same(SafetyOptions, "kappa_signal")
    kappa_signal_every: int = _same(SafetyOptions, "kappa_signal_every")

    def __post_init__(self) -> None:
        check_options(self)


_GROUPS = {"pid": PIDGains, "iqn": IQNOptions, "shield": ShieldOptions}


def _safety_options(recipe: Mapping[str, Any]) -> SafetyOptions:
    """``SafetyOptions()`` with what ``recipe`` sets (groups as mappings or dataclasses);
    a key that is neither an option nor a trainer key of a recipe is refused by name."""
    known = {f.name for f in fields(SafetyOptions)}
    changes = {}
    for key, value in recipe.items():
        if key in _GROUPS:
            group = getattr(SafetyOptions(), key)
            if isinstance(value, Mapping):
                unknown = sorted(set(value) - {f.name for f in fields(group)})
                if unknown:
                    raise ValueError(f"unknown option {key}.{unknown[0]} in the recipe")
                value = replace(group, **value)
            elif not isinstance(value, type(group)):
                raise ValueError(
                    f"{key} must be a {type(group).__name__} or a mapping of its fields, "
                    f"got {value!r}"
                )
            changes[key] = value
        elif key in known:
            changes[key] = value
        elif key not in TRAINER_KEYS:
            raise ValueError(
                f"unknown option {key!r} in the recipe: not a SafetyOptions field nor one of "
                f"the trainer's ({', '.join(TRAINER_KEYS)})"
            )
    return replace(SafetyOptions(), **changes)


def options_constraint(options: SafetyOptions) -> GradientLagrangian | PIDLagrangian:
    """The constraint ``options`` select: the gradient rule with its κ options, or the
    PID rule with its gains (then the gradient rule's damping is not read)."""
    pid = options.kappa_rule == "pid"
    return make_constraint(
        options.kappa_rule,
        kappa_init=options.kappa_init,
        parametrization=options.kappa_parametrization,
        damp_scale=0.0 if pid else options.damp_scale,
        kappa_max=options.kappa_max,
        kappa_min=options.kappa_min,
        pid=options.pid if pid else None,
        damp_clamp=False if pid else options.damp_clamp,
    )


def loss_parts(recipe: SafetyOptions | Mapping[str, Any] | None = None) -> dict[str, Any]:
    """:class:`~wcsac_rl.objectives.WCSACLoss`'s keywords for a recipe:
    ``safety_head``, ``signal``, a new ``constraint`` and ``alpha_init``.

    ``recipe``: what a recipe sets over ``SafetyOptions``' defaults and
    ``off_policy.yaml``'s (``PAPER_OPTIONS``, ``KIT_OPTIONS``, ``kit_options("dynamic")``,
    ``{**PAPER_OPTIONS, "cost_n_steps": 5}``; ``None``: nothing), or a ``SafetyOptions``
    (a config read with :func:`~wcsac_rl.options.read_options`; ``alpha_init`` is then
    the off-policy default). The trainer's keys a recipe holds (learning rates, the
    episode window) are not the loss's and are left out, as is ``risk_level`` (the
    loss's first keyword: give it yourself). The Gaussian head's options stay at their
    defaults with ``safety_critic="iqn"`` (an IQN head has no variance to learn); a
    Gaussian head does not read the IQN head's.

    Example:
        >>> from wcsac_rl.objectives import PAPER_OPTIONS
        >>> parts = loss_parts(PAPER_OPTIONS)
        >>> parts["signal"].kappa_states, parts["safety_head"].cost_n_steps, parts["alpha_init"]
        ('replay', 1, 1.0)
    """
    alpha_init = TRAINER_KEYS["alpha_init"]
    if not isinstance(recipe, (SafetyOptions, Mapping, type(None))):
        raise TypeError(
            "loss_parts takes a recipe: a mapping of options (e.g. PAPER_OPTIONS, "
            f"kit_options()) or a SafetyOptions, got {type(recipe).__name__} {recipe!r:.60}"
        )
    if isinstance(recipe, SafetyOptions):
        options = recipe
    else:
        recipe = dict(recipe or {})
        alpha_init = recipe.get("alpha_init", alpha_init)  # (checked by the loss)
        options = _safety_options(recipe)
    head = {f.name: getattr(options, f.name, None) for f in fields(SafetyHeadOptions)}
    head.update({name: getattr(options.iqn, name) for name in _IQN_HEAD})
    if options.safety_critic == "iqn":  # (an IQN head refuses the Gaussian head's options)
        for name in _GAUSSIAN_HEAD:
            head[name] = SafetyHeadOptions.__dataclass_fields__[name].default
    return {
        "safety_head": SafetyHeadOptions(**head),
        "signal": SignalOptions(
            **{f.name: getattr(options, f.name) for f in fields(SignalOptions)}
        ),
        "constraint": options_constraint(options),
        "alpha_init": alpha_init,
    }


_IQN_HEAD = ("num_quantiles", "num_target_quantiles", "huber_kappa")
_GAUSSIAN_HEAD = ("variance_loss", "variance_target")

_PARTS = {
    "safety_head": (SafetyHeadOptions, "SafetyHeadOptions"),
    "signal": (SignalOptions, "SignalOptions"),
    "constraint": ((GradientLagrangian, PIDLagrangian), "GradientLagrangian or PIDLagrangian"),
}

PART_OF_OPTION: Mapping[str, str] = {
    **{f.name: f"safety_head=SafetyHeadOptions({f.name}=...)" for f in fields(SafetyHeadOptions)},
    **{f.name: f"signal=SignalOptions({f.name}=...)" for f in fields(SignalOptions)},
    **{
        name: f"constraint={where}"
        for name, where in (
            ("kappa_rule", "GradientLagrangian(...) or PIDLagrangian(...)"),
            ("kappa_init", "GradientLagrangian(kappa_init=...)"),
            ("kappa_parametrization", "GradientLagrangian(parametrization=...)"),
            ("damp_scale", "GradientLagrangian(damp_scale=...)"),
            ("damp_clamp", "GradientLagrangian(damp_clamp=...)"),
            ("kappa_max", "GradientLagrangian(kappa_max=...)"),
            ("kappa_min", "GradientLagrangian(kappa_min=...)"),
            ("pid", "PIDLagrangian(gains=PIDGains(...))"),
        )
    },
}
"""Where each option of a flat recipe goes among the loss's parts (a keyword the loss
does not take is refused naming its part)."""


_OWNERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def claim_constraint(
    loss: Any, constraint: GradientLagrangian | PIDLagrangian
) -> GradientLagrangian | PIDLagrangian:
    """Make ``constraint`` ``loss``'s own (returned): a constraint (κ and its state) already
    held by another live loss is refused in one line, since training either loss would
    move the other's κ. A copy (``copy.deepcopy``) is a new constraint and may be claimed."""
    owner = _OWNERS.get(constraint)
    holder = None if owner is None else owner()
    if holder is not None and holder is not loss:
        raise ValueError(
            f"constraint is another {type(holder).__name__}'s (its {type(constraint).__name__} "
            "holds that loss's κ, which training this one would move): give each loss its "
            "own, e.g. a new loss_parts(recipe) per loss or copy.deepcopy(constraint)"
        )
    _OWNERS[constraint] = weakref.ref(loss)
    return constraint


def default_parts(
    safety_network: Any,
    safety_head: SafetyHeadOptions | None,
    signal: SignalOptions | None,
    constraint: GradientLagrangian | PIDLagrangian | None,
    alpha_init: Any = TRAINER_KEYS["alpha_init"],
) -> tuple[SafetyHeadOptions, SignalOptions, GradientLagrangian | PIDLagrangian]:
    """The parts given, and the paper's (:data:`~wcsac_rl.options.PAPER_OPTIONS`, for the
    kind of ``safety_network``: Gaussian or IQN) for those that are ``None``: read only
    what any TorchRL batch holds (no n-step entries, start states or episode window). A
    part of the wrong kind, or an ``alpha_init`` that is not a number in its range, is
    refused in one line naming it."""
    check_value("alpha_init", alpha_init, ALPHA_INIT)
    given = {"safety_head": safety_head, "signal": signal, "constraint": constraint}
    for name, value in given.items():
        kind, label = _PARTS[name]
        if value is not None and not isinstance(value, kind):
            raise ValueError(f"{name} must be a {label}, got {type(value).__name__}")
    if None in given.values():
        first = safety_network[0] if isinstance(safety_network, (list, tuple)) else safety_network
        kind = "iqn" if is_iqn_critic(first) else "gaussian"
        paper = loss_parts({**PAPER_OPTIONS, "safety_critic": kind})
        given = {name: paper[name] if value is None else value for name, value in given.items()}
    return given["safety_head"], given["signal"], given["constraint"]
