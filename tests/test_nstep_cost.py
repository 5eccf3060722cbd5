"""n-step cost entries (NStepCost) and the safety critic's n-step targets."""

from __future__ import annotations

import pytest
import torch
from _loss_helpers import make_batch, make_loss
from _tolerance import assert_close_f32
from tensordict import TensorDict

from wcsac_rl.objectives import NStepCost


def _trajectories(envs: int = 3, steps: int = 12, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    done = torch.rand(envs, steps, 1, generator=g) < 0.2
    truncated = done & (torch.rand(envs, steps, 1, generator=g) < 0.5)
    return TensorDict(
        {
            "observation": torch.randn(envs, steps, 4, generator=g),
            "next": {
                "observation": torch.randn(envs, steps, 4, generator=g),
                "cost": torch.bernoulli(torch.full((envs, steps, 1), 0.4), generator=g),
                "done": done,
                "terminated": done & ~truncated,
            },
        },
        [envs, steps],
    )


def _brute_force(td: TensorDict, n: int, gamma: float):
    """The n-step entries by walking each trajectory step by step."""
    envs, steps = td.shape
    nxt = td["next"]
    cost = torch.zeros(envs, steps)
    count = torch.zeros(envs, steps, dtype=torch.int64)
    obs = torch.zeros(envs, steps, 4)
    term = torch.zeros(envs, steps, dtype=torch.bool)
    ended = torch.zeros(envs, steps, dtype=torch.bool)
    for e in range(envs):
        for t in range(steps):
            k = 0
            while True:
                cost[e, t] += gamma**k * nxt["cost"][e, t + k, 0]
                k += 1
                last = t + k - 1
                if k == n or t + k == steps or nxt["done"][e, last, 0]:
                    break
            count[e, t] = k
            obs[e, t] = nxt["observation"][e, last]
            term[e, t] = nxt["terminated"][e, last, 0]
            ended[e, t] = nxt["done"][e, last, 0]
    return cost, count, obs, term, ended


@pytest.mark.parametrize("n", [1, 2, 5, 20])
def test_nstep_entries_equal_a_step_by_step_walk_of_each_trajectory(n):
    td = _trajectories()
    out = NStepCost(n, gamma=0.9)(td.clone())["nstep"]
    cost, count, obs, term, ended = _brute_force(td, n, 0.9)
    # the walk adds ≤ 20 float32 terms γ^k c ≤ 1 to partial sums ≤ Σ 0.9^k = 10 (one
    # rounding each); NStepCost sums in float64 and rounds once
    assert_close_f32(out["cost"].squeeze(-1), cost, ops=21, magnitude=10.0)
    assert torch.equal(out["steps"], count)
    assert torch.equal(out["observation"], obs)
    assert torch.equal(out["terminated"].squeeze(-1), term)
    assert torch.equal(out["done"].squeeze(-1), ended)
    assert (ended & ~term).any()  # the data have truncations to tell apart


def test_a_padded_piece_ends_at_its_last_kept_step():
    """TorchRL's ``split_trajs`` pads each piece after its last step and marks the padding
    in ``("collector", "mask")``: the kept steps' entries are those of the piece cut
    there (the padding's costs and states never enter them)."""
    td = _trajectories()
    lengths = [12, 5, 8]  # (cut in the middle of an episode: the lookahead must stop)
    assert not td["next", "done"][[1, 2], [4, 7]].any()
    mask = torch.zeros(td.shape, dtype=torch.bool)
    for env, length in enumerate(lengths):
        mask[env, :length] = True
    padded = td.clone()
    padded["next", "cost"][~mask] = 1e6
    padded["next", "observation"][~mask] = 1e6
    padded["collector", "mask"] = mask
    got = NStepCost(5, gamma=0.9)(padded)["nstep"]
    for env, length in enumerate(lengths):
        alone = NStepCost(5, gamma=0.9)(td[env : env + 1, :length].clone())["nstep"]
        for key in ("cost", "steps", "observation", "terminated", "done"):
            assert torch.equal(got[key][env : env + 1, :length], alone[key]), (env, key)


def _with_step_count(td: TensorDict) -> TensorDict:
    """``td`` with the ``step_count`` its episodes give (0 at each start)."""
    done = td["next", "done"].squeeze(-1)
    count = torch.zeros(td.shape, dtype=torch.int64)
    for t in range(1, td.shape[-1]):
        count[:, t] = torch.where(done[:, t - 1], 0, count[:, t - 1] + 1)
    td["step_count"] = count.unsqueeze(-1)
    return td


def test_a_time_major_batch_is_refused_or_read_along_its_named_time_dimension():
    """A ``[time, envs]`` batch would sum costs across envs: refused in one line where its
    ``step_count`` shows it; read along time where the time dimension is named (TorchRL's
    ``"time"``), giving the entries of the same batch laid out ``[envs, time]``."""
    env_major = _with_step_count(_trajectories())
    expected = NStepCost(3, gamma=0.9)(env_major.clone())["nstep"]
    time_major = env_major.transpose(0, 1).contiguous()
    with pytest.raises(ValueError) as err:
        NStepCost(3, gamma=0.9)(time_major.clone())
    assert "last dimension is not time" in str(err.value) and "\n" not in str(err.value)
    named = time_major.clone()
    named.refine_names("time", None)
    got = NStepCost(3, gamma=0.9)(named)["nstep"]
    for key in ("cost", "steps", "observation", "terminated", "done"):
        assert torch.equal(got[key], expected[key].transpose(0, 1)), key
    # the env-major batch with its step_count passes the check, unchanged
    assert torch.equal(
        expected["steps"], NStepCost(3, gamma=0.9)(_trajectories())["nstep"]["steps"]
    )


def test_one_step_entries_are_the_transition_itself():
    td = _trajectories()
    out = NStepCost(1, gamma=0.5)(td.clone())["nstep"]
    assert torch.equal(out["cost"], td["next", "cost"])
    assert torch.equal(out["observation"], td["next", "observation"])
    assert bool((out["steps"] == 1).all())


@pytest.mark.parametrize(
    ("kwargs", "message"), [({"n_steps": 0}, "n_steps"), ({"gamma": 1.5}, "gamma")]
)
def test_bad_arguments_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        NStepCost(**{"n_steps": 3, "gamma": 0.9, **kwargs})


def test_for_loss_follows_keys_the_loss_is_given_after_it():
    """``NStepCost.for_loss(loss)`` built before ``loss.set_keys(...)`` reads the new keys
    (from the loss at each call), not the ones of the moment it was built."""
    loss = make_loss(cost_n_steps=3)
    nstep = NStepCost.for_loss(loss)
    assert (nstep.n_steps, nstep.gamma) == (3, loss.cost_gamma)
    td = _trajectories(seed=4)
    renamed = _trajectories(seed=5)  # other costs and flags under the new names
    for old, new in (("cost", "my_cost"), ("done", "my_done"), ("terminated", "my_term")):
        td["next", new] = renamed["next", old]
    td["next", "observation"] = renamed["next", "observation"]
    loss.set_keys(cost="my_cost", done="my_done", terminated="my_term", nstep="ahead")
    assert (nstep.cost_key, nstep.out_key) == ("my_cost", "ahead")
    out = nstep(td.clone())
    assert "nstep" not in out.keys()
    expected = NStepCost(3, loss.cost_gamma)(renamed.clone())["nstep"]
    assert (out["ahead"] == expected).all()
    with pytest.raises(AttributeError, match=r"loss\.set_keys\(cost=\.\.\.\)"):
        nstep.cost_key = "other"
    own = NStepCost(3, 0.9, cost_key="c")  # an NStepCost built on its own keeps its keys
    own.cost_key = "c2"
    assert own.cost_key == "c2" and own.out_key == "nstep"


def test_loss_bootstraps_the_safety_critic_from_the_nstep_state():
    torch.manual_seed(0)
    loss = make_loss(cost_n_steps=3, variance_target="td")
    loss.make_value_estimator(gamma=0.8)
    batch = NStepCost(3, gamma=0.8)(_trajectories(envs=1, steps=16).squeeze(0).unsqueeze(0))
    batch = batch.reshape(-1)
    batch["observation"] = torch.randn(16, 5)  # the loss's critics read 5-dim observations
    batch["next", "observation"] = torch.randn(16, 5)
    batch["nstep", "observation"] = torch.randn(16, 5)
    batch["action"] = torch.rand(16, 2) * 2 - 1
    batch["next", "reward"] = torch.zeros(16, 1)
    assert ("nstep", "cost") in loss.in_keys and ("nstep", "observation") in loss.in_keys
    torch.manual_seed(1)
    targets = loss.compute_targets(batch)
    # the same draws: a' ~ π(s') for the reward target, then a_m ~ π(s_{t+m}) for the cost
    torch.manual_seed(1)
    loss._sample_policy(batch["next"])
    action_m, _ = loss._sample_policy(batch["nstep"])
    with torch.no_grad():
        qc, vc, *_ = loss.safety_head.values(
            batch["nstep"], loss.target_safety_network_params, action_m
        )
    steps = batch["nstep", "steps"].float()
    alive = (~batch["nstep", "terminated"].squeeze(-1)).float()
    discount = 0.8**steps
    expected = batch["nstep", "cost"].squeeze(-1) + discount * alive * qc
    torch.testing.assert_close(targets["cost_target"], expected)
    torch.testing.assert_close(targets["cost_next_variance"], discount**2 * alive * vc)
    with pytest.raises(KeyError, match="NStepCost"):
        loss.compute_targets(batch.exclude("nstep"))


@pytest.mark.parametrize("n_steps", [1, 3])
@pytest.mark.parametrize("bootstrap", [None, True, False])
def test_safety_targets_stop_at_time_limits_unless_told_to_bootstrap(n_steps, bootstrap):
    """γ_c = 1: by default the cost sum ends where the episode ends, truncations included;
    ``cost_bootstrap_truncated=True`` bootstraps across them (only terminations stop)."""
    torch.manual_seed(0)
    loss = make_loss(
        cost_n_steps=n_steps,
        variance_target="td",
        cost_gamma=1.0,
        cost_bootstrap_truncated=bootstrap,
    )
    assert loss.cost_bootstrap_truncated is bool(bootstrap)
    batch = NStepCost(n_steps, gamma=1.0)(_trajectories(envs=1, steps=16, seed=3))
    batch = batch.reshape(-1)
    for key in ("observation", ("next", "observation"), ("nstep", "observation")):
        batch[key] = torch.randn(16, 5)
    batch["action"] = torch.rand(16, 2) * 2 - 1
    batch["next", "reward"] = torch.zeros(16, 1)
    torch.manual_seed(1)
    targets = loss.compute_targets(batch)
    torch.manual_seed(1)
    # the reward target's a' ~ π(s'); the n-step target draws a_m ~ π(s_{t+m}) after it
    action = loss._sample_policy(batch["next"])[0]
    ahead = batch["nstep"] if n_steps > 1 else batch["next"]
    if n_steps > 1:
        action = loss._sample_policy(ahead)[0]
    ahead = ahead.clone().set("action", action)
    with torch.no_grad():
        qc = loss.safety_head.values(ahead, loss.target_safety_network_params).mean
    ends = batch["nstep", "terminated" if bootstrap else "done"].squeeze(-1)
    assert (batch["nstep", "done"] & ~batch["nstep", "terminated"]).any()  # truncations
    expected = batch["nstep", "cost"].squeeze(-1) + (~ends).float() * qc
    torch.testing.assert_close(targets["cost_target"], expected)


def test_nonnegative_cost_clamps_q_where_it_is_used_not_where_it_is_fitted():
    torch.manual_seed(0)
    loss = make_loss(risk_level=0.1, nonnegative_cost=True)
    value = torch.tensor([-2.0, 0.5])
    variance = torch.tensor([4.0, 4.0])
    torch.testing.assert_close(
        loss.cvar(value, variance), torch.tensor([0.0, 0.5]) + loss.cvar_multiplier * 2.0
    )
    # the regression still sees the raw prediction: a negative Q^c gets a gradient
    batch = make_batch()
    with torch.no_grad():  # Q^c ≡ −3 for the online and the target mean network
        for params in (loss.safety_network_params, loss.target_safety_network_params):
            for p in params["module", "mean_net"].values(True, True):
                p.zero_()
            params["module", "mean_net", "4", "bias"].fill_(-3.0)
    loss_mean, _, meta = loss.safety_loss(batch)
    assert bool((meta["cost_value"] < 0).all())
    loss_mean.backward()
    grad = loss.safety_network_params["module", "mean_net", "4", "bias"].grad
    assert grad is not None and float(grad) < 0  # pushes Q^c up towards targets ≥ 0
    # ... whose bootstrapped part uses max(Q̄^c, 0) = 0
    targets = loss.compute_targets(batch)
    cost = batch["next", "cost"].squeeze(-1)
    torch.testing.assert_close(targets["cost_target"], cost)
