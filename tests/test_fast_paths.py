"""The fast paths compute exactly what the general TorchRL paths compute.

Direct tanh-Normal sampling (``DirectSampling``), the inline TD(0) reward target,
``PolyakUpdate``, ``TanhNormalPolicy`` and the twin critic read from its stacked weights
(``evaluate_stacked_mlp``) are there for speed only (``fast_paths``:
``wcsac_rl.objectives.fast_paths``); each is checked here against the path it replaces:
same values, same gradients, same fall-backs.
"""

from __future__ import annotations

import pytest
import torch
from _loss_helpers import (
    ACT_DIM,
    OBS_DIM,
    assert_same_losses_and_gradients,
    flat_parts,
    make_batch,
    make_loss,
    paper_options,
)
from _tolerance import assert_close_f32
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SoftUpdate

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.modules.actor import TanhNormalPolicy, tanh_normal_actor_plan
from wcsac_rl.objectives import PAPER_OPTIONS, PolyakUpdate
from wcsac_rl.objectives.fast_paths import (
    DirectSampling,
    evaluate_stacked_mlp,
    stacked_mlp_layout,
)


def _torchrl_draw(actor, observation):
    dist = actor.get_dist(TensorDict({"observation": observation}, observation.shape[:1]))
    return dist.rsample_and_log_prob()


@pytest.mark.parametrize(
    "low, high", [(-1.0, 1.0), (torch.tensor([-2.0, 0.0]), torch.tensor([0.5, 3.0]))]
)
@pytest.mark.parametrize("loc_scale", [1.0, 30.0], ids=["moderate", "saturated"])
def test_direct_draw_equals_torchrl_tanh_normal(low, high, loc_scale):
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(low, high, shape=(ACT_DIM,)), width=16)
    sampling = DirectSampling.of(actor)
    assert sampling is not None
    plan = sampling.plan
    assert (plan.low is None) == isinstance(low, float)  # no affine map for [-1, 1]
    params = TensorDict.from_module(actor)
    observation = loc_scale * torch.randn(64, OBS_DIM)
    grads = []
    for draw in ("direct", "torchrl"):
        actor.zero_grad(set_to_none=True)
        torch.manual_seed(3)
        if draw == "direct":
            action, log_prob = sampling.sample(params, observation)
        else:
            action, log_prob = _torchrl_draw(actor, observation)
        (action.sum() + log_prob.sum()).backward()
        grads.append(({n: p.grad.clone() for n, p in actor.named_parameters()}, action, log_prob))
    (g_direct, a_direct, lp_direct), (g_torchrl, a_torchrl, lp_torchrl) = grads
    # actions and log-probabilities: a few roundings after the MLP's 16-term sums,
    # relative to their largest value
    assert_close_f32(a_direct, a_torchrl, ops=16, msg="action")
    assert_close_f32(lp_direct, lp_torchrl, ops=16, msg="log_prob")
    assert torch.isfinite(lp_direct).all()
    for name in g_torchrl:
        # each gradient entry sums 64 per-sample terms (the batch), whose size is that
        # of the tensor's largest entry: with loc_scale 30 the terms reach 10³ and
        # cancel, so an entry's own size is no scale (it failed on AVX-512 by 2e-5)
        assert_close_f32(g_direct[name], g_torchrl[name], ops=64, msg=name)
    if loc_scale == 30.0:  # the draws really saturate the tanh
        assert ((a_direct - torch.as_tensor(high)).abs() < 1e-5).any() or (
            (a_direct - torch.as_tensor(low)).abs() < 1e-5
        ).any()


@pytest.mark.parametrize("variance", [True, False])
def test_direct_sampling_gives_the_same_losses_and_gradients(variance):
    direct = make_loss(variance=variance, damp_scale=1.0)
    general = make_loss(variance=variance, damp_scale=1.0)
    general._paths.sampling = None  # the actor's distribution, every other path the same
    assert direct.fast_paths["direct_sampling"] == "taken"
    general.load_state_dict(direct.state_dict())
    assert_same_losses_and_gradients(direct, general, make_batch())


def _actor_not_from_make_actor() -> ProbabilisticActor:
    """A tanh-Normal actor with TorchRL's NormalParamExtractor, not the kit's layout."""
    net = nn.Sequential(nn.Linear(OBS_DIM, 2 * ACT_DIM), NormalParamExtractor())
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=Bounded(-1.0, 1.0, shape=(ACT_DIM,)),
        distribution_class=TanhNormal,
    )


def test_actors_not_built_like_make_actor_fall_back_or_are_refused():
    torch.manual_seed(0)
    spec = Bounded(-1.0, 1.0, shape=(ACT_DIM,))
    actor = _actor_not_from_make_actor()
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=8) for _ in range(2)]
    safety = make_safety_critic(OBS_DIM, ACT_DIM, width=8)
    loss = WCSACLoss(actor, qvalues, safety, **flat_parts(**PAPER_OPTIONS))
    assert loss.fast_paths["direct_sampling"].startswith("not taken: it is not built like")
    out = loss(make_batch())  # the general path still works
    assert torch.isfinite(out["loss_actor"])
    with pytest.raises(ValueError, match="fast_paths=True needs the actor sampled"):
        WCSACLoss(actor, qvalues, safety, fast_paths=True)
    # a TanhNormal with options beyond the bounds is not taken over either
    tanh_loc = make_actor(OBS_DIM, spec, width=8)
    tanh_loc.module[-1].distribution_kwargs["tanh_loc"] = True
    assert tanh_normal_actor_plan(tanh_loc) is None


def test_inline_td0_target_equals_torchrl_estimator_and_defers_to_it_when_needed():
    loss = make_loss()
    loss.make_value_estimator(gamma=0.9)
    batch = make_batch()
    next_value = torch.randn(16, 1)
    expected_td = batch.clone(False)
    expected_td.set(("next", "state_value"), next_value)
    expected = loss.value_estimator.value_estimate(expected_td)
    # the same elementwise operations in the same order (r + γ·(1 − term)·V), each
    # correctly rounded on every CPU: bitwise equal
    torch.testing.assert_close(loss._reward_target(batch, next_value), expected, rtol=0, atol=0)
    # multi-step batches carry steps_to_next_obs: the estimator's γ^n is used
    batch.set("steps_to_next_obs", torch.full((16, 1), 3))
    terminated = batch["next", "terminated"]
    want = batch["next", "reward"] + 0.9**3 * (~terminated).float() * next_value
    # γ³ rounded to float32 once here and as a float32 power there, then a product and
    # a sum: 4 roundings of the target's size
    assert_close_f32(loss._reward_target(batch, next_value), want, ops=4)


def test_polyak_update_equals_torchrl_soft_update():
    losses = [make_loss(seed=0), make_loss(seed=0)]
    updaters = [SoftUpdate(losses[0], tau=0.05), PolyakUpdate(losses[1], tau=0.05)]
    optimizers = [torch.optim.SGD(loss.parameters(), lr=0.1) for loss in losses]
    for step in range(3):
        for loss, updater, optimizer in zip(losses, updaters, optimizers):
            torch.manual_seed(step)
            out = loss(make_batch(seed=step))
            sum(v for k, v in out.items() if k.startswith("loss_")).backward()
            optimizer.step()
            optimizer.zero_grad()
            updater.step()
    soft, polyak = (dict(loss.named_buffers()) for loss in losses)
    targets = [name for name in soft if name.startswith("target_")]
    assert len(targets) >= 12  # twin reward critic, safety mean and variance networks
    for name in targets:
        # one fused lerp against a multiply and an add, per step: ≤ 4 roundings of the
        # parameters' size in each of the 3 steps
        assert_close_f32(polyak[name], soft[name], ops=12, msg=name)
    # and the targets moved away from their initial copy
    initial = make_loss(seed=0)
    moved = [
        name
        for name in targets
        if not torch.equal(polyak[name], dict(initial.named_buffers())[name])
    ]
    assert set(moved) == set(targets)


@pytest.mark.parametrize(
    "low, high", [(-1.0, 1.0), (torch.tensor([-2.0, 0.0]), torch.tensor([0.5, 3.0]))]
)
@pytest.mark.parametrize("exploration", [None, "random", "deterministic", "mean"])
def test_tanh_normal_policy_acts_like_the_actor(low, high, exploration):
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(low, high, shape=(ACT_DIM,)), width=16)
    policy = TanhNormalPolicy(actor)
    observation = 3 * torch.randn(32, OBS_DIM)
    outputs = []
    for module in (policy, actor):
        torch.manual_seed(4)
        td = TensorDict({"observation": observation}, [32])
        if exploration is None:  # the actor's default: random
            outputs.append(module(td))
        else:
            with set_exploration_type(ExplorationType.from_str(exploration)):
                outputs.append(module(td))
    fast, reference = outputs
    assert set(fast.keys()) == set(reference.keys()) == {"observation", "loc", "scale", "action"}
    for key in ("loc", "scale", "action"):
        # the same MLP (16-term sums) then a few elementwise steps, relative to the
        # largest entry
        assert_close_f32(fast[key], reference[key], ops=16, msg=key)
    low_t, high_t = torch.as_tensor(low), torch.as_tensor(high)
    assert ((fast["action"] >= low_t) & (fast["action"] <= high_t)).all()


def test_tanh_normal_policy_refuses_other_actors_and_follows_training():
    with pytest.raises(ValueError, match=r"built like wcsac_rl\.modules\.make_actor"):
        TanhNormalPolicy(_actor_not_from_make_actor())
    loss = make_loss()
    policy = TanhNormalPolicy(loss.actor_network)
    td = TensorDict({"observation": torch.randn(4, OBS_DIM)}, [4])
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        before = policy(td.clone())["action"]
        with torch.no_grad():  # an optimiser step on the loss's actor parameters
            for p in loss.actor_network_params.values(True, True):
                p.add_(0.1)
        after = policy(td.clone())["action"]
    assert not torch.allclose(before, after)


# ------------------------------------------------ the twin critic read without vmap
def _grads_and_values(loss, batch, seed=5):
    torch.manual_seed(seed)
    out = loss(batch.clone())
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    return out, {n: p.grad.clone() for n, p in loss.named_parameters() if p.grad is not None}


@pytest.mark.parametrize("activation", ["relu", "tanh", "elu", "gelu"])
@pytest.mark.parametrize("shape", [(64,), (1,), (3, 5)])
def test_stacked_mlp_is_the_vmapped_twin_critic_bit_for_bit(activation, shape):
    """``evaluate_stacked_mlp`` replaces TorchRL's vmapped call of the twin critic: the
    same values and the same gradients (to the stacked weights and to the action), equal
    to the last bit, at any batch shape."""
    torch.manual_seed(0)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=16, activation=activation) for _ in range(2)]
    safety = make_safety_critic(OBS_DIM, ACT_DIM, kind="iqn", width=16)
    loss = WCSACLoss(
        make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=16), qvalues, safety
    )
    layout = stacked_mlp_layout(loss.qvalue_network, "action")
    assert layout is not None and loss.critics.stacked == layout
    g = torch.Generator().manual_seed(1)
    observation = torch.randn(*shape, OBS_DIM, generator=g)
    readings = []
    for path in ("vmap", "stacked"):
        action = (
            torch.rand(*shape, ACT_DIM, generator=torch.Generator().manual_seed(2)) * 2 - 1
        ).requires_grad_()
        params = loss.qvalue_network_params.apply(lambda p: p.detach().clone().requires_grad_())
        if path == "vmap":
            td = TensorDict({"observation": observation, "action": action}, shape)
            q = loss._vmap_qnetworkN0(td, params).get("state_action_value")
        else:
            q = evaluate_stacked_mlp(torch.cat([observation, action], -1), params, layout)
        weights = torch.randn(q.shape, generator=torch.Generator().manual_seed(3))
        (q * weights).sum().backward()
        readings.append((q.detach(), action.grad, [p.grad for p in params.values(True, True)]))
    (q_v, a_v, g_v), (q_s, a_s, g_s) = readings
    assert q_v.shape == q_s.shape == (2, *shape, 1)
    assert torch.equal(q_v, q_s) and torch.equal(a_v, a_s)
    assert len(g_v) == len(g_s) == 6 and all(torch.equal(x, y) for x, y in zip(g_v, g_s))


def _through_module_calls(loss):
    """What the loss did before: the twin through TorchRL's vmapped call, the IQN
    critic through its module."""
    loss.critics.read_through_modules()
    assert loss.critics.stacked is None and getattr(loss.safety_head, "_reader", None) is None
    return loss


def _unfused(loss):
    """The Gaussian critic read apart from the twin, the twin from its stacked weights."""
    loss._paths.fused = None
    loss._paths.stacked = stacked_mlp_layout(loss.qvalue_network, "action")
    return loss


def _torchrl_networks_loss(**kwargs):
    """A TorchRL user's own networks: ``torchrl.modules.MLP`` critics, a two-MLP safety critic."""
    torch.manual_seed(0)
    actor = _actor_not_from_make_actor()
    qvalue = ValueOperator(
        MLP(in_features=OBS_DIM + ACT_DIM, out_features=1, num_cells=[16, 16]),
        in_keys=["observation", "action"],
    )
    safety = TensorDictModule(
        _MeanVariance(), in_keys=["observation", "action"], out_keys=["cost_value", "cost_variance"]
    )
    return WCSACLoss(actor, qvalue, safety, **flat_parts(num_qvalue_nets=2, **kwargs))


class _MeanVariance(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.mean = MLP(in_features=OBS_DIM + ACT_DIM, out_features=1, num_cells=[16, 16])
        self.variance = MLP(in_features=OBS_DIM + ACT_DIM, out_features=1, num_cells=[16, 16])

    def forward(self, observation, action):
        return self.mean(observation, action), nn.functional.softplus(
            self.variance(observation, action)
        )


@pytest.mark.parametrize(
    "build",
    [
        lambda: make_loss(kind="iqn", width=16),  # the kit's default critic
        lambda: _unfused(make_loss(width=16)),  # the Gaussian critic, unfused
        lambda: make_loss(kind="iqn", width=16, cost_n_steps=3, kappa_states="initial"),
        lambda: _torchrl_networks_loss(**PAPER_OPTIONS),
    ],
    ids=["iqn", "gaussian-unfused", "iqn-nstep-start-states", "torchrl-networks"],
)
def test_loss_reads_critics_without_module_calls_and_gives_the_same_bits(build):
    """Every loss output and every parameter gradient, over two optimizer steps, is the
    same bit for bit whether the twin critic is read from its stacked weights (and the
    IQN critic from its parameters) or through TorchRL's vmapped call (and the
    module)."""
    direct, general = build(), _through_module_calls(build())
    assert direct.critics.stacked is not None and direct.critics.fused is None
    if direct.safety_critic_kind == "iqn":
        assert direct.safety_head._reader is not None
    general.load_state_dict(direct.state_dict())
    batch = make_batch(initial=True, seed=4)
    batch["nstep"] = TensorDict(  # read by the n-step case only
        {
            "observation": batch["next", "observation"],
            "cost": batch["next", "cost"],
            "steps": torch.full((16, 1), 3),
            "terminated": batch["next", "terminated"],
        },
        [16],
    )
    optimizers = [torch.optim.Adam(loss.parameters(), lr=1e-2) for loss in (direct, general)]
    for step in range(2):
        results = []
        for loss, optimizer in zip((direct, general), optimizers):
            optimizer.zero_grad()
            results.append(_grads_and_values(loss, batch, seed=step))
            optimizer.step()
        (out_d, grad_d), (out_g, grad_g) = results
        assert out_d.keys() == out_g.keys() and grad_d.keys() == grad_g.keys()
        for key in out_d.keys():
            assert torch.equal(out_d[key], out_g[key]), key
        for name in grad_d:
            assert torch.equal(grad_d[name], grad_g[name]), name


class _ScaledMLP(MLP):
    def forward(self, *inputs):  # not TorchRL's forward: reading its weights would be wrong
        return 2 * super().forward(*inputs)


def test_twin_critics_not_read_as_torchrl_mlps_keep_the_vmapped_call():
    torch.manual_seed(0)
    assert make_loss(width=8).critics.stacked is None  # fused with the Gaussian critic instead
    assert make_loss(kind="iqn", width=8, deactivate_vmap=True).critics.stacked is None
    spec = Bounded(-1.0, 1.0, shape=(ACT_DIM,))
    safety = make_safety_critic(OBS_DIM, ACT_DIM, kind="iqn", width=8)
    for module in (
        _ScaledMLP(in_features=OBS_DIM + ACT_DIM, out_features=1, num_cells=[8]),
        MLP(
            in_features=OBS_DIM + ACT_DIM,
            out_features=1,
            num_cells=[8],
            norm_class=nn.LayerNorm,
            norm_kwargs={"normalized_shape": 8},
        ),
        MLP(in_features=OBS_DIM + ACT_DIM, out_features=(1,), num_cells=[8]),
    ):
        qvalue = ValueOperator(module, in_keys=["observation", "action"])
        loss = WCSACLoss(
            make_actor(OBS_DIM, spec, width=8),
            qvalue,
            safety,
            **flat_parts("iqn", num_qvalue_nets=2, **paper_options("iqn")),
        )
        assert loss.critics.stacked is None, type(module).__name__
        out = loss(make_batch())  # the vmapped call still serves it
        assert torch.isfinite(out["loss_qvalue"])


def test_one_keyword_switches_every_path_and_the_loss_reports_them():
    fast, general = make_loss(kind="iqn", width=8), make_loss(kind="iqn", width=8, fast_paths=False)
    assert fast.fast_paths == {
        "direct_sampling": "taken",
        "fused_critics": "not taken: an IQN safety critic is not fused with the reward "
        "critics (it also reads quantile fractions)",
        "stacked_qvalue": "taken",
        "safety_read": "taken",
        "td0_target": "taken",
    }
    assert set(general.fast_paths.values()) == {"not taken: fast_paths=False"}
    assert general.critics.stacked is None and general.safety_head._reader is None
    assert make_loss(width=8).fast_paths["fused_critics"] == "taken"
    with pytest.raises(ValueError, match="fast_paths must be None, True or False"):
        make_loss(fast_paths="yes")
