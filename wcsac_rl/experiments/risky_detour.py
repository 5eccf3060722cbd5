"""WCSAC vs SAC-Lag on a sequential task with a risky shortcut and a safe detour.

The tiny env (:class:`~wcsac_rl.envs.tiny.TinyHazardEnv`) with a *risky* hazard:
each step inside the hazard disc costs 5 with probability 0.02. The straight route
from (−1, 0) to the goal at (1, 0) crosses the disc (~14 steps inside): its
episodic cost has mean ≈ 1.4, within the limit d = 3, but CVaR_0.1 ≈ 6.7, over it
(measured over 2000 straight episodes; the discounted cost from the start state:
mean 1.16, CVaR_0.1 5.7). The detour around the disc costs nothing and takes a few
more steps. So SAC-Lag (expected cost ≤ d) should keep the shortcut, and WCSAC-0.1
(CVaR_0.1 ≤ d) should take the detour.

Each row is trained by the project's own :class:`~wcsac_rl.training.Trainer` from
the Hydra config (``conf/``). The route of the final deterministic policy is read
on the same geometry with a hazard that charges every step (cost 1): an episode
with cost > 0 crossed the disc.

``python -m wcsac_rl.experiments.risky_detour --seeds 0 1 2`` prints the table.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from wcsac_rl.envs import make_env
from wcsac_rl.evaluation.episodes import run_episodes

__all__ = ["RISKY_HAZARD", "ROWS", "DetourRun", "detour_config", "train_on_risky_detour"]

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
COST_LIMIT = 3.0
RISKY_HAZARD = {"hazard_cost": 5.0, "hazard_cost_prob": 0.02}
"""The tiny env's hazard made a risky shortcut (see the module docstring)."""

SCHEDULE = (
    "env=tiny",
    f"+env.kwargs.hazard_cost={RISKY_HAZARD['hazard_cost']}",
    f"+env.kwargs.hazard_cost_prob={RISKY_HAZARD['hazard_cost_prob']}",
    f"cost_limit={COST_LIMIT}",
    "algo.alpha_init=0.2",
    "algo.collector.num_envs=1",
    "algo.collector.frames_per_batch=50",
    "algo.collector.utd_ratio=1.0",
    "algo.collector.init_random_frames=500",
    "algo.batch_size=128",
    "algo.buffer_size=20000",
    "algo.network.width=64",
    "total_frames=4000",
    "epoch_frames=500",
    "eval_episodes=10",
    "checkpoint_every_epochs=100",
    "progress_bar=false",
    "logger=none",
)
"""A few thousand frames with one env and one update per frame: about a minute."""

ROWS: dict[str, tuple[str, ...]] = {
    "sac_lag": ("algo=sac_lag",),
    "wcsac_0.1": ("algo=wcsac", "risk_level=0.1"),
}


@dataclass
class DetourRun:
    """The final deterministic policy of one training run."""

    crossing_share: float  # test episodes whose path entered the hazard disc
    goal_share: float  # test episodes that reached the goal
    mean_return: float
    kappa: float
    seconds: float


def detour_config(row: str, seed: int, *overrides: str) -> DictConfig:
    """The Hydra config of one row (``"sac_lag"`` or ``"wcsac_0.1"``) on the task."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(
            "config", overrides=[*SCHEDULE, *ROWS[row], f"seed={seed}", "threads=1", *overrides]
        )


def route_of(policy, *, episodes: int = 20, seed: int = 10_000) -> tuple[float, float, float]:
    """(crossing share, goal share, mean return) of ``policy``'s deterministic episodes."""
    env = make_env("tiny", seed=seed, num_workers=min(episodes, 10), parallel=False)
    try:
        results = run_episodes(env, policy, episodes, deterministic=True, max_steps=100)
    finally:
        env.close()
    crossing = sum(r.cost > 0 for r in results) / len(results)
    goals = sum(r.goal_reached > 0 for r in results) / len(results)
    return crossing, goals, statistics.fmean(r.ret for r in results)


def train_on_risky_detour(
    row: str, seed: int, *overrides: str, run_dir: Path | None = None
) -> DetourRun:
    """Train ``row`` on the risky-detour task through the project's Trainer."""
    from wcsac_rl.training import make_trainer

    cfg = detour_config(row, seed, *overrides)
    start = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        trainer = make_trainer(cfg, run_dir or Path(tmp) / "run")
        try:
            trainer.run()
            crossing, goals, ret = route_of(trainer.policy)
            kappa = float(trainer.loss.kappa)
        finally:
            trainer.close()
    return DetourRun(crossing, goals, ret, kappa, time.time() - start)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m wcsac_rl.experiments.risky_detour")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides applied to every row")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print("| row | crossing share per seed | goal share per seed | return per seed | κ |")
    print("|---|---|---|---|---|")
    for row in args.rows:
        runs = [train_on_risky_detour(row, seed, *args.overrides) for seed in args.seeds]
        fmt = lambda xs: ", ".join(f"{x:.2f}" for x in xs)  # noqa: E731
        print(
            f"| {row} | {fmt(r.crossing_share for r in runs)} | "
            f"{fmt(r.goal_share for r in runs)} | {fmt(r.mean_return for r in runs)} | "
            f"{fmt(r.kappa for r in runs)} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
