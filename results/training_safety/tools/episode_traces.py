"""One line per episode of a checkpoint's policy on StaticEnv: where it started, how close
it came to the hazard (at the origin, radius 0.7) and to the goal (at (1.1, 1.1)), where
it ended, and for a costly episode the step it entered the hazard and its speed inside.

Usage (from the repository root, the run's commit checked out)::

    OMP_NUM_THREADS=1 python results/training_safety/tools/episode_traces.py RUN_DIR N [random|det] [ENV_SEED]

``random`` (the default) samples the policy's actions, ``det`` takes its mean action (as
the test episodes do). ENV_SEED (default 123) seeds the start states and the sampled
actions.
"""

from __future__ import annotations

import sys

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from wcsac_rl.evaluation.evaluator import load_policy

GOAL = np.array([1.1, 1.1])


def main(run_dir: str, episodes: int, mode: str = "random", env_seed: int = 123) -> None:
    torch.set_num_threads(1)
    torch.manual_seed(env_seed)  # the sampled actions too
    loaded = load_policy(run_dir, env_seed=env_seed)
    print(f"run {run_dir}: frames {loaded.frames}, {mode} actions")
    exploration = ExplorationType.RANDOM if mode == "random" else ExplorationType.DETERMINISTIC
    with set_exploration_type(exploration), torch.no_grad():
        for ep in range(episodes):
            td = loaded.env.rollout(1000, loaded.policy, break_when_any_done=True)
            cost = td["next", "cost"].reshape(-1).numpy()
            xy = td["robot_xy"].reshape(-1, 2).numpy()
            r = np.linalg.norm(xy, axis=1)
            g = np.linalg.norm(xy - GOAL, axis=1)
            line = (
                f"ep {ep:2d} len {len(cost):4d} return {td['next', 'reward'].sum().item():6.2f} "
                f"cost {cost.sum():4.0f} start ({xy[0, 0]:+.2f},{xy[0, 1]:+.2f}) "
                f"closest to hazard {r.min():.2f} to goal {g.min():.2f} "
                f"end ({xy[-1, 0]:+.2f},{xy[-1, 1]:+.2f})"
            )
            if cost.sum() > 0:
                speed = np.linalg.norm(np.diff(xy, axis=0), axis=1)[cost[:-1] > 0]
                line += f" entered at step {int(np.argmax(cost > 0))}"
                line += f" speed inside {speed.mean() if len(speed) else 0.0:.4f}"
            print(line, flush=True)


if __name__ == "__main__":
    a = sys.argv[1:]
    main(a[0], int(a[1]), *(a[2:3]), *(int(x) for x in a[3:4]))
