"""Statistics over runs: each run one number, a row summarised over its runs.

Each run is reduced to its own EC, C0.1, ER and goals (:func:`run_values`); a row is
summarised with rliable's definitions (Agarwal et al. 2021), computed with scipy: the
interquartile mean (:func:`iqm`) with its stratified bootstrap interval
(:func:`iqm_interval`), and the probability of improvement of row A over row B for a
cost (:func:`probability_of_improvement`) with its interval (:func:`improvement_interval`).
Definitions and how a study reads them: docs/evaluation_protocol.md. The resampling is
seeded (a report made twice writes the same bytes); the kit does not depend on rliable.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence

import numpy as np
from scipy import stats

from wcsac_rl.evaluation.metrics import exceedance_proportion
from wcsac_rl.objectives.risk import empirical_cvar

__all__ = [
    "CONFIDENCE",
    "HELD_OUT_SEEDS",
    "N_RESAMPLES",
    "RESAMPLING_SEED",
    "RUN_METRICS",
    "TUNING_SEEDS",
    "cdf_band",
    "improvement_interval",
    "interval_excludes",
    "iqm",
    "iqm_interval",
    "is_held_out",
    "probability_of_improvement",
    "run_values",
]

RUN_METRICS = ("EC", "C0.1", "ER", "goals")
"""The per-run values (:func:`run_values`) the report summarises over runs."""

TUNING_SEEDS: tuple[int, ...] = (0, 1, 2, 3, 4, 5, 6, 7, 10, 20, 30, 40, 50, 60, 70)
"""Seeds some committed screen has used: runs of these seeds are in-sample
(docs/evaluation_protocol.md)."""

HELD_OUT_SEEDS: tuple[int, ...] = tuple(range(100, 120))
"""Seeds fixed before their runs and never used to choose anything: only their runs back a
claim (docs/evaluation_protocol.md; 100-109 first, 110-119 fixed with them and first used
by results/heldout_learned_tail/)."""

CONFIDENCE = 0.95
N_RESAMPLES = 10_000
RESAMPLING_SEED = 0
"""Every interval resamples with ``numpy.random.default_rng(RESAMPLING_SEED)``."""


def is_held_out(seed: int) -> bool:
    """Whether a run of training seed ``seed`` is held-out (:data:`HELD_OUT_SEEDS`).

    >>> is_held_out(100), is_held_out(119), is_held_out(10), is_held_out(120)
    (True, True, False, False)
    """
    return int(seed) in HELD_OUT_SEEDS


def run_values(
    costs: Sequence[float], returns: Sequence[float], goals: Sequence[float], cost_limit: float
) -> dict[str, float]:
    """One run's values from its test episodes: EC, C0.1, ER, goals per episode, the
    share of episodes over ``cost_limit`` and the number of episodes.

    >>> v = run_values([0, 0, 0, 0, 0, 0, 0, 0, 0, 30], [1.0] * 10, [1] * 10, cost_limit=15)
    >>> v["EC"], v["C0.1"], v["ER"], v["goals"], v["over_budget"], v["episodes"]
    (3.0, 30.0, 1.0, 1.0, 0.1, 10)
    """
    cost = np.asarray(costs, dtype=np.float64).reshape(-1)
    ret = np.asarray(returns, dtype=np.float64).reshape(-1)
    goal = np.asarray(goals, dtype=np.float64).reshape(-1)
    if cost.size == 0 or cost.size != ret.size or cost.size != goal.size:
        raise ValueError(f"got {cost.size} costs, {ret.size} returns and {goal.size} goals")
    if not (np.isfinite(cost).all() and np.isfinite(ret).all() and np.isfinite(goal).all()):
        raise ValueError("run_values: non-finite episode values")
    return {
        "EC": float(cost.mean()),
        "C0.1": empirical_cvar(cost, 0.1),
        "ER": float(ret.mean()),
        "goals": float(goal.mean()),
        "over_budget": exceedance_proportion(cost, cost_limit),
        "episodes": int(cost.size),
    }


def _runs(values: Sequence[float], what: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.size < 2:
        raise ValueError(f"{what}: statistics over runs need >= 2 runs, got {array.size}")
    if not np.isfinite(array).all():
        raise ValueError(f"{what}: non-finite run values")
    return array


def _iqm_statistic(sample: np.ndarray, axis: int = -1) -> np.ndarray:
    return stats.trim_mean(sample, 0.25, axis=axis)


def iqm(values: Sequence[float]) -> float:
    """The interquartile mean of the runs' values: ``scipy.stats.trim_mean(values, 0.25)``
    (``⌊n/4⌋`` runs cut at each end; rliable's ``aggregate_iqm``).

    >>> iqm([0.0, 1.0, 2.0, 100.0]), iqm([5.0, 1.0, 3.0, 2.0, 4.0, 0.0, 9.0, 8.0])
    (1.5, 3.5)
    """
    return float(_iqm_statistic(_runs(values, "iqm")))


def _percentile_interval(
    data: tuple[np.ndarray, ...],
    statistic,
    point: np.ndarray | float,
    *,
    n_resamples: int,
    seed: int,
) -> tuple[np.ndarray, np.ndarray]:
    """scipy's percentile bootstrap interval (each sample resampled on its own); where
    every resample gives the same value scipy returns NaN: the interval is that point."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", stats.DegenerateDataWarning)
        result = stats.bootstrap(
            data,
            statistic,
            n_resamples=n_resamples,
            confidence_level=CONFIDENCE,
            method="percentile",
            vectorized=True,
            paired=False,
            random_state=np.random.default_rng(seed),
        )
    point = np.asarray(point, dtype=np.float64)
    low = np.where(np.isnan(result.confidence_interval.low), point, result.confidence_interval.low)
    high = np.where(
        np.isnan(result.confidence_interval.high), point, result.confidence_interval.high
    )
    return low, high


def iqm_interval(
    values: Sequence[float], *, n_resamples: int = N_RESAMPLES, seed: int = RESAMPLING_SEED
) -> tuple[float, float]:
    """The 95 % percentile interval of the IQM over runs, the runs resampled with
    replacement (:mod:`scipy.stats.bootstrap`, seeded: the same values give the same
    interval).

    >>> iqm_interval([2.0, 2.0, 2.0])
    (2.0, 2.0)
    """
    runs = _runs(values, "iqm_interval")
    low, high = _percentile_interval(
        (runs,), _iqm_statistic, _iqm_statistic(runs), n_resamples=n_resamples, seed=seed
    )
    return float(low), float(high)


def _lower_share(a: np.ndarray, b: np.ndarray, axis: int = -1) -> np.ndarray:
    """``P(A < B) + ½ P(A = B)`` over all pairs: Mann-Whitney U of ``(B, A)`` / (n_A n_B)."""
    a = np.moveaxis(a, axis, -1)
    b = np.moveaxis(b, axis, -1)
    u = stats.mannwhitneyu(b, a, axis=-1, method="asymptotic").statistic
    return np.asarray(u, dtype=np.float64) / (a.shape[-1] * b.shape[-1])


def probability_of_improvement(a: Sequence[float], b: Sequence[float]) -> float:
    """The probability that a run of A has a *lower* value (cost) than a run of B, ties
    counting half: ``P(X < Y) + ½ P(X = Y)`` with X a run of A, Y one of B.

    >>> probability_of_improvement([0.0, 1.0], [1.0, 2.0])  # pairs: <, <, =, <
    0.875
    >>> probability_of_improvement([3.0, 3.0], [3.0, 3.0])
    0.5
    """
    return float(_lower_share(_runs(a, "A"), _runs(b, "B")))


def improvement_interval(
    a: Sequence[float],
    b: Sequence[float],
    *,
    n_resamples: int = N_RESAMPLES,
    seed: int = RESAMPLING_SEED,
) -> tuple[float, float]:
    """The 95 % percentile interval of :func:`probability_of_improvement`, the runs of A
    and those of B resampled independently (seeded)."""
    x, y = _runs(a, "A"), _runs(b, "B")
    low, high = _percentile_interval(
        (x, y), _lower_share, _lower_share(x, y), n_resamples=n_resamples, seed=seed
    )
    return float(low), float(high)


def cdf_band(
    values: Sequence[float],
    grid: Sequence[float],
    *,
    n_resamples: int = 2000,
    seed: int = RESAMPLING_SEED,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fraction of runs with a value ``<= x`` at each ``x`` of ``grid`` (the score
    distribution of a cost), and its 95 % percentile band resampling the runs.

    >>> share, low, high = cdf_band([0.0, 0.0, 4.0], [0.0, 2.0, 4.0])
    >>> [round(float(s), 3) for s in share], float(low[-1]), float(high[-1])
    ([0.667, 0.667, 1.0], 1.0, 1.0)
    """
    runs = _runs(values, "cdf_band")
    points = np.asarray(grid, dtype=np.float64).reshape(-1)

    def share(sample: np.ndarray, axis: int = -1) -> np.ndarray:
        sample = np.moveaxis(sample, axis, -1)
        return np.moveaxis((sample[..., None] <= points).mean(axis=-2), -1, 0)

    point = share(runs)
    low, high = _percentile_interval((runs,), share, point, n_resamples=n_resamples, seed=seed)
    return point, low, high


def interval_excludes(interval: tuple[float, float], value: float) -> bool:
    """Whether ``value`` lies outside the closed interval (NaN bounds: no)."""
    lo, hi = interval
    if math.isnan(lo) or math.isnan(hi):
        return False
    return value < lo or value > hi
