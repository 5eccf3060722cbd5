"""``algo.kappa_hold_goal_rate``: κ held where it starts (its optimizer not stepped)
until an epoch whose finished training episodes reached the goal at that rate, then
free for good; the hold and its release are in progress.csv and the checkpoint."""

from __future__ import annotations

import csv
import math

import pytest
import torch
from _training_helpers import compose_config

from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint

HOLD = ("algo=wcsac", "env=tiny", "algo.kappa_hold_goal_rate=1.0")


def _rows(run_dir):
    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _kappa(trainer) -> float:
    return float(trainer.loss.constraint.kappa)


def test_kappa_is_held_until_an_epoch_reaches_the_goal_rate_then_moves(tmp_path):
    trainer = make_trainer(compose_config(*HOLD), tmp_path / "run")
    try:
        start = _kappa(trainer)
        actor = [p.detach().clone() for p in trainer.agent.actor.parameters()]
        run_dir = trainer.run()
        rows = _rows(run_dir)
        # 400 updates: the actor moved, κ did not, and its optimizer never stepped
        assert int(rows[-1]["updates"]) > 0
        assert any(not torch.equal(a, p) for a, p in zip(actor, trainer.agent.actor.parameters()))
        assert _kappa(trainer) == start == pytest.approx(math.log(2.0))
        assert trainer.optimizers["kappa"].state_dict()["state"] == {}
        # (a random tiny-env policy reaches the goal in fewer than all of its episodes)
        rates = [float(r["train/goal_rate"]) for r in rows]
        assert all(rate < 1.0 for rate in rates if not math.isnan(rate))
        assert [float(r["train/kappa_held"]) for r in rows] == [1.0, 1.0]
        assert load_checkpoint(trainer.checkpoint_path)["learner"]["kappa_held"] is True
        # an epoch at the rate releases κ: the next update moves it
        trainer.observe_training_episodes({"train/goal_rate": 1.0})
        assert trainer.kappa_held is False
        trainer.update(trainer.sample())
        assert _kappa(trainer) != start
        # for good: a slower epoch later does not hold it again
        trainer.observe_training_episodes({"train/goal_rate": 0.0})
        assert trainer.kappa_held is False
    finally:
        trainer.close()


def test_an_epoch_without_finished_episodes_does_not_release_kappa(tmp_path):
    trainer = make_trainer(compose_config(*HOLD[:-1], "algo.kappa_hold_goal_rate=0.5"), tmp_path)
    try:
        trainer.observe_training_episodes({"train/goal_rate": math.nan})
        assert trainer.kappa_held is True
        trainer.observe_training_episodes({"train/goal_rate": 0.5})
        assert trainer.kappa_held is False
    finally:
        trainer.close()


def test_without_the_option_nothing_is_held_or_logged(tmp_path):
    trainer = make_trainer(compose_config("algo=wcsac", "env=tiny"), tmp_path)
    try:
        assert trainer.kappa_held is False
        assert "train/kappa_held" not in trainer.collection_metrics()
        assert "kappa_held" not in trainer.learner_state()
    finally:
        trainer.close()


@pytest.mark.parametrize(
    "overrides, message",
    [
        (("algo.kappa_rule=pid",), "needs algo.kappa_rule=gradient, got pid"),
        (("algo.kappa_hold_goal_rate=1.5",), "algo.kappa_hold_goal_rate must be"),
        (("algo.kappa_hold_goal_rate=-0.1",), "algo.kappa_hold_goal_rate must be"),
    ],
)
def test_a_hold_that_cannot_work_is_one_clear_error(tmp_path, overrides, message):
    with pytest.raises(ConfigError, match=message):
        make_trainer(compose_config(*HOLD, *overrides), tmp_path)
