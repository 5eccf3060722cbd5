"""CVaR far in the tail: exact for every accepted α, down to MIN_RISK_LEVEL = 1e-12,
against the closed form of a single Gaussian, a high-precision integral of a two-component
mixture, and the exact CVaR of discrete pools; a smaller α is one clear error."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from scipy import integrate, optimize, stats

from wcsac_rl.objectives.risk import (
    MIN_RISK_LEVEL,
    empirical_cvar,
    gaussian_cvar,
    gaussian_mixture_cvar,
    quantile_mixture_cvar,
    validate_risk_level,
)

TAIL_LEVELS = [1e-3, 1e-6, 1e-8, 1e-10, MIN_RISK_LEVEL]
FLOAT32_REL = 4 * 2.0**-24  # the float32 result of a float64 computation: a few roundings


def gaussian_cvar_closed_form(mu: float, sigma: float, alpha: float) -> float:
    """μ + σ φ(Φ⁻¹(1 − α)) / α (scipy's isf is exact where 1 − α rounds to 1)."""
    return mu + sigma * stats.norm.pdf(stats.norm.isf(alpha)) / alpha


@pytest.mark.parametrize("alpha", TAIL_LEVELS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_one_gaussian_equals_the_closed_form(alpha, dtype):
    mean, variance = torch.tensor([1.0], dtype=dtype), torch.tensor([4.0], dtype=dtype)
    exact = gaussian_cvar_closed_form(1.0, 2.0, alpha)
    got = gaussian_mixture_cvar(mean, variance, alpha)
    assert got.dtype == dtype
    rel = FLOAT32_REL if dtype == torch.float32 else 1e-12
    assert float(got) == pytest.approx(exact, rel=rel)
    # the per-state formula (Eq. 9) agrees
    assert float(gaussian_cvar(mean, variance, alpha)) == pytest.approx(exact, rel=max(rel, 1e-13))


def test_the_numbers_of_the_issue():
    """N(1, 4): float32's 1 − Φ gave 11.31 at α = 1e-6 (exact 10.90) and −2.80 at 1e-8
    (exact 12.56)."""
    one = (torch.tensor([1.0]), torch.tensor([4.0]))
    assert float(gaussian_mixture_cvar(*one, 1e-6)) == pytest.approx(10.896665433, rel=1e-7)
    assert float(gaussian_mixture_cvar(*one, 1e-8)) == pytest.approx(12.560688369, rel=1e-7)


def _mixture_cvar_by_integration(mus, sigmas, alpha: float) -> float:
    """VaR by root finding on the mixture's survival function, then
    CVaR = v + (1/α) ∫_v^∞ (x − v) p(x) dx by adaptive quadrature (relative 1e-12)."""
    mus, sigmas = list(mus), list(sigmas)

    def sf(x):
        return sum(stats.norm.sf(x, m, s) for m, s in zip(mus, sigmas)) / len(mus)

    lo = min(m + stats.norm.isf(alpha) * s for m, s in zip(mus, sigmas))
    hi = max(m + stats.norm.isf(alpha) * s for m, s in zip(mus, sigmas))
    var = lo if hi - lo < 1e-15 else optimize.brentq(lambda x: sf(x) - alpha, lo, hi, xtol=1e-14)

    def tail(x):
        return (x - var) * sum(stats.norm.pdf(x, m, s) for m, s in zip(mus, sigmas)) / len(mus)

    width = max(sigmas)
    pieces = [var + k * width for k in range(0, 41)]
    total = sum(
        integrate.quad(tail, a, b, epsabs=0.0, epsrel=1e-12, limit=200)[0]
        for a, b in itertools.pairwise(pieces)
    )
    return var + total / alpha


@pytest.mark.parametrize("alpha", [0.1, *TAIL_LEVELS])
@pytest.mark.parametrize(
    ("mus", "sigmas"),
    [([0.0, 3.0], [1.0, 0.5]), ([0.0, 0.5], [1.0, 3.0])],  # tail of the far mean / the wide one
    ids=["far-mean", "wide"],
)
def test_a_two_component_mixture_equals_a_high_precision_integral(alpha, mus, sigmas):
    exact = _mixture_cvar_by_integration(mus, sigmas, alpha)
    got = gaussian_mixture_cvar(
        torch.tensor(mus, dtype=torch.float64),
        torch.tensor(sigmas, dtype=torch.float64) ** 2,
        alpha,
    )
    assert float(got) == pytest.approx(exact, rel=1e-9)


def test_the_gradient_reaches_the_means_and_variances_in_their_dtype():
    mean = torch.tensor([0.0, 3.0], requires_grad=True)
    variance = torch.tensor([1.0, 0.25], requires_grad=True)
    gaussian_mixture_cvar(mean, variance, 1e-8).backward()
    assert mean.grad.dtype == torch.float32 and torch.isfinite(mean.grad).all()
    assert torch.isfinite(variance.grad).all()
    # far in the tail only the component with the far tail counts
    assert float(mean.grad.sum()) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("alpha", TAIL_LEVELS)
def test_pools_of_quantiles_and_samples_give_their_largest_value_in_a_tail_lighter_than_one(alpha):
    quantiles = torch.tensor([[0.0, 1.0, 2.0, 3.0], [4.0, 5.0, 6.0, 7.0]])
    assert float(quantile_mixture_cvar(quantiles, alpha)) == 7.0
    assert empirical_cvar([0.0, 3.0, 30.0, 2.0], alpha) == 30.0


def test_a_pool_keeps_its_fractional_atom_just_above_one():
    # 2 atoms' worth of mass over 1000 atoms: the largest two
    pool = torch.arange(1000.0)
    assert float(quantile_mixture_cvar(pool, 2e-3)) == pytest.approx(998.5)


@pytest.mark.parametrize("alpha", [1e-300, 1e-13, 5e-324])
def test_a_risk_level_below_the_supported_one_is_one_error_naming_it(alpha):
    with pytest.raises(ValueError) as err:
        validate_risk_level(alpha)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"risk_level α={alpha!r} is below")
    assert f"[{MIN_RISK_LEVEL:g}, 1]" in message
    for call in (
        lambda: gaussian_mixture_cvar(torch.zeros(1), torch.ones(1), alpha),
        lambda: quantile_mixture_cvar(torch.zeros(4), alpha),
        lambda: empirical_cvar([1.0], alpha),
    ):
        with pytest.raises(ValueError, match="below the smallest supported"):
            call()
    assert math.isfinite(MIN_RISK_LEVEL)
