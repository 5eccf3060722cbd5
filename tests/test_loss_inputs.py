"""NaN in, error out: the loss refuses bad constructor numbers and an empty
batch by name, offers a check of a batch's values (``check_inputs``, or
``check_finite=True``) without a host synchronisation in its default path, and the
trainer stops on a non-finite collected entry, naming it and the frames, keeping its
last checkpoint."""

from __future__ import annotations

import math

import pytest
import torch
from _loss_helpers import make_batch, make_loss
from _training_helpers import compose_config

from wcsac_rl.envs import NonFiniteStepError, RejectNonFinite, TinyHazardEnv
from wcsac_rl.training import TrainingError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"cost_threshold": math.nan}, "cost_threshold must be >= 0 (a finite number), got nan"),
        ({"cost_threshold": math.inf}, "cost_threshold must be >= 0 (a finite number), got inf"),
        ({"cost_threshold": True}, "cost_threshold must be >= 0 (a finite number), got True"),
        ({"cost_limit": math.nan}, "cost_limit must be >= 0 (an episodic cost budget), got nan"),
        ({"cost_limit": math.nan, "cost_threshold": 1.0}, "cost_limit must be >= 0"),
        ({"cost_limit": math.inf}, "cost_limit must be >= 0 (an episodic cost budget), got inf"),
        ({"risk_level": math.nan}, "risk_level α must be a number in (0, 1], got nan"),
        ({"risk_level": 1e-300}, "risk_level α=1e-300 is below the smallest supported"),
    ],
)
def test_bad_constructor_numbers_are_one_error_naming_the_argument(kwargs, message):
    with pytest.raises(ValueError) as err:
        make_loss(**kwargs)
    assert message in str(err.value)


@pytest.mark.parametrize("initial", [False, True])
def test_an_empty_batch_is_one_error_naming_the_batch_size(initial):
    loss = make_loss(kappa_states="initial" if initial else "replay")
    with pytest.raises(ValueError, match=r"WCSACLoss got an empty batch \(batch_size=\[0\]\)"):
        loss(make_batch(0, initial=initial))


def _poisoned(key, value=math.nan):
    batch = make_batch(16)
    entry = batch[key].clone()
    entry.view(-1)[3] = value
    batch[key] = entry
    return batch


KEYS = [("next", "cost"), ("next", "reward"), ("next", "observation"), "observation"]


@pytest.mark.parametrize("key", KEYS)
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_check_inputs_names_the_non_finite_entry(key, value):
    loss = make_loss()
    loss.check_inputs(make_batch(16))  # a finite batch passes
    with pytest.raises(ValueError) as err:
        loss.check_inputs(_poisoned(key, value))
    message = str(err.value)
    assert message.startswith(f"WCSACLoss: batch entry {key!r} holds 1 non-finite value(s)")
    assert f"(e.g. {value})" in message


def test_check_finite_makes_every_call_refuse_a_non_finite_batch_before_any_gradient():
    loss = make_loss(check_finite=True)
    before = {k: v.detach().clone() for k, v in loss.state_dict().items()}
    with pytest.raises(ValueError, match=r"batch entry \('next', 'cost'\)"):
        loss(_poisoned(("next", "cost")))
    assert all(torch.equal(before[k], v) for k, v in loss.state_dict().items())
    out = loss(make_batch(16))
    assert all(torch.isfinite(v).all() for k, v in out.items() if k.startswith("loss_"))


def test_the_default_path_reads_no_values_a_nan_comes_out_as_nan_losses():
    """What ``check_finite=False`` (the default, compile-friendly) leaves to the caller:
    the trainer checks collected batches and skips non-finite updates."""
    out = make_loss()(_poisoned(("next", "cost")))
    assert not torch.isfinite(out["loss_cost_value"])


def _checkpointed_trainer(tmp_path):
    return make_trainer(
        compose_config("env=tiny", "total_frames=1200", "checkpoint_every_epochs=1"),
        tmp_path / "run",
    )


def _nan_cost_after(steps_before: int):
    real_step = TinyHazardEnv.step
    steps = {"n": 0}

    def step(self, action):
        obs, reward, term, trunc, info = real_step(self, action)
        steps["n"] += 1
        if steps["n"] == steps_before:  # epoch 1: 400 training steps, one 100-step test
            info = {**info, "cost": float("nan")}
        return obs, reward, term, trunc, info

    return step


def test_a_non_finite_collected_entry_stops_the_run_naming_it_and_the_frames(tmp_path, monkeypatch):
    """Past the env's own check (an env without RejectNonFinite, or a transform): the
    trainer's check of each collected batch."""
    trainer = _checkpointed_trainer(tmp_path)
    monkeypatch.setattr(TinyHazardEnv, "step", _nan_cost_after(600))
    monkeypatch.setattr(RejectNonFinite, "_reject", lambda self, what, value: None)
    with pytest.raises(TrainingError) as err:
        trainer.run()
    trainer.close()
    message = str(err.value)
    assert "\n" not in message
    assert "the batch collected at frames 400-600 holds a non-finite ('next', 'cost')" in message
    assert f"the last checkpoint {trainer.checkpoint_path} is kept" in message
    assert load_checkpoint(trainer.checkpoint_path)["frames"] == 400


def test_the_envs_own_refusal_says_where_training_stopped(tmp_path, monkeypatch):
    trainer = _checkpointed_trainer(tmp_path)
    monkeypatch.setattr(TinyHazardEnv, "step", _nan_cost_after(600))
    with pytest.raises(NonFiniteStepError) as err:
        trainer.run()
    trainer.close()
    message = str(err.value)
    assert message.startswith("env tiny (wcsac_rl/TinyHazard-v0) returned a non-finite cost")
    assert "training stopped while collecting the frames after 400" in message
    assert f"the last checkpoint {trainer.checkpoint_path} is kept" in message
    assert load_checkpoint(trainer.checkpoint_path)["frames"] == 400


def test_the_loss_still_takes_its_entries_as_keyword_tensors():
    """(TorchRL's ``dispatch``: the checks did not take the forward's decorator away.)"""
    loss = make_loss()
    batch = make_batch(8)
    entries = {"_".join(k) if isinstance(k, tuple) else k: batch.get(k) for k in loss.in_keys}
    assert len(loss(**entries)) == len(loss.out_keys)
