"""The paper's central claim on the smallest task where it can be checked exactly.

On :class:`~wcsac_rl.envs.risky_bandit.RiskyBanditEnv` the expected cost is under
the limit for every action, but the CVaR_0.1 is not: SAC-Lag must take the
high-reward end, WCSAC-0.1 must settle at the closed-form CVaR-feasible action.

Tolerances: ``abs=1e-3`` is the quoted a* = −0.621's precision, ``abs=1e-6`` the
float64 root finder's; ``0.2`` and ``0.5`` bound what a trained policy reaches
(behaviour, not rounding).
"""

from __future__ import annotations

import pytest

from paper.bandit_ablation import COST_LIMIT, train_on_risky_bandit
from wcsac_rl.envs.risky_bandit import RiskyBanditEnv


def test_bandit_closed_form_facts():
    env = RiskyBanditEnv()
    assert float(env.expected_cost(1.0)) == pytest.approx(0.9)  # E[c] < 3 everywhere
    a_star = env.cvar_feasible_action(0.1, COST_LIMIT)
    assert a_star == pytest.approx(-0.621, abs=1e-3)
    assert float(env.gaussian_cvar(a_star, 0.1)) == pytest.approx(COST_LIMIT, abs=1e-6)
    assert env.cvar_feasible_action(1.0, COST_LIMIT) == 1.0
    with pytest.raises(ValueError, match="no action"):
        env.cvar_feasible_action(0.1, 0.5)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_sac_lag_takes_the_high_reward_end(seed):
    run = train_on_risky_bandit(risk_level=1.0, variance=False, seed=seed, report_risk_level=0.1)
    # measured: E_π[a] = +0.85/+0.86 (tanh-squashed policy with its target entropy)
    assert run.mean_action > 0.7
    assert run.true_cvar > COST_LIMIT + 1.5  # CVaR_0.1 ≈ 5.7: far over the limit


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_wcsac_settles_at_the_cvar_feasible_action(seed):
    a_star = RiskyBanditEnv().cvar_feasible_action(0.1, COST_LIMIT)  # -0.621
    run = train_on_risky_bandit(risk_level=0.1, seed=seed)  # the kit's reads (KIT_READS)
    # measured (variance_loss="glm"): E_π[a] = -0.69, -0.75, -0.65 (seed 3: -0.67) and
    # E_π[CVaR_0.1] 2.69, 2.54, 2.78 (2.80): at or just under the limit
    assert run.mean_action == pytest.approx(a_star, abs=0.2)
    assert COST_LIMIT - 0.7 <= run.true_cvar <= COST_LIMIT + 0.3


@pytest.mark.slow
def test_the_papers_w2_variance_loss_takes_the_high_reward_end_as_sac_lag_does():
    """The loss's own defaults, the paper's, fit the variance with the 2-Wasserstein TD,
    whose fixed point on sampled targets is √V = E[√y]: the rare cost's variance is
    underestimated and WCSAC-0.1 goes where SAC-Lag goes (docs/defaults.md)."""
    paper = {"variance_loss": "w2", "variance_target": "moment", "cost_gamma": None}
    run = train_on_risky_bandit(
        risk_level=0.1, seed=0, **paper, nonnegative_cost=False, kappa_statistic="mean"
    )
    # measured: E_π[a] = +0.87, E_π[CVaR_0.1] 5.7 (SAC-Lag: +0.85, 5.71)
    assert run.mean_action > 0.7
    assert run.true_cvar > COST_LIMIT + 1.5


def test_bandit_exact_cvar_facts():
    env = RiskyBanditEnv()
    # the cost's own CVaR_0.1 is 10·min(p/0.1, 1) = 100 p: 3 at p = 0.03, i.e. a = −0.5
    a_exact = env.cvar_feasible_action(0.1, COST_LIMIT, exact=True)
    assert a_exact == pytest.approx(-0.5, abs=1e-6)
    assert float(env.exact_cvar(a_exact, 0.1)) == pytest.approx(COST_LIMIT, abs=1e-6)
    assert float(env.exact_cvar(1.0, 0.1)) == pytest.approx(9.0)
    assert float(env.exact_cvar(1.0, 1.0)) == pytest.approx(float(env.expected_cost(1.0)))
    # beyond p = α the whole tail is the hit itself
    assert float(env.exact_cvar(1.0, 0.05)) == pytest.approx(10.0)


@pytest.mark.slow
def test_wcsac_with_an_iqn_critic_settles_near_the_exact_cvar_feasible_action():
    """An implicit-quantile critic holds the cost's own CVaR_0.1 at the limit: the
    feasible optimum is a* = −0.5 (exact CVaR; the Gaussian critic's is −0.621, SAC-Lag
    goes to +0.86). Measured, seeds 0, 1, 2: E_π[a] = −0.49, −0.51, −0.38 (exact
    CVaR_0.1 3.03, 2.98, 3.46) on one machine, −0.53, −0.70, −0.53 (2.87, 2.19, 2.90;
    seeds 3, 4: −0.53, −0.63) on another: floating-point rounding moves a seed by up to
    0.2, more than the 0.12 between the two optima, so the test asserts what holds on
    every seed (risk-averse, CVaR within 1 of the limit) and the seeds' mean at a*."""
    a_star = RiskyBanditEnv().cvar_feasible_action(0.1, COST_LIMIT, exact=True)
    runs = [
        train_on_risky_bandit(risk_level=0.1, seed=seed, safety_critic="iqn") for seed in (0, 1, 2)
    ]
    for run in runs:
        assert run.mean_action < -0.3  # (the risk-neutral optimum is +1)
        # d CVaR/da = hit·(p_high − p_low)/(2α) = 4 here: 1 of CVaR is 0.25 of action
        assert run.exact_cvar == pytest.approx(COST_LIMIT, abs=1.0)
    mean_action = sum(run.mean_action for run in runs) / len(runs)
    assert mean_action == pytest.approx(a_star, abs=0.15)
