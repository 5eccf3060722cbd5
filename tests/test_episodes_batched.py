"""Test episodes run side by side give the episodes of one unbatched env per sub-env."""

from __future__ import annotations

from unittest.mock import MagicMock

import pytest
import torch
from _env_helpers import count_steps, tiny_goal_seeker
from tensordict.nn import TensorDictModule
from torchrl.data import Bounded

from wcsac_rl.envs import make_env
from wcsac_rl.modules import make_actor
from wcsac_rl.rollouts.episodes import run_episodes


def _policy(name: str):
    """A deterministic policy computed row by row, so batching cannot change its floats.

    (A batched matrix product may round differently from a single-row one, and the
    point-goal dynamics amplify a 1e-7 action difference into visibly different
    returns within tens of steps.)
    """
    if name == "tiny":  # episodes end
        return tiny_goal_seeker()
    obs_dim = make_env(name).observation_spec["observation"].shape[-1]
    torch.manual_seed(0)
    net = make_actor(obs_dim, Bounded(-1.0, 1.0, shape=(2,)), width=16).module[0].module

    def mean_action(obs):
        rows = obs.reshape(-1, obs.shape[-1])
        return torch.stack([torch.tanh(net(row)[0]) for row in rows]).reshape(*obs.shape[:-1], 2)

    return TensorDictModule(mean_action, in_keys=["observation"], out_keys=["action"])


@pytest.mark.parametrize(
    ("name", "steps"), [("tiny", 60), ("static", 40)], ids=["terminating", "truncated"]
)
def test_side_by_side_episodes_equal_one_env_per_sub_env(name, steps):
    actor = _policy(name)
    batched = make_env(name, seed=3, num_workers=4, parallel=False, max_episode_steps=steps)
    # 6 episodes from 4 sub-envs: a round of 4, then a round of 2
    side_by_side = run_episodes(batched, actor, 6, max_steps=steps)
    reference = []
    for i in range(4):
        single = make_env(name, seed=3 + i, max_episode_steps=steps)
        reference += run_episodes(single, actor, 1, max_steps=steps)
    assert len(side_by_side) == 6
    for got, want in zip(side_by_side[:4], reference):
        assert got.length == want.length
        assert got.goal_reached == want.goal_reached
        assert got.numerical_failure == want.numerical_failure
        # the same float32 rewards summed in float64 by both (≤ 60 × 2⁻⁵³ relative to
        # Σ|r|); 1e-6 is far above that and far below one step's reward
        assert got.ret == pytest.approx(want.ret, rel=1e-6, abs=1e-6)
        assert got.cost == pytest.approx(want.cost, rel=1e-6, abs=1e-6)
    if name == "tiny":  # the terminating task really ends episodes, at different times
        assert all(r.goal_reached == 1 and r.length < steps for r in side_by_side)
        assert len({r.length for r in side_by_side}) > 1
    else:
        assert {r.length for r in side_by_side} == {steps}


def test_random_policy_and_callbacks_work_side_by_side():
    env = make_env("tiny", seed=0, num_workers=3, parallel=False, max_episode_steps=30)
    seen = []
    results = run_episodes(env, None, 3, deterministic=False, max_steps=30, on_episode=seen.append)
    assert seen == results and len(results) == 3
    assert all(1 <= r.length <= 30 for r in results)


def test_max_steps_cuts_episodes_alike_and_deep_batches_are_refused():
    batched = make_env("static", seed=0, num_workers=2, parallel=False, max_episode_steps=50)
    cut = run_episodes(batched, None, 2, max_steps=10)
    single = run_episodes(make_env("static", seed=0, max_episode_steps=50), None, 1, max_steps=10)
    assert [r.length for r in cut] == [10, 10] == [single[0].length] * 2
    deep = MagicMock(batch_size=torch.Size([2, 2]))
    with pytest.raises(ValueError, match="one batch dimension"):
        run_episodes(deep, None, 1)


def test_finished_sub_envs_are_not_stepped_while_the_others_finish():
    env = make_env("tiny", seed=3, num_workers=4, parallel=False, max_episode_steps=60)
    stepped = count_steps(env.base_env.envs)
    results = run_episodes(env, _policy("tiny"), 4, max_steps=60)
    assert len({r.length for r in results}) > 1
    assert stepped == [r.length for r in results]
