"""The paper's analysis of a set of runs: Table 1 and Figures 4, 5 and 6 in one directory.

:func:`build_report` reads the evaluated directories (``evaluation.json``) and training
runs (``config.yaml`` + ``progress.csv``) below the given directories, groups them by
Table-1 row (``algo.label``; seeds pooled; runs of a label that differ in a
:data:`POOLED_KEYS` setting are separate rows) and writes the files docs/reproduce.md
lists (Table 1, Figures 4-6, ``runs.md``, the training-safety table, the statistics over
runs, the outcomes; every figure as PNG and PDF, every Markdown table also as LaTeX).
Below a sweep directory every job is accounted for (:mod:`~wcsac_rl.evaluation.sweeps`).
A report is written whole or not at all (:func:`_staging`) and never over existing files
without ``force``; it covers one env and one budget d.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import re
import secrets
import shutil
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from wcsac_rl.evaluation import plots
from wcsac_rl.evaluation.archive import ARCHIVED_FILES, archived_records, needs_copy
from wcsac_rl.evaluation.evaluator import (
    DEFAULT_SEED_OFFSET,
    Evaluation,
    check_env_code_allowed,
    check_writable,
    read_evaluation,
    stale_evaluation,
)
from wcsac_rl.evaluation.intervals import INTERVAL_METRICS, seed_bootstrap
from wcsac_rl.evaluation.latex import (
    csv_text,
    latex_path,
    markdown_cell,
    markdown_table,
    markdown_text,
    markdown_to_latex,
)
from wcsac_rl.evaluation.metrics import RISK_LEVELS, aggregate_seeds, cvar_key
from wcsac_rl.evaluation.outcomes import (
    FIG_OUTCOMES,
    OUTCOMES_CSV,
    OUTCOMES_MD,
    outcome_rows,
    outcomes_csv,
    outcomes_markdown,
    plot_outcomes,
)
from wcsac_rl.evaluation.paper import paper_comparison_markdown
from wcsac_rl.evaluation.run_report import (
    RunStatistics,
    RunStatisticsError,
    collect_run_statistics,
    write_run_statistics,
)
from wcsac_rl.evaluation.runs import (
    STAGING_SUFFIX,
    display_text,
    env_has_layout,
    env_title,
    find_evaluated_dirs,
    find_progress_dirs,
    has_checkpoint,
    make_row_label,
    row_name,
    row_sort_key,
    split_row_label,
)
from wcsac_rl.evaluation.sweeps import SweepJob, incomplete_jobs
from wcsac_rl.evaluation.training_safety_table import TRAINING_SAFETY_FILES, training_safety_files
from wcsac_rl.options import ENSEMBLE_OPTIONS
from wcsac_rl.training.checkpoint import IDENTITY_KEYS, kept_checkpoints
from wcsac_rl.training.config import ConfigError
from wcsac_rl.training.progress import read_progress
from wcsac_rl.training.provenance import read_provenance
from wcsac_rl.training.registry import find_algorithm, row_algorithm
from wcsac_rl.training.run_dir import check_progress_rows, replace_file
from wcsac_rl.training.safe_load import load_yaml
from wcsac_rl.training.trust import interpolation_in, plain_select, stored_config

__all__ = [
    "ARCHIVED_FILES",
    "ARCHIVE_DIR",
    "FIG4",
    "FIG6",
    "FIG_COST_RETURN",
    "FORMATS",
    "RUNS_MD",
    "TABLE_CSV",
    "TABLE_MD",
    "TABLE_TEX",
    "TABLE_VS_PAPER",
    "TRAJECTORIES",
    "Report",
    "ReportError",
    "build_report",
    "runs_markdown",
    "table1_markdown",
    "table1_rows",
]

TABLE_MD = "table1.md"
TABLE_CSV = "table1.csv"
TABLE_TEX = latex_path(TABLE_MD)
TABLE_VS_PAPER = "table1_vs_paper.md"
RUNS_MD = "runs.md"
ARCHIVE_DIR = "runs"
"""Where ``archive=True`` copies the reported runs' records, below the report's directory."""
FIG4 = "fig4_training_curves.png"
FIG5 = "fig5_trajectories.png"
FIG5_STAGES = "fig5_stages.png"
FIG6 = "fig6_evaluation.png"
FIG_COST_RETURN = "fig_cost_return.png"
TRAJECTORIES = FIG5
FORMATS = plots.FIGURE_FORMATS
"""The files of each figure: a PNG to view and a PDF to print (:func:`~wcsac_rl.evaluation.plots.save_figure`)."""

TABLE_COLUMNS = (
    "label",
    "algorithm",
    "env",
    "cost_limit",
    "EC",
    *(cvar_key(a) for a in RISK_LEVELS),
    "ER",
    "goals",
    "over_budget",
    "episodes",
    "seeds",
    "runs",
    *(f"{metric}_{end}" for metric in INTERVAL_METRICS for end in ("lo", "hi")),
    "EC_seed_std",
    "ER_seed_std",
    "seed_list",
)
"""table1.csv's columns: ``cost_limit`` is the budget the row's runs trained with (the
report's d, for ``over_budget``, is in table1.md's title); ``seeds`` counts distinct
training seeds, ``runs`` the evaluated runs; ``<metric>_lo`` / ``<metric>_hi`` bound the
95 % seed-stratified bootstrap interval (:mod:`~wcsac_rl.evaluation.intervals`)."""
GOAL_COLUMNS = ("goals", "goals_lo", "goals_hi")
"""table1.csv's columns of goals, left out for an env without goals (:func:`env_has_layout`)."""


class ReportError(ConfigError):
    """The report cannot be made as asked; the message says why and what to pass."""


@dataclass
class RunRecord:
    """A training run found on disk (for curves and trajectories)."""

    directory: Path
    label: str
    env: str
    seed: int
    cost_limit: float
    progress: dict[str, list[float]] | None
    sessions: int = 1
    provenance: list[dict[str, Any]] = field(default_factory=list)


@dataclass
class Report:
    """What :func:`build_report` wrote (``files``) and the notes it printed (``warnings``)."""

    out_dir: Path
    files: list[Path] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    rows: list[dict[str, Any]] = field(default_factory=list)
    incomplete: list[SweepJob] = field(default_factory=list)


def _read_run(directory: Path) -> RunRecord:
    cfg = stored_config(load_yaml(directory / "config.yaml"), directory / "config.yaml")
    progress_csv = directory / "progress.csv"
    check_progress_rows(directory)  # (an epoch logged twice: its frames would be wrong)
    progress = read_progress(progress_csv) if progress_csv.is_file() else None
    return RunRecord(
        directory=directory,
        label=str(OmegaConf.select(cfg, "algo.label") or OmegaConf.select(cfg, "algo.name")),
        env=str(OmegaConf.select(cfg, "env.name")),
        seed=int(OmegaConf.select(cfg, "seed")),
        cost_limit=float(OmegaConf.select(cfg, "cost_limit")),
        progress=progress or None,
        sessions=1 + sum(1 for _ in directory.glob("config.resume*.yaml")),
        provenance=read_provenance(directory),
    )


# --------------------------------------------------------------------------- runs.md
def _code_text(records: Sequence[dict[str, Any]], sessions: int) -> str:
    """The commits the run's sessions ran (short), ``+ local changes`` when the work
    tree differed from one; sessions without a record are counted as not recorded."""
    shown = []
    for record in records:
        code = record.get("code") or {}
        commit = code.get("commit")
        if commit:
            text = str(commit)[:7] + (" + local changes" if code.get("dirty") else "")
        else:
            text = f"package {code.get('version') or '?'} (no git checkout)"
        if text not in shown:
            shown.append(text)
    missing = sessions - len(records)
    if missing > 0:
        shown.append(
            f"not recorded ({missing} of {sessions} sessions)" if shown else "not recorded"
        )
    return ", ".join(shown)


def _wall_text(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    minutes = round(seconds / 60)
    return f"{minutes // 60} h {minutes % 60:02d} min"


def runs_markdown(runs: Sequence[RunRecord], env: str | None) -> str:
    """``runs.md``: one line per training run — row, seed, frames trained, training wall
    time (``progress.csv``'s ``time_s``, all sessions), sessions and code commits —
    and the total training time."""
    total, cells = 0.0, []
    for run in sorted(runs, key=lambda r: (row_sort_key(r.label), r.seed, r.directory.name)):
        progress = run.progress or {}
        frames = progress.get("frames", [math.nan])[-1] if progress else math.nan
        seconds = progress.get("time_s", [math.nan])[-1] if progress else math.nan
        if math.isfinite(seconds):
            total += seconds
        cells.append(
            [markdown_cell(run.directory.name), markdown_cell(row_name(run.label)), run.seed,
             f"{int(frames)}" if math.isfinite(frames) else "?", _wall_text(seconds),
             run.sessions, markdown_cell(_code_text(run.provenance, run.sessions))]
        )  # fmt: skip
    header = ["run", "row", "seed", "frames", "training wall time", "sessions", "code"]
    lines = [
        f"# Training runs — {markdown_text(env_title(env)) if env else '?'}",
        "",
        *markdown_table(header, "llrrrrl", cells),
    ]
    lines += [
        "",
        f"Total training wall time: {_wall_text(total)} over {len(runs)} runs (each run's "
        "`time_s`, summed over its sessions; runs that shared the machine ran side by "
        "side, so the sweep's own wall time is shorter). Code: the commit each session "
        "ran, from its `provenance.json`.",
        "",
    ]
    return "\n".join(lines)


# --------------------------------------------------------------------------- Table 1
def table1_rows(evaluations: Sequence[Evaluation], cost_limit: float) -> list[dict[str, Any]]:
    """One Table-1 row per row label (seeds pooled, :func:`aggregate_seeds`), in the
    paper's order, with goals per episode and the 95 % seed-stratified bootstrap
    interval of EC, C_α, ER and goals (:func:`~wcsac_rl.evaluation.intervals.seed_bootstrap`).
    ``cost_limit`` is the report's d (``over_budget``); the row's ``cost_limit`` column is
    its runs' own."""
    by_label: dict[str, list[Evaluation]] = defaultdict(list)
    for ev in evaluations:
        by_label[ev.label].append(ev)
    rows = []
    for label in sorted(by_label, key=row_sort_key):
        evs = sorted(by_label[label], key=lambda e: (int(e.meta.get("seed", 0)), str(e.directory)))
        costs = [e.costs for e in evs]
        returns = [e.returns for e in evs]
        goals = [[ep.goal_reached for ep in e.episodes] for e in evs]
        metrics = aggregate_seeds(costs, returns, cost_limit)
        interval = seed_bootstrap(costs, returns, goals)
        own_limits = {float(e.meta.get("cost_limit", cost_limit)) for e in evs}
        rows.append(
            {
                "label": label,
                "algorithm": row_name(label),
                "env": evs[0].meta["env"],
                "cost_limit": own_limits.pop() if len(own_limits) == 1 else cost_limit,
                **metrics,
                "goals": sum(map(sum, goals)) / metrics["episodes"],
                "seeds": len({e.meta.get("seed") for e in evs}),
                "runs": len(evs),
                **{
                    f"{k}_{end}": v
                    for k, (lo, hi) in interval.items()
                    for end, v in (("lo", lo), ("hi", hi))
                },
                "seed_list": " ".join(str(e.meta.get("seed", "?")) for e in evs),
            }
        )
    return rows


def _learns(algo: object) -> bool:
    """Whether runs of ``algo`` restore a learnt policy (an algorithm the registry does
    not know: as one that does)."""
    entry = find_algorithm(algo)
    return entry is None or entry.learns


def _learns_row(label: str) -> bool:
    entry = row_algorithm(label)
    return entry is None or entry.learns


def _constrained_column(label: str) -> str | None:
    """The column the row's agent constrains (bold in the paper's Table 1)."""
    label, _ = split_row_label(label)
    if (entry := row_algorithm(label)) is not None and entry.risk_neutral and "_paper" not in label:
        return "EC"
    if label.startswith("wcsac_"):
        try:
            key = cvar_key(float(label.split("_", 1)[1]))
        except ValueError:
            return None
        return key if key in {cvar_key(a) for a in RISK_LEVELS} else None
    return None


def table1_markdown(
    rows: Sequence[dict[str, Any]],
    env: str,
    cost_limit: float,
    incomplete: Sequence[SweepJob] = (),
    goals: bool | None = None,
) -> str:
    """Table 1 as Markdown, with a legend of the columns below it and, when a sweep's
    jobs did not all finish, the list of those jobs (:mod:`~wcsac_rl.evaluation.sweeps`).
    ``goals``: with the goals column (default: where ``env`` has goals, :func:`env_has_layout`)."""
    goals = env_has_layout(env) if goals is None else goals
    cvars = [cvar_key(a) for a in RISK_LEVELS]
    metrics = ["EC", *cvars, "ER", *(["goals"] if goals else [])]
    header = ["Algorithm", *metrics, "over budget", "episodes (seeds)"]
    body = []
    for row in rows:
        bold = _constrained_column(row["label"])
        cells = [markdown_cell(row["algorithm"])]
        for key in metrics:
            text = f"{row[key]:.2f}"
            text = f"**{text}**" if key == bold else text
            if not math.isnan(row[key + "_lo"]):  # (one episode of one seed: none)
                text += f" [{row[key + '_lo']:.2f}, {row[key + '_hi']:.2f}]"
            cells.append(text)
        cells.append(f"{100 * row['over_budget']:.1f}%")
        seeds = f"{row['seeds']} seed{'s' if row['seeds'] != 1 else ''}"
        if row["runs"] != row["seeds"]:
            seeds = f"{row['runs']} runs, {seeds}"
        body.append([*cells, f"{row['episodes']} ({seeds})"])
    lines = [
        f"# Table 1 — {markdown_text(env_title(env))}, budget d = {cost_limit:g}",
        "",
        *markdown_table(header, "l" + "r" * (len(header) - 1), body),
    ]
    lines += [
        "",
        "EC: mean episodic cost; C_α: empirical CVaR, the mean cost of the worst ⌈n·α⌉ of "
        "the n test episodes; ER: mean episodic return; "
        + ("goals: goals reached per episode; " if goals else "")
        + f"over budget: share of episodes with cost strictly above d = {cost_limit:g}. "
        "Deterministic (mean-action) test episodes of each seed's final policy, seeds "
        "pooled; [lo, hi]: 95 % bootstrap interval resampling the seeds, then the episodes "
        "within each seed (one seed: the episodes only). In bold: the quantity the agent "
        "constrains (SAC-Lag: EC, WCSAC-α: C_α). A row label with settings in brackets: "
        "runs of that algorithm with another setting than the rest. Per-seed spread: "
        "table1.csv (EC_seed_std, ER_seed_std).",
        "",
    ]
    if incomplete:
        lines += [
            f"## Sweep jobs not finished ({len(incomplete)})",
            "",
            "Missing and failed jobs are not in the table; an unfinished or running job is "
            "if it was evaluated, with the policy of the checkpoint it had then.",
            "",
            *markdown_table(
                ["job", "status", "sweep", "detail"],
                "llll",
                (
                    [markdown_cell(c) for c in (j.name, j.status, j.sweep, j.detail)]
                    for j in incomplete
                ),
            ),
            "",
        ]
    return "\n".join(lines)


def _table_csv(rows: Sequence[dict[str, Any]], goals: bool = True) -> str:
    """table1.csv (:data:`TABLE_COLUMNS`; without :data:`GOAL_COLUMNS` unless ``goals``)."""
    columns = [c for c in TABLE_COLUMNS if goals or c not in GOAL_COLUMNS]
    return csv_text(rows, columns, lineterminator="\r\n")


# ------------------------------------------------------------------------- the report
def _common(values: dict[str, set], what: str, flag: str) -> Any:
    present = set().union(*values.values()) if values else set()
    if len(present) > 1:
        listing = ", ".join(sorted(map(str, present)))
        raise ReportError(f"the runs use several {what} ({listing}); choose one with {flag}")
    return next(iter(present)) if present else None


def _write_text(path: Path, text: str) -> Path:
    """Write ``text`` (UTF-8; a run name that is not is shown with U+FFFD) as a new file
    renamed into place (:func:`~wcsac_rl.training.run_dir.replace_file`)."""
    return replace_file(path, display_text(text))


ENSEMBLE_KEYS = tuple(f"algo.{key}" for key in (*ENSEMBLE_OPTIONS, "damp_clamp"))
"""The safety-critic ensemble's settings: how many critics, how they are read and trained."""

POOLED_KEYS = (
    "cost_limit",
    "total_frames",
    *(k for k in IDENTITY_KEYS if k != "cost_limit"),
    *ENSEMBLE_KEYS,
)
"""What the runs pooled into one row must share (besides the env): the budget d, the
frame budget, what their networks and losses depend on (``IDENTITY_KEYS``) and the
safety-critic ensemble (:data:`ENSEMBLE_KEYS`: two runs of ``algo=wcsac`` read at the
largest member and at a UCB are two rows)."""


def _session_config(directory: Path) -> Any:
    """The run's config as its last session ran it; ``None`` without a readable one."""
    return (_session_config_file(directory) or (None, None))[1]


def _session_config_file(directory: Path) -> tuple[Path, Any] | None:
    """``(path, config)`` of the run's last session (``config.resume<k>.yaml`` with the
    largest k, else ``config.yaml``); ``None`` without a readable one."""
    resumed = sorted(
        directory.glob("config.resume*.yaml"),
        key=lambda p: (
            int(p.stem[len("config.resume") :] or 0)
            if p.stem[len("config.resume") :].isdigit()
            else -1
        ),
    )
    for path in [*reversed(resumed), directory / "config.yaml"]:
        try:
            return path, load_yaml(path)
        except Exception:  # missing or damaged: the next one
            continue
    return None


RUN_FIELDS = {"seed": "seed", "algo": "algo.name", "label": "algo.label", "env": "env.name"}
"""``evaluation.json`` fields and the config keys of the run they must equal: an
evaluation copied from another run, or edited, is not counted as this run's (a held-out
seed written over an in-sample run's would make it one)."""


def _config_mismatch(ev: Evaluation) -> str | None:
    """The first field in which ``ev`` disagrees with its run's config (the last
    session's, :func:`_session_config`), with both values; ``None`` when they agree or
    there is no config (the random policy evaluated without a run)."""
    found = _session_config_file(Path(ev.directory))
    if found is None:
        return None
    path, cfg = found
    for field_name, key in RUN_FIELDS.items():
        value = plain_select(cfg, key)
        if field_name == "label" and value is None:
            value = plain_select(cfg, "algo.name")  # (as the evaluator labels it)
        recorded = ev.meta.get(field_name)
        if value is None or recorded is None or recorded == value:
            continue
        if interpolation_in(value) is not None:  # (never resolved: not compared)
            continue
        return (
            f"{Path(ev.directory) / 'evaluation.json'} has {field_name} {recorded!r}, its "
            f"run's {path.name} {key} {value!r}"
        )
    return None


def _identity(directory: Path, meta: dict[str, Any] | None = None) -> dict[str, str]:
    """The :data:`POOLED_KEYS` a run (or an evaluation's ``meta``) was made with, as text."""
    identity: dict[str, str] = {}
    cfg = _session_config(Path(directory))
    for key in POOLED_KEYS:
        value = None if cfg is None else plain_select(cfg, key)  # (nothing resolved)
        if value is not None and interpolation_in(value) is None:
            identity[key] = repr(value)
    if meta is not None:
        identity["cost_limit"] = repr(float(meta["cost_limit"]))
        identity["evaluation max_episode_steps"] = repr(meta.get("max_episode_steps"))
    return identity


def _setting_text(value: str) -> str:
    """A setting's value as a row label shows it (``"'pid'"`` → ``pid``)."""
    return value[1:-1] if len(value) > 1 and value[0] == value[-1] == "'" else value


def row_labels(
    members: dict[str, list[tuple[str, dict[str, str]]]],
) -> tuple[dict[str, str], list[str]]:
    """Split each label's runs by every :data:`POOLED_KEYS` setting that differs between
    them (keys a run's records lack are not compared): a row pools the seeds of one
    configuration only.

    Args:
        members: per ``algo.label``, its runs as ``(name, identity)``
            (:func:`_identity`).

    Returns:
        ``({name: row label}, warnings)``: the row label is the label itself when its
        runs agree, else :func:`~wcsac_rl.evaluation.runs.make_row_label` of the
        settings that tell them apart; one warning line per label split.

    >>> labels, warnings = row_labels({"sac_lag": [("a", {"cost_limit": "15.0"}),
    ...     ("b", {"cost_limit": "1.5"}), ("c", {"cost_limit": "15.0"})]})
    >>> labels
    {'a': 'sac_lag[cost_limit=15.0]', 'b': 'sac_lag[cost_limit=1.5]', 'c': 'sac_lag[cost_limit=15.0]'}
    >>> warnings
    ['row sac_lag: its runs differ in cost_limit (15.0: 2 runs; 1.5: 1 run), shown as one row per setting']
    """
    labels: dict[str, str] = {}
    warnings: list[str] = []
    for label, runs in members.items():
        keys = sorted(set().union(*(identity for _, identity in runs)))
        differing = [key for key in keys if len({i[key] for _, i in runs if key in i}) > 1]
        for name, identity in runs:
            settings = {key: _setting_text(identity[key]) for key in differing if key in identity}
            labels[name] = make_row_label(label, settings)
        if differing:
            parts = []
            for key in differing:
                counts: dict[str, int] = defaultdict(int)
                for _, identity in runs:
                    if key in identity:
                        counts[_setting_text(identity[key])] += 1
                listing = "; ".join(
                    f"{value}: {n} run{'s' if n > 1 else ''}" for value, n in counts.items()
                )
                parts.append(f"{key} ({listing})")
            warnings.append(
                f"row {label}: its runs differ in {', '.join(parts)}, shown as one row per setting"
            )
    return labels, warnings


@dataclass
class _TrajectorySource:
    directory: Path
    label: str
    seed: int

    @property
    def stem(self) -> str:
        name = re.sub(r"[^A-Za-z0-9._=-]+", "_", self.label).strip("_")
        return f"fig5_{name}_seed{self.seed}"


def _trajectory_sources(
    chosen: Sequence[str | os.PathLike] | None,
    runs: Sequence[RunRecord],
    evaluations: Sequence[Evaluation],
) -> list[_TrajectorySource]:
    """The runs whose policies Figure 5 shows: the chosen ones, else per row the lowest seed."""
    if chosen is not None:
        sources = []
        for raw in chosen:
            directory = Path(raw).expanduser().resolve()
            if has_checkpoint(directory):
                record = _read_run(directory)
                sources.append(_TrajectorySource(directory, record.label, record.seed))
            elif (directory / "evaluation.json").is_file():
                ev = read_evaluation(directory)
                if _learns(ev.meta.get("algo")):
                    raise ReportError(f"{directory}: no checkpoint to draw trajectories from")
                sources.append(_TrajectorySource(directory, ev.label, int(ev.meta["seed"])))
            else:
                raise ReportError(
                    f"{directory}: not a run directory with a checkpoint "
                    "(expected checkpoints/last.pt)"
                )
        return sources
    candidates: dict[str, list[_TrajectorySource]] = defaultdict(list)
    seen: set[Path] = set()
    for run in runs:
        if has_checkpoint(run.directory):
            candidates[run.label].append(_TrajectorySource(run.directory, run.label, run.seed))
            seen.add(run.directory)
    for ev in evaluations:
        directory = Path(ev.directory).resolve()
        if directory in seen:
            continue
        if has_checkpoint(directory) or not _learns(ev.meta.get("algo")):
            candidates[ev.label].append(
                _TrajectorySource(directory, ev.label, int(ev.meta["seed"]))
            )
    return [
        min(candidates[label], key=lambda s: (s.seed, str(s.directory)))
        for label in sorted(candidates, key=row_sort_key)
    ]


def _restore(
    source: _TrajectorySource, env_seed: int
) -> tuple[Any, Any, int, str, dict, int | None]:
    """``(policy, env, max_steps, env_name, env_kwargs, frames)`` for a trajectory source
    (``frames``: what its checkpoint was trained for; ``None`` for the random policy)."""
    if has_checkpoint(source.directory):
        from wcsac_rl.evaluation.evaluator import load_policy
        from wcsac_rl.training.builders import env_kwargs
        from wcsac_rl.training.trainer import env_max_episode_steps

        restored = load_policy(source.directory, env_seed)
        cfg = restored.cfg
        return (
            restored.policy,
            restored.env,
            env_max_episode_steps(cfg),
            str(cfg.env.name),
            env_kwargs(cfg),
            restored.frames,
        )
    from wcsac_rl.envs import make_env

    ev = read_evaluation(source.directory)
    kwargs = {"max_episode_steps": int(ev.meta["max_episode_steps"])}
    env = make_env(str(ev.meta["env"]), seed=env_seed, **kwargs)
    return None, env, kwargs["max_episode_steps"], str(ev.meta["env"]), kwargs, None


def build_report(
    paths: Sequence[str | os.PathLike],
    out_dir: str | os.PathLike,
    *,
    env: str | None = None,
    cost_limit: float | None = None,
    force: bool = False,
    trajectory_runs: Sequence[str | os.PathLike] | None = None,
    trajectories: bool = True,
    trajectory_episodes: int = 5,
    trajectory_max_steps: int | None = None,
    trajectory_seed: int = DEFAULT_SEED_OFFSET,
    video: bool = False,
    video_format: str = "mp4",
    fig6_rows: Sequence[str] | None = None,
    fig6_ymax: float | None = None,
    stage_rows: Sequence[str] | None = None,
    archive: bool = False,
    improvement: Sequence[tuple[str, str]] = (),
    study: bool = False,
    log: Callable[[str], None] = print,
) -> Report:
    """Write Table 1 and Figures 4, 5, 6 for the runs below ``paths`` into ``out_dir``.

    Args:
        paths: run, sweep or evaluation directories (searched recursively).
        out_dir: where the files go (created).
        log: where progress lines go.
        others: the options of ``python -m wcsac_rl.report`` of the same name (its
            ``--help``; ``trajectories=False`` is ``--no-trajectories``, ``improvement``
            the ``--improvement`` pairs, :func:`~wcsac_rl.evaluation.run_report.parse_improvements`).

    Raises:
        ReportError: nothing to report, mixed envs or budgets, existing files without
            ``force``, a video that cannot be made, runs a study cannot pool, an
            evaluation that is not its run's, an ``out_dir`` that cannot be written —
            before anything is written; a write that fails (a full disk) — nothing of
            the report is left (:func:`_staging`), as after any other error.
    """
    out_dir = Path(out_dir).expanduser()
    report = Report(out_dir=out_dir)
    log, warn = _printers(log, report)
    archive_dir = (out_dir / ARCHIVE_DIR).resolve()
    evaluations, runs, env, cost_limit, unreadable = _read_records(
        paths, archive_dir, env, cost_limit, warn
    )
    evaluations, runs = _split_rows(evaluations, runs, warn)
    _account_for_runs(paths, evaluations, runs, report, warn)
    statistics = _run_statistics(
        evaluations, runs, unreadable, env, cost_limit, improvement, study, warn
    )
    sources = _figure5_sources(trajectories, trajectory_runs, runs, evaluations, env, warn)
    rows, comparison, copies = _plan_outputs(
        out_dir, env, cost_limit, evaluations, runs, sources, archive_dir, archive, video,
        video_format, stage_rows, force, warn,
        also=[] if statistics is None else statistics.file_names(FORMATS),
    )  # fmt: skip
    # one colour and marker per row, the same in every figure of the report
    styles = plots.row_styles([e.label for e in evaluations] + [r.label for r in runs])
    with _staging(out_dir) as stage:  # (all files or none: a failure leaves nothing)
        if evaluations:
            report.rows = rows
            report.files += _write_table1(
                stage, rows, env, cost_limit, comparison, evaluations, report.incomplete,
                fig6_rows, fig6_ymax, styles, warn,
            )  # fmt: skip
            report.files += write_run_statistics(
                statistics, stage, _write_text, styles=styles, formats=FORMATS
            )
        else:
            warn("no evaluated runs: Table 1 and Figure 6 skipped")
        trained = [r for r in runs if r.progress]
        if trained:
            report.files += _write_training(stage, trained, env, cost_limit, styles, warn)
        else:
            warn("no training runs with progress.csv: Figure 4 skipped")
        if sources:
            report.files += _figure5(
                sources, stage, episodes=trajectory_episodes, max_steps=trajectory_max_steps,
                env_seed=trajectory_seed, video_format=video_format if video else None,
                stage_rows=stage_rows, title_env=env_title(env) if env else "?", styles=styles,
                log=log,
            )  # fmt: skip
        for source, target in copies:
            staged = stage / ARCHIVE_DIR / target.relative_to(archive_dir)
            staged.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, staged)
            report.files.append(staged)
        report.files = [out_dir / path.relative_to(stage) for path in report.files]
    for path in report.files:
        log(f"wrote {path}")
    return report


@contextlib.contextmanager
def _staging(out_dir: Path) -> Iterator[Path]:
    """A new, empty directory to write the report into; its files are moved into
    ``out_dir`` once every one is written. A report that fails (a full disk, a read-only
    file system, any error) leaves nothing of itself: the directory is removed, with the
    directories made for it, and an ``OSError`` is a :class:`ReportError` naming the file.

    The directory is beside ``out_dir`` when that does not exist yet (then renamed to it,
    one step), inside it when it does (each file then renamed into place). A directory
    no file can be written in is refused before anything is made."""
    try:
        check_writable(out_dir)
    except ConfigError as err:
        raise ReportError(str(err)) from None
    fresh = not out_dir.exists()
    home = out_dir.parent if fresh else out_dir
    made = [d for d in (home, *home.parents) if not d.exists()]  # deepest first
    token = f"{os.getpid()}.{secrets.token_hex(4)}{STAGING_SUFFIX}"
    stage = home / f".{out_dir.name or 'report'}.{token}"
    try:
        home.mkdir(parents=True, exist_ok=True)
        stage.mkdir()
        yield stage
        _move_into(stage, out_dir, fresh)
    except BaseException as err:
        shutil.rmtree(stage, ignore_errors=True)
        for directory in made:
            with contextlib.suppress(OSError):
                directory.rmdir()
        if isinstance(err, OSError):
            raise ReportError(_write_error(err, stage, out_dir)) from None
        raise
    shutil.rmtree(stage, ignore_errors=True)  # (emptied)


def _move_into(stage: Path, out_dir: Path, fresh: bool) -> None:
    """The staged files into ``out_dir``: the directory renamed to it when ``fresh``, else
    each file renamed onto its place (checked first: no place is a directory)."""
    if fresh:
        os.rename(stage, out_dir)
        return
    moves = [(p, out_dir / p.relative_to(stage)) for p in sorted(stage.rglob("*")) if p.is_file()]
    for _, target in moves:
        if target.is_dir() and not target.is_symlink():
            raise ReportError(f"cannot write {target}: it is a directory; move it away")
        target.parent.mkdir(parents=True, exist_ok=True)
    for source, target in moves:
        os.replace(source, target)


def _write_error(err: OSError, stage: Path, out_dir: Path) -> str:
    """One line for an ``OSError`` of writing the report: the report's file it was
    writing (a staged name shown as the file it stands for), or a run's file it read."""
    why = err.strerror or str(err)
    name = err.filename2 or err.filename
    if not name:
        return f"cannot write {out_dir}: {why}"
    path = Path(os.fsdecode(name))
    if path == stage or stage in path.parents:
        return f"cannot write {out_dir / path.relative_to(stage)}: {why}"
    mine, out = path.absolute(), out_dir.absolute()
    if _within(mine, out) or mine in out.parents:  # (the report's directory, or one above)
        return f"cannot write {path}: {why}"
    return f"cannot read {path}: {why}"


def _printers(
    log: Callable[[str], None], report: Report
) -> tuple[Callable[[str], None], Callable[[str], None]]:
    """``(log, warn)``: ``log`` printing any run name (one that is not UTF-8 too), ``warn``
    logging ``warning: <message>`` and keeping the message in ``report.warnings``."""

    def printable(message: str) -> None:
        log(markdown_text(display_text(message)))  # (one line, whatever a name holds)

    def warn(message: str) -> None:
        report.warnings.append(message)
        printable(f"warning: {message}")

    return printable, warn


def _figure5_sources(
    trajectories: bool,
    chosen: Sequence[str | os.PathLike] | None,
    runs: list[RunRecord],
    evaluations: list[Evaluation],
    env: str | None,
    warn: Callable[[str], None],
) -> list[_TrajectorySource]:
    """The runs Figure 5 draws (:func:`_trajectory_sources`), their env code allowed
    (refused before anything is written); none, said in one line, for an env without a
    layout to draw the paths on or without a run with a checkpoint."""
    if not trajectories:
        return []
    if not env_has_layout(env):
        warn(
            f"Figure 5 (trajectories) skipped: env {env} has no layout (hazards, goal) to "
            "draw the paths on; they are drawn for the kit's envs (static, dynamic, "
            "point_goal1, point_goal2, tiny)"
        )
        return []
    sources = _trajectory_sources(chosen, runs, evaluations)
    for source in sources:
        if has_checkpoint(source.directory):
            check_env_code_allowed(source.directory)
    if not sources and chosen is None:
        warn("no run with a checkpoint: Figure 5 (trajectories) skipped")
    return sources


def _read_records(
    paths: Sequence[str | os.PathLike],
    archive_dir: Path,
    env: str | None,
    cost_limit: float | None,
    warn: Callable[[str], None],
) -> tuple[list[Evaluation], list[RunRecord], str | None, float, list[str]]:
    """The evaluations and training runs below ``paths`` (not those of an earlier
    report's archive at ``archive_dir``) of ``env``, the report's env and budget d, and
    the names of the directories whose evaluation cannot be read."""
    for raw in paths:
        if not Path(raw).expanduser().is_dir():
            raise ReportError(f"{raw}: no such directory")
    unreadable: list[str] = []
    if any(_within(Path(raw).expanduser().resolve(), archive_dir) for raw in paths):
        previous_archive = None  # reporting on an archive itself
    else:
        previous_archive = archive_dir
    evaluations: list[Evaluation] = []
    stale: list[str] = []
    for directory in _outside(find_evaluated_dirs(paths), previous_archive):
        try:
            evaluations.append(read_evaluation(directory))
        except ConfigError as err:
            warn(f"skipped: {err}")
            unreadable.append(directory.name)
            continue
        mismatch = _config_mismatch(evaluations[-1])
        if mismatch is not None:  # another run's numbers must not enter Table 1 either
            raise ReportError(
                f"{mismatch}: not this run's evaluation; evaluate it again "
                f"(python -m wcsac_rl.evaluate --force {directory})"
            )
        reason = stale_evaluation(directory)
        if reason is not None:
            stale.append(f"{directory.name} ({reason})")
    if stale:  # stale numbers must not enter Table 1
        raise ReportError(
            f"{len(stale)} evaluation(s) no longer match their run's checkpoint: "
            f"{'; '.join(stale)}; evaluate them again (python -m wcsac_rl.evaluate "
            f"{' '.join(map(str, paths))}) and re-run the report"
        )
    runs = []
    for directory in _outside(find_progress_dirs(paths), previous_archive):
        try:
            runs.append(_read_run(directory))
        except Exception as err:  # a half-written config: report it and go on
            warn(f"skipped {directory}: cannot read config.yaml/progress.csv ({err})")

    envs = {"evaluations": {e.meta["env"] for e in evaluations}, "runs": {r.env for r in runs}}
    if env is not None:
        evaluations = [e for e in evaluations if e.meta["env"] == env]
        runs = [r for r in runs if r.env == env]
    else:
        env = _common(envs, "envs", "--env")
    if not evaluations and not runs:
        where = ", ".join(map(str, paths))
        raise ReportError(
            f"nothing to report under {where}"
            + (f" for env {env!r}" if env else "")
            + ": no evaluated runs (evaluation.json) and no training runs (progress.csv)"
        )
    if cost_limit is None:
        cost_limit = _common(
            {
                "evaluations": {float(e.meta["cost_limit"]) for e in evaluations},
                "runs": {r.cost_limit for r in runs},
            },
            "cost limits",
            "--cost-limit",
        )
    cost_limit = float(cost_limit)
    if not math.isfinite(cost_limit) or cost_limit < 0:
        raise ReportError(f"cost limit must be a number >= 0, got {cost_limit!r}")
    return evaluations, runs, env, cost_limit, unreadable


def _split_rows(
    evaluations: list[Evaluation], runs: list[RunRecord], warn: Callable[[str], None]
) -> tuple[list[Evaluation], list[RunRecord]]:
    """The evaluations and runs with their row labels (:func:`row_labels`): runs of a
    label that differ in a setting are separate rows, said in one warning line per label."""
    by_row: dict[str, list[tuple[str, dict[str, str]]]] = defaultdict(list)
    for ev in evaluations:
        by_row[ev.label].append((str(ev.directory), _identity(ev.directory, ev.meta)))
    labels, split = row_labels(by_row)
    evaluations = [
        dataclasses.replace(ev, meta={**ev.meta, "label": labels[str(ev.directory)]})
        for ev in evaluations
    ]
    by_row = defaultdict(list)
    for run in runs:
        by_row[run.label].append((str(run.directory), _identity(run.directory)))
    run_labels, run_split = row_labels(by_row)
    runs = [dataclasses.replace(r, label=run_labels[str(r.directory)]) for r in runs]
    for message in dict.fromkeys(split + run_split):
        warn(message)
    return evaluations, runs


def _run_statistics(
    evaluations: list[Evaluation],
    runs: list[RunRecord],
    unreadable: list[str],
    env: str | None,
    cost_limit: float,
    improvement: Sequence[tuple[str, str]],
    study: bool,
    warn: Callable[[str], None],
) -> RunStatistics | None:
    """The statistics over runs (:func:`~wcsac_rl.evaluation.run_report.collect_run_statistics`):
    every training run and evaluation below the paths is one of their runs."""
    evaluated = {Path(e.directory).resolve() for e in evaluations}
    unevaluated = [r.directory.name for r in runs if r.directory not in evaluated]
    unevaluated += [name for name in unreadable if name not in unevaluated]
    try:
        return collect_run_statistics(
            evaluations, unevaluated, env=env, cost_limit=cost_limit,
            config_of=_session_config, improvement=improvement, study=study, warn=warn,
        )  # fmt: skip
    except RunStatisticsError as err:
        raise ReportError(str(err)) from None


def _account_for_runs(
    paths: Sequence[str | os.PathLike],
    evaluations: list[Evaluation],
    runs: list[RunRecord],
    report: Report,
    warn: Callable[[str], None],
) -> None:
    """Warn about every sweep job not finished, every run not evaluated and every seed
    evaluated twice in a row."""
    # every job of the sweeps below paths (any launcher): those not finished are named
    report.incomplete = incomplete_jobs(paths)
    for job in report.incomplete:
        warn(f"sweep job {job.describe()}")

    evaluated_dirs = {Path(e.directory).resolve() for e in evaluations}
    unevaluated = [r for r in runs if r.directory not in evaluated_dirs]
    if unevaluated:
        warn(
            f"{len(unevaluated)} training run(s) have no evaluation and are not in Table 1 / "
            f"Figure 6 (run `python -m wcsac_rl.evaluate` on them): "
            + ", ".join(r.directory.name for r in unevaluated)
        )
    seeds_seen: dict[tuple[str, int], int] = defaultdict(int)
    for ev in evaluations:
        seeds_seen[(ev.label, int(ev.meta.get("seed", -1)))] += 1
    for (label, seed), count in seeds_seen.items():
        if count > 1:
            warn(f"row {label}: {count} evaluations with seed {seed} (all are pooled)")


def _files(out_dir: Path, names: Sequence[str]) -> list[Path]:
    """The files of each output name: a figure (``.png``) in each of :data:`FORMATS`, a
    Markdown table with its LaTeX table (``.tex``), any other file itself."""
    files: list[Path] = []
    for name in names:
        path = out_dir / name
        if name.endswith(".png"):
            files += plots.figure_paths(path, FORMATS)
        elif name.endswith(".md"):
            files += [path, path.with_suffix(".tex")]
        else:
            files.append(path)
    return list(dict.fromkeys(files))


def _plan_outputs(
    out_dir: Path,
    env: str | None,
    cost_limit: float,
    evaluations: list[Evaluation],
    runs: list[RunRecord],
    sources: list[_TrajectorySource],
    archive_dir: Path,
    archive: bool,
    video: bool,
    video_format: str,
    stage_rows: Sequence[str] | None,
    force: bool,
    warn: Callable[[str], None],
    also: Sequence[str] = (),
) -> tuple[list[dict[str, Any]], str | None, list[tuple[Path, Path]]]:
    """Table 1's rows, the paper comparison and the archive copies; every output file
    (and the files named ``also``, planned elsewhere) planned, refused if it exists
    without ``force``, and the video encoder checked — before anything is written."""
    names: list[str] = list(also)
    rows: list[dict[str, Any]] = []
    comparison = None
    if evaluations:
        rows = table1_rows(evaluations, cost_limit)
        comparison = paper_comparison_markdown(rows, env, cost_limit) if env else None
        names += [TABLE_MD, TABLE_CSV, FIG6, FIG_COST_RETURN, OUTCOMES_MD, OUTCOMES_CSV]
        names.append(FIG_OUTCOMES)
        if comparison is not None:
            names.append(TABLE_VS_PAPER)
    copies: list[tuple[Path, Path]] = []
    if archive:
        copies = _archive_plan(
            [Path(e.directory) for e in evaluations] + [r.directory for r in runs], archive_dir
        )
    if any(r.progress for r in runs):
        names += [FIG4, RUNS_MD, *TRAINING_SAFETY_FILES]
    if sources:
        names.append(FIG5)
        if stage_rows is not None:
            unknown = sorted(set(stage_rows) - {s.label for s in sources})
            if unknown:
                warn(f"Figure 5 stages: no drawn run of row(s) {', '.join(unknown)}")
        if any(
            kept_checkpoints(s.directory)
            for s in sources
            if stage_rows is None or s.label in stage_rows
        ):
            names.append(FIG5_STAGES)
        names += [f"{s.stem}.png" for s in sources]
        if video:
            names += [f"{s.stem}.{video_format}" for s in sources]
    if video:
        _check_video(video_format, env)
    planned = _files(out_dir, names) + [target for _, target in copies]
    existing = [p for p in planned if p.exists()]
    if existing and not force:
        listing = ", ".join(p.relative_to(out_dir).as_posix() for p in existing)
        raise ReportError(f"{out_dir} already has {listing}; pass --force to overwrite")
    return rows, comparison, copies


def _write_table(path: Path, text: str) -> list[Path]:
    """A Markdown table and the same as a LaTeX booktabs table beside it (``.tex``)."""
    return [_write_text(path, text), _write_text(path.with_suffix(".tex"), markdown_to_latex(text))]


def _write_table1(
    out_dir: Path,
    rows: list[dict[str, Any]],
    env: str | None,
    cost_limit: float,
    comparison: str | None,
    evaluations: list[Evaluation],
    incomplete: list[SweepJob],
    fig6_rows: Sequence[str] | None,
    fig6_ymax: float | None,
    styles: dict[str, plots.RowStyle],
    warn: Callable[[str], None],
) -> list[Path]:
    """Table 1 (Markdown, CSV, LaTeX; beside the paper's), Figure 6, the cost-return
    figure (each row in its ``styles``) and the runs' episode outcomes."""
    title_env = env_title(env) if env else "?"
    goals = env_has_layout(env)
    files = _write_table(out_dir / TABLE_MD, table1_markdown(rows, env, cost_limit, incomplete))
    files.append(_write_text(out_dir / TABLE_CSV, _table_csv(rows, goals=goals)))
    if comparison is not None:
        files += _write_table(out_dir / TABLE_VS_PAPER, comparison)
    costs: dict[str, list[float]] = defaultdict(list)
    for ev in sorted(evaluations, key=lambda e: row_sort_key(e.label)):
        costs[ev.label].extend(ev.costs)
    if fig6_rows is None:
        chosen = [label for label in costs if _learns_row(label)] or list(costs)
    else:
        unknown = sorted(set(fig6_rows) - set(costs))
        if unknown:
            warn(f"Figure 6: no evaluated row(s) {', '.join(unknown)}")
        chosen = [label for label in fig6_rows if label in costs]
    plots.plot_cost_distribution(
        {label: costs[label] for label in chosen},
        out_dir / FIG6,
        cost_limit=cost_limit,
        title=f"Evaluation after training ({title_env})",
        ymax=fig6_ymax,
        styles=styles,
        formats=FORMATS,
    )
    plots.plot_cost_return(
        rows,
        out_dir / FIG_COST_RETURN,
        cost_limit=cost_limit,
        title=f"Cost and return of the test episodes ({title_env}), budget d = {cost_limit:g}",
        styles=styles,
        formats=FORMATS,
    )
    outcomes = outcome_rows(evaluations, goals)
    markdown = outcomes_markdown(outcomes, title_env, goals)
    files += _write_table(out_dir / OUTCOMES_MD, markdown)
    files.append(_write_text(out_dir / OUTCOMES_CSV, outcomes_csv(outcomes, goals)))
    plot_outcomes(
        outcomes, out_dir / FIG_OUTCOMES, title=title_env, has_goals=goals, formats=FORMATS
    )
    return files + _files(out_dir, [FIG6, FIG_COST_RETURN, FIG_OUTCOMES])


def _write_training(
    out_dir: Path,
    runs: list[RunRecord],
    env: str | None,
    cost_limit: float,
    styles: dict[str, plots.RowStyle],
    warn: Callable[[str], None],
) -> list[Path]:
    """runs.md, the training-safety table and Figure 4 of the runs with progress."""
    files = _write_table(out_dir / RUNS_MD, runs_markdown(runs, env))
    for name, text in training_safety_files(runs, env, cost_limit, warn).items():
        files.append(_write_text(out_dir / name, text))
    by_label: dict[str, list[dict[str, list[float]]]] = defaultdict(list)
    for run in sorted(runs, key=lambda r: (row_sort_key(r.label), r.seed)):
        by_label[run.label].append(run.progress)
    plots.plot_training_curves(
        dict(by_label),
        out_dir / FIG4,
        cost_limit=cost_limit,
        title=f"Training on {env_title(env) if env else '?'}",
        styles=styles,
        formats=FORMATS,
    )
    return files + _files(out_dir, [FIG4])


def _within(path: Path, directory: Path) -> bool:
    return path == directory or directory in path.parents


def _outside(directories: Sequence[Path], archive: Path | None) -> list[Path]:
    """``directories`` without the copies a previous ``archive=True`` report made."""
    if archive is None:
        return list(directories)
    return [d for d in directories if not _within(d.resolve(), archive)]


def _archive_plan(directories: Sequence[Path], archive_dir: Path) -> list[tuple[Path, Path]]:
    """``(source, target)`` pairs copying the records of each run directory into
    ``archive_dir/<its name>``, without the files already there byte for byte (as
    ``wcsac-evaluate --archive`` left them: a report after it is not refused for them);
    two runs of one name cannot share the archive."""
    by_name: dict[str, Path] = {}
    for directory in dict.fromkeys(Path(d).resolve() for d in directories):
        other = by_name.setdefault(directory.name, directory)
        if other != directory:
            raise ReportError(
                f"cannot archive {other} and {directory}: both would be "
                f"{archive_dir / directory.name}; report them separately"
            )
    pairs = [
        (path, archive_dir / directory.name / path.name)
        for directory in by_name.values()
        for path in archived_records(directory)
    ]
    return [(path, target) for path, target in pairs if needs_copy(path, target)]


def _check_video(video_format: str, env: str | None) -> None:
    from wcsac_rl.evaluation.trajectories import ffmpeg_executable

    if video_format not in ("mp4", "gif"):
        raise ReportError(f"video format must be mp4 or gif, got {video_format!r}")
    if env == "tiny":
        raise ReportError(
            "videos need a MuJoCo env (static, dynamic, point_goal1, point_goal2); "
            "the tiny env does not render"
        )
    if video_format == "mp4" and ffmpeg_executable() is None:
        raise ReportError(
            "--video needs ffmpeg for mp4, which is not installed: `pip install imageio-ffmpeg` "
            "(it ships an ffmpeg binary) or install the system's ffmpeg, "
            "or pass --video-format gif (uses Pillow)"
        )


def _figure5(
    sources: Sequence[_TrajectorySource],
    out_dir: Path,
    *,
    episodes: int,
    max_steps: int | None,
    env_seed: int,
    video_format: str | None,
    title_env: str,
    styles: dict[str, plots.RowStyle],
    log: Callable[[str], None],
    stage_rows: Sequence[str] | None = None,
) -> list[Path]:
    """Figure 5: every drawn run's panel (one figure each and all in one), the stages of
    the runs with kept checkpoints, and the videos; each panel framed in its row's colour."""
    import torch

    from wcsac_rl.evaluation.trajectories import (
        collect_trajectories,
        render_episode,
        write_video,
    )

    written: list[Path] = []
    panels = []
    stages: list[list[tuple[str, dict, list]]] = []  # per run with kept checkpoints
    stage_labels: list[str] = []
    for source in sources:
        log(f"trajectories: {source.label} seed {source.seed} ({episodes} episodes)")
        policy, env, env_steps, env_name, kwargs, frames = _restore(source, env_seed)
        steps = int(max_steps or env_steps)
        try:
            torch.manual_seed(env_seed)
            layout, trajs = collect_trajectories(env, policy, episodes, max_steps=steps)
        finally:
            env.close()
        title = f"{row_name(source.label)}, seed {source.seed}"
        panels.append((title, layout, trajs))
        staged = stage_rows is None or source.label in stage_rows
        kept = kept_checkpoints(source.directory) if staged else []
        if kept:
            row = []
            for at, path in kept:
                log(f"trajectories: {source.label} seed {source.seed} at {at} frames")
                kept_layout, kept_trajs = _kept_trajectories(path, env_seed, episodes, steps)
                row.append((f"{title}: {_frames_text(at)} frames", kept_layout, kept_trajs))
            row.append((f"{title}: {_frames_text(frames)} frames (end)", layout, trajs))
            stages.append(row)
            stage_labels.append(source.label)
        plots.plot_trajectories(
            [(title, layout, trajs)],
            out_dir / f"{source.stem}.png",
            title=f"{row_name(source.label)} on {title_env}: {episodes} test episodes",
            rows=[source.label], styles=styles, formats=FORMATS,
        )  # fmt: skip
        written += _files(out_dir, [f"{source.stem}.png"])
        if video_format is not None:
            log(f"video: {source.label} seed {source.seed}")
            frames = render_episode(
                env_name, policy, seed=env_seed, max_steps=steps, **_without_steps(kwargs, steps)
            )
            written.append(write_video(frames, out_dir / f"{source.stem}.{video_format}"))
    plots.plot_trajectories(
        panels,
        out_dir / FIG5,
        title=f"Trajectories on {title_env}: {episodes} deterministic test episodes per run",
        rows=[s.label for s in sources], styles=styles, formats=FORMATS,
    )  # fmt: skip
    if stages:
        columns = max(len(row) for row in stages)
        grid = [panel for row in stages for panel in row + [None] * (columns - len(row))]
        labels = [label for label, row in zip(stage_labels, stages) for _ in range(columns)]
        plots.plot_trajectories(
            grid,
            out_dir / FIG5_STAGES,
            title=f"Trajectories on {title_env} during training: {episodes} "
            "deterministic test episodes per panel",
            columns=columns, rows=labels, styles=styles, formats=FORMATS,
        )  # fmt: skip
    return _files(out_dir, [FIG5, *([FIG5_STAGES] if stages else [])]) + written


def _frames_text(frames: int) -> str:
    """``250000`` → ``"250 k"``, ``3000000`` → ``"3 M"``."""
    if frames >= 1_000_000:
        return f"{frames / 1e6:g} M"
    if frames >= 1000:
        return f"{frames / 1e3:g} k"
    return str(frames)


def _kept_trajectories(
    checkpoint: Path, env_seed: int, episodes: int, max_steps: int
) -> tuple[dict, list]:
    """``(layout, trajectories)`` of a kept checkpoint's policy (the same env seed)."""
    import torch

    from wcsac_rl.evaluation.evaluator import load_policy
    from wcsac_rl.evaluation.trajectories import collect_trajectories

    restored = load_policy(checkpoint, env_seed)
    try:
        torch.manual_seed(env_seed)
        return collect_trajectories(restored.env, restored.policy, episodes, max_steps=max_steps)
    finally:
        restored.env.close()


def _without_steps(kwargs: dict, steps: int) -> dict:
    """``make_env`` kwargs with the episode length bounded by ``steps``."""
    out = dict(kwargs)
    out["max_episode_steps"] = min(int(out.get("max_episode_steps") or steps), steps)
    return out
