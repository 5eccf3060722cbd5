"""Checkpoints: atomic writes, locating a run's checkpoint, refusing incompatible configs."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from wcsac_rl._messages import first_line
from wcsac_rl.training.config import ConfigError, TrainingError
from wcsac_rl.training.preemption import DeferredSignals
from wcsac_rl.training.run_dir import replace_file
from wcsac_rl.training.safe_load import (
    MAX_CHECKPOINT_BYTES,
    UnreadableRecord,
    check_buffer_files,
    check_size,
    load_data,
    load_yaml,
)
from wcsac_rl.training.trust import (
    TRUST_KEY,
    check_env_code,
    interpolation_in,
    plain_select,
    stored_config,
)

__all__ = [
    "CHECKPOINT_DIR",
    "INITIAL_STATE_BUFFER_DIR",
    "LAST_CHECKPOINT",
    "RESUME_CHANGEABLE",
    "StateMismatch",
    "check_compatible",
    "check_counters",
    "check_current",
    "check_not_behind",
    "check_resume_changes",
    "check_run_config",
    "checkpoint_digest",
    "find_checkpoint",
    "keep_checkpoint",
    "kept_checkpoints",
    "load_buffers",
    "load_checkpoint",
    "load_module_state",
    "load_optimizer_state",
    "numpy_rng_state",
    "read_checkpoint",
    "resume_config",
    "run_config_record",
    "run_latest_frames",
    "save_checkpoint",
    "set_numpy_rng_state",
]

CHECKPOINT_DIR = "checkpoints"
LAST_CHECKPOINT = "last.pt"
KEPT_PREFIX = "frames-"  # checkpoints/frames-<N>.pt: copies kept at keep_checkpoints_at
REPLAY_BUFFER_DIR = "replay_buffer"
INITIAL_STATE_BUFFER_DIR = "initial_state_buffer"

# What a checkpoint's networks and losses depend on: these must match to resume or
# evaluate. Anything else (frames, cadences, logger, threads) may change on resume.
IDENTITY_KEYS = (
    "algo.name",
    "algo.risk_level",
    "algo.variance",
    "algo.safety_critic",
    "algo.iqn",
    "algo.network",
    "algo.gamma",
    "algo.kappa_parametrization",
    "algo.kappa_rule",
    "env.name",
    "env.id",
    "env.cost_key",
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


def is_disk_full(err: BaseException) -> bool:
    """Whether a failed write failed because the disk (or the quota) is full."""
    if isinstance(err, OSError) and err.errno in _DISK_FULL_ERRNOS:
        return True
    return any(m in first_line(err).lower() for m in _DISK_FULL_MESSAGES)


def write_error_reason(err: BaseException, directory: Path) -> str:
    """A short reason for a failed write into ``directory`` (says so when the disk is full)."""
    if not is_disk_full(err):
        return first_line(err)
    try:
        free = shutil.disk_usage(directory).free
        return f"no space left on its disk ({free / 2**20:.1f} MB free)"
    except OSError:
        return "no space left on its disk"


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` with ``torch.save`` atomically
    (:func:`~wcsac_rl.training.run_dir.replace_file`, a stop signal waiting until the file
    is in place). A failed write (a full disk) keeps
    the previous ``path`` and raises :class:`~wcsac_rl.training.TrainingError` with one
    line that says why.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    kept = (
        "the previous checkpoint is kept"
        if path.is_file()
        else "no checkpoint had been written yet"
    )
    try:
        with DeferredSignals():
            replace_file(path, lambda f: torch.save(state, f))
    except Exception as err:
        hint = f" (free some space, then resume={path.parent.parent})" if is_disk_full(err) else ""
        raise TrainingError(
            f"cannot write checkpoint {path}: {write_error_reason(err, path.parent)}; {kept}{hint}"
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


def numpy_rng_state() -> dict[str, Any]:
    """NumPy's global RNG state as plain data (what a checkpoint holds: ``torch.load``
    with ``weights_only=True`` reads no NumPy arrays)."""
    state = np.random.get_state(legacy=False)
    return {
        "bit_generator": str(state["bit_generator"]),
        "state": {
            "key": [int(k) for k in state["state"]["key"]],
            "pos": int(state["state"]["pos"]),
        },
        "has_gauss": int(state["has_gauss"]),
        "gauss": float(state["gauss"]),
    }


def set_numpy_rng_state(state: dict[str, Any] | tuple) -> None:
    """Restore NumPy's global RNG from :func:`numpy_rng_state` (or from the
    ``np.random.get_state()`` tuple older checkpoints hold)."""
    if isinstance(state, dict):
        state = {
            **state,
            "state": {**state["state"], "key": np.asarray(state["state"]["key"], np.uint32)},
        }
    np.random.set_state(state)


# ------------------------------------------------------------ replay buffers
BUFFERS_PREFIX = "buffers-"
"""Saved buffers live in ``checkpoints/buffers-<frames>/<name>/`` (one directory per
checkpoint that saved them), named by the checkpoint's ``learner["buffers"]`` manifest."""


def _file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while chunk := f.read(1 << 22):
            digest.update(chunk)
    return digest.hexdigest()


def _fsync_file(path: Path) -> None:
    with path.open("rb") as f:
        os.fsync(f.fileno())


def save_buffers(checkpoint_dir: Path, buffers: dict[str, Any], *, frames: int) -> dict[str, Any]:
    """Write replay buffers (``ReplayBuffer.dumps``) for the checkpoint about to be saved
    into ``buffers-<frames>/`` (a temporary directory, flushed, measured and renamed:
    docs/training.md, "Saved replay buffers"); returns the manifest to store in the
    checkpoint. A failed write (a full disk) removes the temporary directory and raises
    ``TrainingError``.
    """
    name = f"{BUFFERS_PREFIX}{int(frames)}"
    final = checkpoint_dir / name
    tmp = checkpoint_dir / f".tmp-{name}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        with DeferredSignals():  # a stop signal waits until the directory is in place
            tmp.mkdir(parents=True)
            for key, buffer in buffers.items():
                buffer.dumps(tmp / key)
            files = {}
            for path in sorted(p for p in tmp.rglob("*") if p.is_file()):
                _fsync_file(path)
                files[str(path.relative_to(tmp))] = [path.stat().st_size, _file_digest(path)]
            if final.exists():  # buffers of an earlier save at the same frame count
                shutil.rmtree(final)
            os.replace(tmp, final)
            fsync_directory(checkpoint_dir)
    except BaseException as err:
        shutil.rmtree(tmp, ignore_errors=True)
        if not isinstance(err, Exception):
            raise
        hint = (
            f" (free some space or set save_replay_buffer=false, then "
            f"resume={checkpoint_dir.parent})"
            if is_disk_full(err)
            else ""
        )
        raise TrainingError(
            f"cannot write the replay buffer into {checkpoint_dir}: "
            f"{write_error_reason(err, checkpoint_dir)}; the previous checkpoint is kept{hint}"
        ) from None
    return {"dir": name, "buffers": sorted(buffers), "files": files}


def verify_buffers(checkpoint_dir: Path, manifest: dict[str, Any], checkpoint: Path) -> Path | None:
    """The directory of a checkpoint's saved buffers after checking every file's size and
    hash (``None`` when the directory is gone: the buffers are then refilled).

    Raises :class:`~wcsac_rl.training.ConfigError` (one line) when a file is missing,
    truncated or changed.
    """
    directory = checkpoint_dir / manifest["dir"]
    if not directory.is_dir():
        return None
    fix = f"delete {directory} to resume without it (the buffer is then refilled)"
    for rel, (size, digest) in manifest["files"].items():
        path = directory / rel
        damage = None
        if not path.is_file():
            damage = f"{rel} is missing"
        elif (actual := path.stat().st_size) != size:
            damage = f"{rel}: {actual} bytes, expected {size}"
        elif _file_digest(path) != digest:
            damage = f"{rel}: its contents changed since it was saved"
        if damage is not None:
            raise ConfigError(
                f"the replay buffer saved with {checkpoint} is damaged ({damage}); {fix}"
            )
    return directory


def load_buffers(
    buffers: dict[str, Any], directory: Path, checkpoint: Path, *, remove: Path | None = None
) -> None:
    """Fill each ``buffers[name]`` from ``directory / name`` (``ReplayBuffer.loads``) where
    that was saved, once every one of them holds data only
    (:func:`~wcsac_rl.training.safe_load.check_buffer_files`: TorchRL unpickles some of
    a saved buffer's files). A refusal (one line) says to delete ``remove`` (default: the
    buffer's own directory) and loads nothing."""
    if remove is not None and Path(remove) == Path(directory):  # a buffers-<frames>/ of its own
        for path in sorted(Path(directory).iterdir()):
            if path.name not in buffers or not path.is_dir() or path.is_symlink():
                raise ConfigError(
                    f"cannot load the replay buffer saved with {checkpoint}: {path} is not one "
                    f"of its buffers ({', '.join(sorted(buffers))}); nothing of it was loaded "
                    f"or executed; delete {remove} to resume without it (the buffer is then "
                    "refilled)"
                )
    saved = {name: directory / name for name in buffers if (directory / name).is_dir()}
    for path in saved.values():
        check_buffer_files(path, checkpoint, remove=path if remove is None else remove)
    for name, path in saved.items():
        buffers[name].loads(path)


def remove_unreferenced_buffers(checkpoint_dir: Path, keep: str | None) -> None:
    """Delete saved buffers no checkpoint names any more (older ``buffers-*``, temporary
    leftovers of an interrupted save, and the pre-manifest ``replay_buffer/``)."""
    if not checkpoint_dir.is_dir():
        return
    for path in checkpoint_dir.iterdir():
        stale = path.name.startswith((BUFFERS_PREFIX, f".tmp-{BUFFERS_PREFIX}"))
        stale = stale or path.name in (REPLAY_BUFFER_DIR, INITIAL_STATE_BUFFER_DIR)
        if path.is_dir() and stale and path.name != keep:
            shutil.rmtree(path, ignore_errors=True)


def keep_checkpoint(checkpoint: Path, frames: int) -> Path:
    """Copy ``checkpoint`` to ``frames-<frames>.pt`` beside it (atomically), for
    figures of the policy during training; returns the copy's path. The copy names
    the same saved buffers, which later checkpoints replace: it restores a policy, and
    resumed from, refills the replay buffer."""
    kept = checkpoint.with_name(f"{KEPT_PREFIX}{int(frames)}.pt")
    try:
        with DeferredSignals(), checkpoint.open("rb") as source:
            replace_file(kept, lambda f: shutil.copyfileobj(source, f))
    except Exception as err:
        raise TrainingError(
            f"cannot keep checkpoint {kept}: {write_error_reason(err, kept.parent)} "
            "(keep_checkpoints_at); checkpoints/last.pt is unaffected"
        ) from None
    fsync_directory(kept.parent)
    return kept


def kept_checkpoints(run_dir: str | os.PathLike) -> list[tuple[int, Path]]:
    """``(frames, path)`` of a run's kept checkpoints (``keep_checkpoints_at``), by frames."""
    directory = Path(run_dir) / CHECKPOINT_DIR
    if not directory.is_dir():
        return []
    kept = []
    for path in directory.glob(f"{KEPT_PREFIX}*.pt"):
        digits = path.stem[len(KEPT_PREFIX) :]
        if digits.isdigit():
            kept.append((int(digits), path))
    return sorted(kept)


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
    """Load a checkpoint written by :func:`save_checkpoint` (on CPU), as data only; one
    ``ConfigError`` line for a file that cannot be read or lacks the ``required`` entries.
    """
    return read_checkpoint(path, required=required)[0]


def read_checkpoint(
    path: Path, *, required: tuple[str, ...] = REQUIRED_ENTRIES
) -> tuple[dict[str, Any], str]:
    """:func:`load_checkpoint`, and the SHA-256 of the very bytes it loaded (what an
    evaluation records to know later whether the run's checkpoint has changed), read as
    data only (:func:`~wcsac_rl.training.safe_load.load_data`).
    """
    try:
        check_size(Path(path), MAX_CHECKPOINT_BYTES, "checkpoint")
        data = Path(path).read_bytes()
    except OSError as err:
        raise ConfigError(f"cannot read checkpoint {path}: {first_line(err)}") from None
    except UnreadableRecord as err:
        raise ConfigError(str(err)) from None
    state = load_data(data, path)  # data only: nothing in the file runs
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
    _check_entries(state, path)
    return state, hashlib.sha256(data).hexdigest()


def _check_entries(state: dict[str, Any], path: Path) -> None:
    """The entries every reader uses have the types :meth:`Trainer.state_dict` writes (a
    crafted file's ``config: 5`` or ``frames: "abc"`` is one line, not a traceback)."""
    if "config" in state:
        stored_config(state["config"], path)  # a mapping of resolved values
        for section in ("algo", "env"):  # what every reader selects by name
            if not isinstance(state["config"].get(section), dict):
                raise ConfigError(
                    f"{path}: its config's '{section}' entry must be a mapping of settings, "
                    f"got {state['config'].get(section)!r}; pass a checkpoint written by train.py"
                )
    frames = state.get("frames", 0)
    if not _count(frames):
        raise ConfigError(
            f"{path}: its 'frames' entry must be a whole number >= 0, got {frames!r}; "
            "pass a checkpoint written by train.py"
        )
    if "learner" in state and not isinstance(state["learner"], dict):
        raise ConfigError(
            f"{path}: its 'learner' entry must hold the networks' states, got "
            f"{type(state['learner']).__name__}; pass a checkpoint written by train.py"
        )


def _count(value: Any) -> bool:
    """A whole number >= 0 (not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _finite(value: Any) -> bool:
    """A finite number (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and np.isfinite(value)


def _all(test: Callable[[Any], bool]) -> Callable[[Any], bool]:
    return lambda value: isinstance(value, list) and all(map(test, value))


COUNT = "a whole number >= 0"
FITS = {
    COUNT: _count,
    "a finite number": _finite,
    "a list of numbers": _all(_finite),
    "a list of counts": _all(_count),
}
"""What a counter of a checkpoint must be, as the refusal says it, and its test."""

COUNTERS = ("updates", "skipped_updates", "epoch")
"""A checkpoint's whole-number counters besides ``frames`` (which every reader checks:
:func:`_check_entries`)."""

EPOCH_PROGRESS = {
    "start_frames": COUNT, "start_updates": COUNT, "failures": COUNT,
    "skipped_updates": COUNT, "seconds": "a finite number", "returns": "a list of numbers",
    "costs": "a list of numbers", "lengths": "a list of counts",
}  # fmt: skip
"""The entries of a checkpoint's ``epoch_progress`` (the epoch in progress): what each is."""


def check_counters(state: dict[str, Any], path: Path) -> None:
    """The counters a resume continues from are what the trainer writes: whole numbers
    >= 0 (frames, updates, epochs, the training-safety counts), finite numbers (the epoch
    in progress's episode returns and costs), each count no larger than what contains it.
    One :class:`~wcsac_rl.training.ConfigError` line naming the entry."""
    from wcsac_rl.training.training_safety import TrainingSafety

    def refuse(entry: str, value: Any, what: str) -> None:
        raise ConfigError(
            f"checkpoint {path}: its {entry} must be {what}, got {value!r:.80}; the file was "
            "changed after train.py wrote it: resume from a checkpoint of the run"
        )

    for key in COUNTERS:
        if key in state and not _count(state[key]):
            refuse(f"'{key}' entry", state[key], COUNT)
    progress = state.get("epoch_progress") or {}
    for key, what in EPOCH_PROGRESS.items():
        if key in progress and not FITS[what](progress[key]):
            refuse(f"epoch_progress.{key}", progress[key], what)
    for key, limit in (("start_frames", "frames"), ("start_updates", "updates")):
        if key in progress and progress[key] > state.get(limit, progress[key]):
            refuse(f"epoch_progress.{key}", progress[key], f"at most its {limit!r} entry")
    safety = state.get("training_safety")
    if safety is not None:
        fields = TrainingSafety.__dataclass_fields__
        if not isinstance(safety, dict) or set(safety) != set(fields):
            refuse("'training_safety' entry", safety, f"a mapping of {', '.join(fields)}")
        for key in ("epochs", "epochs_over_limit", "epochs_over_limit_after_warmup"):
            if not _count(safety[key]):
                refuse(f"training_safety.{key}", safety[key], COUNT)
        for key, limit in (("epochs_over_limit", "epochs"),
                           ("epochs_over_limit_after_warmup", "epochs_over_limit")):  # fmt: skip
            if safety[key] > safety[limit]:
                refuse(f"training_safety.{key}", safety[key], f"at most its {limit!r}")


def checkpoint_digest(path: Path) -> str:
    """SHA-256 of a checkpoint file (see :func:`read_checkpoint`)."""
    try:
        check_size(Path(path), MAX_CHECKPOINT_BYTES, "checkpoint")
    except UnreadableRecord as err:
        raise ConfigError(str(err)) from None
    return _file_digest(Path(path))


def _select(cfg: DictConfig | dict, key: str) -> Any:
    if not isinstance(cfg, DictConfig):
        cfg = OmegaConf.create(cfg)
    value = OmegaConf.select(cfg, key, default=None)
    if isinstance(value, DictConfig):
        return OmegaConf.to_container(value, resolve=True)
    return value


def _own_config_hint(path: Path) -> str:
    """What a refusal to resume with today's config adds: the run continues with its own
    recorded configuration (``resume=<its directory>`` reads the run's config and applies
    only the command line's explicit overrides: :func:`resume_config`)."""
    run_dir = path.parent.parent if path.parent.name == "checkpoints" else path
    return f" (resume={run_dir} continues it with its own recorded configuration)"


def check_compatible(saved_config: dict, cfg: DictConfig, path: Path) -> None:
    """Refuse a checkpoint whose networks/loss were made by a different configuration,
    or whose config lacks options this kit reads (:func:`check_current`)."""
    check_current(saved_config, path)
    keys = [key for key in IDENTITY_KEYS if _select(saved_config, key) != _select(cfg, key)]
    if keys:
        diffs = [
            f"{key}: checkpoint={_select(saved_config, key)!r}, now={_select(cfg, key)!r}"
            for key in keys
        ]
        raise ConfigError(
            f"checkpoint {path} was made by another configuration ({'; '.join(diffs)}); "
            f"run with the same settings or start a new run"
            f"{_own_config_hint(path)}"
        )


RUN_CONFIG_RECORDS = ("config.yaml", ".hydra/config.yaml")
"""Where a run directory records the configuration it was started with (the trainer's
resolved ``config.yaml`` first; Hydra's composed one when the run died before writing it)."""


def run_config_record(run_dir: Path) -> tuple[Path, dict] | None:
    """The configuration ``run_dir`` records for itself, and the file it came from
    (``None``: no readable record). Read as YAML data (OmegaConf's safe loader) and
    returned as a plain container: nothing in it is resolved (Hydra's record keeps its
    ``${...}`` as written)."""
    for name in RUN_CONFIG_RECORDS:
        path = Path(run_dir) / name
        if not path.is_file() or path.is_symlink():
            continue
        try:
            record = load_yaml(path)
        except Exception:  # a damaged record says nothing: try the next one
            continue
        if isinstance(record, DictConfig):
            return path, OmegaConf.to_container(record, resolve=False)
    return None


def check_run_config(saved_config: dict, run_dir: Path, path: Path) -> None:
    """Refuse a checkpoint whose algorithm, α, env or networks (:data:`IDENTITY_KEYS`)
    differ from what the run directory records it was started with (a checkpoint copied
    under another run's directory). Keys a record cannot resolve or lacks are not compared.
    """
    found = run_config_record(run_dir)
    if found is None:
        return
    record_path, record = found
    diffs = []
    for key in IDENTITY_KEYS:
        recorded = plain_select(record, key)
        if interpolation_in(recorded) is not None:
            continue  # Hydra's record, as composed: an interpolation is never resolved here
        saved = _select(saved_config, key)
        if recorded is not None and saved is not None and recorded != saved:
            diffs.append(f"{key}: checkpoint={saved!r}, run={recorded!r}")
    if diffs:
        raise ConfigError(
            f"checkpoint {path} does not belong to the run {run_dir}: {'; '.join(diffs)} "
            f"(the run's {record_path.relative_to(run_dir)}); resume a run from its own "
            "checkpoint"
        )


def _progress_frames(run_dir: Path) -> int | None:
    """The frames of ``progress.csv``'s last whole row (``None``: no such row)."""
    from wcsac_rl.training.progress import read_progress  # (progress imports no checkpoint)

    path = Path(run_dir) / "progress.csv"
    if not path.is_file():
        return None
    try:
        frames = [f for f in read_progress(path, warn=False).get("frames", ()) if f == f]
    except (OSError, ValueError):
        return None
    return int(max(frames)) if frames else None


def run_latest_frames(run_dir: Path) -> tuple[int, str] | None:
    """How far ``run_dir`` has trained, and what says so: its ``checkpoints/last.pt``
    (when readable), else the last row of its ``progress.csv``; ``None`` when neither does."""
    last = Path(run_dir) / CHECKPOINT_DIR / LAST_CHECKPOINT
    if last.is_file():
        try:
            return int(load_checkpoint(last)["frames"]), f"{CHECKPOINT_DIR}/{LAST_CHECKPOINT}"
        except ConfigError:
            pass  # damaged: the records say how far it went
    frames = _progress_frames(run_dir)
    return None if frames is None else (frames, "progress.csv")


def check_not_behind(path: Path, frames: int, run_dir: Path) -> None:
    """Refuse to resume from a checkpoint other than the run's ``last.pt`` (a kept
    ``frames-<N>.pt``) when the run has trained further: continuing from it would write
    over ``last.pt`` and cut ``progress.csv`` back, losing the later progress."""
    last = Path(run_dir) / CHECKPOINT_DIR / LAST_CHECKPOINT
    if Path(path).resolve() == last.resolve():
        return
    latest = run_latest_frames(run_dir)
    if latest is None or latest[0] <= int(frames):
        return
    raise ConfigError(
        f"checkpoint {path} is at {int(frames)} frames but the run {run_dir} has trained to "
        f"{latest[0]} frames ({latest[1]}); resuming from it would overwrite that progress. "
        f"Resume the latest with resume={run_dir} (starting a new run from a kept checkpoint "
        "is not supported)"
    )


RESUME_CHANGEABLE = (
    "resume",
    "total_frames",
    "logger",
    "progress_bar",
    "threads",
    "device",
    "retain_freed_memory",
    "compile",
    "cudagraphs",
    "replay_draw",
    "checkpoint_every_epochs",
    "keep_checkpoints_at",
    "save_replay_buffer",
    "eval_episodes",
    "max_nonfinite_updates",
    "algo.lr",
    "algo.actor_lr",
    "algo.kappa_lr_scale",
    TRUST_KEY,
)
"""What a resumed session may change (a key or a whole config group): extending the
run, where and how it logs, how the process runs, and the learning rates (Adam's
moments come from the checkpoint, the rates from the config). Everything else is the
run's and stays as it was configured."""

CONFIG_GROUPS = {"algo": "name", "env": "name", "logger": "backend"}
"""Config groups (``conf/<group>/``) and the entry that names the chosen option."""


def _leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for key, value in node.items():
            out.update(_leaves(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: node}


def _changeable(key: str) -> bool:
    return any(key == k or key.startswith(k + ".") for k in RESUME_CHANGEABLE)


def check_resume_changes(saved_config: dict, cfg: DictConfig, path: Path) -> None:
    """Refuse a resumed session whose config differs from the run's in a key that is not
    :data:`RESUME_CHANGEABLE` (a run's config has every key this kit reads:
    :func:`check_current`)."""
    saved = _leaves(
        saved_config
        if isinstance(saved_config, dict)
        else OmegaConf.to_container(saved_config, resolve=True)
    )
    now = _leaves(OmegaConf.to_container(cfg, resolve=True))
    keys = [
        key
        for key, value in now.items()
        if key in saved and saved[key] != value and not _changeable(key)
    ]
    if keys:
        diffs = [f"{key}: run={saved[key]!r}, now={now[key]!r}" for key in keys]
        raise ConfigError(
            f"resume continues {path.parent.parent} as it was configured, and "
            f"{'; '.join(diffs)} cannot change on resume (these can: "
            f"{', '.join(RESUME_CHANGEABLE[1:])}); start a new run to change the "
            f"others{_own_config_hint(path)}"
        )


RUN_OF_ANOTHER_COMMIT = 'docs/reproduce.md, "A run of another commit"'
"""Where the command that continues a run of another commit's kit is documented."""


def _recorded_commit(run_dir: Path) -> str | None:
    """The commit the run's first session recorded (``provenance.json``), if a commit id."""
    from wcsac_rl.training.provenance import read_provenance

    records = read_provenance(run_dir)
    code = records[0].get("code") if records else None
    commit = code.get("commit") if isinstance(code, dict) else None
    if isinstance(commit, str) and 7 <= len(commit) <= 40:
        if all(c in "0123456789abcdef" for c in commit):
            return commit
    return None


def check_current(cfg: Any, source: Path) -> None:
    """Refuse, in one line, a stored config (a checkpoint's, a run's ``config.yaml``)
    that lacks options today's kit reads: it was written by another commit's kit, which
    the line names (the run's ``provenance.json``), with the command that continues it
    there. A run's config is its whole configuration; nothing fills in what it lacks."""
    from wcsac_rl.training.config_keys import missing_keys

    missing = missing_keys(cfg)
    if not missing:
        return
    source = Path(source)
    run_dir = source.parent.parent if source.parent.name == CHECKPOINT_DIR else source.parent
    more = f" and {len(missing) - 1} more option(s)" if len(missing) > 1 else ""
    commit = _recorded_commit(run_dir)
    if commit is None:
        where = "by a commit it does not record (no provenance.json): find it in its study's page"
        command = "git worktree add ../wcsac-<commit> <commit>"
    else:
        where, short = f"by commit {commit[:12]}", commit[:12]
        command = f"git worktree add ../wcsac-{short} {short}"
    raise ConfigError(
        f"{run_dir} was written {where}, and its config lacks {missing[0]}{more} that this "
        f"kit reads; continue it with that commit's kit: {command} ({RUN_OF_ANOTHER_COMMIT})"
    )


def resume_config(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """The config a resumed session runs with: the run's own (from its checkpoint), with only
    the command line's explicit ``overrides`` taken from ``cfg`` (Hydra's composed config;
    a group override naming the run's own option changes nothing). Whether a changed key
    may change is checked by the trainer (:func:`check_resume_changes`).
    """
    from hydra.core.override_parser.overrides_parser import OverridesParser

    path = find_checkpoint(cfg.resume)
    run = stored_config(load_checkpoint(path)["config"], path)  # nothing in it resolved
    check_current(run, path)
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    given = {override.key_or_group for override in parsed}
    trusted = OmegaConf.select(cfg, TRUST_KEY, default=False) is True  # this command's word
    check_env_code(
        run,
        path,
        trusted=trusted,
        given_id=OmegaConf.select(cfg, "env.id") if "env.id" in given else None,
        allow=(
            f"add {TRUST_KEY}=true to the command line (or name the same env=gymnasium "
            f"env.id={plain_select(run, 'env.id')} on it)"
        ),
    )
    run[TRUST_KEY] = trusted  # (the run's own value is not this command's word)
    for override in parsed:
        key = override.key_or_group
        if key == "hydra" or key.startswith("hydra.") or key == "resume":
            continue
        if override.is_delete():
            raise ConfigError(f"~{key}: nothing can be removed from a run's config on resume")
        if key in ("experiment", "row"):
            raise ConfigError(
                f"{key}=... cannot be given on resume: the run keeps its own configuration"
            )
        value = OmegaConf.select(cfg, key)
        if key in CONFIG_GROUPS:
            entry = f"{key}.{CONFIG_GROUPS[key]}"
            if OmegaConf.select(run, entry) == OmegaConf.select(cfg, entry):
                continue  # the run's own option: keep its (possibly overridden) values
        if isinstance(value, DictConfig):
            value = OmegaConf.to_container(value, resolve=True)
        OmegaConf.update(run, key, value, merge=False, force_add=True)
    run.resume = str(cfg.resume)
    return run


class StateMismatch(ConfigError):
    """A checkpoint's saved networks do not fit the networks its config builds."""


def _shape(value: Any) -> str:
    return str(list(value.shape)) if isinstance(value, torch.Tensor) else type(value).__name__


CONFIG_DERIVED = ("alpha_init", "cost_threshold", "_target_entropy", "_value_estimator.gamma")
"""A loss's state entries made from its config (β's start, the constraint's threshold from
the cost limit, the target entropy, γ), which cannot change on resume: a checkpoint's
must equal what the config gives."""


def load_module_state(module: torch.nn.Module, state: Any, what: str = "loss") -> None:
    """``module.load_state_dict(state)``, or one :class:`StateMismatch` line naming the
    first entry whose shape differs (networks of another width or depth than the config
    says), or the missing / unexpected entries. Nothing is loaded when it raises."""
    if not isinstance(state, dict):
        raise StateMismatch(f"its learner state has no {what!r} networks (got {_shape(state)})")
    expected = module.state_dict()
    for key, value in expected.items():
        saved = state.get(key)
        if saved is not None and (
            not isinstance(saved, torch.Tensor) or saved.shape != value.shape
        ):
            raise StateMismatch(
                f"its networks do not fit its config: {key} is {_shape(saved)} in the "
                f"checkpoint, {_shape(value)} as configured"
            )
    weights = [key for key, _ in module.named_parameters()]
    weights += [key for key, _ in module.named_buffers() if "params" in key]  # (targets)
    for key in weights:
        saved = state.get(key)
        if isinstance(saved, torch.Tensor) and saved.is_floating_point():
            bad = ~torch.isfinite(saved)
            if bool(bad.any()):
                raise StateMismatch(
                    f"its networks hold non-finite weights: {key} has {int(bad.sum())} NaN "
                    f"or infinite value(s) of {saved.numel()}; a policy or critic with them "
                    "acts and learns on NaN (resume from an earlier checkpoint, or start over)"
                )
    for key in CONFIG_DERIVED:
        saved, now = state.get(key), expected.get(key)
        if isinstance(saved, torch.Tensor) and now is not None and not torch.equal(saved, now):
            raise StateMismatch(
                f"its {key} is {saved.tolist()}, but its config gives {now.tolist()}: a "
                "checkpoint whose state disagrees with its run's config (edited or damaged) "
                "is not resumed"
            )
    try:
        module.load_state_dict(state)
    except (RuntimeError, ValueError, KeyError, TypeError) as err:
        lines = [line.strip() for line in str(err).splitlines() if line.strip()]
        detail = lines[1] if len(lines) > 1 and lines[0].startswith("Error(s)") else lines[0]
        raise StateMismatch(f"its networks do not fit its config: {detail[:300]}") from None


def load_optimizer_state(optimizer: torch.optim.Optimizer, state: dict[str, Any]) -> None:
    """Restore an optimizer's moments and step counts but keep its configured learning rates.

    ``Optimizer.load_state_dict`` also brings back the saved ``lr``, which would make a
    learning rate changed on resume silently ignored.
    """
    for index, moments in (state.get("state") or {}).items() if isinstance(state, dict) else ():
        for name, value in moments.items() if isinstance(moments, dict) else ():
            if isinstance(value, torch.Tensor) and value.is_floating_point():
                if not bool(torch.isfinite(value).all()):
                    raise StateMismatch(
                        f"its optimizer state holds non-finite values ({name} of parameter "
                        f"{index}): its next step would make the networks NaN (resume from "
                        "an earlier checkpoint, or start over)"
                    )
    lrs = [group["lr"] for group in optimizer.param_groups]
    optimizer.load_state_dict(state)
    for group, lr in zip(optimizer.param_groups, lrs):
        group["lr"] = lr
