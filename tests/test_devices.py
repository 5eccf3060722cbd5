"""Device handling in one place (wcsac_rl.training.devices), tested with a non-default
CPU device spec: ``device=cpu:0`` is not ``torch.device("cpu")``, so a piece built on a
hard-coded or wrong device (an env on the learner, a buffer on the env's device, a
tensordict made with ``device="cpu"``) shows here, where no GPU exists. (Tensors and
parameters report ``cpu`` for either spec; tensordicts, storages and the collector
keep the spec they were given.)"""

from __future__ import annotations

import pytest
import torch
from _training_helpers import compose_config

from wcsac_rl.training import make_trainer
from wcsac_rl.training.devices import CPU, run_devices
from wcsac_rl.training.restore import load_run

LEARNER = torch.device("cpu:0")
ENV = torch.device("cpu")


def test_run_devices_put_the_envs_on_the_cpu_and_the_rest_on_the_configured_device():
    devices = run_devices(compose_config("device=cpu:0"))
    assert devices.env == ENV and devices.learner == LEARNER and devices.casts
    assert LEARNER != ENV  # what makes the spec useful on a CPU-only machine
    assert not run_devices(compose_config()).casts and not CPU.casts


@pytest.mark.parametrize("algo", ["wcsac", "sac_lag"])
def test_off_policy_run_on_a_non_default_device_spec_places_every_piece(tmp_path, algo):
    trainer = make_trainer(compose_config("env=tiny", f"algo={algo}", "device=cpu:0"), tmp_path)
    try:
        trainer.run()
        assert trainer.env.device == ENV  # MuJoCo / NumPy step on the CPU
        assert trainer.eval_env.device == LEARNER  # test episodes cast to the learner
        collector_devices = (
            trainer.collector.env_device,
            trainer.collector.policy_device,
            trainer.collector.storing_device,
        )
        assert collector_devices == (ENV, LEARNER, LEARNER)
        assert trainer.replay_buffer.storage.device == LEARNER
        assert trainer.initial_state_buffer.storage.device == LEARNER
        batch = trainer.sample()  # a replay sample with its start states attached
        assert batch.device == LEARNER and batch["initial"].device == LEARNER
        out = trainer.loss(batch)  # the loss runs on it: every tensor on the learner's type
        assert {v.device.type for v in out.values()} == {"cpu"}
        assert trainer.updates > 0 and torch.isfinite(out["kappa"])
    finally:
        trainer.close()
    restored = load_run(tmp_path)  # evaluation rebuilds it on the CPU
    assert restored.cfg.device == "cpu" and restored.env.device == ENV


def test_cpo_run_on_a_non_default_device_spec(tmp_path):
    overrides = [
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
        "device=cpu:0",
    ]
    trainer = make_trainer(compose_config(*overrides, small=False), tmp_path)
    try:
        trainer.run()
        assert trainer.env.device == ENV
        assert trainer.collector.storing_device == LEARNER
    finally:
        trainer.close()
