"""Final evaluation of runs: N deterministic test episodes → ``evaluation.csv`` + ``evaluation.json``.

:func:`evaluate_run` evaluates a run's last checkpoint, :func:`evaluate_random_policy`
the uniform random policy without a run; the files' columns and fields, and when an
existing evaluation is skipped or *stale* (:func:`stale_evaluation`: its recorded
checkpoint SHA-256 no longer matches): docs/reproduce.md. A run evaluated before its
``total_frames``: :func:`unfinished_training`.

**Seeds.** The test env of a run trained with seed ``k`` is seeded with
``k + seed_offset`` (default :data:`DEFAULT_SEED_OFFSET` = 2 000 003, apart from the
training envs, seeded ``k``, and the per-epoch test episodes, ``k + 1 000 003``), and
torch is seeded with the same number (the random policy draws its actions from
torch), so an evaluation is reproducible and different seeds see different start
states. The episodes run side by side, up to ten at a time, in one in-process batch
of test envs (sub-env ``i`` seeded ``k + seed_offset + i``): episode ``j`` is the
first episode of sub-env ``j mod 10`` in round ``j // 10``.
"""

from __future__ import annotations

import csv
import datetime as _dt
import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from wcsac_rl.evaluation.defaults import DEFAULT_EPISODES, DEFAULT_SEED_OFFSET
from wcsac_rl.evaluation.metrics import table1_metrics
from wcsac_rl.evaluation.outcomes import outcome_counts
from wcsac_rl.evaluation.runs import EVALUATION_CSV, EVALUATION_JSON, env_has_layout
from wcsac_rl.rollouts.episodes import EpisodeResult, run_episodes
from wcsac_rl.training.config import ConfigError
from wcsac_rl.training.registry import find_algorithm
from wcsac_rl.training.restore import RestoredRun
from wcsac_rl.training.safe_load import load_json, load_yaml

__all__ = [
    "CSV_COLUMNS",
    "DEFAULT_EPISODES",
    "DEFAULT_SEED_OFFSET",
    "Evaluation",
    "EvaluationExistsError",
    "check_env_code_allowed",
    "check_random_policy",
    "check_writable",
    "evaluate_random_policy",
    "evaluate_run",
    "load_policy",
    "read_evaluation",
    "stale_evaluation",
    "summarize",
    "unfinished_training",
    "write_evaluation",
]

CSV_COLUMNS = ("episode", "return", "cost", "length", "goals", "numerical_failure")
MAX_EPISODE_VALUE = 1e150
"""The largest magnitude of an ``evaluation.csv`` cell read: an episode's cost or return
sums float32 steps (each below 3.4e38) over at most millions of steps, far below it; a
larger value is no episode the evaluator wrote, and its sums and squares over a report's
episodes would overflow to infinity."""


class EvaluationExistsError(ConfigError):
    """The directory already holds an evaluation and ``force`` was not given."""


@dataclass
class Evaluation:
    """One directory's test episodes and what they were run with.

    Attributes:
        directory: where ``evaluation.csv`` / ``evaluation.json`` live.
        meta: ``label``, ``algo``, ``env``, ``seed`` (training seed), ``cost_limit``,
            ``trained_frames``, ``env_seed``, ``max_episode_steps``, ``policy``, ...
        episodes: the per-episode results.
        summary: :func:`summarize` of ``episodes`` (``metrics`` and extras).
        total_frames: the frames the run's config trains for (``total_frames``), where
            :func:`evaluate_run` evaluated it (``None``: the random policy, or read back
            from the files, which do not record it); see :func:`unfinished_training`.
    """

    directory: Path
    meta: dict[str, Any]
    episodes: list[EpisodeResult]
    summary: dict[str, Any] = field(default_factory=dict)
    total_frames: int | None = None

    @property
    def label(self) -> str:
        return str(self.meta["label"])

    @property
    def costs(self) -> list[float]:
        return [e.cost for e in self.episodes]

    @property
    def returns(self) -> list[float]:
        return [e.ret for e in self.episodes]


def summarize(
    episodes: list[EpisodeResult], cost_limit: float, env: str | None = None
) -> dict[str, Any]:
    """The evaluation summary: Table-1 ``metrics`` plus mean length, goals, failures and
    the episodes per outcome class of ``env`` (:mod:`~wcsac_rl.evaluation.outcomes`)."""
    n = len(episodes)
    return {
        "metrics": table1_metrics(
            [e.cost for e in episodes], [e.ret for e in episodes], cost_limit
        ),
        "mean_length": sum(e.length for e in episodes) / n,
        "goals_per_episode": sum(e.goal_reached for e in episodes) / n,
        "numerical_failures": sum(bool(e.numerical_failure) for e in episodes),
        "outcomes": outcome_counts(episodes, env_has_layout(env)),
    }


def _existing(directory: Path) -> list[Path]:
    return [p for p in (directory / EVALUATION_CSV, directory / EVALUATION_JSON) if p.exists()]


def check_can_write(directory: Path, force: bool) -> None:
    """Raise :class:`EvaluationExistsError` if ``directory`` holds an evaluation and not ``force``."""
    existing = _existing(Path(directory))
    if existing and not force:
        raise EvaluationExistsError(
            f"{directory} already has {', '.join(p.name for p in existing)}; "
            "pass --force to overwrite"
        )


def stale_evaluation(directory: str | os.PathLike) -> str | None:
    """Why the evaluation in ``directory`` no longer describes its run's checkpoint
    (``None``: it does, or there is no checkpoint to compare with — e.g. the random
    policy's evaluations without a run).

    Compares the checkpoint's SHA-256 with the one ``evaluation.json`` recorded;
    evaluations written before hashes were recorded are compared by trained frames.
    """
    from wcsac_rl.training.checkpoint import CHECKPOINT_DIR, LAST_CHECKPOINT, load_checkpoint

    directory = Path(directory)
    checkpoint = directory / CHECKPOINT_DIR / LAST_CHECKPOINT
    if not checkpoint.is_file():
        return None
    try:
        meta = load_json(directory / EVALUATION_JSON)
    except (OSError, ValueError):
        return "its evaluation.json cannot be read"
    if not isinstance(meta, dict) or meta.get("checkpoint") is None:
        return None
    from wcsac_rl.training.checkpoint import checkpoint_digest

    recorded = meta.get("checkpoint_sha256")
    if recorded is not None and recorded == checkpoint_digest(checkpoint):
        return None
    try:
        frames = int(load_checkpoint(checkpoint, required=("frames",))["frames"])
    except ConfigError as err:  # damaged, or refused as not data: say which and why
        return str(err)
    evaluated = meta.get("trained_frames")
    if recorded is None and evaluated == frames:
        return None  # an evaluation from before hashes were recorded, of these frames
    return f"evaluated at {evaluated} frames, its checkpoint now has {frames}"


def _text(write: Callable[[Any], None]) -> str:
    """What ``write`` writes to a text stream."""
    import io

    buffer = io.StringIO(newline="")
    write(buffer)
    return buffer.getvalue()


def check_writable(directory: str | os.PathLike) -> None:
    """Refuse, before any work, a directory no file can be written in (read-only, full,
    not a directory: :func:`~wcsac_rl.training.run_dir.unwritable_reason`), in one line."""
    from wcsac_rl.training.run_dir import unwritable_reason

    reason = unwritable_reason(directory)
    if reason is not None:
        reason = reason.removeprefix(f"{Path(directory).expanduser().absolute()}: ")
        raise ConfigError(f"cannot write {directory}: {reason}")


def _write_both(files: dict[Path, str]) -> None:
    """Write ``files`` together, all or none
    (:func:`~wcsac_rl.training.run_dir.replace_files`); one line naming the file."""
    from wcsac_rl.training.run_dir import replace_files

    try:
        replace_files(files)
    except OSError as err:
        raise ConfigError(f"cannot write {err.filename}: {err.strerror or err}") from None


def write_evaluation(evaluation: Evaluation, *, force: bool = False) -> tuple[Path, Path]:
    """Write ``evaluation.csv`` and ``evaluation.json`` into its directory, both or
    neither (:func:`_write_both`).

    Raises:
        ConfigError: the files exist and not ``force`` (:class:`EvaluationExistsError`),
            or they cannot be written (one line naming the file and why).
    """
    directory = Path(evaluation.directory)
    check_can_write(directory, force)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"cannot write {directory}: {err.strerror or err}") from None
    csv_path, json_path = directory / EVALUATION_CSV, directory / EVALUATION_JSON

    def write_csv(f: Any) -> None:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS)
        for i, e in enumerate(evaluation.episodes):
            writer.writerow(
                [i, repr(e.ret), repr(e.cost), e.length, e.goal_reached, int(e.numerical_failure)]
            )

    def write_json(f: Any) -> None:
        json.dump({**evaluation.meta, **evaluation.summary}, f, indent=2, sort_keys=False)
        f.write("\n")

    _write_both({csv_path: _text(write_csv), json_path: _text(write_json)})
    return csv_path, json_path


def read_evaluation(directory: str | os.PathLike) -> Evaluation:
    """Read back what :func:`write_evaluation` wrote (episodes from the CSV).

    Raises:
        ConfigError: missing or malformed files (one line saying which).
    """
    directory = Path(directory)
    json_path, csv_path = directory / EVALUATION_JSON, directory / EVALUATION_CSV
    try:
        data = load_json(json_path)
        with csv_path.open(newline="") as f:
            rows = list(csv.DictReader(f))
        episodes = [_episode(r, i, csv_path) for i, r in enumerate(rows)]
    except FileNotFoundError as err:
        raise ConfigError(f"{directory}: incomplete evaluation ({err.filename} missing)") from None
    except (ValueError, KeyError, TypeError) as err:
        if isinstance(err, ConfigError):
            raise
        raise ConfigError(f"{directory}: cannot read the evaluation files ({err!r})") from None
    if not episodes:
        raise ConfigError(f"{directory}: {EVALUATION_CSV} has no episodes")
    if not isinstance(data, dict):
        raise ConfigError(
            f"{json_path}: not an evaluation (a JSON object), got {type(data).__name__}"
        )
    summary_keys = ("metrics", "mean_length", "goals_per_episode", "numerical_failures", "outcomes")
    summary = {k: data.pop(k) for k in summary_keys if k in data}
    for key in ("label", "env", "cost_limit"):
        if key not in data:
            raise ConfigError(f"{json_path}: missing {key!r}")
    _check_meta(data, json_path)
    return Evaluation(directory=directory, meta=data, episodes=episodes, summary=summary)


def _episode(row: dict[str, Any], index: int, path: Path) -> EpisodeResult:
    """One row of ``evaluation.csv``, each cell a finite number of its kind."""

    def cell(column: str, kind: type) -> Any:
        text = row.get(column)
        try:
            value = float(text)
        except (TypeError, ValueError):
            value = math.nan
        if not math.isfinite(value) or (kind is int and value != int(value)):
            what = "a whole number" if kind is int else "a finite number"
            raise ConfigError(f"{path}: episode row {index}: {column} must be {what}, got {text!r}")
        if abs(value) > MAX_EPISODE_VALUE:
            raise ConfigError(
                f"{path}: episode row {index}: {column} {text!r} is larger than any episode's "
                f"(at most {MAX_EPISODE_VALUE:g} in magnitude; summed over the episodes it "
                "would overflow)"
            )
        return kind(value)

    return EpisodeResult(
        ret=cell("return", float),
        cost=cell("cost", float),
        length=cell("length", int),
        goal_reached=cell("goals", int),
        numerical_failure=bool(cell("numerical_failure", int)),
    )


def _check_meta(meta: dict[str, Any], path: Path) -> None:
    """The fields a report reads have their types (one line naming the field)."""
    for key in ("label", "env", "algo"):
        if key in meta and not isinstance(meta[key], str):
            raise ConfigError(f"{path}: {key!r} must be a string, got {meta[key]!r}")
    limit = meta["cost_limit"]
    if isinstance(limit, bool) or not isinstance(limit, (int, float)) or not limit >= 0:
        raise ConfigError(f"{path}: 'cost_limit' must be a number >= 0, got {limit!r}")
    if not math.isfinite(limit):
        raise ConfigError(f"{path}: 'cost_limit' must be a number >= 0, got {limit!r}")
    for key in ("seed", "trained_frames", "max_episode_steps"):
        value = meta.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
            raise ConfigError(f"{path}: {key!r} must be a whole number, got {value!r}")


def _progress(total: int, desc: str, enabled: bool) -> tuple[tqdm, Callable[[EpisodeResult], None]]:
    bar = tqdm(
        total=total, desc=desc, unit="ep", disable=not enabled, leave=True, dynamic_ncols=True
    )
    sums = {"cost": 0.0, "ret": 0.0, "n": 0}

    def on_episode(result: EpisodeResult) -> None:
        sums["cost"] += result.cost
        sums["ret"] += result.ret
        sums["n"] += 1
        bar.set_postfix(
            cost=f"{sums['cost'] / sums['n']:.2f}",
            ret=f"{sums['ret'] / sums['n']:.2f}",
            refresh=False,
        )
        bar.update(1)

    return bar, on_episode


def _run(
    env: Any,
    policy: Any,
    episodes: int,
    max_steps: int,
    env_seed: int,
    desc: str,
    progress: bool,
) -> list[EpisodeResult]:
    if not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes must be a positive integer, got {episodes!r}")
    torch.manual_seed(env_seed)
    bar, on_episode = _progress(episodes, desc, progress)
    try:
        return run_episodes(
            env, policy, episodes, deterministic=True, max_steps=max_steps, on_episode=on_episode
        )
    finally:
        bar.close()


def _side_by_side(episodes: Any) -> int:
    """How many test episodes run at once (sub-envs of one in-process batch)."""
    from wcsac_rl.training.trainer import EVAL_ENVS

    if not isinstance(episodes, int) or episodes < 1:
        return 1  # _run reports the bad value
    return min(episodes, EVAL_ENVS)


def _now() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


def load_policy(
    run_dir: str | os.PathLike,
    env_seed: int,
    num_envs: int = 1,
    *,
    trust_env_code: bool = False,
) -> RestoredRun:
    """:func:`~wcsac_rl.training.restore.load_run` with its env seeded ``env_seed``
    (``num_envs`` sub-envs side by side; ``trust_env_code``: import the env code the
    run names, see there),
    refusing a checkpoint that restores no policy for a learning algorithm (it
    would silently be evaluated as the random policy)."""
    from wcsac_rl.training.restore import load_run

    restored = load_run(run_dir, seed=env_seed, num_envs=num_envs, trust_env_code=trust_env_code)
    algo = str(restored.cfg.algo.name)
    entry = find_algorithm(algo)
    if restored.policy is None and (entry is None or entry.learns):
        restored.env.close()
        raise ConfigError(
            f"{run_dir}: no policy could be restored from the checkpoint of algo {algo!r}"
        )
    return restored


def check_env_code_allowed(run_dir: str | os.PathLike) -> None:
    """Refuse, before any work, a run whose checkpoints (``last.pt`` and the kept ones)
    name env code the command has not allowed
    (:func:`~wcsac_rl.training.trust.allow_env_code`: a report's ``--trust-env-code``);
    one line, nothing imported."""
    from wcsac_rl.training.checkpoint import find_checkpoint, kept_checkpoints, load_checkpoint
    from wcsac_rl.training.trust import TRUST_FLAG, check_env_code

    last = find_checkpoint(run_dir)
    for path in [last, *(kept for _, kept in kept_checkpoints(last.parent.parent))]:
        check_env_code(
            load_checkpoint(path)["config"], path, trusted=False, allow=f"pass {TRUST_FLAG}"
        )


def _training_seed(run_dir: Path) -> int:
    """The run's training seed: from ``config.yaml``, else from its checkpoint."""

    from wcsac_rl.training.checkpoint import find_checkpoint, load_checkpoint
    from wcsac_rl.training.trust import plain_select

    checkpoint = find_checkpoint(run_dir)  # a clear error first if there is none
    config_yaml = run_dir / "config.yaml"
    if config_yaml.is_file() and not config_yaml.is_symlink():
        try:  # (read as data: nothing in it is resolved)
            seed = plain_select(load_yaml(config_yaml), "seed")
        except Exception:  # a damaged config.yaml: the checkpoint says it too
            seed = None
        if isinstance(seed, int) and not isinstance(seed, bool):
            return seed
    seed = plain_select(load_checkpoint(checkpoint)["config"], "seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"{checkpoint}: its config's seed must be an integer >= 0, got {seed!r}")
    return seed


def evaluate_run(
    run_dir: str | os.PathLike,
    *,
    episodes: int = DEFAULT_EPISODES,
    seed_offset: int = DEFAULT_SEED_OFFSET,
    force: bool = False,
    progress: bool = True,
    max_episode_steps: int | None = None,
    log: Callable[[str], None] | None = None,
    trust_env_code: bool = False,
) -> Evaluation:
    """Evaluate a run's final policy on ``episodes`` deterministic test episodes and save them.

    Args:
        run_dir: a run directory holding ``checkpoints/last.pt``.
        episodes: number of test episodes (the paper: 100 per seed).
        seed_offset: the test env is seeded with ``run seed + seed_offset``.
        force: overwrite an existing evaluation (a stale one is always replaced).
        progress: show a tqdm bar over the episodes.
        max_episode_steps: bound on episode length (default: the run's env's).
        log: where the note about re-evaluating a stale evaluation goes (default:
            ``print`` when ``progress``).
        trust_env_code: import and call the env code a run of ``env=gymnasium`` names
            (:func:`~wcsac_rl.training.restore.load_run`; refused by default).

    Raises:
        ConfigError: no checkpoint / unreadable checkpoint (one line), or an
            evaluation of the run's current checkpoint exists and not ``force``
            (:class:`EvaluationExistsError`; checked before any work).
    """
    from wcsac_rl.training.trainer import env_max_episode_steps

    run_dir = Path(run_dir)
    if not force and _existing(run_dir):
        reason = stale_evaluation(run_dir)
        if reason is None:
            check_can_write(run_dir, force)  # up to date: EvaluationExistsError
        if progress or log is not None:
            (log or print)(f"{run_dir}: evaluating again ({reason})")
        force = True
    env_seed = _training_seed(run_dir) + int(seed_offset)
    restored = load_policy(
        run_dir, env_seed, num_envs=_side_by_side(episodes), trust_env_code=trust_env_code
    )
    cfg = restored.cfg
    steps = int(max_episode_steps or env_max_episode_steps(cfg))
    label = str(cfg.algo.get("label", cfg.algo.name))
    try:
        check_writable(restored.run_dir)  # (before the episodes, not after them)
        results = _run(
            restored.env,
            restored.policy,
            episodes,
            steps,
            env_seed,
            f"{label} seed {cfg.seed}",
            progress,
        )
    finally:
        restored.env.close()
    meta = {
        "label": label,
        "algo": str(cfg.algo.name),
        "env": str(cfg.env.name),
        "seed": int(cfg.seed),
        "cost_limit": float(cfg.cost_limit),
        "risk_level": float(cfg.algo.get("risk_level", cfg.risk_level)),
        "trained_frames": int(restored.frames),
        "policy": "uniform random" if restored.policy is None else "trained (deterministic)",
        "checkpoint": str(Path("checkpoints") / "last.pt"),
        "checkpoint_sha256": restored.checkpoint_sha256,
    }
    total = _total_frames(cfg)
    return _save(restored.run_dir, meta, results, env_seed, steps, force, total_frames=total)


def _save(
    directory: Path,
    meta: dict[str, Any],
    results: list[EpisodeResult],
    env_seed: int,
    steps: int,
    force: bool,
    total_frames: int | None = None,
) -> Evaluation:
    """The :class:`Evaluation` of ``results`` (``meta`` with the episodes' seed, length,
    count and date), written into ``directory`` (:func:`write_evaluation`)."""
    meta = {**meta, "env_seed": env_seed, "max_episode_steps": steps,
            "episodes": len(results), "created": _now()}  # fmt: skip
    summary = summarize(results, float(meta["cost_limit"]), str(meta["env"]))
    evaluation = Evaluation(directory, meta, results, summary, total_frames)
    write_evaluation(evaluation, force=force)
    return evaluation


def _total_frames(cfg: Any) -> int | None:
    """The run's ``total_frames`` (``None`` where its config has no whole number there)."""
    total = cfg.get("total_frames")
    if isinstance(total, bool) or not isinstance(total, int):
        return None
    return total


def unfinished_training(evaluation: Evaluation) -> str | None:
    """``"<run>: evaluated at F of its T frames (training unfinished: ...)"`` where
    :func:`evaluate_run` evaluated a run whose checkpoint has fewer frames than its
    config's ``total_frames`` (stopped early, killed, or still training), else ``None``:
    such an evaluation is of the run so far, not of what its config trains, and
    ``wcsac-evaluate`` says so (one ``warning:`` line per run)."""
    trained = evaluation.meta.get("trained_frames")
    total = evaluation.total_frames
    if total is None or not isinstance(trained, int) or trained >= total:
        return None
    directory = evaluation.directory
    return (
        f"{directory}: evaluated at {trained} of its {total} frames (training unfinished: "
        f"resume it to finish, resume={directory})"
    )


def check_random_policy(env_name: str, cost_limit: float) -> None:
    """Refuse, naming it, an env the random policy cannot be evaluated on or a cost
    limit that is not a budget (:class:`ConfigError`)."""
    from wcsac_rl.envs import PRESET_NAMES

    if env_name not in PRESET_NAMES:
        raise ConfigError(f"unknown env {env_name!r}; choose one of {', '.join(PRESET_NAMES)}")
    if not math.isfinite(cost_limit) or cost_limit < 0:
        raise ConfigError(f"cost limit must be a number >= 0, got {cost_limit!r}")


def evaluate_random_policy(
    env_name: str,
    out_dir: str | os.PathLike,
    *,
    seed: int = 0,
    episodes: int = DEFAULT_EPISODES,
    seed_offset: int = DEFAULT_SEED_OFFSET,
    cost_limit: float = 15.0,
    max_episode_steps: int | None = None,
    force: bool = False,
    progress: bool = True,
) -> Evaluation:
    """Evaluate the uniform random policy (Table 1's "Random Policy") without a training run.

    Same files and seeding as :func:`evaluate_run` for a run of ``algo=random`` with
    training seed ``seed`` (so both ways give the same episodes), written to ``out_dir``.

    Raises:
        ConfigError: unknown env, negative cost limit, or an existing evaluation and
            not ``force``.
    """
    from wcsac_rl.envs import env_info, make_env

    check_random_policy(env_name, cost_limit)
    out_dir = Path(out_dir)
    check_can_write(out_dir, force)
    check_writable(out_dir)
    kwargs = {} if max_episode_steps is None else {"max_episode_steps": int(max_episode_steps)}
    steps = int(env_info(env_name, **kwargs)["max_episode_steps"])
    env_seed = int(seed) + int(seed_offset)
    env = make_env(
        env_name, seed=env_seed, num_workers=_side_by_side(episodes), parallel=False, **kwargs
    )
    try:
        results = _run(env, None, episodes, steps, env_seed, f"random seed {seed}", progress)
    finally:
        env.close()
    meta = {
        "label": "random",
        "algo": "random",
        "env": env_name,
        "seed": int(seed),
        "cost_limit": float(cost_limit),
        "trained_frames": 0,
        "policy": "uniform random",
        "checkpoint": None,
    }
    return _save(out_dir, meta, results, env_seed, steps, force)
