"""Update speed of an ensemble of safety critics (E = 4 and E = 8) beside one, in one process.

Usage::

    python benchmarks/bench_ensemble.py [--threads 1] [--rounds 5] [--updates 20]
                                        [--batch 256] [--width 256] [--json PATH]
    python benchmarks/bench_ensemble.py --batch 8 --width 16 --rounds 1 --updates 1 \\
        --warmup 1                                   # a smoke run (tests)

Each variant is the loss the trainer builds for a config (``compose_config``: the
recipe's options, ``builders.safety_critic_kwargs``' critic, one safety critic per
member, each initialised on its own) on a batch made as the trainer makes it
(``bench_update.pipeline_batch``), updated as ``bench_update`` updates (loss, backward,
Adam, Polyak), timed in interleaved rounds (the median reported) against the variant
with one critic of the same algorithm:

* ``wcsac``: today's default (``algo=wcsac``: one IQN safety critic); ``wcsac_ucb_E4`` /
  ``wcsac_ucb_E8``: the same with ``algo.num_safety_nets`` = 4 / 8 read at their upper
  confidence bound (``algo.ensemble_reading=ucb``, every member in one batched product
  per layer);
* ``cal`` (``algo=cal``: E = 4 mean critics, CAL's Safety-Gym size) and ``cal_E8`` (E = 8,
  its MuJoCo size) against ``cal_E1``, CAL's recipe with one critic.

Printed per variant: updates/s, the ratio to its one-critic variant's, the matrix-product
FLOPs of one update (forward and backward, ``bench_update.flops_per_update``) and their
ratio. Sizes: obs 44, action 2 (StaticEnv's), 2 hidden layers of ``--width``, batch
``--batch`` (the paper's: 256 and 256). ``--json PATH`` writes the rows
(``tests/test_benchmarks.py`` reads it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_update import (
    Sizes,
    Variant,
    add_timing_arguments,
    flops_per_update,
    kit_networks,
    pipeline_batch,
    time_variants,
    torchrl_update_fn,
)

from wcsac_rl import WCSACLoss, compose_config
from wcsac_rl.modules import make_safety_critic
from wcsac_rl.objectives import SACLagLoss, loss_parts
from wcsac_rl.training.builders import safety_critic_kwargs
from wcsac_rl.training.config import safety_options
from wcsac_rl.training.runtime import retain_freed_memory

CONFIGS: dict[str, tuple[str, tuple[str, ...]]] = {
    # name: (its one-critic baseline, the config's overrides)
    "wcsac": ("wcsac", ("algo=wcsac",)),
    "wcsac_ucb_E4": (
        "wcsac",
        ("algo=wcsac", "algo.num_safety_nets=4", "algo.ensemble_reading=ucb"),
    ),
    "wcsac_ucb_E8": (
        "wcsac",
        ("algo=wcsac", "algo.num_safety_nets=8", "algo.ensemble_reading=ucb"),
    ),
    "cal_E1": ("cal_E1", ("algo=cal", "algo.num_safety_nets=1", "algo.ensemble_reading=max")),
    "cal": ("cal_E1", ("algo=cal",)),
    "cal_E8": ("cal_E1", ("algo=cal", "algo.num_safety_nets=8")),
}
"""The variants: each one's baseline (one safety critic) and config."""


def ensemble_loss(name: str, sizes: Sizes):
    """The loss of :data:`CONFIGS` ``name`` with the kit's networks, as ``make_loss``
    builds it, its pipeline batch and its number of safety critics."""
    algo = compose_config(*CONFIGS[name][1]).algo
    options = safety_options(algo)
    critic = safety_critic_kwargs(options)
    actor, qvalues, _ = kit_networks(sizes, **critic)
    members = [
        make_safety_critic(sizes.obs, sizes.act, width=sizes.width, **critic)
        for _ in range(options.num_safety_nets)
    ]
    kwargs = {**loss_parts(options), "alpha_init": float(algo.alpha_init)}
    cls = WCSACLoss
    if algo.name == "wcsac":
        kwargs["risk_level"] = options.risk_level
    else:
        cls = SACLagLoss  # (SAC-Lag and CAL are α = 1)
    safety = members[0] if len(members) == 1 else members
    loss = cls(actor, qvalues, safety, **kwargs)
    return loss, pipeline_batch(loss, sizes, options), options.num_safety_nets


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_timing_arguments(parser)
    parser.add_argument("--json", type=Path, help="also write the rows here as JSON")
    args = parser.parse_args(argv)
    retain_freed_memory()  # as training does (retain_freed_memory: true)
    torch.set_num_threads(args.threads)
    sizes = Sizes(batch=args.batch, width=args.width)
    torch.manual_seed(0)
    variants, members = {}, {}
    for name, (baseline, _) in CONFIGS.items():
        loss, batch, members[name] = ensemble_loss(name, sizes)
        variants[name] = Variant(name, torchrl_update_fn(loss), batch, None, baseline)
    flops = {name: flops_per_update(v.update, v.batch) for name, v in variants.items()}
    rates = time_variants(variants, args.rounds, args.updates, args.warmup)
    print(
        f"\nupdates/s, {args.threads} thread(s), batch {sizes.batch}, width {sizes.width} "
        f"(median of {args.rounds} interleaved rounds of {args.updates} updates):"
    )
    print(
        f"  {'variant':<14} {'E':>2} {'updates/s':>10} {'× one':>7} {'GFLOP/upd':>10} "
        f"{'FLOPs × one':>12}"
    )
    rows = []
    for name, rate in rates.items():
        baseline = variants[name].baseline
        row = {
            "name": name,
            "members": members[name],
            "baseline": baseline,
            "updates_per_s": rate,
            "vs_one": rate / rates[baseline],
            "gflop_per_update": flops[name] / 1e9,
            "flops_vs_one": flops[name] / flops[baseline],
        }
        rows.append(row)
        print(
            f"  {name:<14} {row['members']:>2} {rate:10.1f} {row['vs_one']:7.2f} "
            f"{row['gflop_per_update']:10.3f} {row['flops_vs_one']:12.2f}"
        )
    bad = [
        (row["name"], key)
        for row in rows
        for key, value in row.items()
        if isinstance(value, float) and not math.isfinite(value)
    ]
    if args.json:
        args.json.write_text(json.dumps({"threads": args.threads, "rows": rows}, indent=1))
    if bad:
        raise SystemExit(f"non-finite figures: {bad}")
    return rows


if __name__ == "__main__":
    main()
