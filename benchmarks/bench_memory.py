"""Resident memory (RSS) of a training run at the paper's settings, one run at a time.

Each measurement is a fresh process that builds the trainer from the default config
(StaticEnv, 2×256 networks, replay buffer of 10⁶ transitions, batch 256, UTD 0.25),
optionally fills the replay buffer to capacity first (``--fill``: the steady state of
a 3 M-frame run after its first 10⁶ frames, reached here in seconds by repeating
real transitions), trains ``--frames`` frames and reports its peak RSS
(``ru_maxrss``) and the RSS at the end, with the RSS after each collected batch.

    python benchmarks/bench_memory.py                      # sac_lag and wcsac, 5 000 frames, empty and full buffer
    python benchmarks/bench_memory.py --algos wcsac --frames 8000 --no-fill

The numbers are for this package's defaults (``retain_freed_memory=true``);
``--default-malloc`` measures glibc's defaults instead.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
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


def _child(algo: str, frames: int, fill: bool, default_malloc: bool) -> dict:
    from hydra import compose, initialize_config_dir

    from wcsac_rl.training import make_trainer

    overrides = [
        f"algo={algo}",
        "env=static",
        f"total_frames={frames}",
        f"epoch_frames={frames}",
        "progress_bar=false",
        "logger=none",
        f"retain_freed_memory={'false' if default_malloc else 'true'}",
    ]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    trainer = make_trainer(cfg, Path(tempfile.mkdtemp(prefix="bench_memory_")) / "run")
    start = _rss_mb()
    filled_s = 0.0
    if fill:  # real transitions, repeated up to the buffer's capacity
        t0 = time.time()
        from wcsac_rl.training import builders

        env = builders.make_train_env(cfg)  # not the trainer's: its collector starts it
        rollout = env.rollout(1000, break_when_any_done=False).reshape(-1)
        env.close()
        rows = rollout.select(*trainer.replay_keys)
        capacity = int(cfg.algo.buffer_size)
        while len(trainer.replay_buffer) < capacity:
            trainer.replay_buffer.extend(rows[: capacity - len(trainer.replay_buffer)])
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
    return {
        "algo": algo,
        "frames": frames,
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algos", nargs="+", default=["sac_lag", "wcsac"])
    parser.add_argument("--frames", type=int, default=5000)
    parser.add_argument("--no-fill", action="store_true", help="only the empty-buffer runs")
    parser.add_argument("--fill-only", action="store_true", help="only the full-buffer runs")
    parser.add_argument("--default-malloc", action="store_true", help="retain_freed_memory=false")
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        algo, frames, fill, default_malloc = args.child
        print(json.dumps(_child(algo, int(frames), fill == "1", default_malloc == "1")))
        return
    fills = [False] if args.no_fill else [True] if args.fill_only else [False, True]
    env = {**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")}
    print(
        f"{'algo':8s} {'buffer':>12s} {'frames':>7s} {'peak RSS':>9s} {'end RSS':>8s}  RSS by frames"
    )
    for fill in fills:
        for algo in args.algos:  # one process at a time: nothing else competes for memory
            child = [
                algo,
                str(args.frames),
                "1" if fill else "0",
                "1" if args.default_malloc else "0",
            ]
            out = subprocess.run(
                [sys.executable, __file__, "--child", *child],
                capture_output=True,
                text=True,
                env=env,
                check=True,
            ).stdout
            r = json.loads(out.strip().splitlines()[-1])
            buffer = f"{r['buffer_rows']:,} rows" if fill else "filling"
            trace = " ".join(f"{f}:{m}" for f, m in r["trace"][:: max(1, len(r["trace"]) // 6)])
            print(
                f"{algo:8s} {buffer:>12s} {r['frames']:>7d} {r['peak_rss_mb']:>6d} MB "
                f"{r['rss_end_mb']:>5d} MB  {trace}",
                flush=True,
            )


if __name__ == "__main__":
    main()
