"""A run's records beside its directory: the console's lines kept in ``train.log``,
Hydra's records of a command staged until the command's run is accepted (an existing
run's ``.hydra/`` is written only then: :func:`stage_command`, :class:`HydraJob`), and
what a refused or stopped command made removed again (only what it made).
``wcsac_rl.train`` uses these around a run."""

from __future__ import annotations

import datetime
import logging
import os
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

from wcsac_rl.training.run_dir import (
    HYDRA_STAGING,
    LOCK_FILE,
    discard_unused_run_dir,
    remove_entry,
)

if TYPE_CHECKING:
    from wcsac_rl.training.trainer import Trainer

__all__ = [
    "BEFORE",
    "DEFAULT_ROOTS",
    "LOG_FILE",
    "ConsoleLog",
    "HydraJob",
    "default_run_dir",
    "discard",
    "discard_refused",
    "discard_staged",
    "discard_stopped",
    "entries_before",
    "stage_command",
]


LOG_FILE = "train.log"
"""The console's lines of a run, in its run directory."""


class ConsoleLog:
    """Copy what is written to ``sys.stdout`` / ``sys.stderr`` into a run's ``train.log``.

    Until :meth:`attach` names the file, lines are held in memory (a command refused
    before its run directory is kept writes no file). A progress bar redraws its line
    with carriage returns; the log keeps each line's last state.
    """

    def __init__(self) -> None:
        self._streams: list[tuple[str, TextIO]] = []
        self._pending: list[str] = []  # complete lines before attach()
        self._partial: dict[str, str] = {}  # per stream: the line being written
        self._file: TextIO | None = None
        self._handlers: list[tuple[logging.StreamHandler, Any]] = []
        self.closed = False

    def __enter__(self) -> ConsoleLog:
        tees = {}
        for name in ("stdout", "stderr"):
            stream = getattr(sys, name)
            tees[id(stream)] = tee = _Tee(stream, self, name)
            self._streams.append((name, stream))
            setattr(sys, name, tee)
        # libraries' log handlers that print to the console (TorchRL's), but not the root
        # logger's: Hydra's own handlers, one of which already writes train.log
        self._handlers = []
        for logger in list(logging.Logger.manager.loggerDict.values()):
            for handler in getattr(logger, "handlers", ()):
                stream = getattr(handler, "stream", None)
                if isinstance(handler, logging.StreamHandler) and id(stream) in tees:
                    self._handlers.append((handler, handler.setStream(tees[id(stream)])))
        return self

    def __exit__(self, *exc: object) -> None:
        for handler, stream in self._handlers:
            handler.setStream(stream)
        for name, stream in reversed(self._streams):
            setattr(sys, name, stream)
        self._streams.clear()
        self.closed = True
        for partial in self._partial.values():
            if partial.strip():
                self._line(partial.rsplit("\r", 1)[-1])
        self._partial.clear()
        if self._file is not None:
            self._file.close()
            self._file = None

    def attach(self, path: Path) -> None:
        """Append to ``path`` from now on, starting with the lines held so far."""
        if self._file is not None:
            return
        try:
            self._file = path.open("a", encoding="utf-8", errors="replace")
        except OSError:  # an unwritable run directory: the trainer says so itself
            return
        self._file.writelines(self._pending)
        self._file.flush()
        self._pending.clear()

    def write(self, text: str, stream: str = "stdout") -> None:
        """Keep ``text`` written to ``stream``: each complete line in its last state (a
        progress bar redraws its line after carriage returns)."""
        partial = self._partial.get(stream, "") + text
        while "\n" in partial:
            line, partial = partial.split("\n", 1)
            self._line(line.rsplit("\r", 1)[-1])
        self._partial[stream] = partial

    def _line(self, line: str) -> None:
        if self._file is None:
            self._pending.append(line + "\n")
        else:
            self._file.write(line + "\n")
            self._file.flush()


class _Tee:
    """A text stream that writes through to ``stream`` and to a :class:`ConsoleLog`."""

    def __init__(self, stream: TextIO, log: ConsoleLog, name: str) -> None:
        self._stream = stream
        self._log = log
        self._name = name

    def write(self, text: str) -> int:
        if not self._log.closed:
            self._log.write(text, self._name)
        return self._stream.write(text)

    def flush(self) -> None:
        self._stream.flush()

    def __getattr__(self, name: str) -> Any:  # isatty, encoding, fileno, ...
        return getattr(self._stream, name)


DEFAULT_ROOTS = ("outputs", "multirun")
"""Where Hydra puts runs by default (``conf/config.yaml``), below the current directory."""


def default_run_dir(run_name: str) -> Path:
    """``outputs/<date>/<time>_<run_name>`` below the current directory: where the command
    line's run goes by default (``hydra.run.dir`` in ``conf/config.yaml``)."""
    now = datetime.datetime.now()
    return Path("outputs") / f"{now:%Y-%m-%d}" / f"{now:%H-%M-%S}_{run_name}"


BEFORE: dict[str, Any] = {}
"""What :func:`stage_command` noted before Hydra ran: when (``since``), and the run
directory a literal ``hydra.run.dir=`` names (``dir``) with its entries then
(``existed``; ``None``: it did not exist)."""


def stage_command(argv: Sequence[str]) -> list[str]:
    """``argv`` of a command that runs a job, to hand to Hydra, so that a refusal removes
    only what the command made: what its run directory held is noted (:data:`BEFORE`),
    and Hydra's records of this command go to a staging directory
    (:data:`~wcsac_rl.training.run_dir.HYDRA_STAGING`; not when the line sets
    ``hydra.output_subdir`` itself), an existing run's ``.hydra/`` being written only once
    this command's run is accepted."""
    BEFORE.clear()
    BEFORE["since"] = time.time()
    for arg in argv:
        key, sep, value = arg.lstrip("+").partition("=")
        value = value.strip("'\"")
        if sep and key == "hydra.run.dir" and "${" not in value:  # ("": the current one)
            path = Path(os.path.abspath(Path(value or ".").expanduser()))  # (as Hydra makes it)
            BEFORE["dir"] = path
            BEFORE["existed"] = frozenset(p.name for p in path.iterdir()) if path.is_dir() else None
    if any(arg.lstrip("+").startswith("hydra.output_subdir=") for arg in argv):
        return list(argv)
    return [*argv, f"hydra.output_subdir={HYDRA_STAGING}{os.getpid()}"]


class HydraJob:
    """The directory Hydra made for this command's job (``dir``; ``hydra_cfg``: Hydra's
    config of the job), the records it staged there (``staged``) and what the directory
    held before (``entries``: :func:`entries_before`). What the command made is removed
    when it is refused (:meth:`refuse`) and kept when its run is accepted (:meth:`accept`)."""

    def __init__(self, hydra_cfg: Any) -> None:
        self.dir = Path(hydra_cfg.runtime.output_dir)
        subdir = hydra_cfg.output_subdir
        staging = subdir is not None and Path(str(subdir)).name.startswith(HYDRA_STAGING)
        self.staged = self.dir / str(subdir) if staging else None
        self.entries = entries_before(self.dir, self.staged)

    def refuse(self, *, owned: bool = True) -> None:
        """A refused command leaves nothing behind (:func:`discard`); ``owned=False``:
        another process owns the directory, so only this command's staged records go."""
        if owned:
            discard(self.dir, self.staged)
        else:
            discard_staged(self.staged)

    def accept(self, run_dir: Path) -> None:
        """The run took ``run_dir``: Hydra's staged records become its ``.hydra/``, and
        Hydra's log handlers open their file again (the run may since have given its files
        their own copies: :func:`~wcsac_rl.training.run_dir.own_copies`). A resume of
        another directory (``resume=RUN_DIR``) leaves Hydra's new one, which would stay
        behind empty: its log handlers write into the run's log, and it is removed with
        what this command put there."""
        if Path(run_dir).resolve() != self.dir.resolve():
            _reopen_logs(self.dir, into=run_dir)
            discard(self.dir, self.staged)
            return
        _reopen_logs(run_dir)
        if self.staged is not None and self.staged.is_dir():
            target = self.dir / ".hydra"
            target.mkdir(exist_ok=True)
            for path in self.staged.iterdir():
                os.replace(path, target / path.name)
            self.staged.rmdir()


def discard_staged(staged: Path | None) -> None:
    """Remove this command's own staged Hydra records (named by its pid), nothing else."""
    if staged is not None and staged.is_dir() and not staged.is_symlink():
        shutil.rmtree(staged, ignore_errors=True)


def _reopen_logs(directory: Path, into: Path | None = None) -> None:
    """Hydra's job log handlers writing into ``directory``: their file closed and
    opened again, at the same path or, with ``into``, as ``into``'s ``train.log``."""
    for handler in logging.getLogger().handlers:
        if not isinstance(handler, logging.FileHandler):
            continue
        if Path(handler.baseFilename).parent != Path(directory).absolute():
            continue
        handler.acquire()
        try:
            if handler.stream is not None:
                handler.stream.close()
                handler.stream = None  # (opened again at the next record)
            if into is not None:
                handler.baseFilename = str(Path(into).absolute() / LOG_FILE)
        finally:
            handler.release()


def discard(run_dir: Path, staged: Path | None = None) -> None:
    """Remove what a refused command made: Hydra's staged records, and its run
    directory if the command created it (with the date directory above it that Hydra
    made for it, ``outputs/<date>/``, if that is now empty); a directory that existed
    keeps everything it held (:func:`~wcsac_rl.training.run_dir.discard_unused_run_dir`)."""
    discard_staged(staged)
    noted = BEFORE.get("dir") == Path(os.path.abspath(run_dir))
    existed = BEFORE.get("existed") if noted else None
    created = noted and existed is None
    if discard_unused_run_dir(run_dir, existed=existed, since=BEFORE.get("since"), created=created):
        remove_empty_parents(run_dir)


def discard_refused(run_dir: Path, *, existed: bool, entries: frozenset[str] | None) -> None:
    """Remove what a refused :func:`~wcsac_rl.train.run_training` made: ``run_dir``
    itself where it did not exist, else only what the call made there, its lock file
    (``entries``: the names the directory held before; ``None``: it is not a directory)."""
    if not existed:
        discard(run_dir)
    elif entries is not None:
        discard_unused_run_dir(run_dir, existed=entries)


def entries_before(run_dir: Path, staged: Path | None) -> frozenset[str] | None:
    """The entries of ``run_dir`` before the run wrote anything, without what this
    command itself made there first (Hydra's staged records and its empty job log, the
    directory itself when ``hydra.run.dir`` did not exist): ``None`` when there were
    none (the run's files are all of it)."""
    if BEFORE.get("dir") == Path(os.path.abspath(run_dir)):
        return BEFORE.get("existed")
    if not run_dir.is_dir():
        return None
    names = frozenset(
        p.name
        for p in run_dir.iterdir()
        if not (p.name.startswith(HYDRA_STAGING) or (p.suffix == ".log" and _empty(p)))
    )
    return names or None


def _empty(path: Path) -> bool:
    return path.is_file() and not path.is_symlink() and path.stat().st_size == 0


def discard_stopped(trainer: Trainer, entries: frozenset[str] | None) -> str:
    """A fresh run that stopped before its first checkpoint has nothing to continue from:
    what it wrote is removed (its directory too, when only the run was in it). Returns
    what the error line adds (nothing when a checkpoint is kept: a resumed run's too)."""
    run_dir = Path(trainer.run_dir)
    if trainer.checkpoint_path.is_file() or not run_dir.is_dir():
        return ""
    if entries is None:
        shutil.rmtree(run_dir, ignore_errors=True)
        remove_empty_parents(run_dir)
        return f"; {run_dir} is removed (it held nothing to continue from)"
    for path in run_dir.iterdir():
        if path.name not in entries or path.name == LOCK_FILE:
            remove_entry(path)
    return f"; what the run wrote into {run_dir} is removed (it held nothing to continue from)"


def remove_empty_parents(run_dir: Path) -> None:
    """Hydra's date directories above a removed run (``outputs/<date>/``), once empty."""
    cwd = Path.cwd().resolve()
    parent = run_dir.resolve().parent
    while parent != cwd and parent.is_relative_to(cwd):
        relative = parent.relative_to(cwd)
        if relative.parts[0] not in DEFAULT_ROOTS:
            return
        try:
            parent.rmdir()  # only an empty directory
        except OSError:
            return
        parent = parent.parent
