"""Seed-stratified bootstrap intervals for Table 1's metrics.

A Table-1 row pools the test episodes of several training seeds. Its uncertainty has
two sources: which seeds were trained (seed-to-seed variation, usually the larger) and
which test episodes were drawn (evaluation noise). The interval therefore resamples
in two stages, as a hierarchical bootstrap does:

1. the seeds, with replacement (``S`` draws from the ``S`` seeds), by
   :func:`scipy.stats.bootstrap`, which also forms the percentile interval;
2. within each drawn seed, its test episodes, with replacement (``n_s`` draws from its
   ``n_s`` episodes), inside the statistic;

and computes each metric on the pooled resample exactly as the row does (C_α: the mean
of the worst ``⌈N·α⌉`` of the ``N`` pooled episodes). With a single seed only stage 2
remains, and :func:`scipy.stats.bootstrap` resamples the episodes directly.

The resampling is seeded, so a report made twice writes the same intervals.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import stats

__all__ = ["INTERVAL_METRICS", "seed_bootstrap"]

INTERVAL_METRICS = ("EC", "C0.9", "C0.5", "C0.1", "ER", "goals")
"""The metrics :func:`seed_bootstrap` gives intervals for (``goals``: goals per episode)."""

_ALPHAS = {"C0.9": 0.9, "C0.5": 0.5, "C0.1": 0.1}


def _pooled_metrics(cost: np.ndarray, ret: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """The metrics of :data:`INTERVAL_METRICS` of each row of pooled episodes.

    The arrays are ``(B, L)``; NaN marks padding (rows may pool different numbers of
    episodes when seeds have different episode counts). Returns ``(len(metrics), B)``.
    """
    valid = ~np.isnan(cost)
    count = valid.sum(axis=-1)
    out = np.empty((len(INTERVAL_METRICS), cost.shape[0]))
    out[0] = np.where(valid, cost, 0.0).sum(axis=-1) / count
    # worst first, padding last
    worst_first = -np.sort(np.where(valid, -cost, np.inf), axis=-1)
    cumulative = np.cumsum(np.where(np.isfinite(worst_first), worst_first, 0.0), axis=-1)
    for i, name in enumerate(("C0.9", "C0.5", "C0.1"), start=1):
        # ⌈n·α⌉ as in risk.empirical_cvar (floating noise rounded away first)
        k = np.maximum(1, np.ceil(np.round(count * _ALPHAS[name], 9))).astype(np.int64)
        out[i] = np.take_along_axis(cumulative, (k - 1)[:, None], axis=-1)[:, 0] / k
    out[4] = np.where(valid, ret, 0.0).sum(axis=-1) / count
    out[5] = np.where(valid, goals, 0.0).sum(axis=-1) / count
    return out


def _padded(per_seed: Sequence[np.ndarray], width: int) -> np.ndarray:
    table = np.full((len(per_seed), width), np.nan)
    for i, values in enumerate(per_seed):
        table[i, : values.size] = values
    return table


def seed_bootstrap(
    costs_per_seed: Sequence[Sequence[float]],
    returns_per_seed: Sequence[Sequence[float]],
    goals_per_seed: Sequence[Sequence[float]] | None = None,
    *,
    confidence: float = 0.95,
    n_resamples: int = 2000,
    seed: int = 0,
) -> dict[str, tuple[float, float]]:
    """Percentile intervals of a row's metrics under the two-stage (seeds, then
    episodes) bootstrap described in the module docstring.

    Args:
        costs_per_seed: each seed's episodic costs.
        returns_per_seed: each seed's episodic returns (same episodes).
        goals_per_seed: each seed's goals per episode (``None``: no ``goals`` interval).
        confidence: the interval's level.
        n_resamples: bootstrap resamples.
        seed: seed of the resampling (a report is reproducible).

    Returns:
        ``{metric: (lo, hi)}`` for the metrics of :data:`INTERVAL_METRICS` (NaN for a
        single episode of a single seed: nothing to resample).

    >>> ci = seed_bootstrap([[3.0, 3.0], [3.0, 3.0]], [[1.0, 1.0], [1.0, 1.0]])
    >>> ci["EC"], ci["C0.1"], ci["ER"]
    ((3.0, 3.0), (3.0, 3.0), (1.0, 1.0))
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    if n_resamples < 1:
        raise ValueError(f"n_resamples must be >= 1, got {n_resamples!r}")
    costs = [np.asarray(c, dtype=np.float64).reshape(-1) for c in costs_per_seed]
    returns = [np.asarray(r, dtype=np.float64).reshape(-1) for r in returns_per_seed]
    if goals_per_seed is None:
        goals = [np.zeros_like(c) for c in costs]
    else:
        goals = [np.asarray(g, dtype=np.float64).reshape(-1) for g in goals_per_seed]
    if not costs or len(costs) != len(returns) or len(costs) != len(goals):
        raise ValueError(
            f"need one episode list per seed for costs, returns and goals "
            f"(got {len(costs)}, {len(returns)}, {len(goals)})"
        )
    for i, (c, r, g) in enumerate(zip(costs, returns, goals)):
        if c.size == 0 or c.size != r.size or c.size != g.size:
            raise ValueError(f"seed {i}: {c.size} costs, {r.size} returns, {g.size} goals")
        if not (np.isfinite(c).all() and np.isfinite(r).all() and np.isfinite(g).all()):
            raise ValueError(f"seed {i}: non-finite episode values")
    sizes = np.array([c.size for c in costs])
    width = int(sizes.max())
    table = np.stack([_padded(costs, width), _padded(returns, width), _padded(goals, width)])
    rng = np.random.default_rng(seed)

    def resample_episodes(seeds: np.ndarray) -> np.ndarray:
        """``seeds`` ``(B, S)`` drawn seed indices → metrics ``(M, B)`` of the pooled
        resample, each drawn seed's episodes drawn again with replacement."""
        batch = seeds.shape[0]
        n = sizes[seeds]  # (B, S)
        draw = np.floor(rng.random((batch, seeds.shape[1], width)) * n[..., None]).astype(np.int64)
        keep = np.arange(width)[None, None, :] < n[..., None]
        picked = table[:, seeds[..., None], draw]  # (3, B, S, width)
        picked = np.where(keep[None], picked, np.nan).reshape(3, batch, -1)
        return _pooled_metrics(*picked)

    def outer(drawn: np.ndarray, axis: int = -1) -> np.ndarray:
        metrics = resample_episodes(np.atleast_2d(drawn).astype(np.int64))
        return metrics[:, 0] if drawn.ndim == 1 else metrics

    level = {
        "confidence_level": confidence,
        "n_resamples": n_resamples,
        "method": "percentile",
        "batch": 250,  # bounds the memory of one batch of resamples
    }
    if len(costs) > 1:
        result = stats.bootstrap(
            (np.arange(len(costs)),),
            outer,
            vectorized=True,
            random_state=rng,
            **level,
        )
    elif width == 1:  # one episode of one seed: nothing to resample, no interval
        nan = (math.nan, math.nan)
        return {
            name: nan for name in INTERVAL_METRICS if goals_per_seed is not None or name != "goals"
        }
    else:  # one seed: the episodes are the only level

        def statistic(episodes: np.ndarray, axis: int = -1) -> np.ndarray:
            drawn = np.atleast_2d(episodes).astype(np.int64)
            metrics = _pooled_metrics(*table[:, np.zeros_like(drawn), drawn])
            return metrics[:, 0] if episodes.ndim == 1 else metrics

        result = stats.bootstrap(
            (np.arange(width),), statistic, vectorized=True, random_state=rng, **level
        )
    lows = np.atleast_1d(result.confidence_interval.low)
    highs = np.atleast_1d(result.confidence_interval.high)
    bounds = {}
    for name, lo, hi in zip(INTERVAL_METRICS, lows, highs):
        if goals_per_seed is None and name == "goals":
            continue
        # a constant statistic makes scipy return NaN (a degenerate distribution)
        if math.isnan(lo) or math.isnan(hi):
            point = _pooled_metrics(*table.reshape(3, 1, -1))[INTERVAL_METRICS.index(name), 0]
            lo = hi = point
        bounds[name] = (float(lo), float(hi))
    return bounds
