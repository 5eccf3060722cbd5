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
``update``), so the same file run from two checkouts, in turn, compares them.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

from wcsac_rl import compose_config
from wcsac_rl.training import make_trainer

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
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
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


if __name__ == "__main__":
    main()
