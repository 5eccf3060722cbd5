"""Network builders: the tanh-Normal actor, the reward critic, the safety critics
(Gaussian, and implicit-quantile), and CPO's Gaussian actor and state-value networks;
and acting with them: ``TanhNormalPolicy`` (the actor's fast path for collection and
test episodes, :mod:`~wcsac_rl.modules.actor`), and ``CriticShield``, which filters its
collection actions through a safety critic (:mod:`~wcsac_rl.modules.critic_shield`). The
loss reads these networks from their parameters in :mod:`wcsac_rl.objectives.fast_paths`."""

from wcsac_rl.modules.actor import ClampedLogStdNormalParams, TanhNormalPolicy, make_actor
from wcsac_rl.modules.critic_shield import CriticShield
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
    "CriticShield",
    "GaussianSafetyCritic",
    "IQNSafetyCritic",
    "TanhNormalPolicy",
    "make_actor",
    "make_gaussian_actor",
    "make_qvalue",
    "make_safety_critic",
    "make_state_value",
    "softplus_variance",
]
