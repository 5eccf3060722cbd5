"""The paper's evaluation metrics (Table 1) and their aggregation over seeds. Pure functions.

EC, C_α (the empirical CVaR, :func:`~wcsac_rl.objectives.risk.empirical_cvar`), ER and
the share of episodes over budget (cost strictly above d: :func:`exceedance_proportion`)
as docs/paper.md ("Metrics") defines them; :func:`aggregate_seeds` pools a row's seeds as
the paper does, with the seeds' spread of EC and ER; :func:`curve_mean_std` averages
training curves over seeds at equal env-step counts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from wcsac_rl.objectives.risk import empirical_cvar

__all__ = [
    "METRIC_KEYS",
    "RISK_LEVELS",
    "aggregate_seeds",
    "curve_mean_std",
    "cvar_key",
    "exceedance_proportion",
    "table1_metrics",
]

RISK_LEVELS: tuple[float, ...] = (0.9, 0.5, 0.1)
"""The risk levels of Table 1's C_α columns."""


def cvar_key(risk_level: float) -> str:
    """Column name of C_α, e.g. ``cvar_key(0.5) == "C0.5"``."""
    return f"C{risk_level:g}"


METRIC_KEYS: tuple[str, ...] = (
    "EC",
    *(cvar_key(a) for a in RISK_LEVELS),
    "ER",
    "over_budget",
    "episodes",
)
"""The keys :func:`table1_metrics` returns, in Table 1's column order."""


def _as_array(values: Sequence[float], what: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.size == 0:
        raise ValueError(f"{what}: need at least one episode")
    if np.isnan(array).any():
        raise ValueError(f"{what}: got NaN values")
    return array


def exceedance_proportion(costs: Sequence[float], cost_limit: float) -> float:
    """Fraction of episodes whose cost is strictly greater than ``cost_limit`` (d).

    >>> exceedance_proportion([0, 15, 15.5, 40], 15)
    0.5
    """
    array = _as_array(costs, "exceedance_proportion")
    if not math.isfinite(cost_limit) or cost_limit < 0:
        raise ValueError(f"cost_limit must be a finite number >= 0, got {cost_limit!r}")
    return float(np.mean(array > cost_limit))


def table1_metrics(
    costs: Sequence[float],
    returns: Sequence[float],
    cost_limit: float,
    risk_levels: Sequence[float] = RISK_LEVELS,
) -> dict[str, float]:
    """Table 1's metrics of one set of test episodes.

    Args:
        costs: episodic (undiscounted) costs, one per episode.
        returns: episodic returns, same episodes.
        cost_limit: the budget d (for ``over_budget``).
        risk_levels: the α of the ``C_α`` columns.

    Returns:
        ``{"EC", "C0.9", "C0.5", "C0.1", "ER", "over_budget", "episodes"}`` (one
        ``C<α>`` per risk level; ``episodes`` is ``n``).

    >>> m = table1_metrics([0, 0, 0, 0, 0, 0, 0, 0, 10, 30], [1.0] * 10, cost_limit=15)
    >>> m["EC"], m["C0.1"], m["C0.5"], m["over_budget"], m["episodes"]
    (4.0, 30.0, 8.0, 0.1, 10)
    """
    cost = _as_array(costs, "costs")
    ret = _as_array(returns, "returns")
    if cost.size != ret.size:
        raise ValueError(f"got {cost.size} costs but {ret.size} returns")
    metrics: dict[str, float] = {"EC": float(cost.mean())}
    for alpha in risk_levels:
        metrics[cvar_key(alpha)] = empirical_cvar(cost, alpha)
    metrics["ER"] = float(ret.mean())
    metrics["over_budget"] = exceedance_proportion(cost, cost_limit)
    metrics["episodes"] = int(cost.size)
    return metrics


def aggregate_seeds(
    costs_per_seed: Sequence[Sequence[float]],
    returns_per_seed: Sequence[Sequence[float]],
    cost_limit: float,
    risk_levels: Sequence[float] = RISK_LEVELS,
) -> dict[str, float]:
    """One Table-1 row from several seeds' test episodes.

    The metrics of :func:`table1_metrics` are computed on all episodes pooled (as
    the paper does: C_α over the worst ``⌈300·α⌉`` of 300 episodes), plus
    ``seeds`` (how many), ``EC_seed_std`` and ``ER_seed_std`` (population standard
    deviation of the per-seed means; 0 for one seed).

    >>> row = aggregate_seeds([[0, 20], [10, 10]], [[1, 3], [0, 0]], cost_limit=15)
    >>> row["EC"], row["C0.5"], row["ER"], row["over_budget"], row["seeds"], row["EC_seed_std"]
    (10.0, 15.0, 1.0, 0.25, 2, 0.0)
    """
    if len(costs_per_seed) == 0:
        raise ValueError("aggregate_seeds: need at least one seed")
    if len(costs_per_seed) != len(returns_per_seed):
        raise ValueError(
            f"got costs for {len(costs_per_seed)} seeds but returns for {len(returns_per_seed)}"
        )
    per_seed_cost = [_as_array(c, "costs") for c in costs_per_seed]
    per_seed_ret = [_as_array(r, "returns") for r in returns_per_seed]
    row = table1_metrics(
        np.concatenate(per_seed_cost), np.concatenate(per_seed_ret), cost_limit, risk_levels
    )
    row["seeds"] = len(per_seed_cost)
    row["EC_seed_std"] = float(np.std([c.mean() for c in per_seed_cost]))
    row["ER_seed_std"] = float(np.std([r.mean() for r in per_seed_ret]))
    return row


def curve_mean_std(
    curves: Sequence[tuple[Sequence[float], Sequence[float]]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Mean and standard deviation over seeds of curves ``(x, y)`` at equal x.

    Runs of one sweep log at the same env-step counts; a shorter (interrupted) run
    simply stops contributing. NaN values (an epoch in which no episode ended) are
    ignored.

    Returns:
        ``(x, mean, std, count)`` over the sorted union of the x values; ``std`` is
        the population standard deviation (0 where one run contributes), ``mean``
        and ``std`` are NaN where no run has a value.

    >>> x, mean, std, count = curve_mean_std([([1, 2], [0.0, 2.0]), ([1, 2, 3], [2.0, 4.0, 5.0])])
    >>> x.tolist(), mean.tolist(), std.tolist(), count.tolist()
    ([1.0, 2.0, 3.0], [1.0, 3.0, 5.0], [1.0, 1.0, 0.0], [2, 2, 1])
    """
    if len(curves) == 0:
        raise ValueError("curve_mean_std: need at least one curve")
    xs = np.unique(np.concatenate([np.asarray(x, dtype=np.float64) for x, _ in curves]))
    table = np.full((len(curves), xs.size), np.nan)
    for i, (x, y) in enumerate(curves):
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if x.shape != y.shape:
            raise ValueError(f"curve {i}: {x.size} x values but {y.size} y values")
        table[i, np.searchsorted(xs, x)] = y
    count = np.sum(~np.isnan(table), axis=0)
    mean = np.full(xs.size, np.nan)
    std = np.full(xs.size, np.nan)
    has = count > 0
    mean[has] = np.nanmean(table[:, has], axis=0)
    std[has] = np.nanstd(table[:, has], axis=0)
    return xs, mean, std, count
