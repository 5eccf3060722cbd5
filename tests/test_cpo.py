"""CPOLoss: conjugate gradient, Fisher-vector products, the dual step, the line search, GAE.

Tolerances: the linear-algebra tests run in float64 (ε = 2⁻⁵²), where the default
tolerances (1e-7) and the ones given leave 10⁶ and more roundings of headroom on any
CPU; ``atol=2e-3`` and ``abs=1e-7`` against ``_brute_force_qp`` are its grid's
resolution, not rounding. The float32 tests use ``_tolerance.assert_close_f32``.
"""

from __future__ import annotations

import math

import pytest
import torch
from _tolerance import assert_close_f32
from tensordict import TensorDict
from torchrl.data import Bounded
from torchrl.objectives.value.functional import generalized_advantage_estimate

import wcsac_rl.objectives.cpo as cpo_module
from wcsac_rl.modules.gaussian_actor import make_gaussian_actor, make_state_value
from wcsac_rl.objectives.cpo import (
    CPODirection,
    CPOLoss,
    conjugate_gradient,
    cpo_direction,
)

OBS, ACT = 3, 2


def _loss(*, width: int = 16, seed: int = 0, dtype=torch.float32, **kwargs) -> CPOLoss:
    torch.manual_seed(seed)
    actor = make_gaussian_actor(OBS, Bounded(-1.0, 1.0, shape=(ACT,)), width=width, depth=1)
    value = make_state_value(OBS, width=width, depth=1)
    cost_value = make_state_value(OBS, out_key="state_cost_value", width=width, depth=1)
    kwargs.setdefault("cost_limit", 5.0)
    kwargs.setdefault("max_episode_steps", 10)
    loss = CPOLoss(actor, value, cost_value, **kwargs)
    return loss.to(dtype)


def _flat(loss: CPOLoss) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in loss.actor_network.parameters()])


def _sampled_batch(loss: CPOLoss, n: int = 256, seed: int = 1, dtype=torch.float32):
    """States, and actions sampled from the loss's current policy."""
    g = torch.Generator().manual_seed(seed)
    td = TensorDict({"observation": torch.randn(n, OBS, generator=g, dtype=dtype)}, [n])
    with torch.no_grad():
        dist = loss.actor_network.get_dist(td.clone())
        td["action"] = dist.sample()
        td["loc"] = dist.base_dist.loc
    return td


# ----------------------------------------------------------- conjugate gradient
def test_conjugate_gradient_solves_a_known_spd_system():
    g = torch.Generator().manual_seed(0)
    m = torch.randn(8, 8, generator=g, dtype=torch.float64)
    a = m @ m.T + 0.5 * torch.eye(8, dtype=torch.float64)
    b = torch.randn(8, generator=g, dtype=torch.float64)
    x = conjugate_gradient(lambda v: a @ v, b, iters=50, residual_tol=1e-24)
    torch.testing.assert_close(x, torch.linalg.solve(a, b), rtol=1e-8, atol=1e-8)
    # n iterations suffice in exact arithmetic; fewer leave a larger residual
    rough = conjugate_gradient(lambda v: a @ v, b, iters=2)
    assert torch.linalg.norm(a @ rough - b) > torch.linalg.norm(a @ x - b)
    # the hand-checkable 2 x 2 case
    small = torch.tensor([[4.0, 1.0], [1.0, 3.0]], dtype=torch.float64)
    exact = torch.tensor([1.0 / 11.0, 7.0 / 11.0], dtype=torch.float64)
    rhs = torch.tensor([1.0, 2.0], dtype=torch.float64)
    torch.testing.assert_close(conjugate_gradient(lambda v: small @ v, rhs, iters=2), exact)


# --------------------------------------------------------- Fisher-vector product
@pytest.mark.parametrize("damping", [0.0, 0.1])
def test_fisher_vector_product_equals_the_explicit_hessian_of_the_kl(damping):
    loss = _loss(width=4, dtype=torch.float64, damping=damping)
    td = _sampled_batch(loss, n=16, dtype=torch.float64).select("observation")
    net = loss.actor_network.module[0]  # observation -> (loc, scale): all the actor's params
    names = [name for name, _ in net.named_parameters()]
    shapes = [p.shape for p in net.parameters()]
    theta0 = _flat(loss)
    assert theta0.numel() == sum(p.numel() for p in loss.actor_network.parameters())

    def dist_at(flat):
        params, offset = {}, 0
        for name, shape in zip(names, shapes):
            n = math.prod(shape)
            params[name] = flat[offset : offset + n].view(shape)
            offset += n
        out = torch.func.functional_call(net, params, (td.clone(),))
        return torch.distributions.Normal(out["loc"], out["scale"])

    old = dist_at(theta0)
    old = torch.distributions.Normal(old.loc.detach(), old.scale.detach())

    def mean_kl(flat):
        return torch.distributions.kl_divergence(old, dist_at(flat)).sum(-1).mean()

    hessian = torch.autograd.functional.hessian(mean_kl, theta0)
    v = torch.randn(theta0.numel(), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    fvp = loss.fisher_vector_product(td, v)
    torch.testing.assert_close(fvp, hessian @ v + damping * v, rtol=1e-9, atol=1e-9)
    # the Hessian of the KL at θ_old is the Fisher matrix: symmetric, positive semi-definite
    torch.testing.assert_close(hessian, hessian.T)
    assert torch.linalg.eigvalsh(hessian).min() > -1e-10


# ----------------------------------------------------------------- dual step
def _brute_force_qp(h, g, b, c, delta, n=200_001):
    """max gᵀx s.t. bᵀx + c <= 0, ½xᵀHx <= δ by dense search of the feasible set's boundary.

    A linear objective is maximised on the boundary: on the ellipse's feasible arc
    (sampled densely) or at an end of the constraint line's chord (computed exactly).
    """
    chol = torch.linalg.cholesky(h)
    angles = torch.linspace(0, 2 * math.pi, n, dtype=torch.float64)
    unit = torch.stack([angles.cos(), angles.sin()], 1) * math.sqrt(2 * delta)
    arc = torch.linalg.solve_triangular(chol.T, unit.T, upper=True).T  # ½xᵀHx = δ
    points = [arc[arc @ b + c <= 0]]
    # the chord: x = p0 + t·u with ½xᵀHx = δ, a quadratic in t
    p0 = -c * b / (b @ b)
    u = torch.stack([-b[1], b[0]])
    qa, qb, qc = 0.5 * u @ h @ u, u @ h @ p0, 0.5 * p0 @ h @ p0 - delta
    disc = qb * qb - 4 * qa * qc
    if disc >= 0:
        ends = [(-qb + sign * disc.sqrt()) / (2 * qa) for sign in (-1, 1)]
        points.append(torch.stack([p0 + t * u for t in ends]))
    points = torch.cat(points)
    values = points @ g
    best = values.argmax()
    return float(values[best]), points[best]


def test_the_dual_solution_is_the_optimum_of_the_quadratic_program_in_2d():
    gen = torch.Generator().manual_seed(0)
    delta = 0.05
    seen = set()
    for _ in range(60):
        m = torch.randn(2, 2, generator=gen, dtype=torch.float64)
        h = m @ m.T + 0.3 * torch.eye(2, dtype=torch.float64)
        g = torch.randn(2, generator=gen, dtype=torch.float64)
        b = torch.randn(2, generator=gen, dtype=torch.float64)
        c = 0.5 * float(torch.randn((), generator=gen, dtype=torch.float64))
        d = cpo_direction(g, b, c, delta, lambda v, h=h: torch.linalg.solve(h, v))
        seen.add(d.case)
        if d.case == 0:  # no feasible point: checked in the recovery test
            continue
        x = d.step
        assert 0.5 * x @ h @ x <= delta * (1 + 1e-9)  # inside the trust region
        assert b @ x + c <= 1e-9  # the linearised constraint holds
        best, argbest = _brute_force_qp(h, g, b, c, delta)
        assert float(g @ x) == pytest.approx(best, abs=1e-7)
        torch.testing.assert_close(x, argbest, atol=2e-3, rtol=0)
        # the dual variables reproduce the step: x = H⁻¹(g − νb)/λ
        torch.testing.assert_close(x, torch.linalg.solve(h, g - d.nu * b) / d.lam)
    assert {0, 1, 2, 3} <= seen  # every geometry was exercised


def test_a_far_constraint_gives_the_trpo_step():
    h = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=torch.float64)
    g = torch.tensor([1.0, 0.2], dtype=torch.float64)
    b = torch.tensor([0.1, 0.3], dtype=torch.float64)
    d = cpo_direction(g, b, -10.0, 0.01, lambda v: torch.linalg.solve(h, v))
    assert d.case == 3 and d.nu == 0.0 and not d.infeasible
    natural = torch.linalg.solve(h, g)
    torch.testing.assert_close(d.step, math.sqrt(2 * 0.01 / (g @ natural)) * natural)
    # no cost gradient at all: a TRPO step too (case 4)
    d0 = cpo_direction(g, torch.zeros(2, dtype=torch.float64), -1.0, 0.01, lambda v: v)
    assert d0.case == 4
    torch.testing.assert_close(d0.step, math.sqrt(2 * 0.01 / (g @ g)) * g)
    # ... but if infeasible, with no cost gradient there is nothing to do
    stuck = cpo_direction(g, torch.zeros(2, dtype=torch.float64), 1.0, 0.01, lambda v: v)
    assert stuck.case == 0 and torch.equal(stuck.step, torch.zeros(2, dtype=torch.float64))


def test_the_infeasible_case_takes_the_recovery_step_that_reduces_cost_most():
    h = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=torch.float64)
    g = torch.tensor([1.0, 0.2], dtype=torch.float64)  # the reward would go elsewhere
    b = torch.tensor([0.3, -0.4], dtype=torch.float64)
    delta = 0.01
    d = cpo_direction(g, b, 1.0, delta, lambda v: torch.linalg.solve(h, v))
    assert isinstance(d, CPODirection)
    assert d.case == 0 and d.infeasible and d.recovery
    x = d.step
    s = float(b @ torch.linalg.solve(h, b))
    # on the trust region's boundary, along −H⁻¹b: the largest linearised cost decrease
    assert 0.5 * x @ h @ x == pytest.approx(delta)
    assert float(b @ x) == pytest.approx(-math.sqrt(2 * delta * s))
    _, most_decrease = _brute_force_qp(h, -b, b, -1e9, delta)  # min bᵀx over the region
    torch.testing.assert_close(x, most_decrease, atol=2e-3, rtol=0)
    # infeasible, but the constraint cuts the trust region: a dual step (case 1)
    d1 = cpo_direction(g, b, 0.05, delta, lambda v: torch.linalg.solve(h, v))
    assert d1.case == 1 and d1.infeasible and not d1.recovery
    assert b @ d1.step + 0.05 <= 1e-9
    assert float(g @ d1.step) == pytest.approx(_brute_force_qp(h, g, b, 0.05, delta)[0])


@pytest.mark.parametrize("c", [0.05, -0.05])
def test_parallel_reward_and_cost_gradients_step_to_the_constraint_boundary(c):
    """g = 2b: more reward is more cost; the best point is on the constraint line."""
    h = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=torch.float64)
    b = torch.tensor([0.3, -0.4], dtype=torch.float64)
    g = 2 * b
    delta = 0.01
    d = cpo_direction(g, b, c, delta, lambda v: torch.linalg.solve(h, v))
    w = torch.linalg.solve(h, b)
    assert d.case == (1 if c > 0 else 2)
    torch.testing.assert_close(d.step, -(c / float(b @ w)) * w)  # nearest boundary point
    assert float(b @ d.step) + c == pytest.approx(0.0, abs=1e-12)
    assert float(g @ d.step) == pytest.approx(_brute_force_qp(h, g, b, c, delta)[0], abs=1e-9)


# ------------------------------------------------------- the step on a policy
def _set_advantages(td, reward_adv, cost_adv):
    td["advantage"] = reward_adv.unsqueeze(-1)
    td["cost_advantage"] = cost_adv.unsqueeze(-1)
    return td


def _cost_gradient(loss: CPOLoss, td) -> torch.Tensor:
    """b = ∇ mean(ρ Â^c) at θ_old, computed independently of the loss."""
    dist = loss.actor_network.get_dist(td.select("observation"))
    log_prob = dist.log_prob(td["action"])
    cadv = td["cost_advantage"].squeeze(-1)
    cadv = cadv - cadv.mean()
    surrogate = ((log_prob - log_prob.detach()).exp() * cadv).mean()
    grads = torch.autograd.grad(surrogate, list(loss.actor_network.parameters()))
    return torch.cat([gr.reshape(-1) for gr in grads])


def test_a_feasible_step_respects_the_kl_bound_and_the_linearised_cost_constraint():
    # float64 and enough CG iterations to solve H⁻¹g, H⁻¹b exactly (the step is then
    # the exact QP solution; with 10 CG steps it is within ~1% of it)
    loss = _loss(dtype=torch.float64, cg_iters=300)
    td = _sampled_batch(loss, dtype=torch.float64)
    a = td["action"]
    # the reward wants both action components up, the cost penalises the second one
    _set_advantages(td, a[:, 0] + a[:, 1], a[:, 1])
    b = _cost_gradient(loss, td)
    before = _flat(loss)
    # J_C just under d: feasible, and the constraint cuts the trust region
    info = loss.policy_step(td, episode_cost=5.0 - 1e-3, episode_length=1.0)
    c = -1e-3
    assert int(info["optim_case"]) == 2 and float(info["lagrange_nu"]) > 0
    assert bool(info["accepted"]) and not bool(info["infeasible"])
    step = _flat(loss) - before
    assert float(b @ step) + c <= 1e-6  # the linearised constraint at the chosen step
    assert float(info["cost_surrogate_change"]) <= -c + 1e-7
    assert float(info["surrogate_improvement"]) >= 0
    with torch.no_grad():  # the measured KL(π_old ‖ π_new) is within δ
        new = loss.actor_network.get_dist(td.select("observation"))
        old_scale = torch.full_like(td["loc"], math.exp(-0.5))
        old = torch.distributions.Normal(td["loc"], old_scale)
        kl = torch.distributions.kl_divergence(old, new.base_dist).sum(-1).mean()
    assert float(kl) == pytest.approx(float(info["kl"]), rel=1e-4)
    assert float(kl) <= loss.max_kl
    # compared with the unconstrained (TRPO) step from the same point, CPO raises the
    # cost component less
    trpo = _loss(dtype=torch.float64, cg_iters=300)
    trpo_td = _set_advantages(td.clone(), a[:, 0] + a[:, 1], a[:, 1])
    trpo.policy_step(trpo_td, episode_cost=-1e6, episode_length=1.0)
    with torch.no_grad():
        obs = td.select("observation")
        cpo_mean = loss.actor_network.get_dist(obs.clone()).base_dist.loc[:, 1].mean()
        trpo_mean = trpo.actor_network.get_dist(obs.clone()).base_dist.loc[:, 1].mean()
    assert cpo_mean < trpo_mean


@pytest.mark.parametrize(("excess", "case"), [(5.0, 0), (0.05, 1)])
def test_an_infeasible_step_reduces_the_expected_cost(excess, case):
    """One-step problem with cost = a₁: E[cost | s] = μ₁(s), advantage a₁ − μ₁(s)."""
    loss = _loss()
    td = _sampled_batch(loss)
    a, mu = td["action"], td["loc"]
    # the reward likes what costs (and a₀)
    _set_advantages(td, a[:, 0] + a[:, 1] - mu.sum(-1), a[:, 1] - mu[:, 1])
    expected_cost_before = float(mu[:, 1].mean())
    info = loss.policy_step(td, episode_cost=5.0 + excess, episode_length=1.0)
    assert int(info["optim_case"]) == case
    assert bool(info["infeasible"]) and bool(info["recovery"]) == (case == 0)
    assert bool(info["accepted"]) and float(info["kl"]) <= loss.max_kl
    assert float(info["cost_surrogate_change"]) < 0
    # J_C − d is computed in float64 and rounded to float32 once: ≤ 2⁻²⁴ relative,
    # within approx's default 1e-6
    assert float(info["constraint"]) == pytest.approx(excess)
    with torch.no_grad():
        new_mu = loss.actor_network.get_dist(td.select("observation")).base_dist.loc
    # E[cost] = mean μ₁ fell by about the linearised amount (≥ c = excess here)
    assert float(new_mu[:, 1].mean()) < expected_cost_before - 0.02


def test_a_failed_line_search_keeps_the_old_policy(monkeypatch):
    loss = _loss(backtrack_iters=3)
    td = _sampled_batch(loss)
    _set_advantages(td, td["action"][:, 0], td["action"][:, 1])
    before = _flat(loss)
    real = cpo_module.cpo_direction

    def huge_step(*args, **kwargs):
        direction = real(*args, **kwargs)
        direction.step = direction.step * 1e3  # far outside the trust region
        return direction

    monkeypatch.setattr(cpo_module, "cpo_direction", huge_step)
    info = loss.policy_step(td, episode_cost=0.0, episode_length=1.0)
    assert not bool(info["accepted"])
    assert float(info["line_search_steps"]) == 3 and float(info["step_fraction"]) == 0
    assert float(info["kl"]) == 0
    torch.testing.assert_close(_flat(loss), before, rtol=0, atol=0)  # restored by a copy


# ------------------------------------------------------------------ GAE / keys
def _trajectory_batch(n_envs=3, t=7, seed=0):
    g = torch.Generator().manual_seed(seed)
    done = torch.zeros(n_envs, t, 1, dtype=torch.bool)
    done[:, 3] = True  # an episode ends mid-batch
    terminated = done.clone()
    terminated[0, 3] = False  # ... truncated in env 0
    return TensorDict(
        {
            "observation": torch.randn(n_envs, t, OBS, generator=g),
            "action": torch.randn(n_envs, t, ACT, generator=g),
            "next": {
                "observation": torch.randn(n_envs, t, OBS, generator=g),
                "reward": torch.randn(n_envs, t, 1, generator=g),
                "my_cost": torch.bernoulli(torch.full((n_envs, t, 1), 0.4), generator=g),
                "done": done,
                "terminated": terminated,
                "episode_cost": torch.full((n_envs, t, 1), 4.0),
                "step_count": torch.full((n_envs, t, 1), 4),
            },
        },
        [n_envs, t],
        names=[None, "time"],
    )


def test_compute_advantages_runs_torchrl_gae_on_the_reward_and_on_the_cost():
    loss = _loss()
    loss.make_value_estimator(gamma=0.9, lmbda=0.8, cost_gamma=0.95, cost_lmbda=0.5)
    loss.set_keys(cost="my_cost")
    td = _trajectory_batch()
    loss.compute_advantages(td)
    with torch.no_grad():
        for net, key, target_key, gamma, lmbda, signal in (
            (loss.value_network, "advantage", "value_target", 0.9, 0.8, "reward"),
            (loss.cost_value_network, "cost_advantage", "cost_value_target", 0.95, 0.5, "my_cost"),
        ):
            out_key = net.out_keys[0]
            value = net(td.select("observation").clone())[out_key]
            next_value = net(td["next"].select("observation").clone())[out_key]
            adv, target = generalized_advantage_estimate(
                gamma,
                lmbda,
                value,
                next_value,
                td["next", signal],
                done=td["next", "done"],
                terminated=td["next", "terminated"],
                time_dim=1,
            )
            # the value MLPs (16-term sums) on another batch layout, then GAE's 7-step
            # recursion (a product and a sum per step): ≤ 32 roundings of the largest entry
            assert_close_f32(td[key], adv, ops=32, msg=key)
            assert_close_f32(td[target_key], target, ops=32, msg=target_key)
    # a missing cost key is one clear error
    with pytest.raises(KeyError, match="needs a per-step cost"):
        _loss().compute_advantages(_trajectory_batch())


def test_episode_cost_estimate_uses_finished_episodes_or_the_cost_rate():
    loss = _loss(max_episode_steps=10)
    td = _trajectory_batch()
    assert loss.episode_cost_estimate(td) == (4.0, 4.0, 3)
    td["next", "done"] = torch.zeros_like(td["next", "done"])
    td["next", "cost"] = torch.full_like(td["next", "my_cost"], 0.25)
    assert loss.episode_cost_estimate(td) == (2.5, 10.0, 0)  # 0.25 per step × 10 steps
    with pytest.raises(ValueError, match="no episode ended"):
        _loss(max_episode_steps=None).episode_cost_estimate(td)
    no_sums = _trajectory_batch().exclude(("next", "episode_cost"))
    with pytest.raises(KeyError, match="episode_cost"):
        loss.episode_cost_estimate(no_sums)


def test_forward_returns_the_differentiable_terms():
    loss = _loss()
    loss.set_keys(cost="my_cost")
    td = _trajectory_batch()
    with pytest.raises(KeyError, match="compute_advantages"):
        loss(td)
    loss.compute_advantages(td)
    out = loss(td)
    assert set(out.keys()) == set(loss.out_keys)
    assert all(v.shape == () for v in out.values())
    # loss_cost_objective's gradient is the cost gradient b of the policy step
    grads = torch.autograd.grad(out["loss_cost_objective"], list(loss.actor_network.parameters()))
    flat = torch.cat([g.reshape(-1) for g in grads])
    # a batch mean of 21 per-sample gradients through 16-wide layers, per entry
    assert_close_f32(flat, _cost_gradient(loss, td.reshape(-1)), ops=32)
    # the value losses reach only their own networks
    (out["loss_value"] + out["loss_cost_value"]).backward()
    assert all(p.grad is not None for p in loss.value_network.parameters())
    assert all(p.grad is not None for p in loss.cost_value_network.parameters())
    assert all(p.grad is None for p in loss.actor_network.parameters())
    # reduction="none" gives per-sample terms
    loss_none = _loss(reduction="none")
    loss_none.set_keys(cost="my_cost")
    loss_none.compute_advantages(td)
    out_none = loss_none(td)
    assert out_none["loss_value"].shape == td.shape
    # a mean of 21 non-negative squared errors, summed in another order
    assert_close_f32(out_none["loss_value"].mean(), out["loss_value"], ops=21)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"cost_limit": -1.0}, "cost_limit must be >= 0"),
        ({"max_kl": 0.0}, "max_kl"),
        ({"backtrack_coeff": 1.0}, "backtrack_coeff"),
        ({"cg_iters": 0}, "cg_iters"),
        ({"reduction": "max"}, "reduction"),
    ],
)
def test_bad_arguments_give_one_clear_error(kwargs, message):
    with pytest.raises(ValueError, match=message):
        _loss(**kwargs)


def test_the_loss_state_dict_holds_the_networks_only():
    loss = _loss()
    keys = set(loss.state_dict())
    assert any(k.startswith("actor_network.") for k in keys)
    assert any(k.startswith("value_network.") for k in keys)
    assert any(k.startswith("cost_value_network.") for k in keys)
    assert not any("estimator" in k for k in keys)  # γ/λ come from the config on resume
    with pytest.raises(NotImplementedError, match="GAE only"):
        loss.make_value_estimator(cpo_module.ValueEstimators.TD0)
