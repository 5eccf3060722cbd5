"""The constraint's signal and the cost target on their own: what κ reads where, under
which threshold, and what the safety critic's TD target is made of."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from wcsac_rl.modules import make_safety_critic
from wcsac_rl.objectives import WCSACLoss, gaussian_mixture_cvar, per_step_cost_threshold
from wcsac_rl.objectives.constraint import ConstraintSignal
from wcsac_rl.objectives.critics import CriticValues
from wcsac_rl.objectives.safety_head import CostTarget, GaussianHead, SafetyValues


def _signal(**options) -> ConstraintSignal:
    keys = WCSACLoss.default_keys()
    head = GaussianHead(
        make_safety_critic(3, 1, width=8), keys, risk_level=0.1, nonnegative_cost=False
    )
    return ConstraintSignal(head, keys, **options)


def test_signal_combines_the_critic_and_the_episodes_with_nan_falling_back():
    statistic = torch.tensor([10.0, 10.0, 10.0])
    batch = TensorDict({"episode_cvar": torch.tensor([[20.0], [4.0], [math.nan]])}, [3])
    assert _signal(states="initial").signal(batch, statistic) is statistic
    torch.testing.assert_close(
        _signal(states="initial", signal="max").signal(batch, statistic),
        torch.tensor([20.0, 10.0, 10.0]),
    )
    torch.testing.assert_close(
        _signal(states="initial", signal="episodes").signal(batch, statistic),
        torch.tensor([20.0, 4.0, 10.0]),
    )
    # no critic statistic yet (the actor's own actions): nothing to combine
    assert _signal(states="initial", signal="max").signal(batch, None) is None
    with pytest.raises(KeyError, match="EpisodeCostWindow"):
        _signal(states="initial", signal="max").signal(TensorDict({}, [3]), statistic)


def test_statistic_is_the_per_state_gamma_or_the_mixture_tail():
    values = SafetyValues(torch.tensor([0.0, 1.0, 5.0]), torch.tensor([1.0, 4.0, 0.25]))
    mean = _signal(statistic="mean")
    torch.testing.assert_close(mean.statistic(values), mean.head.cvar(values))
    tail = _signal(statistic="tail").statistic(values)
    expected = gaussian_mixture_cvar(values.mean, values.variance, 0.1)
    torch.testing.assert_close(tail, expected.expand(3))
    # the tail of the mixture is above the mean of the per-state CVaRs
    assert float(tail[0]) > float(mean.statistic(values).mean())
    leaf = SafetyValues(values.mean.clone().requires_grad_(), values.variance)
    assert not _signal(statistic="tail").statistic(leaf).requires_grad


def test_critic_values_are_read_where_the_options_say():
    replay = CriticValues(torch.zeros(2, 4), SafetyValues(torch.ones(4)))
    at_start = CriticValues(torch.zeros(2, 4), SafetyValues(torch.full((4,), 7.0)))
    seen = []

    def at_policy(states):
        seen.append(states)
        return at_start

    starts = TensorDict({"observation": torch.randn(4, 3)}, [4])
    batch = TensorDict({"initial": starts}, [4])
    assert _signal(states="initial").critic_values(batch, replay, at_policy) is at_start
    assert seen and torch.equal(seen[0]["observation"], starts["observation"])
    assert _signal(states="replay", actions="replay").critic_values(batch, replay, at_policy) is (
        replay
    )
    assert _signal(states="replay", actions="policy").critic_values(batch, replay, at_policy) is (
        None
    )
    assert len(seen) == 1
    with pytest.raises(KeyError, match="start states"):
        _signal(states="initial").critic_values(TensorDict({}, [4]), replay, at_policy)


def test_threshold_is_d_at_start_states_and_per_step_at_replay_states():
    assert _signal(states="initial").threshold(15.0, 0.99, 1000) == 15.0
    assert _signal(states="replay").threshold(15.0, 0.99, 1000) == pytest.approx(
        per_step_cost_threshold(15.0, 0.99, 1000)
    )
    assert _signal(states="replay", actions="replay").needs_replay_values
    assert not _signal(states="initial", actions="replay").needs_replay_values


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"states": "start"}, "kappa_states must be one of"),
        ({"actions": "mean"}, "kappa_actions must be one of"),
        ({"statistic": "max"}, "kappa_statistic must be one of"),
        ({"signal": "both"}, "kappa_signal must be one of"),
        ({"states": "replay", "signal": "max"}, "episodic limit"),
    ],
)
def test_bad_signal_options_are_refused_by_name(options, message):
    with pytest.raises(ValueError, match=message):
        _signal(**options)


# ---------------------------------------------------------------- cost target
def _steps(done, terminated, nstep=None):
    n = len(done)
    td = {
        "next": {
            "cost": torch.arange(1.0, n + 1).unsqueeze(-1),
            "done": torch.tensor(done).unsqueeze(-1),
            "terminated": torch.tensor(terminated).unsqueeze(-1),
        }
    }
    if nstep is not None:
        td["nstep"] = nstep
    return TensorDict(td, [n])


@pytest.mark.parametrize("bootstrap_truncated", [None, True, False])
def test_one_step_target_stops_at_terminations_and_by_default_at_time_limits(
    bootstrap_truncated,
):
    target = CostTarget(
        WCSACLoss.default_keys(), gamma=1.0, n_steps=1, bootstrap_truncated=bootstrap_truncated
    )
    target.set_reward_gamma(0.99)
    # row 1 is truncated by the time limit, row 2 terminated
    batch = _steps([False, True, True], [False, False, True])
    marker = SafetyValues(torch.full((3,), 5.0))
    cost, gamma, alive, at = target.bootstrap(batch, torch.tensor(1.0), marker, None)
    torch.testing.assert_close(cost, torch.tensor([1.0, 2.0, 3.0]))
    assert at is marker and float(gamma) == 1.0
    expected = [1.0, 1.0, 0.0] if bootstrap_truncated else [1.0, 0.0, 0.0]
    torch.testing.assert_close(alive, torch.tensor(expected))
    assert target.bootstrap_truncated is bool(bootstrap_truncated)


def test_nstep_target_reads_the_nstep_entries_and_bootstraps_where_they_end():
    target = CostTarget(WCSACLoss.default_keys(), gamma=0.5, n_steps=3)
    nstep = TensorDict(
        {
            "observation": torch.randn(2, 3),
            "cost": torch.tensor([[1.5], [0.0]]),
            "steps": torch.tensor([[3], [1]]),
            "terminated": torch.tensor([[False], [True]]),
            "done": torch.tensor([[False], [True]]),
        },
        [2],
    )
    batch = _steps([False, False], [False, False], nstep)
    ahead = SafetyValues(torch.ones(2))
    seen = []

    def read_ahead(states):
        seen.append(states)
        return ahead

    cost, gamma, alive, at = target.bootstrap(batch, torch.tensor(0.5), None, read_ahead)
    assert at is ahead and torch.equal(seen[0]["observation"], nstep["observation"])
    torch.testing.assert_close(cost, torch.tensor([1.5, 0.0]))
    torch.testing.assert_close(gamma, torch.tensor([0.125, 0.5]))  # γ_c^m
    torch.testing.assert_close(alive, torch.tensor([1.0, 0.0]))
    assert ("nstep", "observation") in target.in_keys(["observation"])
    with pytest.raises(KeyError, match="NStepCost"):
        target.bootstrap(batch.exclude("nstep"), torch.tensor(0.5), None, read_ahead)


def test_cost_target_discount_follows_the_reward_unless_given_and_checks_its_input():
    follows = CostTarget(WCSACLoss.default_keys(), gamma=None, n_steps=1)
    follows.set_reward_gamma(0.9)
    assert follows.gamma == 0.9 and follows.bootstrap_truncated  # γ_c < 1
    assert CostTarget(WCSACLoss.default_keys(), gamma=1.0).bootstrap_truncated is False
    with pytest.raises(KeyError, match="per-step cost"):
        follows.cost(TensorDict({"next": {}}, [2]), torch.float32)
    with pytest.raises(ValueError, match="has shape"):
        follows.cost(TensorDict({"next": {"cost": torch.zeros(2, 3)}}, [2]), torch.float32)
    for bad, message in (
        ({"gamma": 1.5}, r"cost_gamma must be null or in \[0, 1\] \(a number\), got 1.5"),
        ({"n_steps": 0}, "cost_n_steps must be an integer"),
    ):
        with pytest.raises(ValueError, match=message):
            CostTarget(WCSACLoss.default_keys(), **bad)
