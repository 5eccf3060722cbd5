"""A run directory holds one run: records tied to the checkpoint, a lock, the run's own
config on resume."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from _training_helpers import ROOT, TINY_CLI, compose_config

from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, resume_config
from wcsac_rl.training.provenance import read_provenance
from wcsac_rl.training.run_dir import RunLock, cut_records_to


def _rows(run_dir: Path) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _epochs(run_dir: Path) -> list[int]:
    return [int(r["epoch"]) for r in _rows(run_dir)]


def _train(cfg, run_dir):
    trainer = make_trainer(cfg, run_dir)
    try:
        trainer.run()
    finally:
        trainer.close()
    return trainer


# Tiny epochs of 200 frames (one batch each) with updates: about a second each here.
CLI = [*TINY_CLI, "epoch_frames=200"]


def _train_py(*args: str, cwd: Path, **kwargs) -> subprocess.Popen | subprocess.CompletedProcess:
    cmd = [sys.executable, str(ROOT / "train.py"), *args]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    if kwargs.pop("background", False):
        return subprocess.Popen(
            cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=600, env=env)


def _wait_for(predicate, timeout=300.0):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def _data_rows(path: Path) -> int:
    if not path.is_file():
        return 0
    return max(0, len(path.read_text().splitlines()) - 1)


# ------------------------------------------------------------------ item 1
def test_kill_9_between_checkpoints_then_resume_logs_each_epoch_once(tmp_path):
    run_dir = tmp_path / "run"
    proc = _train_py(
        *CLI,
        "total_frames=4000",
        "checkpoint_every_epochs=3",
        f"hydra.run.dir={run_dir}",
        cwd=tmp_path,
        background=True,
    )
    try:
        # epoch 4 logged, the checkpoint still the one of epoch 3
        assert _wait_for(lambda: _data_rows(run_dir / "progress.csv") >= 4)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    logged = _epochs(run_dir)
    checkpoint_epoch = load_checkpoint(run_dir / "checkpoints" / "last.pt")["epoch"]
    assert checkpoint_epoch == 3 and logged[:4] == [1, 2, 3, 4] and len(logged) < 6
    assert (run_dir / ".lock").exists()  # left by the killed process: a stale lock
    result = _train_py(f"resume={run_dir}", f"hydra.run.dir={tmp_path / 'r2'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "dropped" in result.stdout and "logged after the checkpoint (epoch 3" in result.stdout
    assert _epochs(run_dir) == list(range(1, 21))
    assert [int(r["frames"]) for r in _rows(run_dir)] == list(range(200, 4001, 200))
    # the CSV logger's files were cut back too: each step once
    scalars = next((run_dir / "logs").rglob("scalars"))
    steps = [int(line.split(",")[0]) for line in (scalars / "train" / "episodes.csv").open()]
    assert steps == list(range(200, 4001, 200))


def test_cut_records_to_drops_later_rows_and_a_torn_last_line(tmp_path):
    progress = tmp_path / "progress.csv"
    progress.write_text("epoch,frames,x\n1,200,0.5\n2,400,0.25\n3,600,0.1\n4,80")
    scalars = tmp_path / "logs" / "exp" / "scalars"
    scalars.mkdir(parents=True)
    (scalars / "x.csv").write_text("200,0.5\n400,0.25\n600,0.1\n80")
    assert cut_records_to(tmp_path, epoch=2, frames=400) == 2
    assert progress.read_text() == "epoch,frames,x\n1,200,0.5\n2,400,0.25\n"
    assert (scalars / "x.csv").read_text() == "200,0.5\n400,0.25\n"
    assert not list(tmp_path.rglob("*.tmp"))


@pytest.mark.parametrize("leftover", ["progress.csv", "logs", "notes.txt"])
def test_a_new_run_refuses_a_non_empty_directory(tmp_path, leftover):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / ".hydra").mkdir()  # Hydra's own files are expected
    (run_dir / "train.log").write_text("")
    target = run_dir / leftover
    if leftover == "logs":
        target.mkdir()
    else:
        target.write_text("epoch,frames\n1,400\n")
    # (a requeued sweep job lands here too: the message names resume=auto)
    match = rf"already holds a run \({leftover}\).*run the sweep with resume=auto"
    with pytest.raises(ConfigError, match=match):
        make_trainer(compose_config("env=tiny", "algo=random"), run_dir)
    assert target.exists() and not (run_dir / "config.yaml").exists()


def test_a_directory_with_only_hydra_files_is_a_new_run(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / "train.log").write_text("")
    _train(compose_config("env=tiny", "algo=random"), run_dir)
    assert _epochs(run_dir) == [1, 2]


# ------------------------------------------------------------------ item 2
def test_a_second_run_in_a_directory_in_use_fails_with_one_line(tmp_path):
    run_dir = tmp_path / "run"
    first = make_trainer(compose_config("env=tiny", "algo=random"), run_dir)
    try:
        pid = f"pid {os.getpid()}"
        for cfg in (
            compose_config("env=tiny", "algo=random"),
            compose_config("env=tiny", "algo=random", f"resume={run_dir}"),  # no checkpoint yet
        ):
            with pytest.raises(ConfigError, match=rf"is in use by another run \(host .*, {pid}\)"):
                make_trainer(cfg, run_dir)
        first.run()
    finally:
        first.close()
    assert _epochs(run_dir) == [1, 2]
    # released: the run can be continued
    _train(
        compose_config("env=tiny", "algo=random", "total_frames=1200", f"resume={run_dir}"), run_dir
    )
    assert _epochs(run_dir) == [1, 2, 3]


def test_two_train_py_processes_on_one_directory(tmp_path):
    run_dir = tmp_path / "run"
    args = [
        "algo=random",
        "env=tiny",
        "algo.collector.num_envs=2",
        "algo.collector.frames_per_batch=200",
        "epoch_frames=200",
        "progress_bar=false",
        "total_frames=30000",  # long enough to outlive the second process's start
        f"hydra.run.dir={run_dir}",
    ]
    first = _train_py(*args, cwd=tmp_path, background=True)
    try:
        assert _wait_for(lambda: (run_dir / "config.yaml").exists())
        second = _train_py(*args, cwd=tmp_path)
        _, err = first.communicate(timeout=600)
    finally:
        if first.poll() is None:
            first.kill()
    assert first.returncode == 0, err[-2000:]
    assert second.returncode == 1
    assert "is in use by another run (host " in second.stderr and "Traceback" not in second.stderr
    assert _epochs(run_dir) == list(range(1, 151))  # only the first run's rows


def test_a_lock_from_a_dead_process_is_stale(tmp_path):
    code = (
        f"import os, sys; sys.path.insert(0, {str(ROOT)!r})\n"
        "from wcsac_rl.training.run_dir import RunLock\n"
        f"RunLock({str(tmp_path)!r}); os._exit(0)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    assert "pid" in (tmp_path / ".lock").read_text()
    lock = RunLock(tmp_path)  # the dead process's lock is gone with it
    assert lock.held
    lock.release()


# ------------------------------------------------------------------ item 3
def test_resume_config_is_the_runs_own_with_only_the_explicit_overrides(tmp_path):
    run_dir = tmp_path / "run"
    original = compose_config("env=tiny", "seed=5", "algo.batch_size=32", "epoch_frames=200")
    _train(original, run_dir)
    given = ["env=tiny", "algo.network.width=32", "total_frames=1200", f"resume={run_dir}"]
    composed = compose_config(*given, small=False)  # defaults: 3 M frames, batch 256, seed 0
    cfg = resume_config(composed, given)
    assert cfg.seed == 5 and cfg.algo.batch_size == 32 and cfg.epoch_frames == 200
    assert cfg.total_frames == 1200 and cfg.resume == str(run_dir)
    assert cfg.algo.collector.num_envs == 2  # not the default 4
    with pytest.raises(ConfigError, match="cannot be given on resume"):
        resume_config(composed, ["experiment=quickstart"])


def test_train_py_resume_continues_the_run_as_configured_and_keeps_its_config(tmp_path):
    run_dir = tmp_path / "run"
    first = _train_py(*CLI, "seed=7", "total_frames=400", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-2000:]
    config_before = (run_dir / "config.yaml").read_text()
    resumed = _train_py(
        f"resume={run_dir}", "total_frames=800", f"hydra.run.dir={tmp_path / 'r2'}", cwd=tmp_path
    )
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert [int(r["frames"]) for r in _rows(run_dir)] == [200, 400, 600, 800]  # 200-frame epochs
    assert (run_dir / "config.yaml").read_text() == config_before  # never rewritten
    session = yaml.safe_load((run_dir / "config.resume1.yaml").read_text())
    assert session["total_frames"] == 800 and session["seed"] == 7
    assert session["algo"]["batch_size"] == 32 and session["resume"] == str(run_dir)
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["config"]["total_frames"] == 800
    # a setting that is the run's own is refused with one line
    refused = _train_py(
        f"resume={run_dir}",
        "epoch_frames=100",
        "total_frames=1000",
        f"hydra.run.dir={tmp_path / 'r3'}",
        cwd=tmp_path,
    )
    assert refused.returncode == 1 and "Traceback" not in refused.stderr
    assert "error: resume continues" in refused.stderr
    assert "epoch_frames: run=200, now=100 cannot change on resume" in refused.stderr
    assert not (run_dir / "config.resume2.yaml").exists()
    # each session recorded the code it ran and the overrides that compose its config
    first_session, second_session = read_provenance(run_dir)
    assert first_session["overrides"] == [*CLI, "seed=7", "total_frames=400"]
    assert first_session["resumed_from_frames"] is None
    assert second_session["overrides"] == [f"resume={run_dir}", "total_frames=800"]
    assert second_session["resumed_from_frames"] == 400
    head = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=False
    )
    if head.returncode == 0:  # a git checkout (CI's clean clone is one)
        assert first_session["code"]["commit"] == head.stdout.strip()
        assert isinstance(first_session["code"]["dirty"], bool)
    assert not (run_dir / "provenance.resume2.json").exists()  # the refused session wrote none


def test_resume_continues_the_same_wandb_run(tmp_path, monkeypatch):
    import importlib.util

    import torchrl.record.loggers.wandb as wandb_module

    made = []

    class FakeWandbLogger:
        def __init__(self, exp_name, id=None, **kwargs):
            self.exp_name, self.id = exp_name, id or f"run-{len(made)}"
            made.append(self)

        def log_scalar(self, *args, **kwargs):
            pass

        def state_dict(self):
            return {"exp_name": self.exp_name, "local": {"id": self.id}}

        def load_state_dict(self, state):
            pass

    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda n, *a: object() if n == "wandb" else real_find_spec(n, *a),
    )
    monkeypatch.setattr(wandb_module, "WandbLogger", FakeWandbLogger)
    run_dir = tmp_path / "run"
    _train(compose_config("env=tiny", "algo=random", "logger=wandb"), run_dir)
    _train(
        compose_config(
            "env=tiny", "algo=random", "logger=wandb", "total_frames=1200", f"resume={run_dir}"
        ),
        run_dir,
    )
    assert [m.id for m in made] == ["run-0", "run-0"]


def test_an_epoch_without_a_finished_episode_says_so_on_the_progress_bar(tmp_path, capsys):
    # 1000-step StaticEnv episodes, 400 frames: no training episode ends
    run_dir = tmp_path / "run"
    _train(
        compose_config(
            "algo=random",
            "env=static",
            "total_frames=400",
            "epoch_frames=400",
            "eval_episodes=0",
            "progress_bar=true",
        ),
        run_dir,
    )
    assert "no finished episode" in capsys.readouterr().err
    row = _rows(run_dir)[0]
    assert row["train/episodes"] == "0" and row["train/episode_return"] == "nan"


def test_an_epoch_interrupted_by_ctrl_c_is_completed_by_the_resumed_session(tmp_path):
    run_dir = tmp_path / "run"
    options = (
        "env=tiny",
        "algo=random",
        "algo.collector.num_envs=2",
        "algo.collector.frames_per_batch=200",  # 100 steps per env: one episode each
        "total_frames=1600",
    )
    trainer = make_trainer(compose_config(*options), run_dir)
    real_learn = trainer.learn

    def interrupting_learn(batch):
        out = real_learn(batch)
        if trainer.tracker.frames == 600:  # half-way through epoch 2 (400-800)
            raise KeyboardInterrupt
        return out

    trainer.learn = interrupting_learn
    with pytest.raises(KeyboardInterrupt):
        trainer.run()
    trainer.close()
    progress = load_checkpoint(run_dir / "checkpoints" / "last.pt")["epoch_progress"]
    assert progress["start_frames"] == 400 and len(progress["returns"]) == 2
    _train(compose_config(*options, f"resume={run_dir}"), run_dir)
    rows = _rows(run_dir)
    assert [int(r["frames"]) for r in rows] == [400, 800, 1200, 1600]
    # 100-step episodes, 2 envs: 4 finish in every epoch, the interrupted one included
    assert [int(r["train/episodes"]) for r in rows] == [4, 4, 4, 4]
