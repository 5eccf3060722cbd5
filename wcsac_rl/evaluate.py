"""Final evaluation of trained runs: ``python -m wcsac_rl.evaluate RUN_OR_SWEEP_DIR ...``.

For every run directory given, or found below a sweep directory (``checkpoints/last.pt``),
runs N deterministic test episodes of the final policy (default 100) and writes
``evaluation.csv`` and ``evaluation.json`` beside the run
(:mod:`~wcsac_rl.evaluation.evaluator`); ``--random-policy ENV`` evaluates the uniform
random policy without a run; ``--archive DIR`` copies each evaluated run's records
(:mod:`~wcsac_rl.evaluation.archive`). Existing evaluations are skipped unless
``--force``. A path that cannot be evaluated, or a sweep job missing or failed
(:mod:`~wcsac_rl.evaluation.sweeps`), is one ``error:`` line (exit code 1; the other
runs are still evaluated); an unfinished or running one a ``warning:`` (docs/reproduce.md).

Examples::

    python -m wcsac_rl.evaluate multirun/2026-11-22/10-00-00
    python -m wcsac_rl.evaluate outputs/2026-11-22/10-00-00_wcsac_0.5_static_seed0 --episodes 20
    python -m wcsac_rl.evaluate --random-policy static --out evaluations/random_static
    python -m wcsac_rl.evaluate multirun/evidence_static --archive results/evidence_static/runs
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from functools import partial
from pathlib import Path

from wcsac_rl.cli_args import add_trust_env_code, check_seed, check_threads
from wcsac_rl.evaluation.defaults import DEFAULT_EPISODES, DEFAULT_SEED_OFFSET

__all__ = ["add_episode_arguments", "add_process_arguments", "check_episode_arguments", "main",
           "parse_args"]  # fmt: skip


def add_episode_arguments(
    parser: argparse.ArgumentParser, *, episodes: int, episodes_help: str, seed_help: str
) -> None:
    """``--episodes`` (default ``episodes``), ``--seed`` (the test env's seed offset) and
    ``--max-episode-steps`` of a command that runs test episodes."""
    parser.add_argument("--episodes", type=int, default=episodes, help=episodes_help)
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED_OFFSET, help=seed_help)
    parser.add_argument(
        "--max-episode-steps",
        type=int,
        default=None,
        help="bound on an episode's length (default: the env's own)",
    )


def add_process_arguments(parser: argparse.ArgumentParser) -> None:
    """``--trust-env-code``, ``--threads`` and ``--no-progress``."""
    add_trust_env_code(parser)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def check_episode_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse (``parser.error``) the values :func:`add_episode_arguments` and
    :func:`add_process_arguments` added that no run can take."""
    check_seed(parser, "--seed", args.seed)
    check_threads(parser, args.threads)
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.max_episode_steps is not None and args.max_episode_steps < 1:
        parser.error(f"--max-episode-steps must be >= 1, got {args.max_episode_steps}")


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line of ``python -m wcsac_rl.evaluate``."""
    parser = argparse.ArgumentParser(
        prog="python -m wcsac_rl.evaluate",
        description=(
            "Run deterministic test episodes of trained runs' final policies and save "
            "evaluation.csv / evaluation.json beside each run."
        ),
    )
    parser.add_argument(
        "paths",
        nargs="*",
        type=Path,
        help="run directories and/or sweep directories (searched for checkpoints/last.pt)",
    )
    add_episode_arguments(
        parser,
        episodes=DEFAULT_EPISODES,
        episodes_help=f"test episodes per run (default {DEFAULT_EPISODES}, the paper's per seed)",
        seed_help="seed offset of the test episodes: a run trained with seed k is evaluated on "
        f"an env seeded k + SEED (default {DEFAULT_SEED_OFFSET}, apart from the training envs "
        "and the per-epoch test episodes)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="overwrite existing evaluation files (and, with --archive, differing archived ones)",
    )
    parser.add_argument(
        "--archive",
        type=Path,
        default=None,
        metavar="DIR",
        help=(
            "also copy each evaluated run's records (evaluation, config, provenance, "
            "progress.csv; no checkpoint) into DIR/<run name>, as soon as it is evaluated: "
            "what `wcsac-report --archive` keeps, for run directories that may not last"
        ),
    )
    add_process_arguments(parser)
    random_group = parser.add_argument_group("random policy (no training run needed)")
    random_group.add_argument(
        "--random-policy",
        metavar="ENV",
        default=None,
        help="also evaluate the uniform random policy on ENV (static, dynamic, ..., tiny)",
    )
    random_group.add_argument(
        "--random-seeds",
        type=int,
        nargs="+",
        default=[0, 10, 20],
        help="its 'training' seeds, one evaluation directory each (default: 0 10 20)",
    )
    random_group.add_argument(
        "--out",
        type=Path,
        default=None,
        help="where its evaluation directories go (default: evaluations/random_<ENV>)",
    )
    random_group.add_argument(
        "--cost-limit",
        type=float,
        default=15.0,
        help="budget d recorded with its evaluation (default 15)",
    )
    args = parser.parse_args(argv)
    check_episode_arguments(parser, args)
    for seed in args.random_seeds:
        check_seed(parser, "--random-seeds", seed)
    if not args.paths and args.random_policy is None:
        parser.error("give run or sweep directories, or --random-policy ENV")
    return args


def _jobs(args: argparse.Namespace, sweep_jobs, errors: list[str]) -> list[tuple[Path, object]]:
    """``(directory, evaluate)`` of every run below ``args.paths`` and every random-policy
    seed; a path that holds no run adds its line to ``errors`` (and says it)."""
    from wcsac_rl.evaluation.evaluator import evaluate_random_policy, evaluate_run
    from wcsac_rl.evaluation.runs import find_run_dirs

    jobs: list[tuple[Path, object]] = []
    common = {"episodes": args.episodes, "seed_offset": args.seed, "force": args.force,
              "progress": not args.no_progress, "max_episode_steps": args.max_episode_steps}  # fmt: skip
    # the jobs of the sweeps below the paths (any launcher): their status is reported
    # by main, once (a job directory without a checkpoint is not also an error here)
    without_checkpoint = [
        job.directory for job in sweep_jobs if job.directory and not job.has_checkpoint
    ]
    if args.paths:
        run_dirs, find_errors = find_run_dirs(args.paths, accounted=without_checkpoint)
        errors += find_errors
        for message in find_errors:
            print(f"error: {message}", file=sys.stderr, flush=True)
        trust = args.trust_env_code
        jobs += [(d, partial(evaluate_run, d, trust_env_code=trust, **common)) for d in run_dirs]
    if args.random_policy is not None:
        out = args.out or Path("evaluations") / f"random_{args.random_policy}"
        for seed in dict.fromkeys(args.random_seeds):
            directory = out / f"random_{args.random_policy}_seed{seed}"
            job = partial(evaluate_random_policy, args.random_policy, directory, seed=seed,
                          cost_limit=args.cost_limit, **common)  # fmt: skip
            jobs.append((directory, job))
    return jobs


def _random_policy_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with ``--random-policy``'s env, cost limit or ``--out`` (said once,
    not once per seed), or ``None``."""
    from wcsac_rl.evaluation.evaluator import check_random_policy
    from wcsac_rl.training.config import ConfigError

    try:
        check_random_policy(args.random_policy, args.cost_limit)
    except ConfigError as err:
        return str(err)
    out = args.out or Path("evaluations") / f"random_{args.random_policy}"
    if out.exists() and not out.is_dir():
        return f"--out {out} is a file, not a directory"
    return None


def _say_unfinished(sweep_jobs) -> bool:
    """Name a sweep's jobs that did not finish (any launcher), never silently dropped;
    whether one of them is missing or failed (an error)."""
    incomplete = [job for job in sweep_jobs if not job.complete]
    for job in incomplete:
        kind = "warning" if job.status in ("running", "unfinished") else "error"
        print(f"{kind}: sweep job {job.describe()}", file=sys.stderr, flush=True)
    if incomplete:
        print(
            f"{len(incomplete)} sweep job(s) not finished: "
            + ", ".join(f"{job.name} ({job.status})" for job in incomplete),
            flush=True,
        )
    return any(job.status in ("missing", "failed") for job in incomplete)


def main(argv: Sequence[str] | None = None) -> int:
    """Evaluate; return the exit code (1 if any path failed)."""
    args = parse_args(argv)
    import torch

    from wcsac_rl.evaluation.archive import ArchiveError, archive_run
    from wcsac_rl.evaluation.evaluator import EvaluationExistsError, unfinished_training
    from wcsac_rl.evaluation.outcomes import OUTCOME_TITLES
    from wcsac_rl.evaluation.sweeps import all_sweep_jobs
    from wcsac_rl.training.config import ConfigError

    torch.set_num_threads(args.threads)
    errors: list[str] = []
    skipped: list[str] = []
    done: list[str] = []
    archived: list[Path] = []

    def report(directory: Path, evaluation) -> None:
        m = evaluation.summary["metrics"]
        outcomes = ", ".join(
            f"{OUTCOME_TITLES[name]} {count}"
            for name, count in evaluation.summary["outcomes"].items()
            if count
        )
        done.append(str(directory))
        print(
            f"{directory}: {m['episodes']} episodes  EC {m['EC']:.2f}  C0.1 {m['C0.1']:.2f}  "
            f"ER {m['ER']:.2f}  over budget {100 * m['over_budget']:.1f}%  ({outcomes})",
            flush=True,
        )

    if args.random_policy is not None:
        problem = _random_policy_problem(args)
        if problem is not None:
            print(f"error: {problem}", file=sys.stderr, flush=True)
            return 1
    sweep_jobs = all_sweep_jobs(args.paths) if args.paths else []
    jobs = _jobs(args, sweep_jobs, errors)
    # the sweep jobs named at the end as running or unfinished: not warned of twice
    named = {job.directory.resolve() for job in sweep_jobs if job.directory and not job.complete}

    def warn_unfinished(directory: Path, evaluation) -> None:
        """One line for a run evaluated before its ``total_frames``."""
        warning = unfinished_training(evaluation)
        if warning is not None and Path(directory).resolve() not in named:
            print(f"warning: {warning}", file=sys.stderr, flush=True)

    def keep(directory: Path) -> None:
        """With --archive: the records of a run evaluated now or before, copied."""
        if args.archive is None:
            return
        try:
            archived.append(archive_run(directory, args.archive, force=args.force))
        except (ArchiveError, OSError) as err:
            errors.append(str(err))
            print(f"error: archive: {err}", file=sys.stderr, flush=True)

    for job in sweep_jobs:
        if job.complete and not job.has_checkpoint:  # evaluated, its checkpoint removed
            skipped.append(str(job.directory))
            print(f"skipped: {job.directory}: {job.detail}", file=sys.stderr, flush=True)
            keep(job.directory)
    for directory, job in jobs:
        try:
            evaluation = job()
            report(directory, evaluation)
            warn_unfinished(directory, evaluation)
        except EvaluationExistsError as err:
            skipped.append(str(directory))
            print(f"skipped: {err}", file=sys.stderr, flush=True)
        except ConfigError as err:
            errors.append(str(err))
            print(f"error: {err}", file=sys.stderr, flush=True)
            continue
        except Exception as err:  # one broken run must not stop a sweep's evaluation
            first = (str(err).strip().splitlines() or [""])[0]  # one line, never a dump
            errors.append(f"{directory}: {first}")
            print(f"error: {directory}: {type(err).__name__}: {first}", file=sys.stderr, flush=True)
            continue
        keep(directory)
    if archived:
        print(f"{len(archived)} archived in {args.archive}", flush=True)
    print(
        f"{len(done)} evaluated, {len(skipped)} skipped (already evaluated; --force "
        f"re-evaluates), {len(errors)} failed",
        flush=True,
    )
    failed_jobs = _say_unfinished(sweep_jobs)
    return 1 if errors or failed_jobs else 0


if __name__ == "__main__":
    sys.exit(main())
