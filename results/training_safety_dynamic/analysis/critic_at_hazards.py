"""What a DynamicEnv run's safety critic reads where its policy stays inside a hazard.

A study script of results/training_safety_dynamic/ (RESULTS.md, "Why test episodes stay
in a hazard"), not part of the kit. It needs a run directory with its checkpoint and the
replay buffer saved with it (``save_replay_buffer=true``; the study's
``experiment=training_safety_dynamic`` does), run from the repository root:

    python results/training_safety_dynamic/analysis/critic_at_hazards.py stuck RUN
    python results/training_safety_dynamic/analysis/critic_at_hazards.py replay RUN
    python results/training_safety_dynamic/analysis/critic_at_hazards.py refit RUN \
        --kind iqn --n-steps 50 --updates 10000

* ``stuck``: deterministic test episodes of the final policy; for each stretch of at
  least ``--min-stretch`` consecutive steps inside a hazard, the critic's Q^c and Γ_α at
  the state (policy's action) against the steps of cost still to come in the episode.
* ``replay``: the trained critic's Q^c at every replay transition that cost something,
  by when it was collected (50 k-frame brackets), against its stored n-step cost.
* ``refit``: a fresh safety critic of ``--kind`` fitted offline on the same replay (the
  run's actor fixed, uniform batches of 256, Adam at the run's lr, Polyak 0.005), with
  the n-step entries recomputed for ``--n-steps`` inside the collector's per-env
  segments exactly as ``NStepCost`` computes them (checked against the stored entries
  for the run's own n and γ_c); Q^c at the cost steps by age every 2 500 updates.
"""

from __future__ import annotations

import argparse
import itertools
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from wcsac_rl.evaluation.run_calibration import load_safety_run
from wcsac_rl.training import builders
from wcsac_rl.training.trainer import env_max_episode_steps


def _replay(run: Path) -> tuple[TensorDict, int]:
    buffers = sorted((run / "checkpoints").glob("buffers-*"))
    if not buffers:
        raise SystemExit(f"{run}: no saved replay buffer (train with save_replay_buffer=true)")
    storage = TensorDict.load_memmap(buffers[-1] / "replay_buffer" / "storage")
    filled = int(buffers[-1].name.split("-")[1])
    return storage, min(filled, storage.shape[0])


def _brackets(filled: int, width: int = 50_000) -> list[tuple[int, int]]:
    return list(itertools.pairwise([*range(0, filled, width), filled]))


def _rounded(values: torch.Tensor) -> list[float]:
    return [round(float(v), 2) for v in values.reshape(-1)]


def stuck(args: argparse.Namespace) -> None:
    _, env, policy, loss, frames = load_safety_run(args.run, seed=args.seed)
    print(f"{args.run}: {frames} frames, kappa {float(loss.kappa):.3f}")
    grid = torch.linspace(-1.0, 1.0, 21)
    actions = torch.stack(torch.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    stretches = 0
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        for episode in range(args.episodes):
            td = env.rollout(1000, policy, break_when_any_done=True)
            cost = td["next", "cost"].reshape(-1).numpy()
            inside = np.nonzero(cost > 0)[0]
            if len(inside) < args.min_stretch:
                continue
            runs = np.split(inside, np.nonzero(np.diff(inside) != 1)[0] + 1)
            for run in (r for r in runs if len(r) >= args.min_stretch):
                stretches += 1
                at = torch.as_tensor([run[0], run[len(run) // 2]])
                est = loss.safety_estimates(td[at])
                to_go = [float(cost[t:].sum()) for t in at.tolist()]
                # the middle step's state under every action of a 21 x 21 grid
                middle = td[int(at[1])].expand(len(actions)).clone()
                middle["action"] = actions
                cvar = loss.safety_estimates(middle)["cvar"].reshape(-1)
                print(
                    f"episode {episode}: {len(run)} steps inside from step {run[0]}; "
                    f"Q^c {_rounded(est['cost_value'])}, Gamma {_rounded(est['cvar'])} "
                    f"against {to_go} cost to come (at its first and middle step); "
                    f"Gamma over all actions at the middle step "
                    f"{float(cvar.min()):.2f}..{float(cvar.max()):.2f}"
                )
    print(f"{stretches} stretches of >= {args.min_stretch} steps in {args.episodes} episodes")


def replay(args: argparse.Namespace) -> None:
    _, env, _, loss, _ = load_safety_run(args.run, seed=args.seed)
    env.close()
    storage, filled = _replay(Path(args.run))
    cost = storage["next", "cost"][:filled].reshape(-1).numpy()
    where = np.nonzero(cost > 0)[0]
    print(f"{filled} transitions, {len(where)} with a cost")
    for lo, hi in _brackets(filled):
        rows = torch.as_tensor(where[(where >= lo) & (where < hi)])
        if len(rows) == 0:
            continue
        batch = storage[rows]
        qc = loss.safety_estimates(batch)["cost_value"].reshape(-1).numpy()
        nstep = batch["nstep", "cost"].reshape(-1).numpy()
        print(
            f"[{lo // 1000:4d} k, {hi // 1000:4d} k): {len(rows):5d} cost steps, Q^c median "
            f"{np.median(qc):6.2f} (share < 1: {np.mean(qc < 1):.2f}), n-step cost {nstep.mean():.2f}"
        )


def _nstep_entries(storage: TensorDict, filled: int, n: int, gamma: float, segment: int):
    """``NStepCost``'s entries for ``n`` over the stored rows: each collector batch is
    ``segment`` consecutive rows per env, and a lookahead stops at its end or a done."""
    cost = storage["next", "cost"][:filled].reshape(-1).double().numpy()
    done = storage["next", "done"][:filled].reshape(-1).numpy()
    terminated = storage["next", "terminated"][:filled].reshape(-1).numpy()
    rows = np.arange(filled)
    to_done = np.empty(filled, np.int64)  # steps to the first done at or after a row, +1
    nearest = None
    for i in range(filled - 1, -1, -1):
        if i % segment == segment - 1:
            nearest = None
        if done[i]:
            nearest = i
        to_done[i] = filled if nearest is None else nearest - i + 1
    steps = np.minimum(np.minimum(n, segment - rows % segment), to_done)
    discounted = np.zeros(filled)
    for k in range(n):
        live = steps > k
        discounted[live] += gamma**k * cost[rows[live] + k]
    end = rows + steps - 1
    return {
        "steps": torch.as_tensor(steps),
        "cost": torch.as_tensor(discounted, dtype=torch.float32),
        "done": torch.as_tensor(done[end]),
        "terminated": torch.as_tensor(terminated[end]),
    }


def refit(args: argparse.Namespace) -> None:
    torch.manual_seed(args.seed)
    cfg, env, _, trained, _ = load_safety_run(args.run, seed=args.seed)
    overrides = [f"algo.safety_critic={args.kind}"]
    if args.n_steps is not None:
        overrides.append(f"algo.cost_n_steps={args.n_steps}")
    cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(overrides + args.override))
    loss = builders.make_loss(cfg, builders.make_agent(cfg, env), env_max_episode_steps(cfg))
    loss.actor_network_params.data.update_(trained.actor_network_params.data)
    storage, filled = _replay(Path(args.run))
    collector = cfg.algo.collector
    segment = int(collector.frames_per_batch) // int(collector.num_envs)
    entries = _nstep_entries(
        storage, filled, int(cfg.algo.cost_n_steps), float(cfg.algo.cost_gamma), segment
    )
    own = (int(trained.cost_n_steps), float(trained.cost_gamma))
    if (int(cfg.algo.cost_n_steps), float(cfg.algo.cost_gamma)) == own:
        stored = storage["nstep"][:filled]
        same = torch.equal(entries["steps"], stored["steps"].reshape(-1)) and torch.equal(
            entries["cost"], stored["cost"].reshape(-1).float()
        )
        print(f"n-step entries recomputed for the run's own n and γ_c equal the stored: {same}")

    def batch(rows: torch.Tensor) -> TensorDict:
        out = storage[rows].clone()
        nstep = out["nstep"]
        for key, value in entries.items():
            nstep[key] = value[rows].reshape(nstep[key].shape)
        ahead = (rows + entries["steps"][rows] - 1) % storage.shape[0]
        nstep["observation"] = storage["next", "observation"][ahead]
        return out

    cost = storage["next", "cost"][:filled].reshape(-1).numpy()
    where = np.nonzero(cost > 0)[0]
    free = np.random.default_rng(1).choice(np.nonzero(cost == 0)[0], 4000, replace=False)
    brackets = [
        (0, filled - 100_000),
        (filled - 100_000, filled - 50_000),
        (filled - 50_000, filled),
    ]

    def report(update: int) -> None:
        loss.eval()
        medians = []
        for lo, hi in brackets:
            rows = torch.as_tensor(where[(where >= lo) & (where < hi)])
            medians.append(float(loss.safety_estimates(batch(rows))["cost_value"].median()))
        cost_free = float(loss.safety_estimates(batch(torch.as_tensor(free)))["cost_value"].mean())
        loss.train()
        print(
            f"{args.kind} n={cfg.algo.cost_n_steps} {' '.join(args.override)} update {update:6d}: "
            f"Q^c median at the cost steps, by age {[round(m, 2) for m in medians]}, "
            f"mean at cost-free steps {cost_free:.2f}",
            flush=True,
        )

    params = list(loss.safety_network_params.values(True, True))
    targets = list(loss.target_safety_network_params.values(True, True))
    optimizer = torch.optim.Adam(params, lr=float(cfg.algo.lr))
    generator = torch.Generator().manual_seed(args.seed)
    loss.train()
    for update in range(args.updates + 1):
        if update % 2500 == 0 or update == args.updates:
            report(update)
        if update == args.updates:
            break
        terms = loss.safety_loss(batch(torch.randint(0, filled, (256,), generator=generator)))
        total = terms[0] if terms[1] is None else terms[0] + terms[1]
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        with torch.no_grad():
            for param, target in zip(params, targets):
                target.lerp_(param, 0.005)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=("stuck", "replay", "refit"))
    parser.add_argument("run", help="a run directory with its checkpoint and saved replay")
    parser.add_argument("--seed", type=int, default=2_000_003, help="test env / refit seed")
    parser.add_argument("--episodes", type=int, default=60)
    parser.add_argument("--min-stretch", type=int, default=60)
    parser.add_argument("--kind", choices=("iqn", "gaussian"), default="iqn")
    parser.add_argument("--n-steps", type=int, default=None)
    parser.add_argument("--updates", type=int, default=10_000)
    parser.add_argument("override", nargs="*", help="more config overrides for refit")
    args = parser.parse_intermixed_args()
    torch.set_num_threads(1)
    {"stuck": stuck, "replay": replay, "refit": refit}[args.mode](args)


if __name__ == "__main__":
    main()
