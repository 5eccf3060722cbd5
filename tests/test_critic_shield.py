"""The collection-time shield (``algo.shield``): its action rule on critics whose reading
is known, the loss's reading Γ(s, a) it compares, and its wiring into training."""

from __future__ import annotations

import csv
import os
import signal

import pytest
import torch
from _loss_helpers import (
    ACT_DIM,
    OBS_DIM,
    flat_parts,
    linear_quantile_critic,
    make_batch,
    make_loss,
)
from _tolerance import assert_close_f32
from _training_helpers import compose_config
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import (
    CriticShield,
    TanhNormalPolicy,
    make_actor,
    make_qvalue,
    make_safety_critic,
)
from wcsac_rl.training import make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint
from wcsac_rl.training.off_policy import OffPolicyTrainer
from wcsac_rl.training.preemption import Preempted


def _policy(seed: int = 0) -> TanhNormalPolicy:
    torch.manual_seed(seed)
    return TanhNormalPolicy(make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=16))


def _states(rows: int = 64, seed: int = 1) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": torch.randn(rows, OBS_DIM, generator=g)}, [rows])


def _first_coordinate(states, actions):
    """A toy critic: Γ(s, a) = a₀ (the shield keeps the first action coordinate low)."""
    assert states.batch_size == actions.shape[:-1]
    return actions[..., 0]


def _expected(policy, states, candidates, threshold, seed):
    """The rule written out: the policy's action, the ``candidates − 1`` draws after it
    (the same random stream), then the first with a₀ <= threshold, else the lowest a₀."""
    torch.manual_seed(seed)
    td = policy(states.clone())
    actions = torch.cat([td["action"].unsqueeze(0), policy.draw(td, candidates - 1)])
    reading = actions[..., 0]
    expected, replaced = [], []
    for row in range(states.batch_size[0]):
        safe = [k for k in range(candidates) if reading[k, row] <= threshold]
        pick = safe[0] if safe else int(reading[:, row].argmin())
        expected.append(actions[pick, row])
        replaced.append(pick != 0)
    return torch.stack(expected), torch.tensor(replaced)


@pytest.mark.parametrize("threshold", [0.0, -0.5, -2.0])
def test_the_shield_keeps_a_safe_action_else_the_first_safe_candidate_else_the_least_unsafe(
    threshold,
):
    policy, states = _policy(), _states()
    shield = CriticShield(policy, _first_coordinate, threshold, candidates=6)
    expected, replaced = _expected(policy, states, 6, threshold, seed=3)
    torch.manual_seed(3)
    out = shield(states.clone())
    torch.testing.assert_close(out["action"], expected, rtol=0, atol=0)
    assert out["shielded"].shape == (64, 1)
    assert torch.equal(out["shielded"].squeeze(-1), replaced)
    assert replaced.any() and (~replaced).any()  # (some rows kept, some replaced)
    # never a worse reading than the policy's own action, and more rows under the threshold
    torch.manual_seed(3)
    alone = policy(states.clone())["action"][:, 0]
    assert (out["action"][:, 0] <= alone).all()
    assert (out["action"][:, 0] <= threshold).sum() >= (alone <= threshold).sum()
    assert (out["action"][replaced, 0] < alone[replaced]).all()


def test_where_every_action_is_safe_the_shield_is_the_policy_at_the_same_random_state():
    policy, states = _policy(), _states()
    torch.manual_seed(5)
    alone = policy(states.clone())
    shield = CriticShield(policy, _first_coordinate, threshold=1.0, candidates=4)
    torch.manual_seed(5)
    shielded = shield(states.clone())
    torch.testing.assert_close(shielded["action"], alone["action"], rtol=0, atol=0)
    assert not shielded["shielded"].any()


def test_test_episodes_play_the_policy_alone():
    calls = []

    def critic(states, actions):
        calls.append(actions.shape)
        return actions[..., 0]

    policy, states = _policy(), _states()
    shield = CriticShield(policy, critic, threshold=-2.0, candidates=4)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        out = shield(states.clone())
        alone = policy(states.clone())
    torch.testing.assert_close(out["action"], alone["action"], rtol=0, atol=0)
    assert "shielded" not in out.keys() and not calls


def test_the_threshold_is_read_at_every_step():
    level = [2.0]
    policy, states = _policy(), _states()
    shield = CriticShield(policy, _first_coordinate, lambda: level[0], candidates=4)
    assert not shield(states.clone())["shielded"].any()
    level[0] = -2.0
    assert shield(states.clone())["shielded"].any()


def test_a_batch_of_several_dimensions_keeps_its_shape():
    policy = _policy()
    states = TensorDict({"observation": torch.randn(3, 4, OBS_DIM)}, [3, 4])
    out = CriticShield(policy, _first_coordinate, -0.2, candidates=5)(states)
    assert out["action"].shape == (3, 4, ACT_DIM) and out["shielded"].shape == (3, 4, 1)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"candidates": 1}, ValueError, "candidates must be an integer >= 2"),
        ({"candidates": True}, ValueError, "candidates must be an integer >= 2"),
        ({"candidates": 2.5}, ValueError, "candidates must be an integer >= 2"),
        ({"threshold": float("nan")}, ValueError, "threshold must be a number, got nan"),
    ],
)
def test_bad_arguments_are_refused_by_name(kwargs, error, message):
    arguments = {"threshold": 0.0, "candidates": 4, **kwargs}
    with pytest.raises(error, match=message):
        CriticShield(_policy(), _first_coordinate, **arguments)


def test_a_policy_that_is_not_a_tanh_normal_policy_is_refused():
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=16)
    with pytest.raises(TypeError, match="filters a TanhNormalPolicy's actions, got"):
        CriticShield(actor, _first_coordinate, 0.0, candidates=4)


# ------------------------------------------------------------- the loss's reading
@pytest.mark.parametrize(
    "options",
    [
        {"kind": "gaussian"},
        {"kind": "gaussian", "variance": False},
        {"kind": "iqn"},
        {"kind": "gaussian", "num_safety_nets": 2},
    ],
    ids=["gaussian", "mean-only", "iqn", "ensemble"],
)
def test_action_cvar_is_the_critics_gamma_at_the_given_actions(options):
    if "num_safety_nets" in options:
        torch.manual_seed(0)
        loss = WCSACLoss(
            make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=32),
            [make_qvalue(OBS_DIM, ACT_DIM, width=32) for _ in range(2)],
            [make_safety_critic(OBS_DIM, ACT_DIM, width=32) for _ in range(2)],
            **flat_parts(num_safety_nets=2, risk_level=0.5),
        )
    else:
        loss = make_loss(**options)
    batch = make_batch(16)
    expected = loss.safety_estimates(batch)["cvar"]
    reading = loss.action_cvar(batch, batch["action"])
    assert reading.shape == (16,) and not reading.requires_grad
    assert_close_f32(reading, expected, ops=64)
    # K candidate actions per state, [K, B]: row k is the reading at the k-th actions
    actions = torch.rand(3, 16, ACT_DIM) * 2 - 1
    many = loss.action_cvar(batch.expand(3, 16), actions)
    assert many.shape == (3, 16)
    for k in range(3):
        batch_k = batch.clone()
        batch_k["action"] = actions[k]
        assert_close_f32(many[k], loss.safety_estimates(batch_k)["cvar"], ops=64)


def test_action_cvar_of_a_linear_quantile_critic_is_its_tail_mean_at_the_midpoints():
    """Z(s, a, τ) = o₀ + o₁τ: Γ = o₀ + o₁ × the mean of the tail strata's midpoints."""
    alpha, n = 0.2, 4
    torch.manual_seed(0)
    loss = WCSACLoss(
        make_actor(2, Bounded(-1.0, 1.0, shape=(1,)), width=8),
        [make_qvalue(2, 1, width=8) for _ in range(2)],
        linear_quantile_critic(),
        **flat_parts("iqn", risk_level=alpha, num_quantiles=n, nonnegative_cost=False),
    )
    obs = torch.tensor([[2.0, 1.0], [-1.0, 4.0], [3.0, -2.0]])
    reading = loss.action_cvar(TensorDict({"observation": obs}, [3]), torch.zeros(3, 1))
    tail = 1 - alpha + alpha * (torch.arange(n) + 0.5) / n
    assert_close_f32(reading, obs[:, 0] + obs[:, 1] * tail.mean(), ops=8)


# ------------------------------------------------------------------- in training
def _progress(run_dir):
    with open(run_dir / "progress.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_training_collects_through_the_shield_and_logs_its_rate(tmp_path):
    cfg = compose_config("env=tiny", "algo.shield.candidates=4", "algo.shield.scale=0.5")
    trainer = make_trainer(cfg, tmp_path / "run")
    shield = trainer.collection_policy
    assert isinstance(shield, CriticShield) and shield.candidates == 4
    assert trainer.collector.policy is shield
    assert type(trainer.policy) is TanhNormalPolicy  # the test episodes' policy
    # it reads the loss's critic, under half the loss's threshold (d = 15 at the defaults)
    assert shield.cvar == trainer.loss.action_cvar
    assert shield.threshold() == 0.5 * float(trainer.loss.cost_threshold) == 7.5
    # a reading every action fails: the least unsafe of 4 draws is taken, which is not
    # the policy's own (the first) in 3 of 4 steps
    shield.cvar = lambda states, actions: 100.0 + actions[..., 0]
    trainer.run()
    rows = _progress(tmp_path / "run")
    # epoch 1: one random warm-up batch (not counted) and one policy batch (200 steps)
    rates = [float(row["train/shielded"]) for row in rows]
    assert len(rates) == 2
    for rate in rates:
        assert 0.6 < rate < 0.9  # 3/4 ± 4.8 sd of 200 Bernoulli steps (the epochs have 200, 400)


def test_without_a_shield_the_collector_acts_with_the_policy_and_logs_no_rate(tmp_path):
    trainer = make_trainer(compose_config("env=tiny", "total_frames=400"), tmp_path / "run")
    assert trainer.collection_policy is None and trainer.collector.policy is trainer.policy
    trainer.run()
    assert "train/shielded" not in _progress(tmp_path / "run")[0]


class _StopsMidEpoch(OffPolicyTrainer):
    """A shielded run that sends itself SIGUSR1 at 600 frames (mid-epoch 2 of 400)."""

    def learn(self, batch):
        out = super().learn(batch)
        if self.tracker.frames == 600:
            os.kill(os.getpid(), signal.SIGUSR1)
        return out


def test_a_shielded_run_stopped_mid_epoch_continues_exactly(tmp_path):
    """The epoch's shield counts and the random stream it draws candidates from travel
    with the checkpoint: stopped at 600 frames and resumed, the run logs what an
    uninterrupted one does."""
    overrides = (
        "env=tiny",
        "algo.shield.candidates=4",
        "algo.shield.scale=0.5",
        "resume=auto",
        "save_replay_buffer=true",
        "total_frames=1200",
    )
    cfg = compose_config(*overrides)

    def reading(states, actions):  # every action fails: the least unsafe of 4 is taken
        return 100.0 + actions[..., 0]

    def run(cls, run_dir):
        trainer = cls(cfg, run_dir)
        trainer.collection_policy.cvar = reading
        try:
            trainer.run()
        finally:
            trainer.close()

    run(make_trainer, tmp_path / "whole")
    before = signal.signal(signal.SIGUSR1, lambda *_: None)
    try:
        with pytest.raises(Preempted):
            run(_StopsMidEpoch, tmp_path / "stopped")
    finally:
        signal.signal(signal.SIGUSR1, before)
    # the checkpoint holds epoch 2's first 200 policy steps
    saved = load_checkpoint(tmp_path / "stopped" / "checkpoints" / "last.pt")
    counts = saved["learner"]["shield"]
    assert counts["steps"] == 200 and 0 < counts["replaced"] < 200
    run(make_trainer, tmp_path / "stopped")
    # (the envs start new episodes on resume, so returns differ; the shield's flags do
    # not: with every action failing, a step is replaced unless the policy's own draw is
    # the lowest, which the restored random stream decides alone)
    whole, stopped = _progress(tmp_path / "whole"), _progress(tmp_path / "stopped")
    columns = ("frames", "train/shielded")
    assert [[row[c] for c in columns] for row in stopped] == [
        [row[c] for c in columns] for row in whole
    ]
    assert 0.6 < float(whole[1]["train/shielded"]) < 0.9
