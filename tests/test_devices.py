"""Device handling in one place (wcsac_rl.training.devices), tested without a GPU.

* The learner built on ``torch.device("meta")`` (no GPU needed, and unlike ``cpu:N`` a
  different device for real): every parameter, buffer, target, β, κ, optimizer entry,
  replay and start-state storage and replay sample must be there, so a piece built
  without its ``.to(learner)`` (or with a tensor made on the default device) fails
  here. Meta tensors hold no values: nothing is trained on them.
* A whole run with ``device=cpu:0``, a spec unequal to ``torch.device("cpu")`` although
  tensors report ``cpu`` for both: the envs stay on the env device, tensordicts,
  storages and the collector keep the spec they were given, and the collector acts
  with the trainer's own policy (a spec that differs from its parameters' device
  would make TorchRL act with a copy whose weights nothing updates).
"""

from __future__ import annotations

import pytest
import torch
from _training_helpers import TINY_CPO, compose_config

from wcsac_rl.training import builders, make_trainer
from wcsac_rl.training.devices import CPU, run_devices
from wcsac_rl.training.registry import trainer_class
from wcsac_rl.training.restore import load_run
from wcsac_rl.training.trainer import env_max_episode_steps

LEARNER = torch.device("cpu:0")
ENV = torch.device("cpu")
META = torch.device("meta")

CPO_SMALL = [*TINY_CPO, "total_frames=400"]


def _config(algo: str, *overrides: str):
    if algo == "cpo":
        return compose_config(*CPO_SMALL, *overrides, small=False)
    return compose_config("env=tiny", f"algo={algo}", *overrides)


def test_run_devices_put_the_envs_on_the_cpu_and_the_rest_on_the_configured_device():
    devices = run_devices(compose_config("device=cpu:0"))
    assert devices.env == ENV and devices.learner == LEARNER and devices.casts
    assert LEARNER != ENV  # what makes the spec useful on a CPU-only machine
    assert not run_devices(compose_config()).casts and not CPU.casts


def _tensors(*modules: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {
        f"{k}.{name}": t
        for k, module in enumerate(modules)
        for name, t in [*module.named_parameters(), *module.named_buffers()]
    }


@pytest.mark.parametrize("algo", ["wcsac", "sac_lag", "sac", "cpo"])
def test_the_learner_built_on_the_meta_device_has_every_piece_there(monkeypatch, algo):
    """The trainer's own ``_build_learner`` with ``device=meta`` (set after composing:
    ``validate_config`` accepts only real devices). TorchRL's target updater cannot be
    built on meta (``SoftUpdate`` compares storages with ``is_set_to``, which has no meta
    kernel): it is left out; the targets it updates are buffers of the loss, checked
    here. The WCSAC loss cannot run on meta (its forward reads a value on the host: the
    CVaR bracket); SAC-Lag's and SAC's do."""
    cfg = _config(algo)
    cfg.device = "meta"
    monkeypatch.setattr(builders, "make_target_updater", lambda cfg, loss: None)
    cls = trainer_class(algo)
    trainer = cls.__new__(cls)  # only what _build_learner reads: no collector, no run dir
    trainer.cfg = cfg
    trainer.env = builders.make_train_env(cfg)
    trainer.max_episode_steps = env_max_episode_steps(cfg)
    try:
        assert trainer.env.device == ENV
        trainer._build_learner()
        tensors = _tensors(trainer.loss, trainer.policy)
        assert tensors and {n for n, t in tensors.items() if t.device != META} == set()
        if algo == "cpo":
            optimizers = {"value": trainer.learner.value_optimizer}
        else:
            optimizers = trainer.optimizers
            if algo == "wcsac":
                assert trainer.loss.kappa_raw.device == META
        params = [p for o in optimizers.values() for g in o.param_groups for p in g["params"]]
        assert params and {p.device for p in params} == {META}
        if algo == "cpo":
            return  # no replay: the collector's batch is the update's
        # real transitions from the CPU envs, stored as the trainer stores them
        batch = trainer.env.rollout(60, break_when_any_done=False)
        assert batch.device == ENV
        trainer.tracker = None  # (learn() is not called: no update)
        if trainer.postproc is not None:
            batch = trainer.postproc(batch)
        trainer.replay_buffer.extend(batch.reshape(-1).select(*trainer.replay_keys))
        storage = trainer.replay_buffer.storage
        assert storage.device == META
        assert {t.device for t in storage._storage.values(True, True)} == {META}
        if algo in ("wcsac", "sac_lag"):  # kappa_states=initial: start states
            starts = trainer.initial_state_buffer
            assert starts.add_starts(batch) == 2  # one episode start per env
            assert {t.device for t in starts.storage._storage.values(True, True)} == {META}
        sample = trainer.sample()
        assert {t.device for t in sample.values(True, True)} == {META}
        if algo in ("sac_lag", "sac"):
            out = trainer.loss(sample)
            assert {t.device for t in out.values(True, True)} == {META}
    finally:
        trainer.env.close()


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
