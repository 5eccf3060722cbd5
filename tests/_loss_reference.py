"""Fixed-seed losses and gradients of each preset, to hold a restructured loss to the
numbers of the code before it (not collected: no ``test_`` prefix).

``python tests/_loss_reference.py`` writes ``tests/data/loss_reference.pt``; it was
run once on the commit before the loss was split into parts (b61cb3e), and
``tests/test_loss_equivalence.py`` compares today's loss with it.
"""

from __future__ import annotations

from pathlib import Path

import torch
from _loss_helpers import STUDY_OPTIONS
from tensordict import TensorDict
from torchrl.data import Bounded

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PAPER_OPTIONS, NStepCost, StartStateBuffer, loss_parts

REFERENCE = Path(__file__).parent / "data" / "loss_reference.pt"
OBS_DIM, ACT_DIM, WIDTH = 5, 2, 32

# The defaults when the reference was recorded (b61cb3e), where they have changed since:
# the StaticEnv study's reads (SafetyOptions' defaults then; the paper's are now)
RECORDED_DEFAULTS = {**STUDY_OPTIONS, "kappa_signal": "critic", "kappa_rule": "gradient"}
# name -> (safety-critic kind, variance head, loss options): the presets of conf/algo
PRESETS = {
    "wcsac": ("gaussian", True, {"risk_level": 0.1, **RECORDED_DEFAULTS}),
    "wcsac_paper": ("gaussian", True, {"risk_level": 0.1, **PAPER_OPTIONS}),
    # (an IQN critic has no variance head: loss_parts leaves those options out for it)
    "wcsac_iqn": ("iqn", True, {"risk_level": 0.1, **RECORDED_DEFAULTS}),
    "sac_lag": ("gaussian", False, {"risk_level": 1.0, **RECORDED_DEFAULTS}),
    "sac_lag_paper": ("gaussian", False, {"risk_level": 1.0, **PAPER_OPTIONS}),
}


def make_preset_loss(name: str) -> WCSACLoss:
    kind, variance, options = PRESETS[name]
    torch.manual_seed(0)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=WIDTH)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=WIDTH) for _ in range(2)]
    safety = make_safety_critic(OBS_DIM, ACT_DIM, kind=kind, variance=variance, width=WIDTH)
    options = dict(options)
    parts = loss_parts({**options, "safety_critic": kind})  # (and alpha_init: SACLoss's 1)
    risk_level = options["risk_level"]
    loss = WCSACLoss(
        actor, qvalues, safety, risk_level=risk_level, cost_limit=1.5, max_episode_steps=12, **parts
    )
    loss.make_value_estimator(gamma=0.99)
    return loss


def episode_flags() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``terminated``, ``done`` (``[2, 12, 1]``) and ``step_count`` (``[2, 12]``) of two
    envs' 12 steps: env 0's episode terminates at step 7 and a second one starts, both
    are cut at step 11."""
    terminated = torch.zeros(2, 12, 1, dtype=torch.bool)
    terminated[0, 7] = True
    done = terminated.clone()
    done[:, -1] = True
    step = torch.arange(12).expand(2, 12).clone()
    step[0, 8:] = torch.arange(4)
    return terminated, done, step


def make_preset_batch(loss: WCSACLoss) -> TensorDict:
    """Two envs' 12-step episodes (costs, a terminal step), with the n-step entries and
    start states the loss's options read."""
    g = torch.Generator().manual_seed(1)
    shape = (2, 12)
    terminated, done, step = episode_flags()
    traj = TensorDict(
        {
            "observation": torch.randn(*shape, OBS_DIM, generator=g),
            "action": torch.rand(*shape, ACT_DIM, generator=g) * 2 - 1,
            "step_count": step.unsqueeze(-1),
            "next": {
                "observation": torch.randn(*shape, OBS_DIM, generator=g),
                "reward": torch.randn(*shape, 1, generator=g),
                "cost": torch.bernoulli(torch.full((*shape, 1), 0.3), generator=g),
                "done": done,
                "terminated": terminated,
            },
        },
        list(shape),
    )
    if loss.cost_n_steps > 1:
        traj = NStepCost(loss.cost_n_steps, loss.cost_gamma)(traj)
    batch = traj.reshape(-1)
    if loss.kappa_states == "initial":
        starts = StartStateBuffer.for_loss(loss)
        starts.add_starts(traj)
        torch.manual_seed(3)
        batch = starts.attach(batch)
    return batch


def preset_outputs(name: str) -> dict[str, torch.Tensor]:
    """``out/<key>`` for every loss output and ``grad/<parameter>`` after one backward."""
    loss = make_preset_loss(name)
    return outputs_and_gradients(loss, make_preset_batch(loss))


def outputs_and_gradients(loss, batch) -> dict[str, torch.Tensor]:
    """``out/<key>`` for every output of ``loss(batch)`` and ``grad/<parameter>`` after
    one backward of their sum (the loss's own draws seeded)."""
    torch.manual_seed(5)
    out = loss(batch)
    sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    record = {f"out/{k}": v.detach().clone() for k, v in out.items()}
    for param_name, param in loss.named_parameters():
        if param.grad is not None:
            record[f"grad/{param_name}"] = param.grad.clone()
    return record


if __name__ == "__main__":
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    torch.save({name: preset_outputs(name) for name in PRESETS}, REFERENCE)
    print(f"wrote {REFERENCE}")
