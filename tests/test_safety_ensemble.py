"""Several safety critics read pessimistically (``num_safety_nets``, :class:`EnsembleHead`).

Each member must learn exactly as it would alone (its own target, its own TD loss), and
everything that reads Γ — the actor, κ's statistic, the estimates — must read the
largest member's.
"""

from __future__ import annotations

import re

import pytest
import torch
from _loss_helpers import ACT_DIM, OBS_DIM, flat_parts, linear_quantile_critic, make_batch
from _tolerance import assert_close_f32
from _training_helpers import compose_config
from tensordict import TensorDict
from torchrl.data import Bounded

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives.ensemble_head import EnsembleHead, make_safety_head
from wcsac_rl.objectives.loss_options import SafetyHeadOptions
from wcsac_rl.objectives.safety_head import SafetyValues
from wcsac_rl.training import ConfigError, make_trainer

# one-step targets at the replay states: the batch needs no n-step or start-state entries
PLAIN = {"cost_n_steps": 1, "kappa_states": "replay", "risk_level": 0.5}


MAX_TARGET = SafetyHeadOptions(num_safety_nets=2, ensemble_target="max")
"""Two critics, each bootstrapping from the larger target of the two."""


def _ensemble_and_singles(ensemble_target="own", **kwargs):
    """A two-member loss and one single-critic loss per member, sharing actor and
    reward critics; every loss reads its critics one by one (no fused products)."""
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=32)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=32) for _ in range(2)]
    members = [make_safety_critic(OBS_DIM, ACT_DIM, width=32) for _ in range(2)]
    options = {**PLAIN, "fast_paths": False, **kwargs}
    ensemble = WCSACLoss(
        actor,
        qvalues,
        members,
        **flat_parts(num_safety_nets=2, ensemble_target=ensemble_target, **options),
    )
    singles = [WCSACLoss(actor, qvalues, member, **flat_parts(**options)) for member in members]
    return ensemble, singles


def _safety_terms(loss: WCSACLoss, batch) -> list[torch.Tensor]:
    torch.manual_seed(5)  # (the target action a' ~ π(s') is the one draw)
    first, second, _ = loss.safety_loss(batch.clone())
    return [first, second]


def test_each_member_learns_exactly_as_it_would_alone():
    ensemble, singles = _ensemble_and_singles()
    batch = make_batch(16)
    terms = _safety_terms(ensemble, batch)
    alone = [_safety_terms(single, batch) for single in singles]
    for i, term in enumerate(terms):  # the TD losses (Eq. 7 and 8), summed over members
        assert_close_f32(term, alone[0][i] + alone[1][i], ops=32, msg=f"term {i}")
    names = list(ensemble.safety_network_params.keys(True, True))
    grads = torch.autograd.grad(sum(terms), [ensemble.safety_network_params.get(n) for n in names])
    for k, single in enumerate(singles):
        params = [single.safety_network_params.get(n) for n in names]
        own = torch.autograd.grad(sum(alone[k]), params)
        for name, grad, expected in zip(names, grads, own):
            assert grad.shape[0] == 2
            assert_close_f32(grad[k], expected, ops=32, msg=f"member {k} {name}")


def test_the_members_start_apart_and_keep_their_own_targets():
    ensemble, singles = _ensemble_and_singles()
    for params in (ensemble.safety_network_params, ensemble.target_safety_network_params):
        weight = params.get(("module", "mean_net", "0", "weight"))
        assert weight.shape[0] == 2 and not torch.equal(weight[0], weight[1])
    for k, single in enumerate(singles):  # the stacked targets are each member's own
        for name, value in single.target_safety_network_params.items(True, True):
            assert torch.equal(ensemble.target_safety_network_params.get(name)[k], value)


def test_the_actor_and_the_constraint_read_the_largest_members_gamma():
    ensemble, singles = _ensemble_and_singles(kappa_statistic="tail")
    batch = make_batch(16)
    outputs = []
    for loss in (ensemble, *singles):
        torch.manual_seed(7)  # (a' for the targets, then a ~ π(s) for the actor)
        outputs.append(loss(batch.clone()))
    mine, first, second = outputs
    # κ's statistic: the CVaR of the critic mixed over the rows, the larger member's
    assert_close_f32(mine["cvar"], torch.maximum(first["cvar"], second["cvar"]), ops=64)
    assert not torch.equal(first["cvar"], second["cvar"])  # (the members disagree)
    # the actor's Γ at its own actions: the larger member's, row by row
    policy = []
    for loss in (ensemble, *singles):
        torch.manual_seed(11)
        policy.append(loss.actor_loss(batch.clone())[1]["cvar_policy"])
    assert_close_f32(policy[0], torch.maximum(policy[1], policy[2]), ops=64)
    assert (policy[1] > policy[2]).any() and (policy[2] > policy[1]).any()


def test_the_estimates_are_the_pessimistic_members_row_by_row():
    ensemble, singles = _ensemble_and_singles()
    batch = make_batch(32)
    mine = ensemble.safety_estimates(batch)
    first, second = (single.safety_estimates(batch) for single in singles)
    larger = first["cvar"] >= second["cvar"]
    assert larger.any() and (~larger).any()
    for key in ("cvar", "cost_value", "cost_variance"):
        expected = torch.where(larger, first[key], second[key])
        assert_close_f32(mine[key], expected, ops=32, msg=key)


def test_an_iqn_ensemble_reads_the_larger_quantile_function():
    """Two linear quantile 'critics' Z = scale·(o₀ + o₁τ), scales 1 and 3: at
    positive quantiles the second member's Γ is 3× the first's and is the one read."""
    keys = WCSACLoss.default_keys()
    module = linear_quantile_critic()
    member = make_safety_head(
        module, keys, risk_level=0.2, options=SafetyHeadOptions(nonnegative_cost=False)
    )
    head = make_safety_head(
        module,
        keys,
        risk_level=0.2,
        options=SafetyHeadOptions(nonnegative_cost=False, num_safety_nets=2),
    )
    assert isinstance(head, EnsembleHead) and head.kind == "iqn"
    assert list(TensorDict.from_module(module).keys(True, True)) == [("module", "scale")]
    params = TensorDict({"module": {"scale": torch.tensor([1.0, 3.0])}}, [2])
    td = TensorDict({"observation": torch.tensor([[1.0, 2.0], [0.5, 0.0]])}, [2])
    one = member.estimates(td, TensorDict.from_module(module))
    both = head.estimates(td, params)
    assert_close_f32(both["cvar"], 3 * one["cvar"], ops=8)
    # Γ over [0.8, 1] at the strata's midpoints: o₀ + o₁·0.9, times 3
    assert_close_f32(both["cvar"], torch.tensor([8.4, 1.5]), ops=8)


def test_gaussian_ensemble_cvar_and_mixture_are_the_largest_members():
    keys = WCSACLoss.default_keys()
    torch.manual_seed(0)
    member = make_safety_head(make_safety_critic(3, 1, width=8), keys, risk_level=0.5)
    head = EnsembleHead(member, SafetyHeadOptions(num_safety_nets=2))
    mean = torch.tensor([[0.0, 9.0, 1.0], [4.0, 2.0, 1.0]])
    variance = torch.tensor([[1.0, 1.0, 4.0], [1.0, 1.0, 1.0]])
    values = SafetyValues(mean, variance)
    each = [SafetyValues(mean[k], variance[k]) for k in range(2)]
    expected = torch.maximum(member.cvar(each[0]), member.cvar(each[1]))
    assert torch.equal(head.cvar(values), expected)
    mixtures = [member.mixture_cvar(v) for v in each]
    assert torch.equal(head.mixture_cvar(values), torch.maximum(*mixtures))
    assert head.row_shape(values) == torch.Size([3])


def test_a_list_of_safety_critics_must_match_num_safety_nets():
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=8)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=8) for _ in range(2)]
    members = [make_safety_critic(OBS_DIM, ACT_DIM, width=8) for _ in range(2)]
    message = "num_safety_nets=1 but 2 safety critics were given: pass num_safety_nets=2"
    with pytest.raises(ValueError, match=re.escape(message)):
        WCSACLoss(actor, qvalues, members, **flat_parts(**PLAIN))
    with pytest.raises(ValueError, match="num_safety_nets"):
        WCSACLoss(
            actor, qvalues, members, **flat_parts(num_safety_nets=2, fast_paths=True, **PLAIN)
        )
    # one module and num_safety_nets=3: TorchRL's expand_dim re-draws each member
    loss = WCSACLoss(actor, qvalues, members[0], **flat_parts(num_safety_nets=3, **PLAIN))
    weight = loss.safety_network_params.get(("module", "mean_net", "0", "weight"))
    assert weight.shape[0] == 3 and not torch.equal(weight[0], weight[1])


def test_the_ensemble_state_dict_round_trips():
    ensemble, _ = _ensemble_and_singles()
    other, _ = _ensemble_and_singles()
    with torch.no_grad():
        for value in other.safety_network_params.values(True, True):
            value.add_(1.0)
    other.load_state_dict(ensemble.state_dict())
    for name, value in ensemble.safety_network_params.items(True, True):
        assert torch.equal(other.safety_network_params.get(name), value)


@pytest.mark.parametrize("algo", ["wcsac", "sac_lag"])
@pytest.mark.parametrize("critic", ["gaussian", "iqn"])
def test_the_config_builds_that_many_critics_each_initialised_on_its_own(tmp_path, algo, critic):
    cfg = compose_config(
        "env=tiny", f"algo={algo}", f"algo.safety_critic={critic}", "algo.num_safety_nets=2"
    )
    trainer = make_trainer(cfg, tmp_path / "r")
    try:
        loss = trainer.loss
        assert loss.num_safety_nets == 2 and isinstance(loss.safety_head, EnsembleHead)
        kind = "iqn" if critic == "iqn" else ("gaussian" if algo == "wcsac" else "mean")
        assert loss.safety_head.kind == kind
        first = next(iter(loss.safety_network_params.values(True, True)))
        assert first.shape[0] == 2 and not torch.equal(first[0], first[1])
        assert len(trainer.agent.safety) == 2
    finally:
        trainer.close()


# ------------------------------------------------------- ensemble_target="max"
def test_max_target_bootstraps_every_member_from_the_largest_target_row_by_row():
    """Gaussian: per row the member with the larger target mean Q̄^c gives both
    members' targets (its mean and its variance); "own" keeps each member's."""
    keys = WCSACLoss.default_keys()
    torch.manual_seed(0)
    member = make_safety_head(make_safety_critic(3, 1, width=8), keys, risk_level=0.5)
    ahead = SafetyValues(
        torch.tensor([[1.0, 5.0, 2.0], [3.0, 0.0, 2.5]]),
        torch.tensor([[1.0, 2.0, 7.0], [3.0, 4.0, 9.0]]),
    )
    cost, gamma, alive = torch.tensor([0.5, 0.0, 1.0]), torch.tensor(0.5), torch.ones(3)
    shared = EnsembleHead(member, MAX_TARGET).targets(cost, gamma, alive, ahead)
    mean, variance = torch.tensor([3.0, 5.0, 2.5]), torch.tensor([3.0, 2.0, 9.0])
    expected = member.targets(cost, gamma, alive, SafetyValues(mean, variance))
    for key in ("cost_target", "cost_second_moment", "cost_next_variance"):
        assert shared[key].shape == (2, 3)
        assert torch.equal(shared[key][0], expected[key]) and torch.equal(
            shared[key][1], expected[key]
        )
    # cost + γ·Q̄ of the picked member: 0.5 + 1.5, 0 + 2.5, 1 + 1.25
    assert torch.equal(shared["cost_target"][0], torch.tensor([2.0, 2.5, 2.25]))
    own = EnsembleHead(member, SafetyHeadOptions(num_safety_nets=2)).targets(
        cost, gamma, alive, ahead
    )
    assert torch.equal(own["cost_target"][0], torch.tensor([1.0, 2.5, 2.0]))


def test_max_target_of_an_iqn_ensemble_takes_the_larger_members_quantiles():
    keys = WCSACLoss.default_keys()
    member = make_safety_head(
        linear_quantile_critic(),
        keys,
        risk_level=0.2,
        options=SafetyHeadOptions(nonnegative_cost=False),
    )
    quantiles = torch.tensor([[[0.0, 2.0], [4.0, 6.0]], [[1.0, 3.0], [0.0, 1.0]]])  # [2, B=2, N=2]
    ahead = SafetyValues(quantiles.mean(-1), None, quantiles, torch.rand(2, 2))
    cost, gamma, alive = torch.tensor([1.0, 0.0]), torch.tensor(0.5), torch.tensor([1.0, 0.0])
    shared = EnsembleHead(member, MAX_TARGET).targets(cost, gamma, alive, ahead)
    # row 0: member 1 (mean 2 > 1): 1 + 0.5·[1, 3]; row 1: member 0, but terminated: 0
    expected = torch.tensor([[1.5, 2.5], [0.0, 0.0]])
    assert torch.equal(shared["cost_target_quantiles"], expected.expand(2, 2, 2))
    assert torch.equal(shared["cost_target"][1], torch.tensor([2.0, 0.0]))


def test_max_target_in_the_loss_is_each_member_bootstrapping_from_the_pessimistic_one():
    """Member 1's target critic made pessimistic everywhere (+50 on its mean's output):
    with "max" both members' TD losses are a single critic's whose target critic is
    member 1's; with "own" member 0 keeps its own."""
    out = {}
    for target in ("own", "max"):
        ensemble, singles = _ensemble_and_singles(ensemble_target=target)
        last_bias = ("module", "mean_net", "4", "bias")
        assert ensemble.target_safety_network_params.get(last_bias).shape == (2, 1)
        with torch.no_grad():
            ensemble.target_safety_network_params.get(last_bias)[1] += 50.0
            pessimistic = ensemble.target_safety_network_params[1]
            # "max": both members bootstrap from member 1's; "own": member 1 alone does
            for single in singles if target == "max" else singles[1:]:
                single.target_safety_network_params.update_(pessimistic)
        batch = make_batch(16)
        terms = _safety_terms(ensemble, batch)
        alone = [_safety_terms(single, batch) for single in singles]
        out[target] = terms[0]
        assert_close_f32(terms[0], alone[0][0] + alone[1][0], ops=32, msg=target)
        assert_close_f32(terms[1], alone[0][1] + alone[1][1], ops=32, msg=target)
    assert out["own"] < out["max"]  # member 0 regresses on targets ~50 higher


def test_max_target_needs_several_critics_and_a_known_name(tmp_path):
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=8)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=8) for _ in range(2)]
    critic = make_safety_critic(OBS_DIM, ACT_DIM, width=8)
    message = (
        "ensemble_target=max picks among several safety critics: it needs num_safety_nets >= 2"
    )
    with pytest.raises(ValueError, match=re.escape(message)):
        WCSACLoss(actor, qvalues, critic, **flat_parts(ensemble_target="max", **PLAIN))
    with pytest.raises(
        ValueError, match=re.escape("ensemble_target must be one of own, max, merged, got 'min'")
    ):
        WCSACLoss(
            actor, qvalues, critic, **flat_parts(num_safety_nets=2, ensemble_target="min", **PLAIN)
        )
    for overrides, line in (
        (
            ["algo.ensemble_target=max"],
            "algo.ensemble_target=max picks among several safety critics: it needs algo.num_safety_nets >= 2",
        ),
        (
            ["algo.num_safety_nets=2", "algo.ensemble_target=mean"],
            "algo.ensemble_target must be one of own, max, merged, got 'mean'",
        ),
    ):
        with pytest.raises(ConfigError, match=re.escape(line)):
            make_trainer(compose_config("env=tiny", *overrides), tmp_path / "r")
        assert not (tmp_path / "r").exists()


def test_the_config_reaches_the_ensemble_target(tmp_path):
    cfg = compose_config(
        "env=tiny", "algo.safety_critic=iqn", "algo.num_safety_nets=2", "algo.ensemble_target=max"
    )
    trainer = make_trainer(cfg, tmp_path / "r")
    try:
        assert trainer.loss.safety_head.target == "max"
    finally:
        trainer.close()
