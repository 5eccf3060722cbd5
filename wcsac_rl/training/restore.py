"""Load a finished (or interrupted) run for evaluation: its config and trained policy."""

from __future__ import annotations

import numbers
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from tensordict.nn import TensorDictModule
from torchrl.envs import EnvBase

from wcsac_rl.envs import CostKeyError, EnvSourceError
from wcsac_rl.training import builders
from wcsac_rl.training.checkpoint import (
    CHECKPOINT_DIR,
    StateMismatch,
    check_current,
    check_run_config,
    find_checkpoint,
    read_checkpoint,
)
from wcsac_rl.training.config import ConfigError, check_sizes
from wcsac_rl.training.devices import on_cpu
from wcsac_rl.training.registry import trainer_class
from wcsac_rl.training.trust import TRUST_FLAG, check_env_code, stored_config

__all__ = ["RestoredRun", "load_run"]


@dataclass
class RestoredRun:
    """A run read back from its checkpoint.

    Attributes:
        run_dir: the run directory.
        cfg: the run's resolved configuration.
        policy: the trained policy (``None`` for the random policy: uniform actions);
            for the SAC family a :class:`~wcsac_rl.modules.actor.TanhNormalPolicy`
            over the actor (``policy.actor``).
        env: an env of the run's preset for test episodes: unbatched, or
            ``num_envs`` sub-envs stepped side by side (see :func:`load_run`).
        frames: env steps the run was trained for.
        checkpoint: the raw checkpoint dict.
        checkpoint_sha256: SHA-256 of the checkpoint file that was loaded.
    """

    run_dir: Path
    cfg: DictConfig
    policy: TensorDictModule | None
    env: EnvBase
    frames: int
    checkpoint: dict[str, Any]
    checkpoint_sha256: str = ""


def trusted_eval_env(
    cfg: DictConfig, checkpoint_path: Path, *, trust_env_code: bool, seed: int, num_envs: int
) -> EnvBase:
    """The test env of a stored run's ``cfg``, built only if the env code it names is
    allowed (:func:`~wcsac_rl.training.trust.check_env_code`); an env that cannot be
    built (a module that no longer imports, a missing cost key) is one ``ConfigError``
    line naming the checkpoint."""
    check_env_code(
        cfg,
        checkpoint_path,
        trusted=trust_env_code,
        allow=f"pass {TRUST_FLAG} (in Python: trust_env_code=True)",
    )
    try:  # (your env: a module that no longer imports, an env that fails to build)
        return builders.make_eval_env(cfg, seed=seed, num_envs=num_envs)
    except (EnvSourceError, CostKeyError) as err:
        raise ConfigError(f"{checkpoint_path}: {err}") from None


def _check_arguments(seed: Any, num_envs: Any) -> None:
    """``load_run``'s seed (a whole number or None) and num_envs (a whole number >= 1)."""

    def whole(value: Any) -> bool:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)

    if seed is not None and not whole(seed):
        raise ConfigError(f"load_run: seed must be a whole number or None, got {seed!r}")
    if not whole(num_envs) or num_envs < 1:
        raise ConfigError(f"load_run: num_envs must be a whole number >= 1, got {num_envs!r}")


def load_run(
    path: str | os.PathLike,
    *,
    seed: int | None = None,
    num_envs: int = 1,
    trust_env_code: bool = False,
) -> RestoredRun:
    """Rebuild a run's policy from ``path`` (a run dir or a checkpoint file).

    ``seed`` seeds the returned env (default: the eval seed of the run's trainer); with
    ``num_envs > 1`` it is a batch of that many sub-envs (seeded ``seed``, ``seed + 1``,
    ...) for :func:`~wcsac_rl.rollouts.episodes.run_episodes`. A run of your own env is
    built only with ``trust_env_code=True`` (docs/guarantees.md, "Env code runs only on
    your word"). Raises :class:`~wcsac_rl.training.ConfigError` with one clear line when
    the directory holds no checkpoint, it cannot be read, or it names env code not allowed.
    """
    _check_arguments(seed, num_envs)
    checkpoint_path = find_checkpoint(path)
    checkpoint, digest = read_checkpoint(checkpoint_path)
    cfg = on_cpu(stored_config(checkpoint["config"], checkpoint_path))  # whatever it trained on
    check_current(cfg, checkpoint_path)  # (a config of another commit's kit: refused)
    check_sizes(cfg, checkpoint_path)  # (a network or an episode nothing could build or run)
    env = trusted_eval_env(
        cfg, checkpoint_path, trust_env_code=trust_env_code, seed=seed, num_envs=num_envs
    )
    try:
        policy = trainer_class(cfg.algo.name).restore_policy(
            cfg, checkpoint.get("learner", {}), env
        )
        if checkpoint_path.parent.name == CHECKPOINT_DIR:  # in a run: the run's algorithm
            check_run_config(checkpoint["config"], checkpoint_path.parent.parent, checkpoint_path)
    except StateMismatch as err:
        env.close()
        raise ConfigError(f"checkpoint {checkpoint_path}: {err}") from None
    except ConfigError:
        env.close()
        raise
    if policy is not None:
        policy.eval()
    return RestoredRun(
        run_dir=checkpoint_path.parent.parent,
        cfg=cfg,
        policy=policy,
        env=env,
        frames=int(checkpoint["frames"]),
        checkpoint=checkpoint,
        checkpoint_sha256=digest,
    )
