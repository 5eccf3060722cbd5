"""Calibrate a finished run's safety critic: ``calibration.json`` beside the run.

The measurement is :mod:`wcsac_rl.rollouts.critic_calibration` (logged every epoch as
``calib/*``; its names are re-exported here); this module loads a run's checkpoint, runs
its deterministic test episodes and writes the result (``python -m wcsac_rl.calibration``).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from wcsac_rl._messages import first_line
from wcsac_rl.rollouts.critic_calibration import (
    CALIBRATION_KEYS,
    PREFIX,
    EpisodeCalibration,
    calibration_keys,
    calibration_metrics,
    compare_episodes,
    discounted_cost_to_go,
    record_calibration_episodes,
    summarize_calibration,
    supports_calibration,
)
from wcsac_rl.rollouts.episodes import EpisodeResult
from wcsac_rl.training.config import ConfigError
from wcsac_rl.training.progress import read_progress
from wcsac_rl.training.registry import ALGORITHMS, find_algorithm, make_loss
from wcsac_rl.training.training_calibration import TRAIN_PREFIX, TRAINING_CALIBRATION_KEYS

__all__ = [
    "CALIBRATION_JSON",
    "CALIBRATION_KEYS",
    "PREFIX",
    "CalibrationExistsError",
    "EpisodeCalibration",
    "calibrate_run",
    "calibration_keys",
    "calibration_metrics",
    "compare_episodes",
    "discounted_cost_to_go",
    "load_safety_run",
    "record_calibration_episodes",
    "summarize_calibration",
    "supports_calibration",
    "training_episode_readings",
]

CALIBRATION_JSON = "calibration.json"


class CalibrationExistsError(ConfigError):
    """The run already has ``calibration.json`` and ``force`` was not given."""


def load_safety_run(
    run_dir: str | os.PathLike, *, seed: int, num_envs: int = 1, trust_env_code: bool = False
):
    """A run's config, test env, policy and whole loss (safety critic included).

    The loss is built like the trainer's (``builders.make_agent`` /
    its entry's loss, ``registry.make_loss``) and loaded from the checkpoint; the policy acts through
    the loss's actor as in training and evaluation.

    A run of your own env (``env=gymnasium``) names code: it is imported only with
    ``trust_env_code=True`` (as :func:`~wcsac_rl.training.restore.load_run`).

    Returns:
        ``(cfg, env, policy, loss, frames)``; ``env`` has ``num_envs`` sub-envs
        seeded ``seed``, ``seed + 1``, ...

    Raises:
        ConfigError: no or unreadable checkpoint, a run without a safety critic (SAC,
            CPO, random), or a checkpoint whose networks do not fit its config.
    """
    from wcsac_rl.modules.actor import TanhNormalPolicy
    from wcsac_rl.training import builders
    from wcsac_rl.training.checkpoint import (
        StateMismatch,
        check_current,
        find_checkpoint,
        load_checkpoint,
        load_module_state,
    )
    from wcsac_rl.training.devices import on_cpu
    from wcsac_rl.training.restore import trusted_eval_env
    from wcsac_rl.training.trainer import env_max_episode_steps
    from wcsac_rl.training.trust import plain_select, stored_config

    path = find_checkpoint(run_dir)
    checkpoint = load_checkpoint(path)
    cfg = on_cpu(stored_config(checkpoint["config"], path))  # whatever it trained on
    check_current(cfg, path)  # (a config of another commit's kit: refused)
    algo = plain_select(cfg, "algo.name")
    learner = checkpoint["learner"]
    frames = int(checkpoint["frames"])
    entry = find_algorithm(algo)
    if entry is None or not entry.safety_critic:
        safe = ", ".join(name for name, a in ALGORITHMS.items() if a.safety_critic)
        raise ConfigError(
            f"{path.parent.parent}: algo {algo!r} has no safety critic to calibrate "
            f"(calibration needs one of {safe})"
        )
    env = trusted_eval_env(cfg, path, trust_env_code=trust_env_code, seed=seed, num_envs=num_envs)
    try:
        agent = builders.make_agent(cfg, env)
        loss = make_loss(cfg, agent, env_max_episode_steps(cfg))
        load_module_state(loss, learner.get("loss"))
    except StateMismatch as err:
        env.close()
        raise ConfigError(f"checkpoint {path}: {err}") from None
    except (KeyError, RuntimeError) as err:
        env.close()
        raise ConfigError(
            f"{path}: the checkpoint's loss does not fit its config ({first_line(err)})"
        ) from None
    if not supports_calibration(loss):
        env.close()
        raise ConfigError(f"{path}: the loss {type(loss).__name__} has no safety_estimates")
    loss.eval()
    policy = TanhNormalPolicy(agent.actor)  # as OffPolicyTrainer.restore_policy
    policy.eval()
    return cfg, env, policy, loss, frames


def training_episode_readings(run_dir: str | os.PathLike) -> list[dict[str, float]]:
    """Per epoch of the run's ``progress.csv``, its end (``frames``) and the critic's
    reading of that epoch's training episodes against their realised cost-to-go (the
    ``train_calib/*`` columns without their prefix,
    :mod:`~wcsac_rl.training.training_calibration`); empty for a run that did not log
    them (no ``progress.csv``, or one from before these columns)."""
    path = Path(run_dir) / "progress.csv"
    columns = read_progress(path, warn=False) if path.is_file() else {}
    if TRAIN_PREFIX + "episodes" not in columns or "frames" not in columns:
        return []
    return [
        {
            "frames": frames,
            **{
                key.removeprefix(TRAIN_PREFIX): columns.get(key, [math.nan] * (i + 1))[i]
                for key in TRAINING_CALIBRATION_KEYS
            },
        }
        for i, frames in enumerate(columns["frames"])
    ]


def check_can_write(run_dir: Path, force: bool) -> None:
    """Raise :class:`CalibrationExistsError` if ``calibration.json`` exists and not ``force``."""
    path = Path(run_dir) / CALIBRATION_JSON
    if path.exists() and not force:
        raise CalibrationExistsError(f"{path} already exists; pass --force to overwrite")


def calibrate_run(
    run_dir: str | os.PathLike,
    *,
    episodes: int = 30,
    seed_offset: int | None = None,
    force: bool = False,
    max_episode_steps: int | None = None,
    on_episode: Callable[[EpisodeResult], None] | None = None,
    trust_env_code: bool = False,
) -> tuple[Path, dict[str, Any]]:
    """Calibrate a run's final safety critic on deterministic test episodes; write
    ``calibration.json`` beside the run (docs/training.md, "Safety-critic calibration").

    ``run_dir`` is a run directory (or a checkpoint in its ``checkpoints/``); the test env
    is seeded as :func:`~wcsac_rl.evaluation.evaluator.evaluate_run` seeds it (training
    seed + ``seed_offset``), so the episodes are the first ``episodes`` of that
    evaluation; ``trust_env_code``: as :func:`load_safety_run`.

    Returns:
        The path of ``calibration.json`` and what it holds (NaN written as ``null``): the
        meta data, ``metrics`` (:data:`CALIBRATION_KEYS` without their ``calib/``
        prefix), ``per_episode`` (:meth:`EpisodeCalibration.as_dict` and the return) and
        ``training_episodes`` (:func:`training_episode_readings`).

    Raises:
        ConfigError: see :func:`load_safety_run`; :class:`CalibrationExistsError`
            or a run directory that cannot be written (checked before any work);
            ``calibration.json`` that cannot be written after all (a full disk).
    """
    from wcsac_rl.evaluation.evaluator import (
        DEFAULT_SEED_OFFSET,
        _now,
        _side_by_side,
        _training_seed,
        _write_both,
        check_writable,
    )
    from wcsac_rl.training.trainer import env_max_episode_steps

    if not isinstance(episodes, int) or episodes < 1:
        raise ConfigError(f"episodes must be a positive integer, got {episodes!r}")
    from wcsac_rl.training.checkpoint import find_checkpoint

    run_dir = find_checkpoint(run_dir).parent.parent
    check_can_write(run_dir, force)
    check_writable(run_dir)  # (before the episodes, not after them)
    seed_offset = DEFAULT_SEED_OFFSET if seed_offset is None else int(seed_offset)
    env_seed = _training_seed(run_dir) + seed_offset
    cfg, env, policy, loss, frames = load_safety_run(
        run_dir, seed=env_seed, num_envs=_side_by_side(episodes), trust_env_code=trust_env_code
    )
    limit = env_max_episode_steps(cfg)  # the env truncates there whatever max_steps is
    steps = min(int(max_episode_steps or limit), limit)
    torch.manual_seed(env_seed)
    try:
        recorded = record_calibration_episodes(
            env, policy, loss, episodes, max_steps=steps, on_episode=on_episode
        )
    finally:
        env.close()
    compared = compare_episodes(recorded, loss)
    metrics = summarize_calibration(
        compared,
        float(loss.risk_level),
        nonnegative=bool(getattr(loss, "nonnegative_cost", False)),  # as the trainer's
    )
    result = {
        "label": str(cfg.algo.get("label", cfg.algo.name)),
        "algo": str(cfg.algo.name),
        "env": str(cfg.env.name),
        "seed": int(cfg.seed),
        "trained_frames": frames,
        "risk_level": float(loss.risk_level),
        "cost_gamma": float(loss.cost_gamma),
        "cost_threshold": float(loss.cost_threshold),
        "cost_limit": float(cfg.cost_limit),
        "has_variance": bool(loss.has_variance),
        "safety_critic": str(getattr(loss, "safety_critic_kind", "gaussian")),
        "env_seed": env_seed,
        "max_episode_steps": steps,
        "episodes": len(recorded),
        "episodes_at_time_limit": sum(r.result.length >= steps for r in recorded),
        "created": _now(),
        "metrics": {key.removeprefix(PREFIX): value for key, value in metrics.items()},
        "per_episode": [
            {"return": r.result.ret, **c.as_dict()} for r, c in zip(recorded, compared)
        ],
        "training_episodes": training_episode_readings(run_dir),
    }
    path = run_dir / CALIBRATION_JSON
    _write_both({path: json.dumps(_nan_to_null(result), indent=2, allow_nan=False) + "\n"})
    return path, result


def _nan_to_null(value: Any) -> Any:
    """JSON has no NaN: undefined numbers are written as ``null``."""
    if isinstance(value, dict):
        return {k: _nan_to_null(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nan_to_null(v) for v in value]
    return None if isinstance(value, float) and not math.isfinite(value) else value
