"""The safety heads on their own: Γ in closed form, targets, loss terms and where their
gradients go, and the factory that decides the critic's kind.

Float32 tolerances follow ``_tolerance.py``.
"""

from __future__ import annotations

import math
import re
from statistics import NormalDist

import pytest
import torch
from _loss_helpers import linear_quantile_critic
from _tolerance import assert_close_f32
from tensordict import TensorDict

from wcsac_rl.modules import make_safety_critic
from wcsac_rl.objectives import WCSACLoss
from wcsac_rl.objectives.ensemble_head import make_safety_head
from wcsac_rl.objectives.loss_options import SafetyHeadOptions
from wcsac_rl.objectives.safety_head import (
    GaussianHead,
    IQNHead,
    SafetyValues,
    quantile_huber_loss,
)


def _keys():
    return WCSACLoss.default_keys()


def _gaussian(risk_level=0.1, *, variance=True, nonnegative=False, **kwargs) -> GaussianHead:
    torch.manual_seed(0)
    critic = make_safety_critic(3, 1, variance=variance, width=8)
    return GaussianHead(
        critic, _keys(), risk_level=risk_level, nonnegative_cost=nonnegative, **kwargs
    )


def _linear_iqn(risk_level=0.2, *, nonnegative=False, **kwargs) -> tuple[IQNHead, TensorDict]:
    module = linear_quantile_critic()
    options = SafetyHeadOptions(nonnegative_cost=nonnegative, **kwargs)
    head = make_safety_head(module, _keys(), risk_level=risk_level, options=options)
    return head, TensorDict.from_module(module)


# ------------------------------------------------------------------- Gaussian
@pytest.mark.parametrize("alpha", [1e-3, 0.1, 0.5, 0.9])
def test_gaussian_cvar_is_the_closed_form_cvar_of_the_normal(alpha):
    head = _gaussian(alpha)
    mean = torch.tensor([-1.0, 0.0, 2.5])
    std = torch.tensor([0.5, 1.0, 3.0])
    got = head.cvar(SafetyValues(mean, std.pow(2)))
    # CVaR_α of N(μ, σ²) = μ + σ φ(Φ⁻¹(1 − α)) / α, in float64 from the standard library
    z = NormalDist().inv_cdf(1.0 - alpha)
    phi = math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    expected = torch.tensor([m + s * phi / alpha for m, s in zip(mean.tolist(), std.tolist())])
    # √V, one product, one sum (the multiplier itself is float64, rounded once)
    assert_close_f32(got, expected, ops=4)
    # the mixture of one state is that state's Gaussian: the same CVaR
    one = SafetyValues(mean[2:], std[2:].pow(2))
    assert_close_f32(head.mixture_cvar(one), expected[2], ops=16)


def test_nonnegative_cost_clamps_the_mean_in_gamma_not_the_variance():
    head = _gaussian(0.5, nonnegative=True)
    values = SafetyValues(torch.tensor([-2.0, 1.0]), torch.tensor([4.0, 4.0]))
    expected = torch.tensor([0.0, 1.0]) + head.cvar_multiplier * 2.0
    torch.testing.assert_close(head.cvar(values), expected)
    raw = _gaussian(0.5).cvar(values)
    torch.testing.assert_close(raw, torch.tensor([-2.0, 1.0]) + head.cvar_multiplier * 2.0)


def test_a_mean_only_head_is_the_mean_at_alpha_1_and_refused_below():
    head = _gaussian(1.0, variance=False)
    assert (head.kind, head.has_variance, head.loss_names) == ("mean", False, ("loss_cost_value",))
    mean = torch.tensor([0.5, 3.0])
    torch.testing.assert_close(head.cvar(SafetyValues(mean)), mean)
    with pytest.raises(ValueError, match="needs a safety critic with a variance head"):
        _gaussian(0.5, variance=False)


def test_gaussian_targets_are_eq7_and_eq8_with_the_stop_mask():
    head = _gaussian(0.5)
    cost = torch.tensor([1.0, 0.0, 2.0])
    gamma = torch.tensor(0.9)
    alive = torch.tensor([1.0, 1.0, 0.0])
    ahead = SafetyValues(torch.tensor([1.5, 0.5, 7.0]), torch.tensor([2.0, 1.0, 9.0]))
    t = head.targets(cost, gamma, alive, ahead)
    g = 0.9
    torch.testing.assert_close(t["cost_target"], torch.tensor([1 + g * 1.5, g * 0.5, 2.0]))
    torch.testing.assert_close(t["cost_next_variance"], torch.tensor([g * g * 2.0, g * g, 0.0]))
    second = torch.tensor(
        [
            1.0 + 2 * g * 1.5 + g * g * 1.5**2 + g * g * 2.0,
            g * g * 0.5**2 + g * g * 1.0,
            4.0,
        ]
    )
    torch.testing.assert_close(t["cost_second_moment"], second)
    # with nonnegative_cost the bootstrapped mean is max(Q̄, 0)
    clamped = _gaussian(0.5, nonnegative=True).targets(
        cost, gamma, alive, SafetyValues(torch.tensor([-3.0, 0.5, 7.0]), ahead.variance)
    )
    torch.testing.assert_close(clamped["cost_target"], torch.tensor([1.0, g * 0.5, 2.0]))


def test_gaussian_loss_terms_send_gradients_only_to_their_own_network():
    head = _gaussian(0.5, variance_loss="mse")
    params = TensorDict.from_module(head.network)
    batch = TensorDict({"observation": torch.randn(8, 3), "action": torch.rand(8, 1)}, [8])
    values = head.values(batch, params)
    targets = head.targets(torch.rand(8), torch.tensor(0.9), torch.ones(8), values.detach())
    terms = head.loss(values, targets)
    assert set(terms) == {"loss_cost_value", "loss_cost_variance"}
    for name, network in (("loss_cost_value", "mean_net"), ("loss_cost_variance", "variance_net")):
        grads = torch.autograd.grad(
            terms[name].mean(), list(params.values(True, True)), allow_unused=True
        )
        for key, grad in zip(params.keys(True, True), grads):
            assert (grad is not None and bool(grad.abs().sum() > 0)) == (network in key), (
                name,
                key,
            )
    # the mean term is ½(y − Q)², the variance term the MSE against the TD target
    torch.testing.assert_close(
        terms["loss_cost_value"], 0.5 * (targets["cost_target"] - values.mean).pow(2)
    )
    y = head.variance_target(targets, values.mean)
    torch.testing.assert_close(terms["loss_cost_variance"], 0.5 * (values.variance - y).pow(2))


# ------------------------------------------------------------------------ IQN
def test_iqn_gamma_is_the_mean_of_the_tail_quantiles_and_the_mixture_pools_rows():
    head, _ = _linear_iqn(0.5)
    tail = torch.tensor([[1.0, 2.0, 6.0], [-3.0, 0.0, 3.0]])
    torch.testing.assert_close(head.cvar(SafetyValues(tail=tail)), torch.tensor([3.0, 0.0]))
    clamped, _ = _linear_iqn(0.5, nonnegative=True)
    torch.testing.assert_close(clamped.cvar(SafetyValues(tail=tail)), torch.tensor([3.0, 1.0]))
    # the upper half of the 6 pooled atoms {−3, 0, 1, 2, 3, 6}: (2 + 3 + 6) / 3
    pooled = SafetyValues(quantiles=tail)
    torch.testing.assert_close(head.mixture_cvar(pooled), torch.tensor(11.0 / 3.0))
    with pytest.raises(TypeError, match="quantile_cvar"):
        head.cvar(SafetyValues(torch.zeros(2), torch.ones(2)))
    with pytest.raises(TypeError, match="quantile_cvar"):
        _gaussian().cvar(SafetyValues(tail=tail))


def test_iqn_values_read_the_quantile_function_at_the_drawn_fractions():
    head, params = _linear_iqn(0.2, num_quantiles=4, num_target_quantiles=5)
    a, b = torch.tensor([1.0, -2.0]), torch.tensor([4.0, 10.0])
    batch = TensorDict({"observation": torch.stack([a, b], -1), "action": torch.zeros(2, 1)}, [2])
    values = head.values(batch, params, stratified=False)
    # Z = a + bτ at the midpoints of 4 strata of [0, 1] and of [0.8, 1]
    tau = (torch.arange(4.0) + 0.5) / 4
    torch.testing.assert_close(values.fractions, tau)
    torch.testing.assert_close(values.quantiles, a[:, None] + b[:, None] * tau)
    torch.testing.assert_close(values.mean, a + b / 2)
    torch.testing.assert_close(head.cvar(values), a + b * 0.9)  # the mean of τ over [0.8, 1]
    # the variance of the quantiles: b² × the variance of the 4 midpoints, (N² − 1)/(12 N²)
    torch.testing.assert_close(values.variance, b.pow(2) * 15.0 / 192.0)
    # a target reading draws N' = 5 stratified fractions and no tail
    torch.manual_seed(0)
    target = head.values(batch, params, target=True)
    assert target.quantiles.shape == (2, 5) and target.tail is None
    strata = (target.fractions * 5).floor()
    torch.testing.assert_close(strata, torch.arange(5.0))


def test_iqn_targets_and_loss_are_the_quantile_huber_td_loss():
    head, params = _linear_iqn(0.5, huber_kappa=1.0)
    cost, gamma, alive = torch.tensor([1.0, 2.0]), torch.tensor(0.5), torch.tensor([1.0, 0.0])
    ahead = SafetyValues(quantiles=torch.tensor([[2.0, 4.0, 6.0], [8.0, 8.0, 8.0]]))
    t = head.targets(cost, gamma, alive, ahead)
    torch.testing.assert_close(
        t["cost_target_quantiles"], torch.tensor([[2.0, 3.0, 4.0], [2.0, 2.0, 2.0]])
    )
    torch.testing.assert_close(t["cost_target"], torch.tensor([3.0, 2.0]))
    assert t["cost_second_moment"] is None and t["cost_next_variance"] is None
    batch = TensorDict({"observation": torch.randn(2, 2), "action": torch.zeros(2, 1)}, [2])
    values = head.values(batch, params)
    loss = head.loss(values, t)
    assert set(loss) == {"loss_cost_quantile"}
    expected = quantile_huber_loss(values.quantiles, values.fractions, t["cost_target_quantiles"])
    torch.testing.assert_close(loss["loss_cost_quantile"], expected)
    (grad,) = torch.autograd.grad(loss["loss_cost_quantile"].sum(), [params["module", "scale"]])
    assert bool(grad != 0)


# -------------------------------------------------------------------- factory
def test_the_factory_decides_the_kind_once():
    keys = _keys()
    iqn = make_safety_head(make_safety_critic(3, 1, kind="iqn", width=8), keys, risk_level=0.1)
    gaussian = make_safety_head(make_safety_critic(3, 1, width=8), keys, risk_level=0.1)
    assert isinstance(iqn, IQNHead) and iqn.kind == "iqn"
    assert isinstance(gaussian, GaussianHead) and gaussian.kind == "gaussian"
    assert iqn.loss_names == ("loss_cost_quantile",)
    assert gaussian.loss_names == ("loss_cost_value", "loss_cost_variance")
    # a module reading the fractions key is an IQN critic whatever its class
    head, _ = _linear_iqn()
    assert isinstance(head, IQNHead) and head.in_keys == ["observation", "action"]
    with pytest.raises(ValueError, match="variance head"):
        make_safety_head(
            make_safety_critic(3, 1, kind="iqn", width=8),
            keys,
            risk_level=0.1,
            options=SafetyHeadOptions(variance_loss="glm"),
        )
    for bad, message in (
        ({"variance_target": "second"}, "variance_target must be one of"),
        ({"num_quantiles": 0}, "num_quantiles must be an integer >= 1"),
        ({"huber_kappa": -1.0}, re.escape("huber_kappa must be in (0, 1e+06]")),
    ):
        with pytest.raises(ValueError, match=message):
            make_safety_head(
                make_safety_critic(3, 1, width=8),
                keys,
                risk_level=0.1,
                options=SafetyHeadOptions(**bad),
            )
