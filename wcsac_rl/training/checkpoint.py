"""Checkpoints: atomic writes, locating a run's checkpoint, refusing incompatible configs."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from wcsac_rl.training.config import ConfigError

__all__ = [
    "CHECKPOINT_DIR",
    "INITIAL_STATE_BUFFER_DIR",
    "LAST_CHECKPOINT",
    "check_compatible",
    "find_checkpoint",
    "load_checkpoint",
    "load_optimizer_state",
    "save_checkpoint",
]

CHECKPOINT_DIR = "checkpoints"
LAST_CHECKPOINT = "last.pt"
REPLAY_BUFFER_DIR = "replay_buffer"
INITIAL_STATE_BUFFER_DIR = "initial_state_buffer"

# What a checkpoint's networks and losses depend on: these must match to resume or
# evaluate. Anything else (frames, cadences, logger, threads) may change on resume.
IDENTITY_KEYS = (
    "algo.name",
    "algo.risk_level",
    "algo.variance",
    "algo.network",
    "algo.gamma",
    "algo.kappa_parametrization",
    "env.name",
    "env.max_episode_steps",
    "env.kwargs",
    "cost_limit",
)


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` with ``torch.save`` atomically (a crash never leaves half a file)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def find_checkpoint(path: str | os.PathLike) -> Path:
    """The checkpoint file for ``path``: a run dir holding ``checkpoints/last.pt``, or a
    ``.pt`` file in a run's ``checkpoints/`` directory (the run dir is its grandparent)."""
    path = Path(path).expanduser()
    if path.is_file():
        if path.parent.name != CHECKPOINT_DIR:
            raise ConfigError(
                f"{path} is not inside a run's {CHECKPOINT_DIR}/ directory; pass the run "
                f"directory (or <run dir>/{CHECKPOINT_DIR}/<file>.pt) so its logs stay with it"
            )
        return path.resolve()
    candidate = path / CHECKPOINT_DIR / LAST_CHECKPOINT
    if candidate.is_file():
        return candidate
    if not path.exists():
        raise ConfigError(f"no such run directory or checkpoint: {path}")
    raise ConfigError(f"{path} holds no checkpoint (expected {candidate})")


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint` (on CPU)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # a corrupt or foreign file: one clear line
        raise ConfigError(f"cannot read checkpoint {path}: {err}") from None


def _select(cfg: DictConfig | dict, key: str) -> Any:
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    value = OmegaConf.select(cfg, key, default=None)
    if isinstance(value, DictConfig):
        return OmegaConf.to_container(value, resolve=True)
    return value


def check_compatible(saved_config: dict, cfg: DictConfig, path: Path) -> None:
    """Refuse a checkpoint whose networks/loss were made by a different configuration."""
    diffs = [
        f"{key}: checkpoint={_select(saved_config, key)!r}, now={_select(cfg, key)!r}"
        for key in IDENTITY_KEYS
        if _select(saved_config, key) != _select(cfg, key)
    ]
    if diffs:
        raise ConfigError(
            f"checkpoint {path} was made by another configuration ({'; '.join(diffs)}); "
            "run with the same settings or start a new run"
        )


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: dict[str, Any]) -> None:
    """Restore an optimizer's moments and step counts but keep its configured learning rates.

    ``Optimizer.load_state_dict`` also brings back the saved ``lr``, which would make a
    learning rate changed on resume silently ignored.
    """
    lrs = [group["lr"] for group in optimizer.param_groups]
    optimizer.load_state_dict(state)
    for group, lr in zip(optimizer.param_groups, lrs):
        group["lr"] = lr
