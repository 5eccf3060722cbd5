"""Compose the project's Hydra config for tests, at a small scale."""

from __future__ import annotations

import hashlib
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"

# A fast schedule: 2 envs, 200 frames per batch, 50 updates, small networks.
SMALL = [
    "algo.collector.num_envs=2",
    "algo.collector.frames_per_batch=200",
    "algo.collector.init_random_frames=200",
    "algo.batch_size=64",
    "algo.buffer_size=10000",
    "algo.network.width=32",
    "epoch_frames=400",
    "total_frames=800",
    "eval_episodes=1",
    "progress_bar=false",
    "logger=csv",
]
SMALL_RANDOM = [o for o in SMALL if o.startswith(("epoch", "total", "eval", "progress", "logger"))]

# train.py command lines on the tiny env: 2 envs × 100 steps per batch (one tiny-env
# episode each), 16-unit networks; add the frame budget (and epoch size) per test.
TINY_CLI = [
    "env=tiny",
    "algo.collector.num_envs=2",
    "algo.collector.frames_per_batch=200",
    "algo.collector.init_random_frames=200",
    "algo.batch_size=32",
    "algo.network.width=16",
    "eval_episodes=1",
    "progress_bar=false",
]
TINY_CPO = [
    "algo=cpo",
    "env=tiny",
    "algo.collector.num_envs=2",
    "algo.collector.frames_per_batch=200",
    "algo.network.width=16",
    "algo.value_iters=5",
    "epoch_frames=400",
    "eval_episodes=1",
    "progress_bar=false",
]


def compose_config(*overrides: str, small: bool = True) -> DictConfig:
    """``conf/config.yaml`` with the test schedule and then ``overrides`` applied."""
    algo = next((o.split("=", 1)[1] for o in overrides if o.startswith("algo=")), "wcsac")
    base = (SMALL_RANDOM if algo == "random" else SMALL) if small else []
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=[*base, *overrides])


# Columns every algorithm's progress.csv has (docs/training.md, "Logged columns").
COMMON_COLUMNS = {
    "epoch",
    "frames",
    "updates",
    "time_s",
    "train/episodes",
    "train/episode_return",
    "train/episode_cost",
    "train/episode_length",
    "train/cost_rate",
    "train/cumulative_cost",
    "train/epochs_over_limit",
    "train/peak_epoch_cost",
    "train/numerical_failures",
    "train/skipped_updates",
    "train/goal_rate",
    "eval/episode_return",
    "eval/episode_cost",
    "eval/episode_length",
    "eval/goal_rate",
    "time/fps",
    "time/ups",
}


def tree_digests(root: Path, *, skip: tuple[str, ...] = (".lock",)) -> dict[str, str]:
    """SHA-256 of every file below ``root`` (but those named in ``skip``: a run's lock
    file is rewritten by every process that takes it), to show a command changed none."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name not in skip
    }


def fill_replay_alike(*trainers, steps: int = 120) -> None:
    """One rollout of the first trainer's env, through its postproc, stored in every
    trainer's replay buffer (and its start states, where it keeps them): trainers built
    alike then sample the same batches."""
    batch = trainers[0].env.rollout(steps, break_when_any_done=False).reshape(-1)
    if trainers[0].postproc is not None:
        batch = trainers[0].postproc(batch.unsqueeze(0)).reshape(-1)
    for trainer in trainers:
        trainer.replay_buffer.extend(batch.select(*trainer.stored_keys).clone())
        if trainer.initial_state_buffer is not None:
            trainer.initial_state_buffer.add_starts(batch.unsqueeze(0))
