"""Every option of the safety critic and κ, defined once.

:class:`SafetyOptions` (with :class:`PIDGains`, :class:`IQNOptions` and :class:`ShieldOptions`
inside) is the one definition of each WCSAC / SAC-Lag option: its default, what it may
be, a line saying what it does and which part reads it. Everything else reads these
dataclasses:

* the loss's parts take them: the fields of ``SafetyHeadOptions`` and ``SignalOptions``
  (:mod:`wcsac_rl.objectives.loss_options`) are these fields, checked with
  :func:`check_options` (each option's :class:`Option`, then the :data:`RELATIONS`
  between them); a recipe (``PAPER_OPTIONS``, ``wcsac_rl.recipes.KIT_OPTIONS``)
  is what it sets over these defaults;
* the training config (``conf/algo/wcsac.yaml``) starts from :func:`config_defaults`,
  registered with Hydra's ConfigStore (:mod:`wcsac_rl.config_schema`); the YAML files
  set only what differs;
* the config validator and ``builders.make_loss`` read ``algo`` with
  :func:`read_options`: one line naming ``algo.<key>`` for a bad or a missing value.

The allowed values of the choices are defined here too; the parts import them. This
module imports nothing heavy (no torch), so ``wcsac-train --help`` can compose the
config.
"""

from __future__ import annotations

import difflib
import math
import numbers
import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType, SimpleNamespace
from typing import Any

__all__ = [
    "ALPHA_INIT",
    "CONSTRAINT_RULES",
    "ENSEMBLE_OPTIONS",
    "ENSEMBLE_READINGS",
    "ENSEMBLE_TARGETS",
    "EPISODE_STATISTICS",
    "KAPPA_ACTIONS",
    "KAPPA_PARAMETRIZATIONS",
    "KAPPA_SIGNALS",
    "KAPPA_STATES",
    "KAPPA_STATISTICS",
    "LOSS_OPTIONS",
    "NUMBER_CEILING",
    "PAPER_CHOICES",
    "PAPER_OPTIONS",
    "RELATIONS",
    "SAFETY_ALGOS",
    "SAFETY_CRITIC_KINDS",
    "VARIANCE_LOSSES",
    "VARIANCE_TARGETS",
    "IQNOptions",
    "Option",
    "PIDGains",
    "Relation",
    "SafetyOptions",
    "ShieldOptions",
    "check_options",
    "check_value",
    "config_defaults",
    "option_spec",
    "range_text",
    "read_options",
]

# ------------------------------------------------------------------ allowed values
SAFETY_ALGOS = ("wcsac", "sac_lag", "cal")
"""The algorithms (``algo.name``) with a safety critic and κ: these options are theirs."""
SAFETY_CRITIC_KINDS = ("gaussian", "iqn")
"""What :func:`~wcsac_rl.modules.make_safety_critic` builds (``kind``)."""
ENSEMBLE_TARGETS = ("own", "max", "merged")
"""Where several safety critics bootstrap from
(:class:`~wcsac_rl.objectives.ensemble_head.EnsembleHead`)."""
ENSEMBLE_READINGS = ("max", "ucb", "tqc")
"""How several safety critics' Γ is read (:mod:`~wcsac_rl.objectives.ensemble_reading`)."""
VARIANCE_LOSSES = ("w2", "mse", "glm")
"""The Gaussian head's variance TD losses (:mod:`~wcsac_rl.objectives.variance`)."""
VARIANCE_TARGETS = ("moment", "td")
"""The Gaussian head's variance TD targets (:mod:`~wcsac_rl.objectives.safety_head`)."""
KAPPA_ACTIONS = ("replay", "policy")
KAPPA_STATES = ("replay", "initial")
KAPPA_STATISTICS = ("mean", "tail")
KAPPA_SIGNALS = ("critic", "max", "episodes")
"""What κ reads (:class:`~wcsac_rl.objectives.constraint.ConstraintSignal`)."""
EPISODE_STATISTICS = ("cvar", "mean", "rate")
"""What :meth:`~wcsac_rl.objectives.EpisodeCostWindow.for_loss` summarises the window
by: the empirical CVaR at the loss's α, the mean episode cost (α = 1: a lower bound
of every CVaR), or the cost rate per step times the episode limit (the mean cost of
full-length episodes at that rate: an episode that ends early at the goal is held to
the rate of a full one, as the paper's per-step threshold holds every state)."""
CONSTRAINT_RULES = ("gradient", "pid")
KAPPA_PARAMETRIZATIONS = ("softplus", "log")
"""How κ moves and how the gradient rule writes it (:mod:`~wcsac_rl.objectives.constraint`)."""


NUMBER_CEILING = 1.0e6
"""The largest value of a number option with no range of its own (a weight, a scale, an
initial multiplier, a gain): the losses are float32, whose 7 significant digits lose the
reward's and the cost's terms (of order 1) beside a term weighted by more than this, and
whose range overflows long before 1e300."""


# ------------------------------------------------------------------ field metadata
@dataclass(frozen=True)
class Option:
    """What one field may be (its ``metadata["option"]``), and who reads it.

    ``kind``: ``"number"`` (finite, within ``low``/``high``; ``*_open``: the bound
    excluded; with no ``high``, at most ``ceiling``), ``"integer"`` (within
    ``low``/``high`` too), ``"flag"`` (true or false), ``"choice"`` (one of ``choices``),
    ``"risk_level"`` (α in (0, 1]) or ``"group"`` (a nested dataclass).
    ``nullable``: null is allowed too. ``unit``: the note in parentheses of the message
    (``"episodes"``); ``finite_words``: say "a finite number in [0, 1e+06]" rather than
    "in [0, 1e+06] (a number)" (the PID gains' wording). ``reader``: the part that reads it
    (``"loss"``: a keyword of :class:`~wcsac_rl.objectives.WCSACLoss`).
    """

    doc: str
    kind: str
    reader: str = "loss"
    choices: tuple[str, ...] = ()
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    nullable: bool = False
    unit: str = ""
    finite_words: bool = False
    holds: str = ""  # a group: what it holds ("the PID gains")
    unknown_label: str | None = None  # a group: refuse unknown keys as "unknown <label> option"
    members: str = "options"  # a group: what its fields are called ("the gains are ...")
    ceiling: float | None = NUMBER_CEILING  # a number with no high: at most this

    @property
    def upper(self) -> float | None:
        """The largest value allowed: ``high``, or a number's ``ceiling``."""
        if self.high is None and self.kind == "number":
            return self.ceiling
        return self.high

    def requirement(self) -> str:
        """What the value must be, as the messages say it (``"> 0 (a number)"``)."""
        null = "null or " if self.nullable else ""
        if self.kind == "choice":
            return f"{null}one of {', '.join(self.choices)}"
        if self.kind == "flag":
            return f"{'null, ' if self.nullable else ''}true or false"
        bounds = range_text(self.low, self.upper, self.low_open, self.high_open)
        if self.kind == "integer":
            return f"{null}an integer {bounds}{f' ({self.unit})' if self.unit else ''}"
        if self.finite_words:
            return f"{null}a finite number {bounds}".rstrip()
        if not bounds:
            return f"{null}a finite number"
        return f"{null}{bounds} ({self.unit or 'a number'})"

    def accepts(self, value: Any) -> bool:
        if value is None and self.nullable:
            return True
        if self.kind == "choice":
            return isinstance(value, str) and value in self.choices
        if self.kind == "flag":
            return isinstance(value, bool)
        if isinstance(value, bool) or not isinstance(
            value, int if self.kind == "integer" else (int, float)
        ):
            return False
        return (
            (self.kind == "integer" or math.isfinite(value))
            and (self.low is None or (value > self.low if self.low_open else value >= self.low))
            and (
                self.upper is None
                or (value < self.upper if self.high_open else value <= self.upper)
            )
        )

    def coerce(self, value: Any) -> Any:
        """``value`` (accepted) as the type the readers take (a YAML ``1`` as ``1.0``)."""
        if value is None:
            return None
        cast = {"number": float, "risk_level": float, "integer": int, "flag": bool, "choice": str}
        return cast[self.kind](value)


ALPHA_INIT = Option(
    "the entropy weight β's initial value (SACLoss's alpha_init; off_policy.yaml)",
    "number",
    low=0.0,
    low_open=True,
)
"""What ``alpha_init`` may be, for the loss and the config (``algo.alpha_init``)."""


def range_text(low: float | None, high: float | None, low_open: bool, high_open: bool) -> str:
    """A range as the messages say it: ``"in [0, 1]"``, ``"> 0"``, ``"<= 1"`` (``""``: none;
    an ``int`` bound whole: ``"in [1, 1000000]"``)."""
    low, high = (b if b is None or isinstance(b, int) else f"{b:g}" for b in (low, high))
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {low}"
    if high is not None:
        return f"{'<' if high_open else '<='} {high}"
    return ""


def option(default: Any, doc: str, kind: str, **spec: Any) -> Any:
    """A dataclass field with its default and its :class:`Option` metadata."""
    return field(default=default, metadata={"option": Option(doc, kind, **spec)})


def group_spec(doc: str, **spec: Any) -> dict[str, Option]:
    """The metadata of a nested options dataclass field (``pid``, ``iqn``)."""
    return {"option": Option(doc, "group", **spec)}


def option_spec(cls: type, name: str) -> Option:
    """The :class:`Option` of ``cls``'s field ``name``."""
    return cls.__dataclass_fields__[name].metadata["option"]


def option_default(cls: type, name: str) -> Any:
    """``cls``'s field ``name``'s default."""
    return cls.__dataclass_fields__[name].default


def check_value(key: str, value: Any, spec: Option | str) -> None:
    """Raise ``ValueError("<key> must be <what it may be>, got <value>")`` (one line) if
    ``value`` is not what ``spec`` (a str: that :class:`SafetyOptions` option's) allows
    (a group: left to its own dataclass's checks). An integer of any type (numpy's, a
    one-element integer tensor) is an integer, and a numpy float a number."""
    if isinstance(spec, str):
        spec = option_spec(SafetyOptions, spec)
    if spec.kind == "risk_level":
        from wcsac_rl.objectives.risk import validate_risk_level  # (torch: only when checking)

        validate_risk_level(value, name=key)
    elif spec.kind != "group" and not spec.accepts(_as_python_number(value)):
        raise ValueError(f"{key} must be {spec.requirement()}, got {value!r}")


def _as_python_number(value: Any) -> Any:
    """An integer or a real number of another type as Python's ``int`` or ``float``; any
    other value (a bool, a str, a float tensor) as it is."""
    if isinstance(value, bool | str) or value is None:
        return value
    try:
        return operator.index(value)
    except TypeError:
        return float(value) if isinstance(value, numbers.Real) else value


def read_options(cls: type, values: Mapping[str, Any], prefix: str = "") -> Any:
    """``cls`` (an options dataclass) from the entries of ``values`` (a config node), each
    checked (``ValueError`` naming ``<prefix><key>``) and cast to its type, then the
    :data:`RELATIONS` between them.

    An option (or a group) ``values`` lacks is refused naming it: a composed config has
    every one. Entries that are not fields of ``cls`` are left alone (``algo`` also holds the SAC family's options),
    except in a group with an ``unknown_label`` (``algo.pid.kq`` is refused naming the
    closest gain)."""
    read = {}
    for f in fields(cls):
        spec = f.metadata["option"]
        key = f"{prefix}{f.name}"
        if f.name not in values:
            raise ValueError(f"{key} is missing (a composed config has every option)")
        if spec.kind == "group":
            node = values[f.name]
            if not isinstance(node, Mapping):
                raise ValueError(f"{key} must hold {spec.holds}, got {node!r}")
            nested = f.default_factory
            _refuse_unknown(nested, node, key, spec)
            read[f.name] = read_options(nested, node, f"{key}.")
            continue
        value = values[f.name]
        check_value(key, value, spec)
        read[f.name] = spec.coerce(value)
    _check_relations(read, prefix)
    return cls(**read)


def _refuse_unknown(cls: type, node: Mapping[str, Any], key: str, spec: Option) -> None:
    if spec.unknown_label is None:
        return  # (a key no config has is refused by the config's key check)
    known = [f.name for f in fields(cls)]
    unknown = sorted(set(node) - set(known))
    if unknown:
        paths = [f"{key}.{name}" for name in known]
        close = difflib.get_close_matches(f"{key}.{unknown[0]}", paths, n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise ValueError(
            f"unknown {spec.unknown_label} option {key}.{unknown[0]}{hint}; the "
            f"{spec.members} are {', '.join(sorted(known))}"
        )


def config_defaults(cls: type) -> dict[str, Any]:
    """Every field's default, nested groups as dicts: the node Hydra starts ``algo`` from."""
    out = {}
    for f in fields(cls):
        if f.metadata["option"].kind == "group":
            out[f.name] = config_defaults(f.default_factory)
        else:
            out[f.name] = f.default
    return out


# ------------------------------------------------------------------ the options
@dataclass(frozen=True)
class PIDGains:
    """The PID Lagrangian's knobs (Stooke et al. 2020; OmniSafe's ``PIDLagrangian``),
    for ``kappa_rule="pid"`` (:class:`~wcsac_rl.objectives.constraint.PIDLagrangian`).

    Units: the error is in cost units (the signal's: an episode's cost at the
    default ``kappa_states="initial"``) and κ is dimensionless, so a gain is κ per
    cost unit (``ki``: per cost unit and update). Each field's metadata says what it
    may be; a bad one is refused by name (``pid.kp must be a finite number in [0, 1e+06]``).
    """

    kp: float = option(
        0.05, "proportional gain, on an EMA of the error", "number", low=0.0, finite_words=True
    )
    ki: float = option(
        1.0e-6,
        "integral gain: the integral moves by ki·e per update "
        "(clipped to [0, max_kappa]: anti-windup); starts at kappa_init",
        "number",
        low=0.0,
        finite_words=True,
    )
    i_error_max: float | None = option(
        None,
        "the most one update's error adds to the integral (cost units; the error is "
        "clipped at it, so a costly window winds the integral up by at most what a "
        "cost-free one of the same length, error -d, takes off when this is d); "
        "null: the whole error (Stooke et al.'s)",
        "number",
        low=0.0,
        low_open=True,
        nullable=True,
        finite_words=True,
    )
    kd: float = option(
        0.0,
        "derivative gain, on the rise of the signal's EMA over "
        "d_delay updates (only rises count, as in the paper)",
        "number",
        low=0.0,
        finite_words=True,
    )
    d_delay: int = option(
        1, "updates back the derivative compares with", "integer", low=1, unit="updates"
    )
    p_ema: float = option(
        0.99,
        "EMA factor of the error for P (0: the raw error; 0.99: ~100 updates, one collection)",
        "number",
        low=0.0,
        high=1.0,
        high_open=True,
        unit="an EMA factor",
    )
    d_ema: float = option(
        0.0,
        "EMA factor of the signal for D",
        "number",
        low=0.0,
        high=1.0,
        high_open=True,
        unit="an EMA factor",
    )
    max_kappa: float = option(
        100.0,
        "upper bound of κ and of the integral",
        "number",
        low=0.0,
        low_open=True,
        finite_words=True,
    )

    def __post_init__(self) -> None:
        check_options(self, "pid.")


@dataclass(frozen=True)
class IQNOptions:
    """The implicit quantile safety critic's options (``safety_critic="iqn"``)."""

    num_quantiles: int = option(
        20,
        "N fractions τ per evaluation, one per stratum of [0, 1] ([1 − α, 1] for Γ)",
        "integer",
        low=1,
    )
    num_target_quantiles: int = option(20, "N' target fractions τ'", "integer", low=1)
    num_cosines: int = option(
        64, "cosine embedding of τ (as IQN)", "integer", low=1, reader="network"
    )
    huber_kappa: float = option(
        1.0, "κ_H of the quantile Huber loss (IQN)", "number", low=0.0, low_open=True
    )

    def __post_init__(self) -> None:
        check_options(self, "iqn.")


@dataclass(frozen=True)
class ShieldOptions:
    """The collection-time shield's options (:class:`~wcsac_rl.modules.CriticShield`):
    each training step the policy's action and ``candidates − 1`` more drawn from π are
    read by the safety critic (Γ), and an action reading over ``scale`` × the loss's
    ``cost_threshold`` (what κ holds the start states' Γ under: ``d`` at the defaults)
    is replaced by the first candidate under it, else the lowest. Test episodes play the
    policy alone."""

    candidates: int = option(
        0,
        "actions the safety critic reads per training step, the policy's own included "
        "(0: no shield; else >= 2)",
        "integer",
        low=0,
        reader="collector (CriticShield)",
    )
    scale: float = option(
        1.0,
        "the shield's threshold on Γ(s, a), in units of the loss's cost_threshold",
        "number",
        low=0.0,
        low_open=True,
        reader="collector (CriticShield)",
    )

    def __post_init__(self) -> None:
        check_options(self, "shield.")


@dataclass(frozen=True)
class SafetyOptions:
    """The options of WCSAC's and SAC-Lag's safety critic and κ (``algo.*`` in the config).

    Each field carries its default, what it may be, a line of doc and the part that reads
    it (``reader``; ``docs/architecture.md`` maps the parts). The defaults are the paper's
    WCSAC (:data:`PAPER_OPTIONS`, the loss's defaults, ``algo=wcsac_paper``); the kit's
    recipes set what they change in ``conf/algo/`` (evidence: docs/defaults.md).
    """

    kappa_lr_scale: float = option(
        1.0,
        "κ's Adam lr = algo.lr × this (kappa_rule=gradient)",
        "number",
        low=0.0,
        low_open=True,
        reader="optimizer",
    )
    kappa_hold_goal_rate: float = option(
        0.0,
        "κ held where it starts (its optimizer not stepped) until an epoch in which at "
        "least this share of the finished training episodes reached the goal "
        "(train/goal_rate; kappa_rule=gradient, an env with goals); 0: never held",
        "number",
        low=0.0,
        high=1.0,
        reader="trainer",
    )
    damp_scale: float = option(
        0.0, "MDMM damping of κ in the actor loss (kappa_rule=gradient)", "number", low=0.0
    )
    damp_clamp: bool = option(
        False,
        "the damping term at most κ, so the actor's weight stays >= 0 (CAL's rectification; "
        "false: the authors' unclamped damp)",
        "flag",
    )
    safety_critic: str = option(
        "gaussian",
        "gaussian (mean and variance networks) or iqn (implicit quantile network)",
        "choice",
        choices=SAFETY_CRITIC_KINDS,
        reader="network",
    )
    num_safety_nets: int = option(
        1,
        "how many safety critics (each its own initialisation, target and TD loss); "
        "the actor, κ and the shield read them as ensemble_reading says",
        "integer",
        low=1,
    )
    ensemble_target: str = option(
        "own",
        "num_safety_nets > 1: own (each critic bootstraps from its own target critic), "
        "max (all bootstrap, per row, from the member whose target value is largest: "
        "TD3's clipped double-Q, turned pessimistic for a cost) or merged (IQN critics: "
        "all from every member's target quantiles pooled, TQC's and COX-Q's)",
        "choice",
        choices=ENSEMBLE_TARGETS,
    )
    ensemble_reading: str = option(
        "max",
        "num_safety_nets > 1: the Γ the actor, κ and the shield read: max (the largest "
        "member's), ucb (mean + k_ucb·std over the members, CAL) or tqc (IQN critics: "
        "the CVaR_α of every member's quantiles merged, COX-Q)",
        "choice",
        choices=ENSEMBLE_READINGS,
    )
    k_ucb: float = option(
        0.5,
        "ensemble_reading=ucb: the weight of the members' standard deviation (CAL's k)",
        "number",
        low=0.0,
    )
    k_ucb_lr: float = option(
        0.0,
        "ensemble_reading=ucb: adaptive pessimism (CAP): k_ucb moves by this × (the "
        "episode window's cost − d) per update, within [0, k_ucb_max]; 0: k_ucb fixed",
        "number",
        low=0.0,
    )
    k_ucb_max: float = option(
        2.0,
        "k_ucb_lr > 0: the largest k_ucb",
        "number",
        low=0.0,
    )
    prior_scale: float = option(
        0.0,
        "num_safety_nets > 1: a fixed random network per member, times this, added to "
        "its cost value (randomized prior functions; 0: none)",
        "number",
        low=0.0,
    )
    iqn: IQNOptions = field(
        default_factory=IQNOptions,
        metadata=group_spec(
            "the IQN critic's options (safety_critic=iqn only)",
            holds="the IQN critic's options",
            reader="its fields' readers",
        ),
    )
    risk_level: float = option(
        0.5,
        "α ∈ (0, 1]: the tail fraction whose mean cost "
        "(CVaR_α) is constrained; 1 is the expected cost (SAC-Lag)",
        "risk_level",
    )
    variance: bool = option(
        True,
        "Gaussian safety critic with a variance network (false: mean only, SAC-Lag)",
        "flag",
        reader="network",
    )
    variance_loss: str = option(
        "w2",
        "the variance head's TD loss: w2 (the paper's 2-Wasserstein), mse or glm",
        "choice",
        choices=VARIANCE_LOSSES,
    )
    variance_target: str = option(
        "moment",
        "the variance head's TD target: td (squared TD error + γ_c² V̄') or moment (Eq. 8)",
        "choice",
        choices=VARIANCE_TARGETS,
    )
    kappa_actions: str = option(
        "policy",
        "the actions κ reads Γ at: policy (a ~ π) or replay",
        "choice",
        choices=KAPPA_ACTIONS,
    )
    kappa_states: str = option(
        "replay",
        "the states κ reads Γ at: initial (episode starts, vs d) or replay (batch states)",
        "choice",
        choices=KAPPA_STATES,
    )
    kappa_statistic: str = option(
        "mean",
        "tail (CVaR_α of the critic mixed over the states) or mean (of per-state Γ)",
        "choice",
        choices=KAPPA_STATISTICS,
    )
    kappa_signal: str = option(
        "critic",
        "what κ holds under d: critic (Γ), max (of Γ and the recent episodes') or episodes",
        "choice",
        choices=KAPPA_SIGNALS,
    )
    kappa_signal_every: int = option(
        1,
        "kappa_states=initial with kappa_statistic=tail: the critic's start-state "
        "statistic is read every this many training updates and held in between "
        "(1: every update)",
        "integer",
        low=1,
        unit="updates",
    )
    kappa_episode_window: int = option(
        30,
        "kappa_signal max/episodes: the last finished training episodes it reads",
        "integer",
        low=1,
        unit="episodes",
        reader="episode window",
    )
    kappa_episode_statistic: str = option(
        "cvar",
        "kappa_signal max/episodes: their empirical CVaR_α, their mean, or their cost "
        "rate (per step, times the episode limit)",
        "choice",
        choices=EPISODE_STATISTICS,
        reader="episode window",
    )
    kappa_test_window: int = option(
        0,
        "kappa_signal max/episodes: the last deterministic test episodes (eval_episodes "
        "per epoch) whose empirical CVaR_α floors κ's signal too (what Table 1 "
        "measures; 0: none)",
        "integer",
        low=0,
        unit="episodes",
        reader="episode window",
    )
    kappa_rule: str = option(
        "gradient",
        "how κ moves: gradient (Adam on loss_kappa) or pid (PID Lagrangian)",
        "choice",
        choices=CONSTRAINT_RULES,
    )
    pid: PIDGains = field(
        default_factory=PIDGains,
        metadata=group_spec(
            "kappa_rule=pid: the controller's gains",
            holds="the PID gains",
            unknown_label="PID",
            members="gains",
        ),
    )
    shield: ShieldOptions = field(
        default_factory=ShieldOptions,
        metadata=group_spec(
            "a collection-time shield on the safety critic's reading of each action",
            holds="the shield's options",
            reader="collector (CriticShield)",
            unknown_label="shield",
        ),
    )
    kappa_init: float = option(
        math.log(2.0),
        "κ's initial value: softplus(0), the authors'; > 0 under the gradient rule, "
        "the PID rule may start at 0",
        "number",
        low=0.0,
    )
    kappa_parametrization: str = option(
        "softplus",
        "κ = softplus(raw) (authors) or exp(raw) (log)",
        "choice",
        choices=KAPPA_PARAMETRIZATIONS,
    )
    kappa_max: float | None = option(
        None,
        "kappa_rule=gradient: an upper bound of κ, kappa_raw projected under it at every "
        "update (no windup; OmniSafe's lagrangian_upper_bound); null: none, the paper",
        "number",
        low=0.0,
        low_open=True,
        nullable=True,
    )
    kappa_min: float = option(
        0.0,
        "a floor under κ (either rule): the gradient rule's kappa_raw is projected over it "
        "at every update, the PID's output clipped at it; 0: none, the paper",
        "number",
        low=0.0,
        finite_words=True,
    )
    cost_gamma: float | None = option(
        None,
        "γ_c of the safety critic (null: the reward's γ, the paper)",
        "number",
        low=0.0,
        high=1.0,
        nullable=True,
    )
    cost_bootstrap_truncated: bool | None = option(
        None,
        "bootstrap the safety critic across time limits (null: only if γ_c < 1)",
        "flag",
        nullable=True,
    )
    cost_n_steps: int = option(
        1,
        "the safety critic's TD targets bootstrap n steps ahead (1: the paper)",
        "integer",
        low=1,
    )
    nonnegative_cost: bool = option(
        False, "max(Q^c, 0) in targets and Γ (false: the paper)", "flag"
    )

    def __post_init__(self) -> None:
        check_options(self, relations=False)  # (relations: read_options and the parts)


LOSS_OPTIONS = tuple(
    f.name
    for cls in (SafetyOptions, IQNOptions)
    for f in fields(cls)
    if f.metadata["option"].reader == "loss" and f.metadata["option"].kind != "group"
)
"""The options the loss's parts take (:mod:`wcsac_rl.objectives.loss_options`: the fields of
``SafetyHeadOptions``, ``SignalOptions`` and the constraint's)."""


ENSEMBLE_OPTIONS: tuple[str, ...] = (
    "num_safety_nets",
    "ensemble_target",
    "ensemble_reading",
    "k_ucb",
    "k_ucb_lr",
    "k_ucb_max",
    "prior_scale",
)
"""The safety-critic ensemble's options: how many critics, how they bootstrap and are read."""


# ------------------------------------------------------------------ relations
@dataclass(frozen=True)
class Relation:
    """A rule between options (or an option and a value read elsewhere: the critics'
    ``safety_critic`` kind): ``refuses(o)`` is true for the values it refuses (``o``: the
    options by attribute), ``message`` says why in one line (``str.format`` of the
    values, ``{p}``: the prefix naming them). Checked where all of ``names`` are given."""

    names: tuple[str, ...]
    refuses: Callable[[Any], bool]
    message: str


RELATIONS: tuple[Relation, ...] = (
    Relation(
        ("ensemble_target", "num_safety_nets"),
        lambda o: o.ensemble_target != "own" and o.num_safety_nets < 2,
        "{p}ensemble_target={ensemble_target} picks among several safety critics: it needs "
        "{p}num_safety_nets >= 2",
    ),
    Relation(
        ("ensemble_reading", "num_safety_nets"),
        lambda o: o.ensemble_reading != "max" and o.num_safety_nets < 2,
        "{p}ensemble_reading={ensemble_reading} reads an ensemble of safety critics: it "
        "needs {p}num_safety_nets >= 2, got {num_safety_nets}",
    ),
    Relation(
        ("prior_scale", "num_safety_nets"),
        lambda o: o.prior_scale > 0 and o.num_safety_nets < 2,
        "{p}prior_scale > 0 reads an ensemble of safety critics: it needs "
        "{p}num_safety_nets >= 2, got {num_safety_nets}",
    ),
    Relation(
        ("k_ucb", "ensemble_reading"),
        lambda o: o.ensemble_reading != "ucb" and o.k_ucb != option_default(SafetyOptions, "k_ucb"),
        "{p}k_ucb={k_ucb:g} weighs the members' spread in the UCB reading, which this one "
        "does not read: it needs {p}ensemble_reading=ucb, got {ensemble_reading}",
    ),
    Relation(
        ("k_ucb_lr", "ensemble_reading"),
        lambda o: o.k_ucb_lr > 0 and o.ensemble_reading != "ucb",
        "{p}k_ucb_lr={k_ucb_lr:g} adapts the UCB reading's k_ucb: it needs "
        "{p}ensemble_reading=ucb, got {ensemble_reading}",
    ),
    Relation(
        ("k_ucb", "k_ucb_lr", "k_ucb_max"),
        lambda o: o.k_ucb_lr > 0 and not o.k_ucb <= o.k_ucb_max,
        "{p}k_ucb must be <= {p}k_ucb_max ({k_ucb_max:g}) with {p}k_ucb_lr > 0, got {k_ucb:g}",
    ),
    Relation(
        ("ensemble_reading", "ensemble_target"),
        lambda o: o.ensemble_reading == "ucb" and o.ensemble_target != "own",
        "{p}ensemble_reading=ucb reads the members' disagreement: each bootstraps from its "
        "own target ({p}ensemble_target=own), got {ensemble_target}",
    ),
    Relation(
        ("ensemble_target", "safety_critic"),
        lambda o: o.ensemble_target == "merged" and o.safety_critic != "iqn",
        "{p}ensemble_target=merged pools the members' target quantiles: it needs "
        "{p}safety_critic=iqn, got a {safety_critic} critic",
    ),
    Relation(
        ("ensemble_reading", "safety_critic"),
        lambda o: o.ensemble_reading == "tqc" and o.safety_critic != "iqn",
        "{p}ensemble_reading=tqc merges the members' quantiles: it needs "
        "{p}safety_critic=iqn, got a {safety_critic} critic",
    ),
    Relation(
        ("kappa_signal", "kappa_states"),
        lambda o: o.kappa_signal != "critic" and o.kappa_states != "initial",
        "{p}kappa_signal={kappa_signal} needs {p}kappa_states=initial (episode costs are "
        "compared with the episodic limit d), got {kappa_states}",
    ),
    Relation(
        ("kappa_signal_every", "kappa_states", "kappa_statistic"),
        lambda o: (
            o.kappa_signal_every > 1
            and (o.kappa_states != "initial" or o.kappa_statistic != "tail")
        ),
        "{p}kappa_signal_every={kappa_signal_every} holds the critic's start-state tail "
        "between reads: it needs {p}kappa_states=initial and {p}kappa_statistic=tail, got "
        "{kappa_states} and {kappa_statistic}",
    ),
    Relation(
        ("kappa_test_window", "kappa_signal"),
        lambda o: o.kappa_test_window > 0 and o.kappa_signal == "critic",
        "{p}kappa_test_window={kappa_test_window} floors κ's signal by the test episodes' "
        "cost: it needs {p}kappa_signal=max (or episodes), got critic",
    ),
    Relation(
        ("kappa_hold_goal_rate", "kappa_rule"),
        lambda o: o.kappa_hold_goal_rate > 0 and o.kappa_rule != "gradient",
        "{p}kappa_hold_goal_rate={kappa_hold_goal_rate:g} holds κ's optimizer until the "
        "task is learned: it needs {p}kappa_rule=gradient, got {kappa_rule}",
    ),
    Relation(
        ("kappa_init", "kappa_rule"),
        lambda o: o.kappa_rule != "pid" and not o.kappa_init > 0,
        "{p}kappa_init must be > 0 with the gradient rule (κ is softplus or exp of a "
        "parameter; {p}kappa_rule=pid may start at 0), got {kappa_init:g}",
    ),
    Relation(
        ("kappa_init", "kappa_min"),
        lambda o: o.kappa_min > o.kappa_init,
        "{p}kappa_min must be <= {p}kappa_init ({kappa_init:g}, where κ starts), got {kappa_min:g}",
    ),
    Relation(
        ("kappa_max", "kappa_rule"),
        lambda o: o.kappa_max is not None and o.kappa_rule == "pid",
        "{p}kappa_max={kappa_max:g} bounds the gradient rule's κ; with {p}kappa_rule=pid "
        "the bound is {p}pid.max_kappa",
    ),
    Relation(
        ("kappa_init", "kappa_max"),
        lambda o: o.kappa_max is not None and not o.kappa_max >= o.kappa_init,
        "{p}kappa_max must be a finite number >= {p}kappa_init ({kappa_init:g}, where κ "
        "starts), got {kappa_max}",
    ),
    Relation(
        ("kappa_init", "kappa_rule", "pid"),
        lambda o: o.kappa_rule == "pid" and o.kappa_init > o.pid.max_kappa,
        "{p}kappa_init must be <= {p}pid.max_kappa ({pid.max_kappa:g}) with "
        "{p}kappa_rule=pid, got {kappa_init:g}",
    ),
    Relation(
        ("candidates",),
        lambda o: o.candidates == 1,
        "{p}candidates must be 0 (no shield) or >= 2 (the policy's action and at least one "
        "other), got 1",
    ),
)
"""Every rule between options, each written once: the parts' options
(``SafetyHeadOptions``, ``SignalOptions``, :class:`ShieldOptions`), the constraint, the
ensemble head (with its critics' kind) and the config (:func:`read_options`) check the
ones among the options they hold (:func:`check_options`)."""


def check_options(options: Any, prefix: str = "", *, relations: bool = True, **more: Any) -> None:
    """Check each option of ``options`` (an options dataclass, or a mapping of
    ``SafetyOptions``' option names to values) as its :class:`Option` allows, then
    (``relations``) every :data:`RELATIONS` rule among them and ``more`` (a value read
    elsewhere: the critics' ``safety_critic`` kind). One ``ValueError`` line naming the
    options with ``prefix`` (``"algo."``: the config; ``"pid."``: a group)."""
    if isinstance(options, Mapping):
        values = dict(options)
        specs = {name: option_spec(SafetyOptions, name) for name in values}
    else:
        values = {f.name: getattr(options, f.name) for f in fields(options)}
        specs = {f.name: f.metadata["option"] for f in fields(options)}
    for name, value in values.items():
        check_value(f"{prefix}{name}", value, specs[name])
    if relations:
        _check_relations({**values, **more}, prefix)


def _check_relations(values: dict[str, Any], prefix: str) -> None:
    given = SimpleNamespace(**values)
    for relation in RELATIONS:
        if set(relation.names) <= values.keys() and relation.refuses(given):
            raise ValueError(relation.message.format(p=prefix, **values))


PAPER_CHOICES = (
    "variance_loss",
    "variance_target",
    "cost_gamma",
    "cost_n_steps",
    "nonnegative_cost",
    "kappa_states",
    "kappa_statistic",
    "kappa_signal",
    "kappa_rule",
)
"""The options whose paper values the kit's recipes change (``conf/algo/wcsac.yaml``)."""

PAPER_OPTIONS: Mapping[str, Any] = MappingProxyType(
    {name: option_default(SafetyOptions, name) for name in PAPER_CHOICES}
)
"""The safety critic and κ as the paper writes them, which are ``SafetyOptions``' defaults
(Eq. 7–8 with the variance head trained by the 2-Wasserstein TD, one-step targets with
the reward's γ, κ on the mean Γ over replay states against the per-step threshold): the
loss's own defaults and ``algo=wcsac_paper``; printed, the paper's value of each option
the kit's recipes change. ``WCSACLoss(..., **loss_parts(PAPER_OPTIONS))`` is
``WCSACLoss(...)``. The kit's recipes differ, on StaticEnv evidence (docs/defaults.md;
``wcsac_rl.recipes.KIT_OPTIONS``)."""
