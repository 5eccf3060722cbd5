"""``BatchedGymEnv`` gives exactly what one ``GymWrapper`` per sub-env gives."""

from __future__ import annotations

import functools

import gymnasium as gym
import pytest
import torch
from _env_helpers import count_steps, tiny_goal_seeker
from _tolerance import assert_close_f32
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

from wcsac_rl.envs import BatchedGymEnv, make_base_env, make_env, make_gym_env, step_info_spec

N = 3


def _batched(name: str, **kwargs) -> BatchedGymEnv:
    fn = functools.partial(make_gym_env, name, **kwargs)
    return BatchedGymEnv([fn] * N, info_spec=step_info_spec())


def _references(name: str, seed: int, **kwargs):
    refs = [make_base_env(name, **kwargs) for _ in range(N)]
    for i, ref in enumerate(refs):
        ref.set_seed(seed + i)
    return refs


@pytest.mark.parametrize("name", ["static", "dynamic", "tiny"])
def test_steps_and_resets_equal_one_gym_wrapper_per_env(name):
    # short episodes so that every sub-env ends (and is reset) several times
    env = _batched(name, max_episode_steps=7)
    env.set_seed(11)
    refs = _references(name, 11, max_episode_steps=7)
    for spec in ("full_observation_spec", "full_action_spec", "full_reward_spec", "full_done_spec"):
        ref_spec = getattr(refs[0], spec)
        assert getattr(env, spec) == ref_spec.expand(N, *ref_spec.shape), spec
    td = env.reset()
    ref_tds = [ref.reset() for ref in refs]
    g = torch.Generator().manual_seed(0)
    resets = 0
    for _ in range(25):
        action = torch.rand(N, 2, generator=g) * 2 - 1
        td.set("action", action)
        td = env.step(td)
        for i, ref in enumerate(refs):
            ref_td = ref.step(ref_tds[i].set("action", action[i]))
            for key in ref_td["next"].keys(True, True):
                torch.testing.assert_close(
                    td["next", key][i], ref_td["next", key], rtol=0, atol=0, msg=str(key)
                )
            ref_tds[i] = ref_td["next"].exclude("reward", "done", "terminated", "truncated")
            if ref_td["next", "done"].item():
                ref_tds[i] = ref.reset()
        done = td["next", "done"].clone()
        td = td["next"].exclude("reward", "done", "terminated", "truncated")
        if done.any():
            resets += int(done.sum())
            td.set("_reset", done)
            td = env.reset(td)
            for i in range(N):  # the reset envs start over like their references (same code)
                torch.testing.assert_close(
                    td["observation"][i], ref_tds[i]["observation"], rtol=0, atol=0
                )
    assert resets >= N * 3
    env.close()
    for ref in refs:
        ref.close()


def test_partial_reset_leaves_the_other_envs_where_they_are():
    env = _batched("static")
    env.set_seed(0)
    td = env.reset()
    td = env.step(td.set("action", torch.full((N, 2), 0.5)))["next"]
    before = td["observation"].clone()
    mask = torch.tensor([[False], [True], [False]])
    after = env.reset(td.clone().set("_reset", mask))
    torch.testing.assert_close(after["observation"][0], before[0], rtol=0, atol=0)  # untouched
    torch.testing.assert_close(after["observation"][2], before[2], rtol=0, atol=0)
    assert not torch.equal(after["observation"][1], before[1])
    env.close()


def test_make_env_serial_uses_it_with_the_episode_transforms_and_passes_spec_checks():
    env = make_env("dynamic", seed=3, num_workers=N, parallel=False)
    assert isinstance(env.base_env, BatchedGymEnv)
    check_env_specs(env, seed=3)
    collector = Collector(env, None, frames_per_batch=60, total_frames=120)
    batches = list(collector)
    collector.shutdown()
    assert [b.shape for b in batches] == [(N, 20), (N, 20)]
    first = batches[0]
    assert first["next", "cost"].shape == (N, 20, 1)
    assert first["next", "cost"].dtype == torch.float32
    # 20 steps into 1000-step episodes: the transforms' running sums and counters
    assert first["next", "step_count"].squeeze(-1).tolist() == [list(range(1, 21))] * N
    # running float32 sums of 20 steps against cumsum: ≤ 20 roundings of Σ|r|
    for key, signal in (("episode_reward", "reward"), ("episode_cost", "cost")):
        steps = first["next", signal].squeeze(-1)
        assert_close_f32(
            first["next", key].squeeze(-1),
            steps.cumsum(1),
            ops=20,
            magnitude=steps.abs().sum(1).max(),
            msg=key,
        )
    # distinct seeds per sub-env: distinct layouts
    layouts = env.reset()["goal_xy"]
    assert not torch.equal(layouts[0], layouts[1])
    env.close()


def test_same_seed_same_data():
    rollouts = []
    for _ in range(2):
        env = make_env("static", seed=7, num_workers=N, parallel=False)
        torch.manual_seed(0)
        rollouts.append(env.rollout(15, break_when_any_done=False))
        env.close()
    a, b = rollouts
    for key in a.keys(True, True):
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0, msg=str(key))


class _DictObservation(gym.ObservationWrapper):
    def __init__(self, env):
        super().__init__(env)
        space = env.observation_space
        self.observation_space = gym.spaces.Dict({"observation": space, "copy": space})

    def observation(self, observation):
        return {"observation": observation, "copy": observation}


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="at least one"):
        BatchedGymEnv([])
    with pytest.raises(ValueError, match="one flat Box observation"):
        BatchedGymEnv([lambda: _DictObservation(make_gym_env("tiny"))])
    env = _batched("tiny")
    env.reset()
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(TensorDict({"action": torch.full((N, 2), float("nan"))}, [N]))
    env.close()


def test_partial_steps_leave_finished_envs_alone():
    # goal-seeking actions on the tiny task: sub-envs reach the goal at different steps
    env = _batched("tiny", max_episode_steps=60)
    env.set_seed(1)
    stepped = count_steps(env.envs)
    td = env.rollout(60, tiny_goal_seeker(), break_when_all_done=True)
    done = td["next", "done"].squeeze(-1)
    first_done = [int(d.nonzero()[0]) + 1 for d in done]
    assert len(set(first_done)) > 1  # the sub-envs finished at different steps
    assert stepped == first_done  # and none was stepped after its episode ended
    env.close()
