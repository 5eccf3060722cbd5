"""Small shared builders for the loss tests (not collected: no ``test_`` prefix)."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from _tolerance import assert_close_f32
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded

from wcsac_rl import WCSACLoss
from wcsac_rl.modules import make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import PAPER_OPTIONS, loss_parts
from wcsac_rl.options import IQNOptions, SafetyOptions

OBS_DIM = 5
ACT_DIM = 2
# the loss terms of a WCSACLoss with a Gaussian safety critic (variance head included)
LOSS_KEYS = (
    "loss_actor",
    "loss_qvalue",
    "loss_alpha",
    "loss_cost_value",
    "loss_cost_variance",
    "loss_kappa",
)

# Tolerances of assert_same_losses_and_gradients (see _tolerance.py): a loss output is
# a batch mean of terms made by width-32 MLPs, so its roundings are those of 32-term
# sums; a gradient entry sums the batch's per-sample terms through the same layers.
OUTPUT_OPS = 32
GRADIENT_OPS = 32


def make_batch(
    batch: int = 16,
    *,
    terminated_every: int = 4,
    seed: int = 0,
    cost_shape_1: bool = True,
    initial: bool = False,
):
    """A replay batch with random observations, binary costs and some terminal steps
    (and, with ``initial``, a start state per row under ``"initial"``)."""
    g = torch.Generator().manual_seed(seed)
    cost = torch.bernoulli(torch.full((batch, 1), 0.3), generator=g)
    terminated = torch.zeros(batch, 1, dtype=torch.bool)
    terminated[::terminated_every] = True
    td = TensorDict(
        {
            "observation": torch.randn(batch, OBS_DIM, generator=g),
            "action": torch.rand(batch, ACT_DIM, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(batch, OBS_DIM, generator=g),
                "reward": torch.randn(batch, 1, generator=g),
                "cost": cost if cost_shape_1 else cost.squeeze(-1),
                "done": terminated.clone(),
                "terminated": terminated,
            },
        },
        [batch],
    )
    if initial:
        td["initial"] = TensorDict(
            {"observation": torch.randn(batch, OBS_DIM, generator=g) + 1.0}, [batch]
        )
    return td


GAUSSIAN_HEAD = ("variance_loss", "variance_target")
"""The Gaussian head's options (an IQN critic has no variance head: they stay at the schema's)."""


def paper_options(kind: str = "gaussian") -> dict:
    """``PAPER_OPTIONS`` for a safety critic of ``kind`` (an IQN critic has no variance head)."""
    return {k: v for k, v in PAPER_OPTIONS.items() if kind == "gaussian" or k not in GAUSSIAN_HEAD}


IQN_OPTIONS = tuple(IQNOptions.__dataclass_fields__)
RECIPE_KEYS = (*SafetyOptions.__dataclass_fields__, *IQN_OPTIONS)


def recipe_kwargs(
    kind: str = "gaussian", *, paper: bool = True, base: Mapping | None = None, **kwargs
) -> dict:
    """``WCSACLoss``'s keywords for the paper's recipe (:func:`paper_options`; ``paper=False``:
    SafetyOptions' defaults; ``base``: that recipe, e.g. ``KIT_OPTIONS``) changed by the
    flat options among ``kwargs`` (``kappa_init=...``, ``num_quantiles=...``: a recipe, as
    the config writes it, through ``loss_parts``); the loss's own keywords
    (``risk_level``, ``cost_limit``, a part given as an object) pass as they are."""
    if base is None:
        base = paper_options(kind) if paper else {}
    recipe = {**base, "safety_critic": kind}
    iqn = {}
    loss_kwargs = {}
    for key, value in kwargs.items():
        if key in IQN_OPTIONS:
            iqn[key] = value
        elif key in RECIPE_KEYS and key != "risk_level":
            recipe[key] = value
        else:
            loss_kwargs[key] = value
    if iqn:
        recipe["iqn"] = iqn
    return {**loss_parts(recipe), **loss_kwargs}


STUDY_OPTIONS = {
    "variance_loss": "glm",
    "variance_target": "td",
    "cost_gamma": 1.0,
    "cost_n_steps": 10,
    "nonnegative_cost": True,
    "kappa_states": "initial",
    "kappa_statistic": "tail",
}
"""The StaticEnv study's safety critic and κ reads (docs/defaults.md), which the kit's
recipes set over SafetyOptions' (the paper's) defaults: n-step entries, start states,
the GLM variance head. The tests that exercise those paths build on them."""


def flat_parts(kind: str = "gaussian", **kwargs) -> dict:
    """``WCSACLoss``'s keywords for flat options over :data:`STUDY_OPTIONS` (the loss's
    own keywords pass as they are) for a safety critic of ``kind``: :func:`recipe_kwargs`
    on the study's reads."""
    return recipe_kwargs(kind, base=STUDY_OPTIONS, **kwargs)


def make_loss(
    *, variance: bool = True, width: int = 32, seed: int = 0, kind: str = "gaussian", **kwargs
) -> WCSACLoss:
    """A small WCSACLoss; ``kind="iqn"`` gives it an implicit-quantile safety critic. The
    paper's loss unless a test asks otherwise (flat options: :func:`recipe_kwargs`)."""
    torch.manual_seed(seed)
    actor = make_actor(OBS_DIM, Bounded(-1.0, 1.0, shape=(ACT_DIM,)), width=width)
    qvalues = [make_qvalue(OBS_DIM, ACT_DIM, width=width) for _ in range(2)]
    safety = make_safety_critic(OBS_DIM, ACT_DIM, kind=kind, variance=variance, width=width)
    kwargs.setdefault("risk_level", 0.5 if variance else 1.0)
    return WCSACLoss(actor, qvalues, safety, **recipe_kwargs(kind, **kwargs))


def assert_same_losses_and_gradients(first: WCSACLoss, second: WCSACLoss, batch) -> None:
    """Both losses give the same outputs and parameter gradients on ``batch`` (same seed)."""
    outputs = []
    for loss in (first, second):
        torch.manual_seed(5)
        out = loss(batch.clone())
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        outputs.append((out, {n: p.grad.clone() for n, p in loss.named_parameters()}))
    (out_a, grad_a), (out_b, grad_b) = outputs
    assert out_a.keys() == out_b.keys()
    for key in out_b.keys():
        assert_close_f32(out_a[key], out_b[key], ops=OUTPUT_OPS, msg=str(key))
    assert grad_a.keys() == grad_b.keys()
    for name in grad_b:
        assert_close_f32(grad_a[name], grad_b[name], ops=GRADIENT_OPS, msg=name)


class LinearQuantiles(nn.Module):
    """Z(s, a, τ) = obs[0] + obs[1]·τ: an IQN 'critic' whose quantiles the batch sets."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.ones(()))

    def forward(self, observation, action, quantile_fractions):
        return self.scale * (observation[..., :1] + observation[..., 1:2] * quantile_fractions)


def linear_quantile_critic() -> TensorDictModule:
    """:class:`LinearQuantiles` reading (observation, action, quantile_fractions)."""
    return TensorDictModule(
        LinearQuantiles(),
        in_keys=["observation", "action", "quantile_fractions"],
        out_keys=["cost_quantiles"],
    )


def plain_batch(n: int, cost_shape: str = "float32 [B,1]", seed: int = 0) -> TensorDict:
    """What a TorchRL collector and replay buffer hand over: nothing of the kit's."""
    g = torch.Generator().manual_seed(seed)
    cost = torch.bernoulli(torch.full((n, 1), 0.2), generator=g)
    if cost_shape == "float64 [B]":  # TorchRL's SafetyGymnasiumEnv
        cost = cost.squeeze(-1).double()
    return TensorDict(
        {
            "observation": torch.randn(n, 4, generator=g),
            "action": torch.rand(n, 2, generator=g) * 2 - 1,
            "next": {
                "observation": torch.randn(n, 4, generator=g),
                "reward": torch.randn(n, 1, generator=g),
                "cost": cost,
                "done": torch.zeros(n, 1, dtype=torch.bool),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        [n],
    )
