"""Table-1 metrics against hand-computed values on synthetic episode lists; row names.

Tolerances: the metrics are float64 means of a few small integers (errors ~2⁻⁵²
relative); approx's default ``rel=1e-6`` only absorbs writing fractions like 17/7.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from wcsac_rl.evaluation.metrics import (
    METRIC_KEYS,
    aggregate_seeds,
    curve_mean_std,
    cvar_key,
    exceedance_proportion,
    table1_metrics,
)
from wcsac_rl.evaluation.runs import ROW_ORDER, row_name, row_sort_key


def test_cvar_columns_use_the_worst_ceil_n_alpha_episodes():
    costs = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]  # n = 10
    m = table1_metrics(costs, [0.0] * 10, cost_limit=15)
    assert m["C0.1"] == 9.0  # ⌈1⌉ = 1 worst
    assert m["C0.5"] == (9 + 8 + 7 + 6 + 5) / 5  # ⌈5⌉ = 5 worst
    assert m["C0.9"] == sum(range(1, 10)) / 9  # ⌈9⌉ = 9 worst: all but the 0
    # n = 7: ⌈0.7⌉ = 1, ⌈3.5⌉ = 4, ⌈6.3⌉ = 7 (rounded up, never down)
    m = table1_metrics([10, 0, 0, 4, 0, 2, 1], [0.0] * 7, cost_limit=15)
    assert m["C0.1"] == 10.0
    assert m["C0.5"] == (10 + 4 + 2 + 1) / 4
    assert m["C0.9"] == pytest.approx(17 / 7)


def test_cvar_of_300_episodes_takes_exactly_30_at_alpha_0_1():
    # 300 · 0.1 = 30.000000000000004 in floating point: still the worst 30, not 31
    costs = [100.0] * 30 + [1.0] * 270
    m = table1_metrics(costs, [0.0] * 300, cost_limit=15)
    assert m["C0.1"] == 100.0
    assert m["C0.5"] == (30 * 100 + 120 * 1) / 150
    assert m["C0.9"] == (30 * 100 + 240 * 1) / 270
    assert m["episodes"] == 300


def test_table1_metrics_hand_computed():
    costs = [0, 0, 15, 16, 40]
    returns = [1.0, 0.5, 0.0, -0.5, 2.0]
    m = table1_metrics(costs, returns, cost_limit=15)
    assert tuple(m) == METRIC_KEYS
    assert m["EC"] == pytest.approx(71 / 5)
    assert m["ER"] == pytest.approx(0.6)
    assert m["C0.1"] == 40.0  # ⌈0.5⌉ = 1
    assert m["C0.5"] == pytest.approx((40 + 16 + 15) / 3)  # ⌈2.5⌉ = 3
    assert m["C0.9"] == pytest.approx((40 + 16 + 15 + 0 + 0) / 5)  # ⌈4.5⌉ = 5
    assert m["over_budget"] == pytest.approx(2 / 5)  # 16 and 40; 15 is within budget


def test_exceedance_is_strictly_greater_than_the_budget():
    assert exceedance_proportion([15, 15, 15], 15) == 0.0
    assert exceedance_proportion([15.0001, 14.9999], 15) == 0.5
    assert exceedance_proportion([0, 0, 1, 0], 0) == 0.25
    assert exceedance_proportion([100], 15) == 1.0


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: table1_metrics([], [], 15), "at least one"),
        (lambda: table1_metrics([1, 2], [1], 15), "2 costs but 1 returns"),
        (lambda: table1_metrics([1, math.nan], [1, 1], 15), "NaN"),
        (lambda: exceedance_proportion([1], -1), "cost_limit"),
        (lambda: aggregate_seeds([], [], 15), "at least one seed"),
        (lambda: aggregate_seeds([[1]], [[1], [2]], 15), "1 seeds but returns for 2"),
    ],
)
def test_bad_input_is_a_clear_error(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_aggregate_seeds_pools_episodes_like_the_paper():
    seed_a = [0] * 8 + [50, 100]  # EC 15, ER 1
    seed_b = [0] * 10  # EC 0, ER 3
    row = aggregate_seeds([seed_a, seed_b], [[1.0] * 10, [3.0] * 10], cost_limit=15)
    assert row["episodes"] == 20 and row["seeds"] == 2
    assert row["EC"] == 7.5
    assert row["ER"] == 2.0
    # pooled: the worst ⌈20 · 0.1⌉ = 2 episodes are 100 and 50 -> 75
    # (not the mean of the per-seed C0.1, (100 + 0) / 2 = 50)
    assert row["C0.1"] == 75.0
    assert row["C0.5"] == 15.0  # worst 10 of 20: 150 / 10
    assert row["over_budget"] == pytest.approx(2 / 20)
    assert row["EC_seed_std"] == 7.5  # population std of (15, 0)
    assert row["ER_seed_std"] == 1.0  # population std of (1, 3)


def test_aggregate_one_seed_equals_table1_metrics_with_zero_spread():
    costs, returns = [3, 0, 20, 1], [0.1, 0.2, 0.3, 0.4]
    row = aggregate_seeds([costs], [returns], cost_limit=15)
    assert {k: row[k] for k in METRIC_KEYS} == table1_metrics(costs, returns, 15)
    assert row["EC_seed_std"] == 0.0 and row["ER_seed_std"] == 0.0 and row["seeds"] == 1


def test_curve_mean_std_aligns_on_env_steps_and_ignores_nan():
    x, mean, std, count = curve_mean_std(
        [
            ([100, 200, 300], [1.0, math.nan, 3.0]),
            ([100, 200, 300], [3.0, 4.0, 5.0]),
            ([100, 200], [2.0, 6.0]),  # an interrupted run
        ]
    )
    assert x.tolist() == [100, 200, 300]
    assert mean.tolist() == [2.0, 5.0, 4.0]
    assert std == pytest.approx([math.sqrt(2 / 3), 1.0, 1.0])
    assert count.tolist() == [3, 2, 2]


def test_curve_mean_std_all_nan_point_is_nan():
    _, mean, std, count = curve_mean_std([([1, 2], [math.nan, 1.0])])
    assert math.isnan(mean[0]) and math.isnan(std[0]) and count[0] == 0
    assert mean[1] == 1.0 and std[1] == 0.0
    with pytest.raises(ValueError, match="at least one curve"):
        curve_mean_std([])
    with pytest.raises(ValueError, match="x values"):
        curve_mean_std([([1, 2], [1.0])])


def test_cvar_key_and_row_names_and_order():
    assert [cvar_key(a) for a in (0.9, 0.5, 0.1)] == ["C0.9", "C0.5", "C0.1"]
    assert [row_name(label) for label in ROW_ORDER] == [
        "SAC",
        "SAC-Lag",
        "WCSAC-0.9",
        "WCSAC-0.5",
        "WCSAC-0.1",
        "CPO",
        "Random Policy",
    ]
    shuffled = ["random", "mine", "wcsac_0.1", "cpo", "wcsac_0.7", "sac", "wcsac_0.5"]
    shuffled += ["wcsac_0.9", "sac_lag_paper", "cal", "sac_lag", "sac_lag_d7.5"]
    assert sorted(shuffled, key=row_sort_key) == [
        "sac",
        "sac_lag",
        "sac_lag_paper",
        "sac_lag_d7.5",
        "cal",
        "wcsac_0.9",
        "wcsac_0.7",
        "wcsac_0.5",
        "wcsac_0.1",
        "cpo",
        "random",
        "mine",
    ]


def test_metrics_accept_numpy_and_tensors():
    import torch

    costs = np.array([1.0, 2.0, 3.0, 4.0])
    m1 = table1_metrics(costs, np.zeros(4), 2.5)
    m2 = table1_metrics(torch.tensor(costs), torch.zeros(4), 2.5)
    assert m1 == m2 and m1["over_budget"] == 0.5
