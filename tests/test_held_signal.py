"""``kappa_signal_every``: the critic's start-state tail read once in k training updates
and held in between (:class:`~wcsac_rl.objectives.constraint.HeldStatistic`)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _loss_helpers import make_batch, make_loss
from _training_helpers import compose_config

from wcsac_rl.objectives.constraint import HeldStatistic
from wcsac_rl.training import ConfigError, make_trainer, validate_config
from wcsac_rl.training.checkpoint import load_checkpoint
from wcsac_rl.training.progress import read_progress

START_TAIL = {"kappa_states": "initial", "kappa_actions": "policy", "kappa_statistic": "tail"}


def _counting(loss) -> list[int]:
    """Count the loss's evaluations of the critics at the start states."""
    reads = []
    policy_values = loss._policy_values

    def counted(states, layers=None):
        reads.append(states.batch_size[0])
        return policy_values(states, layers)

    loss._policy_values = counted
    return reads


def test_held_statistic_is_read_once_in_every_k_takes():
    hold = HeldStatistic(3)
    pattern = []
    for step in range(7):
        held = hold.take()
        pattern.append(held is None)
        if held is None:
            hold.store(torch.tensor(float(step)))
        else:  # what the last read stored
            assert float(held) == max(s for s, read in enumerate(pattern) if read)
    assert pattern == [True, False, False, True, False, False, True]
    every = HeldStatistic(1)  # a hold of one update: the critic read at every one
    for value in (1.0, 2.0):
        assert every.take() is None
        every.store(torch.tensor(value))
    assert HeldStatistic(np.int64(3)).every == 3
    for bad in (0, 2.0, True):
        with pytest.raises(ValueError, match=r"kappa_signal_every must be an integer >= 1"):
            HeldStatistic(bad)


@pytest.mark.parametrize("kind", ["gaussian", "iqn"])
def test_the_loss_reads_the_start_states_once_in_k_updates_and_holds_the_tail(kind):
    loss = make_loss(kind=kind, kappa_signal_every=3, **START_TAIL)
    reads = _counting(loss)
    cvars = []
    for step in range(7):  # a new batch each update, its start states new too
        out = loss(make_batch(16, seed=step, initial=True))
        cvars.append(float(out["cvar"]))
    assert len(reads) == 3  # updates 1, 4 and 7
    # held between reads, though each batch brings other start states
    assert cvars[0] == cvars[1] == cvars[2] and cvars[3] == cvars[4] == cvars[5]
    assert len({cvars[0], cvars[3], cvars[6]}) == 3
    # evaluation mode reads every call and leaves the hold as it was
    age = int(loss.kappa_signal_hold.age)
    loss.eval()
    loss(make_batch(16, seed=20, initial=True))
    loss(make_batch(16, seed=21, initial=True))
    assert len(reads) == 5 and int(loss.kappa_signal_hold.age) == age


def test_the_first_update_is_the_every_update_loss_and_k1_keeps_its_state_dict():
    batch = make_batch(16, seed=3, initial=True)
    every, held = make_loss(**START_TAIL), make_loss(kappa_signal_every=4, **START_TAIL)
    assert every.kappa_signal_hold is None
    torch.manual_seed(1)
    first = every(batch.clone())
    torch.manual_seed(1)
    second = held(batch.clone())
    for key in ("loss_actor", "loss_kappa", "cvar"):
        assert torch.equal(first[key], second[key]), key
    extra = set(held.state_dict()) - set(every.state_dict())
    assert extra == {"kappa_signal_hold.value", "kappa_signal_hold.age"}


def test_the_hold_travels_with_the_state_dict():
    loss = make_loss(kappa_signal_every=3, **START_TAIL)
    loss(make_batch(16, seed=0, initial=True))
    held_cvar = float(loss(make_batch(16, seed=1, initial=True))["cvar"])
    restored = make_loss(kappa_signal_every=3, seed=1, **START_TAIL)
    restored.load_state_dict(loss.state_dict())
    reads = _counting(restored)
    assert float(restored(make_batch(16, seed=2, initial=True))["cvar"]) == held_cvar
    assert reads == []  # the third update of three still held it
    restored(make_batch(16, seed=3, initial=True))
    assert reads == [16]


@pytest.mark.parametrize(
    "options, message",
    [
        ({"kappa_signal_every": 0, **START_TAIL}, "kappa_signal_every must be"),
        ({"kappa_signal_every": 2.5, **START_TAIL}, "kappa_signal_every must be"),
        (
            {"kappa_signal_every": 2, **START_TAIL, "kappa_statistic": "mean"},
            "kappa_signal_every=2 .* needs kappa_states=initial and kappa_statistic=tail",
        ),
        (
            {"kappa_signal_every": 5, "kappa_states": "replay", "kappa_statistic": "tail"},
            "needs kappa_states=initial",
        ),
    ],
)
def test_bad_values_are_refused_by_name(options, message):
    with pytest.raises(ValueError, match=message):
        make_loss(**options)


def test_config_refuses_by_name_and_the_trainer_passes_it_to_the_loss(tmp_path):
    for overrides, message in (
        (("algo.kappa_signal_every=0",), "algo.kappa_signal_every must be"),
        (
            ("algo.kappa_signal_every=4", "algo.kappa_statistic=mean"),
            "algo.kappa_signal_every=4 .* needs algo.kappa_states=initial",
        ),
    ):
        with pytest.raises(ConfigError, match=message):
            validate_config(compose_config("env=tiny", *overrides))
    run_dir = tmp_path / "run"
    trainer = make_trainer(compose_config("env=tiny", "algo.kappa_signal_every=4"), run_dir)
    try:
        assert trainer.loss.kappa_signal_every == 4
        trainer.run()
        age = int(trainer.loss.kappa_signal_hold.age)
    finally:
        trainer.close()
    assert 1 <= age <= 4
    saved = load_checkpoint(trainer.checkpoint_path)
    assert int(saved["learner"]["loss"]["kappa_signal_hold.age"]) == age
    assert all(v == v for v in read_progress(run_dir / "progress.csv")["loss/cvar"])
