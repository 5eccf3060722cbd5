"""Non-finite data: the trainer skips an update whose loss is not finite (and stops after
``max_nonfinite_updates`` in a row); the envs reject a non-finite reward, cost or
observation with the env's name."""

from __future__ import annotations

import copy
import csv
import math

import gymnasium as gym
import numpy as np
import pytest
import torch
from _training_helpers import compose_config

from wcsac_rl.envs import NonFiniteStepError, RejectNonFinite, TinyHazardEnv, make_env
from wcsac_rl.training import TrainingError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint


def _trainer(tmp_path, *overrides):
    return make_trainer(compose_config("env=tiny", *overrides), tmp_path / "run")


def _poisoned_batch(trainer, key=("next", "cost"), value=math.nan):
    """A replay batch of real transitions (random actions) with one entry poisoned."""
    env = trainer.env
    rollout = env.rollout(40, break_when_any_done=False)
    # poison transition 3 of the flattened batch as collected (the n-step sums below
    # then carry it too)
    entry = rollout[key].clone()
    flat = entry.flatten(0, rollout.ndim - 1)
    flat[3] = value
    rollout[key] = flat.reshape(entry.shape)
    if trainer.postproc is not None:  # the n-step cost entries the loss reads
        rollout = trainer.postproc(rollout)
    batch = rollout.reshape(-1).select(*trainer.replay_keys)[: trainer.cfg.algo.batch_size]
    if trainer.initial_state_buffer is not None:  # start states (rollout starts at a reset)
        trainer.initial_state_buffer.add_starts(rollout)
        batch = trainer.initial_state_buffer.attach(batch)
    if getattr(trainer, "episode_window", None) is not None:  # recent episodes' cost (κ)
        batch = trainer.episode_window.attach(batch)
    return batch


def _parameters(trainer):
    return {k: v.detach().clone() for k, v in trainer.loss.state_dict().items()}


@pytest.mark.parametrize(
    "key", [("next", "cost"), ("next", "reward"), ("next", "observation"), "observation"]
)
def test_a_non_finite_entry_skips_the_update_and_leaves_every_parameter_as_it_was(tmp_path, key):
    trainer = _trainer(tmp_path)
    try:
        good = _poisoned_batch(trainer, value=0.0)
        assert trainer.update(good) is not None  # (the optimizers have moments)
        before = _parameters(trainer)
        moments = copy.deepcopy(trainer.optimizers["critic"].state_dict()["state"])
        assert trainer.update(_poisoned_batch(trainer, key)) is None
        after = _parameters(trainer)
        for name, value in before.items():
            assert torch.equal(value, after[name]), name  # networks, targets, β, κ
        state = trainer.optimizers["critic"].state_dict()["state"]
        for index, entries in moments.items():  # Adam's moments and step counts
            assert all(torch.equal(v, state[index][k]) for k, v in entries.items()), index
        assert trainer.updates == 1 and trainer.skipped_updates == 1
        # a finite batch updates again (and ends the streak)
        assert trainer.update(good) is not None
        assert trainer.updates == 2 and trainer.nonfinite_streak == 0
        assert all(torch.isfinite(v).all() for v in _parameters(trainer).values())
    finally:
        trainer.close()


def test_infinite_cost_is_skipped_too(tmp_path):
    trainer = _trainer(tmp_path, "algo=sac_lag")
    try:
        assert trainer.update(_poisoned_batch(trainer, value=math.inf)) is None
        assert trainer.skipped_updates == 1
    finally:
        trainer.close()


def test_skipped_updates_are_logged_and_a_streak_stops_the_run_with_one_line(tmp_path):
    trainer = _trainer(tmp_path, "max_nonfinite_updates=5", "checkpoint_every_epochs=1")
    poisoned = _poisoned_batch(trainer)
    real_sample = trainer.sample
    calls = {"n": 0}

    def sample():
        calls["n"] += 1
        # 2 poisoned batches in the first epoch's updates, then only poisoned ones
        if calls["n"] in (7, 30) or calls["n"] > 100:
            return poisoned.clone()
        return real_sample()

    trainer.sample = sample
    with pytest.raises(TrainingError) as err:
        trainer.run()
    trainer.close()
    message = str(err.value)
    assert "\n" not in message
    # (the recipe's IQN critic, conf/algo/wcsac.yaml: its one TD loss)
    assert "5 updates in a row" in message and "loss_cost_quantile" in message
    assert "max_nonfinite_updates" in message
    assert f"the last checkpoint {trainer.checkpoint_path} is kept" in message
    with (tmp_path / "run" / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    # epoch 1 (400 frames: 50 updates after each of its 2 batches) logged both
    assert [int(r["train/skipped_updates"]) for r in rows] == [2]
    assert int(rows[0]["updates"]) == 100 - 2
    # the networks were never stepped on a NaN loss: the last checkpoint is finite
    state = load_checkpoint(trainer.checkpoint_path)["learner"]["loss"]
    assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())
    assert all(torch.isfinite(v).all() for v in _parameters(trainer).values())


def test_a_streak_before_the_first_checkpoint_does_not_say_one_is_kept(tmp_path):
    """A run that cannot update from its start (red-team CF1, CF2) says that no
    checkpoint was written, which train.py then removes with the run; not "kept"."""
    trainer = _trainer(tmp_path, "max_nonfinite_updates=2")
    try:
        trainer.skip_update("loss_actor")
        with pytest.raises(TrainingError) as err:
            trainer.skip_update("loss_actor")
    finally:
        trainer.close()
    message = str(err.value)
    assert "no checkpoint had been written yet" in message and "is kept" not in message
    assert "the algorithm's options" in message


def test_max_nonfinite_updates_is_validated(tmp_path):
    from wcsac_rl.training import ConfigError

    with pytest.raises(ConfigError, match="max_nonfinite_updates must be an integer > 0"):
        _trainer(tmp_path, "max_nonfinite_updates=0")


class _NaNCostAt(gym.Wrapper):
    def __init__(self, env, step, what="cost"):
        super().__init__(env)
        self.at, self.what, self.t = step, what, 0

    def reset(self, **kwargs):
        self.t = 0
        return self.env.reset(**kwargs)

    def step(self, action):
        obs, reward, term, trunc, info = self.env.step(action)
        self.t += 1
        if self.t == self.at:
            if self.what == "cost":
                info = {**info, "cost": float("nan")}
            elif self.what == "reward":
                reward = float("inf")
            else:
                obs = obs.copy()
                obs[2] = np.nan
        return obs, reward, term, trunc, info


@pytest.mark.parametrize("what", ["cost", "reward", "observation"])
def test_reject_non_finite_names_the_env_and_the_step(what):
    env = RejectNonFinite(_NaNCostAt(TinyHazardEnv(), 3, what), name="my-env")
    env.reset(seed=0)
    env.step(np.zeros(2))
    env.step(np.zeros(2))
    with pytest.raises(
        NonFiniteStepError, match=rf"env my-env returned a non-finite {what} .* step 3"
    ):
        env.step(np.zeros(2))


@pytest.mark.parametrize("num_workers", [1, 3])
def test_make_env_rejects_a_nan_cost_naming_the_preset(monkeypatch, num_workers):
    real_step = TinyHazardEnv.step

    def nan_cost_step(self, action):
        obs, reward, term, trunc, info = real_step(self, action)
        return obs, reward, term, trunc, {**info, "cost": float("nan")}

    env = make_env("tiny", seed=0, num_workers=num_workers, parallel=False)
    env.rollout(2)  # finite so far
    monkeypatch.setattr(TinyHazardEnv, "step", nan_cost_step)
    with pytest.raises(
        NonFiniteStepError, match=r"env tiny \(wcsac_rl/TinyHazard-v0\) returned a non-finite cost"
    ):
        env.rollout(2)
    env.close()


def test_a_nan_cost_from_the_env_stops_training_with_one_line_and_keeps_the_checkpoint(
    tmp_path, monkeypatch
):
    trainer = _trainer(tmp_path, "total_frames=1200", "checkpoint_every_epochs=1")
    real_step = TinyHazardEnv.step
    steps = {"n": 0}

    def step(self, action):
        obs, reward, term, trunc, info = real_step(self, action)
        steps["n"] += 1
        # epoch 1: 400 training steps and one 100-step test episode; then epoch 2
        if steps["n"] == 600:
            info = {**info, "cost": float("nan")}
        return obs, reward, term, trunc, info

    monkeypatch.setattr(TinyHazardEnv, "step", step)
    with pytest.raises(NonFiniteStepError, match=r"env tiny \(wcsac_rl/TinyHazard-v0\)"):
        trainer.run()
    trainer.close()
    checkpoint = load_checkpoint(trainer.checkpoint_path)
    assert checkpoint["frames"] == 400  # the epoch-1 checkpoint, not overwritten
