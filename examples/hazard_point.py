"""A complete own-env example: a 2-D point that must reach a goal past a hazard.

Train WCSAC on it from any directory (this file's directory on ``PYTHONPATH``)::

    PYTHONPATH=path/to/examples wcsac-train env=gymnasium env.id=hazard_point:make \\
        algo=wcsac risk_level=0.1 cost_limit=5 total_frames=20000

What the kit needs from an env, all shown here (docs/own_environment.md):

* a ``gymnasium.Env`` with a continuous ``Box`` action space with finite bounds and a
  ``Box`` observation space;
* the per-step cost in ``info["cost"]`` (another key: ``env.cost_key=<key>``; or a
  safety-gymnasium 6-tuple ``step``);
* an episode length: here the registration's ``max_episode_steps`` (``make`` wraps the
  env in a ``TimeLimit``), or ``env.max_episode_steps=<steps>`` on the command line.

``make`` is the ``module:callable`` form of ``env.id``; importing the module also
registers ``HazardPoint-v0``, so ``env.id=hazard_point:HazardPoint-v0`` names the same
env through gymnasium's registry. ``env.kwargs`` reach ``make`` (e.g.
``+env.kwargs.hazard_cost=2``).
"""

from __future__ import annotations

from typing import ClassVar

import gymnasium as gym
import numpy as np

__all__ = ["HazardPointEnv", "make"]


class HazardPointEnv(gym.Env):
    """A point in the plane moved by its action (a velocity in [-1, 1]²).

    It starts near (-1, 0) and earns the decrease of its distance to the goal at (1, 0)
    (plus 1 on arrival, which ends the episode); the straight route crosses a hazard disc
    of radius 0.4 at the origin, where each step costs ``hazard_cost``. The observation
    is (x, y, goal - position, distance to the hazard's centre).
    """

    metadata: ClassVar[dict] = {"render_modes": []}

    GOAL = np.array([1.0, 0.0])
    HAZARD_RADIUS = 0.4
    STEP = 0.1

    def __init__(self, hazard_cost: float = 1.0) -> None:
        self.hazard_cost = float(hazard_cost)
        self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(5,), dtype=np.float32)
        self.position = np.zeros(2)

    def _observation(self) -> np.ndarray:
        to_goal = self.GOAL - self.position
        hazard = np.linalg.norm(self.position)
        return np.array([*self.position, *to_goal, hazard], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.position = np.array([-1.0, 0.0]) + self.np_random.uniform(-0.1, 0.1, size=2)
        return self._observation(), {}

    def step(self, action):
        before = np.linalg.norm(self.GOAL - self.position)
        move = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.position = np.clip(self.position + self.STEP * move, -2.0, 2.0)
        after = np.linalg.norm(self.GOAL - self.position)
        reached = bool(after < 0.15)
        reward = float(before - after) + (1.0 if reached else 0.0)
        inside = bool(np.linalg.norm(self.position) < self.HAZARD_RADIUS)
        cost = self.hazard_cost if inside else 0.0
        return self._observation(), reward, reached, False, {"cost": cost}


gym.register("HazardPoint-v0", entry_point=HazardPointEnv, max_episode_steps=50)


def make(**kwargs) -> gym.Env:
    """The env the command line names with ``env.id=hazard_point:make``: 50-step episodes."""
    return gym.wrappers.TimeLimit(HazardPointEnv(**kwargs), max_episode_steps=50)
