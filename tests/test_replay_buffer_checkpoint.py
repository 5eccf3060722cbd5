"""The replay buffer (and the start-state buffer) saved with a checkpoint: atomic, next
to the checkpoint it belongs to, checked on load."""

from __future__ import annotations

import pytest
import torch
from _training_helpers import compose_config

from wcsac_rl.training import ConfigError, TrainingError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint

OPTIONS = ("env=tiny", "save_replay_buffer=true", "checkpoint_every_epochs=1")
INITIAL = ("algo.kappa_states=initial",)


def _train(run_dir, *overrides):
    trainer = make_trainer(compose_config(*OPTIONS, *overrides), run_dir)
    try:
        trainer.run()
    finally:
        trainer.close()
    return trainer


def _resume(run_dir, *overrides):
    return make_trainer(
        compose_config(*OPTIONS, "total_frames=1200", *overrides, f"resume={run_dir}"), run_dir
    )


def test_buffers_are_saved_beside_the_checkpoint_that_names_them(tmp_path):
    run_dir = tmp_path / "run"
    trainer = _train(run_dir, *INITIAL)
    checkpoints = run_dir / "checkpoints"
    # one directory per checkpoint; the epoch-1 one was removed once epoch 2's was in place
    assert sorted(p.name for p in checkpoints.iterdir()) == ["buffers-800", "last.pt"]
    manifest = load_checkpoint(checkpoints / "last.pt")["learner"]["buffers"]
    assert manifest["dir"] == "buffers-800"
    assert set(manifest["buffers"]) == {"replay_buffer", "initial_state_buffer"}
    observation = "replay_buffer/storage/observation.memmap"
    size, digest = manifest["files"][observation]
    assert size == (checkpoints / "buffers-800" / observation).stat().st_size
    assert len(digest) == 64
    resumed = _resume(run_dir, *INITIAL)
    try:
        assert len(resumed.replay_buffer) == len(trainer.replay_buffer) == 800
        assert torch.equal(
            resumed.replay_buffer[:]["observation"], trainer.replay_buffer[:]["observation"]
        )
        assert len(resumed.initial_state_buffer) == len(trainer.initial_state_buffer)
    finally:
        resumed.close()


@pytest.mark.parametrize(
    ("name", "damage", "message"),
    [
        (
            "replay_buffer/storage/observation.memmap",
            "truncate",
            r"replay_buffer/storage/observation\.memmap: \d+ bytes, expected \d+",
        ),
        (
            "replay_buffer/storage/observation.memmap",
            "overwrite",
            r"observation\.memmap: its contents changed since it was saved",
        ),
        ("replay_buffer/storage/next/cost.memmap", "delete", r"cost\.memmap is missing"),
        (
            "initial_state_buffer/storage/observation.memmap",
            "truncate",
            r"initial_state_buffer/storage/observation\.memmap: \d+ bytes",
        ),
    ],
)
def test_a_damaged_buffer_is_one_clear_line_on_resume(tmp_path, name, damage, message):
    run_dir = tmp_path / "run"
    _train(run_dir, *INITIAL)
    path = run_dir / "checkpoints" / "buffers-800" / name
    data = path.read_bytes()
    if damage == "truncate":  # the reproduction: 5 958 of 6 000 rows read as zeros
        path.write_bytes(data[: len(data) // 100])
    elif damage == "overwrite":
        path.write_bytes(bytes(len(data)))
    else:
        path.unlink()
    with pytest.raises(ConfigError, match=message) as err:
        _resume(run_dir, *INITIAL)
    assert "\n" not in str(err.value)
    assert f"delete {run_dir / 'checkpoints' / 'buffers-800'} to resume without it" in str(
        err.value
    )


def test_without_its_buffer_directory_a_resume_refills_the_buffer(tmp_path, capsys):
    import shutil

    run_dir = tmp_path / "run"
    _train(run_dir)
    shutil.rmtree(run_dir / "checkpoints" / "buffers-800")
    resumed = _resume(run_dir)
    try:
        assert len(resumed.replay_buffer) == 0
        assert resumed.update_start_frames == 800 + 200  # refilled before updates resume
        assert "it is refilled instead" in capsys.readouterr().out
    finally:
        resumed.close()


def test_a_failed_buffer_save_keeps_the_previous_checkpoint_and_its_buffers(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    trainer = make_trainer(compose_config(*OPTIONS), run_dir)
    real_dumps = type(trainer.replay_buffer).dumps
    calls = {"n": 0}

    def dumps(self, path):  # (the start-state buffer is a replay buffer too: not counted)
        real_dumps(self, path)
        if self is not trainer.replay_buffer:
            return
        calls["n"] += 1
        if calls["n"] == 2:  # the epoch-2 save: written, then the disk is full
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 7 vs 5")

    monkeypatch.setattr(type(trainer.replay_buffer), "dumps", dumps)
    try:
        with pytest.raises(TrainingError, match=r"cannot write the replay buffer .* no space left"):
            trainer.run()
    finally:
        trainer.close()
    checkpoints = run_dir / "checkpoints"
    assert sorted(p.name for p in checkpoints.iterdir()) == ["buffers-400", "last.pt"]
    assert load_checkpoint(checkpoints / "last.pt")["frames"] == 400
    monkeypatch.undo()
    resumed = _resume(run_dir)  # the epoch-1 checkpoint and its buffer still verify
    try:
        assert len(resumed.replay_buffer) == 400
    finally:
        resumed.close()
