"""The paper's Table 1 and Figures 4-6 for your runs: ``python -m wcsac_rl.report DIR ...``.

Reads the evaluated runs (``evaluation.json``) and training logs (``progress.csv``)
below the given directories and writes into ``--out`` (default ``<first DIR>/report``)
the tables and figures docs/reproduce.md lists (:mod:`~wcsac_rl.evaluation.reporting`;
the statistics over runs and ``--improvement``: docs/evaluation_protocol.md). Existing
files are not overwritten without ``--force``. Errors print one ``error:`` line, exit
with code 1 and leave nothing written.

Examples::

    python -m wcsac_rl.report multirun/2026-11-22/10-00-00
    python -m wcsac_rl.report multirun/2026-11-22/10-00-00 evaluations/random_static --out report
    python -m wcsac_rl.report RUNS --trajectory-runs RUNS/3_wcsac_0.1_static_seed0 --video
    python -m wcsac_rl.report study/runs --out study --no-trajectories \
        --improvement wcsac_0.1:sac_lag --improvement wcsac_0.1:sac_lag_d1.5
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path

from wcsac_rl.cli_args import add_trust_env_code, check_seed, check_threads
from wcsac_rl.evaluation.defaults import DEFAULT_SEED_OFFSET

__all__ = ["main", "parse_args"]


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line of ``python -m wcsac_rl.report``."""
    parser = argparse.ArgumentParser(
        prog="python -m wcsac_rl.report",
        description="Table 1 and Figures 4, 5, 6 of the WCSAC paper for a set of runs.",
    )
    parser.add_argument(
        "paths", nargs="+", type=Path, help="run, sweep or evaluation directories (recursive)"
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="output directory (default: <first path>/report)"
    )
    parser.add_argument("--env", default=None, help="report on this env's runs only")
    parser.add_argument(
        "--cost-limit", type=float, default=None, help="budget d (default: the runs' own)"
    )
    parser.add_argument("--force", action="store_true", help="overwrite existing report files")
    parser.add_argument(
        "--archive",
        action="store_true",
        help="also copy each run's evaluation, config and progress.csv into <out>/runs "
        "(a report of that folder alone gives the same table and Figures 4 and 6)",
    )
    traj = parser.add_argument_group("Figure 5: trajectories")
    traj.add_argument(
        "--trajectory-runs",
        nargs="+",
        type=Path,
        default=None,
        help="runs to draw (default: per row, the run with the lowest seed)",
    )
    traj.add_argument("--no-trajectories", action="store_true", help="skip Figure 5")
    traj.add_argument(
        "--stage-rows",
        nargs="+",
        default=None,
        help="rows whose runs get start/middle/end panels in fig5_stages.png, e.g. sac_lag "
        "as in the paper's Figure 5(a)-(c) (default: every drawn run with kept checkpoints)",
    )
    traj.add_argument(
        "--trajectory-episodes", type=int, default=5, help="episodes per run (default 5)"
    )
    traj.add_argument(
        "--trajectory-max-steps",
        type=int,
        default=None,
        help="bound on those episodes' length (default: the env's)",
    )
    traj.add_argument(
        "--trajectory-seed",
        type=int,
        default=DEFAULT_SEED_OFFSET,
        help=f"env seed of the trajectory episodes, the same for every run (default {DEFAULT_SEED_OFFSET})",
    )
    traj.add_argument(
        "--video",
        action="store_true",
        help="also render each drawn run's first episode with MuJoCo",
    )
    traj.add_argument(
        "--video-format",
        choices=("mp4", "gif"),
        default="mp4",
        help="mp4 needs ffmpeg (pip install imageio-ffmpeg); gif uses Pillow (default mp4)",
    )
    fig6 = parser.add_argument_group("Figure 6")
    fig6.add_argument(
        "--fig6-rows",
        nargs="+",
        default=None,
        help="rows to compare, e.g. sac sac_lag wcsac_0.5 (default: all evaluated but random)",
    )
    fig6.add_argument(
        "--fig6-ymax", type=float, default=None, help="upper view limit of the box plots"
    )
    stats = parser.add_argument_group("statistics over runs")
    stats.add_argument(
        "--improvement",
        action="append",
        default=[],
        metavar="A:B",
        help="row pair: the probability that a run of row A has a lower C0.1 (and EC) than "
        "a run of row B, with its interval; repeat for more pairs (implies --study)",
    )
    stats.add_argument(
        "--study",
        action="store_true",
        help="require the statistics over runs: a run without an evaluation, runs of a row "
        "with other settings or the same seed, a row of one run are errors",
    )
    add_trust_env_code(parser)
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    check_seed(parser, "--trajectory-seed", args.trajectory_seed)
    check_threads(parser, args.threads)
    if args.fig6_ymax is not None and not (math.isfinite(args.fig6_ymax) and args.fig6_ymax > 0):
        parser.error(f"--fig6-ymax must be a finite number > 0 (a cost), got {args.fig6_ymax}")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        parser.error(f"--out {args.out} is a file, not a directory")
    if args.trajectory_episodes < 1:
        parser.error(f"--trajectory-episodes must be >= 1, got {args.trajectory_episodes}")
    if args.trajectory_max_steps is not None and args.trajectory_max_steps < 1:
        parser.error(f"--trajectory-max-steps must be >= 1, got {args.trajectory_max_steps}")
    return args


_SAME_NAMED = ("env", "cost_limit", "force", "trajectory_runs", "trajectory_episodes",
               "trajectory_max_steps", "trajectory_seed", "video", "video_format", "fig6_rows",
               "fig6_ymax", "stage_rows", "archive", "study")  # fmt: skip
"""The options passed to :func:`~wcsac_rl.evaluation.reporting.build_report` by their name."""


def main(argv: Sequence[str] | None = None) -> int:
    """Build the report; return the exit code."""
    args = parse_args(argv)
    import torch

    from wcsac_rl.evaluation.latex import markdown_text
    from wcsac_rl.evaluation.reporting import build_report
    from wcsac_rl.evaluation.run_report import parse_improvements
    from wcsac_rl.evaluation.trajectories import TrajectoryError, VideoError
    from wcsac_rl.training.config import ConfigError
    from wcsac_rl.training.trust import allow_env_code

    torch.set_num_threads(args.threads)
    out = args.out if args.out is not None else args.paths[0] / "report"
    try:
        pairs = parse_improvements(args.improvement)
        with allow_env_code(args.trust_env_code):  # the policies Figure 5 loads
            report = build_report(
                args.paths,
                out,
                trajectories=not args.no_trajectories,
                improvement=pairs,
                **{option: getattr(args, option) for option in _SAME_NAMED},
            )
    except (ConfigError, TrajectoryError, VideoError) as err:
        print(f"error: {markdown_text(err)}", file=sys.stderr)  # (a name's line break as \n)
        return 1
    except OSError as err:  # a run's file that cannot be read (writes are ReportErrors)
        where = f"{err.filename}: " if err.filename else ""
        print(f"error: {markdown_text(where + (err.strerror or str(err)))}", file=sys.stderr)
        return 1
    table = out / "table1.md"
    if table in report.files:
        print()
        print(table.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
