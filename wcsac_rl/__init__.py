"""wcsac_rl: Worst-Case Soft Actor Critic and risk-averse safe-RL baselines for TorchRL.

>>> from wcsac_rl import WCSACLoss, SACLagLoss, make_safety_critic

A training run from Python (the same code as ``wcsac-train``; :mod:`wcsac_rl.train`):

>>> from wcsac_rl import compose_config, run_training

A trained run's policy, a test env and its config in one call
(:func:`~wcsac_rl.training.restore.load_run`):

>>> from wcsac_rl import load_run

The names below are imported on first use (PEP 562), so that ``import wcsac_rl`` (and
``wcsac-train --help``) does not load torch until something needs it.
"""

# Headless MuJoCo rendering by default on Linux servers; must run before anything
# (torchrl included) imports mujoco.
from wcsac_rl import _headless  # noqa: F401  (isort: skip)

# The option schema conf/algo/*.yaml compose from (Hydra's ConfigStore; no torch).
from wcsac_rl import config_schema  # noqa: F401  (isort: skip)

__version__ = "0.1.0"

__all__ = [
    "SACLagLoss",
    "WCSACLoss",
    "compose_config",
    "empirical_cvar",
    "gaussian_cvar",
    "gaussian_cvar_multiplier",
    "load_run",
    "make_actor",
    "make_qvalue",
    "make_safety_critic",
    "per_step_cost_threshold",
    "run_training",
]

_MODULES = ("make_actor", "make_qvalue", "make_safety_critic")
_OBJECTIVES = (
    "SACLagLoss",
    "WCSACLoss",
    "empirical_cvar",
    "gaussian_cvar",
    "gaussian_cvar_multiplier",
    "per_step_cost_threshold",
)
_TRAIN = ("compose_config", "run_training")
_RESTORE = ("load_run",)


def __getattr__(name: str):
    if name in _MODULES:
        from wcsac_rl import modules as source
    elif name in _OBJECTIVES:
        from wcsac_rl import objectives as source
    elif name in _TRAIN:
        from wcsac_rl import train as source
    elif name in _RESTORE:
        from wcsac_rl.training import restore as source
    else:
        raise AttributeError(f"module 'wcsac_rl' has no attribute {name!r}")
    value = getattr(source, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
