"""Quantile regression for the implicit-quantile safety critic: fractions τ and the loss.

:class:`~wcsac_rl.WCSACLoss` with an IQN safety critic draws ``N`` fractions per
critic evaluation with :func:`stratified_fractions` (one τ in each of ``N`` equal
strata of an interval, shared by the batch rows) and trains the critic with
:func:`quantile_huber_loss` (IQN, Dabney et al. 2018, κ_H = 1).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["midpoint_fractions", "quantile_huber_loss", "stratified_fractions"]


def stratified_fractions(
    count: int,
    low: float = 0.0,
    high: float = 1.0,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """``count`` fractions in ``[low, high]``, one uniform draw in each of ``count`` equal strata.

    Each τ_k is uniform on its stratum, so an average over them is an unbiased
    estimate of the average over ``τ ~ U[low, high]`` (as with ``count`` independent
    draws) with the variance of stratified sampling: a step in the quantile function
    (a rare large cost) moves the estimate by at most one stratum's share. Sorted
    ascending. Uses torch's global generator.

    >>> tau = stratified_fractions(4, 0.9, 1.0)
    >>> bool(((tau - 0.9) * 40).floor().eq(torch.arange(4.0)).all())  # one per stratum
    True
    """
    offsets = torch.arange(count, device=device, dtype=dtype)
    offsets = offsets + torch.rand(count, device=device, dtype=dtype)
    return low + (high - low) * offsets / count


def midpoint_fractions(
    count: int,
    low: float = 0.0,
    high: float = 1.0,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """The midpoints of ``count`` equal strata of ``[low, high]`` (deterministic fractions).

    >>> midpoint_fractions(4).tolist()
    [0.125, 0.375, 0.625, 0.875]
    """
    offsets = torch.arange(count, device=device, dtype=dtype) + 0.5
    return low + (high - low) * offsets / count


def quantile_huber_loss(
    quantiles: Tensor, fractions: Tensor, targets: Tensor, kappa: float = 1.0
) -> Tensor:
    r"""IQN's quantile Huber loss, per batch row.

    ``Σ_i (1/N') Σ_j |τ_i − 1{δ_ij < 0}| · L_κ(δ_ij) / κ`` with ``δ_ij = y_j − Z_i``,
    ``L_κ`` the Huber loss (``½δ²`` for ``|δ| ≤ κ``, ``κ(|δ| − ½κ)`` beyond), summed
    over the ``N`` predicted quantiles and averaged over the ``N'`` target samples
    (Dabney et al. 2018, Eq. 4). As ``κ → 0`` it becomes the plain quantile
    (pinball) loss.

    Args:
        quantiles: ``Z_i = Z(s, a, τ_i)``, ``[*B, N]``.
        fractions: their τ_i, ``[N]`` (shared by the batch) or ``[*B, N]``.
        targets: target samples ``y_j``, ``[*B, N']`` (no gradient is taken through them).
        kappa: the Huber threshold κ_H > 0.

    Returns:
        ``[*B]``.

    >>> q = torch.tensor([[0.0, 0.0]]); tau = torch.tensor([0.25, 0.75])
    >>> quantile_huber_loss(q, tau, torch.tensor([[2.0]]))  # δ = 2 > κ: τ_i (2 − ½), summed
    tensor([1.5000])
    """
    predicted = quantiles.unsqueeze(-1)  # [*B, N, 1]
    target = targets.detach().unsqueeze(-2)  # [*B, 1, N']
    # L_κ(δ_ij) in one kernel (and one backward) over [*B, N, N']: the same values and
    # gradients, to the bit, as ½δ² / κ(|δ| − ½κ) written out, at a third less time
    huber = F.huber_loss(*torch.broadcast_tensors(predicted, target), reduction="none", delta=kappa)
    # |τ_i − 1{δ_ij < 0}|: 1 − τ_i where the target is below the quantile, else τ_i
    tau = fractions.unsqueeze(-1)
    weight = torch.where(target < predicted.detach(), 1.0 - tau, tau)
    return (weight * huber).mean(-1).sum(-1) / kappa
