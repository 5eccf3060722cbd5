"""Tiny real runs for the evaluation and report tests, trained once per test process.

:func:`tiny_sweep` trains, in a Hydra-multirun-like layout, two rows × two seeds on
the tiny env (50-step episodes, 800 frames each: a few seconds per run):

    <root>/multirun/2026-01-01/00-00-00/0_wcsac_0.5_tiny_seed0
                                       /1_wcsac_0.5_tiny_seed1
                                       /2_random_tiny_seed0
                                       /3_random_tiny_seed1

Tests copy it (:func:`copy_sweep`) before evaluating or reporting, so they do not
see each other's files.
"""

from __future__ import annotations

import atexit
import shutil
import struct
import tempfile
from pathlib import Path

from _training_helpers import compose_config

from wcsac_rl.training import make_trainer

SWEEP = Path("multirun") / "2026-01-01" / "00-00-00"
RUNS = (
    ("wcsac", "wcsac_0.5", 0),
    ("wcsac", "wcsac_0.5", 1),
    ("random", "random", 0),
    ("random", "random", 1),
)
EPISODE_STEPS = 50

_cache: dict[str, Path] = {}


def train_run(run_dir: Path, algo: str, seed: int, *extra: str) -> Path:
    """One small real run of ``algo`` on the tiny env (50-step episodes)."""
    overrides = [f"algo={algo}", "env=tiny", f"env.max_episode_steps={EPISODE_STEPS}"]
    overrides += [f"seed={seed}", "total_frames=800", "epoch_frames=400", *extra]
    if algo == "wcsac":
        overrides.append("risk_level=0.5")
    trainer = make_trainer(compose_config(*overrides), run_dir)
    try:
        return trainer.run()
    finally:
        trainer.close()


def tiny_sweep() -> Path:
    """The trained sweep directory (made on first use, removed at exit)."""
    if "sweep" not in _cache:
        root = Path(tempfile.mkdtemp(prefix="wcsac_eval_tests_"))
        atexit.register(shutil.rmtree, root, ignore_errors=True)
        sweep = root / SWEEP
        for job, (algo, label, seed) in enumerate(RUNS):
            train_run(sweep / f"{job}_{label}_tiny_seed{seed}", algo, seed)
        _cache["sweep"] = sweep
    return _cache["sweep"]


def copy_sweep(dest: Path) -> Path:
    """A private copy of :func:`tiny_sweep` under ``dest`` (same relative layout)."""
    target = dest / SWEEP
    shutil.copytree(tiny_sweep(), target)
    return target


def run_dirs(sweep: Path) -> list[Path]:
    """The run directories of a (copied) sweep, in job order."""
    return sorted(p for p in sweep.iterdir() if p.is_dir())


def png_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` from a PNG's IHDR chunk; asserts the file is a PNG."""
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    assert data[12:16] == b"IHDR"
    width, height = struct.unpack(">II", data[16:24])
    return width, height
