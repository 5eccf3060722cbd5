"""A new algorithm is one registry entry, one config and one loss (docs/own_algorithm.md).

The three blocks of docs/own_algorithm.md, section 3, are added to a copy of the kit
(``wcsac_rl/``, ``conf/``, ``train.py``), which trains the new algorithm through
``train.py`` on the tiny env; the copy differs from the kit in those three places only.
And every entry of the kit's registry names a trainer and a loss that import, and the
algorithms of ``conf/algo/`` are the registry's.
"""

from __future__ import annotations

import csv
import filecmp
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import yaml
from _training_helpers import ROOT

from wcsac_rl.recipes import algorithm_files
from wcsac_rl.training.registry import ALGORITHMS, resolve
from wcsac_rl.training.trainer import Trainer

DOC = ROOT / "docs" / "own_algorithm.md"
MARKER = "            # a new algorithm: one more Algorithm(...) here (docs/own_algorithm.md)\n"


def _blocks() -> dict[str, str]:
    """The fenced blocks of the doc's section 3 whose first line names their file."""
    section = DOC.read_text().split("## 3. A new algorithm inside the kit's trainer", 1)[1]
    blocks = {}
    for body in re.findall(r"```(?:yaml|python)\n(.*?)```", section, flags=re.S):
        first, rest = body.split("\n", 1)
        blocks[first.lstrip("# ").strip()] = rest
    return blocks


def _copy_kit(dest: Path) -> None:
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(ROOT / "wcsac_rl", dest / "wcsac_rl", ignore=ignore)
    shutil.copytree(ROOT / "conf", dest / "conf", ignore=ignore)
    shutil.copy2(ROOT / "train.py", dest / "train.py")


def _differences(left: Path, right: Path, prefix: str = "") -> list[str]:
    """The files that differ between two trees, or are in one only (relative paths)."""
    cmp = filecmp.dircmp(left, right, ignore=["__pycache__"])
    found = [f"{prefix}{name}" for name in (*cmp.left_only, *cmp.right_only)]
    _, mismatch, errors = filecmp.cmpfiles(left, right, cmp.common_files, shallow=False)
    found += [f"{prefix}{name}" for name in (*mismatch, *errors)]
    for sub in cmp.common_dirs:
        found += _differences(left / sub, right / sub, f"{prefix}{sub}/")
    return sorted(found)


def test_the_doc_names_three_additions():
    assert set(_blocks()) == {
        "conf/algo/penalty_sac.yaml",
        "wcsac_rl/training/registry.py, in ALGORITHMS",
        "penalty_sac.py",
    }


def test_a_new_algorithm_trains_with_only_an_entry_a_config_and_a_loss(tmp_path):
    kit = tmp_path / "kit"
    _copy_kit(kit)
    blocks = _blocks()
    registry = kit / "wcsac_rl" / "training" / "registry.py"
    text = registry.read_text()
    assert text.count(MARKER) == 1
    registry.write_text(
        text.replace(MARKER, blocks.pop("wcsac_rl/training/registry.py, in ALGORITHMS") + MARKER)
    )
    for name, body in blocks.items():
        (kit / name).write_text(body)
    assert _differences(ROOT / "wcsac_rl", kit / "wcsac_rl") == ["training/registry.py"]
    assert _differences(ROOT / "conf", kit / "conf") == ["algo/penalty_sac.yaml"]

    run_dir = tmp_path / "run"
    budget = [
        "total_frames=800",
        "epoch_frames=400",
        "eval_episodes=1",
        "algo.collector.init_random_frames=400",
        "algo.batch_size=64",
        "progress_bar=false",
        "logger=none",
    ]
    env = {**os.environ, "PYTHONPATH": str(kit), "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [sys.executable, "train.py", "algo=penalty_sac", "env=tiny", "algo.penalty=2.0",
         *budget, f"hydra.run.dir={run_dir}"],
        cwd=kit, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert (config["algo"]["name"], config["algo"]["penalty"]) == ("penalty_sac", 2.0)
    assert config["algo"]["recipe"] == "conf/algo/penalty_sac.yaml"
    with (run_dir / "progress.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(float(row["frames"])) for row in rows] == [400, 800]
    assert int(float(rows[-1]["updates"])) > 0  # the penalised loss was stepped ...
    assert math.isfinite(float(rows[-1]["loss/loss_actor"]))  # ... to finite values
    assert (run_dir / "checkpoints").is_dir()


def test_a_config_of_an_algorithm_without_its_entry_is_one_line_and_leaves_no_run(tmp_path):
    kit = tmp_path / "kit"
    _copy_kit(kit)
    (kit / "conf" / "algo" / "penalty_sac.yaml").write_text(_blocks()["conf/algo/penalty_sac.yaml"])
    run_dir = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "train.py", "algo=penalty_sac", "env=tiny", f"hydra.run.dir={run_dir}"],
        cwd=kit, env={**os.environ, "PYTHONPATH": str(kit)}, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip
    assert result.returncode == 1
    assert result.stderr.strip().splitlines() == [
        f"error: unknown algo 'penalty_sac'; choose one of {', '.join(ALGORITHMS)} (a new "
        "algorithm is an entry of ALGORITHMS in wcsac_rl/training/registry.py: "
        "docs/own_algorithm.md)"
    ]
    assert not run_dir.exists()


def test_every_entry_names_a_trainer_and_a_loss_that_import():
    for entry in ALGORITHMS.values():
        assert issubclass(resolve(entry.trainer), Trainer), entry.name
        if entry.loss is not None:
            assert callable(resolve(entry.loss)), entry.name
        if entry.check is not None:
            assert callable(resolve(entry.check)), entry.name
        assert not entry.risk_neutral or entry.safety_critic, entry.name


def test_the_algorithms_of_conf_are_the_registrys():
    names = {
        yaml.safe_load((ROOT / "conf" / "algo" / f"{stem}.yaml").read_text())["name"]
        for stem in algorithm_files(ROOT / "conf")
    }
    assert names == set(ALGORITHMS)
