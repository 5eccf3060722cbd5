"""Small shared pieces for the batched-env and test-episode tests (not collected)."""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
from tensordict.nn import TensorDictModule


def tiny_goal_seeker() -> TensorDictModule:
    """Straight for the goal on the tiny task (``obs[2:4]`` is the goal offset): episodes
    end, at different steps from different starts."""
    return TensorDictModule(
        lambda obs: (10 * obs[..., 2:4]).clamp(-1, 1),
        in_keys=["observation"],
        out_keys=["action"],
    )


def count_steps(envs: Sequence[gym.Env]) -> list[int]:
    """Wrap each env's ``step`` to count its calls; returns the (live) list of counts."""
    counts = [0] * len(envs)
    for i, env in enumerate(envs):
        real_step = env.step

        def counting_step(action, i=i, real_step=real_step):
            counts[i] += 1
            return real_step(action)

        env.step = counting_step
    return counts
