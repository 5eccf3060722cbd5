"""The variance head's regression losses (``wcsac_rl.objectives.variance``).

The GLM loss has the MSE's value and fixed point but the gradient ``V − y`` on the
head's pre-softplus output; the MSE's gradient there is ``(V − y)·sigmoid(z)``, which a
network fitting large variances elsewhere uses to silence every small one.
"""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from wcsac_rl.modules import make_safety_critic, softplus_variance
from wcsac_rl.objectives.variance import VARIANCE_LOSSES, variance_regression_loss

EPS32 = torch.finfo(torch.float32).eps


def test_glm_loss_has_the_mse_value_and_the_residual_as_gradient_in_the_logit():
    z = torch.tensor([-12.0, -3.0, 0.0, 2.5, 8.0], requires_grad=True)
    target = torch.tensor([1.4, 0.0, 2.0, 30.0, 1.0])
    variance = softplus_variance(z)
    glm = variance_regression_loss(variance, target, "glm")
    mse = variance_regression_loss(variance, target, "mse")
    torch.testing.assert_close(glm, mse, rtol=0.0, atol=0.0)
    glm.sum().backward()
    residual = (variance - target).detach()
    # a few float32 roundings of the residual (|V − y| ≤ 30) and of softplus' slope
    torch.testing.assert_close(z.grad, residual, rtol=8 * EPS32, atol=8 * EPS32 * 30)
    # the MSE's own gradient at z = −12 is the residual times sigmoid(−12) ≈ 6e-6
    z_mse = z.detach().clone().requires_grad_(True)
    variance_regression_loss(softplus_variance(z_mse), target, "mse").sum().backward()
    assert abs(float(z_mse.grad[0])) < 1e-5 * abs(float(residual[0]))


def test_w2_loss_is_the_squared_difference_of_standard_deviations():
    variance = torch.tensor([4.0, 0.25])
    target = torch.tensor([9.0, 1.0])
    torch.testing.assert_close(
        variance_regression_loss(variance, target, "w2"), torch.tensor([1.0, 0.25])
    )


def test_targets_get_no_gradient_and_unknown_kinds_are_refused():
    variance = torch.tensor([1.0], requires_grad=True)
    target = torch.tensor([2.0], requires_grad=True)
    for kind in VARIANCE_LOSSES:
        variance_regression_loss(variance, target, kind).sum().backward()
    assert target.grad is None
    with pytest.raises(ValueError, match="must be one of"):
        variance_regression_loss(variance, target, "l1")


def _fit_two_levels(kind: str, seed: int, steps: int = 2000) -> list[float]:
    """Fit the Gaussian critic's variance head to y(x) = 30 (x < 0.1), 2 (x < 0.7),
    0 (else) with one loss; the fitted V at x = 0.05, 0.4, 0.9."""
    torch.manual_seed(seed)
    critic = make_safety_critic(1, 1, width=64)
    optim = torch.optim.Adam(critic.parameters(), lr=1e-3)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        x = torch.rand(256, 1, generator=generator)
        y = torch.where(x < 0.1, 30.0, torch.where(x < 0.7, 2.0, 0.0)).squeeze(-1)
        td = critic(TensorDict({"observation": x, "action": torch.zeros(256, 1)}, [256]))
        loss = variance_regression_loss(td["cost_variance"].squeeze(-1), y, kind).mean()
        optim.zero_grad()
        loss.backward()
        optim.step()
    probe = torch.tensor([[0.05], [0.4], [0.9]])
    with torch.no_grad():
        td = critic(TensorDict({"observation": probe, "action": torch.zeros(3, 1)}, [3]))
    return td["cost_variance"].squeeze(-1).tolist()


@pytest.mark.parametrize("seed", [0, 1])
def test_glm_keeps_the_small_variances_the_mse_silences(seed):
    # measured (seeds 0-2): MSE 27.5-29.6 / 0.000 / 0.000; GLM 26.9-28.8 / 1.96-2.13 / ≤ 0.004
    high_mse, mid_mse, _ = _fit_two_levels("mse", seed)
    high_glm, mid_glm, low_glm = _fit_two_levels("glm", seed)
    assert high_mse > 20.0 and mid_mse < 0.05
    assert high_glm > 20.0
    assert 1.0 < mid_glm < 4.0
    assert low_glm < 0.5
