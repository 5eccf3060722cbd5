"""SAC-Lagrangian as a configuration of :class:`~wcsac_rl.objectives.WCSACLoss`'s parts."""

from __future__ import annotations

from wcsac_rl.objectives.wcsac import WCSACLoss

__all__ = ["SACLagLoss"]


class SACLagLoss(WCSACLoss):
    """SAC-Lagrangian: the parts of :class:`WCSACLoss` configured risk-neutral.

    ``risk_level=1``: Γ = Q^c (the expected cost), so the safety head uses the mean
    alone and the ``"tail"`` statistic is the mean over the states. Give it a
    mean-only safety critic (``make_safety_critic(..., variance=False)``): no variance
    network exists or is trained, which is the paper's ablation. With a Gaussian
    critic the variance is still learned (a diagnostic) but never used; with an IQN
    critic (``kind="iqn"``) Γ is the mean of its quantiles over [0, 1]. Every other
    keyword is :class:`WCSACLoss`'s.

    Example:
        >>> from torchrl.data import Bounded
        >>> from wcsac_rl import SACLagLoss
        >>> from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
        >>> loss = SACLagLoss(make_actor(4, Bounded(-1.0, 1.0, shape=(2,))),
        ...                   [make_qvalue(4, 2) for _ in range(2)],
        ...                   make_safety_critic(4, 2, variance=False), cost_limit=25.0)
        >>> loss.has_variance, loss.risk_level
        (False, 1.0)
    """

    def __init__(
        self, actor_network, qvalue_network, safety_network, *, risk_level=1.0, **kwargs
    ) -> None:
        if risk_level != 1.0:
            raise ValueError(
                "SACLagLoss is the risk-neutral case (risk_level=1); for risk_level < 1 use WCSACLoss"
            )
        super().__init__(actor_network, qvalue_network, safety_network, risk_level=1.0, **kwargs)
