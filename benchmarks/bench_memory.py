"""Resident memory (RSS) of a training run at the paper's settings, one run at a time.

Each measurement is a fresh process that builds the trainer from the default config
(StaticEnv, 2×256 networks, replay buffer of 10⁶ transitions, batch 256, UTD 0.25),
optionally fills the replay buffer to capacity first (``--fill``: the steady state of
a 3 M-frame run after its first 10⁶ frames, reached here in seconds by repeating
real transitions), trains ``--frames`` frames and reports its peak RSS
(``ru_maxrss``) and the RSS at the end, with the RSS after each collected batch.
Each algorithm at the defaults (``wcsac``, ``sac_lag``: their buffer also stores the
10-step cost entries, but not their state s_{t+m}, which the buffer reads from the row
that holds it: ``wcsac_rl/training/replay.py``) and at the paper's options (``wcsac_paper``, ``sac_lag_paper``).

    python benchmarks/bench_memory.py                      # the four, 5 000 frames, empty and full buffer
    python benchmarks/bench_memory.py --algos wcsac --frames 8000 --no-fill
    python benchmarks/bench_memory.py --algos wcsac --env tiny --frames 800 --no-fill \
        --override algo.collector.init_random_frames=400 --json out.json   # a smoke run

The numbers are for this package's defaults (``retain_freed_memory=true``);
``--default-malloc`` measures glibc's defaults instead.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _child(
    algo: str, frames: int, fill: bool, default_malloc: bool, env: str, extra: list[str]
) -> dict:
    from hydra import compose, initialize_config_dir

    from wcsac_rl.training import make_trainer

    overrides = [
        f"algo={algo}",
        f"env={env}",
        f"total_frames={frames}",
        f"epoch_frames={frames}",
        "progress_bar=false",
        "logger=none",
        f"retain_freed_memory={'false' if default_malloc else 'true'}",
        *extra,
    ]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    tmp = tempfile.mkdtemp(prefix="bench_memory_")
    trainer = make_trainer(cfg, Path(tmp) / "run")
    start = _rss_mb()
    filled_s = 0.0
    if fill:  # real transitions, repeated up to the buffer's capacity
        t0 = time.time()
        from wcsac_rl.training import builders

        train_env = builders.make_train_env(cfg)  # not the trainer's: its collector starts it
        rollout = train_env.rollout(1000, break_when_any_done=False)  # [envs, time]
        train_env.close()
        if trainer.initial_state_buffer is not None:
            trainer.initial_state_buffer.add_starts(rollout)
        # written as the trainer writes collected pieces: whole, each with its own n-step
        # entries (the buffer reads a row's n-step state from a later row of its piece)
        if rollout.ndim == 1:  # one env without a batch dimension
            rollout = rollout.unsqueeze(0)
        envs, steps = rollout.shape[0], rollout.shape[-1]
        capacity = int(cfg.algo.buffer_size)
        piece = 0
        while len(trainer.replay_buffer) < capacity:
            env_rows = rollout[piece % envs : piece % envs + 1]  # one env's steps: a piece
            env_rows = env_rows[:, : min(steps, capacity - len(trainer.replay_buffer))]
            if trainer.postproc is not None:  # the n-step cost entries the trainer adds
                env_rows = trainer.postproc(env_rows)
            trainer.replay_buffer.extend(env_rows.reshape(-1).select(*trainer.stored_keys))
            piece += 1
        filled_s = time.time() - t0
    after_fill = _rss_mb()
    trace = []
    learn = trainer.learn

    def traced(batch):
        out = learn(batch)
        trace.append((trainer.tracker.frames, round(_rss_mb())))
        return out

    trainer.learn = traced
    t0 = time.time()
    try:
        trainer.run()
    finally:
        trainer.close()
        shutil.rmtree(tmp, ignore_errors=True)
    return {
        "algo": algo,
        "env": env,
        "frames": frames,
        "updates": trainer.updates,
        "full_buffer": fill,
        "buffer_rows": len(trainer.replay_buffer),
        "retain_freed_memory": not default_malloc,
        "rss_after_build_mb": round(start),
        "rss_after_fill_mb": round(after_fill),
        "fill_s": round(filled_s, 1),
        "train_s": round(time.time() - t0, 1),
        "rss_end_mb": round(_rss_mb()),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "trace": trace,
    }


ALGOS = ["sac_lag", "wcsac", "sac_lag_paper", "wcsac_paper"]


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=ALGOS)
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--env", default="static", help="env preset (default: static)")
    parser.add_argument(
        "--override",
        nargs="*",
        default=[],
        help="further Hydra overrides of each run (e.g. algo.collector.init_random_frames=400)",
    )
    parser.add_argument("--json", type=Path, help="also write the results here as JSON")
    parser.add_argument("--no-fill", action="store_true", help="only the empty-buffer runs")
    parser.add_argument("--fill-only", action="store_true", help="only the full-buffer runs")
    parser.add_argument("--default-malloc", action="store_true", help="retain_freed_memory=false")
    parser.add_argument("--child", nargs=5, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        algo, frames, fill, default_malloc, env = args.child
        result = _child(algo, int(frames), fill == "1", default_malloc == "1", env, args.override)
        print(json.dumps(result))
        return [result]
    if args.frames < 1:
        parser.error("--frames must be at least 1")
    fills = [False] if args.no_fill else [True] if args.fill_only else [False, True]
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    print(
        f"{'algo':13s} {'buffer':>12s} {'frames':>7s} {'peak RSS':>9s} {'end RSS':>8s}  RSS by frames"
    )
    results = []
    for fill in fills:
        for algo in args.algos:  # one process at a time: nothing else competes for memory
            child = [
                algo,
                str(args.frames),
                "1" if fill else "0",
                "1" if args.default_malloc else "0",
                args.env,
            ]
            proc = subprocess.run(
                [sys.executable, __file__, "--child", *child, "--override", *args.override],
                capture_output=True,
                text=True,
                env=env,
            )
            if proc.returncode:
                sys.stderr.write(proc.stderr)
                raise SystemExit(f"the {algo} run ({'full' if fill else 'empty'} buffer) failed")
            out = proc.stdout
            r = json.loads(out.strip().splitlines()[-1])
            results.append(r)
            buffer = f"{r['buffer_rows']:,} rows" if fill else "filling"
            trace = " ".join(f"{f}:{m}" for f, m in r["trace"][:: max(1, len(r["trace"]) // 6)])
            print(
                f"{algo:13s} {buffer:>12s} {r['frames']:>7d} {r['peak_rss_mb']:>6d} MB "
                f"{r['rss_end_mb']:>5d} MB  {trace}",
                flush=True,
            )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
