"""Several safety critics read pessimistically (``num_safety_nets``, :class:`EnsembleHead`).

Each member must learn exactly as it would alone (its own target, its own TD loss), and
everything that reads Γ — the actor, κ's statistic, the estimates — must read the
largest member's.
"""

from __future__ import annotations

import re

import pytest
import torch
from _loss_helpers import ACT_DIM, OBS_DIM, linear_quantile_critic, make_batch
from _tolerance import assert_close_f32
from _training_helpers import compose_config
from tensordict import TensorDict
from torchrl.data import Bounded

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives.safety_head import EnsembleHead, SafetyValues, make_safety_head
from wcsac_rl.training import make_trainer

# one-step targets at the replay states: the batch needs no n-step or start-state entries
PLAIN = {"cost_n_steps": 1, "kappa_states": "replay", "risk_level": 0.5}


def _ensemble_and_singles(**kwargs):
    """A two-member loss and one single-critic loss per member, sharing actor and
    reward critics; every loss reads its critics one by one (no fused products)."""
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=32)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=32) for _ in range(2)]
    members = [make_safety_critic(OBS_DIM, ACT_DIM, width=32) for _ in range(2)]
    options = {**PLAIN, "fuse_critics": False, **kwargs}
    ensemble = WCSACLoss(actor, qvalues, members, num_safety_nets=2, **options)
    singles = [WCSACLoss(actor, qvalues, member, **options) for member in members]
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
    member = make_safety_head(module, keys, risk_level=0.2, nonnegative_cost=False)
    head = make_safety_head(module, keys, risk_level=0.2, nonnegative_cost=False, members=2)
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
    head = EnsembleHead(member, members=2)
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
        WCSACLoss(actor, qvalues, members, **PLAIN)
    with pytest.raises(ValueError, match="num_safety_nets"):
        WCSACLoss(actor, qvalues, members, num_safety_nets=2, fuse_critics=True, **PLAIN)
    # one module and num_safety_nets=3: TorchRL's expand_dim re-draws each member
    loss = WCSACLoss(actor, qvalues, members[0], num_safety_nets=3, **PLAIN)
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
