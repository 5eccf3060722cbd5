"""``replay_draw=round``: a collected batch's updates draw their replay rows in one call
(on the learner's device) and read them by index: the same batches the replay buffer
gives for those rows, n-step states included; the loop's updates use them in order."""

from __future__ import annotations

import pytest
import torch
from _training_helpers import compose_config

from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training import off_policy as off_policy_module
from wcsac_rl.training.replay import NStepReplayBuffer, draw_indices, sample_at


def _filled(tmp_path, *overrides):
    trainer = make_trainer(compose_config("env=tiny", *overrides), tmp_path / "run")
    batch = trainer.env.rollout(150, break_when_any_done=False)
    if trainer.postproc is not None:
        batch = trainer.postproc(batch.unsqueeze(0)).squeeze(0)
    trainer.replay_buffer.extend(batch.reshape(-1).select(*trainer.stored_keys))
    return trainer


@pytest.mark.parametrize(
    "overrides, nstep",
    [(("algo=sac",), False), (("algo=wcsac", "algo.cost_n_steps=10"), True)],
    ids=["plain", "n-step"],
)
def test_rows_read_by_index_are_the_buffers_own_batch(tmp_path, overrides, nstep):
    trainer = _filled(tmp_path, *overrides)
    try:
        buffer = trainer.replay_buffer
        assert isinstance(buffer, NStepReplayBuffer) == nstep
        torch.manual_seed(5)
        expected = buffer.sample()
        actual = sample_at(buffer, expected["index"])
        assert sorted(map(str, actual.keys(True, True))) == sorted(
            map(str, expected.keys(True, True))
        )
        for key in expected.keys(True, True):
            assert torch.equal(actual[key], expected[key]), key
        # one draw of 3 batches' rows: the rows 3 draws of one batch give from the same
        # random state (when nothing else draws in between)
        torch.manual_seed(7)
        drawn = draw_indices(buffer, 3)
        torch.manual_seed(7)
        one_by_one = torch.stack([buffer.sample()["index"] for _ in range(3)])
        assert drawn.shape == (3, buffer.batch_size) and torch.equal(drawn, one_by_one)
    finally:
        trainer.close()


def test_a_round_of_updates_reads_the_rows_drawn_for_it_in_order(tmp_path, monkeypatch):
    trainer = make_trainer(
        compose_config("env=tiny", "algo=wcsac", "replay_draw=round"), tmp_path / "run"
    )
    drawn, used = [], []
    real_draw, real_update = off_policy_module.draw_indices, trainer.update

    def spy_draw(buffer, count):
        drawn.append(real_draw(buffer, count))
        return drawn[-1]

    def spy_update(batch):
        used.append(batch["index"].clone())
        return real_update(batch)

    monkeypatch.setattr(off_policy_module, "draw_indices", spy_draw)
    trainer.update = spy_update
    try:
        collected = iter(trainer.collector)
        for _ in range(3):
            trainer.tracker.add(batch := next(collected))
            trainer.learn(batch)
        assert len(drawn) >= 2  # (one per batch that was learned from)
        assert trainer.updates == len(used) == len(drawn) * trainer.updates_per_batch
        assert torch.equal(torch.stack(used), torch.cat(drawn))
    finally:
        trainer.close()


def test_an_unknown_replay_draw_is_refused_in_one_line(tmp_path):
    with pytest.raises(ConfigError) as excinfo:
        make_trainer(compose_config("env=tiny", "algo=wcsac", "replay_draw=epoch"), tmp_path / "r")
    message = str(excinfo.value)
    assert "\n" not in message and "replay_draw" in message and "'epoch'" in message
