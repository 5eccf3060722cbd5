"""Loss modules (WCSAC, SAC-Lagrangian, CPO), risk measures, ``PolyakUpdate`` (the
target networks' fast path), ``param_groups`` (the optimizer groups with the kit's
learning rates), the data the safety critic's options read (``NStepCost``, ``StartStateBuffer``, ``EpisodeCostWindow``),
and the options themselves (``SafetyOptions``, ``PAPER_OPTIONS``: :mod:`wcsac_rl.options`)."""

from wcsac_rl.objectives.budget import per_step_cost_threshold
from wcsac_rl.objectives.cpo import CPOLoss
from wcsac_rl.objectives.episode_costs import EpisodeCostWindow
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
from wcsac_rl.objectives.target_update import PolyakUpdate
from wcsac_rl.objectives.wcsac import WCSACLoss
from wcsac_rl.options import PAPER_OPTIONS, SafetyOptions

__all__ = [
    "PAPER_OPTIONS",
    "CPOLoss",
    "EpisodeCostWindow",
    "NStepCost",
    "PolyakUpdate",
    "SACLagLoss",
    "SafetyOptions",
    "SingleGroupWarning",
    "StartStateBuffer",
    "WCSACLoss",
    "empirical_cvar",
    "gaussian_cvar",
    "gaussian_cvar_multiplier",
    "gaussian_mixture_cvar",
    "param_groups",
    "per_step_cost_threshold",
    "quantile_mixture_cvar",
    "validate_risk_level",
]
