"""Update and loop throughput, measured side by side in one process.

Usage::

    python benchmarks/bench_update.py [--threads 1] [--rounds 5] [--updates 20]
                                      [--compile] [--no-loop] [--default-malloc]

Prints, with one torch thread by default:

* the machine's single-core fp32 matmul peak (GFLOP/s, measured here);
* updates/s of (a) TorchRL's ``SACLoss`` with TorchRL's ``SoftUpdate`` (what a
  TorchRL user runs), (a') the same with the kit's ``PolyakUpdate``, (b) ``WCSACLoss``
  as the trainer runs it (fused critics, direct sampling, ``PolyakUpdate``),
  (b-) ``WCSACLoss`` through TorchRL's general paths (module calls, ``TanhNormal``,
  ``SoftUpdate``), (b') ``WCSACLoss`` under ``torch.compile`` (``--compile``),
  (c) a plain-PyTorch WCSAC update (``plain_wcsac.py``) and (d) ``WCSACLoss`` with
  the implicit-quantile safety critic (``algo.safety_critic=iqn``: N = N' = 20
  fractions, as the trainer runs it), with its time per update against (b)'s, all
  with the paper's
  sizes (2 × 256 MLPs, batch 256, obs 44, action 2), timed in interleaved rounds
  (median reported), each with its FLOPs per update (forward + backward matrix
  products) and the achieved GFLOP/s as a fraction of the matmul peak;
* StaticEnv steps/s (raw gymnasium and TorchRL-wrapped), collector frames/s (4
  envs in one BatchedGymEnv, random policy) and end-to-end training frames/s of
  WCSAC at the paper's UTD 0.25, against 4 × the update rate (the ceiling when
  collection, replay and logging cost nothing).

Like training (``retain_freed_memory: true``), the process first asks glibc's malloc
to keep freed memory for reuse; ``--default-malloc`` measures without that.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from torch.utils._python_dispatch import TorchDispatchMode
from torchrl.data import Bounded
from torchrl.objectives import SACLoss, SoftUpdate

sys.path.insert(0, str(Path(__file__).resolve().parent))

from plain_wcsac import PlainWCSAC, batch_inputs

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PolyakUpdate
from wcsac_rl.training.builders import adam
from wcsac_rl.training.runtime import retain_freed_memory

OBS, ACT, BATCH = 44, 2, 256


def matmul_peak_gflops(seconds: float = 1.0) -> dict[str, float]:
    """fp32 GFLOP/s of torch.mm at a large square size and at the update's layer sizes."""
    out = {}
    for name, (m, k, n) in {
        "1024x1024x1024": (1024, 1024, 1024),
        "256x256x256 (hidden layer)": (256, 256, 256),
        "256x46x256 (input layer)": (256, 46, 256),
    }.items():
        a, b = torch.randn(m, k), torch.randn(k, n)
        for _ in range(3):
            torch.mm(a, b)
        count, start = 0, time.perf_counter()
        while time.perf_counter() - start < seconds:
            torch.mm(a, b)
            count += 1
        out[name] = 2 * m * k * n * count / (time.perf_counter() - start) / 1e9
    return out


def make_batch() -> TensorDict:
    g = torch.Generator().manual_seed(0)
    return TensorDict(
        {
            "observation": torch.randn(BATCH, OBS, generator=g),
            "action": torch.rand(BATCH, ACT, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(BATCH, OBS, generator=g),
                "reward": torch.randn(BATCH, 1, generator=g),
                "cost": torch.bernoulli(torch.full((BATCH, 1), 0.1), generator=g),
                "done": torch.zeros(BATCH, 1, dtype=torch.bool),
                "terminated": torch.zeros(BATCH, 1, dtype=torch.bool),
            },
        },
        [BATCH],
    )


def torchrl_update_fn(loss, *, updater_class=PolyakUpdate, compile_loss: bool = False):
    updater = updater_class(loss, tau=0.005)
    optim = adam(loss.parameters(), lr=1e-3)
    forward = torch.compile(loss) if compile_loss else loss

    def update(batch):
        out = forward(batch)
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        optim.step()
        optim.zero_grad(set_to_none=True)
        updater.step()

    return update


def build_variants(with_compile: bool) -> dict[str, callable]:
    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, shape=(ACT,))

    def sac():
        return SACLoss(
            make_actor(OBS, spec), [make_qvalue(OBS, ACT) for _ in range(2)], loss_function="l2"
        )

    variants = {
        "(a) TorchRL SACLoss": torchrl_update_fn(sac(), updater_class=SoftUpdate),
        "(a') SACLoss, PolyakUpdate": torchrl_update_fn(sac()),
    }

    def wcsac(kind: str = "gaussian", **kwargs):
        return WCSACLoss(
            make_actor(OBS, spec),
            [make_qvalue(OBS, ACT) for _ in range(2)],
            make_safety_critic(OBS, ACT, kind=kind),
            **kwargs,
        )

    variants["(b) WCSACLoss"] = torchrl_update_fn(wcsac())
    variants["(b-) WCSACLoss, general paths"] = torchrl_update_fn(
        wcsac(fuse_critics=False, direct_sampling=False), updater_class=SoftUpdate
    )
    if with_compile:
        variants["(b') WCSACLoss, compiled"] = torchrl_update_fn(wcsac(), compile_loss=True)
    plain = PlainWCSAC(OBS, ACT)
    variants["(c) plain PyTorch WCSAC"] = plain_update_fn(plain)
    variants[IQN] = torchrl_update_fn(wcsac("iqn"))
    return variants


IQN = "(d) WCSACLoss, IQN critic"


def plain_update_fn(plain: PlainWCSAC):
    def update(batch):
        plain.update(*batch_inputs(batch))

    return update


class _MatmulFlops(TorchDispatchMode):
    """Counts 2·m·k·n for every (batched) matrix product, forward and backward.

    (torch's FlopCounterMode tracks modules, which trips over tensordict's
    parameter containers; matrix products are all but every FLOP of these updates.)
    """

    def __init__(self) -> None:
        super().__init__()
        self.flops = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        name = func.overloadpacket.__name__
        if name in ("mm", "addmm", "bmm", "baddbmm"):
            a, b = (args[0], args[1]) if name in ("mm", "bmm") else (args[1], args[2])
            batch = a.shape[0] if a.dim() == 3 else 1
            self.flops += 2 * batch * a.shape[-2] * a.shape[-1] * b.shape[-1]
        return out


def flops_per_update(update, batch) -> float:
    with _MatmulFlops() as counter:
        update(batch)
    return float(counter.flops)


def time_variants(variants, batch, rounds: int, updates: int) -> dict[str, float]:
    for name, update in variants.items():  # warm-up (and compilation)
        start = time.perf_counter()
        for _ in range(3):
            update(batch)
        print(f"  warm-up {name}: {time.perf_counter() - start:.1f}s", flush=True)
    rates: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, update in variants.items():
            start = time.perf_counter()
            for _ in range(updates):
                update(batch)
            rates[name].append(updates / (time.perf_counter() - start))
    return {name: statistics.median(r) for name, r in rates.items()}


def env_and_loop(update_rate: float, threads: int, retained: bool) -> list[tuple[str, str]]:
    """StaticEnv raw / wrapped steps/s, collector frames/s, end-to-end training frames/s."""
    from bench_envs import raw_steps_per_second, torchrl_steps_per_second
    from torchrl.collectors import Collector

    from wcsac_rl.envs import make_env
    from wcsac_rl.training import make_trainer

    rows = [
        ("StaticEnv raw gymnasium steps/s", f"{raw_steps_per_second('static', 3000):,.0f}"),
        ("StaticEnv TorchRL-wrapped steps/s", f"{torchrl_steps_per_second('static', 3000):,.0f}"),
    ]
    env = make_env("static", seed=0, num_workers=4, parallel=False)
    collector = Collector(env, None, frames_per_batch=400, total_frames=4000)
    start = time.perf_counter()
    frames = sum(batch.numel() for batch in collector)
    rows.append(
        (
            "collector frames/s (4 envs, BatchedGymEnv, random policy)",
            f"{frames / (time.perf_counter() - start):,.0f}",
        )
    )
    collector.shutdown()

    from hydra import compose, initialize_config_dir

    conf = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(
            "config",
            overrides=[
                "env=static",
                "total_frames=8400",
                "epoch_frames=4000",
                "algo.collector.init_random_frames=400",
                "eval_episodes=0",
                "progress_bar=false",
                "logger=none",
                f"threads={threads}",
                f"retain_freed_memory={str(retained).lower()}",
            ],
        )
    with tempfile.TemporaryDirectory() as tmp:
        trainer = make_trainer(cfg, Path(tmp) / "run")
        trainer.run()
        trainer.close()
        rows_csv = (Path(tmp) / "run" / "progress.csv").read_text().splitlines()
    header, last = rows_csv[0].split(","), rows_csv[-2].split(",")  # a full epoch with updates
    values = dict(zip(header, last))
    fps, ups = float(values["time/fps"]), float(values["time/ups"])
    rows.append(
        ("end-to-end WCSAC training frames/s (UTD 0.25)", f"{fps:,.1f} ({ups:.1f} updates/s)")
    )
    rows.append(
        (
            "  vs 4 × isolated WCSACLoss updates/s",
            f"{fps / (4 * update_rate):.0%} of {4 * update_rate:.1f}",
        )
    )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates", type=int, default=20)
    parser.add_argument(
        "--compile", action="store_true", help="also time WCSACLoss under torch.compile"
    )
    parser.add_argument(
        "--no-loop", action="store_true", help="skip the env / collector / training part"
    )
    parser.add_argument(
        "--default-malloc",
        action="store_true",
        help="keep glibc's default malloc thresholds (training retains freed memory)",
    )
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    retained = not args.default_malloc and retain_freed_memory()
    print(
        f"torch {torch.__version__}, {args.threads} thread(s), "
        f"malloc {'retains freed memory' if retained else 'defaults'}"
    )

    peaks = matmul_peak_gflops()
    peak = max(peaks.values())
    print("\nfp32 matmul GFLOP/s:")
    for name, value in peaks.items():
        print(f"  {name:<28} {value:8.1f}")

    batch = make_batch()
    variants = build_variants(args.compile)
    flops = {name: flops_per_update(update, batch) for name, update in variants.items()}
    rates = time_variants(variants, batch, args.rounds, args.updates)
    reference = rates["(a) TorchRL SACLoss"]
    print(
        f"\nupdates/s (median of {args.rounds} interleaved rounds of {args.updates} updates, batch {BATCH}):"
    )
    print(
        f"  {'variant':<32} {'updates/s':>10} {'vs SACLoss':>10} {'GFLOP/upd':>10} {'GFLOP/s':>8} {'of peak':>8}"
    )
    for name, rate in rates.items():
        gflops = flops[name] / 1e9
        print(
            f"  {name:<32} {rate:10.1f} {rate / reference:10.2f} {gflops:10.3f} "
            f"{gflops * rate:8.1f} {gflops * rate / peak:8.0%}"
        )
    ratio = rates["(b) WCSACLoss"] / rates[IQN]
    print(f"\nIQN critic: {ratio:.2f}× the time per update of the Gaussian critic (b)")
    if not args.no_loop:
        wcsac_rate = rates["(b) WCSACLoss"]  # the training run below is eager
        print("\nenvironment and loop:")
        for name, value in env_and_loop(wcsac_rate, args.threads, bool(retained)):
            print(f"  {name:<52} {value}")


if __name__ == "__main__":
    main()
