"""WCSACLoss: gradient routing, targets, keys, reductions, state dict, errors."""

from __future__ import annotations

import math

import pytest
import torch
from _loss_helpers import (
    ACT_DIM,
    LOSS_KEYS,
    OBS_DIM,
    assert_same_losses_and_gradients,
    make_batch,
    make_loss,
    recipe_kwargs,
)
from _tolerance import assert_close_f32
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.objectives import SoftUpdate
from torchrl.objectives.utils import ValueEstimators

from wcsac_rl import SACLagLoss, WCSACLoss, per_step_cost_threshold
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PAPER_OPTIONS, loss_parts

# Which parameter groups each loss term may (and must) send gradients to.
OWNERS = {
    "loss_actor": "actor_network_params.",
    "loss_qvalue": "qvalue_network_params.",
    "loss_cost_value": "safety_network_params.module.mean_net.",
    "loss_cost_variance": "safety_network_params.module.variance_net.",
    "loss_kappa": "constraint.kappa_raw",
    "loss_alpha": "log_alpha",
}


def _grads_after(loss: WCSACLoss, key: str, batch) -> dict[str, torch.Tensor | None]:
    loss.zero_grad(set_to_none=True)
    out = loss(batch)
    out[key].backward()
    return {name: p.grad for name, p in loss.named_parameters()}


@pytest.mark.parametrize("fast", [True, False], ids=["fused+direct", "modules"])
@pytest.mark.parametrize(
    ("kappa_actions", "kappa_states", "kappa_statistic"),
    [
        ("replay", "replay", "mean"),
        ("policy", "replay", "mean"),
        ("policy", "initial", "mean"),
        ("policy", "initial", "tail"),
    ],
)
@pytest.mark.parametrize("damp_scale", [0.0, 10.0])
@pytest.mark.parametrize("key", LOSS_KEYS)
def test_each_loss_term_reaches_exactly_its_own_parameters(
    key, kappa_actions, kappa_states, kappa_statistic, damp_scale, fast
):
    loss = make_loss(
        kappa_actions=kappa_actions,
        kappa_states=kappa_states,
        kappa_statistic=kappa_statistic,
        variance_target="td" if kappa_states == "initial" else "moment",
        damp_scale=damp_scale,
        fast_paths=fast,
    )
    grads = _grads_after(loss, key, make_batch(initial=kappa_states == "initial"))
    owner = OWNERS[key]
    owned = {n for n in grads if n.startswith(owner)}
    assert owned, f"no parameter matches {owner}"
    for name, grad in grads.items():
        if name in owned:
            assert grad is not None and grad.abs().sum() > 0, f"{key} gave no gradient to {name}"
        else:
            assert grad is None or grad.abs().sum() == 0, f"{key} leaked a gradient into {name}"


@pytest.mark.parametrize("fast", [False, True])
@pytest.mark.parametrize("variance_loss", ["w2", "glm"])
def test_every_variance_loss_reaches_only_the_variance_network(variance_loss, fast):
    loss = make_loss(variance_loss=variance_loss, fast_paths=fast)
    grads = _grads_after(loss, "loss_cost_variance", make_batch())
    owner = OWNERS["loss_cost_variance"]
    assert any(name.startswith(owner) for name in grads)
    for name, grad in grads.items():
        if name.startswith(owner):
            assert grad is not None and grad.abs().sum() > 0, f"no gradient to {name}"
        else:
            assert grad is None or grad.abs().sum() == 0, f"leaked a gradient into {name}"


def test_target_parameters_get_no_gradient_and_follow_soft_update():
    loss = make_loss()
    updater = SoftUpdate(loss, tau=0.1)
    optim = torch.optim.SGD(loss.parameters(), lr=0.5)
    out = loss(make_batch())
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    for name, buf in loss.named_buffers():
        if name.startswith("target_"):
            assert buf.grad is None and not buf.requires_grad, name

    before = loss.target_safety_network_params.clone()
    optim.step()
    updater.step()
    online = loss.safety_network_params.detach()
    after = loss.target_safety_network_params
    for key, target in after.items(True, True):
        torch.testing.assert_close(target, 0.9 * before[key] + 0.1 * online[key])
        assert not torch.equal(target, before[key]), key  # it moved
    # the reward critic's targets are updated too
    moved = loss.target_qvalue_network_params != loss.qvalue_network_params.detach()
    assert any(bool(v.any()) for v in moved.values(True, True))


def test_loss_terms_and_diagnostics_are_finite_scalars():
    loss = make_loss(risk_level=0.1)
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
    assert out["kappa"] == pytest.approx(math.log(2.0), rel=1e-6)  # softplus(0)
    assert out["cost_variance"] > 0
    # cvar is the mean of Q^c + multiplier·√V^c at the κ-loss (policy) actions
    assert torch.isfinite(out["cvar"])


def _identical_losses(**kwargs):
    a, b = make_loss(seed=0, **kwargs), make_loss(seed=1, **kwargs)
    b.load_state_dict(a.state_dict())
    return a, b


def test_state_dict_round_trip_restores_every_parameter_buffer_and_output():
    a = make_loss(risk_level=0.1, kappa_init=2.5)
    with torch.no_grad():
        a.log_alpha.fill_(-1.3)
    b = make_loss(seed=7, risk_level=0.1)
    b.load_state_dict(a.state_dict())
    for (na, pa), (nb, pb) in zip(a.state_dict().items(), b.state_dict().items()):
        assert na == nb and torch.equal(pa, pb), na
    assert b.kappa == pytest.approx(2.5, rel=1e-5)
    batch = make_batch()
    torch.manual_seed(3)
    out_a = a(batch.clone())
    torch.manual_seed(3)
    out_b = b(batch.clone())
    for key in out_a.keys():
        torch.testing.assert_close(out_a[key], out_b[key])


@pytest.mark.parametrize("reduction", ["mean", "sum"])
def test_reduction_none_matches_mean_and_sum(reduction):
    batch = make_batch(batch=12)
    none_loss = make_loss(reduction="none", scalar_output_mode="exclude")
    other = make_loss(reduction=reduction)
    torch.manual_seed(0)
    per_sample = none_loss(batch.clone())
    torch.manual_seed(0)
    reduced = other(batch.clone())
    assert per_sample.batch_size == torch.Size([12])
    for key in LOSS_KEYS:
        assert per_sample[key].shape == (12,), key
        expected = per_sample[key].mean() if reduction == "mean" else per_sample[key].sum()
        torch.testing.assert_close(reduced[key], expected, rtol=1e-5, atol=1e-5)


def test_cost_shaped_like_batch_or_like_reward_gives_identical_losses():
    a, b = _identical_losses()
    torch.manual_seed(0)
    out_1 = a(make_batch(cost_shape_1=True))
    torch.manual_seed(0)
    out_0 = b(make_batch(cost_shape_1=False))
    for key in LOSS_KEYS:
        torch.testing.assert_close(out_1[key], out_0[key])


def _rename(batch: TensorDict) -> TensorDict:
    return TensorDict(
        {
            "obs": batch["observation"],
            "act": batch["action"],
            "next": {
                "obs": batch["next", "observation"],
                "rew": batch["next", "reward"],
                ("safety", "c"): batch["next", "cost"],
                "dn": batch["next", "done"],
                "term": batch["next", "terminated"],
            },
        },
        batch.batch_size,
    )


def test_set_keys_with_custom_names_gives_the_same_losses():
    reference = make_loss(width=16)
    torch.manual_seed(0)
    actor = make_actor(
        OBS_DIM,
        Bounded(-1.0, 1.0, shape=(ACT_DIM,)),
        observation_key="obs",
        action_key="act",
        width=16,
    )
    qvalues = [
        make_qvalue(
            OBS_DIM, ACT_DIM, observation_key="obs", action_key="act", out_key="q", width=16
        )
        for _ in range(2)
    ]
    safety = make_safety_critic(
        OBS_DIM,
        ACT_DIM,
        observation_key="obs",
        action_key="act",
        cost_value_key=("safety", "mean"),
        cost_variance_key=("safety", "var"),
        width=16,
    )
    custom = WCSACLoss(actor, qvalues, safety, risk_level=0.5, **loss_parts(PAPER_OPTIONS))
    # the safety critic's out keys are adopted (mean first, variance second)
    assert custom.tensor_keys.cost_value == ("safety", "mean")
    assert custom.tensor_keys.cost_variance == ("safety", "var")
    custom.set_keys(
        state_action_value="q", reward="rew", cost=("safety", "c"), done="dn", terminated="term"
    )
    assert custom.tensor_keys.action == "act"
    assert ("next", ("safety", "c")) in custom.in_keys or ("next", "safety", "c") in custom.in_keys
    custom.load_state_dict(reference.state_dict())

    batch = make_batch()
    torch.manual_seed(1)
    expected = reference(batch.clone())
    torch.manual_seed(1)
    got = custom(_rename(batch))
    for key in expected.keys():
        torch.testing.assert_close(got[key], expected[key])


def test_mean_only_critic_is_sac_lag_without_variance_parameters():
    loss = make_loss(variance=False)
    assert not loss.has_variance
    assert not any("variance" in n for n, _ in loss.named_parameters())
    out = loss(make_batch())
    assert "loss_cost_variance" not in out.keys() and "cost_variance" not in out.keys()
    # Γ = Q^c: the κ loss uses the mean alone
    torch.testing.assert_close(
        out["loss_kappa"], loss.kappa * (out["cost_threshold"] - out["cvar"])
    )

    torch.manual_seed(0)
    lag = SACLagLoss(
        make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=8),
        [make_qvalue(OBS_DIM, ACT_DIM, width=8) for _ in range(2)],
        make_safety_critic(OBS_DIM, ACT_DIM, variance=False, width=8),
        **loss_parts(PAPER_OPTIONS),
    )
    assert isinstance(lag, WCSACLoss) and lag.risk_level == 1.0 and lag.cvar_multiplier == 0.0
    assert set(lag(make_batch()).keys()) == set(lag.out_keys)


def test_risk_neutral_wcsac_ignores_the_variance_in_its_cvar():
    loss = make_loss(risk_level=1.0)
    assert loss.has_variance and loss.cvar_multiplier == 0.0
    mean, var = torch.tensor([1.0, 2.0]), torch.tensor([4.0, 9.0])
    torch.testing.assert_close(loss.cvar(mean, var), mean)
    loss01 = make_loss(risk_level=0.1)
    torch.testing.assert_close(loss01.cvar(mean, var), mean + 1.7549833 * var.sqrt())


# ---------------------------------------------------------------- thresholds
def test_per_step_threshold_matches_spec_and_follows_gamma():
    assert per_step_cost_threshold(15.0, 0.99, 1000) == pytest.approx(1.49994, abs=1e-5)
    assert per_step_cost_threshold(15.0, 1.0, 1000) == pytest.approx(15.0)
    assert per_step_cost_threshold(3.0, 0.99, 1) == pytest.approx(3.0)
    loss = make_loss(cost_limit=15.0, max_episode_steps=1000)
    assert float(loss.cost_threshold) == pytest.approx(1.49994, abs=1e-5)
    loss.make_value_estimator(gamma=0.9)
    assert float(loss.value_estimator.gamma) == pytest.approx(0.9)
    assert float(loss.cost_threshold) == pytest.approx(15.0 * (1 - 0.9**1000) / (0.1 * 1000))
    explicit = make_loss(cost_threshold=0.25)
    explicit.make_value_estimator(gamma=0.5)
    assert float(explicit.cost_threshold) == pytest.approx(0.25)


def test_kappa_at_initial_states_reads_only_the_start_states_and_holds_gamma_under_d():
    loss = make_loss(risk_level=0.1, kappa_states="initial", cost_limit=15.0)
    assert float(loss.cost_threshold) == pytest.approx(15.0)  # Γ(s₀) vs the episodic limit
    batch = make_batch(initial=True)

    def kappa_terms(td):
        torch.manual_seed(3)
        out = loss(td)
        return out["loss_kappa"], out["cvar"]

    base_kappa, base_cvar = kappa_terms(batch.clone())
    # Γ(s₀, a₀ ~ π) recomputed through the public pieces, with the same action noise
    torch.manual_seed(3)
    loss.compute_targets(batch.clone())  # the forward draws a' ~ π(s') first, then a₀
    action0, _ = loss._sample_policy(batch["initial"])
    expected = loss.safety_estimates(batch["initial"].set("action", action0))["cvar"]
    # the forward evaluates the critics fused, safety_estimates one module at a time:
    # ~130 roundings (3 layers over 7 + 32 + 32 inputs, √V, the mean over 16 rows) of
    # values of order 1 + |Γ|
    scale = 1.0 + float(expected.abs().max())
    assert_close_f32(base_cvar, expected.mean(), ops=160, magnitude=scale)
    assert_close_f32(base_kappa, loss.kappa * (15.0 - expected.mean()), ops=160, magnitude=15.0)
    # other replay observations leave the κ term alone; other start states move it
    moved = batch.clone()
    moved["observation"] = moved["observation"] + 3.0
    torch.testing.assert_close(kappa_terms(moved)[0], base_kappa)
    moved_start = batch.clone()
    moved_start["initial", "observation"] = moved_start["initial", "observation"] - 3.0
    assert not torch.allclose(kappa_terms(moved_start)[0], base_kappa)
    with pytest.raises(KeyError, match="start states"):
        loss(make_batch())
    assert loss.initial_state_keys == ["observation"]


@pytest.mark.parametrize("kappa_states", ["initial", "replay"])
def test_tail_statistic_is_the_cvar_of_the_critic_mixed_over_the_states(kappa_states):
    from wcsac_rl.objectives import gaussian_mixture_cvar

    loss = make_loss(risk_level=0.1, kappa_states=kappa_states, kappa_statistic="tail")
    batch = make_batch(initial=True)
    torch.manual_seed(3)
    out = loss(batch.clone())
    torch.manual_seed(3)
    loss.compute_targets(batch.clone())
    states = batch["initial"] if kappa_states == "initial" else batch
    action, _ = loss._sample_policy(states)
    est = loss.safety_estimates(states.clone().set("action", action))
    expected = gaussian_mixture_cvar(est["cost_value"], est["cost_variance"], 0.1)
    # the same Γ recomputed from the same draws; bisection to 2⁻⁵⁰ of the bracket
    # fused vs module-by-module critics (as above), then the same bisection on both
    scale = 1.0 + float(est["cvar"].abs().max())
    assert_close_f32(out["cvar"], expected, ops=160, magnitude=scale)
    assert_close_f32(
        out["loss_kappa"], loss.kappa * (loss.cost_threshold - expected), ops=160, magnitude=scale
    )
    # the tail of the mixture is above the mean of per-state Γ
    assert float(expected) >= float(est["cvar"].mean())
    with pytest.raises(ValueError, match="kappa_statistic must be one of"):
        make_loss(kappa_statistic="max")


def test_safety_estimates_are_the_safety_critics_own_outputs():
    loss = make_loss(risk_level=0.1)
    batch = make_batch()
    est = loss.safety_estimates(batch)
    with loss.safety_network_params.to_module(loss.safety_network):
        out = loss.safety_network(batch.select("observation", "action"))
    torch.testing.assert_close(est["cost_value"], out["cost_value"].squeeze(-1))
    torch.testing.assert_close(est["cost_variance"], out["cost_variance"].squeeze(-1))
    torch.testing.assert_close(est["cvar"], loss.cvar(est["cost_value"], est["cost_variance"]))
    assert not est["cvar"].requires_grad
    lag = make_loss(variance=False)
    assert set(lag.safety_estimates(batch).keys()) == {"cost_value", "cvar"}


# ------------------------------------------------------------ analytic targets
class _ReadOut(nn.Module):
    """Q^c = obs[0] and V^c = obs[1]: a 'critic' whose outputs are set by the batch."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.ones(()))

    def forward(self, observation, action):
        return self.scale * observation[..., :1], self.scale * observation[..., 1:2]


def _readout_loss(variance_loss: str, gamma: float = 0.9, **kwargs) -> WCSACLoss:
    torch.manual_seed(0)
    actor = make_actor(2, Bounded(-1.0, 1.0, shape=(1,)), width=8)
    qvalues = [make_qvalue(2, 1, width=8) for _ in range(2)]
    safety = TensorDictModule(
        _ReadOut(), in_keys=["observation", "action"], out_keys=["cost_value", "cost_variance"]
    )
    loss = WCSACLoss(
        actor,
        qvalues,
        safety,
        risk_level=0.5,
        **recipe_kwargs(variance_loss=variance_loss, **kwargs),
    )
    loss.make_value_estimator(gamma=gamma)
    return loss


def _readout_batch():
    # rows: (Q^c(s,a), V^c(s,a)) in obs, (Q̄^c', V̄^c') in next obs, cost, terminated
    obs = torch.tensor([[2.0, 0.5], [1.0, 4.0], [3.0, 1.0]])
    next_obs = torch.tensor([[1.5, 2.0], [0.5, 1.0], [7.0, 9.0]])
    cost = torch.tensor([[1.0], [0.0], [2.0]])
    terminated = torch.tensor([[False], [False], [True]])
    return TensorDict(
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


def test_cost_mean_and_variance_targets_equal_eq7_and_eq8_with_terminal_mask():
    g = 0.9
    loss = _readout_loss("mse", gamma=g)
    targets = loss.compute_targets(_readout_batch())
    # Eq. 7: y_c = c + γ(1−term) Q̄^c'
    torch.testing.assert_close(
        targets["cost_target"], torch.tensor([1.0 + g * 1.5, 0.0 + g * 0.5, 2.0])
    )
    # Eq. 8: y_v = c² + (1−term)(2γcQ̄' + γ²V̄' + γ²Q̄'²) − Q^c(s,a)²
    row0 = 1.0 + 2 * g * 1.0 * 1.5 + g**2 * 2.0 + g**2 * 1.5**2 - 2.0**2
    row1 = 0.0 + 0.0 + g**2 * 1.0 + g**2 * 0.5**2 - 1.0**2
    row2 = 2.0**2 - 3.0**2  # terminal: no bootstrap, and negative
    cost_value = torch.tensor([2.0, 1.0, 3.0])
    y_v = loss.variance_target(targets, cost_value)
    torch.testing.assert_close(y_v, torch.tensor([row0, row1, row2]))
    # the W2 variant clamps the target to [1e-8, 1e8] as in the paper
    w2 = _readout_loss("w2", gamma=g)
    y_w2 = w2.variance_target(targets, cost_value)
    torch.testing.assert_close(y_w2, torch.tensor([row0, max(row1, 1e-8), 1e-8]))


def test_td_variance_target_is_squared_td_error_plus_discounted_next_variance():
    g = 0.9
    loss = _readout_loss("mse", gamma=g, variance_target="td")
    targets = loss.compute_targets(_readout_batch())
    cost_value = torch.tensor([2.0, 1.0, 3.0])
    # (c + γ(1−term)Q̄' − Q)² + γ²(1−term)V̄'
    row0 = (1.0 + g * 1.5 - 2.0) ** 2 + g**2 * 2.0
    row1 = (0.0 + g * 0.5 - 1.0) ** 2 + g**2 * 1.0
    row2 = (2.0 - 3.0) ** 2  # terminal: no bootstrap
    y_v = loss.variance_target(targets, cost_value)
    torch.testing.assert_close(y_v, torch.tensor([row0, row1, row2]))
    # the moment form has the same value when Q is the mean of its target ...
    moment = _readout_loss("mse", gamma=g)
    at_mean = targets["cost_target"]
    torch.testing.assert_close(
        moment.variance_target(targets, at_mean), loss.variance_target(targets, at_mean)
    )
    # ... but goes negative where Q overshoots it; the td form never does
    assert bool((moment.variance_target(targets, cost_value) < 0).any())
    assert bool((y_v >= 0).all())


def test_cost_gamma_discounts_the_safety_critic_only():
    loss = _readout_loss("mse", gamma=0.9, cost_gamma=0.5)
    assert loss.cost_gamma == 0.5
    targets = loss.compute_targets(_readout_batch())
    torch.testing.assert_close(
        targets["cost_target"], torch.tensor([1.0 + 0.5 * 1.5, 0.0 + 0.5 * 0.5, 2.0])
    )
    torch.testing.assert_close(targets["cost_next_variance"], torch.tensor([0.25 * 2.0, 0.25, 0.0]))
    # the reward target still uses γ = 0.9, and so does nothing else of the cost side
    assert float(loss.value_estimator.gamma) == pytest.approx(0.9)
    thr = per_step_cost_threshold(15.0, 0.5, 1000)
    assert float(loss.cost_threshold) == pytest.approx(thr)
    with pytest.raises(ValueError, match="cost_gamma"):
        make_loss(cost_gamma=1.5)


@pytest.mark.parametrize("variance_loss", ["w2", "mse", "glm"])
def test_variance_loss_values_on_hand_made_tensors(variance_loss):
    loss = _readout_loss(variance_loss)
    batch = _readout_batch()
    targets = loss.compute_targets(batch)
    _, loss_var, meta = loss.safety_loss(batch, targets)
    v = torch.tensor([0.5, 4.0, 1.0])
    y = loss.variance_target(targets, torch.tensor([2.0, 1.0, 3.0]))
    if variance_loss == "w2":
        expected = (v.sqrt() - y.sqrt()).pow(2).mean()
    else:
        expected = (0.5 * (v - y).pow(2)).mean()
    torch.testing.assert_close(loss_var, expected)
    torch.testing.assert_close(meta["cost_variance"], v)


def test_terminal_transitions_do_not_bootstrap_the_reward_either():
    loss = _readout_loss("mse", gamma=0.9)
    batch = _readout_batch()
    batch["next", "reward"] = torch.tensor([[0.0], [0.0], [5.0]])
    targets = loss.compute_targets(batch)
    assert targets["reward_target"][2] == pytest.approx(5.0)


# ------------------------------------------------------------------- errors
@pytest.mark.parametrize("alpha", [0.0, -0.1, 1.5, float("nan"), "high"])
def test_risk_level_outside_unit_interval_is_refused_with_its_meaning(alpha):
    with pytest.raises(ValueError, match="tail fraction"):
        make_loss(risk_level=alpha)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"cost_limit": -1.0}, "cost_limit must be >= 0"),
        ({"cost_threshold": -0.5}, "cost_threshold must be >= 0"),
        ({"max_episode_steps": 0}, "max_episode_steps must be a positive integer"),
        ({"kappa_init": 0.0}, "kappa_init must be > 0"),
        ({"kappa_parametrization": "relu"}, "kappa_parametrization must be one of"),
        ({"kappa_actions": "target"}, "kappa_actions must be one of"),
        ({"damp_scale": -1.0}, r"damp_scale must be in \[0, 1e\+06\]"),
        ({"variance_loss": "l1"}, "variance_loss must be one of"),
        ({"variance_target": "second"}, "variance_target must be one of"),
        ({"kappa_states": "start"}, "kappa_states must be one of"),
    ],
)
def test_bad_constructor_arguments_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        make_loss(**kwargs)


def test_mean_only_critic_below_risk_level_one_is_refused():
    with pytest.raises(ValueError, match="needs a safety critic with a variance head"):
        make_loss(variance=False, risk_level=0.5)
    with pytest.raises(ValueError, match="risk-neutral"):
        SACLagLoss(
            make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=8),
            [make_qvalue(OBS_DIM, ACT_DIM, width=8) for _ in range(2)],
            make_safety_critic(OBS_DIM, ACT_DIM, variance=False, width=8),
            risk_level=0.5,
        )


def test_missing_or_misshapen_cost_gives_a_clear_error():
    loss = make_loss()
    batch = make_batch()
    del batch["next", "cost"]
    with pytest.raises(KeyError, match="needs the per-step cost"):
        loss(batch)
    batch = make_batch()
    batch["next", "cost"] = torch.zeros(16, 2)
    with pytest.raises(ValueError, match="has shape"):
        loss(batch)


def test_multi_step_value_estimators_are_refused():
    loss = make_loss()
    with pytest.raises(NotImplementedError, match="TD\\(0\\)"):
        loss.make_value_estimator(ValueEstimators.TD1)


# ------------------------------------------------------------------ compile
# the UCB ensemble (CAL's reading) with random priors, an adaptive k_ucb and the
# clamped rectification: every new part of the loss inside the one graph
UCB_ENSEMBLE = {
    "num_safety_nets": 4,
    "ensemble_reading": "ucb",
    "prior_scale": 1.0,
    "k_ucb_lr": 0.01,
    "damp_scale": 10.0,
    "damp_clamp": True,
}


@pytest.mark.slow
@pytest.mark.parametrize("options", [{}, UCB_ENSEMBLE], ids=["single", "ucb_ensemble"])
def test_forward_compiles_with_fullgraph_and_matches_eager(options):
    import torch._inductor.config as inductor_config

    loss = make_loss(risk_level=0.1, width=16, **options)
    batch = make_batch()
    if options:
        batch["episode_cvar"] = torch.full((16, 1), 30.0)  # (k_ucb moves by 0.01·15)
        k_ucb = loss.safety_pessimism.k.clone()
    compiled = torch.compile(loss, fullgraph=True)
    with inductor_config.patch(fallback_random=True):
        torch.manual_seed(0)
        got = compiled(batch.clone())
        if options:
            # the compiled backward first (as a training step does, before k moves again)
            sum(v for k, v in got.items() if k.startswith("loss_")).backward()
            stepped = loss.safety_pessimism.k.clone()
            loss.safety_pessimism.k.copy_(k_ucb)  # (the eager update starts where it did)
        torch.manual_seed(0)
        expected = loss(batch.clone())
    if options:
        assert_close_f32(stepped, k_ucb + 0.15, ops=4, magnitude=1.0)
        assert torch.equal(stepped, loss.safety_pessimism.k)
    for key in expected.keys():
        # inductor fuses and reorders the whole update (3 layers of width 16 over a batch
        # of 16, the losses' sums and means): a few hundred roundings of terms of order
        # 1 + |value| for these small networks, and terms cancel in e.g. κ(d − Γ)
        assert_close_f32(got[key], expected[key], ops=512, magnitude=1.0 + expected[key].abs())
    if not options:
        sum(v for k, v in got.items() if k.startswith("loss_")).backward()
    assert loss.kappa_raw.grad is not None


@pytest.mark.parametrize("variance", [True, False])
def test_fused_critic_ensemble_gives_the_same_losses_and_gradients(variance):
    fused = make_loss(variance=variance, fast_paths=True, kappa_actions="replay", damp_scale=1.0)
    separate = make_loss(
        variance=variance, fast_paths=False, kappa_actions="replay", damp_scale=1.0
    )
    assert fused.critics.fused is not None and separate.critics.fused is None
    separate.load_state_dict(fused.state_dict())
    assert_same_losses_and_gradients(fused, separate, make_batch())


def test_critics_that_cannot_be_fused_fall_back_or_are_refused():
    # different widths for the reward and safety critics: no common ensemble
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=8)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=8) for _ in range(2)]
    safety = make_safety_critic(OBS_DIM, ACT_DIM, width=16)
    assert WCSACLoss(actor, qvalues, safety).critics.fused is None
    with pytest.raises(ValueError, match="fast_paths=True needs the critics fused"):
        WCSACLoss(actor, qvalues, safety, fast_paths=True)
    # a critic that is not a plain MLP
    readout = _readout_loss("mse")
    assert readout.critics.fused is None
