"""examples/pendulum_wcsac.py (a TorchRL user's SAC loop with WCSACLoss) runs briefly."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest
import torch

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "pendulum_wcsac.py"


def load_example():
    spec = importlib.util.spec_from_file_location("pendulum_wcsac", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_cost_transform_marks_fast_steps():
    example = load_example()
    env = example.make_env(0)
    td = env.rollout(50)
    speed = td["next", "observation"][..., 2:3].abs()
    assert td["next", "cost"].dtype == torch.float32
    assert torch.equal(td["next", "cost"], (speed > 4.0).float())
    assert td["step_count"][0].item() == 0


def test_the_example_trains_for_a_few_hundred_frames():
    example = load_example()
    stats = example.main(frames=400, seed=0, init_random_frames=200)
    for key in ("alpha", "kappa", "cost_value", "cvar", "entropy"):
        assert math.isfinite(stats[key]), key
    assert stats["kappa"] > 0 and stats["cost_threshold"] == pytest.approx(20.0)
