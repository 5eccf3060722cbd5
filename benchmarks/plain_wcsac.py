"""One WCSAC update in plain PyTorch: the reference of the algorithm, and a benchmark baseline.

``PlainWCSAC.update`` is one gradient step of Worst-Case Soft Actor Critic (Yang et
al., AAAI 2021) written out without TorchRL or tensordict: ``nn.Sequential`` MLPs
and the losses as formulas. It is the paper's update with an MSE variance loss: its
loss terms and gradients are those ``WCSACLoss`` computes with these options::

    WCSACLoss(actor, [qvalue, qvalue], safety, risk_level=α,
              **loss_parts({**PAPER_OPTIONS, "variance_loss": "mse"}))

that is:

* ``variance_target="moment"`` (Eq. 8): V^c's target is the second moment of the
  sampled cost return minus the squared mean,
  ``c² + (1−term)(2γ c Q̄^c' + γ²(V̄^c' + Q̄^c'²)) − Q^c(s, a)²``;
* ``variance_loss="mse"``: ``½ (V^c − y)²`` (not the paper's W2, ``"w2"``; the
  default ``"glm"`` has the same value but another gradient);
* ``cost_gamma=None``, ``cost_n_steps=1``, ``nonnegative_cost=False``: one-step
  cost targets with the reward's γ = 0.99, Q^c used as it is (Eq. 7);
* ``kappa_states="replay"``, ``kappa_actions="policy"``, ``kappa_statistic="mean"``
  (and ``kappa_signal="critic"``, ``damp_scale=0``): κ holds the batch mean of
  Γ(s, a ~ π) under the per-step threshold ``d (1 − γ^T) / ((1 − γ) T)``
  (d = 15, T = 1000: 1.49994);
* ``kappa_parametrization="softplus"``, κ initially softplus(0) = log 2;
* β = exp(log β) with log β = 0 initially, target entropy −|A|;
* two reward critics, ``loss_function="l2"``: their loss is ``Σ_i (Q_i − y)²``
  (summed over the twins, not halved, as TorchRL's SAC), the cost mean's is
  ``½ (Q^c − y_c)²``;
* the networks of :mod:`wcsac_rl.modules`: a tanh-Normal actor with log σ clamped
  to [−20, 2], ``V^c = clamp(softplus(·), 1e-8, 1e8)``.

How to read :meth:`PlainWCSAC.losses` and :meth:`PlainWCSAC.update`: (1) the TD
targets, without gradient, from one next action ``a' ~ π(s')`` and the target
critics; (2) the critics' losses at the replay actions; (3) the actor, β and κ
losses from one reparametrised ``a ~ π(s)`` with the critics frozen; (4) one Adam
step of every parameter group on the sum of the six losses (each term reaches only
its own parameters); (5) Polyak averaging of the target critics.

``tests/test_plain_reference.py`` checks that :meth:`PlainWCSAC.losses` gives
``WCSACLoss``'s six loss terms and the gradients of every parameter group (same
weights, same noise) at α = 0.5 and α = 1, to float32 rounding. Left out here, as
they never bind there: TorchRL's tanh is clamped to ±(1 − 10⁻⁶) (equal to ``tanh``
unless the pre-tanh action exceeds 7), and ``WCSACLoss`` clamps the variance target
to ±1e8. Both compute the threshold from γ = 0.99 (1.4999352; ``WCSACLoss`` keeps it
in a float32 buffer).

``benchmarks/bench_update.py`` times :meth:`PlainWCSAC.update` (2 × 256 networks,
fused Adam) to show what the update costs without any framework overhead. The
package does not use this file.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import torch
from torch import nn
from torch.nn import functional as F


def mlp(in_features: int, out_features: int, width: int = 256) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_features, width),
        nn.ReLU(),
        nn.Linear(width, width),
        nn.ReLU(),
        nn.Linear(width, out_features),
    )


def batch_inputs(batch) -> tuple[torch.Tensor, ...]:
    """The arguments of :meth:`PlainWCSAC.losses` / :meth:`PlainWCSAC.update` from a batch
    in TorchRL's layout (``observation``, ``action`` and ``next``'s ``reward``, ``cost``,
    ``observation``, ``terminated``)."""
    nxt = batch["next"]
    return (
        batch["observation"],
        batch["action"],
        nxt["reward"].squeeze(-1),
        nxt["cost"].squeeze(-1),
        nxt["observation"],
        nxt["terminated"].squeeze(-1).float(),
    )


def variance(raw: torch.Tensor) -> torch.Tensor:
    """The variance head's output ``V^c > 0`` from its last layer."""
    return F.softplus(raw).clamp(1e-8, 1e8)


class PlainWCSAC(nn.Module):
    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        *,
        width: int = 256,
        risk_level: float = 0.5,
        gamma: float = 0.99,
        tau: float = 0.005,
        lr: float = 1e-3,
        cost_limit: float = 15.0,
        max_episode_steps: int = 1000,
        cost_threshold: float | None = None,
    ) -> None:
        super().__init__()
        nd = NormalDist()  # Γ = Q^c + multiplier·√V^c, multiplier = α⁻¹ φ(Φ⁻¹(α)) (Eq. 9)
        self.multiplier = 0.0 if risk_level == 1 else nd.pdf(nd.inv_cdf(risk_level)) / risk_level
        if cost_threshold is None:  # d spread over T steps, discounted: Σ_{t<T} γ^t d/T
            steps = (1 - gamma**max_episode_steps) / (1 - gamma) if gamma < 1 else max_episode_steps
            cost_threshold = cost_limit * steps / max_episode_steps
        self.gamma, self.tau, self.threshold = gamma, tau, cost_threshold
        self.target_entropy = -float(act_dim)
        self.actor = mlp(obs_dim, 2 * act_dim, width)
        self.q1, self.q2 = mlp(obs_dim + act_dim, 1, width), mlp(obs_dim + act_dim, 1, width)
        self.qc, self.vc = mlp(obs_dim + act_dim, 1, width), mlp(obs_dim + act_dim, 1, width)
        self.critics = nn.ModuleList([self.q1, self.q2, self.qc, self.vc])
        self.targets = nn.ModuleList([mlp(obs_dim + act_dim, 1, width) for _ in range(4)])
        self.targets.load_state_dict(self.critics.state_dict())
        self.targets.requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.zeros(()))  # log β
        self.kappa_raw = nn.Parameter(torch.zeros(()))  # κ = softplus(kappa_raw)
        self.optimizers = [
            torch.optim.Adam(self.actor.parameters(), lr=lr, fused=True),
            torch.optim.Adam(self.critics.parameters(), lr=lr, fused=True),
            torch.optim.Adam([self.log_alpha], lr=lr, fused=True),
            torch.optim.Adam([self.kappa_raw], lr=lr, fused=True),
        ]

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparametrised ``a = tanh(μ + σ ε)``, ``ε ~ N(0, I)``, and ``log π(a|s)``."""
        loc, log_std = self.actor(obs).chunk(2, -1)
        std = log_std.clamp(-20, 2).exp()
        u = loc + std * torch.randn_like(loc)
        normal = -((u - loc) ** 2) / (2 * std**2) - std.log() - 0.5 * math.log(2 * math.pi)
        log_det = 2 * (math.log(2) - u - F.softplus(-2 * u))  # log tanh'(u), stably
        return torch.tanh(u), normal.sum(-1) - log_det.sum(-1)

    def losses(self, obs, act, rew, cost, next_obs, terminated) -> dict[str, torch.Tensor]:
        """The six loss terms of one update (batch means), named as ``WCSACLoss`` names them.

        ``rew``, ``cost`` and ``terminated`` (0. or 1.) are shaped like the batch.
        """
        beta = self.log_alpha.exp().detach()
        kappa = F.softplus(self.kappa_raw)
        # (1) targets: a' ~ π(s'), the target critics, no gradient
        with torch.no_grad():
            next_act, next_logp = self.sample(next_obs)
            x_next = torch.cat([next_obs, next_act], -1)
            tq1, tq2, tqc, tvc = (net(x_next).squeeze(-1) for net in self.targets)
            tvc = variance(tvc)
            not_term = 1.0 - terminated
            y_r = rew + self.gamma * not_term * (torch.min(tq1, tq2) - beta * next_logp)
            y_c = cost + self.gamma * not_term * tqc  # Eq. 7
            # E[(c + γ C')²] with C' ~ N(Q̄^c', V̄^c'): minus Q^c(s, a)², the target of Eq. 8
            m2 = cost**2 + not_term * (2 * self.gamma * cost * tqc + self.gamma**2 * (tvc + tqc**2))
        # (2) the critics at the replay actions
        x = torch.cat([obs, act], -1)
        q1, q2, qc = self.q1(x).squeeze(-1), self.q2(x).squeeze(-1), self.qc(x).squeeze(-1)
        vc = variance(self.vc(x).squeeze(-1))
        loss_q = ((q1 - y_r) ** 2 + (q2 - y_r) ** 2).mean()
        loss_qc = 0.5 * ((qc - y_c) ** 2).mean()
        loss_vc = 0.5 * ((vc - (m2 - qc.detach() ** 2)) ** 2).mean()
        # (3) actor, β and κ at a ~ π(s); gradients reach the actor through a only
        pi_act, logp = self.sample(obs)
        x_pi = torch.cat([obs, pi_act], -1)
        self.critics.requires_grad_(False)
        q_pi = torch.min(self.q1(x_pi), self.q2(x_pi)).squeeze(-1)
        cvar_pi = (
            self.qc(x_pi).squeeze(-1) + self.multiplier * variance(self.vc(x_pi)).squeeze(-1).sqrt()
        )
        self.critics.requires_grad_(True)
        loss_pi = (beta * logp - q_pi + kappa.detach() * cvar_pi).mean()
        loss_alpha = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        loss_kappa = (kappa * (self.threshold - cvar_pi.detach())).mean()
        return {
            "loss_actor": loss_pi,
            "loss_qvalue": loss_q,
            "loss_alpha": loss_alpha,
            "loss_cost_value": loss_qc,
            "loss_cost_variance": loss_vc,
            "loss_kappa": loss_kappa,
        }

    def update(self, obs, act, rew, cost, next_obs, terminated) -> torch.Tensor:
        """One update: the losses, (4) one Adam step per group, (5) Polyak targets."""
        total = sum(self.losses(obs, act, rew, cost, next_obs, terminated).values())
        total.backward()
        for optimizer in self.optimizers:
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            online = [p for net in self.critics for p in net.parameters()]
            target = [p for net in self.targets for p in net.parameters()]
            torch._foreach_lerp_(target, online, self.tau)
        return total.detach()
