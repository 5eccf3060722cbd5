"""The replay buffer reads each row's n-step state from the row that holds it.

``NStepReplayBuffer`` does not store ``("nstep", "observation")`` (``s_{t+m}``, 4·obs_dim
bytes per row); it reads it at sampling from the next observation of transition
``t+m−1``, written in the same collected piece. Checked against the stored copy: through
wrap-arounds of the ring, after a save and load (also of a buffer saved with the copy),
and through the trainer (the same batches as a trainer storing it).
"""

from __future__ import annotations

import pytest
import torch
from _training_helpers import compose_config
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from wcsac_rl.objectives import NStepCost
from wcsac_rl.training import builders, make_trainer
from wcsac_rl.training.replay import NStepReplayBuffer

OBS = 3


def _piece(seed: int, envs: int = 2, steps: int = 12) -> TensorDict:
    """A collected piece ``[envs, steps]`` with episode ends, costs and the n-step
    entries; ``expected`` holds NStepCost's own ``s_{t+m}`` of each row."""
    g = torch.Generator().manual_seed(seed)
    done = torch.rand(envs, steps, 1, generator=g) < 0.15
    piece = TensorDict(
        {
            "observation": torch.randn(envs, steps, OBS, generator=g),
            "next": {
                "observation": torch.randn(envs, steps, OBS, generator=g),
                "cost": torch.rand(envs, steps, 1, generator=g),
                "done": done,
                "terminated": done.clone(),
            },
        },
        [envs, steps],
    )
    piece = NStepCost(4, gamma=1.0)(piece)
    piece["expected"] = piece["nstep", "observation"].clone()
    return piece


def _buffer(capacity: int) -> NStepReplayBuffer:
    return NStepReplayBuffer(
        storage=LazyTensorStorage(capacity),
        batch_size=64,
        nstep_key="nstep",
        state_keys=["observation"],
    )


def _stored(piece: TensorDict) -> TensorDict:
    return piece.reshape(-1).exclude(("nstep", "observation"))


@pytest.mark.parametrize("capacity", [50, 24, 200])
def test_sampled_nstep_states_are_those_nstep_cost_gave_through_wraparounds(capacity):
    buffer = _buffer(capacity)
    assert buffer.gathered_keys == [("nstep", "observation")]
    for seed in range(7):  # 7 pieces of 24 rows: the ring wraps (but at 200) mid-piece
        buffer.extend(_stored(_piece(seed)))
        assert "observation" not in buffer[:]["nstep"].keys()
        for _ in range(3):
            batch = buffer.sample()
            assert torch.equal(batch["nstep", "observation"], batch["expected"])
    # the lookahead reached past the row itself (m > 1) somewhere
    assert int(buffer[:]["nstep", "steps"].max()) == 4


def test_a_saved_buffer_loads_and_reads_the_same_states(tmp_path):
    buffer = _buffer(50)
    for seed in range(3):
        buffer.extend(_stored(_piece(seed)))
    buffer.dumps(tmp_path / "new")
    loaded = _buffer(50)
    loaded.loads(tmp_path / "new")
    torch.manual_seed(0)
    batch = loaded.sample()
    assert torch.equal(batch["nstep", "observation"], batch["expected"])
    # a buffer saved with the state stored (before this buffer existed) loads too
    old = TensorDictReplayBuffer(storage=LazyTensorStorage(50), batch_size=64)
    for seed in range(3):
        old.extend(_piece(seed).reshape(-1))
    old.dumps(tmp_path / "old")
    loaded = _buffer(50)
    loaded.loads(tmp_path / "old")
    loaded.extend(_stored(_piece(5)))  # (the stored copy is then stale for these rows)
    for _ in range(3):
        batch = loaded.sample()
        assert torch.equal(batch["nstep", "observation"], batch["expected"])


def _trainer(run_dir, store: bool, monkeypatch):
    if store:  # the buffer as it was: every entry the loss reads stored
        monkeypatch.setattr(
            builders,
            "make_replay_buffer",
            lambda cfg, *args: TensorDictReplayBuffer(
                storage=LazyTensorStorage(int(cfg.algo.buffer_size)),
                batch_size=int(cfg.algo.batch_size),
            ),
        )
    trainer = make_trainer(compose_config("env=tiny", "total_frames=800"), run_dir)
    monkeypatch.undo()
    try:
        trainer.run()
    finally:
        trainer.close()
    return trainer


def test_the_trainer_samples_what_it_sampled_when_storing_the_state(tmp_path, monkeypatch):
    reads = _trainer(tmp_path / "reads", False, monkeypatch)
    stores = _trainer(tmp_path / "stores", True, monkeypatch)
    assert isinstance(reads.replay_buffer, NStepReplayBuffer)
    assert ("nstep", "observation") in reads.replay_keys  # (what a batch holds)
    assert ("nstep", "observation") not in reads.stored_keys
    assert ("nstep", "observation") in stores.stored_keys
    assert "observation" not in reads.replay_buffer[:]["nstep"].keys()
    assert len(reads.replay_buffer) == len(stores.replay_buffer) == 800
    # the same run (same batches, same updates): the same parameters at the end
    for (name, a), b in zip(reads.loss.named_parameters(), stores.loss.parameters()):
        assert torch.equal(a, b), name
    for seed in range(3):
        torch.manual_seed(seed)
        a = reads.sample()
        torch.manual_seed(seed)
        b = stores.sample()
        assert torch.equal(a["nstep", "steps"], b["nstep", "steps"])
        assert int(a["nstep", "steps"].max()) > 1
        assert torch.equal(a["nstep", "observation"], b["nstep", "observation"])


def test_pieces_larger_than_the_buffer_store_the_state(tmp_path):
    cfg = compose_config("env=tiny", "algo.buffer_size=150")  # pieces of 200 frames
    trainer = make_trainer(cfg, tmp_path / "run")
    try:
        assert not isinstance(trainer.replay_buffer, NStepReplayBuffer)
        assert ("nstep", "observation") in trainer.stored_keys
    finally:
        trainer.close()
