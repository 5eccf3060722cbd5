"""A tiny, fast, cost-bearing env (numpy only) for smoke tests and training-loop examples.

A point mass moves by ``speed × clip(action, −1, 1)`` per step from near ``start_xy``
to a goal disc; the reward is progress towards the goal (``dist_prev − dist_now``) plus
``reward_goal`` on arrival, which ends the episode, and the cost is 1 while the point is
strictly inside the hazard disc on the straight path (the reward-greedy path crosses
it; the safe one goes around). With ``hazard_cost_prob < 1`` the hazard is a *risky*
shortcut (a step inside costs ``hazard_cost`` with that probability: small expected
cost, heavy tail). The observation (6 dims, ``float32``) is ``[x, y, goal_x − x,
goal_y − y, hazard_x − x, hazard_y − y]``; ``info`` carries the keys of
:class:`~wcsac_rl.envs.point_goal.PointGoalEnv`, so the same wrapping, metrics and
plots work unchanged.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from wcsac_rl.envs.layout import reset_layout
from wcsac_rl.envs.point_goal import validate_action

__all__ = ["TinyHazardEnv"]


def _number(name: str, value: Any, *, low: float | None = None, strict: bool = False) -> float:
    """``value`` as a finite float (``> low`` with ``strict``, else ``>= low``), or a
    ``ValueError`` naming ``name``."""
    bound = "" if low is None else f" {'>' if strict else '>='} {low:g}"
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if (
        isinstance(value, bool)
        or not math.isfinite(number)
        or (low is not None and (number <= low if strict else number < low))
    ):
        raise ValueError(f"{name} must be a finite number{bound}, got {value!r}")
    return number


def _point(name: str, value: Any) -> tuple[float, float]:
    """``value`` as an ``(x, y)`` pair of finite floats, or a ``ValueError`` naming ``name``."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ValueError(f"{name} must be a pair (x, y) of finite numbers, got {value!r}")
    try:
        return (_number(name, value[0]), _number(name, value[1]))
    except ValueError:
        raise ValueError(f"{name} must be a pair (x, y) of finite numbers, got {value!r}") from None


class TinyHazardEnv(gym.Env):
    """Point mass to a goal past a hazard disc: the smallest env with a real cost trade-off.

    The task is the module's: ``goal_xy`` / ``goal_size``, ``hazard_xy`` / ``hazard_size``,
    a start drawn from ``start_xy + U(-start_noise, start_noise)^2``, ``speed`` per unit
    action, ``reward_goal`` on arrival, ``hazard_cost`` charged per step inside with
    probability ``hazard_cost_prob``, ``truncated=True`` after ``max_episode_steps``;
    ``render_mode`` is only ``None`` (this env does not render).

    Examples:
        >>> env = TinyHazardEnv()
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape
        (6,)
        >>> obs, reward, terminated, truncated, info = env.step(np.array([1.0, 0.0]))
        >>> info["cost"]
        0.0
    """

    metadata = {"render_modes": [], "render_fps": 50}  # noqa: RUF012

    def __init__(
        self,
        *,
        max_episode_steps: int = 100,
        speed: float = 0.05,
        goal_xy: tuple[float, float] = (1.0, 0.0),
        goal_size: float = 0.1,
        hazard_xy: tuple[float, float] = (0.0, 0.0),
        hazard_size: float = 0.35,
        start_xy: tuple[float, float] = (-1.0, 0.0),
        start_noise: float = 0.2,
        reward_goal: float = 1.0,
        hazard_cost: float = 1.0,
        hazard_cost_prob: float = 1.0,
        render_mode: str | None = None,
    ) -> None:
        if render_mode is not None:
            raise ValueError(f"TinyHazardEnv does not render; got render_mode={render_mode!r}")
        if (
            isinstance(max_episode_steps, bool)
            or not isinstance(max_episode_steps, (int, np.integer))
            or max_episode_steps < 1
        ):
            raise ValueError(
                f"max_episode_steps must be an integer >= 1, got {max_episode_steps!r}"
            )
        if not 0.0 <= float(hazard_cost_prob) <= 1.0:
            raise ValueError(f"hazard_cost_prob must be in [0, 1], got {hazard_cost_prob}")
        if not float(hazard_cost) >= 0.0:
            raise ValueError(f"hazard_cost must be >= 0, got {hazard_cost}")
        self.hazard_cost = float(hazard_cost)
        self.hazard_cost_prob = float(hazard_cost_prob)
        self.render_mode = None
        self.max_episode_steps = int(max_episode_steps)
        self.speed = _number("speed", speed, low=0.0, strict=True)
        self.goal_size = _number("goal_size", goal_size, low=0.0, strict=True)
        self.hazard_size = _number("hazard_size", hazard_size, low=0.0)
        self.start_noise = _number("start_noise", start_noise, low=0.0)
        self.reward_goal = _number("reward_goal", reward_goal)
        self._start_xy = _point("start_xy", start_xy)
        self._default_goal = _point("goal_xy", goal_xy)
        self._default_hazard = _point("hazard_xy", hazard_xy)
        self._gx, self._gy = self._default_goal
        self._hx, self._hy = self._default_hazard
        self._x = self._y = 0.0
        self._start = (0.0, 0.0)
        self._steps = 0
        self._dist_prev = 0.0
        self._needs_reset = True
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(6,), dtype=np.float32)

    def reset(
        self, *, seed: int | None = None, options: Mapping[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; ``options={"layout": {...}}`` accepts ``robot_xy``,
        ``goal_xy`` and ``hazards_xy`` (one pair) like the point-goal env."""
        super().reset(seed=seed)
        explicit, _ = reset_layout(
            options,
            hazards_num=1,
            vases_num=0,
            missing="TinyHazardEnv has no robot heading and no vases; valid layout keys are "
            "['robot_xy', 'goal_xy', 'hazards_xy']",
        )
        self._gx, self._gy = (
            tuple(explicit["goal"].tolist()) if "goal" in explicit else self._default_goal
        )
        self._hx, self._hy = (
            tuple(explicit["hazard0"].tolist()) if "hazard0" in explicit else self._default_hazard
        )
        if "robot" in explicit:
            self._x, self._y = explicit["robot"].tolist()
        else:
            noise = self.np_random.uniform(-self.start_noise, self.start_noise, size=2)
            self._x = self._start_xy[0] + float(noise[0])
            self._y = self._start_xy[1] + float(noise[1])
        self._start = (self._x, self._y)
        self._steps = 0
        self._dist_prev = math.hypot(self._gx - self._x, self._gy - self._y)
        self._needs_reset = False
        return self._obs(), self._info(goal_reached=False)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Move by ``speed * clip(action, -1, 1)``; the reward and cost are the module's."""
        if self._needs_reset:
            raise RuntimeError(
                "TinyHazardEnv.step() called before reset() or after the episode ended; "
                "call reset() first"
            )
        a = validate_action(action, (2,))
        self._x += self.speed * float(a[0])
        self._y += self.speed * float(a[1])
        self._steps += 1
        dist = math.hypot(self._gx - self._x, self._gy - self._y)
        reward = self._dist_prev - dist
        self._dist_prev = dist
        goal_reached = dist <= self.goal_size
        if goal_reached:
            reward += self.reward_goal
        terminated = goal_reached
        truncated = self._steps >= self.max_episode_steps
        self._needs_reset = terminated or truncated
        info = self._info(goal_reached=goal_reached)
        if info["cost"] > 0.0:
            charged = self.hazard_cost_prob >= 1.0 or (
                self.np_random.random() < self.hazard_cost_prob
            )
            info["cost"] = info["cost_hazards"] = self.hazard_cost if charged else 0.0
        return self._obs(), reward, terminated, truncated, info

    def layout(self) -> dict[str, Any]:
        """Current layout with sizes, in the same format as ``PointGoalEnv.layout()``."""
        return {
            "robot_xy": np.array([self._x, self._y]),
            "robot_heading": 0.0,
            "robot_start_xy": np.array(self._start),
            "robot_start_heading": 0.0,
            "goal_xy": np.array([self._gx, self._gy]),
            "goal_size": self.goal_size,
            "hazards_xy": np.array([[self._hx, self._hy]]),
            "hazards_size": self.hazard_size,
            "vases_xy": np.zeros((0, 2)),
            "vases_size": 0.0,
            "placement_extents": (-1.5, -1.5, 1.5, 1.5),
        }

    def _obs(self) -> np.ndarray:
        x, y = self._x, self._y
        return np.array(
            [x, y, self._gx - x, self._gy - y, self._hx - x, self._hy - y], dtype=np.float32
        )

    def _info(self, *, goal_reached: bool) -> dict[str, Any]:
        hazard_dist = math.hypot(self._hx - self._x, self._hy - self._y)
        cost = 1.0 if hazard_dist < self.hazard_size else 0.0
        return {
            "cost": cost,
            "goal_reached": goal_reached,
            "numerical_failure": False,
            "robot_xy": np.array([self._x, self._y]),
            "robot_heading": 0.0,
            "goal_xy": np.array([self._gx, self._gy]),
            "goal_dist": self._dist_prev,
            "hazard_dists": np.array([hazard_dist]),
            "hazard_min_dist": hazard_dist,
            "cost_hazards": cost,
        }
