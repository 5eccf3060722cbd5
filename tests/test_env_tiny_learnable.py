"""The tiny env is learnable in a few thousand steps (plain TorchRL SAC, no wcsac_rl loss)."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate

from wcsac_rl.envs import make_env


class _QNet(nn.Module):
    def __init__(self):
        super().__init__()
        self.mlp = MLP(in_features=8, out_features=1, num_cells=[64, 64])

    def forward(self, observation, action):
        return self.mlp(torch.cat([observation, action], -1))


@pytest.mark.slow
def test_sac_reaches_the_goal_after_3000_steps():
    torch.manual_seed(0)
    env = make_env("tiny", seed=0)
    actor = ProbabilisticActor(
        TensorDictModule(
            nn.Sequential(
                MLP(in_features=6, out_features=4, num_cells=[64, 64]), NormalParamExtractor()
            ),
            in_keys=["observation"],
            out_keys=["loc", "scale"],
        ),
        in_keys=["loc", "scale"],
        spec=env.action_spec,
        distribution_class=TanhNormal,
        return_log_prob=True,
    )
    qvalue = ValueOperator(_QNet(), in_keys=["observation", "action"])
    loss = SACLoss(actor, qvalue, num_qvalue_nets=2, alpha_init=0.2)
    loss.make_value_estimator(gamma=0.99)
    target_update = SoftUpdate(loss, eps=0.995)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-3)
    collector = Collector(
        env,
        actor,
        frames_per_batch=50,
        total_frames=3000,
        init_random_frames=500,
        auto_register_policy_transforms=False,
    )
    buffer = ReplayBuffer(storage=LazyTensorStorage(3000), batch_size=128)
    frames = 0
    for batch in collector:
        buffer.extend(batch.reshape(-1))
        frames += batch.numel()
        if frames >= 500:
            for _ in range(50):
                out = loss(buffer.sample())
                (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()
                optim.step()
                optim.zero_grad()
                target_update.step()
        collector.update_policy_weights_()
    collector.shutdown()

    eval_env = make_env("tiny", seed=123)
    reached, returns = 0, 0.0
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in range(10):
            td = eval_env.rollout(100, actor)
            reached += int(td["next", "goal_reached"].any())
            returns += td["next", "episode_reward"][-1].item()
    assert reached >= 8
    assert returns / 10 > 2.0  # ≈ 1.9 progress + 1.0 bonus; a random policy gets ≈ 0
