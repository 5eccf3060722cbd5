"""Network builders: the tanh-Normal actor, the reward critic and the Gaussian safety critic."""

from wcsac_rl.modules.actor import ClampedLogStdNormalParams, make_actor
from wcsac_rl.modules.reward_critic import make_qvalue
from wcsac_rl.modules.safety_critic import (
    VARIANCE_MAX,
    VARIANCE_MIN,
    GaussianSafetyCritic,
    make_safety_critic,
)

__all__ = [
    "VARIANCE_MAX",
    "VARIANCE_MIN",
    "ClampedLogStdNormalParams",
    "GaussianSafetyCritic",
    "make_actor",
    "make_qvalue",
    "make_safety_critic",
]
