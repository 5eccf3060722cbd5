"""``wcsac_rl.load_run``: a trained run's policy, a test env and its config in one call."""

from __future__ import annotations

import torch
from _evaluation_helpers import EPISODE_STEPS, train_run
from _tolerance import assert_close_f32
from torchrl.envs.utils import ExplorationType, set_exploration_type

import wcsac_rl
from wcsac_rl.rollouts.episodes import run_episodes
from wcsac_rl.training.restore import load_run


def test_load_run_is_public_and_its_policy_rolls_out_a_whole_episode(tmp_path):
    assert "load_run" in wcsac_rl.__all__ and wcsac_rl.load_run is load_run
    run_dir = train_run(tmp_path / "run", "wcsac", 0)
    run = wcsac_rl.load_run(run_dir, seed=5)
    try:
        assert run.cfg.algo.name == "wcsac" and float(run.cfg.risk_level) == 0.5
        assert run.frames == 800
        with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
            episode = run.env.rollout(10 * EPISODE_STEPS, run.policy, break_when_any_done=True)
            # the actions are the policy's: its mean action at each observed state
            acted = run.policy(episode.select("observation").clone())["action"]
    finally:
        run.env.close()
    assert episode.shape == (EPISODE_STEPS,)  # the tiny env's time limit ends it
    assert bool(episode["next", "done"][-1]) and not episode["next", "done"][:-1].any()
    # (a batch of 50 rows rounds differently from one row at a time: the 32-wide MLP's
    # float32 sums, relative to the largest action; see _tolerance.py)
    assert_close_f32(acted, episode["action"], ops=32)
    assert bool((episode["action"].abs() <= 1).all())  # within the action spec
    # the same episode the evaluation runs (which sums in float64), from the same env seed
    again = wcsac_rl.load_run(run_dir, seed=5)
    try:
        (result,) = run_episodes(again.env, again.policy, 1)
    finally:
        again.env.close()
    assert result.length == EPISODE_STEPS
    assert result.ret == float(episode["next", "reward"].double().sum())
    assert result.cost == float(episode["next", "cost"].double().sum())
