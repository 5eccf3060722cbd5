"""Statistics over runs (wcsac_rl.evaluation.run_statistics) against hand computations.

Tolerances: the values are float64 means of <= 10 numbers of magnitude <= 10 (a sum in
another order differs by <= 10 × 10 × 2⁻⁵² ≈ 2e-14): 1e-12 bounds that. Bootstrap bounds
are compared with the exact bootstrap distribution (every resample enumerated) where the
2.5 % and 97.5 % quantiles sit more than 6 standard errors of an empirical CDF value at
10 000 resamples (0.0019 at p = 0.037) away from a step of that distribution.
"""

from __future__ import annotations

import numpy as np
import pytest

from wcsac_rl.evaluation.run_statistics import (
    HELD_OUT_SEEDS,
    TUNING_SEEDS,
    cdf_band,
    improvement_interval,
    interval_excludes,
    iqm,
    iqm_interval,
    is_held_out,
    probability_of_improvement,
    run_values,
)

TOL = 1e-12


def test_iqm_cuts_a_quarter_of_the_runs_at_each_end():
    # 8 runs: 2 cut at each end, the mean of the middle 4 (2, 3, 4, 5)
    assert iqm([9.0, 0.0, 5.0, 3.0, 4.0, 2.0, 1.0, 8.0]) == pytest.approx(3.5, abs=TOL)
    # 10 runs: ⌊10/4⌋ = 2 cut at each end, the mean of the middle 6
    ten = [100.0, 0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, -50.0]
    assert iqm(ten) == pytest.approx((1 + 2 + 3 + 4 + 5 + 6) / 6, abs=TOL)
    # 3 runs: nothing cut (⌊3/4⌋ = 0): the mean
    assert iqm([0.0, 3.0, 9.0]) == pytest.approx(4.0, abs=TOL)
    # an outlier run moves the mean, not the IQM
    assert iqm([1.0, 1.0, 1.0, 1000.0]) == pytest.approx(1.0, abs=TOL)


def test_probability_of_improvement_counts_pairs_and_half_the_ties():
    # A = (1, 2, 3), B = (2, 4, 6): of 9 pairs, A lower in 7, one tie (2, 2)
    assert probability_of_improvement([1.0, 2.0, 3.0], [2.0, 4.0, 6.0]) == pytest.approx(
        7.5 / 9, abs=TOL
    )
    assert probability_of_improvement([2.0, 4.0, 6.0], [1.0, 2.0, 3.0]) == pytest.approx(
        1.5 / 9, abs=TOL
    )
    # unequal numbers of runs: A = (0, 5), B = (1, 2, 5, 9): lower in 1+1+1+1 + 0+0+0+1, one tie
    assert probability_of_improvement([0.0, 5.0], [1.0, 2.0, 5.0, 9.0]) == pytest.approx(
        5.5 / 8, abs=TOL
    )
    assert probability_of_improvement([0.0, 0.0, 0.0], [0.0, 0.0]) == 0.5


def test_iqm_interval_matches_the_exact_bootstrap_distribution():
    """Runs (0, 3, 9): 27 equally likely resamples; the IQM of 3 runs is their mean. Each
    extreme resample (0, 0, 0) and (9, 9, 9) has probability 1/27 ≈ 0.037 > 0.025, so the
    percentile interval is exactly [0, 9]."""
    assert iqm_interval([0.0, 3.0, 9.0]) == (0.0, 9.0)
    # (2, 2, 2, 7): the resample of four 2s has probability (3/4)^4 ≈ 0.32: the lower
    # bound is 2; the upper is the 97.5 % quantile of trim_mean over the 256 resamples
    values = np.array([2.0, 2.0, 2.0, 7.0])
    draws = np.array(np.meshgrid(*[range(4)] * 4)).reshape(4, -1).T
    from scipy import stats

    exact = np.sort(stats.trim_mean(values[draws], 0.25, axis=1))
    cdf_at = {float(v): float(np.mean(exact <= v)) for v in np.unique(exact)}
    upper = min(v for v, p in cdf_at.items() if p >= 0.975)
    below = max(p for v, p in cdf_at.items() if v < upper)
    assert below < 0.975 - 0.01 and cdf_at[upper] > 0.975 + 0.01  # away from a step
    assert iqm_interval(values) == (2.0, upper)


def test_improvement_interval_matches_the_exact_bootstrap_distribution():
    """A = (0, 1), B = (1, 2), each resampled on its own (4 × 4 outcomes): P(A lower) is 0.5
    with probability 1/16, 0.75 with 1/4, 0.875 with 1/4 and 1 with 7/16, so the 95 %
    interval is [0.5, 1]: it does not exclude 0.5 (the point is 0.875)."""
    assert probability_of_improvement([0.0, 1.0], [1.0, 2.0]) == 0.875
    interval = improvement_interval([0.0, 1.0], [1.0, 2.0])
    assert interval == (0.5, 1.0)
    assert not interval_excludes(interval, 0.5)
    # ten runs each, every run of A below every run of B: every resample gives 1
    a, b = np.arange(10.0), np.arange(10.0) + 100
    assert improvement_interval(a, b) == (1.0, 1.0)
    assert interval_excludes((1.0, 1.0), 0.5) and interval_excludes((0.1, 0.4), 0.5)


def test_intervals_are_reproducible_and_seeded():
    rng = np.random.default_rng(7)
    a, b = rng.exponential(5.0, 10), rng.exponential(8.0, 10)
    first = (iqm_interval(a), improvement_interval(a, b), cdf_band(a, [1.0, 5.0]))
    again = (iqm_interval(a), improvement_interval(a, b), cdf_band(a, [1.0, 5.0]))
    assert first[:2] == again[:2]
    for x, y in zip(first[2], again[2]):
        assert x.tobytes() == y.tobytes()
    lo, hi = first[0]
    assert lo <= iqm(a) <= hi and lo < hi
    lo, hi = first[1]
    assert 0.0 <= lo <= probability_of_improvement(a, b) <= hi <= 1.0
    other = iqm_interval(a, seed=1)
    assert other != first[0]  # another seed, other resamples


def test_cdf_band_is_the_share_of_runs_at_or_below_x():
    share, low, high = cdf_band([0.0, 0.0, 4.0, 10.0], [0.0, 3.9, 4.0, 10.0, 11.0])
    assert share.tolist() == [0.5, 0.5, 0.75, 1.0, 1.0]
    assert (low <= share).all() and (share <= high).all()
    assert low[-1] == high[-1] == 1.0  # every resample has all runs <= 11


def test_run_values_and_c_alpha_is_ec_over_alpha_when_most_episodes_cost_nothing():
    """95 of 100 episodes cost 0: the worst ⌈100·0.1⌉ = 10 hold all the cost, so
    C0.1 = EC / 0.1 (the matched-mean identity of docs/evaluation_protocol.md)."""
    costs = [0.0] * 95 + [10.0, 20.0, 3.0, 4.0, 5.0]
    values = run_values(costs, [1.0] * 100, [1] * 50 + [0] * 50, cost_limit=15)
    assert values["EC"] == pytest.approx(0.42, abs=TOL)
    assert values["C0.1"] == pytest.approx(values["EC"] / 0.1, abs=TOL)
    assert values["goals"] == 0.5 and values["over_budget"] == 0.01  # only 20 > d
    assert values["episodes"] == 100
    with pytest.raises(ValueError, match="got 2 costs, 1 returns and 2 goals"):
        run_values([0.0, 1.0], [1.0], [0, 1], cost_limit=15)


def test_one_run_has_no_statistics_over_runs():
    for call in (lambda: iqm([1.0]), lambda: iqm_interval([1.0])):
        with pytest.raises(ValueError, match="need >= 2 runs, got 1"):
            call()
    with pytest.raises(ValueError, match="A: statistics over runs need >= 2 runs, got 1"):
        probability_of_improvement([1.0], [1.0, 2.0])


def test_held_out_seeds_are_disjoint_from_every_tuning_seed():
    assert HELD_OUT_SEEDS == tuple(range(100, 120))
    assert not set(HELD_OUT_SEEDS) & set(TUNING_SEEDS)
    assert [is_held_out(s) for s in (0, 70, 99, 100, 110, 119, 120)] == [0, 0, 0, 1, 1, 1, 0]
