"""``WCSACLoss``'s own defaults are the paper's WCSAC on a plain TorchRL batch, as
``SACLoss``'s are the published SAC: a user swapping one for the other needs none of the
kit's transforms."""

from __future__ import annotations

import pytest
import torch
from _loss_helpers import plain_batch
from torchrl.data import Bounded

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PAPER_OPTIONS, loss_parts

SPEC = Bounded(-1.0, 1.0, shape=(2,))


def _loss(kind: str = "gaussian") -> WCSACLoss:
    torch.manual_seed(0)
    return WCSACLoss(
        make_actor(4, SPEC), [make_qvalue(4, 2) for _ in range(2)],
        make_safety_critic(4, 2, kind=kind), risk_level=0.1, cost_limit=15.0, action_spec=SPEC,
    )  # fmt: skip


@pytest.mark.parametrize("kind", ["gaussian", "iqn"])
@pytest.mark.parametrize("cost_shape", ["float32 [B,1]", "float64 [B]"])
def test_the_defaults_train_on_a_plain_torchrl_batch(kind, cost_shape):
    loss = _loss(kind)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-3)
    before = {name: p.detach().clone() for name, p in loss.named_parameters()}
    for step in range(5):
        out = loss(plain_batch(32, cost_shape, seed=step))
        total = sum(v for k, v in out.items() if k.startswith("loss_"))
        assert torch.isfinite(total)
        optim.zero_grad()
        total.backward()
        optim.step()
    moved = {n for n, p in loss.named_parameters() if not torch.equal(p, before[n])}
    assert any(n.startswith("actor_network") for n in moved)
    assert any(n.startswith("safety_network") for n in moved)
    assert "constraint.kappa_raw" in moved


def test_the_defaults_are_the_papers_options():
    """κ on the mean Γ over the batch's states, one-step cost targets with the reward's γ,
    the critic alone, the gradient rule from softplus(0), β from 1 (SACLoss's)."""
    loss = _loss()
    paper = loss_parts(PAPER_OPTIONS)
    assert loss.head_options == paper["safety_head"]
    assert loss.signal_options == paper["signal"]
    assert (loss.kappa_states, loss.kappa_signal, loss.cost_n_steps) == ("replay", "critic", 1)
    assert float(loss.constraint.kappa) == pytest.approx(torch.log(torch.tensor(2.0)).item())
    assert float(loss.log_alpha.exp()) == pytest.approx(1.0)


def test_two_default_losses_share_no_part():
    first, second = _loss(), _loss()
    assert first.constraint is not second.constraint
    first.constraint.kappa_raw.data.fill_(3.0)
    assert float(second.constraint.kappa) == pytest.approx(torch.log(torch.tensor(2.0)).item())


def test_a_users_own_iqn_module_gets_the_iqn_defaults():
    """A safety critic the user wrapped in their own module is recognised as an IQN one by
    the quantile fractions it reads (as the head builder recognises it), so the default
    parts are the paper's for an IQN critic and the loss trains."""
    from tensordict.nn import TensorDictModule

    class Wrapped(torch.nn.Module):
        def __init__(self, inner):
            super().__init__()
            self.inner = inner

        def forward(self, *inputs):
            return self.inner(*inputs)

    kit = make_safety_critic(4, 2, kind="iqn")
    own = TensorDictModule(Wrapped(kit.module), in_keys=kit.in_keys, out_keys=kit.out_keys)
    torch.manual_seed(0)
    loss = WCSACLoss(
        make_actor(4, SPEC), [make_qvalue(4, 2) for _ in range(2)], own,
        risk_level=0.1, cost_limit=15.0, action_spec=SPEC,
    )  # fmt: skip
    assert loss.safety_critic_kind == "iqn"
    assert loss.head_options == loss_parts({**PAPER_OPTIONS, "safety_critic": "iqn"})["safety_head"]
    out = loss(plain_batch(16, "float32 [B,1]"))
    assert torch.isfinite(sum(v for k, v in out.items() if k.startswith("loss_")))
