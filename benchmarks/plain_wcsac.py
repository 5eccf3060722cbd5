"""A plain-PyTorch WCSAC update (no TorchRL, no tensordict), the reference for benchmarks.

Same networks (2 × 256 ReLU), same losses as ``WCSACLoss``'s defaults (MSE variance
loss, κ at policy actions, softplus κ, log β), same (fused) Adam and polyak schedule. It exists
to show what the update costs without any framework overhead; it is not used by
the package.
"""

from __future__ import annotations

import math

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
        cost_threshold: float = 1.49994,
    ) -> None:
        super().__init__()
        from statistics import NormalDist

        nd = NormalDist()
        self.multiplier = 0.0 if risk_level == 1 else nd.pdf(nd.inv_cdf(risk_level)) / risk_level
        self.gamma, self.tau, self.threshold = gamma, tau, cost_threshold
        self.target_entropy = -float(act_dim)
        self.actor = mlp(obs_dim, 2 * act_dim, width)
        self.q1, self.q2 = mlp(obs_dim + act_dim, 1, width), mlp(obs_dim + act_dim, 1, width)
        self.qc, self.vc = mlp(obs_dim + act_dim, 1, width), mlp(obs_dim + act_dim, 1, width)
        self.critics = nn.ModuleList([self.q1, self.q2, self.qc, self.vc])
        self.targets = nn.ModuleList([mlp(obs_dim + act_dim, 1, width) for _ in range(4)])
        self.targets.load_state_dict(self.critics.state_dict())
        self.targets.requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.zeros(()))
        self.kappa_raw = nn.Parameter(torch.zeros(()))
        self.optimizers = [
            torch.optim.Adam(self.actor.parameters(), lr=lr, fused=True),
            torch.optim.Adam(self.critics.parameters(), lr=lr, fused=True),
            torch.optim.Adam([self.log_alpha], lr=lr, fused=True),
            torch.optim.Adam([self.kappa_raw], lr=lr, fused=True),
        ]

    def sample(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, log_std = self.actor(obs).chunk(2, -1)
        std = log_std.clamp(-20, 2).exp()
        u = loc + std * torch.randn_like(loc)
        log_prob = (-((u - loc) ** 2) / (2 * std**2) - std.log() - 0.5 * math.log(2 * math.pi)).sum(
            -1
        )
        log_prob = log_prob - (2 * (math.log(2) - u - F.softplus(-2 * u))).sum(-1)
        return torch.tanh(u), log_prob

    def update(self, obs, act, rew, cost, next_obs, terminated) -> torch.Tensor:
        alpha = self.log_alpha.exp().detach()
        kappa = F.softplus(self.kappa_raw)
        with torch.no_grad():
            next_act, next_logp = self.sample(next_obs)
            x_next = torch.cat([next_obs, next_act], -1)
            tq1, tq2, tqc, tvc = (net(x_next).squeeze(-1) for net in self.targets)
            tvc = F.softplus(tvc).clamp(1e-8, 1e8)
            not_term = 1.0 - terminated
            y_r = rew + self.gamma * not_term * (torch.min(tq1, tq2) - alpha * next_logp)
            y_c = cost + self.gamma * not_term * tqc
            m2 = cost**2 + not_term * (2 * self.gamma * cost * tqc + self.gamma**2 * (tvc + tqc**2))
        x = torch.cat([obs, act], -1)
        q1, q2, qc = self.q1(x).squeeze(-1), self.q2(x).squeeze(-1), self.qc(x).squeeze(-1)
        vc = F.softplus(self.vc(x)).squeeze(-1).clamp(1e-8, 1e8)
        loss_q = ((q1 - y_r) ** 2 + (q2 - y_r) ** 2).mean()
        loss_qc = 0.5 * ((qc - y_c) ** 2).mean()
        loss_vc = 0.5 * ((vc - (m2 - qc.detach() ** 2)) ** 2).mean()

        pi_act, logp = self.sample(obs)
        x_pi = torch.cat([obs, pi_act], -1)
        self.critics.requires_grad_(False)
        q_pi = torch.min(self.q1(x_pi), self.q2(x_pi)).squeeze(-1)
        cvar_pi = (
            self.qc(x_pi).squeeze(-1)
            + self.multiplier * F.softplus(self.vc(x_pi)).squeeze(-1).clamp(1e-8, 1e8).sqrt()
        )
        self.critics.requires_grad_(True)
        loss_pi = (alpha * logp - q_pi + kappa.detach() * cvar_pi).mean()
        loss_alpha = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        loss_kappa = (kappa * (self.threshold - cvar_pi.detach())).mean()

        total = loss_q + loss_qc + loss_vc + loss_pi + loss_alpha + loss_kappa
        total.backward()
        for optimizer in self.optimizers:
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            online = [p for net in self.critics for p in net.parameters()]
            target = [p for net in self.targets for p in net.parameters()]
            torch._foreach_lerp_(target, online, self.tau)
        return total.detach()
