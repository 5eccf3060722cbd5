"""Device handling in one place (wcsac_rl.training.devices), tested without a GPU.

* A whole run with ``device=cpu:0``, a spec unequal to ``torch.device("cpu")`` although
  tensors report ``cpu`` for both: the envs stay on the env device, tensordicts,
  storages and the collector keep the spec they were given, and the collector acts
  with the trainer's own policy (a spec that differs from its parameters' device
  would make TorchRL act with a copy whose weights nothing updates).
"""

from __future__ import annotations

import pytest
import torch
from _training_helpers import compose_config

from wcsac_rl.training import make_trainer
from wcsac_rl.training.devices import CPU, run_devices
from wcsac_rl.training.restore import load_run

LEARNER = torch.device("cpu:0")
ENV = torch.device("cpu")

CPO_SMALL = [
    "algo=cpo",
    "env=tiny",
    "algo.collector.num_envs=2",
    "algo.collector.frames_per_batch=200",
    "algo.network.width=16",
    "algo.value_iters=5",
    "epoch_frames=400",
    "total_frames=400",
    "eval_episodes=1",
    "progress_bar=false",
]


def _config(algo: str, *overrides: str):
    if algo == "cpo":
        return compose_config(*CPO_SMALL, *overrides, small=False)
    return compose_config("env=tiny", f"algo={algo}", *overrides)


def test_run_devices_put_the_envs_on_the_cpu_and_the_rest_on_the_configured_device():
    devices = run_devices(compose_config("device=cpu:0"))
    assert devices.env == ENV and devices.learner == LEARNER and devices.casts
    assert LEARNER != ENV  # what makes the spec useful on a CPU-only machine
    assert not run_devices(compose_config()).casts and not CPU.casts


def _assert_collector_acts_with_the_trainers_policy(trainer) -> None:
    collector = trainer.collector
    assert collector.policy is trainer.policy  # not a copy: it follows every update
    first = next(trainer.policy.parameters())
    assert collector.policy_device == first.device
    trained = {p.data_ptr() for p in trainer.loss.parameters()}
    assert {p.data_ptr() for p in collector.policy.parameters()} <= trained


@pytest.mark.parametrize("algo", ["wcsac", "sac_lag"])
def test_off_policy_run_on_a_non_default_device_spec_places_every_piece(tmp_path, algo):
    trainer = make_trainer(_config(algo, "device=cpu:0"), tmp_path)
    try:
        _assert_collector_acts_with_the_trainers_policy(trainer)
        trainer.run()
        assert trainer.env.device == ENV  # MuJoCo / NumPy step on the CPU
        assert trainer.eval_env.device == LEARNER  # test episodes cast to the learner
        assert (trainer.collector.env_device, trainer.collector.storing_device) == (ENV, LEARNER)
        assert trainer.replay_buffer.storage.device == LEARNER
        assert trainer.initial_state_buffer.storage.device == LEARNER
        batch = trainer.sample()  # a replay sample with its start states attached
        assert batch.device == LEARNER and batch["initial"].device == LEARNER
        assert trainer.updates > 0 and torch.isfinite(trainer.loss(batch)["kappa"])
    finally:
        trainer.close()
    restored = load_run(tmp_path)  # evaluation rebuilds it on the CPU
    assert restored.cfg.device == "cpu" and restored.env.device == ENV


def test_cpo_run_on_a_non_default_device_spec(tmp_path):
    trainer = make_trainer(_config("cpo", "device=cpu:0"), tmp_path)
    try:
        _assert_collector_acts_with_the_trainers_policy(trainer)
        trainer.run()
        assert trainer.env.device == ENV
        assert trainer.collector.storing_device == LEARNER
    finally:
        trainer.close()
