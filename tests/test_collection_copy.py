"""With the learner off the CPU the collector acts with a CPU copy of the actor, which
takes the learner's weights after each batch's updates and after a resume. Here (no
GPU) the copy is forced on a CPU learner (``collect_on_cpu_copy``)."""

from __future__ import annotations

import pytest
import torch
from _training_helpers import compose_config
from tensordict import TensorDict

from wcsac_rl.training import make_trainer
from wcsac_rl.training.off_policy import OffPolicyTrainer


def _weights(module) -> TensorDict:
    return TensorDict.from_module(module).data.clone()


def _equal(a: TensorDict, b: TensorDict) -> bool:
    return all(torch.equal(a[k], b[k]) for k in a.keys(True, True))


def _learn_batches(trainer, batches: int) -> None:
    collected = iter(trainer.collector)
    for _ in range(batches):
        trainer.tracker.add(batch := next(collected))
        trainer.learn(batch)


def test_the_collector_acts_with_a_cpu_copy_refreshed_after_each_batch(tmp_path, monkeypatch):
    monkeypatch.setattr(OffPolicyTrainer, "collect_on_cpu_copy", True)
    trainer = make_trainer(compose_config("env=tiny", "algo=wcsac"), tmp_path / "run")
    try:
        copy, actor = trainer.acting_copy, trainer.agent.actor
        assert copy is not None and trainer.collector.policy is copy
        assert copy.actor is not actor and trainer.policy.actor is actor  # (tests: the learner's)
        learner, acting = TensorDict.from_module(actor), TensorDict.from_module(copy.actor)
        assert all(learner[k].data_ptr() != acting[k].data_ptr() for k in learner.keys(True, True))
        initial = _weights(actor)
        assert _equal(_weights(copy.actor), initial)
        _learn_batches(trainer, 3)  # (the first is the random warm-up: no update)
        assert trainer.updates > 0 and not _equal(_weights(actor), initial)
        assert _equal(_weights(copy.actor), _weights(actor))
        # between refreshes the copy keeps the weights it acted with
        trainer.update(trainer.sample())
        assert not _equal(_weights(copy.actor), _weights(actor))
        # a resumed learner's weights reach the copy
        state = trainer.learner_state()
        resumed = make_trainer(compose_config("env=tiny", "algo=wcsac"), tmp_path / "other")
        try:
            resumed.load_learner_state(state)
            assert _equal(_weights(resumed.acting_copy.actor), _weights(actor))
        finally:
            resumed.close()
    finally:
        trainer.close()


@pytest.mark.parametrize("overrides", [(), ("algo.shield.candidates=4",)], ids=["plain", "shield"])
def test_a_cpu_learner_and_a_shielded_collector_act_with_the_learners_policy(
    tmp_path, monkeypatch, overrides
):
    """No copy on a CPU learner; none with a shield either (it reads the learner's
    safety critic), whatever the device."""
    if overrides:
        monkeypatch.setattr(OffPolicyTrainer, "collect_on_cpu_copy", True)
    trainer = make_trainer(compose_config("env=tiny", "algo=wcsac", *overrides), tmp_path / "r")
    try:
        assert trainer.acting_copy is None
        expected = trainer.policy if not overrides else trainer.collection_policy
        assert trainer.collector.policy is expected
    finally:
        trainer.close()
