"""Shutdown is clean: a stop signal while a checkpoint is written waits until the
file is in place (the old or the new file, never a temporary one), and the message of a
stopped run names the command that continues it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from _training_helpers import ROOT, compose_config

from wcsac_rl.training import make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, resume_config
from wcsac_rl.training.off_policy import OffPolicyTrainer
from wcsac_rl.training.preemption import DeferredSignals, Preempted


def test_deferred_signals_deliver_after_the_block_to_the_previous_handler():
    got = []
    before = signal.signal(signal.SIGUSR1, lambda s, f: got.append(s))
    try:
        with DeferredSignals():
            os.kill(os.getpid(), signal.SIGUSR1)
            with DeferredSignals():  # nested: the outer block keeps it
                os.kill(os.getpid(), signal.SIGUSR1)
            assert got == []
        assert got == [signal.SIGUSR1]  # once: the first one decides
    finally:
        signal.signal(signal.SIGUSR1, before)


WRITE_WITH_SIGTERM = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    import torch
    from wcsac_rl.training.checkpoint import save_checkpoint

    path = Path(sys.argv[1])
    save_checkpoint(path, {"frames": 400, "x": torch.zeros(1000)})
    real_save = torch.save

    def save(obj, f, *args, **kwargs):
        f.write(b"half a file")
        os.kill(os.getpid(), signal.SIGTERM)  # the scheduler, mid-write
        f.seek(0)
        f.truncate()
        return real_save(obj, f, *args, **kwargs)

    torch.save = save
    save_checkpoint(path, {"frames": 800, "x": torch.ones(1000)})
    print("not reached: SIGTERM ends the process once the file is in place")
    """
)


def test_sigterm_during_a_checkpoint_write_ends_the_process_after_the_file_is_in_place(tmp_path):
    path = tmp_path / "checkpoints" / "last.pt"
    result = subprocess.run(
        [sys.executable, "-c", WRITE_WITH_SIGTERM, str(path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == -signal.SIGTERM, result.stderr[-2000:]
    assert "not reached" not in result.stdout
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]  # no last.pt.tmp
    assert load_checkpoint(path, required=())["frames"] == 800


class SignalsDuringItsFinalSave(OffPolicyTrainer):
    """A real trainer that gets SIGTERM while it writes its final checkpoint."""

    def save(self):
        if self.tracker.frames == int(self.cfg.total_frames):
            os.kill(os.getpid(), signal.SIGTERM)
        return super().save()


def test_sigterm_during_the_final_checkpoint_finds_the_run_complete(tmp_path, capsys):
    run_dir = tmp_path / "run"
    trainer = SignalsDuringItsFinalSave(compose_config("env=tiny", "algo=sac"), run_dir)
    try:
        assert trainer.run() == run_dir
    finally:
        trainer.close()
    out = capsys.readouterr().out
    assert (
        f"SIGTERM: the run is complete (800 frames); checkpoint written to {trainer.checkpoint_path}"
        in out
    )
    assert load_checkpoint(trainer.checkpoint_path)["frames"] == 800
    assert not [p for p in run_dir.rglob("*") if p.name.endswith(".tmp")]
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


class SignalsItself(OffPolicyTrainer):
    def learn(self, batch):
        out = super().learn(batch)
        if self.tracker.frames == 600:
            os.kill(os.getpid(), signal.SIGTERM)
        return out


def test_a_stopped_run_without_resume_auto_names_resume_run_dir_which_continues_it(tmp_path):
    run_dir = tmp_path / "run"
    trainer = SignalsItself(compose_config("env=tiny", "algo=sac", "total_frames=1200"), run_dir)
    try:
        with pytest.raises(Preempted) as stopped:
            trainer.run()
    finally:
        trainer.close()
    message = str(stopped.value)
    assert message.endswith(f"continue it with: python train.py resume={run_dir}")
    assert "same command" not in message
    # the named command continues it (train.py resume=RUN_DIR: the run's own config)
    given = [f"resume={run_dir}"]
    resumed = make_trainer(resume_config(compose_config(*given, small=False), given), Path("x"))
    try:
        resumed.run()
    finally:
        resumed.close()
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["frames"] == 1200
