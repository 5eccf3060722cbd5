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
  the n-step entries recomputed for ``--n-steps`` by the kit's ``NStepCost`` over the
  collector's batches as stored (checked against the stored entries for the run's own n
  and γ_c); Q^c at the cost steps by age every 2 500 updates.
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
from wcsac_rl.objectives.nstep import NStepCost
from wcsac_rl.training import builders
from wcsac_rl.training.trainer import env_max_episode_steps


def _replay(run: Path) -> tuple[TensorDict, int]:
    buffers = {int(p.name.split("-")[1]): p for p in (run / "checkpoints").glob("buffers-*")}
    if not buffers:
        raise SystemExit(f"{run}: no saved replay buffer (train with save_replay_buffer=true)")
    filled = max(buffers)  # the newest (by frames: "buffers-1000000" sorts before "-400000")
    storage = TensorDict.load_memmap(buffers[filled] / "replay_buffer" / "storage")
    return storage, min(filled, storage.shape[0])


def _cost_rows(storage: TensorDict, filled: int) -> tuple[np.ndarray, np.ndarray]:
    """The stored rows with a cost and those without."""
    cost = storage["next", "cost"][:filled].reshape(-1).numpy()
    return np.nonzero(cost > 0)[0], np.nonzero(cost == 0)[0]


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
    where, _ = _cost_rows(storage, filled)
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
    # the n-step entries of this n and γ_c, by the kit's own postproc over the collector's
    # batches: each is `segment` consecutive stored rows per env, its lookahead cut at the end
    collector = cfg.algo.collector
    segment = int(collector.frames_per_batch) // int(collector.num_envs)
    if filled % segment:
        raise SystemExit(f"{filled} stored rows are not whole batches of {segment} per env")
    steps = TensorDict({"next": storage["next"][:filled]}, [filled]).reshape(-1, segment)
    nstep = NStepCost.for_loss(loss)(steps)["nstep"].reshape(filled)
    own = (int(trained.cost_n_steps), float(trained.cost_gamma))
    if (loss.cost_n_steps, float(loss.cost_gamma)) == own:
        stored = storage["nstep"][:filled]
        same = all(torch.equal(nstep[key], stored[key]) for key in stored.keys())
        print(f"n-step entries recomputed for the run's own n and γ_c equal the stored: {same}")

    def batch(rows: torch.Tensor) -> TensorDict:
        out = storage[rows].clone()
        out["nstep"] = nstep[rows]
        return out

    where, free_rows = _cost_rows(storage, filled)
    free = np.random.default_rng(1).choice(free_rows, 4000, replace=False)
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
