"""The prepared device check (``make gpu-check``): on a CUDA machine, the device tests,
then a short training on the GPU, eager, compiled and captured (the compiled update
replayed as a CUDA graph), side by side with the same training on this machine's CPU
(eager and compiled): gradient updates/s and frames/s of each.

Usage::

    python benchmarks/gpu_check.py [--frames 20000] [--epoch-frames 10000]
                                   [--algo wcsac] [--env static] [--device cuda]
                                   [--timeout 240] [--json PATH]
    python benchmarks/gpu_check.py --device cpu --env tiny --frames 800 \\
        --epoch-frames 400 --no-tests --override algo.network.width=16   # the smoke run

Where torch sees no CUDA device (``--device cuda``, the default) it says so in one line
and exits 0: nothing to check. Otherwise each training is ``train.py`` in a fresh
process (one torch thread, ``device=...``, ``compile=...``, ``cudagraphs=...``, two
epochs by default) in
a temporary directory, and its rates are read from the last epoch's row of its
``progress.csv`` (the first epoch holds the replay warm-up and the compile):
``updates/s`` = the epoch's updates / its ``time/update_s`` (the learner alone),
``frames/s`` = ``time/fps`` (the whole loop: collection, updates, test episodes).
A training that fails or runs past ``--timeout`` is reported as such (its last lines
shown) and the check exits 1.

The figures go in docs/performance.md with the card's name (``torch.cuda.get_device_name``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from wcsac_rl.training.progress import read_progress

ROOT = Path(__file__).resolve().parents[1]
MODES = {
    "eager": ("compile=false",),
    "compiled": ("compile=true",),
    "captured": ("compile=true", "cudagraphs=true"),
}
"""How the update runs: eager, the whole update under ``torch.compile``, or that compiled
update replayed as a CUDA graph (CUDA only: not run on the CPU side)."""
CUDA_ONLY_MODES = ("captured",)


def cuda_missing(device: str) -> str | None:
    """Why ``device`` cannot be checked here (``None``: it can)."""
    if torch.device(device).type != "cuda" or torch.cuda.is_available():
        return None
    build = f"torch {torch.__version__}" + ("" if torch.version.cuda else ", a CPU build")
    return f"gpu-check: no CUDA device on this machine ({build}): nothing to check"


def train(args: argparse.Namespace, device: str, mode: str, workdir: Path) -> dict:
    """One short training on ``device`` in ``mode``: its last epoch's rates, or why not."""
    run_dir = workdir / f"{device.replace(':', '_')}_{mode}"
    command = [
        sys.executable,
        str(ROOT / "train.py"),
        f"algo={args.algo}",
        f"env={args.env}",
        f"device={device}",
        *MODES[mode],
        f"total_frames={args.frames}",
        f"epoch_frames={args.epoch_frames}",
        "eval_episodes=1",
        "logger=csv",
        "progress_bar=false",
        f"seed={args.seed}",
        f"hydra.run.dir={run_dir}",
        *args.override,
    ]
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    start = time.monotonic()
    try:
        proc = subprocess.run(
            command, cwd=workdir, env=env, capture_output=True, text=True, timeout=args.timeout
        )
    except subprocess.TimeoutExpired:
        return {"device": device, "mode": mode, "error": f"past --timeout {args.timeout} s"}
    wall = time.monotonic() - start
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-5:]
        return {"device": device, "mode": mode, "error": " | ".join(tail)}
    columns = read_progress(run_dir / "progress.csv")
    updates = columns["updates"]
    epoch_updates = updates[-1] - (updates[-2] if len(updates) > 1 else 0.0)
    update_s = columns["time/update_s"][-1]
    return {
        "device": device,
        "mode": mode,
        "epochs": len(updates),
        "updates_per_s": epoch_updates / update_s if update_s > 0 else math.nan,
        "frames_per_s": columns["time/fps"][-1],
        "wall_s": wall,
    }


def device_tests() -> int:
    """The device tests (tests/test_devices.py) in a fresh process: their exit code."""
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "tests/test_devices.py"],
        cwd=ROOT,
    ).returncode


def table(results: list[dict]) -> str:
    lines = [
        "| device | mode | updates/s (learner) | frames/s (loop) | wall s |",
        "|---|---|---:|---:|---:|",
    ]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['device']} | {r['mode']} | failed: {r['error']} | | |")
        else:
            lines.append(
                f"| {r['device']} | {r['mode']} | {r['updates_per_s']:.1f} | "
                f"{r['frames_per_s']:.1f} | {r['wall_s']:.0f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python benchmarks/gpu_check.py")
    parser.add_argument("--device", default="cuda", help="the device to check (default cuda)")
    parser.add_argument("--algo", default="wcsac")
    parser.add_argument("--env", default="static")
    parser.add_argument("--frames", type=int, default=20_000, help="frames per training")
    parser.add_argument("--epoch-frames", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1, help="torch threads per training")
    parser.add_argument("--timeout", type=int, default=240, help="seconds per training")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    parser.add_argument("--no-tests", action="store_true", help="skip the device tests")
    parser.add_argument("--no-host", action="store_true", help="skip the CPU side")
    parser.add_argument("--override", nargs="*", default=[], help="more train.py overrides")
    parser.add_argument("--json", type=Path, help="also write the results as JSON")
    args = parser.parse_args(argv)

    missing = cuda_missing(args.device)
    if missing is not None:
        print(missing)
        return 0
    card = (
        torch.cuda.get_device_name(torch.device(args.device))
        if torch.device(args.device).type == "cuda"
        else "the host CPU"
    )
    print(f"gpu-check on {args.device} ({card}), torch {torch.__version__}")
    tests = None if args.no_tests else device_tests()
    devices = [args.device] + ([] if args.no_host or args.device == "cpu" else ["cpu"])
    results = []
    with tempfile.TemporaryDirectory(prefix="gpu_check_") as tmp:
        for device in devices:
            for mode in args.modes:
                if mode in CUDA_ONLY_MODES and torch.device(device).type != "cuda":
                    continue
                results.append(train(args, device, mode, Path(tmp)))
                print(table(results[-1:]).splitlines()[-1], flush=True)
    print(table(results))
    if args.json is not None:
        args.json.write_text(
            json.dumps({"card": card, "tests_exit_code": tests, "results": results}, indent=1)
        )
    failed = tests not in (None, 0) or any("error" in r for r in results)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
