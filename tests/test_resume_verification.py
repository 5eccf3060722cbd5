"""A resume keeps what exists: it never goes back behind the run's latest
progress, and it continues only a checkpoint that belongs to the run it writes into.

Every refusal is one line, before anything is written: every file of the run stays
byte-identical (its ``.lock`` names the process that last held it, and is left out).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _training_helpers import ROOT, compose_config, tree_digests

from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, resume_config
from wcsac_rl.training.restore import load_run


def _train(cfg, run_dir: Path) -> None:
    trainer = make_trainer(cfg, run_dir)
    try:
        trainer.run()
    finally:
        trainer.close()


snapshot = tree_digests


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    """Finished tiny runs: WCSAC α = 0.1 (800 frames, frames-400.pt kept) and SAC-Lag."""
    root = tmp_path_factory.mktemp("runs")
    _train(
        compose_config("env=tiny", "risk_level=0.1", "keep_checkpoints_at=[1]"),
        root / "wcsac",
    )
    _train(compose_config("env=tiny", "algo=sac_lag", "total_frames=400"), root / "sac_lag")
    return {"wcsac": root / "wcsac", "sac_lag": root / "sac_lag"}


@pytest.fixture
def wcsac(runs, tmp_path) -> Path:
    run = tmp_path / "wcsac"
    shutil.copytree(runs["wcsac"], run)
    return run


def _resume(target: str | Path, *overrides: str):
    """The trainer ``train.py resume=<target>`` builds (the run's own config)."""
    given = [f"resume={target}", *overrides]
    cfg = resume_config(compose_config(*given, small=False), given)
    return make_trainer(cfg, Path("unused"))


def test_resuming_a_kept_checkpoint_behind_the_run_is_refused_naming_both_frame_counts(wcsac):
    kept = wcsac / "checkpoints" / "frames-400.pt"
    before = snapshot(wcsac)
    with pytest.raises(ConfigError) as err:
        _resume(kept, "total_frames=1200")
    message = str(err.value)
    assert "\n" not in message
    assert f"checkpoint {kept} is at 400 frames" in message
    assert "has trained to 800 frames (checkpoints/last.pt)" in message
    assert f"resume={wcsac}" in message and "not supported" in message
    assert snapshot(wcsac) == before


def test_without_last_pt_the_progress_record_says_how_far_the_run_went(wcsac):
    (wcsac / "checkpoints" / "last.pt").unlink()
    before = snapshot(wcsac)
    with pytest.raises(ConfigError, match=r"at 400 frames .* trained to 800 frames \(progress"):
        _resume(wcsac / "checkpoints" / "frames-400.pt")
    assert snapshot(wcsac) == before


def test_a_kept_checkpoint_at_the_runs_latest_frames_still_resumes(tmp_path):
    run = tmp_path / "run"
    _train(compose_config("env=tiny", "algo=random", "keep_checkpoints_at=[2]"), run)
    trainer = _resume(run / "checkpoints" / "frames-800.pt", "total_frames=1200")
    try:
        assert trainer.tracker.frames == 800
    finally:
        trainer.close()


def test_a_checkpoint_copied_under_another_runs_directory_is_refused(runs, tmp_path):
    """A WCSAC α = 0.1 ``last.pt`` under a SAC-Lag run: resume=DIR takes the config from
    the checkpoint, so the run directory's own ``config.yaml`` is what tells them apart."""
    run = tmp_path / "sac_lag"
    shutil.copytree(runs["sac_lag"], run)
    shutil.copyfile(runs["wcsac"] / "checkpoints" / "last.pt", run / "checkpoints" / "last.pt")
    before = snapshot(run)
    for target in (run, run / "checkpoints" / "last.pt"):
        with pytest.raises(ConfigError) as err:
            _resume(target, "total_frames=1200")
        message = str(err.value)
        assert "\n" not in message and f"does not belong to the run {run}" in message
        assert "algo.name: checkpoint='wcsac', run='sac_lag'" in message
        assert "algo.risk_level: checkpoint=0.1, run=1.0" in message
        assert "(the run's config.yaml)" in message
    # resume=auto composes the sac_lag config: the checkpoint is refused against it
    with pytest.raises(ConfigError, match=r"another configuration \(algo\.name: checkpoint="):
        make_trainer(compose_config("env=tiny", "algo=sac_lag", "resume=auto"), run)
    assert snapshot(run) == before


def test_without_config_yaml_hydras_record_of_the_run_is_compared(runs, tmp_path):
    run = tmp_path / "sac_lag"
    shutil.copytree(runs["sac_lag"], run)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text((run / "config.yaml").read_text())
    (run / "config.yaml").unlink()
    shutil.copyfile(runs["wcsac"] / "checkpoints" / "last.pt", run / "checkpoints" / "last.pt")
    with pytest.raises(ConfigError, match=r"algo\.name: .*\(the run's \.hydra/config\.yaml\)"):
        _resume(run)


def _network_of_another_width(run: Path) -> None:
    """The checkpoint's config (and the run's record) say width 64; its tensors are 32."""
    path = run / "checkpoints" / "last.pt"
    state = load_checkpoint(path)
    assert state["config"]["algo"]["network"]["width"] == 32
    state["config"]["algo"]["network"]["width"] = 64
    torch.save(state, path)
    config = run / "config.yaml"
    config.write_text(config.read_text().replace("width: 32", "width: 64"))


def test_networks_of_other_shapes_than_the_config_are_one_line_on_resume_and_evaluate(
    runs, tmp_path
):
    run = tmp_path / "run"
    shutil.copytree(runs["wcsac"], run)
    _network_of_another_width(run)
    before = snapshot(run)
    for call in (lambda: _resume(run, "total_frames=1200"), lambda: load_run(run)):
        with pytest.raises(ConfigError) as err:
            call()
        message = str(err.value)
        assert "\n" not in message
        assert message.startswith(f"checkpoint {run / 'checkpoints' / 'last.pt'}: its networks")
        assert "in the checkpoint" in message and "as configured" in message
    assert snapshot(run) == before


def test_train_py_refuses_a_kept_checkpoint_behind_the_run_in_one_line(wcsac, tmp_path):
    before = snapshot(wcsac)
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "train.py"),
            f"resume={wcsac / 'checkpoints' / 'frames-400.pt'}",
            f"hydra.run.dir={tmp_path / 'session'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "is at 400 frames" in errors[0] and "800 frames" in errors[0]
    assert snapshot(wcsac) == before
    assert not (tmp_path / "session").exists()
