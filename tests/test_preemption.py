"""Stop signals and resume=auto, in process: a run stopped by SIGTERM / SIGUSR1 / SIGUSR2
checkpoints at a batch boundary, hands the signal on, and the same config continues it.

(Through real launchers, killed from outside: tests/test_launchers.py.)"""

from __future__ import annotations

import csv
import os
import signal
from pathlib import Path

import pytest
from _training_helpers import compose_config

from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint
from wcsac_rl.training.off_policy import OffPolicyTrainer
from wcsac_rl.training.preemption import Preempted, StopSignals


def _rows(run_dir: Path) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _run(cfg, run_dir: Path, cls=None):
    trainer = (cls or make_trainer)(cfg, run_dir)
    try:
        trainer.run()
    finally:
        trainer.close()
    return trainer


class SignalsItself(OffPolicyTrainer):
    """A real trainer that sends itself a real signal once it has collected ``at`` frames."""

    at = 600
    signum = signal.SIGUSR1

    def learn(self, batch):
        out = super().learn(batch)
        if self.tracker.frames == self.at:
            os.kill(os.getpid(), self.signum)
        return out


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2])
def test_a_stop_signal_checkpoints_mid_epoch_then_the_same_config_continues(tmp_path, signum):
    run_dir = tmp_path / "run"
    cfg = compose_config("env=tiny", "algo=sac", "resume=auto", "total_frames=1200")
    calls = []

    def previous(sig, frame):  # what a scheduler's handler (submitit's) would be
        calls.append((sig, load_checkpoint(run_dir / "checkpoints" / "last.pt")["frames"]))

    before = signal.signal(signum, previous)
    try:
        SignalsItself.signum = signum
        with pytest.raises(Preempted) as stopped:
            _run(cfg, run_dir, SignalsItself)
        # the handler that was there before gets the signal, after the checkpoint
        assert calls == [(signum, 600)]
        assert signal.getsignal(signum) is previous
    finally:
        signal.signal(signum, before)
    assert stopped.value.signum == signum and stopped.value.frames == 600
    assert stopped.value.exit_code == 128 + signum
    assert "resume=auto" in str(stopped.value)
    checkpoint = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    assert checkpoint["frames"] == 600 and checkpoint["epoch"] == 1  # mid-epoch 2
    assert [int(r["frames"]) for r in _rows(run_dir)] == [400]

    _run(cfg, run_dir)  # the same config again: resume=auto continues the run dir
    rows = _rows(run_dir)
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3]
    assert [int(r["frames"]) for r in rows] == [400, 800, 1200]
    assert (run_dir / "config.resume1.yaml").is_file()
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["frames"] == 1200


class SignalsDuringItsFirstSave(OffPolicyTrainer):
    """A real trainer that gets a stop signal while it writes its first periodic checkpoint."""

    def save(self):
        self.saves = [*getattr(self, "saves", []), self.tracker.frames]
        if len(self.saves) == 1:
            os.kill(os.getpid(), signal.SIGUSR1)
        return super().save()


def test_a_stop_signal_during_a_periodic_checkpoint_does_not_save_it_again(tmp_path):
    run_dir = tmp_path / "run"
    cfg = compose_config("env=tiny", "algo=sac", "total_frames=1200", "checkpoint_every_epochs=1")
    before = signal.signal(signal.SIGUSR1, signal.SIG_DFL)
    try:
        trainer = SignalsDuringItsFirstSave(cfg, run_dir)
        try:
            with pytest.raises(Preempted) as stopped:
                trainer.run()
        finally:
            trainer.close()
    finally:
        signal.signal(signal.SIGUSR1, before)
    assert stopped.value.frames == 400 and trainer.saves == [400]  # one save, not two
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["frames"] == 400


def test_stop_signals_restore_the_previous_handlers_and_leave_ignored_signals_alone():
    recorder = []
    before = {s: signal.getsignal(s) for s in (signal.SIGUSR1, signal.SIGUSR2)}
    signal.signal(signal.SIGUSR1, lambda s, f: recorder.append(s))
    signal.signal(signal.SIGUSR2, signal.SIG_IGN)
    try:
        with StopSignals() as stop:
            os.kill(os.getpid(), signal.SIGUSR1)
            os.kill(os.getpid(), signal.SIGUSR2)  # ignored before: stays ignored
            assert stop.received == signal.SIGUSR1
            assert recorder == []  # recorded, not handed on yet
            stop.forward()
            assert recorder == [signal.SIGUSR1]
        assert signal.getsignal(signal.SIGUSR2) is signal.SIG_IGN
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


def test_resume_auto_starts_a_new_run_then_extends_it(tmp_path):
    run_dir = tmp_path / "run"
    _run(compose_config("env=tiny", "algo=sac", "resume=auto"), run_dir)
    assert not (run_dir / "config.resume1.yaml").exists()
    _run(compose_config("env=tiny", "algo=sac", "resume=auto", "total_frames=1200"), run_dir)
    assert [int(r["frames"]) for r in _rows(run_dir)] == [400, 800, 1200]
    assert (run_dir / "config.resume1.yaml").is_file()


def test_resume_auto_refuses_a_checkpoint_of_another_configuration(tmp_path):
    run_dir = tmp_path / "run"
    _run(compose_config("env=tiny", "algo=sac", "resume=auto"), run_dir)
    with pytest.raises(ConfigError, match=r"algo\.tau: run=0\.005, now=0\.01 cannot change"):
        make_trainer(
            compose_config("env=tiny", "algo=sac", "resume=auto", "algo.tau=0.01"), run_dir
        )
    with pytest.raises(ConfigError, match="another configuration"):
        make_trainer(compose_config("env=tiny", "algo=wcsac", "resume=auto"), run_dir)


def test_resume_auto_without_a_checkpoint_starts_over_and_keeps_foreign_files(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    # what a session killed before its first checkpoint leaves
    (run_dir / "config.yaml").write_text("seed: 0\n")
    (run_dir / "progress.csv").write_text("epoch,frames\n1,400\n2,800\n")
    _run(compose_config("env=tiny", "algo=sac", "resume=auto"), run_dir)
    assert [int(r["frames"]) for r in _rows(run_dir)] == [400, 800]  # once each, new

    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match=r"holds files that are not a run's \(notes\.txt\)"):
        make_trainer(compose_config("env=tiny", "algo=sac", "resume=auto"), other)
    assert (other / "notes.txt").read_text() == "mine"


class CtrlCInsideTheCritics(OffPolicyTrainer):
    """A real SAC trainer whose user presses Ctrl-C (a real SIGINT) inside the vmapped
    Q-critics of its fifth update."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.pressed_at = None

        def press(module, args):
            if self.updates == 4 and self.pressed_at is None:
                self.pressed_at = self.updates
                os.kill(os.getpid(), signal.SIGINT)

        self.loss.qvalue_network.register_forward_pre_hook(press)


def test_ctrl_c_inside_an_update_checkpoints_after_that_update(tmp_path):
    """Ctrl-C inside TorchRL's vmapped critics (where a KeyboardInterrupt surfaces as a
    RuntimeError from tensordict: no checkpoint, no resume command) lands after the
    update: the checkpoint holds whole updates."""
    run_dir = tmp_path / "run"
    cfg = compose_config("env=tiny", "algo=sac", "total_frames=1200")
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # (a test worker ignores it)
    try:
        trainer = CtrlCInsideTheCritics(cfg, run_dir)
        try:
            with pytest.raises(KeyboardInterrupt):
                trainer.run()
        finally:
            trainer.close()
    finally:
        signal.signal(signal.SIGINT, before)
    assert trainer.pressed_at == 4
    checkpoint = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    assert checkpoint["updates"] == 5  # the fifth update whole, then the checkpoint
    assert checkpoint["updates"] == trainer.updates
