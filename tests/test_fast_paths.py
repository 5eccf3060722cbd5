"""The fast paths compute exactly what the general TorchRL paths compute.

Direct tanh-Normal sampling (``direct_sampling``), the inline TD(0) reward target,
``PolyakUpdate`` and ``TanhNormalPolicy`` are there for speed only; each is checked here against the
path it replaces: same values, same gradients, same fall-backs.
"""

from __future__ import annotations

import pytest
import torch
from _loss_helpers import (
    ACT_DIM,
    OBS_DIM,
    assert_same_losses_and_gradients,
    make_batch,
    make_loss,
)
from _tolerance import assert_close_f32
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.objectives import SoftUpdate

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.modules.tanh_normal import (
    TanhNormalPolicy,
    sample_tanh_normal,
    tanh_normal_actor_plan,
)
from wcsac_rl.objectives import PAPER_OPTIONS, PolyakUpdate


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
    plan = tanh_normal_actor_plan(actor)
    assert plan is not None
    assert (plan.low is None) == isinstance(low, float)  # no affine map for [-1, 1]
    params = TensorDict.from_module(actor)
    observation = loc_scale * torch.randn(64, OBS_DIM)
    grads = []
    for draw in ("direct", "torchrl"):
        actor.zero_grad(set_to_none=True)
        torch.manual_seed(3)
        if draw == "direct":
            action, log_prob = sample_tanh_normal(plan, params, observation)
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
    direct = make_loss(variance=variance, direct_sampling=True, damp_scale=1.0)
    general = make_loss(variance=variance, direct_sampling=False, damp_scale=1.0)
    assert direct._actor_plan is not None and general._actor_plan is None
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
    loss = WCSACLoss(actor, qvalues, safety, **PAPER_OPTIONS)
    assert loss._actor_plan is None
    out = loss(make_batch())  # the general path still works
    assert torch.isfinite(out["loss_actor"])
    with pytest.raises(ValueError, match="direct_sampling=True needs"):
        WCSACLoss(actor, qvalues, safety, direct_sampling=True)
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
