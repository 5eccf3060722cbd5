"""Train WCSAC or a baseline: ``wcsac-train algo=wcsac risk_level=0.5 env=dynamic``.

The same command three ways: the installed console script ``wcsac-train``,
``python -m wcsac_rl.train`` and, in a checkout, ``python train.py`` (the card's entry
point, which calls :func:`cli`). Hydra composes ``conf/config.yaml`` (in a regular
install, the copy shipped inside the package: :mod:`wcsac_rl.config_dir`); with no
overrides this is the paper's full run. Sweeps: ``wcsac-train -m algo=wcsac
risk_level=0.1,0.5,0.9 seed=0,10,20``; your own env: ``wcsac-train env=gymnasium
env.id=my_module:make`` (docs/own_environment.md). A run stopped by ``SIGTERM`` /
``SIGUSR1`` / ``SIGUSR2`` checkpoints first and exits with 128 + the signal's number.

In a notebook (or any Python program), the same run without a command line::

    from wcsac_rl import compose_config, run_training
    cfg = compose_config("env=gymnasium", "env.id=my_module:make", "total_frames=20000")
    run_dir = run_training(cfg)          # progress.csv, checkpoints/, curves.png there

The console's lines of a run (its messages, the progress bar's final state, the paths
it prints, an error that stopped it) are kept in the run directory's ``train.log``.
This module imports only Hydra at first, so that ``--help`` answers at once.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, TextIO

import hydra
from omegaconf import DictConfig

from wcsac_rl.config_dir import CONF_DIR

if TYPE_CHECKING:
    from wcsac_rl.training.trainer import Trainer

__all__ = [
    "check_command_line",
    "check_interpolations",
    "check_override_syntax",
    "cli",
    "compose_config",
    "main",
    "run_training",
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


def _user_errors() -> tuple[type[BaseException], ...]:
    """Errors a user can cause or fix: one line (exit code 1), never a traceback."""
    from wcsac_rl.envs import NonFiniteStepError
    from wcsac_rl.training import ConfigError, TrainingError

    return (ConfigError, TrainingError, NonFiniteStepError)


def _build(cfg: DictConfig, run_dir: Path, overrides: Sequence[str] | None) -> Trainer:
    """The trainer for ``cfg`` (resume=RUN_DIR: the run's own config with only the
    explicit overrides applied; resume=auto: the composed config, checked against the
    run directory's checkpoint); an option of the command line that the chosen
    algorithm does not read is said in one warning line."""
    from wcsac_rl.training import make_trainer
    from wcsac_rl.training.applicability import warn_inapplicable
    from wcsac_rl.training.checkpoint import resume_config
    from wcsac_rl.training.run_dir import AUTO_RESUME

    overrides = list(overrides or ())
    if cfg.get("resume") == AUTO_RESUME:
        _check_auto_resume_dir()
    if cfg.get("resume") and cfg.resume != AUTO_RESUME:
        cfg = resume_config(cfg, overrides)
    warn_inapplicable(cfg, overrides)
    return make_trainer(cfg, run_dir, overrides=overrides)


def _check_auto_resume_dir() -> None:
    """resume=auto continues the run in the directory the command names: refused (one
    line) where that directory is a new timestamped one each time (Hydra's default)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode
    from omegaconf import OmegaConf

    from wcsac_rl.training import ConfigError

    hydra_cfg = HydraConfig.get()
    key = "sweep" if hydra_cfg.mode == RunMode.MULTIRUN else "run"
    template = str(OmegaConf.to_container(hydra_cfg[key], resolve=False)["dir"])
    if "${now:" in template:
        raise ConfigError(
            f"resume=auto continues the run in the directory the command names, but "
            f"hydra.{key}.dir is a new timestamped one each time ({template}): nothing "
            f"can be continued there; name it (hydra.{key}.dir=outputs/my_run resume=auto) "
            "or continue a run by its path (resume=outputs/<date>/<time>_<name>)"
        )


def _say_recipe(cfg: DictConfig) -> None:
    """A run's first line: the recipe files that shaped its ``algo`` (``algo.recipe``,
    also in its ``config.yaml``)."""
    recipe = cfg.algo.get("recipe")
    print(f"recipe: {recipe if recipe is not None else 'not recorded in the run config'}")


def _finish(trainer: Trainer) -> tuple[Path, Path | None]:
    """Train, then draw the curves (while the run still holds its directory's lock)."""
    from wcsac_rl.evaluation.plots import plot_run_curves

    run_dir = trainer.run()
    curves = plot_run_curves(
        run_dir / "progress.csv",
        run_dir / "curves.png",
        cost_limit=float(trainer.cfg.cost_limit),
    )
    return run_dir, curves


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def main(cfg: DictConfig) -> None:
    """The Hydra task: one run (a job of a sweep) in Hydra's output directory."""
    from hydra.core.hydra_config import HydraConfig

    from wcsac_rl.training.preemption import Preempted
    from wcsac_rl.training.run_dir import RunInUseError

    user_errors = _user_errors()
    hydra_cfg = HydraConfig.get()
    run_dir = Path(hydra_cfg.runtime.output_dir)
    staged = _staged_records(run_dir, hydra_cfg.output_subdir)
    entries = _entries_before(run_dir, staged)
    with ConsoleLog() as log:
        try:
            trainer = _build(cfg, run_dir, hydra_cfg.overrides.task)
        except RunInUseError as err:  # another process owns the directory: only ours goes
            _discard_staged(staged)
            _exit_with(f"error: {err}")
        except user_errors as err:
            _discard(run_dir, staged)  # a refused command leaves nothing behind
            _exit_with(f"error: {err}")
        except BaseException:
            _discard(run_dir, staged)
            raise
        if trainer.run_dir.resolve() != run_dir.resolve():  # resume=RUN_DIR: another run's
            _leave_hydra_dir(run_dir, trainer.run_dir, staged)
        else:
            _reopen_run_logs(trainer.run_dir)
            _keep_records(run_dir, staged)
        log.attach(trainer.run_dir / LOG_FILE)
        _say_recipe(trainer.cfg)
        try:
            run_dir, curves = _finish(trainer)
        except KeyboardInterrupt:
            sys.exit(130)
        except Preempted as stop:
            print(f"{stop}", file=sys.stderr, flush=True)
            sys.exit(stop.exit_code)
        except user_errors as err:
            trainer.close()  # (its lock released before its files go)
            _exit_with(f"error: {err}{_discard_stopped(trainer, entries)}")
        finally:
            trainer.close()
        print(f"run directory: {run_dir}")
        print(f"  metrics (one row per epoch): {run_dir / 'progress.csv'}")
        print(f"  logger output:               {run_dir / 'logs'}")
        print(f"  checkpoint:                  {trainer.checkpoint_path}")
        print(f"  training curves:             {curves}")
        print(f"  console log:                 {run_dir / LOG_FILE}")


DEFAULT_ROOTS = ("outputs", "multirun")
"""Where Hydra puts runs by default (``conf/config.yaml``), below the current directory."""


_BEFORE: dict[str, Any] = {}
"""What :func:`cli` noted before Hydra ran: when (``since``), and the run directory a
literal ``hydra.run.dir=`` names (``dir``) with its entries then (``existed``; ``None``:
it did not exist)."""


def _note_before(argv: Sequence[str]) -> None:
    import os
    import time

    _BEFORE.clear()
    _BEFORE["since"] = time.time()
    for arg in argv:
        key, sep, value = arg.lstrip("+").partition("=")
        value = value.strip("'\"")
        if sep and key == "hydra.run.dir" and "${" not in value:  # ("": the current one)
            path = Path(os.path.abspath(Path(value or ".").expanduser()))  # (as Hydra makes it)
            _BEFORE["dir"] = path
            _BEFORE["existed"] = (
                frozenset(p.name for p in path.iterdir()) if path.is_dir() else None
            )


def _stage_hydra_records(argv: list[str]) -> list[str]:
    """``argv`` with Hydra's records of this command sent to a staging directory
    (:data:`~wcsac_rl.training.run_dir.HYDRA_STAGING`; not when the line sets
    ``hydra.output_subdir`` itself): an existing run's ``.hydra/`` is written only once
    this command's run is accepted."""
    import os

    from hydra._internal.utils import get_args_parser

    try:
        args, _ = get_args_parser().parse_known_args(argv)
    except SystemExit:  # a malformed flag: Hydra answers it
        return argv
    if args.help or args.hydra_help or args.info or args.cfg or args.shell_completion:
        return argv  # (nothing runs: Hydra's answers show the config as it is; no torch)
    if any(arg.lstrip("+").startswith("hydra.output_subdir=") for arg in argv):
        return argv
    from wcsac_rl.training.run_dir import HYDRA_STAGING

    return [*argv, f"hydra.output_subdir={HYDRA_STAGING}{os.getpid()}"]


def _staged_records(run_dir: Path, subdir: str | None) -> Path | None:
    from wcsac_rl.training.run_dir import HYDRA_STAGING

    if subdir is None or not Path(str(subdir)).name.startswith(HYDRA_STAGING):
        return None
    return run_dir / str(subdir)


def _keep_records(run_dir: Path, staged: Path | None) -> None:
    """The accepted run's Hydra records: from the staging directory into ``.hydra/``."""
    import os

    if staged is None or not staged.is_dir():
        return
    target = run_dir / ".hydra"
    target.mkdir(exist_ok=True)
    for path in staged.iterdir():
        os.replace(path, target / path.name)
    staged.rmdir()


def _discard_staged(staged: Path | None) -> None:
    """Remove this command's own staged Hydra records (named by its pid), nothing else."""
    import shutil

    if staged is not None and staged.is_dir() and not staged.is_symlink():
        shutil.rmtree(staged, ignore_errors=True)


def _reopen_run_logs(run_dir: Path) -> None:
    """Hydra's job log handler opened ``<run dir>/train.log`` before the run took its
    directory; the run may since have given its files their own copies (a run copied
    with hard links: :func:`~wcsac_rl.training.run_dir.own_copies`), so the handlers
    writing into the run directory open their file again (the run's own)."""
    for handler in logging.getLogger().handlers:
        if (
            isinstance(handler, logging.FileHandler)
            and Path(handler.baseFilename).parent == Path(run_dir).absolute()
        ):
            handler.acquire()
            try:
                if handler.stream is not None:
                    handler.stream.close()
                handler.stream = handler._open()
            finally:
                handler.release()


def _leave_hydra_dir(hydra_dir: Path, run_dir: Path, staged: Path | None) -> None:
    """A resume of another directory (``resume=RUN_DIR``): Hydra's own new directory
    would stay behind empty (the run records this session's config itself), so its
    log handlers write into the run's log instead and it is removed with what this
    command put there."""
    for handler in logging.getLogger().handlers:
        if (
            isinstance(handler, logging.FileHandler)
            and Path(handler.baseFilename).parent == Path(hydra_dir).absolute()
        ):
            handler.acquire()
            try:
                if handler.stream is not None:
                    handler.stream.close()
                    handler.stream = None  # (opened again at the next record)
                handler.baseFilename = str(Path(run_dir).absolute() / LOG_FILE)
            finally:
                handler.release()
    _discard(hydra_dir, staged)


def _discard(run_dir: Path, staged: Path | None = None) -> None:
    """Remove what a refused command made: Hydra's staged records, and its run
    directory if the command created it (with the date directory above it that Hydra
    made for it, ``outputs/<date>/``, if that is now empty); a directory that existed
    keeps everything it held (:func:`~wcsac_rl.training.run_dir.discard_unused_run_dir`)."""
    import os

    from wcsac_rl.training.run_dir import discard_unused_run_dir

    _discard_staged(staged)
    noted = _BEFORE.get("dir") == Path(os.path.abspath(run_dir))
    existed = _BEFORE.get("existed") if noted else None
    created = noted and existed is None
    if discard_unused_run_dir(
        run_dir, existed=existed, since=_BEFORE.get("since"), created=created
    ):
        _remove_empty_parents(run_dir)


def _entries_before(run_dir: Path, staged: Path | None) -> frozenset[str] | None:
    """The entries of ``run_dir`` before the run wrote anything, without what this
    command itself made there first (Hydra's staged records and its empty job log, the
    directory itself when ``hydra.run.dir`` did not exist): ``None`` when there were
    none (the run's files are all of it)."""
    import os

    from wcsac_rl.training.run_dir import HYDRA_STAGING

    if _BEFORE.get("dir") == Path(os.path.abspath(run_dir)):
        return _BEFORE.get("existed")
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


def _discard_stopped(trainer: Trainer, entries: frozenset[str] | None) -> str:
    """A fresh run that stopped before its first checkpoint has nothing to continue from:
    what it wrote is removed (its directory too, when only the run was in it). Returns
    what the error line adds (nothing when a checkpoint is kept: a resumed run's too)."""
    import shutil

    from wcsac_rl.training.run_dir import LOCK_FILE

    run_dir = Path(trainer.run_dir)
    if trainer.checkpoint_path.is_file() or not run_dir.is_dir():
        return ""
    if entries is None:
        shutil.rmtree(run_dir, ignore_errors=True)
        _remove_empty_parents(run_dir)
        return f"; {run_dir} is removed (it held nothing to continue from)"
    for path in run_dir.iterdir():
        if path.name in entries and path.name != LOCK_FILE:
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    return f"; what the run wrote into {run_dir} is removed (it held nothing to continue from)"


def _remove_empty_parents(run_dir: Path) -> None:
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


def _exit_with(message: str) -> None:
    print(message, file=sys.stderr, flush=True)
    sys.exit(1)


def check_command_line(argv: list[str]) -> None:
    """Refuse an override of a key no chosen config has (``algo.batchsize=64``) in one
    line naming the closest key, before Hydra composes the config (Hydra's own refusal
    names none); ``--help`` and Hydra's other flags pass untouched (and fast)."""
    from hydra._internal.utils import get_args_parser

    try:
        args, _ = get_args_parser().parse_known_args(argv)
    except SystemExit:  # a malformed flag: Hydra answers it
        return
    if args.help or args.hydra_help or args.info or args.cfg or args.shell_completion:
        return
    from wcsac_rl.training.config_keys import check_override_keys
    from wcsac_rl.training.errors import ConfigError

    try:
        check_override_syntax(list(args.overrides))
        check_interpolations(list(args.overrides))
        check_override_keys(list(args.overrides))
        check_output_dirs(list(args.overrides))
        check_sweep_jobs(list(args.overrides), multirun=bool(args.multirun))
    except ConfigError as err:
        sys.exit(f"error: {err}")


def check_sweep_jobs(overrides: list[str], *, multirun: bool = True) -> None:
    """Without ``-m`` a sweep (``algo.lr=1,2``) is one line saying to add it or to quote
    the value. With ``-m``, every value of each sweep the command line names is checked
    before the launcher starts a job (``seed=1,abc`` is refused before seed 1 trains):
    the config of each value, the other sweeps at their first, composed and validated. A
    sweep that resumes runs (``resume=...``) is checked by each job against its own run."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from wcsac_rl.training.config import validate_config
    from wcsac_rl.training.errors import ConfigError

    parser = OverridesParser.create()
    parsed = parser.parse_overrides(overrides)
    sweeps = [o for o in parsed if o.is_sweep_override() and not o.is_hydra_override()]
    given = {o.get_key_element() for o in sweeps}
    sweeps += [  # an experiment's own sweep (hydra.sweeper.params), where it runs one
        o
        for o in parser.parse_overrides(_config_sweeps(overrides, multirun))
        if o.get_key_element() not in given
    ]
    if sweeps and not multirun and sweeps[0].input_line in overrides:
        key, _, value = sweeps[0].input_line.partition("=")
        raise ConfigError(
            f"{sweeps[0].input_line} is a sweep of values: add -m (--multirun) to run one job "
            f"for each, or quote the value to give it whole: \"{key}='{value}'\""
        )
    if not sweeps or any(o.get_key_element().lstrip("+~") == "resume" for o in parsed):
        return
    fixed = [o.input_line for o in parsed if not o.is_sweep_override()]
    first = {id(o): next(iter(o.sweep_string_iterator())) for o in sweeps}
    for sweep in sweeps:
        for value in sweep.sweep_string_iterator():
            job = [f"{o.get_key_element()}={value if o is sweep else first[id(o)]}" for o in sweeps]
            validate_config(_job_config(fixed, job))


def _config_sweeps(overrides: list[str], multirun: bool) -> list[str]:
    """The sweep an experiment's config runs (``hydra.sweeper.params`` as overrides,
    ``+row=sac,wcsac_0.1``), where the command runs in MULTIRUN mode: none otherwise."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    if not any(o.lstrip("+").startswith("experiment=") for o in overrides):
        return []
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            hydra_cfg = compose("config", overrides, return_hydra_config=True).hydra
    except Exception:  # (composition errors: the command itself reports them)
        return []
    finally:
        GlobalHydra.instance().clear()
    if not (multirun or str(hydra_cfg.mode) == "RunMode.MULTIRUN"):
        return []
    params = OmegaConf.to_container(hydra_cfg.sweeper.get("params") or {}, resolve=False)
    return [f"{key}={value}" for key, value in params.items()]


def _job_config(fixed: list[str], job: list[str]) -> DictConfig:
    """The config of one job of a sweep, a job that cannot be composed one line naming it."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from wcsac_rl._messages import first_line
    from wcsac_rl.training.errors import ConfigError

    try:
        return compose_config(*fixed, *job)
    except (HydraException, OmegaConfBaseException) as err:
        cause = f" ({first_line(err.__cause__)})" if err.__cause__ is not None else ""
        raise ConfigError(
            f"the sweep's job {' '.join(job)} cannot be composed: {first_line(err)}{cause}; "
            "give that option only to the jobs that have it (a sweep of fewer rows)"
        ) from None


def check_override_syntax(overrides: list[str]) -> None:
    """Refuse, in one line naming it, an override Hydra's grammar cannot read (a path
    with a newline, a character outside its lexer's such as ``ü``) and one that names no
    key (``=5``): Hydra's own refusals are stacks of lines (or a traceback)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    from wcsac_rl.training.errors import ConfigError

    parser = OverridesParser.create()
    for override in overrides:
        key, sep, _ = override.partition("=")
        if sep and not key.lstrip("+~").strip():
            raise ConfigError(f"cannot read the override {override!r}: it names no key (key=value)")
        try:
            parser.parse_overrides([override])
        except (HydraException, ValueError) as err:
            reason = (str(err).strip().splitlines() or [type(err).__name__])[0]
            reason = reason.split(":", 1)[0] if reason.startswith("Lexer") else reason
            key = override.split("=", 1)[0]
            raise ConfigError(
                f"cannot read the override {override!r} ({reason}): quote its value inside "
                f"the argument, e.g. \"{key}='...'\", or choose a value without newlines or "
                "characters outside ASCII"
            ) from None


def check_interpolations(overrides: list[str]) -> None:
    """Refuse, in one line naming the key and the variable, an override whose
    interpolation cannot resolve: ``${oc.env:NAME}`` of an unset variable without a
    default, or a key that refers to itself (``seed=${seed}``). Hydra would resolve
    them while making the run's directory, in its own stack of lines."""
    import os
    import re

    from wcsac_rl.training.errors import ConfigError

    for override in overrides:
        key, sep, value = override.lstrip("+~").partition("=")
        if sep and key == "run_name" and "${" not in value:
            from wcsac_rl.training.config import check_run_name  # (imports torch)

            check_run_name(value.strip("'\""))  # (before Hydra makes outputs/<date>/<name>)
        if not sep or "${" not in value:
            continue
        for name, default in re.findall(r"\$\{oc\.env:\s*([^,}\s]+)\s*(,[^}]*)?\}", value):
            if not default and name not in os.environ:
                raise ConfigError(
                    f"{key}={value}: the environment variable {name} is not set (set it, "
                    f"or give a default: ${{oc.env:{name},<default>}})"
                )
        if re.search(r"\$\{\s*" + re.escape(key) + r"\s*\}", value):
            raise ConfigError(f"{key}={value} refers to itself; give {key} a value")


def check_output_dirs(overrides: list[str]) -> None:
    """Refuse, in one line, a run or sweep directory that cannot be written (a read-only
    file system, another user's directory) before Hydra tries to create it (its own
    failure is a stack of lines). Directories given with interpolations are checked up
    to their first one; without ``hydra.run.dir`` / ``hydra.sweep.dir``, Hydra writes
    below the current directory."""
    from wcsac_rl.training.errors import ConfigError
    from wcsac_rl.training.run_dir import unwritable_reason

    given = {}
    for override in overrides:
        key, sep, value = override.lstrip("+").partition("=")
        if sep and key in ("hydra.run.dir", "hydra.sweep.dir"):
            given[key] = value.strip("'\"")
    for key, value in (given or {"the current directory": "."}).items():
        literal = value.split("${", 1)[0] or "."
        reason = unwritable_reason(literal)
        if reason is not None:
            where = f"{key}={value}" if key != "the current directory" else key
            raise ConfigError(
                f"cannot write the run's directory ({where}): {reason}; choose a directory "
                "you can write (hydra.run.dir=..., or hydra.sweep.dir=... for a sweep)"
            )


def cli(argv: Sequence[str] | None = None) -> None:
    """The ``wcsac-train`` console script (and ``python -m wcsac_rl.train``, ``train.py``)."""
    if argv is not None:
        sys.argv = [sys.argv[0], *argv]
    check_command_line(sys.argv[1:])
    _note_before(sys.argv[1:])
    sys.argv = [sys.argv[0], *_stage_hydra_records(sys.argv[1:])]
    main()


def compose_config(*overrides: str) -> DictConfig:
    """The config the command line ``wcsac-train <overrides>`` would train, for
    :func:`run_training` (an unknown key is refused in one line naming the closest).

    >>> cfg = compose_config("algo=sac_lag", "env=tiny", "seed=3")
    >>> cfg.algo.name, cfg.env.name, cfg.seed, cfg.run_name
    ('sac_lag', 'tiny', 3, 'sac_lag_tiny_seed3')
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from wcsac_rl.training.config_keys import check_override_keys

    check_override_keys(list(overrides))
    was_initialized = GlobalHydra.instance().is_initialized()
    previous = GlobalHydra.instance().config_loader() if was_initialized else None
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose("config", overrides=list(overrides))
    finally:
        if previous is not None:  # (a Hydra app calling this keeps its own state)
            GlobalHydra.instance().clear()
            GlobalHydra.instance().initialize(previous)


def run_training(
    cfg: DictConfig,
    run_dir: str | Path | None = None,
    *,
    overrides: Sequence[str] | None = None,
) -> Path:
    """Train the run ``cfg`` describes (:func:`compose_config`, or a saved
    ``config.yaml`` loaded with OmegaConf) and return its run directory.

    The same code as ``wcsac-train``: the config is validated first (one
    :class:`~wcsac_rl.training.ConfigError` naming the key), the run writes
    ``progress.csv``, ``checkpoints/``, ``logs/``, ``curves.png`` and ``train.log`` into
    ``run_dir`` (default: ``outputs/<date>/<time>_<run_name>`` below the current
    directory, as the command line's). A refused config leaves no directory behind.

    Args:
        cfg: the composed config.
        run_dir: the run's directory (new or empty; ``cfg.resume`` continues another).
        overrides: the overrides ``cfg`` was composed with, recorded in the run's
            ``provenance.json`` (and the resume rules of the command line apply to them).

    Raises:
        ConfigError: a config the run cannot start from; TrainingError: a run that could
        not go on (its last checkpoint is kept).
    """
    import datetime

    if run_dir is None:
        now = datetime.datetime.now()
        run_dir = Path("outputs") / f"{now:%Y-%m-%d}" / f"{now:%H-%M-%S}_{cfg.run_name}"
    from wcsac_rl.training.run_dir import RunInUseError, discard_unused_run_dir

    run_dir = Path(run_dir).absolute()
    existed = run_dir.exists()
    entries = frozenset(p.name for p in run_dir.iterdir()) if run_dir.is_dir() else None
    with ConsoleLog() as log:
        try:
            trainer = _build(cfg, run_dir, overrides)
        except RunInUseError:
            raise  # (another process owns the directory: nothing here is this call's)
        except BaseException:
            if not existed:
                _discard(run_dir)
            elif entries is not None:  # (only what the refused call made: its lock file)
                discard_unused_run_dir(run_dir, existed=entries)
            raise
        log.attach(trainer.run_dir / LOG_FILE)
        _say_recipe(trainer.cfg)
        try:
            done, curves = _finish(trainer)
        except _user_errors() as err:
            trainer.close()
            removed = _discard_stopped(trainer, entries)
            if removed and err.args:
                err.args = (f"{err.args[0]}{removed}", *err.args[1:])
            raise
        finally:
            trainer.close()
        print(f"run directory: {done} (training curves: {curves})")
    return done


if __name__ == "__main__":
    cli()
