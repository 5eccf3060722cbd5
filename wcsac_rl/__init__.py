"""wcsac_rl: Worst-Case Soft Actor Critic and risk-averse safe-RL baselines for TorchRL.

>>> from wcsac_rl import WCSACLoss, SACLagLoss, make_safety_critic
"""

import os as _os
import sys as _sys

# Headless MuJoCo rendering by default on Linux servers; must run before anything
# (torchrl included) imports mujoco.
if _sys.platform.startswith("linux") and not _os.environ.get("DISPLAY"):
    _os.environ.setdefault("MUJOCO_GL", "egl")

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
