"""Test episodes: run a policy for whole episodes and record return, cost and length."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = ["EpisodeResult", "run_episodes", "summarize_episodes"]


@dataclass(frozen=True)
class EpisodeResult:
    """One finished episode. ``ret`` and ``cost`` are undiscounted sums."""

    ret: float
    cost: float
    length: int
    goal_reached: int  # goals reached during the episode (0 when the env does not say)
    numerical_failure: bool

    def as_dict(self) -> dict:
        return asdict(self)


def run_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None,
    num_episodes: int,
    *,
    deterministic: bool = True,
    max_steps: int = 100_000,
    on_episode: Callable[[EpisodeResult], None] | None = None,
) -> list[EpisodeResult]:
    """Run ``num_episodes`` whole episodes of ``policy`` in an unbatched ``env``.

    Args:
        env: a TorchRL env with batch size ``[]`` whose steps carry ``("next", "cost")``.
        policy: the actor; ``None`` samples uniform random actions.
        num_episodes: how many episodes.
        deterministic: act with the policy's mode/mean (the paper's test episodes)
            instead of sampling.
        max_steps: safety bound on one episode's length (the env truncates earlier).
        on_episode: called after each episode (e.g. to advance a progress bar).
    """
    if env.batch_size != torch.Size([]):
        raise ValueError(f"run_episodes needs an unbatched env, got batch size {env.batch_size}")
    exploration = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    results = []
    with torch.no_grad(), set_exploration_type(exploration):
        for _ in range(num_episodes):
            td = env.rollout(max_steps, policy, break_when_any_done=True)
            nxt = td.get("next")
            goal = nxt.get("goal_reached", None)
            failure = nxt.get("numerical_failure", None)
            result = EpisodeResult(
                ret=float(nxt.get("reward").sum()),
                cost=float(nxt.get("cost").sum()),
                length=int(td.shape[-1]),
                goal_reached=0 if goal is None else int(goal.sum()),
                numerical_failure=False if failure is None else bool(failure.any()),
            )
            results.append(result)
            if on_episode is not None:
                on_episode(result)
    return results


def summarize_episodes(results: list[EpisodeResult]) -> dict[str, float]:
    """Means of return, cost and length over episodes (NaN when there are none)."""
    if not results:
        nan = float("nan")
        return {"episode_return": nan, "episode_cost": nan, "episode_length": nan}
    n = len(results)
    return {
        "episode_return": sum(r.ret for r in results) / n,
        "episode_cost": sum(r.cost for r in results) / n,
        "episode_length": sum(r.length for r in results) / n,
    }
