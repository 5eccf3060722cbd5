"""A one-step continuous bandit where expected cost and CVaR disagree (pure torch, batched).

The action ``a ∈ [−1, 1]`` earns reward ``a`` and costs ``hit`` with probability
``p(a)``, linear from ``p_low`` (``a = −1``) to ``p_high`` (``a = 1``); every episode is
one terminal step, so everything about the cost is known in closed form: its expected
value stays under a modest limit for every action (SAC-Lag should go to ``a = 1``),
while its Gaussian CVaR_α (:meth:`RiskyBanditEnv.cvar_feasible_action`) and exact
CVaR_α ``hit · min(p/α, 1)`` (:meth:`RiskyBanditEnv.exact_cvar`) give CVaR-feasible
optima below it (docs/defaults.md, "The risky bandit"). The smallest task on which the
paper's central claim can be checked, at millions of steps per second.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Composite, Unbounded
from torchrl.envs import EnvBase

from wcsac_rl.objectives.risk import gaussian_cvar_multiplier

__all__ = ["RiskyBanditEnv"]


class RiskyBanditEnv(EnvBase):
    """One-step bandit with reward ``a`` and cost ``hit`` with probability ``p(a)``.

    Keyword Args:
        hit: size of the rare cost. Default 10.
        p_low, p_high: hit probability at ``a = −1`` and ``a = 1``. Defaults 0.01, 0.09.
        batch_size: TorchRL batch size (parallel bandits in one env). Default ``()``.
        device: torch device.

    Keys: ``observation`` (a constant 1, shape ``[*B, 1]``), ``action`` ``[*B, 1]``,
    ``("next", "reward")`` and ``("next", "cost")`` ``[*B, 1]``; every step is terminal.

    Example:
        >>> env = RiskyBanditEnv(batch_size=[4])
        >>> td = env.rollout(1)
        >>> td["next", "cost"].shape, bool(td["next", "terminated"].all())
        (torch.Size([4, 1, 1]), True)
    """

    def __init__(
        self,
        *,
        hit: float = 10.0,
        p_low: float = 0.01,
        p_high: float = 0.09,
        batch_size: torch.Size | tuple = (),
        device: torch.device | str | None = None,
    ) -> None:
        if hit <= 0:
            raise ValueError(f"hit must be > 0, got {hit}")
        if not 0.0 <= p_low <= p_high <= 1.0:
            raise ValueError(f"need 0 <= p_low <= p_high <= 1, got p_low={p_low}, p_high={p_high}")
        super().__init__(batch_size=torch.Size(batch_size), device=device)
        self.hit = float(hit)
        self.p_low = float(p_low)
        self.p_high = float(p_high)
        shape = (*self.batch_size, 1)
        self.observation_spec = Composite(
            observation=Unbounded(shape=shape, device=self.device), shape=self.batch_size
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=shape, device=self.device)
        self.reward_spec = Unbounded(shape=shape, device=self.device)
        self.full_observation_spec["cost"] = Unbounded(shape=shape, device=self.device)
        self._generator = torch.Generator(device=self.device if self.device is not None else "cpu")

    # ------------------------------------------------------------- closed form
    def hit_probability(self, action: torch.Tensor | float) -> torch.Tensor:
        """``p(a)``: linear from ``p_low`` at ``a = −1`` to ``p_high`` at ``a = 1``."""
        a = torch.as_tensor(action, dtype=torch.float64).clamp(-1.0, 1.0)
        return self.p_low + (self.p_high - self.p_low) * (a + 1.0) / 2.0

    def expected_cost(self, action: torch.Tensor | float) -> torch.Tensor:
        """``E[c | a] = hit · p(a)``."""
        return self.hit * self.hit_probability(action)

    def gaussian_cvar(self, action: torch.Tensor | float, risk_level: float) -> torch.Tensor:
        """CVaR_α of the Gaussian with the cost's mean and variance (what WCSAC estimates)."""
        p = self.hit_probability(action)
        std = self.hit * (p * (1.0 - p)).sqrt()
        return self.hit * p + gaussian_cvar_multiplier(risk_level) * std

    def exact_cvar(self, action: torch.Tensor | float, risk_level: float) -> torch.Tensor:
        """The cost's own CVaR_α, ``hit · min(p(a)/α, 1)``: the mean of its worst α share."""
        p = self.hit_probability(action)
        return self.hit * (p / risk_level).clamp(max=1.0)

    def cvar_feasible_action(
        self, risk_level: float, cost_limit: float, *, exact: bool = False
    ) -> float:
        """The largest action whose CVaR_α is within ``cost_limit`` (bisection): the
        Gaussian CVaR (default, what WCSAC's Gaussian critic estimates) or, with
        ``exact``, the cost's own (:meth:`exact_cvar`).

        Returns 1.0 if every action is feasible and raises ``ValueError`` if none is.
        """
        cvar = self.exact_cvar if exact else self.gaussian_cvar
        if float(cvar(1.0, risk_level)) <= cost_limit:
            return 1.0
        if float(cvar(-1.0, risk_level)) > cost_limit:
            raise ValueError(f"no action meets CVaR_{risk_level} <= {cost_limit}")
        low, high = -1.0, 1.0
        for _ in range(60):
            mid = 0.5 * (low + high)
            if float(cvar(mid, risk_level)) <= cost_limit:
                low = mid
            else:
                high = mid
        return low

    # ------------------------------------------------------------------ EnvBase
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        shape = (*self.batch_size, 1)
        return TensorDict(
            {
                "observation": torch.ones(shape, device=self.device),
                "cost": torch.zeros(shape, device=self.device),
                "done": torch.zeros(shape, dtype=torch.bool, device=self.device),
                "terminated": torch.zeros(shape, dtype=torch.bool, device=self.device),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").clamp(-1.0, 1.0)
        p = self.hit_probability(action).to(action.dtype)
        hit = torch.rand(p.shape, generator=self._generator, device=self.device) < p
        shape = (*self.batch_size, 1)
        return TensorDict(
            {
                "observation": torch.ones(shape, device=self.device),
                "reward": action.clone(),
                "cost": hit.to(action.dtype) * self.hit,
                "done": torch.ones(shape, dtype=torch.bool, device=self.device),
                "terminated": torch.ones(shape, dtype=torch.bool, device=self.device),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            seed = int(torch.empty((), dtype=torch.int64).random_().item())
        self._generator.manual_seed(int(seed) % (2**63))
