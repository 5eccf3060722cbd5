"""The cost budget: the episodic limit ``d``, the episode length ``T``, and the threshold
a discounted safety critic is held under. One definition, used by the losses and the
config's validation.
"""

from __future__ import annotations

import math
from numbers import Real

__all__ = ["per_step_cost_threshold", "validate_cost_limit", "validate_max_episode_steps"]


def validate_cost_limit(cost_limit: float) -> float:
    """``d`` as a float; ``ValueError`` unless it is a finite number ``>= 0``.

    >>> validate_cost_limit(15)
    15.0
    """
    if isinstance(cost_limit, bool) or not isinstance(cost_limit, Real):
        raise ValueError(
            f"cost_limit must be a number (an episodic cost budget), got {cost_limit!r}"
        )
    if not (math.isfinite(cost_limit) and cost_limit >= 0):
        raise ValueError(f"cost_limit must be >= 0 (an episodic cost budget), got {cost_limit}")
    return float(cost_limit)


def validate_max_episode_steps(max_episode_steps: int) -> int:
    """``T`` as an int; ``ValueError`` unless it is a positive integer.

    >>> validate_max_episode_steps(1000)
    1000
    """
    if (
        isinstance(max_episode_steps, bool)
        or not isinstance(max_episode_steps, Real)
        or int(max_episode_steps) != max_episode_steps
        or max_episode_steps <= 0
    ):
        raise ValueError(f"max_episode_steps must be a positive integer, got {max_episode_steps!r}")
    return int(max_episode_steps)


def per_step_cost_threshold(cost_limit: float, gamma: float, max_episode_steps: int) -> float:
    """Turn an episodic cost limit ``d`` into the threshold for a *discounted* cost critic.

    ``d_step = (d / T) · Σ_{t<T} γ^t = d (1 − γ^T) / ((1 − γ) T)``: the discounted
    sum of a cost spread evenly (``d / T`` per step) over an episode of ``T`` steps.

    >>> round(per_step_cost_threshold(15.0, 0.99, 1000), 5)
    1.49994
    """
    cost_limit = validate_cost_limit(cost_limit)
    horizon = validate_max_episode_steps(max_episode_steps)
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"gamma must be in [0, 1], got {gamma}")
    discounted_steps = horizon if gamma == 1.0 else (1.0 - gamma**horizon) / (1.0 - gamma)
    return cost_limit * discounted_steps / horizon
