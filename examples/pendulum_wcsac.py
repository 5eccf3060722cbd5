"""WCSAC on gymnasium's Pendulum in a TorchRL user's own SAC loop (issue 28).

TorchRL's SAC example flow — env, collector, replay buffer, ``SACLoss``, ``SoftUpdate``,
one optimizer — with ``SACLoss`` swapped for ``WCSACLoss`` and a made-up cost: 1 at every
step where the pendulum spins faster than ``speed_limit`` rad/s. What the swap adds
(marked ``# WCSAC`` below): the cost transform, a safety critic, ``NStepCost`` as the
collector's postproc and a ``StartStateBuffer`` (the loss's defaults read n-step cost
targets and episode start states; ``WCSACLoss(..., **PAPER_OPTIONS)`` needs neither) and
the optimizer's parameter groups (κ at its own learning rate).

    python examples/pendulum_wcsac.py --frames 20000
"""

from __future__ import annotations

import argparse

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer, Unbounded
from torchrl.envs import GymEnv, StepCounter, Transform, TransformedEnv
from torchrl.objectives import SoftUpdate

from wcsac_rl import WCSACLoss, make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import NStepCost, StartStateBuffer, param_groups


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


def make_env(seed: int) -> TransformedEnv:
    env = TransformedEnv(GymEnv("Pendulum-v1"), StepCounter())
    env.append_transform(SpeedCost())  # WCSAC
    env.set_seed(seed)
    return env


def main(frames: int = 20_000, seed: int = 0, init_random_frames: int = 1_000) -> dict:
    torch.manual_seed(seed)
    env = make_env(seed)
    obs_dim = env.observation_spec["observation"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    actor = make_actor(obs_dim, env.action_spec_unbatched, width=64)
    loss = WCSACLoss(
        actor,
        [make_qvalue(obs_dim, act_dim, width=64) for _ in range(2)],
        make_safety_critic(obs_dim, act_dim, width=64),  # WCSAC
        risk_level=0.5,  # WCSAC: α
        cost_limit=20.0,  # WCSAC: d, fast steps per 200-step episode
        max_episode_steps=200,
    )
    loss.make_value_estimator(gamma=0.99)
    nstep = NStepCost.for_loss(loss)  # WCSAC
    starts = StartStateBuffer.for_loss(loss)  # WCSAC
    updater = SoftUpdate(loss, tau=0.005)
    optim = torch.optim.Adam(param_groups(loss, lr=3e-4))  # WCSAC: κ's own group
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100_000), batch_size=128)
    collector = Collector(
        env,
        actor,
        frames_per_batch=100,
        total_frames=frames,
        init_random_frames=init_random_frames,
    )
    out = None
    for data in collector:
        buffer.extend(nstep(data).reshape(-1))  # WCSAC: nstep(...)
        starts.add_starts(data)  # WCSAC
        if len(buffer) < init_random_frames:
            continue
        for _ in range(25):
            out = loss(starts.attach(buffer.sample()))  # WCSAC: starts.attach(...)
            sum(v for k, v in out.items() if k.startswith("loss_")).backward()
            optim.step()
            optim.zero_grad()
            updater.step()
    collector.shutdown()
    return {} if out is None else {k: float(v) for k, v in out.items() if not k.startswith("loss_")}


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(main(args.frames, args.seed))
