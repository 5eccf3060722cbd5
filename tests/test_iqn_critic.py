"""The implicit-quantile (IQN) safety critic and WCSACLoss with it.

Unit tests (shapes, gradient routing, targets, Γ, errors, fast-path fall-backs) run
on small networks; the learning tests (``slow``) train the critic on the 5-state
chain of ``test_safety_critic_distribution.py`` and a one-step two-point cost, whose
return distributions are known in closed form, and WCSAC-0.1 on the risky bandit.

Float32 tolerances follow ``_tolerance.py``; learning tolerances are measured over
seeds, with the margin stated where they are used.
"""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from _loss_helpers import (
    ACT_DIM,
    OBS_DIM,
    assert_same_losses_and_gradients,
    flat_parts,
    linear_quantile_critic,
    make_batch,
    paper_options,
)
from _loss_helpers import make_loss as _make_loss
from _tolerance import assert_close_f32
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.objectives import SoftUpdate

import wcsac_rl.objectives.safety_head as safety_head_module
from wcsac_rl import WCSACLoss
from wcsac_rl.modules import IQNSafetyCritic, make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PolyakUpdate, SafetyHeadOptions, quantile_mixture_cvar
from wcsac_rl.objectives.fast_paths import IQNReader
from wcsac_rl.objectives.safety_head import (
    midpoint_fractions,
    quantile_huber_loss,
    stratified_fractions,
)


def make_loss(**kwargs) -> WCSACLoss:
    kwargs.setdefault("risk_level", 0.1)
    return _make_loss(kind="iqn", **kwargs)


@pytest.mark.parametrize("activation, depth", [("relu", 2), ("tanh", 1), ("elu", 3), ("gelu", 2)])
@pytest.mark.parametrize("shape", [(64,), (1,), (3, 5)])
@pytest.mark.parametrize("shared", [True, False], ids=["shared-tau", "per-row-tau"])
def test_reader_is_the_module_bit_for_bit(activation, depth, shape, shared):
    """``IQNReader`` (how the loss reads the critic) gives the module's quantiles for
    one row of τ expanded over the batch (a batch of one row is read row by row, as the
    module does) or τ per row, and the same gradients to every parameter, the state and
    the action, to the last bit."""
    torch.manual_seed(0)
    critic = make_safety_critic(
        OBS_DIM, ACT_DIM, kind="iqn", width=16, depth=depth, activation=activation
    )
    reader = IQNReader.of(critic.module, ("module",))
    assert reader is not None and reader.features.activate_last
    g = torch.Generator().manual_seed(1)
    tau = torch.rand(7, generator=g)
    fractions = tau.expand(*shape, 7) if shared else torch.rand(*shape, 7, generator=g)
    readings = []
    for path in ("module", "reader"):
        obs = torch.randn(
            *shape, OBS_DIM, generator=torch.Generator().manual_seed(2)
        ).requires_grad_()
        act = torch.rand(
            *shape, ACT_DIM, generator=torch.Generator().manual_seed(3)
        ).requires_grad_()
        params = TensorDict.from_module(critic).apply(lambda p: p.detach().clone().requires_grad_())
        if path == "module":
            td = TensorDict(
                {"observation": obs, "action": act, "quantile_fractions": fractions}, shape
            )
            with params.to_module(critic):
                z = critic(td)["cost_quantiles"]
        else:
            z = reader.quantiles(params, obs, act, fractions)
        (z * torch.randn(z.shape, generator=torch.Generator().manual_seed(4))).sum().backward()
        readings.append(
            (z.detach(), obs.grad, act.grad, [p.grad for p in params.values(True, True)])
        )
    (z_m, o_m, a_m, g_m), (z_r, o_r, a_r, g_r) = readings
    assert z_m.shape == z_r.shape == (*shape, 7)
    assert torch.equal(z_m, z_r) and torch.equal(o_m, o_r) and torch.equal(a_m, a_r)
    assert all(torch.equal(x, y) for x, y in zip(g_m, g_r, strict=True))


def test_reader_declines_what_it_cannot_read_exactly():
    critic = make_safety_critic(OBS_DIM, ACT_DIM, kind="iqn", width=8)

    class Shifted(IQNSafetyCritic):  # a subclass may compute otherwise
        def forward(self, observation, action, quantile_fractions):
            return super().forward(observation, action, quantile_fractions) + 1.0

    assert IQNReader.of(Shifted(OBS_DIM, ACT_DIM, width=8)) is None
    assert IQNReader.of(critic) is None  # the TensorDictModule, not the network
    odd = IQNSafetyCritic(OBS_DIM, ACT_DIM, width=8)
    odd.features.append(nn.Dropout(0.1))  # not Linear / activation layers
    assert IQNReader.of(odd) is None
    # a loss given such a critic reads it through the module, with the same results
    loss = make_loss(width=8)
    assert loss.safety_head._reader is not None
    swapped = make_loss(width=8)
    swapped.safety_head.read_through_module()
    assert swapped.safety_head._reader is None
    batch = make_batch(8)
    torch.manual_seed(0)
    first = loss(batch.clone())["loss_cost_quantile"]
    torch.manual_seed(0)
    assert torch.equal(first, swapped(batch.clone())["loss_cost_quantile"])


@pytest.fixture
def midpoints(monkeypatch):
    """Make the loss read its critic at the strata's midpoints instead of random draws."""
    monkeypatch.setattr(safety_head_module, "stratified_fractions", midpoint_fractions)


# ------------------------------------------------------------------- module
def test_module_writes_quantiles_for_shared_or_per_row_fractions_with_the_same_values():
    torch.manual_seed(0)
    critic = make_safety_critic(OBS_DIM, ACT_DIM, kind="iqn", width=32)
    assert isinstance(critic.module, IQNSafetyCritic)
    assert critic.in_keys == ["observation", "action", "quantile_fractions"]
    assert critic.out_keys == ["cost_quantiles"]
    obs, act = torch.randn(6, OBS_DIM), torch.rand(6, ACT_DIM) * 2 - 1
    tau = torch.rand(7)
    grads, values = [], []
    for fractions in (tau.expand(6, 7), tau.expand(6, 7).clone()):  # shared, then per row
        critic.zero_grad(set_to_none=True)
        td = TensorDict({"observation": obs, "action": act, "quantile_fractions": fractions}, [6])
        z = critic(td)["cost_quantiles"]
        assert z.shape == (6, 7)
        z.square().sum().backward()
        values.append(z.detach())
        grads.append({n: p.grad.clone() for n, p in critic.named_parameters()})
    # one product [6, 32] × [32, 7] against 7 products [32] · [32] per row: 32-term
    # sums that round in another order
    assert_close_f32(values[0], values[1], ops=32)
    for name in grads[1]:
        # each gradient entry sums 6 × 7 terms through the same 32-wide layers
        assert_close_f32(grads[0][name], grads[1][name], ops=64, msg=name)
    # rows differ in τ: each row its own quantiles; an unbatched state-action works too
    per_row = torch.rand(6, 7)
    td = TensorDict({"observation": obs, "action": act, "quantile_fractions": per_row}, [6])
    z = critic(td)["cost_quantiles"]
    single = critic.module(obs[2], act[2], per_row[2])
    assert single.shape == (7,)
    assert_close_f32(single.detach(), z[2].detach(), ops=32)


def test_module_errors_are_clear():
    with pytest.raises(ValueError, match="kind must be one of"):
        make_safety_critic(4, 2, kind="categorical")
    with pytest.raises(ValueError, match="mean-only ablation"):
        make_safety_critic(4, 2, kind="iqn", variance=False)
    with pytest.raises(ValueError, match="depth >= 1"):
        make_safety_critic(4, 2, kind="iqn", depth=0)


def test_quantile_fractions_are_stratified_or_midpoints():
    torch.manual_seed(0)
    for _ in range(20):
        tau = stratified_fractions(20, 0.9, 1.0)
        stratum = ((tau - 0.9) / 0.1 * 20).floor()
        # float32 rounding can put a draw on its stratum's upper edge, never beyond
        assert bool((stratum - torch.arange(20.0)).abs().le(1).all())
        assert bool(((tau >= 0.9) & (tau <= 1.0)).all())
    torch.testing.assert_close(
        midpoint_fractions(4, 0.5, 1.0), torch.tensor([0.5625, 0.6875, 0.8125, 0.9375])
    )


# ------------------------------------------------------------- quantile loss
def test_quantile_huber_loss_equals_the_definition_on_hand_made_tensors():
    quantiles = torch.tensor([[0.0, 1.0, 2.5], [3.0, -1.0, 0.2]], requires_grad=True)
    fractions = torch.tensor([0.1, 0.5, 0.9])
    targets = torch.tensor([[0.5, 3.0], [-2.0, 0.3]])
    for kappa in (1.0, 0.5):
        got = quantile_huber_loss(quantiles, fractions, targets, kappa)
        expected = []
        for b in range(2):
            total = 0.0
            for i, j in itertools.product(range(3), range(2)):
                delta = float(targets[b, j] - quantiles[b, i].detach())
                huber = (
                    0.5 * delta**2 if abs(delta) <= kappa else kappa * (abs(delta) - 0.5 * kappa)
                )
                total += abs(float(fractions[i]) - (delta < 0)) * huber / kappa / 2
            expected.append(total)
        # float64 reference of a few float32 operations on numbers of size ≤ 5
        assert_close_f32(got.detach(), torch.tensor(expected), ops=16, magnitude=5.0)
    # the gradient pushes each quantile towards its τ-quantile: here Z_0 (τ = 0.1) is
    # below both targets of row 0 and is pulled up, Z_2 (τ = 0.9) above one of them
    quantile_huber_loss(quantiles, fractions, targets).sum().backward()
    assert quantiles.grad[0, 0] < 0
    # the targets get no gradient
    targets.requires_grad_(True)
    quantile_huber_loss(quantiles, fractions, targets).sum().backward()
    assert targets.grad is None


@pytest.mark.parametrize("kappa", [1.0, 0.5])
@pytest.mark.parametrize("shared", [True, False], ids=["shared-fractions", "per-row-fractions"])
def test_quantile_huber_loss_is_the_written_out_definition_to_the_bit(kappa, shared):
    """The fused Huber kernel gives the values and gradients of the loss written out
    term by term (½δ² / κ(|δ| − ½κ), |τ − 1{δ < 0}|), bit for bit: on random float32 data
    of several scales, with exact ties (δ = 0) and |δ| at the threshold κ; a training
    run's numbers do not depend on which form computes them."""

    def written_out(quantiles, fractions, targets):
        delta = targets.detach().unsqueeze(-2) - quantiles.unsqueeze(-1)
        magnitude = delta.abs()
        huber = torch.where(
            magnitude <= kappa, 0.5 * delta.pow(2), kappa * (magnitude - 0.5 * kappa)
        )
        weight = (fractions.unsqueeze(-1) - (delta.detach() < 0).to(delta.dtype)).abs()
        return (weight * huber).mean(-1).sum(-1) / kappa

    g = torch.Generator().manual_seed(0)
    for scale in (0.01, 1.0, 100.0):
        quantiles = torch.randn(64, 8, generator=g) * scale
        targets = torch.randn(64, 6, generator=g) * scale
        targets[:, 0] = quantiles[:, 0]  # δ = 0
        targets[:8, 1] = quantiles[:8, 1] + kappa  # |δ| at κ, or a rounding off it
        shape = (8,) if shared else (64, 8)
        fractions = torch.rand(shape, generator=g)
        quantiles.requires_grad_(True)
        got = quantile_huber_loss(quantiles, fractions, targets, kappa)
        (got_grad,) = torch.autograd.grad(got.sum(), quantiles)
        expected = written_out(quantiles, fractions, targets)
        (expected_grad,) = torch.autograd.grad(expected.sum(), quantiles)
        assert torch.equal(got, expected)
        assert torch.equal(got_grad, expected_grad)


# ------------------------------------------------------------ gradient routing
LOSS_KEYS = ["loss_actor", "loss_qvalue", "loss_alpha", "loss_cost_quantile", "loss_kappa"]
OWNERS = {
    "loss_actor": "actor_network_params.",
    "loss_qvalue": "qvalue_network_params.",
    "loss_cost_quantile": "safety_network_params.",
    "loss_kappa": "constraint.kappa_raw",
    "loss_alpha": "log_alpha",
}


@pytest.mark.parametrize("direct", [True, False], ids=["direct", "torchrl-sampling"])
@pytest.mark.parametrize(
    ("kappa_actions", "kappa_states", "kappa_statistic"),
    [
        ("replay", "replay", "mean"),
        ("replay", "replay", "tail"),
        ("policy", "replay", "mean"),
        ("policy", "initial", "mean"),
        ("policy", "initial", "tail"),
    ],
)
@pytest.mark.parametrize("damp_scale", [0.0, 10.0])
@pytest.mark.parametrize("key", LOSS_KEYS)
def test_each_loss_term_reaches_exactly_its_own_parameters(
    key, kappa_actions, kappa_states, kappa_statistic, damp_scale, direct
):
    loss = make_loss(
        kappa_actions=kappa_actions,
        kappa_states=kappa_states,
        kappa_statistic=kappa_statistic,
        damp_scale=damp_scale,
        fast_paths=None if direct else False,
        cost_n_steps=1,
    )
    loss.zero_grad(set_to_none=True)
    out = loss(make_batch(initial=kappa_states == "initial"))
    out[key].backward()
    grads = {name: p.grad for name, p in loss.named_parameters()}
    owned = {n for n in grads if n.startswith(OWNERS[key])}
    assert owned, f"no parameter matches {OWNERS[key]}"
    for name, grad in grads.items():
        if name in owned:
            assert grad is not None and grad.abs().sum() > 0, f"{key} gave no gradient to {name}"
        else:
            assert grad is None or grad.abs().sum() == 0, f"{key} leaked a gradient into {name}"


@pytest.mark.parametrize("updater_class", [SoftUpdate, PolyakUpdate])
def test_target_critic_gets_no_gradient_and_follows_the_target_updaters(updater_class):
    loss = make_loss()
    updater = updater_class(loss, tau=0.1)
    optim = torch.optim.SGD(loss.parameters(), lr=0.5)
    out = loss(make_batch())
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    for name, buf in loss.named_buffers():
        if name.startswith("target_"):
            assert buf.grad is None and not buf.requires_grad, name
    before = loss.target_safety_network_params.clone()
    assert set(before.keys(True, True)) == set(loss.safety_network_params.keys(True, True))
    optim.step()
    updater.step()
    online = loss.safety_network_params.detach()
    for key, target in loss.target_safety_network_params.items(True, True):
        # θ̄ + τ(θ − θ̄) (lerp) against 0.9 θ̄ + 0.1 θ: a few roundings of the weights' size
        expected = 0.9 * before[key] + 0.1 * online[key]
        assert_close_f32(target, expected, ops=4, magnitude=1.0 + expected.abs().max())
        assert not torch.equal(target, before[key]), key


def test_loss_terms_and_diagnostics_are_finite_scalars_with_the_documented_keys():
    loss = make_loss()
    assert loss.safety_critic_kind == "iqn" and not loss.has_variance
    out = loss(make_batch())
    expected = set(LOSS_KEYS) | {
        "alpha",
        "kappa",
        "entropy",
        "cost_value",
        "cost_variance",
        "cvar",
        "cost_threshold",
    }
    assert set(out.keys()) == expected == set(loss.out_keys)
    for key, value in out.items():
        assert value.shape == () and torch.isfinite(value), key
        if not key.startswith("loss_"):
            assert not value.requires_grad, key
    assert out["cost_variance"] >= 0
    # the loss writes τ itself: neither the batch nor a start state needs it
    assert "quantile_fractions" not in loss.in_keys
    assert loss.initial_state_keys == ["observation"]


@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_reduction_none_matches_mean_and_sum(reduction):
    batch = make_batch(batch=12)
    none_loss = make_loss(reduction="none", scalar_output_mode="exclude")
    other = make_loss(reduction=reduction)
    torch.manual_seed(0)
    per_sample = none_loss(batch.clone())
    torch.manual_seed(0)
    reduced = other(batch.clone())
    for key in LOSS_KEYS:
        assert per_sample[key].shape == (12,), key
        expected = per_sample[key].mean() if reduction == "mean" else per_sample[key].sum()
        # a sum over 12 rows of the same per-row terms, in another order
        assert_close_f32(
            reduced[key], expected, ops=24, magnitude=1.0 + per_sample[key].abs().sum()
        )


def test_state_dict_round_trip_restores_every_output():
    a = make_loss(kappa_init=2.5)
    b = make_loss(seed=7)
    b.load_state_dict(a.state_dict())
    assert b.kappa == pytest.approx(2.5, rel=1e-5)
    batch = make_batch()
    torch.manual_seed(3)
    out_a = a(batch.clone())
    torch.manual_seed(3)
    out_b = b(batch.clone())
    for key in out_a.keys():
        torch.testing.assert_close(out_a[key], out_b[key], rtol=0, atol=0)


def test_fast_paths_give_the_same_losses_and_gradients():
    direct = make_loss(damp_scale=1.0)  # direct sampling, the stacked twin, the IQN read
    general = make_loss(fast_paths=False, damp_scale=1.0)
    general.load_state_dict(direct.state_dict())
    assert_same_losses_and_gradients(direct, general, make_batch())


def test_sac_lag_with_an_iqn_critic_holds_the_mean_quantile_under_the_threshold(midpoints):
    from wcsac_rl import SACLagLoss

    loss = SACLagLoss(
        make_actor(2, Bounded(-1.0, 1.0, shape=(1,)), width=8),
        [make_qvalue(2, 1, width=8) for _ in range(2)],
        _linear_critic(),
        **flat_parts("iqn", num_quantiles=4, cost_threshold=1.0, **paper_options("iqn")),
    )
    assert loss.safety_critic_kind == "iqn" and loss.risk_level == 1.0
    out = loss(_linear_batch())
    a, b = _linear_batch()["observation"].unbind(-1)
    # α = 1: Γ is the mean of Z = a + bτ over [0, 1], Z at τ = 1/2
    assert_close_f32(out["cvar"], (a + b / 2).mean(), ops=16, magnitude=10.0)
    assert "loss_cost_quantile" in out.keys()
    with pytest.raises(TypeError, match="quantile_cvar"):
        loss.cvar(a, b)


def test_fusing_falls_back_for_an_iqn_critic_or_is_refused():
    assert make_loss().critics.fused is None  # fast_paths=None: module calls
    assert make_loss(fast_paths=False).critics.fused is None
    with pytest.raises(ValueError, match="IQN safety critic is not fused"):
        make_loss(fast_paths=True)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"variance_target": "td"}, "variance head"),
        ({"variance_loss": "glm"}, "variance head"),
        ({"num_quantiles": 0}, "num_quantiles must be an integer >= 1"),
        ({"num_target_quantiles": 1.5}, "num_target_quantiles must be an integer >= 1"),
        ({"huber_kappa": 0.0}, r"huber_kappa must be in \(0, 1e\+06\]"),
    ],
)
def test_bad_iqn_arguments_are_refused(kwargs, message):
    """Given as the head's options (a recipe with ``safety_critic="iqn"`` leaves the
    Gaussian head's options at their defaults), a bad one is refused in one line."""
    with pytest.raises(ValueError, match=message) as err:
        make_loss(safety_head=SafetyHeadOptions(**kwargs))
    assert "\n" not in str(err.value)


# ---------------------------------------------------------- analytic targets


def _linear_critic() -> TensorDictModule:
    return linear_quantile_critic()


def _linear_loss(gamma: float = 0.9, **kwargs) -> WCSACLoss:
    torch.manual_seed(0)
    safety = _linear_critic()
    kwargs.setdefault("risk_level", 0.2)
    kwargs.setdefault("num_quantiles", 4)
    kwargs.setdefault("num_target_quantiles", 5)
    loss = WCSACLoss(
        make_actor(2, Bounded(-1.0, 1.0, shape=(1,)), width=8),
        [make_qvalue(2, 1, width=8) for _ in range(2)],
        safety,
        **flat_parts("iqn", **{**paper_options("iqn"), **kwargs}),
    )
    loss.make_value_estimator(gamma=gamma)
    return loss


def _linear_batch(initial: bool = False) -> TensorDict:
    # rows: (Z = a + bτ) from obs at (s, a), (a', b') from next obs, cost, terminated
    obs = torch.tensor([[2.0, 1.0], [1.0, 4.0], [3.0, 2.0]])
    next_obs = torch.tensor([[1.5, 2.0], [-3.0, 1.0], [7.0, 9.0]])
    cost = torch.tensor([[1.0], [0.0], [2.0]])
    terminated = torch.tensor([[False], [False], [True]])
    td = TensorDict(
        {
            "observation": obs,
            "action": torch.zeros(3, 1),
            "next": {
                "observation": next_obs,
                "reward": torch.zeros(3, 1),
                "cost": cost,
                "done": terminated.clone(),
                "terminated": terminated,
            },
        },
        [3],
    )
    if initial:
        td["initial"] = TensorDict(
            {"observation": torch.tensor([[0.0, 1.0], [4.0, 8.0], [1.0, 0.0]])}, [3]
        )
    return td


def test_linear_critic_is_recognised_by_its_fraction_key():
    loss = _linear_loss()
    assert loss.safety_critic_kind == "iqn"
    assert loss.tensor_keys.cost_quantiles == "cost_quantiles"


@pytest.mark.parametrize("nonnegative", [False, True])
def test_targets_are_cost_plus_discounted_target_quantiles(midpoints, nonnegative):
    g = 0.9
    loss = _linear_loss(gamma=g, nonnegative_cost=nonnegative)
    targets = loss.compute_targets(_linear_batch())
    tau = (torch.arange(5.0) + 0.5) / 5  # N' = 5 target fractions at their midpoints
    next_z = torch.stack([1.5 + 2.0 * tau, -3.0 + 1.0 * tau, 7.0 + 9.0 * tau])
    if nonnegative:
        next_z = next_z.clamp(min=0.0)
    expected = (
        torch.tensor([[1.0], [0.0], [2.0]]) + g * torch.tensor([[1.0], [1.0], [0.0]]) * next_z
    )
    # c + γ·Z̄: two roundings of values of size ≤ 20
    assert_close_f32(targets["cost_target_quantiles"], expected, ops=4)
    assert_close_f32(targets["cost_target"], expected.mean(-1), ops=8)
    assert targets["cost_second_moment"] is None and targets["cost_next_variance"] is None


def test_nstep_targets_bootstrap_from_the_state_m_steps_ahead(midpoints):
    g = 0.5
    loss = _linear_loss(gamma=g, cost_n_steps=3)
    batch = _linear_batch()
    batch["nstep"] = TensorDict(
        {
            "observation": torch.tensor([[1.0, 1.0], [2.0, 0.0], [5.0, 5.0]]),
            "cost": torch.tensor([[1.75], [0.5], [2.0]]),
            "steps": torch.tensor([[3], [2], [1]]),
            "terminated": torch.tensor([[False], [False], [True]]),
        },
        [3],
    )
    targets = loss.compute_targets(batch)
    tau = (torch.arange(5.0) + 0.5) / 5
    z_m = torch.stack([1.0 + tau, 2.0 + 0.0 * tau, 5.0 + 5.0 * tau])
    discount = torch.tensor([[g**3], [g**2], [0.0]])
    expected = torch.tensor([[1.75], [0.5], [2.0]]) + discount * z_m
    assert_close_f32(targets["cost_target_quantiles"], expected, ops=4)


@pytest.mark.parametrize("members", [1, 2])
@pytest.mark.parametrize("target", [False, True])
@pytest.mark.parametrize("stratified", [True, False])
def test_a_skipped_reading_draws_exactly_what_a_reading_draws(members, target, stratified):
    """The n-step targets do not read the target critic at ``(s', a')`` but draw its
    fractions there: the random stream after the skip is the one after the reading (so
    every later draw, and the training run, is what it was when the reading was made),
    for one critic and for an ensemble, whose members draw one after the other."""
    loss = make_loss(num_safety_nets=members)
    params = loss.target_safety_network_params if target else loss.safety_network_params
    batch = make_batch(8)
    torch.manual_seed(3)
    loss.safety_head.values(batch, params, target=target, stratified=stratified)
    after_reading = torch.get_rng_state()
    torch.manual_seed(3)
    loss.safety_head.skip_reading(params, target=target, stratified=stratified)
    assert torch.equal(torch.get_rng_state(), after_reading)


def test_nstep_targets_evaluate_the_iqn_critic_once_per_reading_they_use():
    """One update's forward with n-step targets and κ at start states evaluates the
    safety network at the replay state-actions, at the actor's actions, at the start
    states and (target parameters) at s_{t+m}: four calls, none discarded."""
    loss = make_loss(cost_n_steps=3, kappa_states="initial")
    calls = []
    head, read = loss.safety_head, loss.safety_head.quantiles
    head.quantiles = lambda *args: calls.append(1) or read(*args)  # one reading per call
    batch = make_batch(8, initial=True)
    batch["nstep"] = TensorDict(
        {
            "observation": batch["next", "observation"],
            "cost": batch["next", "cost"],
            "steps": torch.full((8, 1), 3),
            "terminated": batch["next", "terminated"],
        },
        [8],
    )
    loss(batch)
    assert len(calls) == 4


@pytest.mark.parametrize("nonnegative", [False, True])
def test_gamma_is_the_mean_of_the_tail_quantiles_and_estimates_use_midpoints(nonnegative):
    alpha, n = 0.2, 4
    loss = _linear_loss(risk_level=alpha, nonnegative_cost=nonnegative)
    batch = _linear_batch()
    batch["observation"] = torch.tensor([[2.0, 1.0], [-1.0, 4.0], [3.0, -2.0]])
    est = loss.safety_estimates(batch)
    a, b = batch["observation"][:, 0], batch["observation"][:, 1]
    full = (torch.arange(n) + 0.5) / n
    tail = 1 - alpha + alpha * full
    z_full = a[:, None] + b[:, None] * full
    z_tail = a[:, None] + b[:, None] * tail
    if nonnegative:
        z_tail = z_tail.clamp(min=0.0)
    assert_close_f32(est["cost_quantiles"], z_full, ops=4)
    assert_close_f32(est["cost_value"], z_full.mean(-1), ops=8)
    assert_close_f32(est["cvar"], z_tail.mean(-1), ops=8)
    # the variance of the quantiles: b² × the variance of the N midpoints (N² − 1)/(12 N²)
    assert_close_f32(est["cost_variance"], b**2 * (n**2 - 1) / (12 * n**2), ops=16)
    if not nonnegative:  # Z linear in τ: the tail mean is Z at the tail's centre
        assert_close_f32(est["cvar"], a + b * (1 - alpha / 2), ops=8)
    assert not est["cvar"].requires_grad


@pytest.mark.parametrize(
    ("kappa_states", "kappa_actions", "kappa_statistic"),
    [
        ("replay", "replay", "mean"),
        ("replay", "policy", "mean"),
        ("replay", "policy", "tail"),
        ("initial", "policy", "mean"),
        ("initial", "policy", "tail"),
    ],
)
def test_kappa_loss_holds_the_documented_statistic_under_the_threshold(
    midpoints, kappa_states, kappa_actions, kappa_statistic
):
    """Z does not depend on the action here, so Γ is known whatever a ~ π draws."""
    alpha, n = 0.2, 4
    loss = _linear_loss(
        risk_level=alpha,
        kappa_states=kappa_states,
        kappa_actions=kappa_actions,
        kappa_statistic=kappa_statistic,
        cost_threshold=1.0,
    )
    batch = _linear_batch(initial=True)
    out = loss(batch)
    states = batch["initial"] if kappa_states == "initial" else batch
    a, b = states["observation"][:, 0], states["observation"][:, 1]
    mid = (torch.arange(n) + 0.5) / n
    if kappa_statistic == "mean":
        expected = (a + b * (1 - alpha / 2)).mean()
    else:
        expected = quantile_mixture_cvar(a[:, None] + b[:, None] * mid, alpha)
    assert_close_f32(out["cvar"], expected, ops=16, magnitude=10.0)
    assert_close_f32(out["loss_kappa"], loss.kappa * (1.0 - expected), ops=16, magnitude=10.0)


# ----------------------------------------------------------------- compile
@pytest.mark.slow
@pytest.mark.parametrize(
    "options",
    [{}, {"num_safety_nets": 3, "ensemble_reading": "tqc", "prior_scale": 1.0}],
    ids=["single", "tqc_ensemble"],
)
def test_forward_compiles_with_fullgraph_and_matches_eager(options):
    import torch._inductor.config as inductor_config

    loss = make_loss(width=16, **options)
    batch = make_batch()
    compiled = torch.compile(loss, fullgraph=True)
    with inductor_config.patch(fallback_random=True):
        torch.manual_seed(0)
        got = compiled(batch.clone())
        torch.manual_seed(0)
        expected = loss(batch.clone())
    for key in expected.keys():
        # as for the Gaussian critic (test_wcsac_loss.py): inductor reorders the
        # update's few hundred roundings of terms of order 1 + |value|
        assert_close_f32(got[key], expected[key], ops=512, magnitude=1.0 + expected[key].abs())
    sum(v for k, v in got.items() if k.startswith("loss_")).backward()
    assert loss.kappa_raw.grad is not None


# --------------------------------------------- learning: the chain's distribution
def chain_return_distribution(state: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Atoms (ascending) and probabilities of Σ_k γ^k c_{state+k} on the chain of
    ``test_safety_critic_distribution.py`` (independent Bernoulli costs), float64."""
    from test_safety_critic_distribution import GAMMA, HIT, PROB, N

    outcomes = []
    for hits in itertools.product((0, 1), repeat=N - state):
        value = sum(GAMMA**k * float(HIT[state + k]) * h for k, h in enumerate(hits))
        prob = math.prod(
            float(PROB[state + k]) if h else 1 - float(PROB[state + k]) for k, h in enumerate(hits)
        )
        outcomes.append((value, prob))
    outcomes.sort()
    atoms, probs = zip(*outcomes)
    return torch.tensor(atoms, dtype=torch.float64), torch.tensor(probs, dtype=torch.float64)


def distribution_cvar(atoms: torch.Tensor, probs: torch.Tensor, alpha: float) -> float:
    """CVaR_α of a discrete distribution: the mean of its upper α share of mass."""
    remaining, total = alpha, 0.0
    for atom, prob in zip(reversed(atoms.tolist()), reversed(probs.tolist())):
        share = min(prob, remaining)
        total += share * atom
        remaining -= share
    return total / alpha


def huber_quantiles(
    atoms: torch.Tensor, weights: torch.Tensor, fractions: torch.Tensor, kappa: float
) -> torch.Tensor:
    """The minimisers z(τ) of E[ρ^κ_τ(Y − z)] for a discrete Y (float64 bisection on the
    derivative Σ_k w_k |τ − 1{y_k < z}| clip(y_k − z, −κ, κ), decreasing in z)."""
    low = torch.full_like(fractions, float(atoms.min()) - kappa)
    high = torch.full_like(fractions, float(atoms.max()) + kappa)
    for _ in range(60):
        z = (low + high) / 2
        delta = atoms - z.unsqueeze(-1)
        weight = (fractions.unsqueeze(-1) - (delta < 0).double()).abs()
        slope = (weights * weight * delta.clamp(-kappa, kappa)).sum(-1)
        low, high = torch.where(slope > 0, z, low), torch.where(slope > 0, high, z)
    return (low + high) / 2


def huber_td_fixed_point(n_steps: int, fractions: torch.Tensor, kappa: float) -> list[torch.Tensor]:
    """The quantiles Z_i(τ) the quantile-Huber TD loss converges to on the chain.

    Z_i(τ) is the Huber τ-quantile (:func:`huber_quantiles`) of its target's law,
    ``Σ_{k<m} γ^k c_{i+k} + γ^m Z_{i+m}(τ')`` with ``τ' ~ U[0, 1]`` (``m = min(n, N − i)``,
    no bootstrap past the terminal state), solved backwards from the last state on
    the grid ``fractions`` (midpoints, so each τ' carries weight 1/M). With κ → 0 it
    is the closed-form distribution's quantile function; with κ_H = 1 the Huber
    projection pulls each quantile towards its neighbours by up to ~κ_H, and that bias
    compounds through the bootstraps.
    """
    from test_safety_critic_distribution import GAMMA, HIT, PROB, N

    grid = len(fractions)
    quantiles: list[torch.Tensor] = [torch.empty(0)] * N
    for i in reversed(range(N)):
        m = min(n_steps, N - i)
        atoms, weights = [], []
        for hits in itertools.product((0, 1), repeat=m):
            atoms.append(sum(GAMMA**k * float(HIT[i + k]) * h for k, h in enumerate(hits)))
            weights.append(
                math.prod(
                    float(PROB[i + k]) if h else 1 - float(PROB[i + k]) for k, h in enumerate(hits)
                )
            )
        atoms, weights = (
            torch.tensor(atoms, dtype=torch.float64),
            torch.tensor(weights, dtype=torch.float64),
        )
        if i + m < N:
            atoms = (atoms.unsqueeze(-1) + GAMMA**m * quantiles[i + m]).reshape(-1)
            weights = (weights.unsqueeze(-1) / grid).expand(-1, grid).reshape(-1)
        quantiles[i] = huber_quantiles(atoms, weights, fractions, kappa)
    return quantiles


def test_huber_fixed_point_helper_is_the_closed_form_quantile_function_as_kappa_vanishes():
    """The reference the learning test compares with, checked against the closed form."""
    fractions = (torch.arange(400, dtype=torch.float64) + 0.5) / 400
    for n_steps in (1, 3):
        for i, z in enumerate(huber_td_fixed_point(n_steps, fractions, kappa=1e-3)):
            atoms, probs = chain_return_distribution(i)
            cdf = probs.cumsum(0)
            index = torch.searchsorted(cdf, fractions).clamp(max=len(atoms) - 1)
            # a τ on an atom's cdf step may land on either side: compare where it does not
            away = (cdf.unsqueeze(-1) - fractions).abs().min(0).values > 1.5 / 400
            # bisection to 2⁻⁶⁰ of the bracket; a Huber quantile is within κ of the
            # quantile when atoms are more than κ apart, and the bootstraps add each
            # successor's error discounted: at most κ Σ_{k<5} γ^k
            bound = 1e-3 * sum(0.9**k for k in range(5))
            torch.testing.assert_close(z[away], atoms[index][away], rtol=0, atol=bound)


@pytest.mark.slow
@pytest.mark.parametrize("n_steps", [1, 3])
def test_learned_quantiles_match_the_chain_return_distribution(n_steps):
    """The IQN critic on the 5-state chain (as the Gaussian one in
    ``test_safety_critic_distribution.py``), 3000 updates of the critic alone.

    Reference: the quantile-Huber TD fixed point of the closed-form return
    distribution (:func:`huber_td_fixed_point`, κ_H = 1) on a 400-point τ grid. Measured
    over seeds 0–4 (n = 1 and 3), learned vs fixed point: W1 ≤ 0.087, |ΔCVaR_0.1| ≤
    0.36, |ΔCVaR_0.5| ≤ 0.10, |Δmean| ≤ 0.063; the tolerances are 1.5× those. Against
    the closed form itself the learned CVaR is off by the Huber projection's own bias
    (at κ_H = 1: CVaR_0.1 of state 0 is 1.27 under the true 7.77 for n = 1, 0.58 for
    n = 3) plus that learning tolerance.
    """
    from test_safety_critic_distribution import GAMMA, N, _chain_sampler

    torch.manual_seed(0)
    loss = WCSACLoss(
        make_actor(N, Bounded(-1.0, 1.0, shape=(1,)), width=16),
        [make_qvalue(N, 1, width=16) for _ in range(2)],
        make_safety_critic(N, 1, kind="iqn", width=64),
        **flat_parts("iqn", risk_level=0.5, **{**paper_options("iqn"), "cost_n_steps": n_steps}),
    )
    loss.make_value_estimator(gamma=GAMMA)
    steps = 3000
    optim = torch.optim.Adam(loss.safety_network_params.values(True, True), lr=3e-3)
    # a decaying step size averages out the sampled targets' noise at the end
    schedule = torch.optim.lr_scheduler.LinearLR(optim, 1.0, 0.05, total_iters=steps)
    updater = SoftUpdate(loss, tau=0.02)
    sample = _chain_sampler(256, torch.Generator().manual_seed(0), n_steps)
    for _ in range(steps):
        loss_quantile, loss_variance, _ = loss.safety_loss(sample())
        assert loss_variance is None
        loss_quantile.backward()
        optim.step()
        optim.zero_grad()
        schedule.step()
        updater.step()

    fractions = (torch.arange(400, dtype=torch.float64) + 0.5) / 400
    repeats = 64  # the costs do not depend on the action: average over random actions
    td = TensorDict(
        {
            "observation": torch.eye(N).repeat_interleave(repeats, 0),
            "action": torch.rand(N * repeats, 1) * 2 - 1,
        },
        [N * repeats],
    )
    with torch.no_grad():
        learned = loss.safety_head.quantiles(td, loss.safety_network_params, fractions.float())
    learned = learned.view(N, repeats, -1).mean(1).double()
    reference = huber_td_fixed_point(n_steps, fractions, kappa=1.0)
    tolerance = {0.1: 0.55, 0.5: 0.15, 1.0: 0.1}
    for i in range(N):
        atoms, probs = chain_return_distribution(i)
        w1 = float((learned[i] - reference[i]).abs().mean())
        assert w1 <= 0.13, f"state {i}: W1 to the fixed point {w1:.3f}"
        for alpha, tol in tolerance.items():
            tail = fractions > 1 - alpha
            got = float(learned[i][tail].mean())
            fixed = float(reference[i][tail].mean())
            closed = distribution_cvar(atoms, probs, alpha)
            assert got == pytest.approx(fixed, abs=tol), f"state {i} CVaR_{alpha}"
            assert abs(got - closed) <= abs(fixed - closed) + tol, f"state {i} CVaR_{alpha}"


# ------------------------------------------------------------- through the trainer
def _train(run_dir, *overrides):
    from _training_helpers import compose_config

    from wcsac_rl.training import make_trainer

    trainer = make_trainer(compose_config("env=tiny", *overrides), run_dir)
    try:
        return trainer, trainer.run()
    finally:
        trainer.close()


def _rows(run_dir) -> list[dict[str, str]]:
    import csv

    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


IQN_RUN = (
    "algo.safety_critic=iqn",
    "algo.risk_level=0.1",
    "algo.kappa_states=initial",
    "algo.kappa_statistic=tail",
    "algo.cost_n_steps=4",
    "algo.nonnegative_cost=true",
    "algo.variance_target=td",  # a Gaussian option: not used by the IQN critic
    "eval_episodes=3",
)


def test_trainer_runs_resumes_and_calibrates_an_iqn_critic(tmp_path, capsys):
    import json

    from wcsac_rl.calibration import main as calibration_main
    from wcsac_rl.evaluation.run_calibration import CALIBRATION_KEYS
    from wcsac_rl.training import ConfigError
    from wcsac_rl.training.checkpoint import load_checkpoint

    trainer, run_dir = _train(tmp_path / "run", *IQN_RUN, "save_replay_buffer=true")
    loss = trainer.loss
    assert loss.safety_critic_kind == "iqn" and loss.num_quantiles == 20
    assert isinstance(trainer.agent.safety.module, IQNSafetyCritic)
    rows = _rows(run_dir)
    assert [int(r["frames"]) for r in rows] == [400, 800]
    columns = set(rows[0])
    assert {
        "loss/loss_cost_quantile",
        "loss/cost_value",
        "loss/cost_variance",
        "loss/cvar",
    } <= columns
    assert not {"loss/loss_cost_value", "loss/loss_cost_variance"} & columns
    for row in rows:
        for key in ("loss/loss_cost_quantile", "loss/cvar", "loss/kappa"):
            assert math.isfinite(float(row[key])), key
        # the per-epoch calibration reads the critic's quantiles
        for key in ("start_cost_value", "start_cvar", "start_std", "start_tail_cvar"):
            assert math.isfinite(float(row[f"calib/{key}"])), key
        assert float(row["calib/start_tail_cvar"]) >= 0.0  # nonnegative_cost
    checkpoint = load_checkpoint(trainer.checkpoint_path)
    assert checkpoint["config"]["algo"]["safety_critic"] == "iqn"

    # resume: the same run goes on, with its replay and start-state buffers
    resumed, same_dir = _train(
        tmp_path / "ignored",
        *IQN_RUN,
        "save_replay_buffer=true",
        "total_frames=1200",
        f"resume={run_dir}",
    )
    assert same_dir == run_dir
    assert [int(r["frames"]) for r in _rows(run_dir)] == [400, 800, 1200]
    assert resumed.updates == trainer.updates + 100
    before = checkpoint["learner"]["loss"]
    after = load_checkpoint(resumed.checkpoint_path)["learner"]["loss"]
    moved = [k for k in before if k.startswith("safety_network_params")]
    assert moved and all(not torch.equal(before[k], after[k]) for k in moved)
    # a Gaussian critic cannot continue an IQN run
    with pytest.raises(ConfigError, match="safety_critic"):
        _train(tmp_path / "x", *IQN_RUN, "algo.safety_critic=gaussian", f"resume={run_dir}")

    # the calibration CLI on the finished run
    assert calibration_main([str(run_dir), "--episodes", "4", "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "(IQN safety critic)" in printed and "std of quantiles / spread" in printed
    data = json.loads((run_dir / "calibration.json").read_text())
    assert data["safety_critic"] == "iqn" and not data["has_variance"]
    assert set(data["metrics"]) == {k.removeprefix("calib/") for k in CALIBRATION_KEYS}
    metrics = data["metrics"]
    assert math.isfinite(metrics["start_cost_value"])  # the mean quantile, not clamped
    # Γ and the pooled tail use max(Z, 0) (nonnegative_cost); standard deviations
    for key in ("start_cvar", "start_std", "start_tail_cvar", "mean_std"):
        assert metrics[key] is not None and metrics[key] >= 0.0, key


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("algo.safety_critic=categorical", "algo.safety_critic must be one of gaussian, iqn"),
        ("algo.iqn.num_quantiles=0", "algo.iqn.num_quantiles must be an integer >= 1"),
        ("algo.iqn.num_cosines=2.5", "algo.iqn.num_cosines must be an integer >= 1"),
        ("algo.iqn.huber_kappa=0", "algo.iqn.huber_kappa must be in (0, 1e+06]"),
    ],
)
def test_bad_iqn_config_fails_before_any_work(tmp_path, override, message):
    import re

    from _training_helpers import compose_config

    from wcsac_rl.training import ConfigError, make_trainer

    with pytest.raises(ConfigError, match=re.escape(message)):
        make_trainer(compose_config("env=tiny", "algo.safety_critic=iqn", override), tmp_path / "r")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("alpha", ["0.9", "0.5", "0.1"])
def test_table1_wcsac_rows_run_the_kits_iqn_critic_and_are_named(alpha):
    from _training_helpers import compose_config

    from wcsac_rl.evaluation.runs import row_name

    cfg = compose_config(f"+row=wcsac_{alpha}", small=False)
    assert cfg.algo.name == "wcsac" and cfg.algo.safety_critic == "iqn"
    assert cfg.algo.risk_level == float(alpha) and cfg.algo.label == f"wcsac_{alpha}"
    assert row_name(cfg.algo.label) == f"WCSAC-{alpha}"
