"""The ensemble's readings beside the largest member's: the upper confidence bound (CAL),
the merged-quantile tail (TQC), random prior functions, and the batched evaluation of
the members (``ensemble_reading``, ``k_ucb``, ``prior_scale``)."""

from __future__ import annotations

import math
import re

import pytest
import torch
from _loss_helpers import ACT_DIM, OBS_DIM, flat_parts, linear_quantile_critic, make_batch
from _tolerance import assert_close_f32
from _training_helpers import compose_config
from torchrl.data import Bounded
from torchrl.objectives import SoftUpdate

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives.ensemble_head import EnsembleHead, make_safety_head
from wcsac_rl.objectives.ensemble_reading import ucb, upper_tail_mean
from wcsac_rl.objectives.loss_options import SafetyHeadOptions
from wcsac_rl.objectives.safety_head import SafetyValues
from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.config_keys import check_override_keys

PLAIN = {"cost_n_steps": 1, "kappa_states": "replay", "risk_level": 0.5}
ENSEMBLE_ONLY = (
    "ensemble_reading",
    "ensemble_target",
    "prior_scale",
    "k_ucb",
    "k_ucb_lr",
    "k_ucb_max",
)


def _losses(members=3, kind="gaussian", **kwargs):
    """An ensemble loss over ``members`` critics (its members read in one batched product)
    and one single-critic loss per member (TorchRL's general path: no fused critics),
    sharing the actor and the reward critics."""
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=32)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=32) for _ in range(2)]
    critics = [make_safety_critic(OBS_DIM, ACT_DIM, kind=kind, width=32) for _ in range(members)]
    options = {**PLAIN, **kwargs}
    singles = {k: v for k, v in options.items() if k not in ENSEMBLE_ONLY}
    singles.setdefault("fast_paths", False)
    ensemble = WCSACLoss(
        actor, qvalues, critics, **flat_parts(kind, num_safety_nets=members, **options)
    )
    return ensemble, [
        WCSACLoss(actor, qvalues, critic, **flat_parts(kind, **singles)) for critic in critics
    ]


# ------------------------------------------------------------------ the UCB reading
def test_ucb_is_the_mean_plus_k_sample_standard_deviations_by_hand():
    head = make_safety_head(
        make_safety_critic(3, 1, variance=False, width=8),
        WCSACLoss.default_keys(),
        risk_level=1.0,
        options=SafetyHeadOptions(num_safety_nets=3, ensemble_reading="ucb", k_ucb=0.5),
    )
    mean = torch.tensor([[1.0, 5.0], [3.0, 0.0], [2.0, 1.0]])  # [E=3, B=2]
    # column 0: mean 2, squared deviations 1 + 1 + 0 over E − 1 = 2: std 1
    # column 1: mean 2, squared deviations 9 + 4 + 1 over 2: std √7 (not √(14/3))
    expected = torch.tensor([2.0 + 0.5 * 1.0, 2.0 + 0.5 * math.sqrt(7.0)])
    assert_close_f32(head.cvar(SafetyValues(mean)), expected, ops=8)
    assert_close_f32(ucb(mean, 0.5), expected, ops=8)
    # κ's tail statistic at α = 1: each member's mixture is its mean over the rows
    # (3, 1.5, 1.5): mean 2, std √((1 + ¼ + ¼)/2) = √0.75
    assert_close_f32(
        head.mixture_cvar(SafetyValues(mean)), torch.tensor(2.0 + 0.5 * 0.75**0.5), ops=8
    )


def test_the_actor_kappa_and_the_shield_read_the_members_upper_confidence_bound():
    ensemble, singles = _losses(ensemble_reading="ucb", k_ucb=0.7, kappa_statistic="tail")
    assert ensemble.safety_head.stacked is not None  # (one batched product)
    batch = make_batch(16)
    policy, statistics, shield = [], [], []
    action = torch.rand(16, ACT_DIM) * 2 - 1
    for loss in (ensemble, *singles):
        torch.manual_seed(11)
        metadata = loss.actor_loss(batch.clone())[1]
        policy.append(metadata["cvar_policy"])
        statistics.append(metadata["cvar_constraint"])
        shield.append(loss.action_cvar(batch, action))
    for name, readings in (("actor", policy), ("kappa", statistics), ("shield", shield)):
        expected = ucb(torch.stack(readings[1:]), 0.7)
        magnitude = 1.0 + torch.stack(readings[1:]).abs().max()
        assert_close_f32(readings[0], expected, ops=64, magnitude=magnitude, msg=name)
        assert not torch.allclose(readings[0], torch.stack(readings[1:]).max(0)[0])


@pytest.mark.parametrize("kind", ["gaussian", "iqn"])
def test_each_member_learns_as_it_would_alone_and_only_its_own_parameters(kind):
    """Per-member targets: the batched ensemble's TD loss is the sum of the singles',
    and one member's loss sends gradient to its own slice of the stacked parameters only."""
    ensemble, singles = _losses(kind=kind, ensemble_reading="ucb")
    batch = make_batch(16)
    head, params = ensemble.safety_head, ensemble.safety_network_params
    torch.manual_seed(5)
    targets = ensemble.compute_targets(batch.clone())
    values = head.values(batch, params)
    names = list(params.keys(True, True))
    for k in range(3):
        member_values = SafetyValues(*(None if v is None else v[k] for v in values))
        member_targets = {n: None if t is None else t[k] for n, t in targets.items()}
        loss_k = sum(v.mean() for v in head.member.loss(member_values, member_targets).values())
        grads = torch.autograd.grad(
            loss_k, [params.get(n) for n in names], allow_unused=True, retain_graph=True
        )
        for name, grad in zip(names, grads):
            others = torch.cat([grad[:k], grad[k + 1 :]])
            assert torch.count_nonzero(others) == 0, (k, name)
        assert any(torch.count_nonzero(grad[k]) > 0 for grad in grads)
    if kind == "gaussian":  # (an IQN ensemble draws one set of fractions for all members)
        torch.manual_seed(5)
        terms = [t for t in ensemble.safety_loss(batch.clone())[:2] if t is not None]
        alone = []
        for single in singles:
            torch.manual_seed(5)
            alone.append([t for t in single.safety_loss(batch.clone())[:2] if t is not None])
        for i, term in enumerate(terms):
            assert_close_f32(term, sum(a[i] for a in alone), ops=64, msg=f"term {i}")


@pytest.mark.parametrize("kind", ["gaussian", "iqn"])
def test_eight_members_are_one_batched_product_per_layer(kind, monkeypatch):
    ensemble, _ = _losses(members=8, kind=kind, ensemble_reading="ucb")
    head, params = ensemble.safety_head, ensemble.safety_network_params
    calls, baddbmm = [], torch.baddbmm
    monkeypatch.setattr(torch, "baddbmm", lambda *a, **k: calls.append(1) or baddbmm(*a, **k))
    batch = make_batch(16)
    values = head.values(batch, params, stratified=False)
    # Gaussian: 3 layers, mean and variance networks of all 8 members in each product;
    # IQN: the feature MLP's 2 layers, τ's embedding and the merge
    assert len(calls) == (3 if kind == "gaussian" else 4)
    monkeypatch.setattr(torch, "baddbmm", baddbmm)
    for k in range(8):  # the same values as each member's own reading
        own = head.member.values(batch, params[k], stratified=False)
        for got, expected in zip(values, own):
            if got is not None and expected is not None and got.dim() > 1:
                assert_close_f32(got[k], expected, ops=64, magnitude=1.0 + expected.abs().max())


# ------------------------------------------------------------ the merged-quantile tail
def test_tqc_reads_the_upper_tail_of_the_members_merged_quantiles_by_hand():
    member = make_safety_head(
        linear_quantile_critic(),
        WCSACLoss.default_keys(),
        risk_level=0.5,
        options=SafetyHeadOptions(nonnegative_cost=False),
    )
    head = EnsembleHead(member, SafetyHeadOptions(num_safety_nets=2, ensemble_reading="tqc"))
    # [E=2, B=2, N=3]; row 0 merged and sorted: 0 1 2 3 4 5, the upper half 5 4 3
    quantiles = torch.tensor(
        [[[0.0, 1.0, 5.0], [9.0, 9.0, 9.0]], [[2.0, 3.0, 4.0], [-1.0, 0.0, 1.0]]]
    )
    values = SafetyValues(quantiles.mean(-1), None, quantiles)
    # row 1 merged: -1 0 1 9 9 9, the upper half 9 9 9
    assert torch.equal(head.cvar(values), torch.tensor([4.0, 9.0]))
    # α = 0.25: 1.5 atoms of 6, the largest and half the next: (5 + ½·4)/1.5
    head.risk_level = 0.25
    assert_close_f32(head.cvar(values), torch.tensor([14.0 / 3.0, 9.0]), ops=4)
    # the mixture: all 12 atoms pooled, the upper quarter (3 atoms) 9 9 9
    assert torch.equal(head.mixture_cvar(values), torch.tensor(9.0))
    assert_close_f32(
        upper_tail_mean(torch.tensor([[4.0, 0.0, 3.0, 1.0, 2.0]]), 0.5), torch.tensor([3.2]), ops=4
    )


def test_a_tqc_ensemble_in_the_loss_reads_the_merged_tail():
    ensemble, _ = _losses(kind="iqn", ensemble_reading="tqc", risk_level=0.2)
    batch = make_batch(8)
    values = ensemble.safety_head.values(batch, ensemble.safety_network_params, stratified=False)
    merged = values.quantiles.clamp(min=0.0).movedim(0, -2).reshape(8, -1)  # [B, 3·20]
    expected = merged.sort(-1, descending=True).values[:, :12].mean(-1)  # the upper 20 %
    estimates = ensemble.safety_estimates(batch)
    assert_close_f32(estimates["cvar"], expected, ops=16, magnitude=1.0 + expected.abs().max())
    assert estimates["cost_quantiles"].shape == (8, 60)


# ----------------------------------------------------------------- random priors
def _prior_loss(kind="gaussian", reading="ucb"):
    return _losses(kind=kind, ensemble_reading=reading, prior_scale=2.0)[0]


@pytest.mark.parametrize("kind", ["gaussian", "iqn"])
def test_the_prior_is_in_every_reading(kind):
    """Online, target and detached readings, the estimates and the shield all add
    ``scale · p_k(s, a)`` to member k's cost value (to each of an IQN's quantiles)."""
    loss = _prior_loss(kind)
    head, prior = loss.safety_head, loss.safety_prior
    batch = make_batch(8)
    x = torch.cat([batch["observation"], batch["action"]], -1)
    offset = prior(x)  # [E, B]
    assert offset.shape == (3, 8) and offset.abs().min() > 0
    readings = {
        "online": lambda: head.values(batch, loss.safety_network_params, stratified=False),
        "target": lambda: head.values(
            batch, loss.target_safety_network_params, target=True, stratified=False
        ),
        "detached": lambda: head.values(
            batch, loss.safety_network_params.detach(), stratified=False
        ),
    }
    with torch.no_grad():
        got = {name: read() for name, read in readings.items()}
        estimates = loss.safety_estimates(batch)
        shield = loss.action_cvar(batch, batch["action"])
        prior.scale = 0.0
        without = {name: read() for name, read in readings.items()}
        estimates_without = loss.safety_estimates(batch)
        shield_without = loss.action_cvar(batch, batch["action"])
    for name in readings:
        assert_close_f32(
            got[name].mean, without[name].mean + offset, ops=16, magnitude=10.0, msg=name
        )
        if kind == "iqn":
            shifted = without[name].quantiles + offset.unsqueeze(-1)
            assert_close_f32(got[name].quantiles, shifted, ops=16, magnitude=10.0, msg=name)
    assert_close_f32(
        estimates["cost_value"],
        estimates_without["cost_value"] + offset.mean(0),
        ops=16,
        magnitude=10.0,
    )
    assert not torch.allclose(shield, shield_without)


def test_the_prior_is_never_trained_and_the_target_keeps_it():
    loss = _prior_loss()
    prior = loss.safety_prior
    before = {name: value.clone() for name, value in prior.state_dict().items()}
    assert all(not value.requires_grad for value in prior.state_dict().values())
    assert not any("safety_prior" in name for name, _ in loss.named_parameters())
    assert not any(
        "prior" in str(key) for key in loss.target_safety_network_params.keys(True, True)
    )
    assert all(f"safety_prior.{name}" in loss.state_dict() for name in before)
    optimizer = torch.optim.Adam(loss.parameters(), lr=0.1)
    updater = SoftUpdate(loss, tau=0.5)
    for _ in range(2):
        out = loss(make_batch(16))
        optimizer.zero_grad()
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        assert all(value.grad is None for value in prior.state_dict().values())
        optimizer.step()
        updater.step()
    for name, value in prior.state_dict().items():
        assert torch.equal(value, before[name]), name
    # the members differ in their priors, and a fresh loss draws its own
    weight = prior.state_dict()["weight_0"]
    assert not torch.equal(weight[0], weight[1])


def test_a_prior_loss_round_trips_its_state_dict():
    loss, other = _prior_loss(), _losses(ensemble_reading="ucb", prior_scale=2.0)[0]
    with torch.no_grad():
        other.safety_prior.weight_0.add_(1.0)
    other.load_state_dict(loss.state_dict())
    assert torch.equal(other.safety_prior.weight_0, loss.safety_prior.weight_0)


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize(
    ("kwargs", "line"),
    [
        (
            {"ensemble_reading": "ucb"},
            "ensemble_reading=ucb reads an ensemble of safety critics: it needs num_safety_nets >= 2, got 1",
        ),
        (
            {"prior_scale": 1.0},
            "prior_scale > 0 reads an ensemble of safety critics: it needs num_safety_nets >= 2, got 1",
        ),
        ({"num_safety_nets": 2, "k_ucb": -0.5}, "k_ucb must be in [0, 1e+06] (a number), got -0.5"),
        (
            {"num_safety_nets": 2, "prior_scale": -1.0},
            "prior_scale must be in [0, 1e+06] (a number), got -1.0",
        ),
        (
            {"num_safety_nets": 2, "ensemble_reading": "mean"},
            "ensemble_reading must be one of max, ucb, tqc, got 'mean'",
        ),
        (
            {"num_safety_nets": 2, "ensemble_reading": "tqc"},
            "ensemble_reading=tqc merges the members' quantiles: it needs safety_critic=iqn, got a gaussian critic",
        ),
        (
            {"num_safety_nets": 2, "ensemble_reading": "ucb", "ensemble_target": "max"},
            "ensemble_reading=ucb reads the members' disagreement: each bootstraps from its own target (ensemble_target=own), got max",
        ),
    ],
)
def test_the_loss_refuses_a_bad_ensemble_option_in_one_line(kwargs, line):
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=8)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=8) for _ in range(2)]
    critic = make_safety_critic(OBS_DIM, ACT_DIM, width=8)
    with pytest.raises(ValueError, match=f"^{re.escape(line)}$"):
        WCSACLoss(actor, qvalues, critic, **flat_parts(**PLAIN, **kwargs))


@pytest.mark.parametrize(
    ("overrides", "line"),
    [
        (
            ["algo.ensemble_reading=ucb"],
            "algo.ensemble_reading=ucb reads an ensemble of safety critics: it needs algo.num_safety_nets >= 2, got 1",
        ),
        (
            ["algo.num_safety_nets=4", "algo.k_ucb=-1"],
            "algo.k_ucb must be in [0, 1e+06] (a number), got -1",
        ),
        (
            ["algo.num_safety_nets=4", "algo.prior_scale=-0.1"],
            "algo.prior_scale must be in [0, 1e+06] (a number), got -0.1",
        ),
        (
            ["algo.num_safety_nets=2", "algo.safety_critic=gaussian", "algo.ensemble_reading=tqc"],
            "algo.ensemble_reading=tqc merges the members' quantiles: it needs algo.safety_critic=iqn, got a gaussian critic",
        ),
    ],
)
def test_the_config_refuses_a_bad_ensemble_option_in_one_line(tmp_path, overrides, line):
    with pytest.raises(ConfigError, match=f"^{re.escape(line)}") as error:
        make_trainer(compose_config("env=tiny", *overrides), tmp_path / "r")
    assert "\n" not in str(error.value)
    assert not (tmp_path / "r").exists()


SAC_LINE = (
    "unknown config key algo.{key}: an option of the safety critic and κ, which the "
    "algo=sac{where} config does not have (algo=sac_lag, cal and wcsac do)"
)


@pytest.mark.parametrize("key", ["num_safety_nets=4", "ensemble_reading=ucb", "prior_scale=1"])
def test_an_ensemble_option_given_to_sac_is_one_line_naming_it(tmp_path, key):
    name = key.split("=")[0]
    with pytest.raises(ConfigError, match=f"^{re.escape(SAC_LINE.format(key=name, where=''))}$"):
        check_override_keys(["algo=sac", f"algo.{key}"])
    composed = compose_config("env=tiny", "algo=sac", f"+algo.{key}")  # (added: checked composed)
    line = SAC_LINE.format(key=name, where=" env=tiny logger=csv")
    with pytest.raises(ConfigError, match=f"^{re.escape(line)}$"):
        make_trainer(composed, tmp_path / "r")
    assert not (tmp_path / "r").exists()


def test_the_config_reaches_the_reading_and_the_prior(tmp_path):
    cfg = compose_config(
        "env=tiny",
        "algo.num_safety_nets=4",
        "algo.ensemble_reading=ucb",
        "algo.k_ucb=0.25",
        "algo.prior_scale=1.5",
    )
    trainer = make_trainer(cfg, tmp_path / "r")
    try:
        head = trainer.loss.safety_head
        assert (head.reading, head.k_ucb, head.members) == ("ucb", 0.25, 4)
        assert head.prior is trainer.loss.safety_prior and head.prior.scale == 1.5
    finally:
        trainer.close()


# ------------------------------------------------------- CAL's rectification and dual
@pytest.mark.parametrize(
    ("signal", "clamped", "unclamped"),
    [
        # slack 0.4: c·0.4 = 4 > λ = 0.5, CAL's weight λ − min(4, λ) = 0; the authors' −3.5
        ([1.0, 1.2], 0.0, 0.5 - 4.0),
        # slack 0.01: 0.1 < λ, both 0.4
        ([1.48, 1.50], 0.4, 0.4),
        # violated by 1: the weight rises to λ + 10 either way
        ([2.0, 3.0], 10.5, 10.5),
    ],
)
def test_damping_is_cals_rectification_only_when_clamped(signal, clamped, unclamped):
    """CAL: ``λ − clamp(c · mean(d̂ − Q̂(s, a_buffer)), max=λ)``, c = 10; the kit's
    ``damp_scale`` alone is the authors' unclamped MDMM term."""
    from wcsac_rl.objectives.constraint import make_constraint

    threshold, signal = torch.tensor(1.5), torch.tensor(signal)
    for damp_clamp, expected in ((True, clamped), (False, unclamped)):
        constraint = make_constraint(
            "gradient",
            kappa_init=0.5,
            parametrization="log",
            damp_scale=10.0,
            damp_clamp=damp_clamp,
        )
        weight = constraint.penalty_weight(signal, threshold)
        assert_close_f32(weight, torch.tensor(expected), ops=8, magnitude=11.0, msg=str(damp_clamp))


# ------------------------------------------------------ adaptive pessimism (CAP)
def test_adaptive_k_ucb_follows_a_known_cost_sequence():
    """k ← clip(k + lr·(C − d), 0, k_max) per update; NaN (no episode yet) holds it."""
    from wcsac_rl.objectives.ensemble_head import AdaptivePessimism

    cap = AdaptivePessimism(0.5, lr=0.01, k_max=1.0)
    limit, expected = torch.tensor(15.0), []
    k = 0.5
    for cost in (math.nan, 25.0, 45.0, 45.0, 15.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0):
        cap.step(torch.tensor([[cost]]), limit)
        if not math.isnan(cost):
            k = min(max(k + 0.01 * (cost - 15.0), 0.0), 1.0)
        expected.append(k)
        assert_close_f32(cap.k, torch.tensor(k), ops=16, magnitude=1.0, msg=str(cost))
    # 0.5 → 0.6 → 0.9 → 1 (capped) → 1 → 0.9 → 0.75 → 0.6 ... → 0.15
    assert expected[3] == 1.0 and abs(expected[-1] - 0.15) < 1e-12


def test_the_loss_adapts_k_ucb_from_the_batchs_episode_costs_and_reads_it():
    ensemble, singles = _losses(ensemble_reading="ucb", k_ucb=0.5, k_ucb_lr=0.02, k_ucb_max=3.0)
    assert ensemble.safety_pessimism is ensemble.safety_head.pessimism
    batch = make_batch(16)
    with pytest.raises(
        KeyError, match=re.escape("an adaptive k_ucb reads the recent episodes' cost")
    ):
        ensemble(batch.clone())
    batch["episode_cvar"] = torch.full((16, 1), 40.0)  # d = 15: 25 over, k + 0.02·25
    ensemble.train()
    out = ensemble(batch.clone())
    assert_close_f32(ensemble.safety_pessimism.k, torch.tensor(1.0), ops=8, magnitude=1.0)
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()  # (k moved after use)
    ensemble.eval()  # (evaluation mode reads, and does not move, k)
    ensemble(batch.clone())
    assert_close_f32(ensemble.safety_pessimism.k, torch.tensor(1.0), ops=8, magnitude=1.0)
    action = torch.rand(16, ACT_DIM) * 2 - 1
    each = torch.stack([single.action_cvar(batch, action) for single in singles])
    magnitude = 1.0 + each.abs().max()
    assert_close_f32(
        ensemble.action_cvar(batch, action), ucb(each, 1.0), ops=64, magnitude=magnitude
    )
    assert "safety_pessimism.k" in ensemble.state_dict()


@pytest.mark.parametrize(
    ("kwargs", "line"),
    [
        (
            {"k_ucb_lr": 0.1},
            "k_ucb_lr=0.1 adapts the UCB reading's k_ucb: it needs ensemble_reading=ucb, got max",
        ),
        (
            {"ensemble_reading": "ucb", "k_ucb_lr": 0.1, "k_ucb": 3.0},
            "k_ucb must be <= k_ucb_max (2) with k_ucb_lr > 0, got 3",
        ),
        (
            {"ensemble_reading": "ucb", "k_ucb_lr": -0.1},
            "k_ucb_lr must be in [0, 1e+06] (a number), got -0.1",
        ),
    ],
)
def test_a_bad_adaptive_option_is_one_line(kwargs, line):
    with pytest.raises(ValueError, match=f"^{re.escape(line)}$"):
        _losses(members=2, **kwargs)


def test_the_trainer_attaches_the_episode_window_for_an_adaptive_k_ucb(tmp_path):
    cfg = compose_config(
        "env=tiny",
        "algo.num_safety_nets=2",
        "algo.ensemble_reading=ucb",
        "algo.k_ucb_lr=0.01",
        "algo.kappa_episode_statistic=mean",
    )
    trainer = make_trainer(cfg, tmp_path / "r")
    try:
        assert trainer.episode_window is not None
        assert trainer.loss.safety_head.pessimism.k_max == 2.0
    finally:
        trainer.close()


# ----------------------------------------------------------------------- algo=cal
def test_algo_cal_trains_with_cals_critic_rectification_and_dual(tmp_path):
    """``algo=cal``: SAC-Lag's mean critic as a UCB ensemble (E = 4, k = 0.5), CAL's
    rectification (c = 10, clamped), the dual on replay states at the buffer's actions
    against d̂ = d(1 − γ^T)/((1 − γ)T); its κ statistic and loss against hand values."""
    from wcsac_rl import SACLagLoss

    trainer = make_trainer(compose_config("env=tiny", "algo=cal"), tmp_path / "r")
    try:
        loss = trainer.loss
        assert isinstance(loss, SACLagLoss) and loss.safety_critic_kind == "mean"
        head = loss.safety_head
        assert (head.members, head.reading, head.k_ucb, head.target) == (4, "ucb", 0.5, "own")
        assert (loss.damp_scale, loss.constraint.damp_clamp) == (10.0, True)
        assert (loss.kappa_states, loss.kappa_actions, loss.kappa_statistic) == (
            "replay",
            "replay",
            "mean",
        )
        assert loss.constraint.parametrization == "log"
        gamma, steps, d = 0.99, loss.max_episode_steps, 15.0
        assert loss.cost_gamma == gamma
        threshold = d * (1 - gamma**steps) / ((1 - gamma) * steps)
        assert float(loss.cost_threshold) == pytest.approx(threshold, rel=1e-6)
        trainer.run()
        batch = trainer.sample()
        with torch.no_grad():
            members = head.values(batch, loss.safety_network_params).mean  # [4, B], buffer a
        centred = members - members.mean(0)
        by_hand = members.mean(0) + 0.5 * (centred.pow(2).sum(0) / 3).sqrt()
        loss.eval()
        out = loss(batch.clone())
        magnitude = 1.0 + by_hand.abs().max()
        assert_close_f32(out["cvar"], by_hand.mean(), ops=64, magnitude=magnitude)
        expected = (loss.kappa * (threshold - by_hand)).mean()
        assert_close_f32(out["loss_kappa"], expected, ops=64, magnitude=magnitude)
    finally:
        trainer.close()


def test_algo_cal_is_risk_neutral(tmp_path):
    line = "algo=cal is risk-neutral (algo.risk_level=1); use algo=wcsac for α < 1"
    with pytest.raises(ConfigError, match=f"^{re.escape(line)}$"):
        make_trainer(compose_config("env=tiny", "algo=cal", "algo.risk_level=0.5"), tmp_path / "r")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("target", [False, True])
def test_a_batched_iqn_ensembles_skipped_reading_draws_what_its_reading_draws(target):
    """The members share one draw of fractions per reading, and so does a skip (the
    n-step targets' at ``(s', a')``): the random stream after it is the reading's."""
    ensemble, _ = _losses(kind="iqn", ensemble_reading="ucb")
    params = ensemble.target_safety_network_params if target else ensemble.safety_network_params
    torch.manual_seed(3)
    values = ensemble.safety_head.values(make_batch(8), params, target=target)
    after_reading = torch.get_rng_state()
    torch.manual_seed(3)
    ensemble.safety_head.skip_reading(params, target=target)
    assert torch.equal(torch.get_rng_state(), after_reading)
    assert values.fractions.shape == (3, 20) and torch.equal(
        values.fractions[0], values.fractions[2]
    )


def test_merged_targets_pool_every_members_target_quantiles_by_hand():
    """``ensemble_target="merged"`` (TQC, COX-Q): each member regresses on all the
    members' target quantiles, pooled and sorted: ``c + γ·sort(Z̄_0 ∪ Z̄_1)``."""
    member = make_safety_head(
        linear_quantile_critic(),
        WCSACLoss.default_keys(),
        risk_level=0.5,
        options=SafetyHeadOptions(nonnegative_cost=False),
    )
    head = EnsembleHead(
        member,
        SafetyHeadOptions(num_safety_nets=2, ensemble_target="merged", ensemble_reading="tqc"),
    )
    quantiles = torch.tensor([[[0.0, 2.0], [5.0, 6.0]], [[1.0, 3.0], [4.0, 7.0]]])  # [E, B, N']
    ahead = SafetyValues(quantiles.mean(-1), None, quantiles)
    cost, gamma, alive = torch.tensor([1.0, 0.0]), torch.tensor(0.5), torch.tensor([1.0, 0.0])
    targets = head.targets(cost, gamma, alive, ahead)["cost_target_quantiles"]
    # row 0: 1 + 0.5·[0, 1, 2, 3]; row 1: terminated, the cost alone
    expected = torch.tensor([[1.0, 1.5, 2.0, 2.5], [0.0, 0.0, 0.0, 0.0]])
    assert targets.shape == (2, 2, 4) and torch.equal(targets, expected.expand(2, 2, 4))
    line = (
        "ensemble_target=merged pools the members' target quantiles: it needs "
        "safety_critic=iqn, got a gaussian critic"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(line)}$"):
        _losses(members=2, ensemble_target="merged")
    loss, _ = _losses(kind="iqn", ensemble_target="merged", ensemble_reading="tqc")
    out = loss(make_batch(8))  # (each member's loss against the 3·20 pooled targets)
    assert torch.isfinite(out["loss_cost_quantile"])
