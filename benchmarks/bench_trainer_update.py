"""The trainer's own update, timed as the training loop runs it: updates per second.

Usage::

    python benchmarks/bench_trainer_update.py [--algo wcsac] [--env static]
                                              [--modes eager compiled round]
                                              [--rounds 11]
                                              [--updates 20] [--warmup 5]
                                              [--override KEY=VALUE ...] [--json PATH]

``bench_update.py`` times each loss in an update function of its own; this script
times ``OffPolicyTrainer.update`` itself (what ``train.py`` runs: a replay sample, the
loss, backward, the masked fused Adam steps, the Polyak update) on a trainer built from
the composed config (``algo=wcsac``: the kit's recipe, 2 × 256, batch 256), its replay
buffer first filled with random transitions. The updates of a round are taken as
``learn`` takes a batch's: their finite flags read once, after the last. ``--modes``:
``eager``, ``compiled`` (``compile=true``, the whole update compiled; its first
updates compile it, untimed) and ``round`` (``replay_draw=round``: the round's replay
rows drawn in one call). Rounds of the modes interleave; the median round is
reported. One torch thread.

It uses only what every commit of the trainer has (``make_trainer``, ``sample``,
``update``): ``--against CHECKOUT`` runs this checkout's trainer and the other
checkout's (its ``wcsac_rl``, this file's timing) in two worker processes, one round of
each in turn (each side first in every other round; both pinned to one processor, so
that neither keeps a less busy core), and prints each side's rate and the median of the
rounds' ratios (each worker waits while the other runs: a change of the machine's load
reaches both); ``--pairs K`` repeats that with K fresh pairs of processes, whose speed
varies by a percent or two with their memory layout (the same checkout against itself
measured 0.982–0.989 with one pair), and reports the median of the pairs' ratios::

    python benchmarks/bench_trainer_update.py --against /tmp/older-checkout --pairs 6 --rounds 21
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from wcsac_rl import compose_config
from wcsac_rl.training import make_trainer

ROOT = Path(__file__).resolve().parents[1]
MODES = {"eager": (), "compiled": ("compile=true",), "round": ("replay_draw=round",)}


def build(args: argparse.Namespace, mode: str, workdir: Path):
    """A trainer in ``mode`` with ``--fill`` random transitions in its buffer."""
    cfg = compose_config(
        f"algo={args.algo}",
        f"env={args.env}",
        "logger=none",
        "progress_bar=false",
        *MODES[mode],
        *args.override,
    )
    trainer = make_trainer(cfg, workdir / mode)
    torch.manual_seed(0)
    batches = iter(trainer.collector)  # (random actions during init_random_frames)
    while len(trainer.replay_buffer) < args.fill:
        batch = next(batches)
        trainer.tracker.add(batch)
        if trainer.postproc is not None:
            batch = trainer.postproc(batch)
        trainer.replay_buffer.extend(batch.reshape(-1).select(*trainer.stored_keys))
        if getattr(trainer, "initial_state_buffer", None) is not None:
            trainer.initial_state_buffer.add_starts(batch)
        if getattr(trainer, "episode_window", None) is not None:
            trainer.episode_window.add_episodes(batch)
    return trainer


def timed_round(trainer, updates: int) -> float:
    """Seconds for ``updates`` updates taken as ``learn`` takes a batch's."""
    batched = hasattr(trainer, "_pending")  # (a trainer that reads the flags per batch)
    at_once = getattr(trainer, "replay_draw", "update") == "round"
    start = time.perf_counter()
    if batched:
        trainer._pending = []
    indices = None
    if at_once:
        from wcsac_rl.training.replay import draw_indices

        indices = draw_indices(trainer.replay_buffer, updates)
    for i in range(updates):
        trainer.update(trainer.sample() if indices is None else trainer.sample(indices[i]))
    if batched:
        steps, trainer._pending = trainer._pending, None
        trainer._count(steps)
    return time.perf_counter() - start


class Worker:
    """A trainer in another process, on the ``wcsac_rl`` of ``checkout``, timed a round
    at a time on request (so rounds of two checkouts interleave as modes do)."""

    def __init__(self, checkout: Path, args: argparse.Namespace, mode: str) -> None:
        command = [sys.executable, str(Path(__file__).resolve()), "--worker"]
        command += ["--algo", args.algo, "--env", args.env, "--modes", mode]
        command += ["--warmup", str(args.warmup), "--fill", str(args.fill)]
        command += ["--cpu", str(args.cpu), "--override", *args.override]
        env = {**os.environ, "PYTHONPATH": str(checkout), "OMP_NUM_THREADS": "1"}
        self.checkout = checkout
        self.proc = subprocess.Popen(
            command, cwd=checkout, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )
        self._read("READY")

    def _read(self, tag: str) -> str:
        for line in self.proc.stdout:
            if line.startswith(tag):
                return line[len(tag) :].strip()
        raise RuntimeError(f"the worker on {self.checkout} ended (exit {self.proc.wait()})")

    def round(self, updates: int) -> float:
        self.proc.stdin.write(f"{updates}\n")
        self.proc.stdin.flush()
        return float(self._read("ROUND"))

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def worker(args: argparse.Namespace) -> None:
    """``--worker``: build, warm up, then time a round per line of stdin."""
    if args.cpu is not None and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.cpu})
    with tempfile.TemporaryDirectory() as tmp:
        trainer = build(args, args.modes[0], Path(tmp))
        try:
            timed_round(trainer, args.warmup)
            print("READY", flush=True)
            for line in sys.stdin:
                print(f"ROUND {timed_round(trainer, int(line))}", flush=True)
        finally:
            trainer.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--algo", default="wcsac")
    parser.add_argument("--env", default="static")
    parser.add_argument("--modes", nargs="+", choices=list(MODES), default=["eager"])
    parser.add_argument("--rounds", type=int, default=11)
    parser.add_argument("--updates", type=int, default=20, help="updates per round")
    parser.add_argument("--warmup", type=int, default=5, help="untimed updates per mode")
    parser.add_argument("--fill", type=int, default=2000, help="transitions in the buffer")
    parser.add_argument("--override", nargs="*", default=[], help="more config overrides")
    parser.add_argument("--json", type=Path, help="also write the figures here as JSON")
    parser.add_argument(
        "--against",
        type=Path,
        help="another checkout: its trainer's update (first of --modes) beside this one's",
    )
    parser.add_argument(
        "--cpu",
        type=int,
        help="--against: the processor both workers are pinned to (default: the first this "
        "process may use), so that neither side keeps a less busy core",
    )
    parser.add_argument(
        "--pairs", type=int, default=1, help="--against: pairs of fresh worker processes"
    )
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    if args.worker:
        return worker(args)
    if args.against is not None:
        return compare(args)
    with tempfile.TemporaryDirectory() as tmp:
        trainers = {mode: build(args, mode, Path(tmp)) for mode in args.modes}
        try:
            for mode, trainer in trainers.items():
                start = time.perf_counter()
                timed_round(trainer, args.warmup)
                print(f"{mode}: {args.warmup} warm-up updates {time.perf_counter() - start:.1f} s")
            seconds = {mode: [] for mode in trainers}
            for _ in range(args.rounds):
                for mode, trainer in trainers.items():
                    seconds[mode].append(timed_round(trainer, args.updates))
        finally:
            for trainer in trainers.values():
                trainer.close()
    rows = []
    for mode, times in seconds.items():
        rate = args.updates / statistics.median(times)
        rows.append({"mode": mode, "updates_per_s": rate, "rounds": len(times)})
        print(f"{mode}: {rate:.1f} updates/s (median of {len(times)} rounds)")
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    sys.stdout.flush()


def compare(args: argparse.Namespace) -> None:
    """``--against``: this checkout's and another's update in worker processes, their
    rounds interleaved, ``--pairs`` times with fresh processes (a process's speed varies
    by a percent or two with its memory layout); each side's median rate and the median
    of the pairs' ratios (each the median of its rounds' ratios)."""
    mode = args.modes[0]
    if args.cpu is None and hasattr(os, "sched_getaffinity"):
        args.cpu = min(os.sched_getaffinity(0))
    sides = {"this": ROOT, "against": args.against.resolve()}
    seconds = {name: [] for name in sides}
    pair_ratios, round_ratios = [], []
    for pair in range(args.pairs):
        order = list(sides)[:: 1 if pair % 2 == 0 else -1]  # (who starts first, too)
        workers = {name: Worker(sides[name], args, mode) for name in order}
        times = {name: [] for name in sides}
        try:
            for r in range(args.rounds):  # (each side first in every other round)
                for name in order[:: 1 if r % 2 == 0 else -1]:
                    times[name].append(workers[name].round(args.updates))
        finally:
            for runner in workers.values():
                runner.close()
        ratios = [a / t for t, a in zip(times["this"], times["against"])]
        pair_ratios.append(statistics.median(ratios))
        round_ratios.extend(ratios)
        for name in sides:
            seconds[name].extend(times[name])
        print(f"pair {pair + 1}: this / against {pair_ratios[-1]:.3f}", flush=True)
    rows = []
    for name, times in seconds.items():
        rate = args.updates / statistics.median(times)
        rows.append({"side": name, "checkout": str(sides[name]), "mode": mode,
                     "updates_per_s": rate, "rounds": len(times)})  # fmt: skip
        print(f"{name} ({sides[name]}), {mode}: {rate:.1f} updates/s (median of {len(times)})")
    ratio = statistics.median(pair_ratios)
    print(f"this / against, updates/s: {ratio:.3f} (median of {len(pair_ratios)} pairs' "
          f"ratios; range {min(pair_ratios):.3f}–{max(pair_ratios):.3f})")  # fmt: skip
    rows.append(
        {"ratio_this_over_against": ratio, "pair_ratios": pair_ratios, "round_ratios": round_ratios}
    )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
