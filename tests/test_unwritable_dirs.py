"""Tracebacks turned into lines: a run, a resume or a sweep into a directory that
cannot be written, and an evaluation of a checkpoint whose networks do not fit its config,
are each one ``error:`` line with exit code 1."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest
import torch
from _training_helpers import ROOT, compose_config

from wcsac_rl.evaluate import main as evaluate_main
from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint
from wcsac_rl.training.run_dir import RunLock, unwritable_reason


def _mount(args: list[str]) -> bool:
    return subprocess.run(["mount", *args], capture_output=True, check=False).returncode == 0


@pytest.fixture
def readonly(tmp_path):
    """A directory nobody can write: a read-only tmpfs (as root), else mode 0555."""
    path = tmp_path / "readonly"
    path.mkdir()
    if os.geteuid() == 0:
        if not _mount(["-t", "tmpfs", "-o", "size=64k,ro", "tmpfs", str(path)]):
            pytest.skip("cannot mount a read-only tmpfs here")
        yield path
        subprocess.run(["umount", "-l", str(path)], check=False)
    else:
        path.chmod(0o555)
        yield path
        path.chmod(0o755)


def test_unwritable_reason_names_the_directory_and_why(readonly, tmp_path):
    assert unwritable_reason(tmp_path / "new" / "run") is None  # made on demand
    reason = unwritable_reason(readonly / "run" / "deeper")
    assert reason is not None and reason.startswith(f"{readonly}: ")
    (tmp_path / "file").write_text("x")
    assert unwritable_reason(tmp_path / "file" / "run") == f"{tmp_path / 'file'} is not a directory"


def test_a_run_lock_in_a_read_only_directory_is_one_config_error(readonly):
    with pytest.raises(ConfigError, match=rf"cannot write to the run directory {readonly}/run: "):
        RunLock(readonly / "run")
    with pytest.raises(ConfigError, match="cannot write to the run directory"):
        make_trainer(compose_config("env=tiny", "algo=random"), readonly / "run")


@pytest.mark.parametrize("where", ["hydra.run.dir", "cwd"])
def test_train_py_into_a_read_only_directory_is_one_line(readonly, tmp_path, where):
    args = ["env=tiny", "algo=random", "total_frames=400"]
    if where == "hydra.run.dir":
        args.append(f"hydra.run.dir={readonly / 'run'}")
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *args],
        cwd=readonly if where == "cwd" else tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: cannot write the run's directory (")
    assert str(readonly) in lines[0]


def test_evaluating_a_checkpoint_whose_networks_do_not_fit_its_config_is_one_line(tmp_path, capsys):
    run = tmp_path / "run"
    trainer = make_trainer(compose_config("env=tiny", "algo=sac", "total_frames=400"), run)
    try:
        trainer.run()
    finally:
        trainer.close()
    path = trainer.checkpoint_path
    state = load_checkpoint(path)
    state["config"]["algo"]["network"]["width"] = 64  # the tensors are 32 wide
    torch.save(state, path)
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert evaluate_main([str(run), "--episodes", "1", "--no-progress"]) == 1
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error:")]
    assert errors == [
        f"error: checkpoint {path}: its networks do not fit its config: "
        "actor_network_params.module.0.module.0.0.weight is [32, 6] in the checkpoint, "
        "[64, 6] as configured"
    ]
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before
    shutil.rmtree(run)
