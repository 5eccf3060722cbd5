"""``+row=cal`` is a row like the others: a sweep of it through train.py (the experiments'
local launcher), then ``evaluate`` and ``report`` name it "CAL" beside SAC-Lag; and it is
a row of the evidence sweep."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from _training_helpers import ROOT, TINY_CLI

from wcsac_rl.evaluation.sweeps import sweep_jobs


def _sweep(tmp_path):
    sweep = tmp_path / "sweep"
    command = [
        sys.executable,
        str(ROOT / "train.py"),
        "-m",
        "hydra/launcher=local",
        "hydra.launcher.n_jobs=1",
        *TINY_CLI,
        "resume=auto",
        "+row=cal,sac_lag",
        "seed=0",
        "total_frames=400",
        "epoch_frames=400",
        f"hydra.sweep.dir={sweep}",
        "hydra.sweep.subdir=${run_name}",
    ]
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": path}
    result = subprocess.run(
        command, cwd=tmp_path, capture_output=True, text=True, timeout=600, env=env
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return sweep


@pytest.mark.slow
def test_a_cal_row_trains_in_a_sweep_and_is_evaluated_and_reported(tmp_path):
    from wcsac_rl.evaluate import main as evaluate
    from wcsac_rl.report import main as report

    sweep = _sweep(tmp_path)
    jobs = sorted(p.name for p in sweep.iterdir() if not p.name.startswith("."))
    assert jobs == ["cal_tiny_seed0", "multirun.yaml", "sac_lag_tiny_seed0"]
    assert [job.status for job in sweep_jobs(sweep)] == ["finished", "finished"]
    config = (sweep / "cal_tiny_seed0" / "config.yaml").read_text()
    assert "name: cal" in config and "ensemble_reading: ucb" in config
    assert evaluate([str(sweep), "--episodes", "2", "--no-progress"]) == 0
    assert report([str(sweep), "--no-trajectories"]) == 0
    table = (sweep / "report" / "table1.md").read_text()
    assert "| CAL |" in table and "| SAC-Lag |" in table
    # the report's order: CAL after SAC-Lag's rows
    assert table.index("| SAC-Lag |") < table.index("| CAL |")
    assert "not finished" not in table


def test_cal_is_a_row_of_the_evidence_sweep():
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["experiment=evidence_static"], return_hydra_config=True)
        assert "cal" in cfg.hydra.sweeper.params["+row"].split(",")
        job = compose("config", overrides=["experiment=evidence_static", "+row=cal", "seed=0"])
    assert job.algo.name == "cal" and job.algo.label == "cal"
    assert job.run_name == "cal_static_seed0" and job.total_frames == 200_000
