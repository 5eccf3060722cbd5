"""The regression losses of the Gaussian safety critic's variance head V^c.

All three fit V^c(s, a) to its TD target ``y`` (``WCSACLoss.variance_target``); they
differ in how the error reaches the head's pre-softplus output ``z``
(``V = softplus(z)``, :func:`~wcsac_rl.modules.softplus_variance`):

* ``"w2"`` — the paper's 2-Wasserstein term ``V + y − 2√(V y) = (√V − √y)²``. On noisy
  sampled targets it converges to ``(E√y)²``, not ``E y``.
* ``"mse"`` — ``½ (V − y)²``, consistent for ``E y``. Its gradient in ``z`` is
  ``(V − y)·sigmoid(z)``: where V is small the factor ``sigmoid(z) ≈ V`` silences the
  error, so a network that fits the large variances near a hazard drives the rest of
  the state space to the floor and cannot climb back (measured: a two-level target of
  30 and 2 is fitted as 28 and 0.000; see docs/defaults.md).
* ``"glm"`` — the same fixed point ``V = E y``, with the gradient ``V − y`` in ``z``:
  the update a generalised linear model gets from its canonical link, so a small V
  with a larger target is pulled up as hard as a large one. The reported value is the
  MSE's ``½ (V − y)²`` (comparable across the two); only the gradient differs. The
  weighting is exact for the softplus head; for another positive transform it stays a
  descent direction with the same fixed point.
"""

from __future__ import annotations

import torch
from torch import Tensor

from wcsac_rl.options import VARIANCE_LOSSES

__all__ = ["VARIANCE_LOSSES", "variance_regression_loss"]


def variance_regression_loss(variance: Tensor, target: Tensor, kind: str) -> Tensor:
    """The element-wise loss of the variance head's prediction ``variance`` (> 0) against
    its TD ``target`` (``target > 0`` for ``"w2"``), not reduced.

    Args:
        variance (Tensor): V^c(s, a), the head's output (gradients flow through it).
        target (Tensor): the TD target ``y`` (no gradient is taken through it).
        kind (str): ``"w2"``, ``"mse"`` or ``"glm"`` (see the module docstring).
    """
    target = target.detach()
    if kind == "w2":
        return variance + target - 2 * (variance * target).sqrt()
    if kind == "mse":
        return 0.5 * (variance - target).pow(2)
    if kind == "glm":
        # d softplus(z)/dz = sigmoid(z) = 1 − exp(−V): dividing the MSE's residual by it
        # makes the gradient in z the residual itself. The value is the MSE's.
        residual = variance.detach() - target
        slope = (-torch.expm1(-variance.detach())).clamp_min(1e-8)
        surrogate = (variance - variance.detach()) * (residual / slope)
        return 0.5 * residual.pow(2) + surrogate
    raise ValueError(f"variance loss must be one of {VARIANCE_LOSSES}, got {kind!r}")
