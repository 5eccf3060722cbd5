"""examples/pendulum_wcsac.py (a TorchRL user's SAC loop with WCSACLoss) runs briefly."""

from __future__ import annotations

import importlib.util
import math
import re
import warnings
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


ITERATION = re.compile(
    r"iteration +(\d+)  frames +(\d+)  return +(-?\d+\.\d)  cost +(\d+\.\d)(  \(random actions\))?"
)


def test_the_example_trains_logging_each_episode_and_ends_with_a_verdict(capsys):
    example = load_example()
    with warnings.catch_warnings():
        warnings.simplefilter("error", FutureWarning)  # TorchRL's InitTracker warning
        stats = example.main(frames=800, seed=0, init_random_frames=400)
    for key in ("alpha", "kappa", "cost_value", "cvar", "entropy"):
        assert math.isfinite(stats[key]), key
    assert stats["kappa"] > 0 and stats["cost_threshold"] == pytest.approx(20.0)
    lines = capsys.readouterr().out.strip().splitlines()
    iterations = [ITERATION.fullmatch(line) for line in lines if line.startswith("iteration")]
    assert all(iterations) and len(iterations) == 4  # one 200-step episode per iteration
    for i, match in enumerate(iterations):
        assert int(match[1]) == i + 1 and int(match[2]) == 200 * (i + 1)
        assert float(match[3]) == pytest.approx(stats["returns"][i], abs=0.05)
        assert float(match[4]) == pytest.approx(stats["costs"][i], abs=0.05)
        assert bool(match[5]) == (i < 2)  # the first 400 frames act at random
    # Pendulum's reward is in [-16.3, 0] per step; a cost counts steps, at most 200
    assert all(-16.3 * 200 <= r <= 0 for r in stats["returns"])
    assert all(c == int(c) and 0 <= c <= 200 for c in stats["costs"])
    assert lines[-1] == stats["verdict"] == example.verdict(stats["returns"], 2, stats["costs"])
    assert lines[-1].startswith("verdict: ")
    assert re.fullmatch(
        r"verdict: (learned|did not learn) \(mean return of the last 1 episodes -?\d+\.\d, "
        r"best of 2 random-action episodes -?\d+\.\d\), (within|over) the cost limit "
        r"\(their mean cost \d+\.\d, d = 20\)",
        lines[-1],
    )


def test_the_verdict_compares_the_policy_s_last_episodes_with_the_random_ones():
    example = load_example()
    returns = [-1200.0, -800.0, -900.0, -700.0, -300.0, -200.0]  # 2 random, then 4
    assert example.verdict(returns, 2, [50, 60, 40, 30, 25, 10]) == (
        "verdict: learned (mean return of the last 1 episodes -200.0, best of 2 "
        "random-action episodes -800.0), within the cost limit (their mean cost 10.0, d = 20)"
    )
    returns = [-1200.0, -700.0, *[-900.0] * 6, -650.0, -750.0]  # 2 random, then 8
    assert example.verdict(returns, 2, [0] * 9 + [35]) == (
        "verdict: did not learn (mean return of the last 2 episodes -700.0, best of 2 "
        "random-action episodes -700.0), within the cost limit (their mean cost 17.5, d = 20)"
    )
    assert example.verdict(returns, 2, [0] * 8 + [30, 35]).endswith(
        "over the cost limit (their mean cost 32.5, d = 20)"
    )
    assert example.verdict(returns, 2).endswith("episodes -700.0)")  # SAC: no cost
    assert example.verdict([-1200.0], 1).startswith("verdict: no episode of both")
