"""The safety critic's Γ at states that are really visited, against gamma_map.py's at-rest reads.

gamma_map.py places the robot at rest, heading at the goal. The replay buffer holds
moving robots. This tool rolls out N episodes of 1 000 steps from a checkpoint, first
with its own stochastic policy and then with uniform random actions. It splits the
states those episodes visit into three regions: in the hazard (r < 0.7), near the goal
(closer than GOAL_RADIUS to (1.1, 1.1)) and elsewhere. For each region it prints the
mean Γ_α at the visited states (a = π(s), deterministic). It also prints the mean Γ_α
with the robot placed at rest at the same positions, which is what gamma_map.py reads.
Up to 400 visited states per region are read, and 100 at rest.

Usage (from the repository root, the run's commit checked out)::

    OMP_NUM_THREADS=1 python results/training_safety/tools/visited_reads.py RUN_DIR [N [GOAL_RADIUS]]

N defaults to 10 and GOAL_RADIUS to 0.35. It reuses gamma_map.py's rebuild and reads,
so it is pinned to the same commit (ee73765).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gamma_map import GOAL, evaluate, observe, rebuild

HAZARD_RADIUS = 0.7


def main(run_dir: str, episodes: int = 10, goal_radius: float = 0.35) -> None:
    torch.manual_seed(0)
    _, ckpt, env, loss, policy = rebuild(run_dir)
    print(
        f"run {run_dir}: frames {ckpt['frames']} kappa {float(loss.kappa):.4f} "
        f"head {loss.safety_head.kind} goal radius {goal_radius}"
    )
    for who in ("policy", "random"):
        obs, xy = [], []
        with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
            for _ in range(episodes):
                actor = policy if who == "policy" else None  # None: uniform random actions
                td = env.rollout(1000, actor, break_when_any_done=True)
                obs.append(td["observation"].reshape(td.numel(), -1))
                xy.append(td["robot_xy"].reshape(-1, 2))
        obs, xy = torch.cat(obs), torch.cat(xy).numpy()
        r = np.linalg.norm(xy, axis=1)
        g = np.linalg.norm(xy - GOAL, axis=1)
        regions = {
            "hazard": r < HAZARD_RADIUS,
            "goal": g < goal_radius,
            "elsewhere": (r >= HAZARD_RADIUS) & (g >= goal_radius),
        }
        for name, mask in regions.items():
            idx = np.flatnonzero(mask)
            if len(idx) == 0:
                print(f"  {who:6s} {name:9s} n     0")
                continue
            idx = idx[np.linspace(0, len(idx) - 1, min(400, len(idx))).astype(int)]
            visited = evaluate(loss, policy, obs[idx])[0]
            at_rest = evaluate(loss, policy, observe(env, xy[idx][:100]))[0]
            print(
                f"  {who:6s} {name:9s} n {int(mask.sum()):5d}  visited: Γ {visited['gamma'].mean():6.2f} "
                f"(Q^c {visited['mean'].mean():6.2f})  at rest there: Γ {at_rest['gamma'].mean():6.2f}"
            )


if __name__ == "__main__":
    args = sys.argv[1:]
    main(args[0], *(int(a) if i == 0 else float(a) for i, a in enumerate(args[1:])))
