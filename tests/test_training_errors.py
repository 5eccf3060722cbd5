"""Errors a user (or a full disk) causes are one line naming the problem and the fix, and
a failed save never loses the previous checkpoint nor leaves its temporary file."""

from __future__ import annotations

import errno
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _training_helpers import ROOT, compose_config

from wcsac_rl.training import ConfigError, TrainingError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, save_checkpoint
from wcsac_rl.training.restore import load_run


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("seed=-1", "seed must be an integer >= 0, got -1"),
        ("seed=1.5", "seed must be an integer >= 0, got 1.5"),
        ("device=cuda", "device=cuda"),
        ("device=tpu", "device must be cpu, cuda[:N] or mps"),
    ],
)
def test_bad_seed_and_device_are_one_config_error_before_any_work(tmp_path, override, message):
    if override == "device=cuda" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ConfigError, match=__import__("re").escape(message)):
        make_trainer(compose_config("env=tiny", override), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_cuda_without_cuda_says_how_to_fix_it(tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config("env=tiny", "device=cuda:0"), tmp_path / "run")
    assert "no CUDA device" in str(err.value) and "device=cpu" in str(err.value)


@pytest.mark.parametrize(
    ("logger", "package"), [("tensorboard", "tensorboard"), ("wandb", "wandb")]
)
def test_a_logger_whose_package_is_missing_names_the_extra(tmp_path, monkeypatch, logger, package):
    import importlib.util

    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util,
        "find_spec",
        lambda name, *a: None if name == package else real_find_spec(name, *a),
    )
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config("env=tiny", f"logger={logger}"), tmp_path / "run")
    message = str(err.value)
    assert f"logger={logger} needs the {package} package" in message
    assert f'pip install -e ".[{package}]"' in message and "logger=csv" in message


def _finished_run(tmp_path, *overrides, name="run"):
    trainer = make_trainer(compose_config("env=tiny", *overrides), tmp_path / name)
    try:
        trainer.run()
    finally:
        trainer.close()
    return trainer


@pytest.mark.parametrize("missing", ["config", "learner", "frames"])
def test_a_checkpoint_without_its_entries_is_one_clear_line(tmp_path, missing):
    trainer = _finished_run(tmp_path, "algo=random")
    path = trainer.checkpoint_path
    state = load_checkpoint(path)
    del state[missing]
    torch.save(state, path)
    for call in (
        lambda: load_run(path.parent.parent),
        lambda: make_trainer(
            compose_config("env=tiny", "algo=random", f"resume={path.parent.parent}"),
            tmp_path / "x",
        ),
    ):
        with pytest.raises(
            ConfigError, match=rf"not a wcsac_rl training checkpoint \(no '{missing}'"
        ):
            call()
    torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(ConfigError, match="not a wcsac_rl training checkpoint"):
        load_run(path.parent.parent)
    torch.save(torch.zeros(3), path)
    with pytest.raises(ConfigError, match="not a wcsac_rl training checkpoint"):
        load_run(path.parent.parent)


def _disk_full_torch_save(kind):
    """A torch.save that writes part of the file, then fails as a full disk does."""

    def save(obj, f, *args, **kwargs):
        handle = open(f, "wb") if isinstance(f, (str, Path)) else f
        handle.write(b"x" * 1000)
        handle.flush()
        if isinstance(f, (str, Path)):
            handle.close()
        if kind == "torch":  # what torch.save raises on a full tmpfs (measured)
            raise RuntimeError(
                "[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598"
            )
        raise OSError(errno.ENOSPC, "No space left on device")

    return save


@pytest.mark.parametrize("kind", ["torch", "oserror"])
def test_a_failed_save_removes_its_temporary_file_and_keeps_the_previous_checkpoint(
    tmp_path, monkeypatch, kind
):
    path = tmp_path / "checkpoints" / "last.pt"
    save_checkpoint(path, {"frames": 400})
    monkeypatch.setattr(torch, "save", _disk_full_torch_save(kind))
    with pytest.raises(TrainingError) as err:
        save_checkpoint(path, {"frames": 800})
    message = str(err.value)
    assert "\n" not in message
    assert f"cannot write checkpoint {path}" in message
    assert "no space left on its disk" in message and "previous checkpoint is kept" in message
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]  # no last.pt.tmp
    monkeypatch.undo()
    assert load_checkpoint(path, required=())["frames"] == 400


def test_a_full_disk_at_a_checkpoint_stops_the_run_with_one_line(tmp_path, monkeypatch):
    trainer = make_trainer(
        compose_config("env=tiny", "total_frames=1200", "checkpoint_every_epochs=1"),
        tmp_path / "run",
    )
    real_save = torch.save
    saves = {"n": 0}

    def save(obj, f, *args, **kwargs):
        saves["n"] += 1
        if saves["n"] == 2:  # the epoch-2 checkpoint
            return _disk_full_torch_save("torch")(obj, f)
        return real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", save)
    with pytest.raises(TrainingError, match="no space left on its disk"):
        trainer.run()
    trainer.close()
    monkeypatch.undo()
    assert load_checkpoint(trainer.checkpoint_path)["frames"] == 400
    assert not list(trainer.checkpoint_path.parent.glob("*.tmp"))


def _small_tmpfs(path: Path, size: str) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    result = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
        capture_output=True,
        check=False,
    )
    return result.returncode == 0


def test_a_real_full_disk_keeps_the_previous_checkpoint(tmp_path):
    """The same on a 600 kB tmpfs (needs permission to mount; skipped otherwise)."""
    disk = tmp_path / "disk"
    if not _small_tmpfs(disk, "600k"):
        pytest.skip("cannot mount a tmpfs here")
    try:
        path = disk / "checkpoints" / "last.pt"
        save_checkpoint(path, {"frames": 400, "x": torch.zeros(1000)})
        with pytest.raises(TrainingError, match="no space left on its disk"):
            save_checkpoint(path, {"frames": 800, "x": torch.zeros(1_000_000)})
        assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]
        assert load_checkpoint(path, required=())["frames"] == 400
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)  # lazy: even if a file is open


def _train_py(*args, cwd):
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("seed=-1", "error: seed must be an integer >= 0, got -1"),
        ("logger.backend=nope", "error: logger.backend must be csv"),
    ],
)
def test_train_py_prints_one_line(tmp_path, override, message):
    result = _train_py("env=tiny", override, f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path)
    assert result.returncode == 1
    assert message in result.stderr
    assert "Traceback" not in result.stderr


def test_a_full_disk_while_logging_stops_the_run_with_one_line(tmp_path, monkeypatch):
    from wcsac_rl.training import progress

    trainer = make_trainer(compose_config("env=tiny", "algo=random"), tmp_path / "run")

    def full_disk(self, row):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(progress.ProgressWriter, "write", full_disk)
    with pytest.raises(TrainingError, match=r"cannot write to .*run: no space left on its disk"):
        trainer.run()
    trainer.close()
