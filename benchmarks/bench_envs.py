"""Env throughput: raw gymnasium steps/s and TorchRL-wrapped steps/s for each preset.

Usage::

    python benchmarks/bench_envs.py [--steps N] [--envs static dynamic ...] [--json PATH]

Random actions, one process, resets included in the timing. "raw" steps the
gymnasium env directly; "torchrl" steps ``make_env(name)`` (GymWrapper + info reader
+ StepCounter/RewardSum/CostSum) through ``env.rollout`` with pre-drawn random
actions; "batched x4" does the same with ``make_env(name, num_workers=4,
parallel=False)`` (one ``BatchedGymEnv``, the training default) and counts frames.
``--json PATH`` also writes the rows as JSON (``tests/test_benchmarks.py`` reads it).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from wcsac_rl.envs import PRESET_NAMES, make_env, make_gym_env


def raw_steps_per_second(name: str, steps: int, seed: int = 0) -> float:
    """Steps/s of the bare gymnasium env with uniform random actions."""
    env = make_gym_env(name)
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1.0, 1.0, size=(steps, 2))
    env.reset(seed=seed)
    start = time.perf_counter()
    for a in actions:
        *_, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            env.reset()
    elapsed = time.perf_counter() - start
    env.close()
    return steps / elapsed


def torchrl_steps_per_second(name: str, steps: int, seed: int = 0, num_envs: int = 1) -> float:
    """Frames/s of ``make_env(name)`` stepped by ``rollout`` with pre-drawn random actions.

    The actions are drawn up front so the timing covers the env and its TorchRL
    wrapping, not the sampling of a random policy from the action spec. With
    ``num_envs > 1`` the envs are one in-process batch and ``steps`` batched steps
    give ``steps × num_envs`` frames.
    """
    env = make_env(name, seed=seed, num_workers=num_envs, parallel=False)
    shape = (steps + 10, 2) if num_envs == 1 else (steps + 10, num_envs, 2)
    actions = torch.rand(shape, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    it = iter(actions)

    def policy(td):
        return td.set("action", next(it))

    env.rollout(10, policy, break_when_any_done=False)  # warm-up
    start = time.perf_counter()
    td = env.rollout(steps, policy, break_when_any_done=False)
    elapsed = time.perf_counter() - start
    assert td.shape[-1] == steps
    env.close()
    return steps * num_envs / elapsed


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=5000, help="steps per measurement")
    parser.add_argument("--envs", nargs="*", default=list(PRESET_NAMES), help="preset names")
    parser.add_argument("--json", type=Path, help="also write the rows here as JSON")
    args = parser.parse_args(argv)
    if args.steps < 4:
        parser.error("--steps must be at least 4 (the batched cell steps 4 envs steps // 4 times)")
    unknown = [name for name in args.envs if name not in PRESET_NAMES]
    if unknown:
        parser.error(f"unknown env presets {unknown}; choose from {list(PRESET_NAMES)}")
    torch.set_num_threads(1)

    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"torch {torch.__version__}, {args.steps} steps per cell, 1 process"
    )
    header = (
        f"{'env':<12} {'raw gym steps/s':>16} {'torchrl steps/s':>16} {'overhead':>9} "
        f"{'batched x4 frames/s':>20} {'overhead':>9}"
    )
    print(header)
    print("-" * len(header))
    rows = []
    for name in args.envs:
        raw = raw_steps_per_second(name, args.steps)
        wrapped = torchrl_steps_per_second(name, args.steps)
        batched = torchrl_steps_per_second(name, args.steps // 4, num_envs=4)
        print(
            f"{name:<12} {raw:>16,.0f} {wrapped:>16,.0f} {raw / wrapped:>8.1f}x "
            f"{batched:>20,.0f} {raw / batched:>8.1f}x",
            flush=True,
        )
        rows.append(
            {
                "env": name,
                "raw_steps_per_s": raw,
                "torchrl_steps_per_s": wrapped,
                "batched4_frames_per_s": batched,
            }
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    bad = [
        row["env"]
        for row in rows
        if not all(math.isfinite(v) for k, v in row.items() if k != "env")
    ]
    if bad:
        raise SystemExit(f"non-finite rates for {bad}")
    return rows


if __name__ == "__main__":
    main()
