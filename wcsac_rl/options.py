"""Every option of the safety critic and κ, defined once.

:class:`SafetyOptions` (with :class:`PIDGains`, :class:`IQNOptions` and :class:`ShieldOptions`
inside) is the one definition of each WCSAC / SAC-Lag option: its default, what it may
be, a line saying what it does and which part reads it. Everything else reads these
dataclasses:

* the loss's parts take them: the fields of ``SafetyHeadOptions`` and ``SignalOptions``
  (:mod:`wcsac_rl.objectives.loss_options`) are these fields, checked with
  :func:`check_value`; a recipe (``PAPER_OPTIONS``, ``wcsac_rl.recipes.KIT_OPTIONS``)
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
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType
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
    "SAFETY_ALGOS",
    "SAFETY_CRITIC_KINDS",
    "VARIANCE_LOSSES",
    "VARIANCE_TARGETS",
    "IQNOptions",
    "Option",
    "PIDGains",
    "SafetyOptions",
    "ShieldOptions",
    "check_ensemble",
    "check_fields",
    "check_kappa_bound",
    "check_shield_candidates",
    "check_signal_every",
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
"""What κ reads (:mod:`~wcsac_rl.objectives.constraint_signal`)."""
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
    excluded; with no ``high``, at most :data:`NUMBER_CEILING`), ``"integer"``
    (``>= low``), ``"flag"`` (true or false), ``"choice"`` (one of ``choices``), ``"risk_level"`` (α in (0, 1]) or ``"group"`` (a nested dataclass).
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

    @property
    def upper(self) -> float | None:
        """The largest value allowed: ``high``, or a number's :data:`NUMBER_CEILING`."""
        if self.high is None and self.kind == "number":
            return NUMBER_CEILING
        return self.high

    def requirement(self) -> str:
        """What the value must be, as the messages say it (``"> 0 (a number)"``)."""
        null = "null or " if self.nullable else ""
        if self.kind == "choice":
            return f"{null}one of {', '.join(self.choices)}"
        if self.kind == "flag":
            return f"{'null, ' if self.nullable else ''}true or false"
        unit = f" ({self.unit})" if self.unit else ""
        if self.kind == "integer":
            return f"{null}an integer >= {self.low:g}{unit}"
        bounds = range_text(self.low, self.upper, self.low_open, self.high_open)
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
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if self.kind == "integer":
            return isinstance(value, int) and value >= self.low
        return (
            math.isfinite(value)
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
    """A range as the messages say it: ``"in [0, 1]"``, ``"> 0"``, ``"<= 1"`` (``""``: none)."""
    if low is not None and high is not None:
        return f"in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    if low is not None:
        return f"{'>' if low_open else '>='} {low:g}"
    if high is not None:
        return f"{'<' if high_open else '<='} {high:g}"
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


def check_value(key: str, value: Any, spec: Option) -> None:
    """Raise ``ValueError("<key> must be <what it may be>, got <value>")`` (one line) if
    ``value`` is not what ``spec`` allows. The loss, the parts' options dataclasses and
    the config validator all check with this."""
    if spec.kind == "risk_level":
        from wcsac_rl.objectives.risk import validate_risk_level  # (torch: only when checking)

        validate_risk_level(value, name=key)
    elif spec.kind != "group" and not spec.accepts(value):
        raise ValueError(f"{key} must be {spec.requirement()}, got {value!r}")


def check_fields(instance: Any, prefix: str = "") -> None:
    """Check every (non-group) field of a dataclass ``instance`` (``prefix``: how the
    messages name them, ``"pid."``)."""
    for f in fields(instance):
        spec = f.metadata["option"]
        if spec.kind != "group":
            check_value(f"{prefix}{f.name}", getattr(instance, f.name), spec)


def read_options(cls: type, values: Mapping[str, Any], prefix: str = "") -> Any:
    """``cls`` (an options dataclass) from the entries of ``values`` (a config node), each
    checked (``ValueError`` naming ``<prefix><key>``) and cast to its type.

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
        check_fields(self, "pid.")


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
        check_fields(self, "iqn.")


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
        check_fields(self, "shield.")  # (candidates=1: check_shield_candidates)


def check_shield_candidates(candidates: int, prefix: str = "") -> None:
    """``candidates`` is 0 (no shield) or at least 2: one ``ValueError`` line naming
    the option with ``prefix`` (``"algo.shield."``: the config validator)."""
    if candidates == 1:
        raise ValueError(
            f"{prefix}candidates must be 0 (no shield) or >= 2 (the policy's action and "
            "at least one other), got 1"
        )


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
        check_fields(self)


LOSS_OPTIONS = tuple(
    f.name
    for cls in (SafetyOptions, IQNOptions)
    for f in fields(cls)
    if f.metadata["option"].reader == "loss" and f.metadata["option"].kind != "group"
)
"""The options the loss's parts take (:mod:`wcsac_rl.objectives.loss_options`: the fields of
``SafetyHeadOptions``, ``SignalOptions`` and the constraint's)."""


def check_kappa_bound(
    kappa_init: float,
    kappa_max: float | None,
    rule: str,
    prefix: str = "",
    kappa_min: float = 0.0,
) -> None:
    """What ``kappa_init``, ``kappa_max`` and ``kappa_min`` must be beside the rule and
    each other (each alone is checked by :func:`check_value`; ``kappa_min`` here too, as
    a constraint built directly has no other check of it): ``kappa_init`` > 0 under the
    gradient rule (κ is a function of a parameter; the PID rule may start at 0);
    ``kappa_max`` only the gradient rule's bound (the PID rule's is ``pid.max_kappa``),
    finite and at least ``kappa_init``; ``kappa_min`` (either rule) at most
    ``kappa_init``, where κ starts. One
    ``ValueError`` line naming the options with ``prefix`` (``"algo."``: the config
    validator; ``""``: the constraint). The one definition of these relations, for the
    config and the loss."""
    if rule != "pid" and not kappa_init > 0:
        raise ValueError(
            f"{prefix}kappa_init must be > 0 with the gradient rule (κ is softplus or exp "
            f"of a parameter; {prefix}kappa_rule=pid may start at 0), got {kappa_init:g}"
        )
    check_value(f"{prefix}kappa_min", kappa_min, option_spec(SafetyOptions, "kappa_min"))
    if kappa_min > kappa_init:
        raise ValueError(
            f"{prefix}kappa_min must be <= {prefix}kappa_init ({kappa_init:g}, where κ "
            f"starts), got {kappa_min:g}"
        )
    if kappa_max is None:
        return
    if rule == "pid":
        raise ValueError(
            f"{prefix}kappa_max={kappa_max:g} bounds the gradient rule's κ; with "
            f"{prefix}kappa_rule=pid the bound is {prefix}pid.max_kappa"
        )
    if not (math.isfinite(kappa_max) and kappa_max >= kappa_init):
        raise ValueError(
            f"{prefix}kappa_max must be a finite number >= {prefix}kappa_init "
            f"({kappa_init:g}, where κ starts), got {kappa_max}"
        )


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


def check_ensemble(options: Any, *, kind: str | None = None, prefix: str = "") -> None:
    """The ensemble options of ``options`` (a :class:`SafetyOptions`, or the loss's
    ``SafetyHeadOptions``: any object with the fields of :data:`ENSEMBLE_OPTIONS`)
    against each other and, given, the critics' ``kind`` (``"gaussian"`` / ``"iqn"``;
    ``None``: unchecked). ``ensemble_target`` other than ``"own"`` picks among several
    critics; a reading other than ``"max"``, or a prior (``prior_scale``), needs several;
    ``"ucb"`` reads their disagreement, so each bootstraps from its own target;
    ``"tqc"`` and the ``"merged"`` target pool quantiles, so the critics are IQN ones;
    ``k_ucb_lr`` > 0 adapts the UCB reading's ``k_ucb`` within ``[0, k_ucb_max]``.
    One ``ValueError`` line naming the options with ``prefix`` (``"algo."``: the config
    validator; ``""``: the loss): the one definition of these relations."""
    reading, num_safety_nets = options.ensemble_reading, options.num_safety_nets
    ensemble_target, prior_scale = options.ensemble_target, options.prior_scale
    k_ucb, k_ucb_lr, k_ucb_max = options.k_ucb, options.k_ucb_lr, options.k_ucb_max
    check_value(
        f"{prefix}ensemble_target", ensemble_target, option_spec(SafetyOptions, "ensemble_target")
    )
    if ensemble_target != "own" and num_safety_nets == 1:
        raise ValueError(
            f"{prefix}ensemble_target={ensemble_target} picks among several safety critics: "
            f"it needs {prefix}num_safety_nets >= 2"
        )
    check_value(
        f"{prefix}ensemble_reading", reading, option_spec(SafetyOptions, "ensemble_reading")
    )
    for name, value in (
        ("prior_scale", prior_scale),
        ("k_ucb", k_ucb),
        ("k_ucb_lr", k_ucb_lr),
        ("k_ucb_max", k_ucb_max),
    ):
        check_value(f"{prefix}{name}", value, option_spec(SafetyOptions, name))
    if num_safety_nets < 2 and (reading != "max" or prior_scale > 0):
        what = f"ensemble_reading={reading}" if reading != "max" else "prior_scale > 0"
        raise ValueError(
            f"{prefix}{what} reads an ensemble of safety critics: it needs "
            f"{prefix}num_safety_nets >= 2, got {num_safety_nets}"
        )
    if reading != "ucb" and k_ucb != option_default(SafetyOptions, "k_ucb"):
        raise ValueError(
            f"{prefix}k_ucb={k_ucb:g} weighs the members' spread in the UCB reading, which "
            f"this one does not read: it needs {prefix}ensemble_reading=ucb, got {reading}"
        )
    if k_ucb_lr > 0 and reading != "ucb":
        raise ValueError(
            f"{prefix}k_ucb_lr={k_ucb_lr:g} adapts the UCB reading's k_ucb: it needs "
            f"{prefix}ensemble_reading=ucb, got {reading}"
        )
    if k_ucb_lr > 0 and not k_ucb <= k_ucb_max:
        raise ValueError(
            f"{prefix}k_ucb must be <= {prefix}k_ucb_max ({k_ucb_max:g}) with "
            f"{prefix}k_ucb_lr > 0, got {k_ucb:g}"
        )
    if reading == "ucb" and ensemble_target != "own":
        raise ValueError(
            f"{prefix}ensemble_reading=ucb reads the members' disagreement: each bootstraps "
            f"from its own target ({prefix}ensemble_target=own), got {ensemble_target}"
        )
    if ensemble_target == "merged" and kind is not None and kind != "iqn":
        raise ValueError(
            f"{prefix}ensemble_target=merged pools the members' target quantiles: it needs "
            f"{prefix}safety_critic=iqn, got a {kind} critic"
        )
    if reading == "tqc" and kind is not None and kind != "iqn":
        raise ValueError(
            f"{prefix}ensemble_reading=tqc merges the members' quantiles: it needs "
            f"{prefix}safety_critic=iqn, got a {kind} critic"
        )


def check_signal_every(every: int, states: str, statistic: str, prefix: str = "") -> None:
    """``kappa_signal_every`` is an integer >= 1, and above 1 only where the critic's
    statistic is one number per batch read where nothing else reads the critic: at the
    start states (``kappa_states="initial"``) with ``kappa_statistic="tail"``. One
    ``ValueError`` line naming the options with ``prefix``, for the config and the loss."""
    check_value(
        f"{prefix}kappa_signal_every", every, option_spec(SafetyOptions, "kappa_signal_every")
    )
    if every > 1 and (states != "initial" or statistic != "tail"):
        raise ValueError(
            f"{prefix}kappa_signal_every={every} holds the critic's start-state tail "
            f"between reads: it needs {prefix}kappa_states=initial and "
            f"{prefix}kappa_statistic=tail, got {states} and {statistic}"
        )


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
