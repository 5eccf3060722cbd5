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

import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import hydra
from omegaconf import DictConfig

from wcsac_rl.command_line import (
    check_command_line,
    check_interpolations,
    check_output_dirs,
    check_override_syntax,
    compose_config,
)
from wcsac_rl.config_dir import CONF_DIR

if TYPE_CHECKING:
    from wcsac_rl.training.trainer import Trainer

__all__ = [
    "check_command_line",
    "check_interpolations",
    "check_output_dirs",
    "check_override_syntax",
    "cli",
    "compose_config",
    "main",
    "run_training",
]


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
    from wcsac_rl.training.run_dir import AUTO_RESUME, check_auto_resume_dir

    overrides = list(overrides or ())
    if cfg.get("resume") == AUTO_RESUME:
        from hydra.core.hydra_config import HydraConfig

        check_auto_resume_dir(HydraConfig.get())
    if cfg.get("resume") and cfg.resume != AUTO_RESUME:
        cfg = resume_config(cfg, overrides)
    warn_inapplicable(cfg, overrides)
    return make_trainer(cfg, run_dir, overrides=overrides)


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
    from wcsac_rl.training.run_records import LOG_FILE, ConsoleLog, HydraJob, discard_stopped

    user_errors = _user_errors()
    hydra_cfg = HydraConfig.get()
    job = HydraJob(hydra_cfg)
    with ConsoleLog() as log:
        try:
            trainer = _build(cfg, job.dir, hydra_cfg.overrides.task)
        except RunInUseError as err:  # another process owns the directory: only ours goes
            job.refuse(owned=False)
            _exit_with(f"error: {err}")
        except user_errors as err:
            job.refuse()  # a refused command leaves nothing behind
            _exit_with(f"error: {err}")
        except BaseException:
            job.refuse()
            raise
        job.accept(trainer.run_dir)
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
            _exit_with(f"error: {err}{discard_stopped(trainer, job.entries)}")
        finally:
            trainer.close()
        print(f"run directory: {run_dir}")
        print(f"  metrics (one row per epoch): {run_dir / 'progress.csv'}")
        print(f"  logger output:               {run_dir / 'logs'}")
        print(f"  checkpoint:                  {trainer.checkpoint_path}")
        print(f"  training curves:             {curves}")
        print(f"  console log:                 {run_dir / LOG_FILE}")


def _exit_with(message: str) -> None:
    print(message, file=sys.stderr, flush=True)
    sys.exit(1)


def cli(argv: Sequence[str] | None = None) -> None:
    """The ``wcsac-train`` console script (and ``python -m wcsac_rl.train``, ``train.py``)."""
    if argv is not None:
        sys.argv = [sys.argv[0], *argv]
    if check_command_line(sys.argv[1:]):  # a job runs (Hydra's answers need no torch)
        from wcsac_rl.training.run_records import stage_command

        sys.argv = [sys.argv[0], *stage_command(sys.argv[1:])]
    main()


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
    from wcsac_rl.training.run_dir import RunInUseError
    from wcsac_rl.training.run_records import (
        LOG_FILE,
        ConsoleLog,
        default_run_dir,
        discard_refused,
        discard_stopped,
    )

    run_dir = Path(run_dir if run_dir is not None else default_run_dir(cfg.run_name)).absolute()
    existed = run_dir.exists()
    entries = frozenset(p.name for p in run_dir.iterdir()) if run_dir.is_dir() else None
    with ConsoleLog() as log:
        try:
            trainer = _build(cfg, run_dir, overrides)
        except RunInUseError:
            raise  # (another process owns the directory: nothing here is this call's)
        except BaseException:
            discard_refused(run_dir, existed=existed, entries=entries)
            raise
        log.attach(trainer.run_dir / LOG_FILE)
        _say_recipe(trainer.cfg)
        try:
            done, curves = _finish(trainer)
        except _user_errors() as err:
            trainer.close()
            removed = discard_stopped(trainer, entries)
            if removed and err.args:
                err.args = (f"{err.args[0]}{removed}", *err.args[1:])
            raise
        finally:
            trainer.close()
        print(f"run directory: {done} (training curves: {curves})")
    return done


if __name__ == "__main__":
    cli()
