"""wcsac_rl: Worst-Case Soft Actor Critic and risk-averse safe-RL baselines for TorchRL.

>>> from wcsac_rl import WCSACLoss, SACLagLoss, make_safety_critic
"""

# Headless MuJoCo rendering by default on Linux servers; must run before anything
# (torchrl included) imports mujoco.
from wcsac_rl import _headless  # noqa: F401  (isort: skip)

from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import (
    SACLagLoss,
    WCSACLoss,
    empirical_cvar,
    gaussian_cvar,
    gaussian_cvar_multiplier,
    per_step_cost_threshold,
)

__version__ = "0.1.0"

__all__ = [
    "SACLagLoss",
    "WCSACLoss",
    "empirical_cvar",
    "gaussian_cvar",
    "gaussian_cvar_multiplier",
    "make_actor",
    "make_qvalue",
    "make_safety_critic",
    "per_step_cost_threshold",
]
