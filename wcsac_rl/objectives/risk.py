"""Risk measures: the Gaussian CVaR of the safety critic, the CVaR of a pool of quantiles,
and the empirical CVaR of samples.

Convention (the paper's): the risk level ``α ∈ (0, 1]`` is the *tail fraction*.
``CVaR_α`` of a cost is the mean of its worst ``α`` fraction: small α is risk-averse,
``α = 1`` is the plain expectation (risk-neutral). Some ports use ``α' = 1 − α``;
this module does not.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from statistics import NormalDist

import torch

__all__ = [
    "MIN_RISK_LEVEL",
    "empirical_cvar",
    "gaussian_cvar",
    "gaussian_cvar_multiplier",
    "gaussian_mixture_cvar",
    "quantile_mixture_cvar",
    "upper_tail_mean",
    "validate_risk_level",
]

_STD_NORMAL = NormalDist()


MIN_RISK_LEVEL = 1e-12
"""The smallest accepted α. Every CVaR here is exact (to float64 rounding, then the
input's dtype) for α in ``[MIN_RISK_LEVEL, 1]``: the Gaussian mixture's VaR search and
tail expectation run in float64 with the tail mass as ``erfc`` (no ``1 − Φ``
cancellation). Below it a tail fraction means one episode in more than 10¹² and float32
networks cannot tell the fractions ``1 − α`` of an IQN critic from 1."""


def validate_risk_level(risk_level: float, *, name: str = "risk_level") -> float:
    """Return ``risk_level`` as a float, or raise ``ValueError`` if it is not a number in
    ``[MIN_RISK_LEVEL, 1]`` (10⁻¹² to 1; a bool or a string is not a number:
    ``risk_level=true`` is refused, not 1). ``name`` is how the message calls it
    (``algo.risk_level`` in a config)."""
    alpha = math.nan
    if not isinstance(risk_level, (bool, str, bytes)):
        try:
            alpha = float(risk_level)
        except (TypeError, ValueError):
            pass
    if not 0.0 < alpha <= 1.0:  # also refuses NaN
        raise ValueError(
            f"{name} α must be a number in (0, 1], got {risk_level!r}. α is the tail "
            "fraction of the cost distribution that CVaR_α averages over: α = 0.1 is the mean "
            "of the worst 10% (risk-averse), α = 1 is the plain expected cost (risk-neutral, "
            "SAC-Lag)."
        )
    if alpha < MIN_RISK_LEVEL:
        raise ValueError(
            f"{name} α={risk_level!r} is below the smallest supported tail fraction "
            f"{MIN_RISK_LEVEL:g}: use a risk level in [{MIN_RISK_LEVEL:g}, 1]"
        )
    return alpha


def gaussian_cvar_multiplier(risk_level: float) -> float:
    """``α⁻¹ φ(Φ⁻¹(α))``: CVaR_α of N(μ, σ²) is ``μ + multiplier · σ`` (paper, Eq. 9).

    >>> round(gaussian_cvar_multiplier(0.1), 5), round(gaussian_cvar_multiplier(0.5), 5)
    (1.75498, 0.79788)
    >>> gaussian_cvar_multiplier(1.0)
    0.0
    """
    alpha = validate_risk_level(risk_level)
    if alpha == 1.0:
        return 0.0
    # φ is symmetric, so φ(Φ⁻¹(α)) = φ(Φ⁻¹(1 − α)): either tail gives the same value.
    return _STD_NORMAL.pdf(_STD_NORMAL.inv_cdf(alpha)) / alpha


def gaussian_cvar(
    mean: torch.Tensor, variance: torch.Tensor | None, risk_level: float
) -> torch.Tensor:
    """``Γ = mean + α⁻¹ φ(Φ⁻¹(α)) √variance``, the CVaR_α of a Gaussian cost.

    ``variance=None`` (a mean-only critic) is allowed only at ``α = 1``.
    """
    multiplier = gaussian_cvar_multiplier(risk_level)
    if multiplier == 0.0:
        return mean
    if variance is None:
        raise ValueError(
            f"CVaR at risk_level={risk_level} needs a variance; a mean-only critic "
            "supports only risk_level=1 (SAC-Lagrangian)."
        )
    return mean + multiplier * variance.sqrt()


def empirical_cvar(costs: Sequence[float] | torch.Tensor, risk_level: float) -> float:
    """Mean of the worst ``⌈n·α⌉`` values of a sample (the paper's C_α of test episodes).

    >>> empirical_cvar([0, 0, 0, 0, 0, 0, 0, 0, 10, 30], 0.1)
    30.0
    >>> empirical_cvar([0, 0, 0, 0, 0, 0, 0, 0, 10, 30], 0.2)
    20.0
    """
    alpha = validate_risk_level(risk_level)
    values = torch.as_tensor(costs, dtype=torch.float64).flatten()
    n = values.numel()
    if n == 0:
        raise ValueError("empirical_cvar needs at least one value")
    if torch.isnan(values).any():
        raise ValueError("empirical_cvar got NaN values")
    # n·α in floating point can land just above an integer (300 · 0.1 = 30.000000000000004):
    # round away that noise before taking the ceiling.
    k = max(1, math.ceil(round(n * alpha, 9)))
    worst = torch.topk(values, k).values
    return float(worst.mean())


_SQRT2 = math.sqrt(2.0)
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def _normal_sf(z: torch.Tensor) -> torch.Tensor:
    """``1 − Φ(z)`` without cancellation: ``erfc(z/√2)/2`` is exact far into the tail."""
    return 0.5 * torch.special.erfc(z / _SQRT2)


def _normal_pdf(z: torch.Tensor) -> torch.Tensor:
    return torch.exp(-0.5 * z * z - _LOG_SQRT_2PI)


def gaussian_mixture_cvar(
    mean: torch.Tensor,
    variance: torch.Tensor | None,
    risk_level: float,
    *,
    weights: torch.Tensor | None = None,
    rounds: int = 5,
    points: int = 33,
    min_std: float = 1e-6,
) -> torch.Tensor:
    """CVaR_α of the equal-weight mixture of ``N(mean_i, variance_i)`` (a 0-dim tensor).

    The cost of an episode whose start state is drawn from a batch of start states:
    each state's own Gaussian, mixed. Unlike the mean of the per-state CVaRs (which
    is never larger), this counts a few risky start states among many safe ones as
    the tail they are. Computed exactly through Rockafellar–Uryasev,
    ``CVaR_α = min_v v + E[(C − v)⁺] / α``, ``E[(C − v)⁺] = σ φ(z) + (μ − v)(1 − Φ(z))``,
    ``z = (v − μ)/σ``. The minimiser (the VaR, where the tail mass equals α) lies
    between the smallest and the largest of the components' own VaRs
    ``μ_i + Φ⁻¹(1 − α) σ_i``; it is bracketed by ``rounds`` grid searches of ``points``
    candidates each, every one a single batched evaluation (no host synchronisation):
    the bracket shrinks by ``(points − 1)^rounds`` (32⁵ ≈ 2²⁵ by default), and the
    objective is flat at its minimum, so the CVaR's error is second order in it. With
    one component (or equal ones) the bracket is the exact VaR.

    **Precision.** The search and the tail expectation run in float64, the tail mass
    ``1 − Φ(z)`` as ``erfc(z/√2)/2`` (float32's ``1 − Φ`` is 0 beyond z ≈ 5.3, where
    α = 10⁻⁸ lives), and the result is returned in ``mean``'s dtype (gradients flow
    through the cast). It is exact to float64 rounding for every accepted α,
    ``[MIN_RISK_LEVEL, 1]`` = [10⁻¹², 1] (:func:`validate_risk_level` refuses smaller
    ones); e.g. N(1, 4) at α = 10⁻⁸ gives 12.5607 (closed form μ + σ φ(Φ⁻¹(1−α))/α).

    Zero (or ``None``) variances give the CVaR of the means themselves, with the
    fractional atom at the VaR counted in part (so with ``n·α`` an integer it is the
    mean of the worst ``n·α`` means). No gradient flows through the VaR.

    ``weights`` (shaped like ``mean``, ≥ 0, e.g. a bool mask of valid rows) mixes the
    components with those weights instead; a component of weight 0 does not count at
    all, whatever its values (NaN and ±inf too; see :func:`_weighted`).

    >>> means = torch.arange(10.0)
    >>> float(gaussian_mixture_cvar(means, None, 0.2))  # mean of the worst 2 means
    8.5
    >>> one = gaussian_mixture_cvar(torch.tensor([1.0]), torch.tensor([4.0]), 0.1)
    >>> round(float(one), 4) == round(1.0 + gaussian_cvar_multiplier(0.1) * 2.0, 4)
    True
    """
    alpha = validate_risk_level(risk_level)
    if int(rounds) != rounds or rounds < 1 or int(points) != points or points < 3:
        raise ValueError(f"need rounds >= 1 and points >= 3, got {rounds} and {points}")
    dtype = mean.dtype
    mean = mean.reshape(-1)
    if weights is not None:
        weights, (mean, variance) = _weighted(weights, mean, variance)
    if alpha == 1.0:
        return mean.mean() if weights is None else (weights.to(dtype) * mean).sum()
    mean = mean.double()
    std = torch.zeros_like(mean) if variance is None else variance.reshape(-1).double().sqrt()
    std = std.clamp(min=min_std)
    if weights is not None:
        weights = weights.double()
    var = _mixture_var(mean.detach(), std.detach(), alpha, int(rounds), int(points), weights)
    z = (var - mean) / std
    excess = std * _normal_pdf(z) + (mean - var) * _normal_sf(z)
    excess = excess.mean() if weights is None else (weights * excess).sum()
    return (var + excess / alpha).to(dtype)


def _weighted(weights: torch.Tensor, *values: torch.Tensor | None):
    """``weights`` flattened and normalised to sum 1 in float64 (all zero: left 0), and each of
    ``values`` flattened with its weight-0 entries replaced by 0 (a selection, so that
    a NaN or ±inf there reaches neither the result nor any gradient)."""
    weights = weights.reshape(-1)
    keep = weights > 0
    weights = weights.to(torch.float64)  # (the normalisation exact to float64 rounding)
    weights = weights / weights.sum().clamp(min=torch.finfo(weights.dtype).tiny)
    kept = [
        None if v is None else torch.where(keep, v.reshape(-1), torch.zeros_like(v.reshape(-1)))
        for v in values
    ]
    return weights, kept


def _mixture_var(
    mean: torch.Tensor,
    std: torch.Tensor,
    alpha: float,
    rounds: int,
    points: int,
    weights: torch.Tensor | None = None,
) -> torch.Tensor:
    """The VaR of :func:`gaussian_mixture_cvar`'s mixture (float64, no gradient)."""
    # Φ⁻¹(1 − α) = −Φ⁻¹(α), exact even where 1 − α rounds to 1; a tensor op, so that
    # torch.compile(fullgraph=True) traces it (statistics.NormalDist is not traceable)
    z_alpha = -torch.special.ndtri(torch.tensor(alpha, dtype=mean.dtype, device=mean.device))
    own = mean + z_alpha * std  # each component's VaR: the mixture's lies among them
    if weights is None:
        low, high = own.min(), own.max()
    else:  # among the components that count
        keep = weights > 0
        some = keep.any()  # (none counts: the result is then a plain 0-weight sum)
        low = torch.where(keep, own, torch.full_like(own, math.inf)).min()
        high = torch.where(keep, own, torch.full_like(own, -math.inf)).max()
        low, high = torch.where(some, low, own.min()), torch.where(some, high, own.max())
    steps = torch.linspace(0.0, 1.0, points, dtype=mean.dtype, device=mean.device)
    for _ in range(rounds):
        grid = low + (high - low) * steps
        sf = _normal_sf((grid.unsqueeze(-1) - mean) / std)
        tail = sf.mean(-1) if weights is None else (sf * weights).sum(-1)
        # the tail mass falls along the grid: the VaR lies after the last point with
        # more than α of the mass above it
        last = ((tail > alpha).sum() - 1).clamp(0, points - 2)
        # (a gather, not grid[last]: indexing by a tensor would read it on the host)
        low, high = grid.gather(0, torch.stack([last, last + 1])).unbind()
    return (low + high) / 2


def quantile_mixture_cvar(
    quantiles: torch.Tensor, risk_level: float, *, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """CVaR_α of the equal-weight pool of every entry of ``quantiles`` (a 0-dim tensor).

    ``quantiles`` ``[*S, N]`` holds, per state, ``N`` quantiles of its cost
    distribution at evenly spread fractions (sampled per stratum or at midpoints):
    each is an atom of weight ``1/N`` of that state's distribution, so the pool of
    all of them, with equal weights, is the mixture over the states — the
    distribution-free counterpart of :func:`gaussian_mixture_cvar` for an
    implicit-quantile critic. Its CVaR_α is the mean of the upper ``α`` share of
    the pooled atoms, the atom at the VaR counted in part (exact for the discrete
    pool: with ``M·α`` an integer it is the mean of the largest ``M·α`` values).
    Shapes are static, so there is no host synchronisation.

    ``weights`` ``[*S]`` (≥ 0, e.g. a bool mask of valid states) weighs each state's
    atoms instead; a state of weight 0 does not count at all, whatever its quantiles.

    >>> quantile_mixture_cvar(torch.arange(10.0).reshape(2, 5), 0.2)  # the worst 2 of 10
    tensor(8.5000)
    >>> round(float(quantile_mixture_cvar(torch.tensor([[0.0, 1.0, 2.0, 3.0]]), 0.3)), 4)
    2.8333
    """
    alpha = validate_risk_level(risk_level)
    pooled = quantiles.reshape(-1)
    count = pooled.numel()
    if count == 0:
        raise ValueError("quantile_mixture_cvar needs at least one quantile")
    if weights is not None:
        return _weighted_pool_cvar(quantiles, weights, alpha)
    if alpha == 1.0:
        return pooled.mean()
    return upper_tail_mean(pooled, alpha)


def upper_tail_mean(atoms: torch.Tensor, risk_level: float) -> torch.Tensor:
    """The mean of the upper ``risk_level`` share of the ``M`` equal-weight atoms in the
    last dimension of ``atoms`` ``[*B, M]``, the atom at the VaR counted in part (the
    CVaR_α of the discrete distribution they make; with ``M·α`` an integer, the mean of
    the largest ``M·α``): ``[*B]``. Static shapes, no host synchronisation.

    >>> upper_tail_mean(torch.tensor([[4.0, 0.0, 3.0, 1.0, 2.0]]), 0.5)  # 4, 3 and ½·2
    tensor([3.2000])
    """
    count = atoms.shape[-1]
    # M·α in floating point can land just above an integer: round that noise away
    # (not below one atom: a tail lighter than one atom is the largest atom)
    mass = round(count * float(risk_level), 9)
    if mass <= 1.0:
        return atoms.max(-1)[0]
    whole = math.floor(mass)
    top = torch.topk(atoms, min(count, math.ceil(mass)), dim=-1).values
    weights = torch.ones(top.shape[-1], dtype=atoms.dtype, device=atoms.device)
    if top.shape[-1] > whole:
        weights[whole] = mass - whole
    return (top * weights).sum(-1) / mass


def _weighted_pool_cvar(quantiles: torch.Tensor, weights: torch.Tensor, alpha: float):
    """:func:`quantile_mixture_cvar` with per-state weights: the pooled atoms sorted
    from the largest, each taking its weight's share of the upper α until α is used up
    (static shapes: no host synchronisation)."""
    atoms = quantiles.shape[-1]
    states = quantiles.reshape(-1, atoms)
    state_weights, (_,) = _weighted(weights, states[:, 0])
    mass = state_weights.to(quantiles.dtype).unsqueeze(-1).expand_as(states).reshape(-1) / atoms
    keep = mass > 0
    pooled = states.reshape(-1)
    lowest = torch.full_like(pooled, -math.inf)
    order = torch.where(keep, pooled, lowest).argsort(descending=True)
    values = torch.where(keep, pooled, torch.zeros_like(pooled)).gather(0, order)
    mass = mass.gather(0, order)
    before = mass.cumsum(0) - mass
    share = (alpha - before).clamp(min=0).minimum(mass)
    return (share * values).sum() / share.sum().clamp(min=torch.finfo(share.dtype).tiny)
