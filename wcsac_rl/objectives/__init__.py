"""Loss modules (WCSAC, SAC-Lagrangian, CPO), risk measures, ``PolyakUpdate`` (the
target networks' fast path), ``param_groups`` (the optimizer groups with the kit's
learning rates), the data the safety critic's options read (``NStepCost``, ``StartStateBuffer``, ``EpisodeCostWindow``),
the loss's parts (``SafetyHeadOptions``, ``SignalOptions``, ``GradientLagrangian``,
``PIDLagrangian``) and the recipes that fill them (``loss_parts``; ``KIT_OPTIONS``,
``kit_options``, ``recipe_options``: :mod:`wcsac_rl.recipes`; ``PAPER_OPTIONS``,
``SafetyOptions``: :mod:`wcsac_rl.options`)."""

from wcsac_rl.objectives.budget import per_step_cost_threshold
from wcsac_rl.objectives.constraint import GradientLagrangian, PIDGains, PIDLagrangian
from wcsac_rl.objectives.cpo import CPOLoss
from wcsac_rl.objectives.episode_costs import EpisodeCostWindow
from wcsac_rl.objectives.fast_paths import PolyakUpdate
from wcsac_rl.objectives.loss_options import SafetyHeadOptions, SignalOptions, loss_parts
from wcsac_rl.objectives.nstep import NStepCost
from wcsac_rl.objectives.param_groups import SingleGroupWarning, param_groups
from wcsac_rl.objectives.risk import (
    empirical_cvar,
    gaussian_cvar,
    gaussian_cvar_multiplier,
    gaussian_mixture_cvar,
    quantile_mixture_cvar,
    validate_risk_level,
)
from wcsac_rl.objectives.sac_lag import SACLagLoss
from wcsac_rl.objectives.start_states import StartStateBuffer
from wcsac_rl.objectives.wcsac import WCSACLoss
from wcsac_rl.options import PAPER_OPTIONS, SafetyOptions
from wcsac_rl.recipes import KIT_OPTIONS, kit_options, recipe_options

__all__ = [
    "KIT_OPTIONS",
    "PAPER_OPTIONS",
    "CPOLoss",
    "EpisodeCostWindow",
    "GradientLagrangian",
    "NStepCost",
    "PIDGains",
    "PIDLagrangian",
    "PolyakUpdate",
    "SACLagLoss",
    "SafetyHeadOptions",
    "SafetyOptions",
    "SignalOptions",
    "SingleGroupWarning",
    "StartStateBuffer",
    "WCSACLoss",
    "empirical_cvar",
    "gaussian_cvar",
    "gaussian_cvar_multiplier",
    "gaussian_mixture_cvar",
    "kit_options",
    "loss_parts",
    "param_groups",
    "per_step_cost_threshold",
    "quantile_mixture_cvar",
    "recipe_options",
    "validate_risk_level",
]
