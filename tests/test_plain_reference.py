"""benchmarks/plain_wcsac.py is the reference of one WCSAC update: ``PlainWCSAC.losses``
gives ``WCSACLoss``'s six loss terms, and each term the same gradient in every
parameter, with the options its docstring lists (``PAPER_OPTIONS`` and
``variance_loss="mse"``), at α = 0.5 and α = 1, through the loss's fast paths
(fused critics, direct sampling) and through TorchRL's modules.

Both are given the same weights (the plain networks' copied into the loss's
functional parameters, targets included) and the same noise (torch seeded right
before each; both draw ε for ``a' ~ π(s')`` first, then for ``a ~ π(s)``, each
``[B, |A|]``). The targets differ from the online critics, and β and κ from their
initial values, so a loss that reads the wrong ones fails.

Every term is compared. The per-step threshold is computed from γ = 0.99 on both
sides (``WCSACLoss`` keeps the γ it was given, not its estimator's float32 copy
0.99000001, which would move the threshold by 1.4·10⁻⁶: ∂threshold/∂γ ≈ 150 at
d = 15, T = 1000); the loss stores it in float32. TorchRL's tanh, clamped to ±(1 − 10⁻⁶), is checked not to bind on these draws.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from _loss_helpers import ACT_DIM, LOSS_KEYS, OBS_DIM, make_batch, make_loss
from _tolerance import assert_close_f32
from torch import nn
from torch.nn import functional as F

from wcsac_rl.objectives import per_step_cost_threshold
from wcsac_rl.objectives.risk import gaussian_cvar_multiplier

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from plain_wcsac import PlainWCSAC, batch_inputs

WIDTH = 32
BATCH = 16
SEED = 7

# Tolerances (tests/_tolerance.py: ops × 2⁻²³ × magnitude). A loss is a batch mean of
# 16 terms built from width-32 MLP outputs (each a sum of ≤ 32 products per layer), so
# each side rounds ~32 times at the scale of those terms: ops = 32. The magnitude is
# 1 + |loss|, at least the largest summand of every loss here, also of those that are
# differences (|β log π| ≤ 1.3, κ·threshold ≤ 1.8, |log β|(|log π| + |A|) ≤ 3.3). A
# gradient entry sums 16 per-row terms through the same layers: ops = 32 at the scale
# of the tensor's largest entry. Observed (here, and with ATEN_CPU_CAPABILITY=default,
# avx2, avx512 and MKL_ENABLE_INSTRUCTIONS=SSE4_2): most values agree exactly, the
# largest differences are 0.55 × 2⁻²³ × (1 + |loss|) and 2.8 × 2⁻²³ × the largest
# gradient entry, ≥ 11× under these tolerances. A real difference (a missing ½, a
# dropped min or mask, a wrong γ power) moves a value by a fraction of itself, 10³–10⁵
# times more; changing one weight by 10⁻³ already fails.
LOSS_OPS = 32
GRADIENT_OPS = 32


def _pairs(plain: PlainWCSAC, loss, *, target: bool = False) -> list[tuple]:
    """``(name, plain tensor, loss tensor, twin index or None)`` for every weight and
    bias of the critics (``target``: of the target critics), else also of the actor,
    log β and κ's raw parameter."""
    if target:
        q, s, (q1, q2, qc, vc) = (
            loss.target_qvalue_network_params,
            loss.target_safety_network_params,
            plain.targets,
        )
    else:
        q, s, (q1, q2, qc, vc) = (
            loss.qvalue_network_params,
            loss.safety_network_params,
            plain.critics,
        )
    networks = [
        ("q1", q1, q, ("module",), 0),  # the twin critics are stacked on a leading dim
        ("q2", q2, q, ("module",), 1),
        ("qc", qc, s, ("module", "mean_net"), None),
        ("vc", vc, s, ("module", "variance_net"), None),
    ]
    pairs = []
    if not target:
        actor = ("actor", plain.actor, loss.actor_network_params, ("module", "0") * 2, None)
        networks.insert(0, actor)
        pairs += [
            ("log_alpha", plain.log_alpha, loss.log_alpha, None),
            ("kappa_raw", plain.kappa_raw, loss.kappa_raw, None),
        ]
    for name, net, params, prefix, index in networks:
        for layer in ("0", "2", "4"):  # the Linear layers of Linear, ReLU, Linear, ReLU, Linear
            for kind in ("weight", "bias"):
                param = params.get((*prefix, layer, kind))
                pairs.append(
                    (f"{name}.{layer}.{kind}", getattr(net[int(layer)], kind), param, index)
                )
    return pairs


def _twins_at_min(plain: PlainWCSAC, inputs) -> list[tuple[nn.Module, nn.Module, torch.Tensor]]:
    """``(first twin, second twin, input)`` where the losses take the twins' minimum:
    the targets at ``(s', a')``, the online critics at ``(s, a ~ π)``, with the draws
    the losses make after ``SEED``. Asserts that TorchRL's tanh clamp does not bind
    on those draws."""
    obs, next_obs = inputs[0], inputs[4]
    torch.manual_seed(SEED)
    with torch.no_grad():
        next_act, act = plain.sample(next_obs)[0], plain.sample(obs)[0]
    assert torch.cat([next_act, act]).abs().max() < 1 - 1e-6
    return [
        (plain.targets[0], plain.targets[1], torch.cat([next_obs, next_act], -1)),
        (plain.q1, plain.q2, torch.cat([obs, act], -1)),
    ]


def _plain_and_loss(risk_level: float, fast: bool, inputs) -> tuple[PlainWCSAC, object]:
    """A ``PlainWCSAC`` and the ``WCSACLoss`` it is the reference of, with its weights."""
    torch.manual_seed(0)
    plain = PlainWCSAC(OBS_DIM, ACT_DIM, width=WIDTH, risk_level=risk_level)
    with torch.no_grad():  # targets ≠ online critics, β and κ away from their initial values
        for p in plain.targets.parameters():
            p.add_(0.1 * torch.randn_like(p))
        plain.log_alpha.fill_(-0.7)
        plain.kappa_raw.fill_(0.8)
        # random twins differ mostly by an offset, so one is the minimum nearly
        # everywhere: shift the second by the median difference, so each is on half
        for first, second, x in _twins_at_min(plain, inputs):
            second[4].bias += torch.quantile(first(x) - second(x), 0.5)
    loss = make_loss(risk_level=risk_level, variance_loss="mse", fast_paths=fast)
    with torch.no_grad():
        for target in (False, True):
            for name, src, dst, index in _pairs(plain, loss, target=target):
                dst = dst.data if index is None else dst.data[index]
                assert dst.shape == src.shape, name
                dst.copy_(src)
    return plain, loss


def _grads(pairs, side: int) -> dict[str, torch.Tensor]:
    """Each parameter's gradient (zeros where none) from ``pairs``' plain (1) or loss (2) side."""
    out = {}
    for name, *tensors, index in pairs:
        tensor = tensors[side - 1]
        grad = torch.zeros_like(tensor) if tensor.grad is None else tensor.grad
        out[name] = grad if side == 1 or index is None else grad[index]
    return out


@pytest.mark.parametrize("fast", [True, False], ids=["fused+direct", "modules"])
@pytest.mark.parametrize("risk_level", [0.5, 1.0])
def test_plain_reference_equals_wcsac_loss(risk_level, fast):
    batch = make_batch(BATCH)
    inputs = batch_inputs(batch)
    plain, loss = _plain_and_loss(risk_level, fast, inputs)
    # every branch is taken: terminal and other steps, costs 0 and 1, either twin the minimum
    assert 0 < inputs[-1].sum() < BATCH and 0 < inputs[3].sum() < BATCH
    with torch.no_grad():
        for first, second, x in _twins_at_min(plain, inputs):
            assert 4 <= (first(x) < second(x)).sum() <= BATCH - 4

    torch.manual_seed(SEED)
    plain_out = plain.losses(*inputs)
    torch.manual_seed(SEED)
    loss_out = loss(batch.clone())
    pairs = _pairs(plain, loss)
    for key in LOSS_KEYS:
        expected = loss_out[key].detach()
        assert_close_f32(
            plain_out[key].detach(), expected, ops=LOSS_OPS, magnitude=1 + expected.abs(), msg=key
        )
        plain.zero_grad(set_to_none=True)
        loss.zero_grad(set_to_none=True)
        plain_out[key].backward(retain_graph=True)
        loss_out[key].backward(retain_graph=True)
        got, want = _grads(pairs, 1), _grads(pairs, 2)
        for name in want:
            # a parameter the term does not reach has a zero gradient on both sides
            assert_close_f32(got[name], want[name], ops=GRADIENT_OPS, msg=f"{key}: {name}")


@pytest.mark.parametrize("risk_level", [0.5, 1.0])
def test_plain_reference_starts_as_wcsac_loss(risk_level):
    """Initial β, κ, target entropy, CVaR multiplier, γ and threshold, and the options."""
    plain = PlainWCSAC(OBS_DIM, ACT_DIM, width=WIDTH, risk_level=risk_level)
    loss = make_loss(risk_level=risk_level, variance_loss="mse")
    assert plain.log_alpha.item() == loss.log_alpha.item() == 0.0  # β = 1
    assert F.softplus(plain.kappa_raw).item() == pytest.approx(loss.kappa.item(), rel=1e-7)
    assert plain.target_entropy == loss.target_entropy.item() == -ACT_DIM
    assert plain.multiplier == gaussian_cvar_multiplier(risk_level) == loss.cvar_multiplier
    assert (plain.multiplier == 0.0) == (risk_level == 1.0)
    assert plain.gamma == loss.cost_gamma == 0.99  # the γ given, not a float32 copy
    assert plain.threshold == per_step_cost_threshold(15.0, 0.99, 1000)
    # the loss keeps the same threshold, rounded to its float32 buffer
    assert loss.cost_threshold.item() == torch.tensor(plain.threshold).item()
    assert (loss.variance_loss, loss.variance_target_kind) == ("mse", "moment")
    assert (loss.cost_n_steps, loss.nonnegative_cost) == (1, False)
    assert (loss.kappa_states, loss.kappa_actions, loss.kappa_statistic) == (
        "replay",
        "policy",
        "mean",
    )
    assert (loss.kappa_signal, loss.damp_scale, loss.kappa_parametrization) == (
        "critic",
        0.0,
        "softplus",
    )
    assert (loss.num_qvalue_nets, loss.loss_function) == (2, "l2")
    for online, target in zip(plain.critics.parameters(), plain.targets.parameters()):
        assert torch.equal(online, target)


def test_plain_update_steps_every_group_and_averages_the_targets():
    """``update`` = the six losses, one Adam step of every parameter, Polyak targets."""
    inputs = batch_inputs(make_batch(BATCH))
    plain, _ = _plain_and_loss(0.5, True, inputs)
    before = {name: p.detach().clone() for name, p in plain.named_parameters()}
    targets = [p.detach().clone() for p in plain.targets.parameters()]
    torch.manual_seed(SEED)
    expected_total = sum(plain.losses(*inputs).values()).detach()
    plain.zero_grad(set_to_none=True)
    torch.manual_seed(SEED)
    total = plain.update(*inputs)
    assert total == expected_total
    for name, p in plain.named_parameters():
        if not p.requires_grad:  # the targets
            continue
        assert p.grad is None
        # Adam's first step moves every entry with a nonzero gradient by ≈ lr
        assert not torch.equal(p, before[name]), name
    for old, new, online in zip(targets, plain.targets.parameters(), plain.critics.parameters()):
        assert_close_f32(new, torch.lerp(old, online, plain.tau), ops=2)
