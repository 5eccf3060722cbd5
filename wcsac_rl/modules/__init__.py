"""Network builders: the tanh-Normal actor, the reward critic, the safety critics
(Gaussian, and implicit-quantile), and CPO's Gaussian actor and state-value networks."""

from wcsac_rl.modules.actor import ClampedLogStdNormalParams, make_actor
from wcsac_rl.modules.gaussian_actor import make_gaussian_actor, make_state_value
from wcsac_rl.modules.quantile_critic import IQNSafetyCritic
from wcsac_rl.modules.reward_critic import make_qvalue
from wcsac_rl.modules.safety_critic import (
    SAFETY_CRITIC_KINDS,
    VARIANCE_MAX,
    VARIANCE_MIN,
    GaussianSafetyCritic,
    make_safety_critic,
    softplus_variance,
)

__all__ = [
    "SAFETY_CRITIC_KINDS",
    "VARIANCE_MAX",
    "VARIANCE_MIN",
    "ClampedLogStdNormalParams",
    "GaussianSafetyCritic",
    "IQNSafetyCritic",
    "make_actor",
    "make_gaussian_actor",
    "make_qvalue",
    "make_safety_critic",
    "make_state_value",
    "softplus_variance",
]
