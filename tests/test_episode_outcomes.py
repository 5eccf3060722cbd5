"""Whether a run learned, at a glance: each test episode classed (goal reached or not,
with or without cost, numerical failure) in evaluation.json and the report, and the
per-epoch goal rate of the training episodes in progress.csv."""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict

from wcsac_rl.evaluation.evaluator import Evaluation, read_evaluation, summarize, write_evaluation
from wcsac_rl.evaluation.outcomes import (
    GOAL_OUTCOMES,
    PLAIN_OUTCOMES,
    episode_outcome,
    goal_share,
    learned,
    outcome_counts,
    outcome_rows,
    outcomes_csv,
    outcomes_markdown,
)
from wcsac_rl.rollouts.episodes import EpisodeResult
from wcsac_rl.training.progress import EpisodeTracker


def _episode(cost=0.0, goals=0, failure=False, length=1000):
    return EpisodeResult(ret=0.0, cost=cost, length=length, goal_reached=goals,
                         numerical_failure=failure)  # fmt: skip


@pytest.mark.parametrize(
    "episode, with_goals, without_goals",
    [
        (_episode(goals=1, length=300), "goal", "cost_free"),
        (_episode(cost=4.0, goals=2), "goal_cost", "cost"),
        (_episode(), "no_goal", "cost_free"),
        (_episode(cost=827.0), "no_goal_cost", "cost"),
        (_episode(cost=1.0, goals=1, failure=True), "failure", "failure"),
    ],
)
def test_each_episode_has_one_class(episode, with_goals, without_goals):
    assert episode_outcome(episode, has_goals=True) == with_goals
    assert episode_outcome(episode, has_goals=False) == without_goals


def test_counts_hold_every_class_and_learned_is_95_percent_reaching_the_goal():
    episodes = [_episode(goals=1)] * 94 + [_episode(cost=2.0, goals=1)] + [_episode()] * 5
    counts = outcome_counts(episodes, has_goals=True)
    assert list(counts) == list(GOAL_OUTCOMES)
    assert counts == {"goal": 94, "goal_cost": 1, "no_goal": 5, "no_goal_cost": 0, "failure": 0}
    assert goal_share(counts) == 0.95 and learned(counts) == "yes"
    counts["goal"] -= 1
    counts["no_goal_cost"] += 1
    assert learned(counts) == "no"
    plain = outcome_counts(episodes, has_goals=False)
    assert list(plain) == list(PLAIN_OUTCOMES) and plain == {
        "cost_free": 99,
        "cost": 1,
        "failure": 0,
    }
    assert math.isnan(goal_share(plain)) and learned(plain) == "-"


def test_evaluation_json_keeps_the_outcome_counts_and_reads_them_back(tmp_path):
    episodes = [_episode(goals=1), _episode(cost=3.0), _episode(cost=3.0)]
    meta = {"label": "wcsac_0.1", "env": "static", "cost_limit": 15.0, "seed": 3}
    summary = summarize(episodes, 15.0, "static")
    assert summary["outcomes"] == {"goal": 1, "goal_cost": 0, "no_goal": 0, "no_goal_cost": 2,
                                   "failure": 0}  # fmt: skip
    write_evaluation(Evaluation(directory=tmp_path, meta=meta, episodes=episodes, summary=summary))
    assert json.loads((tmp_path / "evaluation.json").read_text())["outcomes"] == summary["outcomes"]
    assert read_evaluation(tmp_path).summary["outcomes"] == summary["outcomes"]
    # an env without goals (a user's gymnasium env) has the classes that apply
    assert summarize(episodes, 15.0, "gymnasium")["outcomes"] == {"cost_free": 1, "cost": 2,
                                                                  "failure": 0}  # fmt: skip


def test_the_report_table_has_a_column_per_class_and_a_line_per_run(tmp_path):
    runs = []
    for label, seed, episodes in [
        ("wcsac_0.1", 1, [_episode(goals=1)] * 19 + [_episode(cost=900.0)]),
        ("sac_lag", 2, [_episode(cost=40.0, goals=1)] * 20),
        ("wcsac_0.1", 0, [_episode()] * 20),
    ]:
        meta = {"label": label, "env": "static", "cost_limit": 15.0, "seed": seed}
        directory = tmp_path / f"{label}_static_seed{seed}"
        runs.append(Evaluation(directory=directory, meta=meta, episodes=episodes, summary={}))
    rows = outcome_rows(runs, has_goals=True)
    assert [(r["label"], r["seed"]) for r in rows] == [("sac_lag", 2), ("wcsac_0.1", 0),
                                                      ("wcsac_0.1", 1)]  # fmt: skip
    table = outcomes_markdown(rows, "StaticEnv", has_goals=True).splitlines()
    assert table[4] == (
        "| row | seed | goal, cost-free | goal, with cost | no goal, cost-free | "
        "no goal, with cost | numerical failure | episodes | learned | run |"
    )
    assert table[6:] == [
        "| SAC-Lag | 2 | 0 | 20 | 0 | 0 | 0 | 20 | yes | sac_lag_static_seed2 |",
        "| WCSAC-0.1 | 0 | 0 | 0 | 20 | 0 | 0 | 20 | no | wcsac_0.1_static_seed0 |",
        "| WCSAC-0.1 | 1 | 19 | 0 | 0 | 1 | 0 | 20 | yes | wcsac_0.1_static_seed1 |",
    ]  # fmt: skip
    csv_lines = outcomes_csv(rows, has_goals=True).splitlines()
    assert csv_lines[0] == ("label,algorithm,seed,run,goal,goal_cost,no_goal,no_goal_cost,"
                            "failure,episodes,goal_share")  # fmt: skip
    assert csv_lines[3] == "wcsac_0.1,WCSAC-0.1,1,wcsac_0.1_static_seed1,19,0,0,1,0,20,0.95"


def _batch(goal, done):
    """A collector batch of ``[envs, time]`` with the tracker's entries."""
    goal, done = torch.tensor(goal), torch.tensor(done)
    shape = list(done.shape)
    zeros = torch.zeros(*shape, 1)
    nxt = {"done": done.unsqueeze(-1), "goal_reached": goal.unsqueeze(-1),
           "episode_reward": zeros, "episode_cost": zeros, "cost": zeros,
           "step_count": torch.ones(*shape, 1, dtype=torch.int64)}  # fmt: skip
    return TensorDict({"next": nxt}, shape)


def test_the_training_goal_rate_counts_episodes_that_reached_a_goal_across_batches():
    tracker = EpisodeTracker()
    # env 0: a goal at t = 1, its episode ends in the next batch; env 1: an episode ends
    # at t = 2 without a goal, the next one reaches one at t = 3 and ends there
    tracker.add(_batch([[False, True, False, False], [False, False, False, True]],
                       [[False, False, False, False], [False, False, True, True]]))  # fmt: skip
    assert tracker.reached == [False, True]
    tracker.add(_batch([[False, False, False, False], [False, False, False, False]],
                       [[False, True, False, True], [False, False, False, True]]))  # fmt: skip
    # env 0: the episode that began in the first batch (goal) ends at t = 1, the next at
    # t = 3 (no goal); env 1: one more without a goal
    assert tracker.reached == [False, True, True, False, False]
    assert tracker.epoch_metrics()["train/goal_rate"] == 2 / 5
    tracker.reset_epoch()
    assert math.isnan(tracker.epoch_metrics()["train/goal_rate"])  # no episode ended


def test_an_env_without_goals_has_no_training_goal_rate():
    tracker = EpisodeTracker()
    batch = _batch([[True, True]], [[False, True]]).exclude(("next", "goal_reached"))
    tracker.add(batch)
    assert tracker.epoch_metrics()["train/episodes"] == 1
    assert math.isnan(tracker.epoch_metrics()["train/goal_rate"])
