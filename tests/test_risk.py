"""CVaR helpers: the Gaussian multiplier against a table and Monte-Carlo; empirical CVaR.

The table is docs/paper.md, "CVaR multipliers". Tolerances: everything here is
float64. ``abs=1e-5`` is the table's 5 decimals;
``rel=1e-12`` a closed form evaluated in float64 (a few × 2⁻⁵²); ``abs=0.02`` against
Monte Carlo is ≈ 4 standard errors of a 2·10⁶-sample tail mean (seeded); the
empirical CVaRs of integers are exact sums, approx's default only covers the division.
"""

from __future__ import annotations

import math

import pytest
import torch

from wcsac_rl import empirical_cvar, gaussian_cvar, gaussian_cvar_multiplier


@pytest.mark.parametrize(
    ("alpha", "expected"),
    [(0.1, 1.75498), (0.5, 0.79788), (0.9, 0.19500), (1.0, 0.0)],
)
def test_multiplier_matches_the_table(alpha, expected):
    assert gaussian_cvar_multiplier(alpha) == pytest.approx(expected, abs=1e-5)


def test_multiplier_at_one_half_is_sqrt_two_over_pi():
    assert gaussian_cvar_multiplier(0.5) == pytest.approx(math.sqrt(2 / math.pi), rel=1e-12)


@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.5, 0.9])
def test_gaussian_cvar_equals_monte_carlo_tail_mean(alpha):
    g = torch.Generator().manual_seed(0)
    mean, std = 2.0, 3.0
    samples = mean + std * torch.randn(2_000_000, generator=g, dtype=torch.float64)
    mc = empirical_cvar(samples, alpha)
    closed = float(gaussian_cvar(torch.tensor(mean), torch.tensor(std**2), alpha))
    assert closed == pytest.approx(mc, abs=0.02)


def test_gaussian_cvar_is_monotone_in_risk_level():
    mean, var = torch.tensor(1.0), torch.tensor(4.0)
    values = [float(gaussian_cvar(mean, var, a)) for a in (0.01, 0.1, 0.5, 0.9, 1.0)]
    assert values == sorted(values, reverse=True)
    assert values[-1] == 1.0


def test_mean_only_cvar_below_one_is_refused():
    assert gaussian_cvar(torch.tensor(1.0), None, 1.0) == 1.0
    with pytest.raises(ValueError, match="needs a variance"):
        gaussian_cvar(torch.tensor(1.0), None, 0.5)


def test_empirical_cvar_hand_computed():
    costs = [0, 0, 0, 0, 0, 0, 0, 0, 10, 30]
    assert empirical_cvar(costs, 0.1) == 30.0
    assert empirical_cvar(costs, 0.2) == 20.0
    assert empirical_cvar(costs, 0.25) == pytest.approx(40 / 3)  # ⌈2.5⌉ = 3 worst
    assert empirical_cvar(costs, 1.0) == 4.0
    assert empirical_cvar([7.0], 0.1) == 7.0


def test_empirical_cvar_uses_exactly_ceil_n_alpha_despite_float_noise():
    # 300 · 0.1 is 30.000000000000004 in floating point: still the worst 30, not 31.
    costs = torch.arange(300, dtype=torch.float64)
    assert empirical_cvar(costs, 0.1) == pytest.approx(float(costs[-30:].mean()))
    assert empirical_cvar(costs, 0.9) == pytest.approx(float(costs[-270:].mean()))


def test_empirical_cvar_bad_input():
    with pytest.raises(ValueError, match="at least one"):
        empirical_cvar([], 0.5)
    with pytest.raises(ValueError, match="NaN"):
        empirical_cvar([1.0, float("nan")], 0.5)
    with pytest.raises(ValueError, match="tail fraction"):
        empirical_cvar([1.0], 0.0)


# -------------------------------------------------------- mixture of Gaussians
@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.5, 0.9])
def test_mixture_cvar_equals_monte_carlo_of_the_mixture(alpha):
    from wcsac_rl.objectives import gaussian_mixture_cvar

    g = torch.Generator().manual_seed(0)
    mean = torch.tensor([0.0, 0.5, 1.0, 8.0], dtype=torch.float64)
    std = torch.tensor([0.1, 1.0, 0.5, 2.0], dtype=torch.float64)
    n = 1_000_000
    component = torch.randint(0, 4, (n,), generator=g)
    samples = mean[component] + std[component] * torch.randn(n, generator=g, dtype=torch.float64)
    mc = empirical_cvar(samples, alpha)
    closed = float(gaussian_mixture_cvar(mean, std**2, alpha))
    # Monte-Carlo error of a tail mean of ≥ 50 000 samples with spread ≲ 4: ~0.02
    assert closed == pytest.approx(mc, abs=0.03)


@pytest.mark.parametrize("alpha", [0.01, 0.1, 0.5])
def test_mixture_cvar_matches_a_fine_float64_minimisation_on_wide_mixtures(alpha):
    """256 states whose means spread over [0, 100] and whose standard deviations span
    1e-3 to 30 (a batch of start states where a few are risky): the grid search's
    float32 result against Rockafellar–Uryasev minimised over 40 001 float64 points."""
    from wcsac_rl.objectives import gaussian_mixture_cvar

    g = torch.Generator().manual_seed(4)
    mean = torch.rand(256, generator=g, dtype=torch.float64) ** 4 * 100
    std = 10 ** (torch.rand(256, generator=g, dtype=torch.float64) * 4.5 - 3)
    normal = torch.distributions.Normal(0.0, 1.0)
    v = torch.linspace(float((mean - 10 * std).min()), float((mean + 10 * std).max()), 40_001)
    v = v.to(torch.float64)
    best = torch.full((), float("inf"), dtype=torch.float64)
    for chunk in v.split(2_000):
        z = (chunk.unsqueeze(-1) - mean) / std
        excess = std * normal.log_prob(z).exp() + (mean - chunk.unsqueeze(-1)) * (1 - normal.cdf(z))
        best = torch.minimum(best, (chunk + excess.mean(-1) / alpha).min())
    got = gaussian_mixture_cvar(mean.float(), std.float().pow(2), alpha)
    # the reference grid (steps ≈ 0.02) misses the flat minimum by a second-order amount;
    # float32 terms up to ~400 / α: a few hundred roundings of 4e2 · 6e-8, relative ≪ 1e-4
    assert float(got) == pytest.approx(float(best), rel=1e-4)


def test_mixture_cvar_special_cases():
    from wcsac_rl.objectives import gaussian_mixture_cvar

    mean = torch.tensor([3.0, 1.0, 2.0, 0.0])
    var = torch.tensor([1.0, 4.0, 0.25, 9.0])
    # one component: the Gaussian CVaR; α = 1: the mean of the means
    one = gaussian_mixture_cvar(mean[:1], var[:1], 0.1)
    torch.testing.assert_close(one, gaussian_cvar(mean[0], var[0], 0.1), rtol=1e-5, atol=0)
    torch.testing.assert_close(gaussian_mixture_cvar(mean, var, 1.0), mean.mean())
    # no variance: the worst α share of the means, fractional atom counted in part
    assert float(gaussian_mixture_cvar(mean, None, 0.5)) == pytest.approx(2.5, abs=1e-5)
    assert float(gaussian_mixture_cvar(mean, None, 0.375)) == pytest.approx(
        (3.0 + 2.0 * 0.5) / 1.5, abs=1e-5
    )
    # never below the mean of the per-state CVaRs (a few risky states are the tail)
    per_state = gaussian_cvar(mean, var, 0.1).mean()
    assert float(gaussian_mixture_cvar(mean, var, 0.1)) >= float(per_state)
    # gradients reach the means and variances (the VaR itself is held fixed)
    mean_p = mean.clone().requires_grad_(True)
    var_p = var.clone().requires_grad_(True)
    gaussian_mixture_cvar(mean_p, var_p, 0.1).backward()
    assert mean_p.grad is not None and var_p.grad is not None
    assert float(mean_p.grad.sum()) == pytest.approx(1.0, abs=1e-4)  # a shift moves it 1:1
    with pytest.raises(ValueError, match="points >= 3"):
        gaussian_mixture_cvar(mean, var, 0.1, points=2)


# ----------------------------------------------------- pooled quantiles (IQN)
@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.3, 0.5, 1.0])
@pytest.mark.parametrize("shape", [(1, 7), (6, 20), (300, 20)])
def test_quantile_mixture_cvar_is_the_tail_mean_of_the_pooled_atoms(alpha, shape):
    from wcsac_rl.objectives import gaussian_mixture_cvar, quantile_mixture_cvar

    g = torch.Generator().manual_seed(1)
    quantiles = torch.randn(shape, generator=g, dtype=torch.float64).exp()
    got = float(quantile_mixture_cvar(quantiles, alpha))
    # each pooled value an atom of mass 1/M: the upper α of the mass, the last atom in part
    ordered = sorted(quantiles.flatten().tolist(), reverse=True)
    remaining, total = alpha, 0.0
    for value in ordered:
        share = min(1.0 / len(ordered), remaining)
        total, remaining = total + share * value, remaining - share
    # float64 sums of ≤ 6000 positive terms of size ≤ e⁴
    assert got == pytest.approx(total / alpha, rel=1e-12)
    # a pool of zero-variance Gaussians is the same mixture; gaussian_mixture_cvar
    # smooths each atom into a Gaussian of σ = min_std = 1e-6, which moves a tail mean
    # by ≲ σ/α ≤ 2e-5
    means = quantiles.flatten()
    assert got == pytest.approx(float(gaussian_mixture_cvar(means, None, alpha)), abs=2e-5)


def test_quantile_mixture_cvar_of_dense_gaussian_quantiles_is_the_gaussian_mixture_cvar():
    from statistics import NormalDist

    from wcsac_rl.objectives import gaussian_mixture_cvar, quantile_mixture_cvar

    mean = torch.tensor([0.0, 0.5, 1.0, 8.0], dtype=torch.float64)
    std = torch.tensor([0.1, 1.0, 0.5, 2.0], dtype=torch.float64)
    k = 4000  # quantiles per state at the midpoints of k strata
    z = torch.tensor([NormalDist().inv_cdf((i + 0.5) / k) for i in range(k)], dtype=torch.float64)
    quantiles = mean.unsqueeze(-1) + std.unsqueeze(-1) * z
    for alpha in (0.1, 0.5):
        got = float(quantile_mixture_cvar(quantiles, alpha))
        # the midpoints miss the part of each stratum's mass beyond its midpoint: in
        # the top stratum of the widest component that is ≲ σ·φ(Φ⁻¹(1 − 1/k))/k ≈ 1e-6
        # per unit of mass, far below 1e-3 after dividing by α
        assert got == pytest.approx(float(gaussian_mixture_cvar(mean, std**2, alpha)), abs=1e-3)


def test_quantile_mixture_cvar_refuses_an_empty_pool():
    from wcsac_rl.objectives import quantile_mixture_cvar

    with pytest.raises(ValueError, match="at least one"):
        quantile_mixture_cvar(torch.empty(0, 5), 0.1)
    with pytest.raises(ValueError, match="tail fraction"):
        quantile_mixture_cvar(torch.ones(2, 2), 0.0)
