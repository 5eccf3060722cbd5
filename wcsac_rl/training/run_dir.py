"""A run directory: one run at a time (:class:`RunLock`), new runs only in empty directories,
records that never run ahead of the checkpoint they are resumed from
(:func:`cut_records_to`), and every record written whole (:func:`replace_file`).

The rules: docs/guarantees.md ("A run directory has one owner", "A refused command
changes nothing that existed before it").
"""

from __future__ import annotations

import csv
import io
import os
import shutil
import socket
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

from wcsac_rl.training.config import ConfigError
from wcsac_rl.training.preemption import DeferredSignals

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no locks
    fcntl = None

__all__ = [
    "AUTO_RESUME",
    "LOCK_FILE",
    "RunInUseError",
    "RunLock",
    "check_auto_resume_dir",
    "check_new_run_dir",
    "check_own_files",
    "check_progress_rows",
    "check_restartable_run_dir",
    "cut_records_to",
    "discard_unused_run_dir",
    "lock_holder",
    "own_copies",
    "remove_entry",
    "replace_file",
    "replace_files",
    "replace_text",
    "unwritable_reason",
]

AUTO_RESUME = "auto"
"""``resume=auto``: continue the run directory's checkpoint if it has one, else start."""
LOCK_FILE = ".lock"
RUN_ENTRIES = (
    "config.yaml",
    "provenance.json",
    "progress.csv",
    "logs",
    "checkpoints",
    "curves.png",
)
"""What a run writes into its directory before (or without) a checkpoint."""
HYDRA_ENTRIES = (".hydra",)
"""What Hydra writes into a run directory before the trainer starts (and ``*.log``)."""
HYDRA_STAGING = ".hydra-pending-"
"""``wcsac-train`` has Hydra write a command's records to ``.hydra-pending-<pid>/``
(``hydra.output_subdir``): they become ``.hydra/`` once the run is accepted, and are
removed when it is refused (another run's records are never written over)."""


def _is_pre_run_entry(path: Path) -> bool:
    """Hydra's files, or the lock file: what a run directory holds before a run writes."""
    return (
        path.name in (*HYDRA_ENTRIES, LOCK_FILE)
        or path.name.startswith(HYDRA_STAGING)
        or (path.is_file() and path.suffix == ".log")
    )


def _shown(names: list[str]) -> str:
    return ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")


def _is_resumed_session_record(path: Path) -> bool:
    """``config.resume<k>.yaml`` / ``provenance.resume<k>.json`` of a resumed session."""
    return (path.name.startswith("config.resume") and path.suffix == ".yaml") or (
        path.name.startswith("provenance.resume") and path.suffix == ".json"
    )


LOCK_ATTEMPTS = 3
LOCK_RETRY_S = 0.1


def lock_holder(run_dir: Path) -> str | None:
    """Who holds ``run_dir``'s lock (``"host h, pid N"``), or ``None`` when no live process
    does (no lock file, a stale one, or no ``fcntl``). Never waits: the probe takes a shared
    lock for an instant (a run starting then retries, :class:`RunLock`); across nodes it
    sees a run where the shared filesystem forwards ``flock`` locks (NFS does).
    """
    if fcntl is None:  # pragma: no cover - not POSIX
        return None
    try:
        fd = os.open(Path(run_dir) / LOCK_FILE, os.O_RDONLY)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return os.pread(fd, 200, 0).decode(errors="replace").strip() or "unknown"
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


class RunInUseError(ConfigError):
    """Another live process holds the run directory's lock: this process owns nothing in
    it and must remove nothing there but what it alone made (its own staged records)."""


class RunLock:
    """Hold ``<run dir>/.lock`` exclusively until :meth:`release` (or the process ends: the
    OS drops the lock however it ends, so a lock file left by a dead process is free again;
    the file holds the owner's host and pid for the message the second run prints).

    Raises :class:`RunInUseError` (one line, naming the holder) when another live process
    holds it (tried :data:`LOCK_ATTEMPTS` times, :data:`LOCK_RETRY_S` apart). Where
    ``fcntl`` does not exist (Windows) the lock is a no-op.
    """

    def __init__(self, run_dir: Path) -> None:
        self.path = Path(run_dir) / LOCK_FILE
        self._fd: int | None = None
        if fcntl is None:  # pragma: no cover - not POSIX
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:  # read-only, not ours, not a directory
            raise ConfigError(
                f"cannot write to the run directory {self.path.parent}: "
                f"{err.strerror or err}; a run (or a resume) writes its records and "
                "checkpoints there: choose a directory you can write"
            ) from None
        for attempt in range(LOCK_ATTEMPTS):
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except OSError:
                if attempt + 1 < LOCK_ATTEMPTS:  # (lock_holder's probe holds it briefly)
                    time.sleep(LOCK_RETRY_S)
        else:
            holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise RunInUseError(
                f"{self.path.parent} is in use by another run ({holder}); wait for it to "
                "finish or choose another directory"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"host {socket.gethostname()}, pid {os.getpid()}\n".encode(), 0)
        self._fd = fd

    @property
    def held(self) -> bool:
        return self._fd is not None

    def release(self) -> None:
        """Give the lock up (the file stays: an unlocked file is a free directory)."""
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor releases the flock
            self._fd = None


def unwritable_reason(directory: str | os.PathLike) -> str | None:
    """Why ``directory`` (created if missing) cannot be written, or ``None`` if it can:
    its nearest existing ancestor must be a directory in which a file can be created
    (tried with a temporary file, removed at once: this holds for root on a read-only
    file system too, where permission bits do not)."""
    path = Path(directory).expanduser().absolute()
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a directory"
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as err:
        return f"{existing}: {err.strerror or err}"
    return None


def discard_unused_run_dir(
    run_dir: Path,
    *,
    existed: frozenset[str] | None = None,
    since: float | None = None,
    created: bool = False,
) -> bool:
    """Undo what a refused command wrote into ``run_dir``: only what it created itself
    (Hydra's staged records, an empty job log, the lock file; the directory where
    ``created``), and nothing while another live process holds the directory's lock.
    ``existed``: the entries before the command (``None``: not known, then the directory is
    removed only if it holds nothing else, a log in it empty and newer than ``since``).
    Returns whether the directory was removed.
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir() or run_dir.is_symlink():
        return False
    if lock_holder(run_dir) is not None:  # a live process owns it: nothing here is ours
        return False
    if created:
        shutil.rmtree(run_dir, ignore_errors=True)
        return True

    def made_here(path: Path) -> bool:
        if existed is not None and path.name in existed:
            return False
        if path.name.startswith(HYDRA_STAGING):
            return path.is_dir() and not path.is_symlink()
        if path.is_symlink() or not path.is_file():
            return False
        if path.name == LOCK_FILE:
            return True
        stat = path.stat()  # Hydra's job log, opened (and so created) before the job
        new = since is None or stat.st_ctime >= since - 1  # (coarse file clocks)
        return path.suffix == ".log" and stat.st_size == 0 and new

    entries = list(run_dir.iterdir())
    ours = [p for p in entries if made_here(p)]
    if existed is None:  # (not known to have existed: all of it, or nothing)
        if len(ours) < len(entries):
            return False
        shutil.rmtree(run_dir, ignore_errors=True)
        return True
    for path in ours:
        remove_entry(path)
    return False


def remove_entry(path: Path) -> None:
    """Remove ``path``: a directory with what it holds, anything else (a link) itself."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def check_new_run_dir(run_dir: Path) -> None:
    """Refuse a new run in a directory that already holds files of a run (or anything else)."""
    run_dir = Path(run_dir)
    if not run_dir.exists():
        return
    entries = sorted(p.name for p in run_dir.iterdir() if not _is_pre_run_entry(p))
    if entries:
        shown = _shown(entries)
        has_checkpoint = (run_dir / "checkpoints" / "last.pt").is_file()
        fix = (
            f"continue it with resume={run_dir} or choose another directory"
            if has_checkpoint
            else "a new run needs an empty directory: choose another one"
        )
        # a sweep job that was requeued (SLURM) or retried (Ray), or a sweep run again
        sweep = (
            "; a sweep job run again (a requeued or retried job, the same sweep command) "
            "continues its own directory only with resume=auto: run the sweep with resume=auto"
        )
        raise ConfigError(f"{run_dir} already holds a run ({shown}); {fix}{sweep}")


def check_auto_resume_dir(hydra_cfg: object) -> None:
    """resume=auto continues the run in the directory the command names: refused (one
    line) where ``hydra_cfg`` (Hydra's config of the job) makes that directory a new
    timestamped one each time (Hydra's default)."""
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    key = "sweep" if hydra_cfg.mode == RunMode.MULTIRUN else "run"
    template = str(OmegaConf.to_container(hydra_cfg[key], resolve=False)["dir"])
    if "${now:" in template:
        raise ConfigError(
            f"resume=auto continues the run in the directory the command names, but "
            f"hydra.{key}.dir is a new timestamped one each time ({template}): nothing "
            f"can be continued there; name it (hydra.{key}.dir=outputs/my_run resume=auto) "
            "or continue a run by its path (resume=outputs/<date>/<time>_<name>)"
        )


def check_restartable_run_dir(run_dir: Path) -> None:
    """``resume=auto`` without a checkpoint: start the run over in ``run_dir``, which may
    hold what a session killed before its first checkpoint wrote (its records are cut);
    anything else is refused, as for a new run.
    """
    run_dir = Path(run_dir)
    if not run_dir.exists():
        return
    others = sorted(
        p.name
        for p in run_dir.iterdir()
        if not (_is_pre_run_entry(p) or p.name in RUN_ENTRIES or _is_resumed_session_record(p))
    )
    if others:
        raise ConfigError(
            f"{run_dir} has no checkpoint to continue and holds files that are not a run's "
            f"({_shown(others)}); resume=auto starts a run only in an empty directory or one "
            "a killed run left before its first checkpoint: choose another directory"
        )
    dropped = cut_records_to(run_dir, epoch=0, frames=0)
    if dropped:
        print(
            f"{run_dir}: no checkpoint to continue; starting the run over (dropped "
            f"{dropped} progress.csv row(s) of a session that ended before its first checkpoint)"
        )


def _run_entries(run_dir: Path) -> list[Path]:
    """A run's entries: everything below it (but wandb's own folder, which links its
    latest run), links not followed."""
    paths = []
    for parent, dirs, files in os.walk(run_dir, followlinks=False):
        dirs[:] = [d for d in dirs if d != "wandb"]
        paths += [Path(parent) / name for name in [*dirs, *files]]
    return sorted(paths)


def own_copies(run_dir: Path) -> list[Path]:
    """Give every file of the run that is shared with another path (a hard link: ``cp
    -al RUN COPY``) a copy of its own, written beside it and renamed over it, so that
    what a resume appends or writes never reaches the other run. Call it holding the
    run's lock (:class:`RunLock`). Returns the files copied."""
    copied = []
    for path in _run_entries(Path(run_dir)):
        if path.is_symlink() or not path.is_file() or path.stat().st_nlink < 2:
            continue
        private = path.with_name(f".{path.name}.own")
        shutil.copy2(path, private)
        os.replace(private, path)
        copied.append(path)
    return copied


def check_own_files(run_dir: Path) -> None:
    """Refuse (one line) to continue a run one of whose entries is a symbolic link: a
    resume appends to ``progress.csv`` and the logger's files and writes over its
    checkpoints, and through a link it would write outside the run."""
    run_dir = Path(run_dir)
    for path in _run_entries(run_dir):
        if path.is_symlink():
            raise ConfigError(
                f"{path} is a symbolic link (to {os.readlink(path)}); a resume writes into "
                f"the run's own files only: replace it with the file itself to continue "
                f"{run_dir}"
            )


def check_progress_rows(run_dir: Path, epoch: int | None = None) -> None:
    """Refuse (one line naming the epoch) a run whose ``progress.csv`` rows (up to the
    checkpoint's ``epoch``; ``None``: all of them) are not epochs 1, 2, ... once each
    and in order: a resume would keep a duplicated or missing row in its records, and a
    report would read its frames and time from it."""
    path = Path(run_dir) / "progress.csv"
    if not path.is_file():
        return
    header, rows = _read_csv(path)
    if not header:
        return
    if "epoch" not in header:  # (a resume would append its rows under another header)
        raise ConfigError(
            f"{path}: its header has no 'epoch' column (got {', '.join(header)}); it is not "
            "the run's progress log: restore the run's own progress.csv"
        )
    col = header.index("epoch")
    expected = 1
    for number, row in enumerate(rows, start=2):  # (line numbers: the header is line 1)
        if len(row) != len(header):
            continue  # a row cut short by a kill: dropped on resume
        value = _number(row[col])
        if value is None or (epoch is not None and value > epoch):
            continue
        if value != expected:
            what = "again" if value < expected else f"where epoch {expected} belongs"
            upto = "" if epoch is None else f" up to the checkpoint's epoch {epoch}"
            raise ConfigError(
                f"{path}: line {number} logs epoch {value:g} {what} (its rows{upto} must be "
                "epochs 1, 2, ... once each, in order): restore the run's own progress.csv"
            )
        expected += 1


def replace_file(path: str | os.PathLike, data: str | bytes | Callable[[BinaryIO], object]) -> Path:
    """Write ``data`` (text as UTF-8, or a function that writes into the open file) to
    ``path`` as a new file renamed into place, the one way the kit writes a record or a
    checkpoint: a link at ``path`` (symbolic, or a hard link shared with another run) is
    replaced, never written through; the temporary file beside it is created exclusively,
    never follows a link, is flushed to disk before the rename and is removed again if
    anything fails (a full disk, a stop)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
    # a leftover of a process killed mid-write whose pid this one has again (a
    # container's processes start at the same pids): removed, a link itself not its target
    tmp.unlink(missing_ok=True)
    try:
        with os.fdopen(os.open(tmp, flags, 0o644), "wb") as f:
            if callable(data):
                data(f)
            else:
                f.write(data.encode("utf-8") if isinstance(data, str) else bytes(data))
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def replace_files(files: dict[Path, str | bytes]) -> list[Path]:
    """Write ``files`` (path → content) together: each is written whole beside its place
    (:func:`replace_file`, ``.<name>.<pid>.new``) and only then are they renamed into
    place, so a failure (a full disk, a read-only file system, a stop) before the renames
    leaves the previous files as they were and none of its own. An ``OSError`` is
    re-raised with ``filename`` the file it was writing."""
    staged = {
        Path(path): Path(path).with_name(f".{Path(path).name}.{os.getpid()}.new") for path in files
    }
    current = next(iter(staged), None)
    try:
        for current, data in zip(staged, files.values(), strict=True):
            replace_file(staged[current], data)
        for current in staged:
            os.replace(staged[current], current)
    except OSError as err:
        raise OSError(err.errno, err.strerror or str(err), str(current)) from None
    finally:
        for new in staged.values():
            new.unlink(missing_ok=True)
    return list(staged)


def replace_text(path: Path, text: str) -> None:
    """:func:`replace_file`, a stop signal waiting until the file is in place."""
    with DeferredSignals():
        replace_file(path, text)


def _number(text: str | None) -> float | None:
    try:
        return float(text) if text not in (None, "") else None
    except ValueError:
        return None


def _read_csv(path: Path) -> tuple[list[str] | None, list[list[str]]]:
    """A CSV file's header (``None``: an empty file) and its rows."""
    with path.open(newline="") as f:
        reader = csv.reader(f)
        return next(reader, None), list(reader)


def _cut_progress(path: Path, epoch: int) -> int:
    """Keep the rows of ``progress.csv`` up to ``epoch``; returns how many were dropped."""
    header, rows = _read_csv(path)
    if header is None:
        return 0
    col = header.index("epoch") if "epoch" in header else None
    kept = [
        row
        for row in rows
        if col is not None
        and len(row) == len(header)  # a row cut short by a kill is dropped too
        and (e := _number(row[col])) is not None
        and e <= epoch
    ]
    if len(kept) == len(rows):
        return 0
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(header)
    writer.writerows(kept)
    replace_text(path, buf.getvalue())
    return len(rows) - len(kept)


def _cut_scalar_file(path: Path, frames: int) -> int:
    """TorchRL's CSV logger writes ``step,value`` lines; keep those with step ≤ ``frames``."""
    lines = path.read_text().splitlines(keepends=True)
    kept = []
    for line in lines:
        step, sep, _ = line.partition(",")
        value = _number(step)
        if sep and line.endswith("\n") and value is not None and value <= frames:
            kept.append(line)
    if len(kept) == len(lines):
        return 0
    replace_text(path, "".join(kept))
    return len(lines) - len(kept)


def cut_records_to(run_dir: Path, *, epoch: int, frames: int) -> int:
    """Cut the run's records back to a checkpoint taken after ``epoch`` (at ``frames``).

    ``progress.csv`` keeps its rows up to ``epoch``, the CSV logger's files under
    ``logs/`` their lines up to step ``frames``. Returns the number of rows dropped
    from ``progress.csv``.
    """
    run_dir = Path(run_dir)
    dropped = 0
    progress = run_dir / "progress.csv"
    if progress.is_file():
        dropped = _cut_progress(progress, epoch)
    logs = run_dir / "logs"
    if logs.is_dir():
        for scalars in logs.rglob("scalars"):
            for path in scalars.rglob("*.csv"):
                _cut_scalar_file(path, frames)
    return dropped
