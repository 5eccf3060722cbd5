"""Train WCSAC or a baseline: ``python train.py algo=wcsac risk_level=0.5 env=dynamic``.

Hydra composes ``conf/config.yaml``; with no overrides this is the paper's full run.
Sweeps: ``python train.py -m algo=wcsac risk_level=0.1,0.5,0.9 seed=0,10,20``; on a
cluster: ``python train.py -m experiment=table1_static hydra/launcher=slurm`` (README,
"Run the paper's sweeps on a cluster"). A run stopped by ``SIGTERM`` / ``SIGUSR1`` /
``SIGUSR2`` checkpoints first and exits with 128 + the signal's number.
"""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from wcsac_rl.envs import NonFiniteStepError
from wcsac_rl.evaluation.plots import plot_run_curves
from wcsac_rl.training import ConfigError, TrainingError, make_trainer
from wcsac_rl.training.checkpoint import resume_config
from wcsac_rl.training.preemption import Preempted
from wcsac_rl.training.run_dir import AUTO_RESUME, discard_unused_run_dir

# errors a user can cause or fix: printed as one line (exit code 1), never a traceback
USER_ERRORS = (ConfigError, TrainingError, NonFiniteStepError)


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        # resume=RUN_DIR: the run's own config, with only the explicit overrides applied;
        # resume=auto (sweeps): the composed config, checked against this run dir's checkpoint
        overrides = list(HydraConfig.get().overrides.task)
        if cfg.resume and cfg.resume != AUTO_RESUME:
            cfg = resume_config(cfg, overrides)
        trainer = make_trainer(cfg, run_dir, overrides=overrides)
    except USER_ERRORS as err:
        discard_unused_run_dir(run_dir)  # a refused command leaves no directory behind
        sys.exit(f"error: {err}")
    try:
        run_dir = trainer.run()
        # (drawn while the run still holds its directory's lock, as every file of the run)
        curves = plot_run_curves(
            run_dir / "progress.csv",
            run_dir / "curves.png",
            cost_limit=float(trainer.cfg.cost_limit),
        )
    except KeyboardInterrupt:
        sys.exit(130)
    except Preempted as stop:
        print(f"{stop}", file=sys.stderr, flush=True)
        sys.exit(stop.exit_code)
    except USER_ERRORS as err:
        sys.exit(f"error: {err}")
    finally:
        trainer.close()
    print(f"run directory: {run_dir}")
    print(f"  metrics (one row per epoch): {run_dir / 'progress.csv'}")
    print(f"  logger output:               {run_dir / 'logs'}")
    print(f"  checkpoint:                  {trainer.checkpoint_path}")
    print(f"  training curves:             {curves}")


def check_command_line(argv: list[str]) -> None:
    """Refuse an override of a key no chosen config has (``algo.batchsize=64``) in one
    line naming the closest key, before Hydra composes the config (Hydra's own refusal
    names none)."""
    from hydra._internal.utils import get_args_parser

    from wcsac_rl.training.config_keys import check_override_keys

    try:
        args, _ = get_args_parser().parse_known_args(argv)
    except SystemExit:  # --help and friends: Hydra answers them
        return
    try:
        check_override_keys(list(args.overrides))
        check_output_dirs(list(args.overrides))
    except ConfigError as err:
        sys.exit(f"error: {err}")


def check_output_dirs(overrides: list[str]) -> None:
    """Refuse, in one line, a run or sweep directory that cannot be written (a read-only
    file system, another user's directory) before Hydra tries to create it (its own
    failure is a stack of lines). Directories given with interpolations are checked up
    to their first one; without ``hydra.run.dir`` / ``hydra.sweep.dir``, Hydra writes
    below the current directory."""
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


if __name__ == "__main__":
    check_command_line(sys.argv[1:])
    main()
