"""Checkpoints: atomic writes, locating a run's checkpoint, refusing incompatible configs."""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from wcsac_rl.training.config import ConfigError, TrainingError

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


REQUIRED_ENTRIES = ("config", "frames", "learner")
"""What every reader of a training checkpoint needs (resume needs the counters too)."""

# How torch.save and the OS report a full disk (torch: "unexpected pos 704 vs 598" on
# a full tmpfs, measured; "file write failed" from its zip writer)
_DISK_FULL_ERRNOS = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC)}
_DISK_FULL_MESSAGES = ("unexpected pos", "file write failed", "no space left")


def write_error_reason(err: BaseException, directory: Path) -> str:
    """A short reason for a failed write into ``directory`` (says so when the disk is full)."""
    text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    full = (isinstance(err, OSError) and err.errno in _DISK_FULL_ERRNOS) or any(
        m in text.lower() for m in _DISK_FULL_MESSAGES
    )
    if not full:
        return text
    try:
        free = shutil.disk_usage(directory).free
        return f"no space left on its disk ({free / 2**20:.1f} MB free)"
    except OSError:
        return "no space left on its disk"


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` with ``torch.save`` atomically: to ``<path>.tmp``, flushed to disk,
    then renamed over ``path``. A crash never leaves half a file, and a failed write
    (a full disk) removes the temporary file, keeps the previous ``path`` and raises
    :class:`~wcsac_rl.training.TrainingError` with one line that says why.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    try:
        with tmp.open("wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as err:  # Ctrl-C mid-write too: never leave the temporary file
        tmp.unlink(missing_ok=True)
        if not isinstance(err, Exception):
            raise
        raise TrainingError(
            f"cannot write checkpoint {path}: {write_error_reason(err, path.parent)}; the "
            f"previous checkpoint is kept (free some space, then resume={path.parent.parent})"
        ) from None
    fsync_directory(path.parent)


def fsync_directory(directory: Path) -> None:
    """Make a rename inside ``directory`` durable (no-op where directories cannot be opened)."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


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


def load_checkpoint(path: Path, *, required: tuple[str, ...] = REQUIRED_ENTRIES) -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint` (on CPU).

    Raises :class:`~wcsac_rl.training.ConfigError` (one line) for a file that cannot
    be read or is not a training checkpoint (a dict with the ``required`` entries).
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:  # a corrupt or foreign file: one clear line
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"cannot read checkpoint {path}: {reason}") from None
    if not isinstance(state, dict):
        raise ConfigError(
            f"{path} is not a wcsac_rl training checkpoint (it holds a {type(state).__name__}, "
            "not the dict train.py writes)"
        )
    missing = [key for key in required if key not in state]
    if missing:
        raise ConfigError(
            f"{path} is not a wcsac_rl training checkpoint (no {', '.join(map(repr, missing))} "
            "entry); pass a run directory written by train.py"
        )
    return state


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
