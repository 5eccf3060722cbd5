"""Where the time of one ``WCSACLoss`` update goes: a torch.profiler breakdown by part.

Usage::

    python benchmarks/profile_update.py [--options kit gaussian paper] [--updates 30]
                                        [--repeats 3] [--ablation ROUNDS]
                                        [--batch 256] [--width 256] [--json PATH]

One torch thread, glibc's malloc keeping freed memory (as training runs: without
it, first touches of fresh pages show up as copies). The update is the trainer's (``OffPolicyTrainer.update``): the
loss's forward, the finite-loss check, backward, the finite-gradient check, one fused
Adam step, the Polyak target update; its batch comes through the kit's pipeline
(``bench_update.pipeline_batch``: n-step entries, start states). The loss's methods
are wrapped in ``torch.profiler.record_function`` labels on the instance (the
loss's code is not changed), and every profiled operator's own time is given to the
innermost label around it; backward operators are given to the label of the forward
operator they differentiate (the autograd sequence number). So each part's share
counts its forward, its backward and the Python between its operators:

* ``targets`` — ``a' ~ π(s')``, the target reward critics at ``(s', a')`` and the
  target safety critic where its target bootstraps (at ``(s', a')``, or with
  ``cost_n_steps > 1`` at ``s_{t+m}``, in the same batched products);
* ``targets: n-step draw`` — ``a ~ π(s_{t+m})`` (``cost_n_steps > 1``);
* ``kappa: start-state values`` — ``a₀ ~ π(s₀)`` and the safety critic at the start
  states (``kappa_states="initial"``);
* ``kappa: statistic`` — the per-state Γ or the CVaR of the Gaussian mixture
  (``kappa_statistic="tail"``);
* ``online critics`` — the four critics at the replay ``(s, a)`` (forward and
  backward), and ``critic losses`` — the TD losses on them;
* ``actor loss`` — ``a ~ π(s)`` with gradient and the critics at it;
* ``forward: rest``, ``backward: rest`` (gradient accumulation, the engine),
  ``finite checks``, ``optimizer step``, ``target update``.

Cross-cutting, inside those: ``actor sampling`` (every draw of ``a ~ π``), ``stack
critic parameters`` (the fused ensemble's per-update gather) and ``safety module
call`` (the safety critic called as a module, not fused). The profiler adds a fixed
cost per operator, so operator-heavy parts are over-counted against the matrix
products; the shares are relative, not timings. ``--ablation`` cross-checks them
without the profiler: the update's time with each extra of the kit's options
(``python train.py``'s) switched off alone (:data:`ABLATIONS`), with the Gaussian
critic and at the paper's options, against the kit's time, in interleaved rounds.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import math
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile, record_function

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_update import OPTION_SETS, Sizes, kit_loss

from wcsac_rl import WCSACLoss
from wcsac_rl.objectives import PolyakUpdate
from wcsac_rl.training.builders import adam
from wcsac_rl.training.runtime import retain_freed_memory

PREFIX = "wcsac_profile::"
PARTS = {  # (owner, method) -> the part it is; owner "" is the loss, else its attribute
    ("", "compute_targets"): "targets",
    ("", "_sample_action"): "targets: n-step draw",
    ("", "_policy_values"): "kappa: start-state values",
    ("constraint_signal", "statistic"): "kappa: statistic",
    ("", "_online_values"): "online critics",
    ("", "qvalue_loss"): "critic losses",
    ("", "safety_loss"): "critic losses",
    ("", "_actor_loss"): "actor loss",
}
DETAILS = {  # (owner, method) -> a cross-cutting detail inside the parts
    ("", "_sample_policy"): "actor sampling",
    ("critics", "layers"): "stack critic parameters",
    ("safety_head", "values"): "safety module call",
}
STEPS = ("forward", "finite checks", "backward", "optimizer step", "target update")


def _label(name: str) -> str:
    return PREFIX + name


def instrument(loss: WCSACLoss) -> None:
    """Wrap the methods of the loss and of its parts (on the instances: their code is
    not changed) in profiler labels. A method this script names but the loss does
    not have is an error: the breakdown would silently lose a part."""
    for (owner, method), name in {**PARTS, **DETAILS}.items():
        target = getattr(loss, owner) if owner else loss
        original = getattr(target, method, None)
        if original is None:
            where = f"loss.{owner}" if owner else type(loss).__name__
            raise SystemExit(f"profile_update.py instruments {where}.{method}, which is gone")

        @functools.wraps(original)
        def wrapped(*args, _original=original, _name=name, **kwargs):
            with record_function(_label(_name)):
                return _original(*args, **kwargs)

        setattr(target, method, wrapped)


def make_update(loss: WCSACLoss):
    """The trainer's update (``OffPolicyTrainer.update``) with one label per step."""
    optimizer = adam(loss.parameters(), lr=1e-3)
    updater = PolyakUpdate(loss, tau=0.005)

    def update(batch):
        with record_function(_label("forward")):
            out = loss(batch)
            total = sum(value for key, value in out.items() if key.startswith("loss_"))
        with record_function(_label("finite checks")):
            assert bool(torch.isfinite(total))
        with record_function(_label("backward")):
            total.backward()
        with record_function(_label("finite checks")):
            grads = [p.grad for p in loss.parameters() if p.grad is not None]
            assert bool(torch.isfinite(torch.nn.utils.get_total_norm(grads)))
        with record_function(_label("optimizer step")):
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        with record_function(_label("target update")):
            updater.step()

    return update


def _labels_of(event) -> tuple[str, ...]:
    """The wcsac_profile labels around ``event`` (itself included), outermost first."""
    labels = []
    while event is not None:
        if event.name.startswith(PREFIX):
            labels.append(event.name[len(PREFIX) :])
        event = event.cpu_parent
    return tuple(reversed(labels))


def _part_and_detail(labels: tuple[str, ...]) -> tuple[str, str | None]:
    parts = [name for name in labels if name in set(PARTS.values())]
    details = [name for name in labels if name in set(DETAILS.values())]
    step = labels[0] if labels else "outside"
    if parts:
        return parts[-1], details[-1] if details else None
    return (f"{step}: rest" if step in ("forward", "backward") else step), (
        details[-1] if details else None
    )


def breakdown(events) -> dict[str, dict]:
    """Self time (and matrix-product FLOPs) per (part, detail), backward operators
    given to their forward's part."""
    forward_of = {}  # autograd sequence number -> (part, detail) of the forward op
    for event in events:
        if event.sequence_nr >= 0 and not event.name.startswith("autograd::engine"):
            labels = _labels_of(event)
            if labels and labels[0] == "forward":
                forward_of.setdefault(event.sequence_nr, _part_and_detail(labels))
    times: dict[tuple[str, str | None], float] = defaultdict(float)
    flops: dict[str, float] = defaultdict(float)
    for event in events:
        labels = _labels_of(event)
        key = _part_and_detail(labels)
        if labels and labels[0] == "backward":
            # inside an engine node: the part of the forward op it differentiates
            node = event
            while node is not None and not node.name.startswith("autograd::engine"):
                node = node.cpu_parent
            if node is not None and node.sequence_nr in forward_of:
                key = forward_of[node.sequence_nr]
        times[key] += event.self_cpu_time_total
        flops[key[0]] += event.flops or 0
    total = sum(times.values())
    total_flops = sum(flops.values())
    parts: dict[str, dict] = {}
    for (part, detail), us in times.items():
        entry = parts.setdefault(
            part,
            {"share": 0.0, "flop_share": flops[part] / total_flops, "details": defaultdict(float)},
        )
        entry["share"] += us / total
        if detail is not None:
            entry["details"][detail] += us / total
    return {
        name: {**entry, "details": dict(entry["details"])}
        for name, entry in sorted(parts.items(), key=lambda kv: -kv[1]["share"])
    }


def top_operators(prof) -> dict[str, float]:
    """Each operator's self time, as a share of the profiled total."""
    averages = [a for a in prof.key_averages() if not a.key.startswith(PREFIX)]
    total = sum(a.self_cpu_time_total for a in averages)
    return {a.key: a.self_cpu_time_total / total for a in averages}


def profile_options(options: str, sizes: Sizes, updates: int, warmup: int) -> dict:
    torch.manual_seed(0)
    loss, batch = kit_loss(options, sizes)
    instrument(loss)
    update = make_update(loss)
    for _ in range(warmup):
        update(batch)
    with profile(activities=[ProfilerActivity.CPU], with_flops=True) as prof:
        for _ in range(updates):
            update(batch)
    events = prof.events()
    return {
        "gflop_per_update": sum(e.flops or 0 for e in events) / updates / 1e9,
        "parts": breakdown(events),
        "operators": top_operators(prof),
    }


def combine(options: str, repeats: list[dict], top: int = 12) -> dict:
    """Medians over the repeats of each part's share (and of its details), and the
    operators with the largest median self time."""
    parts = {name for r in repeats for name in r["parts"]}

    def median(values) -> float:
        return statistics.median(values) if values else 0.0

    combined = {}
    for name in parts:
        entries = [
            r["parts"].get(name, {"share": 0.0, "flop_share": 0.0, "details": {}}) for r in repeats
        ]
        details = {d for e in entries for d in e["details"]}
        combined[name] = {
            "share": median([e["share"] for e in entries]),
            "share_range": [min(e["share"] for e in entries), max(e["share"] for e in entries)],
            "flop_share": median([e["flop_share"] for e in entries]),
            "details": {d: median([e["details"].get(d, 0.0) for e in entries]) for d in details},
        }
    operators = {op for r in repeats for op in r["operators"]}
    op_shares = {op: median([r["operators"].get(op, 0.0) for r in repeats]) for op in operators}
    return {
        "options": options,
        "repeats": len(repeats),
        "gflop_per_update": median([r["gflop_per_update"] for r in repeats]),
        "parts": dict(sorted(combined.items(), key=lambda kv: -kv[1]["share"])),
        "top_operators": dict(sorted(op_shares.items(), key=lambda kv: -kv[1])[:top]),
    }


ABLATIONS = {
    "kit": ("kit", {}),
    "kappa_signal=critic": ("kit", {"kappa_signal": "critic"}),
    "cost_n_steps=1": ("kit", {"cost_n_steps": 1}),
    "kappa_statistic=mean": ("kit", {"kappa_statistic": "mean"}),
    "Gaussian critic": ("gaussian", {}),
    "Gaussian critic, kappa_states=replay": ("gaussian", {"kappa_states": "replay"}),
    "paper options": ("paper", {}),
}
"""The variants the ablation times against ``kit`` (``python train.py``'s default): an
option set of ``bench_update.OPTION_SETS`` and the options changed in it. Each of
the kit's extras switched off alone (the episode window, the n-step targets, the tail
statistic), the Gaussian critic (``kappa_signal="critic"``), the same without the start
states, and the paper's options (the loss's own defaults)."""


def ablation(sizes: Sizes, rounds: int, updates: int, warmup: int) -> list[dict]:
    """Time per update (no profiler) of each :data:`ABLATIONS` variant relative to the
    kit's: medians of ``rounds`` interleaved rounds of ``updates`` updates."""
    runs = {}
    for name, (options, changes) in ABLATIONS.items():
        torch.manual_seed(0)
        loss, batch = kit_loss(options, sizes, changes)
        runs[name] = (make_update(loss), batch)
    for update, batch in runs.values():
        for _ in range(warmup):
            update(batch)
    seconds: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(rounds):
        for name, (update, batch) in runs.items():
            start = time.perf_counter()
            for _ in range(updates):
                update(batch)
            seconds[name].append((time.perf_counter() - start) / updates)
    base = statistics.median(seconds["kit"])
    return [
        {"variant": name, "time_vs_kit": statistics.median(values) / base}
        for name, values in seconds.items()
    ]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--options", nargs="+", choices=OPTION_SETS, default=list(OPTION_SETS))
    parser.add_argument("--updates", type=int, default=30, help="profiled updates per repeat")
    parser.add_argument("--warmup", type=int, default=5, help="unprofiled updates first")
    parser.add_argument(
        "--repeats", type=int, default=3, help="profiles per option set, interleaved (medians)"
    )
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--width", type=int, default=256, help="hidden units (2 layers)")
    parser.add_argument(
        "--ablation",
        type=int,
        default=0,
        metavar="ROUNDS",
        help="also time the update (no profiler) with each extra of the kit's options "
        "switched off, in this many interleaved rounds of --updates updates",
    )
    parser.add_argument("--json", type=Path, help="also write the breakdown here as JSON")
    args = parser.parse_args(argv)
    for name in ("updates", "repeats", "batch", "width"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be at least 1")
    torch.set_num_threads(1)
    retain_freed_memory()  # as training does (retain_freed_memory: true)
    sizes = Sizes(batch=args.batch, width=args.width)
    raw: dict[str, list[dict]] = {options: [] for options in args.options}
    for _ in range(args.repeats):
        for options in args.options:
            with contextlib.redirect_stdout(sys.stderr):  # the profiler's own chatter
                raw[options].append(profile_options(options, sizes, args.updates, args.warmup))
    results = [combine(options, runs) for options, runs in raw.items()]
    for result in results:
        print(
            f"\nWCSACLoss [{result['options']}] update, batch {sizes.batch}, "
            f"2 x {sizes.width}, {result['gflop_per_update']:.3f} GFLOP: median shares of "
            f"{args.repeats} x {args.updates} profiled updates"
        )
        print(f"  {'part':<28} {'time':>6} {'(range)':>15} {'FLOPs':>6}")
        for part, entry in result["parts"].items():
            details = ", ".join(
                f"{name} {share:.1%}" for name, share in sorted(entry["details"].items())
            )
            low, high = entry["share_range"]
            print(
                f"  {part:<28} {entry['share']:6.1%} {f'({low:.1%}-{high:.1%})':>15} "
                f"{entry['flop_share']:6.1%}" + (f"   (of which {details})" if details else "")
            )
        print("  top operators (median self time):")
        for op, share in result["top_operators"].items():
            print(f"    {op:<48} {share:6.1%}")
    ablation_rows = None
    if args.ablation:
        with contextlib.redirect_stdout(sys.stderr):
            ablation_rows = ablation(sizes, args.ablation, args.updates, args.warmup)
        print(
            f"\ntime per update against the kit's (no profiler; medians of "
            f"{args.ablation} interleaved rounds of {args.updates} updates):"
        )
        for row in ablation_rows:
            print(f"  {row['variant']:<32} {row['time_vs_kit']:6.3f}")
    output = {"profiles": results, "ablation": ablation_rows}
    if args.json:
        args.json.write_text(json.dumps(output, indent=1))
    for options, runs in raw.items():
        for run in runs:
            shares = [entry["share"] for entry in run["parts"].values()]
            flop_shares = [entry["flop_share"] for entry in run["parts"].values()]
            if not all(math.isfinite(x) and x >= 0 for x in shares + flop_shares) or not (
                math.isclose(sum(shares), 1.0, rel_tol=1e-6)
                and math.isclose(sum(flop_shares), 1.0, rel_tol=1e-6)
            ):
                raise SystemExit(f"[{options}] the shares do not add up to the profiled total")
    return output


if __name__ == "__main__":
    main()
