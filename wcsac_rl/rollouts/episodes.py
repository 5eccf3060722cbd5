"""Test episodes: run a policy for whole episodes and record return, cost and length.

:func:`run_episodes` gives one :class:`EpisodeResult` per episode;
:func:`record_episodes` runs the very same episodes and also keeps chosen entries of
every step (e.g. observation, action and cost) as one TensorDict per episode.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

__all__ = [
    "EpisodeResult",
    "RecordedEpisode",
    "record_episodes",
    "run_episodes",
    "summarize_episodes",
]


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


@dataclass(frozen=True)
class RecordedEpisode:
    """One finished episode and the entries recorded at each of its steps.

    Attributes:
        result: the episode's :class:`EpisodeResult`.
        steps: a TensorDict of batch size ``[result.length]``: step ``t`` holds the
            recorded entries of the tensordict the env stepped (root entries as the
            policy saw and wrote them, ``("next", ...)`` entries as the env returned
            them).
    """

    result: EpisodeResult
    steps: TensorDictBase | None


def run_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None,
    num_episodes: int,
    *,
    deterministic: bool = True,
    max_steps: int = 100_000,
    on_episode: Callable[[EpisodeResult], None] | None = None,
) -> list[EpisodeResult]:
    """Run ``num_episodes`` whole episodes of ``policy`` in ``env``.

    With an unbatched env the episodes run one after the other. With a batch of
    ``n`` envs (e.g. ``make_env(name, num_workers=n, parallel=False)``) they run
    ``n`` at a time, side by side: each sub-env contributes its first episode of a
    round (results in sub-env order), and a round stops once every sub-env needed
    has finished one (or after ``max_steps``, which cuts an episode in both cases). Same episodes as ``n`` unbatched envs seeded like the
    sub-envs, for a fraction of the per-step overhead. (A policy evaluated on a
    batch may round differently from one evaluated on a single row, and the
    point-goal dynamics amplify such 1e-7 differences: individual episodes then
    differ while their statistics do not.)

    Args:
        env: a TorchRL env with batch size ``[]`` or ``[n]`` whose steps carry
            ``("next", "cost")``.
        policy: the actor; ``None`` samples uniform random actions.
        num_episodes: how many episodes.
        deterministic: act with the policy's mode/mean (the paper's test episodes)
            instead of sampling.
        max_steps: bound on one episode's length (normally the env truncates earlier;
            an episode still running after ``max_steps`` steps is cut there).
        on_episode: called after each episode (e.g. to advance a progress bar).

    Raises:
        ValueError: an env with more than one batch dimension.
    """
    return [
        episode.result
        for episode in _run(
            env, policy, num_episodes, deterministic, max_steps, on_episode, record=None
        )
    ]


def record_episodes(
    env: EnvBase,
    policy: Callable[[TensorDictBase], TensorDictBase] | None,
    num_episodes: int,
    keys: Sequence[NestedKey],
    *,
    deterministic: bool = True,
    max_steps: int = 100_000,
    on_episode: Callable[[EpisodeResult], None] | None = None,
) -> list[RecordedEpisode]:
    """:func:`run_episodes`, also keeping the entries ``keys`` of every step.

    The episodes (and their results) are the ones :func:`run_episodes` gives for the
    same env, policy and seeds: recording only copies entries, it draws no random
    numbers and changes no step.

    Args:
        keys: the entries to keep per step, e.g. ``["observation", "action",
            ("next", "cost")]``; each must be in every stepped tensordict.
        env, policy, num_episodes, deterministic, max_steps, on_episode: as in
            :func:`run_episodes`.

    Raises:
        ValueError: an env with more than one batch dimension.
        KeyError: a key the stepped tensordicts do not have.
    """
    return _run(env, policy, num_episodes, deterministic, max_steps, on_episode, list(keys))


def _run(
    env: EnvBase,
    policy,
    num_episodes: int,
    deterministic: bool,
    max_steps: int,
    on_episode: Callable[[EpisodeResult], None] | None,
    record: list[NestedKey] | None,
) -> list[RecordedEpisode]:
    """The episodes of :func:`run_episodes`; ``steps`` is ``None`` unless ``record``."""
    if len(env.batch_size) > 1:
        raise ValueError(
            f"run_episodes needs an unbatched env or one batch dimension, got {env.batch_size}"
        )
    exploration = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    results: list[RecordedEpisode] = []
    with torch.no_grad(), set_exploration_type(exploration):
        while len(results) < num_episodes:
            if env.batch_size == torch.Size([]):
                episodes = [_single_episode(env, policy, max_steps, record)]
            else:
                wanted = min(num_episodes - len(results), env.batch_size[0])
                episodes = _side_by_side_episodes(env, policy, max_steps, wanted, record)
            for episode in episodes:
                results.append(episode)
                if on_episode is not None:
                    on_episode(episode.result)
    return results


def _single_episode(
    env: EnvBase, policy, max_steps: int, record: list[NestedKey] | None
) -> RecordedEpisode:
    rollout = env.rollout(max_steps, policy, break_when_any_done=True)
    nxt = _on_cpu(rollout.get("next"))
    goal = nxt.get("goal_reached", None)
    failure = nxt.get("numerical_failure", None)
    result = EpisodeResult(
        # summed in float64, like the side-by-side episodes (the same numbers on any CPU)
        ret=float(nxt.get("reward").double().sum()),
        cost=float(nxt.get("cost").double().sum()),
        length=int(nxt.shape[-1]),
        goal_reached=0 if goal is None else int(goal.sum()),
        numerical_failure=False if failure is None else bool(failure.any()),
    )
    steps = None if record is None else rollout.select(*record, strict=True)
    return RecordedEpisode(result, steps)


def _side_by_side_episodes(
    env: EnvBase, policy, max_steps: int, wanted: int, record: list[NestedKey] | None
) -> list[RecordedEpisode]:
    """The first episode of sub-envs ``0 .. wanted-1`` of a batched env, stepped together.

    With ``record``, those entries of each batched step are kept (on the device the
    env returns them on: the learner's, where the policy and safety critic read them);
    a sub-env's episode is the first ``length`` of them (it runs from the first step on
    and only waits once it has finished). The episodes' totals are kept on the CPU.
    """
    n = env.batch_size[0]
    ret = torch.zeros(n, dtype=torch.float64)
    cost = torch.zeros(n, dtype=torch.float64)
    goals = torch.zeros(n, dtype=torch.int64)
    failed = torch.zeros(n, dtype=torch.bool)
    length = torch.zeros(n, dtype=torch.int64)
    running = torch.zeros(n, dtype=torch.bool)
    running[:wanted] = True
    partial = _steps_partially(env)
    recorded: list[TensorDictBase] = []
    td = env.reset()
    for _ in range(max_steps):
        td = env.rand_action(td) if policy is None else policy(td)
        if partial and not running.all():  # finished sub-envs wait for the others
            td.set("_step", running.unsqueeze(-1).to(td.device or "cpu", copy=True))
        td, next_td = env.step_and_maybe_reset(td)
        if record is not None:
            recorded.append(td.select(*record, strict=True).clone())
        nxt = _on_cpu(td.get("next"))
        active = running.clone()
        ret += torch.where(active, nxt.get("reward").reshape(n).double(), 0.0)
        cost += torch.where(active, nxt.get("cost").reshape(n).double(), 0.0)
        goal = nxt.get("goal_reached", None)
        if goal is not None:
            goals += (goal.reshape(n) & active).long()
        failure = nxt.get("numerical_failure", None)
        if failure is not None:
            failed |= failure.reshape(n) & active
        length += active.long()
        running &= ~nxt.get("done").reshape(n)
        if not running.any():
            break
        td = next_td
    # an episode still running after max_steps ends there, as a rollout would end it
    steps = torch.stack(recorded, dim=1) if record is not None else None  # [n, T]
    return [
        RecordedEpisode(
            EpisodeResult(
                ret=float(ret[i]),
                cost=float(cost[i]),
                length=int(length[i]),
                goal_reached=int(goals[i]),
                numerical_failure=bool(failed[i]),
            ),
            None if steps is None else steps[i, : int(length[i])].clone(),
        )
        for i in range(wanted)
    ]


STEP_ENTRIES = ("reward", "cost", "done", "goal_reached", "numerical_failure")
"""The entries of a step's ``"next"`` the episodes' totals read."""


def _on_cpu(nxt: TensorDictBase) -> TensorDictBase:
    """A step's :data:`STEP_ENTRIES`, on the CPU (an env that casts its output to the
    learner, e.g. a GPU, returns them there; the totals are kept on the CPU)."""
    if nxt.device is not None and nxt.device.type == "cpu":
        return nxt  # (the envs' own output: nothing to move)
    return nxt.select(*STEP_ENTRIES, strict=False).to("cpu")


def _steps_partially(env: EnvBase) -> bool:
    """Whether ``env`` steps only the sub-envs a ``"_step"`` mask selects."""
    from torchrl.envs import TransformedEnv

    from wcsac_rl.envs.batched_gym import BatchedGymEnv

    base = env.base_env if isinstance(env, TransformedEnv) else env
    return isinstance(base, BatchedGymEnv)


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
