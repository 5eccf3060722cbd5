"""The realised cost of recent episodes, for a κ that does not wait for the critic.

The safety critic's value at a start state has to integrate costs met hundreds of
steps later, so after the policy changes it lags: on StaticEnv, training episodes
cost 40 while the critic's start-state CVaR still read 10–14, below d = 15, and κ
fell by two orders of magnitude in that time. The costs of the episodes just
collected carry no such lag (they are noisy instead). With
``kappa_signal="max"`` (or ``"episodes"``) :class:`~wcsac_rl.objectives.WCSACLoss`
lets κ see them too; :class:`EpisodeCostWindow` is what provides them in a TorchRL
loop: it keeps the costs of the last ``window`` finished episodes of collected data
and attaches their empirical CVaR_α (the mean of the worst ``⌈α·n⌉``) to each sampled
batch. The wcsac_rl trainer uses it the same way.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey

from wcsac_rl.objectives.loss_keys import LossKey, follow_loss_keys
from wcsac_rl.objectives.risk import empirical_cvar, validate_risk_level
from wcsac_rl.options import EPISODE_STATISTICS, check_value

__all__ = ["EPISODE_STATISTICS", "EpisodeCostWindow"]


class EpisodeCostWindow:
    """The costs of the last ``window`` finished episodes and their empirical CVaR_α.

    Args:
        risk_level: the α of the CVaR (1: the mean episode cost).

    Keyword Args:
        window: how many of the most recent finished episodes count. Default 30
            (at α = 0.1 the CVaR is then the mean of the worst 3).
        episode_cost_key: the running episode cost in collected data, read at the
            steps where ``done_key`` is set (the wcsac_rl envs write it; elsewhere
            ``torchrl.envs.RewardSum(in_keys=["cost"], out_keys=["episode_cost"])``).
            Default ``("next", "episode_cost")``.
        done_key: Default ``("next", "done")``.
        out_key: where :meth:`attach` puts the CVaR
            (``loss.tensor_keys.episode_cvar``). Default ``"episode_cvar"``.
        test_window: also keep the costs of the last ``test_window`` deterministic
            test episodes (:meth:`add_test_costs`); :attr:`value` is then the larger of
            the two windows' statistics, the test window's always its empirical
            CVaR at ``test_risk_level`` (what Table 1 measures). Default 0: none.
        test_risk_level: the α of the test window's CVaR. Default: ``risk_level``.
        horizon: summarise the (training) window by its cost *rate* instead: its summed
            cost over its summed length, times ``horizon`` (the episode cost at that rate
            over a full ``horizon``-step episode). Episodes that end early, at a goal,
            are then held to the rate of a full one: a 100-step episode costing 3 counts
            as 30 at ``horizon=1000``. Needs ``risk_level=1``. Default ``None``: the CVaR.
        length_key: the episode length in collected data, read where episodes end
            (TorchRL's ``StepCounter`` writes it). Default ``("next", "step_count")``.

    Built by :meth:`for_loss`, ``out_key`` is the loss's ``episode_cvar`` key, read at
    each call: a later ``loss.set_keys(episode_cvar=...)`` is followed.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> window = EpisodeCostWindow(0.5, window=4)
        >>> data = TensorDict({"next": {
        ...     "episode_cost": torch.tensor([[1.0], [5.0], [2.0], [9.0], [7.0]]),
        ...     "done": torch.tensor([[True], [False], [True], [True], [True]])}}, [5])
        >>> window.add_episodes(data)  # four episodes end here: costs 1, 2, 9, 7
        4
        >>> window.value  # the worst half of them
        8.0
        >>> window.attach(TensorDict({}, [3]))["episode_cvar"].squeeze(-1)
        tensor([8., 8., 8.])
    """

    out_key = LossKey("episode_cvar")

    def __init__(
        self,
        risk_level: float,
        *,
        window: int = 30,
        episode_cost_key: NestedKey = ("next", "episode_cost"),
        done_key: NestedKey = ("next", "done"),
        out_key: NestedKey = "episode_cvar",
        test_window: int = 0,
        test_risk_level: float | None = None,
        horizon: int | None = None,
        length_key: NestedKey = ("next", "step_count"),
    ) -> None:
        check_value("window", window, "kappa_episode_window")
        check_value("test_window", test_window, "kappa_test_window")
        self.risk_level = validate_risk_level(risk_level)
        if horizon is not None:
            if isinstance(horizon, bool) or int(horizon) != horizon or horizon < 1:
                raise ValueError(f"horizon must be an integer >= 1 (steps), got {horizon!r}")
            if self.risk_level != 1.0:
                raise ValueError(
                    f"a cost rate (horizon={horizon}) is a mean: risk_level must be 1, "
                    f"got {risk_level!r}"
                )
        self.horizon = None if horizon is None else int(horizon)
        self.length_key = length_key
        self.test_risk_level = validate_risk_level(
            risk_level if test_risk_level is None else test_risk_level, name="test_risk_level"
        )
        self.window = int(window)
        self.test_window = int(test_window)
        self.episode_cost_key = episode_cost_key
        self.done_key = done_key
        self.out_key = out_key
        self._costs: deque[float] = deque(maxlen=self.window)
        self._lengths: deque[float] = deque(maxlen=self.window)
        self._test_costs: deque[float] = deque(maxlen=max(self.test_window, 1))
        self._value = math.nan

    @classmethod
    def for_loss(cls, loss, *, statistic: str = "cvar", **kwargs) -> EpisodeCostWindow:
        """The window a loss with ``kappa_signal != "critic"`` reads (its key), at the
        loss's α (``statistic="cvar"``), at α = 1 (``"mean"``: the mean episode cost,
        which no CVaR is below: with ``kappa_signal="max"`` it floors the critic's Γ
        by what the episodes actually cost, without asking more of the tail), or as the
        cost rate over the loss's ``max_episode_steps`` (``"rate"``: ``horizon``)."""
        check_value("statistic", statistic, "kappa_episode_statistic")
        risk_level = loss.risk_level if statistic == "cvar" else 1.0
        if statistic == "rate":
            kwargs["horizon"] = int(loss.max_episode_steps)
        kwargs.setdefault("test_risk_level", loss.risk_level)
        if "out_key" in kwargs:
            return cls(risk_level, **kwargs)
        return follow_loss_keys(cls(risk_level, **kwargs), loss)

    def __len__(self) -> int:
        return len(self._costs)

    @property
    def costs(self) -> list[float]:
        """The costs in the window, oldest first."""
        return list(self._costs)

    @property
    def test_costs(self) -> list[float]:
        """The costs in the test window, oldest first (empty with ``test_window=0``)."""
        return list(self._test_costs)

    @property
    def value(self) -> float:
        """The empirical CVaR_α of the window, or with a test window the larger of it and
        the test window's CVaR (NaN before the first episode of either ends)."""
        return self._value

    @property
    def lengths(self) -> list[float]:
        """The lengths (steps) of the episodes in the window, oldest first (kept with a
        ``horizon`` only: empty otherwise)."""
        return list(self._lengths)

    def _update(self) -> None:
        values = []
        if self._costs:
            if self.horizon is None:
                values.append(empirical_cvar(list(self._costs), self.risk_level))
            else:
                values.append(self.horizon * math.fsum(self._costs) / math.fsum(self._lengths))
        if self.test_costs:
            values.append(empirical_cvar(self.test_costs, self.test_risk_level))
        self._value = max(values) if values else math.nan

    def add_episodes(self, batch: TensorDictBase) -> int:
        """Add the episodes that end in collected ``batch``; returns how many there were.

        ``batch`` may be ``[num_envs, time]`` (a collector's layout): episodes are
        taken in time order, which matters only for which ones leave a full window.
        """
        if batch.ndim > 1:  # time last: order the ends by time, then by env
            batch = batch.transpose(0, batch.ndim - 1)
        flat = batch.reshape(-1)
        keys = (self.episode_cost_key, self.done_key)
        if self.horizon is not None:
            keys += (self.length_key,)
        missing = [key for key in keys if key not in flat.keys(True)]
        if missing:
            raise KeyError(
                f"the batch has no {missing}: EpisodeCostWindow reads the running episode cost "
                "where episodes end (add torchrl.envs.RewardSum(in_keys=['cost'], "
                "out_keys=['episode_cost']) to the env; a rate also reads the length: "
                "torchrl.envs.StepCounter())"
            )
        done = flat.get(self.done_key).reshape(-1).bool()
        ended = flat.get(self.episode_cost_key).reshape(-1)[done]
        if ended.numel():
            costs = ended.double().tolist()
            if any(not math.isfinite(c) for c in costs):
                raise ValueError(f"non-finite episode costs in the batch: {costs}")
            lengths = []  # (kept for a rate only)
            if self.horizon is not None:
                lengths = flat.get(self.length_key).reshape(-1)[done].double().tolist()
                if any(not (math.isfinite(n) and n >= 1) for n in lengths):
                    raise ValueError(f"episode lengths must be >= 1 steps, got {lengths}")
            self._costs.extend(costs)
            self._lengths.extend(lengths)
            self._update()
        return int(ended.numel())

    def add_test_costs(self, costs) -> None:
        """Add the costs of finished deterministic test episodes (``test_window > 0``)."""
        if not self.test_window:
            raise RuntimeError("this window keeps no test episodes (test_window=0)")
        costs = [float(c) for c in costs]
        if any(not math.isfinite(c) for c in costs):
            raise ValueError(f"non-finite test episode costs: {costs}")
        if costs:
            self._test_costs.extend(costs)
            self._update()

    def attach(self, batch: TensorDictBase) -> TensorDictBase:
        """``batch`` with the window's CVaR (``[*B, 1]``, NaN if no episode has ended yet)
        under ``out_key``."""
        value = torch.full((*batch.shape, 1), self._value, device=batch.device)
        batch.set(self.out_key, value)
        return batch

    def state_dict(self) -> dict[str, Any]:
        return {
            "costs": list(self._costs),
            "lengths": list(self._lengths),
            "window": self.window,
            "risk_level": self.risk_level,
            "test_costs": self.test_costs,
            "test_window": self.test_window,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the windows' episodes (a checkpoint's ``state_dict()``; one saved
        without a test window leaves it empty, one saved without lengths counts its
        episodes as full ``horizon``-step ones)."""
        costs = [float(c) for c in state["costs"]]
        lengths = [float(n) for n in state.get("lengths") or ()]
        if self.horizon is None:
            lengths = []
        elif len(lengths) != len(costs) or not all(n >= 1 for n in lengths):
            # saved by a window without a rate: its episodes count as full ones
            lengths = [float(self.horizon)] * len(costs)
        self._costs.clear()
        self._costs.extend(costs)  # a smaller window keeps the most recent
        self._lengths.clear()
        self._lengths.extend(lengths)
        self._test_costs.clear()
        if self.test_window:
            self._test_costs.extend(float(c) for c in state.get("test_costs", ()))
        self._update()
