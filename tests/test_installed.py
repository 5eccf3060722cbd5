"""The kit installed (not editable) and used from outside the repository.

A fresh virtualenv gets a regular ``pip install`` of a copy of the checkout (the
dependencies, pip and setuptools are this interpreter's, shared through a path file:
no downloads); then,
from an empty directory with a user's env module on ``PYTHONPATH``:
``wcsac-train env=gymnasium env.id=my_module:make ...`` trains and prints its run
directory, ``progress.csv`` holds the cost, ``train.log`` what the console showed;
``wcsac-evaluate <run> --episodes 5`` writes ``evaluation.json``; and
``wcsac-train +risk_levl=0.1`` is refused in one line naming ``risk_level`` with
nothing left behind. The configs come from the copy shipped inside the package.
"""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
from _training_helpers import ROOT

pytestmark = pytest.mark.slow

SOURCES = ("pyproject.toml", "setup.py", "README.md", "LICENSE", "wcsac_rl", "conf")
"""What an install is built from (a copy: the build writes build/ and *.egg-info)."""

SMALL = [
    "algo.collector.num_envs=2",
    "algo.collector.frames_per_batch=100",
    "algo.collector.init_random_frames=100",
    "algo.batch_size=32",
    "algo.network.width=16",
    "epoch_frames=200",
    "total_frames=450",  # not whole batches: the rounding is said once
    "eval_episodes=2",
]


def _run(cmd: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    """Run ``cmd``; its output decoded as written (``text=True`` would turn a progress
    bar's carriage returns into newlines)."""
    result = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, timeout=900)
    result.stdout, result.stderr = result.stdout.decode(), result.stderr.decode()
    return result


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    """A virtualenv with wcsac_rl installed from a copy of the checkout, not editable."""
    base = tmp_path_factory.mktemp("installed")
    source = base / "source"
    source.mkdir()
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(path, source / name)
    venv = base / "venv"
    # no pip or setuptools of its own: this interpreter's (setuptools >= 77) build it
    subprocess.run(
        [sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=600
    )
    python = venv / "bin" / "python"
    site = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    # this interpreter's packages (torch, torchrl, hydra, ...) as the dependencies, after
    # the venv's own (a plain path: its .pth files, the checkout's editable install among
    # them, are not run)
    (Path(site) / "dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    subprocess.run(
        [
            str(python),
            "-m",
            "pip",
            "install",
            "--quiet",
            "--no-deps",
            "--no-build-isolation",
            str(source),
        ],
        check=True,
        timeout=900,
        cwd=base,
    )
    return venv


def _user_env(base: Path) -> dict[str, str]:
    """An empty working directory's environment with the user's module on PYTHONPATH."""
    module_dir = base / "my_envs"
    module_dir.mkdir()
    shutil.copy2(ROOT / "examples" / "hazard_point.py", module_dir / "my_module.py")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(module_dir)
    return env


def test_installed_wcsac_train_trains_your_env_from_any_directory(venv, tmp_path):
    env = _user_env(tmp_path)
    work = tmp_path / "work"
    work.mkdir()
    bin_dir = venv / "bin"

    where = _run(
        [str(bin_dir / "python"), "-c", "import wcsac_rl.config_dir as c; print(c.CONF_DIR)"],
        work,
        env,
    )
    conf = Path(where.stdout.strip())
    assert conf.is_relative_to(venv) and (conf / "env" / "gymnasium.yaml").is_file(), where

    train = _run(
        [
            str(bin_dir / "wcsac-train"),
            "env=gymnasium",
            "env.id=my_module:make",
            "algo=wcsac",
            "risk_level=0.1",
            "cost_limit=5",
            *SMALL,
        ],
        work,
        env,
    )
    assert train.returncode == 0, train.stderr[-3000:]
    assert "Traceback" not in train.stderr
    run_dir = Path(train.stdout.split("run directory: ", 1)[1].splitlines()[0])
    assert run_dir.is_relative_to(work) and run_dir.name.endswith("_wcsac_0.1_gymnasium_seed0")

    with (run_dir / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["frames"]) for r in rows] == [200, 400, 500]  # the last: the rounded-up batch
    costs = [float(r["train/episode_cost"]) for r in rows]
    assert all(c >= 0 for c in costs) and "train/cumulative_cost" in rows[0]

    # train.log: every line the console showed (the progress bar's last state per line)
    log = (run_dir / "train.log").read_text()
    for line in (train.stdout + train.stderr).split("\n"):
        shown = line.rsplit("\r", 1)[-1].strip()
        if shown:
            assert shown in log, shown
    assert "total_frames=450 is rounded up to 500" in log
    assert log.count("rounded up") == 1

    evaluate = _run(
        [str(bin_dir / "wcsac-evaluate"), str(run_dir), "--episodes", "5", "--trust-env-code"],
        work,
        env,
    )
    assert evaluate.returncode == 0, evaluate.stderr[-3000:]
    evaluation = json.loads((run_dir / "evaluation.json").read_text())
    assert evaluation["episodes"] == 5 and evaluation["env"] == "gymnasium"


def test_installed_wcsac_train_refuses_a_misspelt_key_in_one_line(venv, tmp_path):
    work = tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    result = _run([str(venv / "bin" / "wcsac-train"), "+risk_levl=0.1"], work, env)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode != 0
    assert 1 <= len(lines) <= 3 and "risk_level" in lines[0], result.stderr
    assert list(work.iterdir()) == []
