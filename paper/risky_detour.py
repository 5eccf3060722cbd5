"""WCSAC vs SAC-Lag on a sequential task with a risky shortcut and a safe detour.

The tiny env (:class:`~wcsac_rl.envs.tiny.TinyHazardEnv`) with a *risky* hazard:
each step inside the hazard disc costs 5 with probability 0.02. The straight route
from (−1, 0) to the goal at (1, 0) crosses the disc (~14 steps inside): its
episodic cost has mean ≈ 1.4, within the limit d = 3, but CVaR_0.1 ≈ 6.7, over it
(measured over 2000 straight episodes; the discounted cost from the start state:
mean 1.16, CVaR_0.1 5.7). The detour around the disc costs nothing and takes 2–3
more steps (~40 instead of ~38). So SAC-Lag (expected cost ≤ d) should keep the
shortcut, and WCSAC-0.1 (CVaR_0.1 ≤ d) should take the detour. A route with k ≤ 5
steps inside has CVaR_0.1 = k exactly, so grazing the rim for up to
:data:`RISKY_STEPS_INSIDE` = 3 steps is still within d: the *risky share* counts
the episodes over that, the *crossing share* every episode that entered the disc.

Each row is trained by the project's own :class:`~wcsac_rl.training.Trainer` from
the Hydra config (``conf/``). The route of the final deterministic policy is read
on the same geometry with a hazard that charges every step (cost 1): an episode's
cost is its number of steps inside the disc (:func:`route_of`, 20 episodes).

**The learner.** Both rows get the same safety critic and κ (:data:`LEARNER`: the
StaticEnv options, ``td`` variance target, non-negative Q^c, κ on the CVaR_α of the
start-state mixture, γ_c = 1, with 50-step cost targets over 100-frame collector
batches so a start state's target spans the hazard) and the same schedule
(:data:`SCHEDULE`). What the kit's defaults did on this task, and the changes:

* **Entropy scale.** The reward is progress (≤ 0.05 a step) plus 1 at the goal, so
  every route to the goal returns ≈ 2.9; the shortcut is worth only the discount of
  2–3 steps, ≈ 0.02 in Q^r. With ``alpha_init`` 0.2 the entropy bonus (≈ 0.3 a
  step) outweighed the reward and delayed termination: neither row reached the goal
  in 8 000–12 000 frames. ``alpha_init=0.01``: both rows reach it within ~2 000 frames.
* **Initial κ.** With κ₀ = softplus(0) ≈ 0.69, κΓ outweighs a 0.02 reward gap at the
  first cost seen: both rows stopped at the rim or went round before their critic
  had seen the shortcut's tail; κ then fell at the same rate in both (the tail of a
  policy that never crosses is 0), and the final route was decided by when κ fell
  under ~0.015, not by the tail (at 8 000 frames, 10-step targets: SAC-Lag ended on
  the shortcut on 4/5 seeds, WCSAC entered the disc on 3/5). Worse, the Gaussian
  critic's variance head collapsed in that cost-free phase and could not recover
  (see below): WCSAC's start-state CVaR read 1.3 while its policy crossed (realised
  6.2). ``kappa_init=0.02`` lets both rows
  take the shortcut first, the critic learn its cost distribution, and κ rise for
  WCSAC only (``kappa_lr_scale=3``: fast enough to rise within the budget); SAC-Lag's
  κ falls to 0, its start-state mean (≈ 1.4) being under d.
* **Not fixed here (shared code):** the variance head ``softplus(z)`` with targets
  ≈ 0 on cost-free states drives z to −10…−150, where its gradient vanishes (and is 0
  below the 1e-8 clamp), so after a cost-free stretch it underestimates the variance.
  κ then settles where the *estimated* start-state tail is ≈ d (3.0 in the logs),
  and WCSAC's route keeps switching between the detour, a graze and the shortcut
  during training: the table is the final policy at 10 000 frames. γ_c = 1 also lets
  the critic's values grow without bound for a policy that loiters without reaching
  the goal (episodes then end by truncation and are bootstrapped): seed 3 (κ 0.22)
  and seed 5 stop short of the goal on some or all start states.

Measured (``python -m paper.risky_detour --seeds 0 1 2 3 4 5``, CPU
seconds per run while two other trainings shared the 2 cores; 56–59 s and 37–39 s per
WCSAC / SAC-Lag run on a less loaded machine):

| row | seed | crossing share | risky share | steps inside | goal share | return | κ | CPU s |
|---|---|---|---|---|---|---|---|---|
| sac_lag | 0 | 1.00 | 1.00 | 14.1 | 1.00 | 2.93 | 0.000 | 68 |
| sac_lag | 1 | 1.00 | 1.00 | 14.6 | 1.00 | 2.93 | 0.000 | 63 |
| sac_lag | 2 | 1.00 | 1.00 | 14.2 | 1.00 | 2.93 | 0.000 | 59 |
| sac_lag | 3 | 1.00 | 1.00 | 14.3 | 1.00 | 2.93 | 0.000 | 47 |
| sac_lag | 4 | 1.00 | 1.00 | 14.2 | 1.00 | 2.94 | 0.000 | 44 |
| sac_lag | 5 | 1.00 | 1.00 | 14.3 | 1.00 | 2.94 | 0.000 | 51 |
| wcsac_0.1 | 0 | 0.05 | 0.00 | 0.1 | 1.00 | 2.94 | 0.016 | 71 |
| wcsac_0.1 | 1 | 0.00 | 0.00 | 0.0 | 1.00 | 2.94 | 0.008 | 70 |
| wcsac_0.1 | 2 | 0.00 | 0.00 | 0.0 | 1.00 | 2.94 | 0.024 | 69 |
| wcsac_0.1 | 3 | 0.00 | 0.00 | 0.0 | 0.70 | 1.69 | 0.222 | 66 |
| wcsac_0.1 | 4 | 0.00 | 0.00 | 0.0 | 1.00 | 2.93 | 0.006 | 62 |
| wcsac_0.1 | 5 | 0.20 | 0.20 | 1.1 | 0.00 | 1.87 | 0.054 | 68 |

SAC-Lag takes the shortcut on 6/6 seeds. WCSAC-0.1 stays off it on 6/6 (risky
share ≤ 0.2, at most 1.1 steps inside on average) and takes the detour to the goal
on 4/6 (seeds 0, 1, 2, 4); per epoch, only seed 1 held the detour from 3 000 frames
on, seeds 0, 2 and 4 reached it in the last 1–4 epochs. The same seed and config give
the same numbers on CPU.
See ``results/risky_detour.md`` for the configurations tried on the way.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

from wcsac_rl.config_dir import CONF_DIR as _CONF_DIR
from wcsac_rl.envs import make_env
from wcsac_rl.rollouts.episodes import run_episodes

__all__ = [
    "LEARNER",
    "RISKY_HAZARD",
    "RISKY_STEPS_INSIDE",
    "ROWS",
    "SCHEDULE",
    "DetourRun",
    "Route",
    "detour_config",
    "route_of",
    "train_on_risky_detour",
]

CONF_DIR = _CONF_DIR
COST_LIMIT = 3.0
RISKY_HAZARD = {"hazard_cost": 5.0, "hazard_cost_prob": 0.02}
"""The tiny env's hazard made a risky shortcut (see the module docstring)."""
RISKY_STEPS_INSIDE = 3
"""A route with more steps than this inside the disc is over the limit by its own
CVaR: with k ≤ 5 steps inside, every charged outcome lies in the worst 10 %
(1 − 0.98^5 < 0.1), so CVaR_0.1 = 5 · 0.02 k / 0.1 = k, within d = 3 up to k = 3."""

LEARNER = (
    "algo.variance_target=td",
    "algo.cost_n_steps=50",
    "algo.nonnegative_cost=true",
    "algo.kappa_states=initial",
    "algo.kappa_statistic=tail",
    "algo.cost_gamma=1.0",
)
"""The safety critic and κ of both rows (the options found on StaticEnv, see
``results/static_critic``), with n-step cost targets spanning the way from the start
to past the hazard (~40 steps)."""

SCHEDULE = (
    "env=tiny",
    f"+env.kwargs.hazard_cost={RISKY_HAZARD['hazard_cost']}",
    f"+env.kwargs.hazard_cost_prob={RISKY_HAZARD['hazard_cost_prob']}",
    f"cost_limit={COST_LIMIT}",
    "algo.alpha_init=0.01",
    "algo.kappa_init=0.02",
    "algo.kappa_lr_scale=3.0",
    "algo.collector.num_envs=1",
    "algo.collector.frames_per_batch=100",
    "algo.collector.utd_ratio=1.0",
    "algo.collector.init_random_frames=500",
    "algo.batch_size=128",
    "algo.buffer_size=20000",
    "algo.network.width=64",
    "total_frames=10000",
    "epoch_frames=1000",
    "eval_episodes=10",
    "checkpoint_every_epochs=100",
    "progress_bar=false",
    "logger=none",
)
"""One env, one update per frame, 10 000 frames (see the module docstring)."""

ROWS: dict[str, tuple[str, ...]] = {
    "sac_lag": ("algo=sac_lag", *LEARNER),
    "wcsac_0.1": ("algo=wcsac", "risk_level=0.1", *LEARNER),
}


class Route(NamedTuple):
    """Where a policy's deterministic test episodes went (see :func:`route_of`)."""

    crossing: float  # share of episodes whose path entered the hazard disc
    risky: float  # share with more than RISKY_STEPS_INSIDE steps inside (CVaR_0.1 > d)
    goal: float  # share that reached the goal
    steps_inside: float  # mean steps inside the disc per episode
    mean_return: float


@dataclass
class DetourRun:
    """The final deterministic policy of one training run."""

    crossing_share: float  # test episodes whose path entered the hazard disc
    risky_share: float  # test episodes with more than RISKY_STEPS_INSIDE steps inside
    goal_share: float  # test episodes that reached the goal
    steps_inside: float  # mean steps inside the disc per test episode
    mean_return: float
    kappa: float
    seconds: float  # wall-clock
    cpu_seconds: float  # this process's CPU time (the wall-clock time on an idle core)


def detour_config(row: str, seed: int, *overrides: str) -> DictConfig:
    """The Hydra config of one row (``"sac_lag"`` or ``"wcsac_0.1"``) on the task."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(
            "config", overrides=[*SCHEDULE, *ROWS[row], f"seed={seed}", "threads=1", *overrides]
        )


def route_of(policy, *, episodes: int = 20, seed: int = 10_000) -> Route:
    """The route of ``policy``'s deterministic episodes from the task's start states.

    Read with the default hazard, which charges 1 per step inside the disc: an
    episode's cost is its number of steps inside.
    """
    env = make_env("tiny", seed=seed, num_workers=min(episodes, 10), parallel=False)
    try:
        results = run_episodes(env, policy, episodes, deterministic=True, max_steps=100)
    finally:
        env.close()
    n = len(results)
    return Route(
        crossing=sum(r.cost > 0 for r in results) / n,
        risky=sum(r.cost > RISKY_STEPS_INSIDE for r in results) / n,
        goal=sum(r.goal_reached > 0 for r in results) / n,
        steps_inside=statistics.fmean(r.cost for r in results),
        mean_return=statistics.fmean(r.ret for r in results),
    )


def train_on_risky_detour(
    row: str, seed: int, *overrides: str, run_dir: Path | None = None
) -> DetourRun:
    """Train ``row`` on the risky-detour task through the project's Trainer."""
    from wcsac_rl.training import make_trainer

    cfg = detour_config(row, seed, *overrides)
    start, cpu_start = time.time(), time.process_time()
    with tempfile.TemporaryDirectory() as tmp:
        trainer = make_trainer(cfg, run_dir or Path(tmp) / "run")
        try:
            trainer.run()
            route = route_of(trainer.policy)
            kappa = float(trainer.loss.kappa)
        finally:
            trainer.close()
    return DetourRun(
        crossing_share=route.crossing,
        risky_share=route.risky,
        goal_share=route.goal,
        steps_inside=route.steps_inside,
        mean_return=route.mean_return,
        kappa=kappa,
        seconds=time.time() - start,
        cpu_seconds=time.process_time() - cpu_start,
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m paper.risky_detour")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=list(ROWS))
    parser.add_argument("overrides", nargs="*", help="Hydra overrides applied to every row")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    print(
        "| row | seed | crossing share | risky share | steps inside | goal share | return "
        "| κ | wall s | CPU s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for row in args.rows:
        for seed in args.seeds:
            r = train_on_risky_detour(row, seed, *args.overrides)
            print(
                f"| {row} | {seed} | {r.crossing_share:.2f} | {r.risky_share:.2f} | "
                f"{r.steps_inside:.1f} | {r.goal_share:.2f} | {r.mean_return:.2f} | "
                f"{r.kappa:.3f} | {r.seconds:.0f} | {r.cpu_seconds:.0f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
