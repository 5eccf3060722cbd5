"""Update and loop throughput, measured side by side in one process.

Usage::

    python benchmarks/bench_update.py [--threads 1] [--rounds 5] [--updates 20]
                                      [--options kit gaussian paper] [--compile]
                                      [--no-loop] [--default-malloc] [--json PATH]
                                      [--variants NAME ...]
    python benchmarks/bench_update.py --options kit --variants wcsac_kit \
        wcsac_kit_module_calls --rounds 11 --no-loop      # a direct read's gain, alone
    python benchmarks/bench_update.py --batch 8 --width 16 --rounds 1 --updates 1 \\
        --peak-seconds 0.01 --env tiny --loop-frames 800     # a smoke run (tests)

Prints, with one torch thread by default:

* the machine's single-core fp32 matmul peak (GFLOP/s, measured here);
* updates/s of every variant below, timed in interleaved rounds (median reported),
  each with its FLOPs per update (forward + backward matrix products) and the
  achieved GFLOP/s as a fraction of the matmul peak. Each ``WCSACLoss`` variant is
  timed at each option set of ``--options`` (:data:`OPTION_SETS`): ``kit`` (what
  ``python train.py`` runs, ``conf/algo/wcsac.yaml``: the IQN safety critic, κ on the larger of
  its start-state CVaR and the empirical CVaR_α of the last training episodes),
  ``gaussian`` (the kit's safety critic and κ options with the Gaussian critic: 10-step
  cost targets, κ on the tail statistic at episode start states, κ on the critic alone)
  and ``paper``
  (``PAPER_OPTIONS`` = ``algo=wcsac_paper``, ``WCSACLoss``'s own defaults). Its batch comes through the
  kit's pipeline, as the trainer builds it: collected trajectories →
  ``make_postproc(loss)`` (the n-step cost entries) → the replay rows the loss reads
  → a uniform sample → ``StartStateBuffer.attach`` (a start state per row) →
  ``EpisodeCostWindow.attach`` (the recent episodes' CVaR, ``kit``).

  - ``sac``: TorchRL's ``SACLoss`` + ``SoftUpdate`` with the kit's networks (what a
    TorchRL user runs); ``sac_polyak``: the same with the kit's ``PolyakUpdate``;
  - ``wcsac_<options>``: ``WCSACLoss`` as the trainer runs it (fused critics, direct
    sampling, ``PolyakUpdate``);
  - ``wcsac_<options>_general``: ``WCSACLoss`` through TorchRL's general paths
    (module calls, ``TanhNormal``, ``SoftUpdate``);
  - ``wcsac_kit_module_calls``: ``wcsac_kit`` with its twin read through TorchRL's
    vmapped call and its IQN critic through its module, as before 2cefd15 read them
    from their parameters (the same values bit for bit: the difference is the gain);
  - ``wcsac_kit_signal_every10``: ``wcsac_kit`` with ``kappa_signal_every=10`` (the
    critic's start-state tail read once in 10 updates and held in between; not the
    default: it changes κ's course);
  - ``wcsac_<options>_compiled``: under ``torch.compile`` (``--compile``);
  - ``sac_torchrl_nets`` / ``wcsac_<options>_torchrl_nets``: ``SACLoss`` and
    ``WCSACLoss`` with TorchRL's generic networks (``torchrl.modules.MLP``,
    ``ProbabilisticActor`` + ``TanhNormal``, ``ValueOperator``; a user's own
    networks; their safety critic is two MLPs, mean and softplus variance, under
    every option set): ``loss(td)`` + backward + Adam step + ``SoftUpdate``;
  - ``plain_wcsac_paper``: the plain-PyTorch update of ``plain_wcsac.py`` (the
    paper's loss with an MSE variance loss, no framework).

  "vs SAC" compares with ``sac`` (kit networks) or ``sac_torchrl_nets`` (TorchRL's
  networks). Sizes: ``--width`` (2 hidden layers), ``--batch``, obs 44, action 2
  (the paper's: 2 × 256, batch 256);
* StaticEnv steps/s (raw gymnasium and TorchRL-wrapped), collector frames/s (4
  envs in one BatchedGymEnv, random policy) and, per option set, end-to-end training
  frames/s of WCSAC at the paper's UTD 0.25 against 4 × that loss's update rate (the
  ceiling when collection, replay and logging cost nothing) (``--no-loop`` skips it).

``--json PATH`` also writes every figure as JSON (``tests/test_benchmarks.py`` reads it).
Like training (``retain_freed_memory: true``), the process first asks glibc's malloc
to keep freed memory for reuse; ``--default-malloc`` measures without that.
"""

from __future__ import annotations

import argparse
import csv
import functools
import json
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torchrl.data import Bounded
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate

sys.path.insert(0, str(Path(__file__).resolve().parent))

from plain_wcsac import PlainWCSAC, batch_inputs

from wcsac_rl import WCSACLoss, compose_config
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PolyakUpdate, StartStateBuffer, loss_parts
from wcsac_rl.objectives.inputs import collected_keys
from wcsac_rl.options import SafetyOptions
from wcsac_rl.training.builders import (
    adam,
    episode_window,
    make_postproc,
    safety_critic_kwargs,
)
from wcsac_rl.training.config import safety_options
from wcsac_rl.training.runtime import retain_freed_memory

OBS, ACT = 44, 2
CONFIG_OVERRIDES = {
    "kit": ("algo=wcsac",),
    "gaussian": (  # wcsac.yaml's critic and κ reads, its training-safety choices undone
        "algo=wcsac",
        "algo.safety_critic=gaussian",
        "algo.variance_loss=glm",
        "algo.variance_target=td",
        "algo.kappa_signal=critic",
        "algo.kappa_episode_window=30",
        "algo.kappa_lr_scale=1.0",
        "algo.alpha_init=1.0",
        "algo.actor_lr=null",
    ),
    "paper": ("algo=wcsac_paper",),
}
"""The option sets each ``WCSACLoss`` variant is timed at (``--options``), as the config
composes them: ``kit`` is ``python train.py``'s default, ``gaussian`` its safety critic
and κ reads with the Gaussian critic, ``paper`` ``PAPER_OPTIONS`` (``SafetyOptions``' and
the loss's own defaults). The end-to-end loop runs these configs."""
OPTION_SETS = tuple(CONFIG_OVERRIDES)


@dataclass(frozen=True)
class OptionSet:
    """One option set: the safety options and the loss keywords the trainer adds."""

    options: SafetyOptions
    extra: dict = field(default_factory=dict)

    def replace(self, **changes) -> OptionSet:
        """These options with ``changes`` (e.g. ``safety_critic="gaussian"``)."""
        return OptionSet(replace(self.options, **changes), self.extra)

    def loss_kwargs(self) -> dict:
        """``WCSACLoss``'s keywords, as ``make_loss`` passes them."""
        return {**loss_parts(self.options), **self.extra}


@functools.cache
def option_set(name: str) -> OptionSet:
    """The options of :data:`CONFIG_OVERRIDES` ``name``, as the trainer reads them from
    the composed config (``tests/test_benchmarks.py`` pins ``paper`` to ``SafetyOptions()``,
    the paper's)."""
    if name not in CONFIG_OVERRIDES:
        raise KeyError(f"unknown option set {name!r}; one of {OPTION_SETS}")
    algo = compose_config(*CONFIG_OVERRIDES[name]).algo
    return OptionSet(safety_options(algo), {"alpha_init": float(algo.alpha_init)})


@dataclass(frozen=True)
class Sizes:
    batch: int = 256
    width: int = 256
    obs: int = OBS
    act: int = ACT


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
        while count == 0 or time.perf_counter() - start < seconds:
            torch.mm(a, b)
            count += 1
        out[name] = 2 * m * k * n * count / (time.perf_counter() - start) / 1e9
    return out


# ------------------------------------------------------------------ batches
def trajectories(sizes: Sizes, *, envs: int = 4, episode_steps: int = 50) -> TensorDict:
    """Collector-shaped data ``[envs, T]``: random transitions in ``episode_steps``-step
    episodes (``step_count`` marks their starts; a few end by termination), cost 1
    with probability 0.1, and the running ``episode_cost`` the kit's envs write.
    ``T`` gives at least twice ``sizes.batch`` rows."""
    g = torch.Generator().manual_seed(0)
    steps = max(2 * episode_steps, -(-2 * sizes.batch // envs))
    shape = (envs, steps)
    step_count = (torch.arange(steps) % episode_steps).expand(shape).clone()
    truncated = step_count == episode_steps - 1
    terminated = torch.rand(shape, generator=g) < 0.005
    cost = torch.bernoulli(torch.full(shape, 0.1), generator=g)
    # the cost since each episode's start (a terminated row ends its episode early)
    episode_cost = cost.clone()
    for t in range(1, steps):
        fresh = (step_count[:, t] == 0) | terminated[:, t - 1]
        episode_cost[:, t] += torch.where(fresh, 0.0, episode_cost[:, t - 1])
    return TensorDict(
        {
            "observation": torch.randn(*shape, sizes.obs, generator=g),
            "action": torch.rand(*shape, sizes.act, generator=g) * 2 - 1,
            "step_count": step_count.unsqueeze(-1),
            "next": {
                "observation": torch.randn(*shape, sizes.obs, generator=g),
                "reward": torch.randn(*shape, 1, generator=g),
                "cost": cost.unsqueeze(-1),
                "episode_cost": episode_cost.unsqueeze(-1),
                "step_count": (step_count + 1).unsqueeze(-1),
                "done": (terminated | truncated).unsqueeze(-1),
                "terminated": terminated.unsqueeze(-1),
            },
        },
        list(shape),
    )


def pipeline_batch(loss, sizes: Sizes, options: SafetyOptions | None = None) -> TensorDictBase:
    """A replay batch for ``loss`` built as the trainer builds it (``OffPolicyTrainer.learn``
    and ``.sample``): the collector postproc (n-step cost entries), the rows the loss
    reads, a uniform sample, a start state per row for ``kappa_states="initial"`` and,
    where κ reads the episodes (``kappa_signal`` not ``"critic"``), the CVaR of the
    trainer's ``EpisodeCostWindow`` for ``options`` (``builders.episode_window``) over
    the trajectories' finished episodes."""
    traj = trajectories(sizes)
    postproc = make_postproc(loss)
    if postproc is not None:
        traj = postproc(traj)
    rows = traj.reshape(-1).select(*sorted(collected_keys(loss), key=str))
    index = torch.randint(len(rows), (sizes.batch,), generator=torch.Generator().manual_seed(1))
    batch = rows[index]
    if getattr(loss, "kappa_states", "replay") == "initial":
        starts = StartStateBuffer.for_loss(loss)
        starts.add_starts(traj)
        torch.manual_seed(2)
        batch = starts.attach(batch)
    if getattr(loss, "kappa_signal", "critic") != "critic":
        if options is None:
            raise ValueError(
                f"kappa_signal={loss.kappa_signal} reads an episode-cost window: "
                "pass options= (the SafetyOptions that size it)"
            )
        episodes = episode_window(options, loss)
        if not episodes.add_episodes(traj.reshape(-1)):
            raise RuntimeError("the benchmark's trajectories finished no episode")
        batch = episodes.attach(batch)
    return batch


# ------------------------------------------------------------------ networks
def kit_networks(sizes: Sizes, **critic):
    """The kit's networks (``make_actor`` / ``make_qvalue`` / ``make_safety_critic``;
    ``critic``: the last one's keywords, ``builders.safety_critic_kwargs``)."""
    spec = Bounded(-1.0, 1.0, shape=(sizes.act,))
    w = sizes.width
    actor = make_actor(sizes.obs, spec, width=w)
    qvalues = [make_qvalue(sizes.obs, sizes.act, width=w) for _ in range(2)]
    safety = make_safety_critic(sizes.obs, sizes.act, width=w, **critic)
    return actor, qvalues, safety


def kit_loss(
    name: str, sizes: Sizes, changes: dict | None = None, **kwargs
) -> tuple[WCSACLoss, TensorDictBase]:
    """``WCSACLoss`` at option set ``name`` (``changes``: options replaced in it) with the
    kit's networks as the trainer builds them, and its pipeline batch (``kwargs``: the
    loss's other keywords, e.g. ``fast_paths=False``)."""
    options = option_set(name).replace(**(changes or {}))
    critic = safety_critic_kwargs(options.options)
    loss = WCSACLoss(*kit_networks(sizes, **critic), **options.loss_kwargs(), **kwargs)
    return loss, pipeline_batch(loss, sizes, options.options)


def torchrl_networks(sizes: Sizes):
    """A TorchRL user's own networks: ``torchrl.modules.MLP``, a ``ProbabilisticActor``
    with ``TanhNormal``, one ``ValueOperator`` (the loss makes the twins) and a safety
    critic of two MLPs (mean, softplus variance)."""
    spec = Bounded(-1.0, 1.0, shape=(sizes.act,))
    cells = [sizes.width, sizes.width]

    def mlp(in_features: int, out_features: int) -> MLP:
        return MLP(in_features=in_features, out_features=out_features, num_cells=cells)

    actor = ProbabilisticActor(
        TensorDictModule(
            nn.Sequential(mlp(sizes.obs, 2 * sizes.act), NormalParamExtractor()),
            in_keys=["observation"],
            out_keys=["loc", "scale"],
        ),
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
    )
    sa = sizes.obs + sizes.act
    qvalue = ValueOperator(mlp(sa, 1), in_keys=["observation", "action"])
    safety = TensorDictSequential(
        TensorDictModule(mlp(sa, 1), in_keys=["observation", "action"], out_keys=["cost_value"]),
        TensorDictModule(
            _Softplus(mlp(sa, 1)), in_keys=["observation", "action"], out_keys=["cost_variance"]
        ),
    )
    return actor, qvalue, safety


class _Softplus(nn.Module):
    """``softplus(net(*inputs))``: a positive output (the variance head)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return nn.functional.softplus(self.net(*inputs))


# ------------------------------------------------------------------ variants
@dataclass
class Variant:
    label: str
    update: Callable[[TensorDictBase], None]
    batch: TensorDictBase
    options: str | None  # an OPTION_SETS key, or None (SAC)
    baseline: str  # the SAC variant it is compared with
    flop_updates: int = 1  # FLOPs per update: the mean over this many (a held κ signal: k)


def through_module_calls(loss: WCSACLoss) -> WCSACLoss:
    """``loss`` reading its unfused twin through TorchRL's vmapped call and its IQN
    critic through its module, as before they were read from their parameters
    (2cefd15): the same values, bit for bit (``tests/test_fast_paths.py``), so the
    difference in rate is what those reads saved."""
    loss.critics.read_through_modules()
    return loss


def torchrl_update_fn(loss, *, updater_class=PolyakUpdate, compile_loss: bool = False):
    """``loss(td)`` + backward of the summed ``loss_*`` terms + Adam step + target update."""
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


def plain_update_fn(plain: PlainWCSAC):
    def update(batch):
        plain.update(*batch_inputs(batch))

    return update


def build_variants(
    sizes: Sizes, option_sets: list[str], with_compile: bool = False
) -> dict[str, Variant]:
    torch.manual_seed(0)
    variants: dict[str, Variant] = {}

    def add(name, label, loss, options, baseline, batch=None, **kwargs):
        safety = None if options is None else option_set(options).options
        loss_batch = pipeline_batch(loss, sizes, safety) if batch is None else batch
        update = torchrl_update_fn(loss, **kwargs)
        flop_updates = getattr(loss, "kappa_signal_every", 1)
        variants[name] = Variant(label, update, loss_batch, options, baseline, flop_updates)

    def sac(networks):
        actor, qvalues, _ = networks
        return SACLoss(actor, qvalues, loss_function="l2")

    add("sac", "TorchRL SACLoss", sac(kit_networks(sizes)), None, "sac", updater_class=SoftUpdate)
    add("sac_polyak", "SACLoss, PolyakUpdate", sac(kit_networks(sizes)), None, "sac")
    add(
        "sac_torchrl_nets",
        "SACLoss, TorchRL networks",
        SACLoss(*torchrl_networks(sizes)[:2], num_qvalue_nets=2, loss_function="l2"),
        None,
        "sac_torchrl_nets",
        updater_class=SoftUpdate,
    )
    for options in option_sets:
        name = f"wcsac_{options}"
        loss, batch = kit_loss(options, sizes)
        add(name, f"WCSACLoss [{options}]", loss, options, "sac", batch)
        if options == "kit":  # the same update before the critics were read directly
            slow, batch = kit_loss(options, sizes)
            add(
                f"{name}_module_calls",
                f"WCSACLoss [{options}], critics through vmap and module calls",
                through_module_calls(slow),
                options,
                "sac",
                batch,
            )
        if options == "kit":  # κ's start-state tail read once in 10 updates
            held, batch = kit_loss(options, sizes, {"kappa_signal_every": 10})
            add(
                f"{name}_signal_every10",
                f"WCSACLoss [{options}], κ's start-state tail every 10 updates",
                held,
                options,
                "sac",
                batch,
            )
        general, batch = kit_loss(options, sizes, fast_paths=False)
        add(
            f"{name}_general",
            f"WCSACLoss [{options}], general paths",
            general,
            options,
            "sac",
            batch,
            updater_class=SoftUpdate,
        )
        if with_compile:
            compiled, batch = kit_loss(options, sizes)
            add(
                f"{name}_compiled",
                f"WCSACLoss [{options}], compiled",
                compiled,
                options,
                "sac",
                batch,
                compile_loss=True,
            )
        actor, qvalue, safety = torchrl_networks(sizes)
        user = option_set(options).replace(safety_critic="gaussian").loss_kwargs()
        add(
            f"{name}_torchrl_nets",
            f"WCSACLoss [{options}], TorchRL networks",
            WCSACLoss(actor, qvalue, safety, num_qvalue_nets=2, **user),
            options,
            "sac_torchrl_nets",
            updater_class=SoftUpdate,
        )
    if "paper" in option_sets:
        plain = PlainWCSAC(sizes.obs, sizes.act, width=sizes.width)
        variants["plain_wcsac_paper"] = Variant(
            "plain PyTorch WCSAC [paper, mse]",
            plain_update_fn(plain),
            kit_loss("paper", sizes)[1],
            "paper",
            "sac",
        )
    return variants


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


def flops_per_update(update, batch, updates: int = 1) -> float:
    """Matrix-product FLOPs of one update, the mean over ``updates`` of them (an update
    that reads κ's start-state tail once in k does its work in k)."""
    with _MatmulFlops() as counter:
        for _ in range(updates):
            update(batch)
    return float(counter.flops) / updates


def time_variants(
    variants: dict[str, Variant], rounds: int, updates: int, warmup: int = 3
) -> dict[str, float]:
    """Median updates/s of each variant over ``rounds`` interleaved rounds."""
    for name, v in variants.items():  # warm-up (and compilation)
        start = time.perf_counter()
        for _ in range(warmup):
            v.update(v.batch)
        print(f"  warm-up {name}: {time.perf_counter() - start:.1f}s", flush=True)
    rates: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, v in variants.items():
            start = time.perf_counter()
            for _ in range(updates):
                v.update(v.batch)
            rates[name].append(updates / (time.perf_counter() - start))
    return {name: statistics.median(r) for name, r in rates.items()}


# ------------------------------------------------------------------ the loop
def _last_full_epoch(progress_csv: Path, epoch_frames: int) -> dict[str, str]:
    """The last ``progress.csv`` row of a whole epoch with updates in it."""
    with progress_csv.open() as f:
        rows = [
            row
            for row in csv.DictReader(f)
            if row.get("time/ups")
            and float(row["time/ups"]) > 0
            and int(float(row["frames"])) % epoch_frames == 0
        ]
    if not rows:
        raise RuntimeError(f"{progress_csv}: no whole epoch with updates; raise --loop-frames")
    return rows[-1]


def env_rows(env: str, steps: int) -> list[dict]:
    """Raw / wrapped steps/s of ``env`` and collector frames/s (4 envs, random actions)."""
    from bench_envs import raw_steps_per_second, torchrl_steps_per_second
    from torchrl.collectors import Collector

    from wcsac_rl.envs import make_env

    rows = [
        {"what": f"{env} raw gymnasium steps/s", "value": raw_steps_per_second(env, steps)},
        {"what": f"{env} TorchRL-wrapped steps/s", "value": torchrl_steps_per_second(env, steps)},
    ]
    frames_per_batch = max(4, steps // 8 * 4)
    collector = Collector(
        make_env(env, seed=0, num_workers=4, parallel=False),
        None,
        frames_per_batch=frames_per_batch,
        total_frames=frames_per_batch * 4,
    )
    start = time.perf_counter()
    frames = sum(batch.numel() for batch in collector)
    rows.append(
        {
            "what": "collector frames/s (4 envs, BatchedGymEnv, random policy)",
            "value": frames / (time.perf_counter() - start),
        }
    )
    collector.shutdown()
    return rows


def training_loop(
    options: str, sizes: Sizes, env: str, frames: int, threads: int, retained: bool
) -> dict:
    """Frames/s and updates/s of a short training run at option set ``options``
    (:data:`CONFIG_OVERRIDES`), from its last whole epoch (400-frame batches, UTD 0.25)."""
    from wcsac_rl.training import make_trainer

    epoch_frames = max(400, (frames // 2) // 400 * 400)
    cfg = compose_config(
        *CONFIG_OVERRIDES[options],
        f"env={env}",
        f"total_frames={frames}",
        f"epoch_frames={epoch_frames}",
        "algo.collector.init_random_frames=400",
        f"algo.batch_size={sizes.batch}",
        f"algo.network.width={sizes.width}",
        "eval_episodes=0",
        "progress_bar=false",
        "logger=none",
        f"threads={threads}",
        f"retain_freed_memory={str(retained).lower()}",
    )
    with tempfile.TemporaryDirectory() as tmp:
        trainer = make_trainer(cfg, Path(tmp) / "run")
        try:
            trainer.run()
        finally:
            trainer.close()
        row = _last_full_epoch(Path(tmp) / "run" / "progress.csv", epoch_frames)
    return {"options": options, "fps": float(row["time/fps"]), "ups": float(row["time/ups"])}


# ------------------------------------------------------------------ main
def add_timing_arguments(parser: argparse.ArgumentParser) -> None:
    """The options every update benchmark shares: threads, interleaved rounds of timed
    updates after untimed warm-up ones, and the sizes (batch, hidden width)."""
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--updates", type=int, default=20, help="updates per round")
    parser.add_argument("--warmup", type=int, default=3, help="untimed updates per variant")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--width", type=int, default=256, help="hidden units (2 layers)")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_timing_arguments(parser)
    parser.add_argument("--options", nargs="+", choices=OPTION_SETS, default=list(OPTION_SETS))
    parser.add_argument(
        "--variants",
        nargs="+",
        metavar="NAME",
        help="time only these variants (and the SAC rows they are compared with); "
        "default: every one",
    )
    parser.add_argument("--peak-seconds", type=float, default=1.0, help="per matmul size")
    parser.add_argument(
        "--compile", action="store_true", help="also time WCSACLoss under torch.compile"
    )
    parser.add_argument(
        "--no-loop", action="store_true", help="skip the env / collector / training part"
    )
    parser.add_argument("--env", default="static", help="env preset of the loop part")
    parser.add_argument("--env-steps", type=int, default=3000, help="steps per env measurement")
    parser.add_argument("--loop-frames", type=int, default=8400, help="frames per training run")
    parser.add_argument(
        "--default-malloc",
        action="store_true",
        help="keep glibc's default malloc thresholds (training retains freed memory)",
    )
    parser.add_argument("--json", type=Path, help="also write the figures here as JSON")
    args = parser.parse_args(argv)
    for name in ("threads", "rounds", "updates", "batch", "width", "env_steps", "loop_frames"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be at least 1")
    torch.set_num_threads(args.threads)
    retained = not args.default_malloc and retain_freed_memory()
    sizes = Sizes(batch=args.batch, width=args.width)
    print(
        f"torch {torch.__version__}, {args.threads} thread(s), "
        f"malloc {'retains freed memory' if retained else 'defaults'}, "
        f"batch {sizes.batch}, 2 x {sizes.width} MLPs, obs {sizes.obs}, action {sizes.act}"
    )

    peaks = matmul_peak_gflops(args.peak_seconds)
    peak = max(peaks.values())
    print("\nfp32 matmul GFLOP/s:")
    for name, value in peaks.items():
        print(f"  {name:<28} {value:8.1f}")

    variants = build_variants(sizes, args.options, args.compile)
    if args.variants:
        unknown = sorted(set(args.variants) - set(variants))
        if unknown:
            parser.error(
                f"--variants: unknown {', '.join(unknown)} (with --options "
                f"{' '.join(args.options)}: {', '.join(variants)})"
            )
        keep = set(args.variants) | {variants[name].baseline for name in args.variants}
        variants = {name: v for name, v in variants.items() if name in keep}
    flops = {
        name: flops_per_update(v.update, v.batch, v.flop_updates) for name, v in variants.items()
    }
    rates = time_variants(variants, args.rounds, args.updates, args.warmup)
    print(f"\nupdates/s (median of {args.rounds} interleaved rounds of {args.updates} updates):")
    print(
        f"  {'variant':<40} {'updates/s':>10} {'vs SAC':>7} {'GFLOP/upd':>10} "
        f"{'GFLOP/s':>8} {'of peak':>8}"
    )
    update_rows = []
    for name, rate in rates.items():
        v = variants[name]
        gflops = flops[name] / 1e9
        row = {
            "name": name,
            "label": v.label,
            "options": v.options,
            "updates_per_s": rate,
            "vs_sac": rate / rates[v.baseline],
            "baseline": v.baseline,
            "gflop_per_update": gflops,
            "gflop_per_s": gflops * rate,
            "of_peak": gflops * rate / peak,
        }
        update_rows.append(row)
        print(
            f"  {name:<40} {rate:10.1f} {row['vs_sac']:7.2f} {gflops:10.3f} "
            f"{row['gflop_per_s']:8.1f} {row['of_peak']:8.0%}"
        )

    loop_rows: list[dict] = []
    if not args.no_loop:
        print("\nenvironment and loop:")
        for row in env_rows(args.env, args.env_steps):
            loop_rows.append(row)
            print(f"  {row['what']:<60} {row['value']:,.0f}")
        for options in args.options:  # the training runs are eager
            run = training_loop(
                options, sizes, args.env, args.loop_frames, args.threads, bool(retained)
            )
            isolated = rates.get(f"wcsac_{options}")  # (not timed when --variants omits it)
            run["of_ceiling"] = run["fps"] / (4 * isolated) if isolated else None
            loop_rows.append({"what": f"end-to-end WCSAC [{options}] frames/s", **run})
            ceiling = (
                f" = {run['of_ceiling']:.0%} of 4 x its isolated updates/s" if isolated else ""
            )
            print(
                f"  {'end-to-end WCSAC [' + options + '] frames/s (UTD 0.25)':<60} "
                f"{run['fps']:,.1f} ({run['ups']:.1f} updates/s){ceiling}"
            )
    result = {
        "torch": torch.__version__,
        "threads": args.threads,
        "sizes": sizes.__dict__,
        "matmul_peak_gflops": peaks,
        "updates": update_rows,
        "loop": loop_rows,
    }
    bad = [
        key
        for rows in (update_rows, loop_rows)
        for row in rows
        for key, value in row.items()
        if isinstance(value, float) and not math.isfinite(value)
    ]
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    if bad:
        raise SystemExit(f"non-finite figures: {bad}")
    return result


if __name__ == "__main__":
    main()
