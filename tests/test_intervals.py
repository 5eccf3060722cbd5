"""The seed-stratified bootstrap of Table 1's intervals (wcsac_rl.evaluation.intervals):
checked against exact enumerations of every resample on tiny cases."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from wcsac_rl.evaluation.intervals import INTERVAL_METRICS, _pooled_metrics, seed_bootstrap
from wcsac_rl.evaluation.metrics import table1_metrics

RESAMPLES = 20_000
MARGIN = 0.02  # > 6 standard errors of an empirical CDF value at 20 000 resamples


def _exact_distribution(costs, returns, goals, metric):
    """Every equally likely outcome of the two-stage bootstrap (seeds drawn with
    replacement, then each drawn seed's episodes with replacement): the metric's atoms
    and their cumulative probabilities. Seeds with equal episode counts only (then
    every ordered outcome has the same probability)."""
    seeds = len(costs)
    values = []
    for drawn in itertools.product(range(seeds), repeat=seeds):
        inner = [itertools.product(range(len(costs[k])), repeat=len(costs[k])) for k in drawn]
        for picks in itertools.product(*inner):
            episodes = [(k, e) for k, p in zip(drawn, picks) for e in p]
            c = [costs[k][e] for k, e in episodes]
            r = [returns[k][e] for k, e in episodes]
            g = [goals[k][e] for k, e in episodes]
            row = table1_metrics(c, r, cost_limit=15)
            row["goals"] = float(np.mean(g))
            values.append(row[metric])
    atoms, counts = np.unique(np.round(values, 12), return_counts=True)
    return atoms, np.cumsum(counts) / len(values)


def _exact_quantile(atoms, cdf, q):
    """The atom at probability ``q``, or ``None`` when ``q`` lies within MARGIN of a step
    (where a sampled percentile may fall on either side)."""
    below = np.concatenate([[0.0], cdf[:-1]])
    for atom, lo, hi in zip(atoms, below, cdf):
        if lo + MARGIN < q < hi - MARGIN:
            return atom
    return None


TWO_SEEDS = ([[0.0, 10.0], [3.0, 5.0]], [[1.0, 2.0], [0.0, 4.0]], [[0, 1], [1, 1]])
ONE_SEED = ([[0.0, 4.0, 30.0]], [[-1.0, 0.5, 2.0]], [[1, 0, 1]])


@pytest.mark.parametrize("case", [TWO_SEEDS, ONE_SEED], ids=["two seeds", "one seed"])
def test_intervals_match_an_exact_enumeration_of_the_resamples(case):
    checked = 0
    for confidence in (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95):
        bounds = seed_bootstrap(*case, confidence=confidence, n_resamples=RESAMPLES, seed=3)
        for metric in INTERVAL_METRICS:
            atoms, cdf = _exact_distribution(*case, metric)
            for q, bound in zip(((1 - confidence) / 2, (1 + confidence) / 2), bounds[metric]):
                expected = _exact_quantile(atoms, cdf, q)
                if expected is not None:
                    assert bound == pytest.approx(expected, abs=1e-9), (metric, confidence, q)
                    checked += 1
    assert checked >= 40  # most (metric, level) pairs are away from a step


def test_constant_data_gives_a_zero_width_interval():
    bounds = seed_bootstrap([[2.0] * 5] * 3, [[-1.0] * 5] * 3, [[1] * 5] * 3)
    assert bounds == {
        "EC": (2.0, 2.0),
        "C0.9": (2.0, 2.0),
        "C0.5": (2.0, 2.0),
        "C0.1": (2.0, 2.0),
        "ER": (-1.0, -1.0),
        "goals": (1.0, 1.0),
    }


def test_the_seeds_are_resampled_not_only_the_episodes():
    """Two seeds that each always cost the same: within-seed resampling alone would give
    a zero-width interval; resampling the seeds gives EC in {0, 5, 10} with
    probabilities 1/4, 1/2, 1/4, so the 95 % interval is [0, 10]."""
    bounds = seed_bootstrap([[0.0] * 10, [10.0] * 10], [[0.0] * 10, [0.0] * 10], seed=1)
    assert bounds["EC"] == (0.0, 10.0)
    assert "goals" not in bounds


def test_pooled_metrics_equal_table_1s_with_unequal_episode_counts():
    rng = np.random.default_rng(0)
    for _ in range(20):
        sizes = rng.integers(1, 12, size=3)
        cost = [rng.choice([0.0, 0.0, 3.0, 17.0, 40.0], size=n) for n in sizes]
        ret = [rng.normal(size=n) for n in sizes]
        goal = [rng.integers(0, 2, size=n).astype(float) for n in sizes]
        width = 12 * 3
        padded = np.full((3, 1, width), np.nan)
        for i, values in enumerate((cost, ret, goal)):
            flat = np.concatenate(values)
            padded[i, 0, : flat.size] = flat
        got = _pooled_metrics(*padded)[:, 0]
        expected = table1_metrics(np.concatenate(cost), np.concatenate(ret), cost_limit=15)
        expected["goals"] = float(np.concatenate(goal).mean())
        for i, metric in enumerate(INTERVAL_METRICS):
            assert got[i] == pytest.approx(expected[metric], rel=1e-12, abs=1e-12), metric


def test_the_same_call_gives_the_same_interval():
    data = ([[0.0, 3.0, 20.0], [1.0, 1.0, 50.0]], [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]])
    assert seed_bootstrap(*data, seed=7) == seed_bootstrap(*data, seed=7)


def test_a_single_episode_has_no_interval():
    bounds = seed_bootstrap([[4.0]], [[1.0]], [[1]])
    assert all(np.isnan(lo) and np.isnan(hi) for lo, hi in bounds.values())


@pytest.mark.parametrize(
    ("args", "kwargs", "message"),
    [
        (([[1.0]], [[1.0, 2.0]]), {}, "seed 0: 1 costs, 2 returns"),
        (([[1.0], [2.0]], [[1.0]]), {}, "one episode list per seed"),
        (([[np.nan, 1.0]], [[1.0, 2.0]]), {}, "seed 0: non-finite"),
        (([[1.0, 2.0]], [[1.0, 2.0]]), {"confidence": 1.0}, "confidence must be in"),
        (([[1.0, 2.0]], [[1.0, 2.0]]), {"n_resamples": 0}, "n_resamples must be >= 1"),
        (([[]], [[]]), {}, "seed 0: 0 costs"),
    ],
)
def test_bad_input_is_named(args, kwargs, message):
    with pytest.raises(ValueError, match=message):
        seed_bootstrap(*args, **kwargs)
