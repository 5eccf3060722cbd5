"""The loss evaluates no critic whose values it does not read.

* the TD targets read the target reward critics at ``(s', a')`` and the target safety
  critic once, where its target bootstraps (at ``s_{t+m}`` with n-step targets: not also
  at ``(s', a')``), fused into the same batched products when the critics are fused;
* κ at start states reads the safety critic alone (not the reward critics; a fused
  mean-only safety critic with one of them, see below).

Counted in matrix-product FLOPs (``FlopCounterMode``), which are exact; that the values
themselves are unchanged is ``tests/test_loss_equivalence.py``'s (every preset's losses
and gradients equal the recorded ones).
"""

from __future__ import annotations

import pytest
import torch
from _loss_helpers import flat_parts
from _loss_reference import ACT_DIM, OBS_DIM, WIDTH, make_preset_batch
from torch.utils.flop_counter import FlopCounterMode
from torchrl.data import Bounded

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PAPER_OPTIONS

# matrix-product FLOPs per row: the actor OBS-W-W-2·ACT, each critic (OBS+ACT)-W-W-1
ACTOR = 2 * (OBS_DIM * WIDTH + WIDTH * WIDTH + WIDTH * 2 * ACT_DIM)
CRITIC = 2 * ((OBS_DIM + ACT_DIM) * WIDTH + WIDTH * WIDTH + WIDTH)


def _loss(variance: bool, fuse: bool, **options) -> WCSACLoss:
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=WIDTH)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=WIDTH) for _ in range(2)]
    safety = make_safety_critic(OBS_DIM, ACT_DIM, variance=variance, width=WIDTH)
    loss = WCSACLoss(
        actor,
        qvalues,
        safety,
        **flat_parts(
            risk_level=0.1 if variance else 1.0,
            cost_limit=1.5,
            max_episode_steps=12,
            fast_paths=fuse,
            **options,
        ),
    )
    loss.make_value_estimator(gamma=0.99)
    return loss


def _flops(fn, *args):
    with FlopCounterMode(display=False) as counter:
        out = fn(*args)
    return counter.get_total_flops(), out


@pytest.mark.parametrize("fuse", [True, False], ids=["fused", "modules"])
@pytest.mark.parametrize("variance", [True, False], ids=["wcsac", "sac_lag"])
@pytest.mark.parametrize("n_steps", [10, 1])
def test_targets_read_each_target_critic_once(fuse, variance, n_steps):
    loss = _loss(variance, fuse, cost_n_steps=n_steps)
    batch = make_preset_batch(loss)
    rows = batch.shape[0]
    safety_nets = 2 if variance else 1
    flops, targets = _flops(loss.compute_targets, batch)
    # a' ~ π(s') and (n-step) a ~ π(s_{t+m}); two reward critics and the safety critic
    # once (at s_{t+m} with n steps, at s' with one) — except that fused critics keep
    # their one product over every member at s' (another grouping rounds differently)
    draws = 2 if n_steps > 1 else 1
    kept = safety_nets if fuse and n_steps > 1 else 0
    assert flops == rows * (draws * ACTOR + (2 + safety_nets + kept) * CRITIC)
    assert torch.isfinite(targets["cost_target"]).all()


@pytest.mark.parametrize("fuse", [True, False], ids=["fused", "modules"])
@pytest.mark.parametrize("variance", [True, False], ids=["wcsac", "sac_lag"])
def test_start_state_signal_reads_the_safety_critic_alone(fuse, variance):
    loss = _loss(variance, fuse)
    batch = make_preset_batch(loss)
    states = batch["initial"]
    # the fused ensemble evaluates at least two members (one member alone is another
    # kernel, which rounds differently): a mean-only safety critic with a reward critic
    critics = 2 if variance or fuse else 1
    torch.manual_seed(7)
    flops, values = _flops(loss._policy_values, states)
    assert flops == batch.shape[0] * (ACTOR + critics * CRITIC)
    assert values.qvalue is None
    # the same safety values, bit for bit, as reading every critic at the same draw
    torch.manual_seed(7)
    action, _ = loss._sample_policy(states)
    with torch.no_grad():
        every = loss._critic_values(states, action, loss._detached_critics())
    assert every.qvalue is not None
    assert torch.equal(values.safety.mean, every.safety.mean)
    if variance:
        assert torch.equal(values.safety.variance, every.safety.variance)


def test_the_paper_options_read_no_start_states_and_no_nstep_state():
    loss = _loss(True, True, **PAPER_OPTIONS)
    batch = make_preset_batch(loss)
    flops, _ = _flops(loss.compute_targets, batch)
    assert flops == batch.shape[0] * (ACTOR + 4 * CRITIC)
    assert loss.cost_target.bootstrap_states(batch) is None
