"""WCSAC on gymnasium's Pendulum in a TorchRL user's own SAC loop.

TorchRL's SAC example flow — env, collector, replay buffer, ``SACLoss``, ``SoftUpdate``,
one optimizer — with ``SACLoss`` swapped for ``WCSACLoss`` and a made-up cost: 1 at every
step where the pendulum spins faster than ``speed_limit`` rad/s. What the swap adds
(marked ``# WCSAC`` below, each line or block): the cost transform, a safety critic (the
kit's IQN one), the kit's recipe (``**loss_parts(KIT_OPTIONS)``), ``NStepCost`` as the
collector's postproc, a ``StartStateBuffer`` and an ``EpisodeCostWindow`` (the recipe reads
n-step cost targets, episode start states and the recent episodes' cost; the loss's
defaults, the paper's WCSAC, need none of them), the optimizer's parameter groups (κ at
its own learning rate) and the episodes' cost in the log.

Each iteration collects one 200-step episode (Pendulum's time limit) and prints its
return and cost; the last line is a verdict: whether the policy's last episodes return
more than the random warm-up's best, and whether their cost is within the limit d.

    python examples/pendulum_wcsac.py --frames 20000
"""

from __future__ import annotations

import argparse

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer, Unbounded
from torchrl.envs import GymEnv, RewardSum, StepCounter, Transform, TransformedEnv
from torchrl.objectives import SoftUpdate

from wcsac_rl import WCSACLoss, make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import (
    KIT_OPTIONS,
    EpisodeCostWindow,
    NStepCost,
    StartStateBuffer,
    loss_parts,
    param_groups,
)


class SpeedCost(Transform):  # WCSAC: the made-up cost, ("next", "cost") = 1 above the limit
    """``cost = 1`` where the pendulum's angular speed ``|θ̇|`` exceeds ``speed_limit``."""

    def __init__(self, speed_limit: float = 4.0) -> None:
        super().__init__(in_keys=["observation"], out_keys=["cost"])
        self.speed_limit = speed_limit

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        speed = next_tensordict.get("observation")[..., 2:3].abs()
        return next_tensordict.set("cost", (speed > self.speed_limit).to(torch.float32))

    def _reset(self, tensordict, tensordict_reset):
        return tensordict_reset

    def transform_reward_spec(self, reward_spec):
        reward_spec["cost"] = Unbounded(shape=(*reward_spec.shape, 1), dtype=torch.float32)
        return reward_spec


EPISODE_STEPS = 200  # Pendulum-v1's time limit: one episode per iteration
COST_LIMIT = 20.0  # WCSAC: d, fast steps allowed per episode


def make_env(seed: int) -> TransformedEnv:
    env = TransformedEnv(GymEnv("Pendulum-v1"), StepCounter())
    env.append_transform(SpeedCost())  # WCSAC
    env.append_transform(RewardSum(in_keys=["reward", "cost"]))  # episode sums (+ cost: WCSAC)
    env.set_seed(seed)
    return env


def verdict(returns: list[float], random_episodes: int, costs: list[float] | None = None) -> str:
    """One line: is the mean return of the last quarter of the policy's episodes above
    the best of the first ``random_episodes`` (the warm-up's random actions), and (given
    ``costs``) is their mean cost within d?"""
    policy = len(returns) - random_episodes
    if random_episodes == 0 or policy <= 0:
        return "verdict: no episode of both the random warm-up and the policy; run more frames"
    k = max(1, policy // 4)
    best_random, last = max(returns[:random_episodes]), sum(returns[-k:]) / k
    line = (
        f"verdict: {'learned' if last > best_random else 'did not learn'} (mean return of "
        f"the last {k} episodes {last:.1f}, best of {random_episodes} random-action "
        f"episodes {best_random:.1f})"
    )
    if costs is not None:  # WCSAC: the last episodes' mean cost against d
        cost = sum(costs[-k:]) / k
        within = "within" if cost <= COST_LIMIT else "over"
        line += f", {within} the cost limit (their mean cost {cost:.1f}, d = {COST_LIMIT:g})"
    return line


def main(frames: int = 20_000, seed: int = 0, init_random_frames: int = 1_000) -> dict:
    torch.manual_seed(seed)
    env = make_env(seed)
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    actor = make_actor(obs_dim, env.action_spec_unbatched, width=64)
    loss = WCSACLoss(
        actor,
        [make_qvalue(obs_dim, act_dim, width=64) for _ in range(2)],
        make_safety_critic(obs_dim, act_dim, kind="iqn", width=64),  # WCSAC
        risk_level=0.5,  # WCSAC: α
        cost_limit=COST_LIMIT,  # WCSAC: d, fast steps per 200-step episode
        max_episode_steps=EPISODE_STEPS,  # WCSAC: the episodes' length
        **loss_parts(KIT_OPTIONS),  # WCSAC: the kit's recipe
    )
    loss.make_value_estimator(gamma=0.99)
    nstep = NStepCost.for_loss(loss)  # WCSAC
    starts = StartStateBuffer.for_loss(loss)  # WCSAC
    window = KIT_OPTIONS["kappa_episode_window"]  # WCSAC: κ also reads the last episodes
    episodes = EpisodeCostWindow.for_loss(loss, window=window)  # WCSAC
    updater = SoftUpdate(loss, tau=0.005)
    optim = torch.optim.Adam(param_groups(loss, lr=3e-4))  # WCSAC: κ's own group
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100_000), batch_size=128)
    collector = Collector(
        env,
        actor,
        frames_per_batch=EPISODE_STEPS,
        total_frames=frames,
        init_random_frames=init_random_frames,
        auto_register_policy_transforms=True,  # TorchRL appends the InitTracker it asks for
    )
    out, returns, frames_done, random_episodes = None, [], 0, 0
    costs = []  # WCSAC: each episode's cost
    for iteration, data in enumerate(collector, 1):
        buffer.extend(nstep(data).reshape(-1))  # WCSAC: nstep(...)
        starts.add_starts(data)  # WCSAC
        episodes.add_episodes(data)  # WCSAC
        frames_done += data.numel()
        done = data["next", "done"].squeeze(-1)
        returns += data["next", "episode_reward"][done].squeeze(-1).tolist()
        costs += data["next", "episode_cost"][done].squeeze(-1).tolist()  # WCSAC
        warm_up = frames_done - data.numel() < init_random_frames  # random actions
        random_episodes += int(done.sum()) if warm_up else 0
        episode = f"return {returns[-1]:8.1f}" if done.any() else "-"
        episode += f"  cost {costs[-1]:5.1f}" if done.any() else ""  # WCSAC
        note = "  (random actions)" if warm_up else ""
        print(f"iteration {iteration:3d}  frames {frames_done:6d}  {episode}{note}", flush=True)
        if len(buffer) < init_random_frames:
            continue
        for _ in range(50):
            out = loss(episodes.attach(starts.attach(buffer.sample())))  # WCSAC: attach(...)
            sum(v for k, v in out.items() if k.startswith("loss_")).backward()
            optim.step()
            optim.zero_grad()
            updater.step()
    collector.shutdown()
    stats = (
        {} if out is None else {k: float(v) for k, v in out.items() if not k.startswith("loss_")}
    )
    print({k: round(v, 3) for k, v in stats.items() if k in ("alpha", "kappa", "cvar")})
    stats["verdict"] = verdict(returns, random_episodes, costs)  # WCSAC: costs
    print(stats["verdict"])
    return {**stats, "returns": returns, "costs": costs}  # WCSAC: costs


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(args.frames, args.seed)
