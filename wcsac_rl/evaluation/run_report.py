"""The report's runs one by one, and each row summarised over its runs.

:func:`collect_run_statistics` checks the report's runs and computes the tables
``run_values.md`` / ``.csv`` (one line per run), ``run_statistics.md`` / ``.csv`` (per
row, the IQM over runs with its interval; the probability of improvement of the pairs
asked for) and ``improvement.csv``; :func:`write_run_statistics` writes them with
``fig_runs.png`` and ``fig_score_distribution.png``
(:func:`~wcsac_rl.evaluation.plots.plot_run_values`). What they hold and which runs may
be pooled (:data:`EXECUTION_KEYS`, :data:`EVALUATION_KEYS`): docs/evaluation_protocol.md.
A failed check leaves these files out with one warning line in a plain report, and is an
error (nothing written) in a study's (``study=True``, implied by naming pairs).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from wcsac_rl.evaluation.defaults import CLAIM_RUNS
from wcsac_rl.evaluation.latex import (
    csv_text,
    latex_path,
    markdown_cell,
    markdown_table,
    markdown_text,
    markdown_to_latex,
)
from wcsac_rl.evaluation.plots import FIGURE_FORMATS, figure_paths
from wcsac_rl.evaluation.run_statistics import (
    HELD_OUT_SEEDS,
    RUN_METRICS,
    improvement_interval,
    interval_excludes,
    iqm,
    iqm_interval,
    is_held_out,
    probability_of_improvement,
    run_values,
)
from wcsac_rl.evaluation.runs import env_has_layout, env_title, row_name, row_sort_key
from wcsac_rl.training.config import ConfigError
from wcsac_rl.training.provenance import read_provenance

__all__ = [
    "CLAIM_RUNS",
    "EVALUATION_KEYS",
    "EXECUTION_KEYS",
    "FIG_RUNS",
    "FIG_SCORE",
    "IMPROVEMENT_CSV",
    "IMPROVEMENT_METRICS",
    "RUN_STATISTICS_CSV",
    "RUN_STATISTICS_MD",
    "RUN_STATISTICS_TEX",
    "RUN_VALUES_CSV",
    "RUN_VALUES_MD",
    "RUN_VALUES_TEX",
    "RunStatistics",
    "RunStatisticsError",
    "check_improvement_pairs",
    "collect_run_statistics",
    "parse_improvement",
    "parse_improvements",
    "write_run_statistics",
]

RUN_VALUES_MD = "run_values.md"
RUN_VALUES_CSV = "run_values.csv"
RUN_STATISTICS_MD = "run_statistics.md"
RUN_STATISTICS_CSV = "run_statistics.csv"
RUN_VALUES_TEX = latex_path(RUN_VALUES_MD)
RUN_STATISTICS_TEX = latex_path(RUN_STATISTICS_MD)
IMPROVEMENT_CSV = "improvement.csv"
FIG_RUNS = "fig_runs.png"
FIG_SCORE = "fig_score_distribution.png"

IMPROVEMENT_METRICS = ("C0.1", "EC", "ER")
"""The measures the probability of improvement is given on: the costs C0.1 and EC, and the
return ER (there a lower value is the worse one)."""

EXECUTION_KEYS = (
    "seed",
    "run_name",
    "resume",
    "progress_bar",
    "save_replay_buffer",
    "checkpoint_every_epochs",
    "keep_checkpoints_at",
    "retain_freed_memory",
    "device",
    "threads",
    "compile",
    "logger",
    "trust_env_code",
    "algo.recipe",
)
"""Config keys (and sections) the runs of a row may differ in: the seed, and where and how
a run was executed, checkpointed and logged, not what was trained (``algo.recipe`` names
the files its settings came from; the settings themselves are compared). Device, threads and
compilation change the floating-point kernels as a machine does; like the machine they are
a recorded source of variation, not a setting."""

EVALUATION_KEYS = ("algo", "env", "cost_limit", "risk_level", "trained_frames", "policy",
                   "max_episode_steps", "episodes")  # fmt: skip
"""``evaluation.json`` settings the runs of a row must share (and the env-seed offset,
``env_seed - seed``)."""

RUN_COLUMNS = ("label", "algorithm", "seed", "split", "machine", "run", "EC", "C0.1", "ER",
               "goals", "over_budget", "episodes")  # fmt: skip
ROW_COLUMNS = (
    "label",
    "algorithm",
    "runs",
    "held_out_runs",
    "seed_list",
    "machines",
    *(f"{metric}_{part}" for metric in RUN_METRICS for part in ("iqm", "lo", "hi")),
)
IMPROVEMENT_COLUMNS = ("a", "b", "metric", "p_a_lower", "lo", "hi", "runs_a", "runs_b",
                       "held_out_a", "held_out_b", "reading")  # fmt: skip


class RunStatisticsError(ConfigError):
    """The statistics over runs cannot be made from these runs; the message says why."""


def parse_improvement(text: str) -> tuple[str, str]:
    """``"wcsac_0.1:sac_lag"`` → ``("wcsac_0.1", "sac_lag")``: row A, whose runs should have
    the lower cost, and row B.

    >>> parse_improvement("wcsac_0.1:sac_lag_d1.5")
    ('wcsac_0.1', 'sac_lag_d1.5')
    """
    a, sep, b = text.partition(":")
    if not sep or not a or not b or ":" in b:
        raise RunStatisticsError(
            f"--improvement takes A:B, two row labels (e.g. wcsac_0.1:sac_lag), got {text!r}"
        )
    check_improvement_pairs([(a, b)])
    return a, b


def parse_improvements(texts: Sequence[str]) -> list[tuple[str, str]]:
    """Every ``--improvement A:B`` (:func:`parse_improvement`), refusing a pair given twice.

    >>> parse_improvements(["wcsac_0.1:sac_lag", "wcsac_0.1:sac_lag_d1.5"])
    [('wcsac_0.1', 'sac_lag'), ('wcsac_0.1', 'sac_lag_d1.5')]
    """
    pairs = [parse_improvement(text) for text in texts]
    check_improvement_pairs(pairs)
    return pairs


def check_improvement_pairs(pairs: Sequence[tuple[str, str]]) -> None:
    """Refuse (:class:`RunStatisticsError`, one line) a row set against itself (its P is
    0.5 by construction, no finding) and a pair asked for twice (its lines twice)."""
    seen: set[tuple[str, str]] = set()
    for a, b in pairs:
        if a == b:
            raise RunStatisticsError(
                f"--improvement {a}:{b} sets row {a!r} against itself; name two different rows"
            )
        if (a, b) in seen:
            raise RunStatisticsError(f"--improvement {a}:{b} is given twice; give each pair once")
        seen.add((a, b))


@dataclass
class RunStatistics:
    """What :func:`collect_run_statistics` made: per-run values (``runs``), per-row
    statistics (``rows``), the pairs (``improvements``) and the rows left out for having
    one run."""

    env: str | None
    cost_limit: float
    runs: list[dict[str, Any]]
    rows: list[dict[str, Any]]
    improvements: list[dict[str, Any]] = field(default_factory=list)
    single: list[str] = field(default_factory=list)

    def tables(self) -> dict[str, str]:
        """File name → text of every table."""
        values, statistics = run_values_markdown(self), run_statistics_markdown(self)
        files = {
            RUN_VALUES_MD: values,
            RUN_VALUES_CSV: csv_text(self.runs, _columns(self, RUN_COLUMNS)),
            RUN_VALUES_TEX: markdown_to_latex(values),
            RUN_STATISTICS_MD: statistics,
            RUN_STATISTICS_CSV: csv_text(self.rows, _columns(self, ROW_COLUMNS)),
            RUN_STATISTICS_TEX: markdown_to_latex(statistics),
        }
        if self.improvements:
            files[IMPROVEMENT_CSV] = csv_text(self.improvements, IMPROVEMENT_COLUMNS)
        return files

    def file_names(self, formats: Sequence[str] = FIGURE_FORMATS) -> list[str]:
        """Every file :func:`write_run_statistics` writes (tables, and the figures in
        each of ``formats``)."""
        figures = [
            p.name for name in (FIG_RUNS, FIG_SCORE) for p in figure_paths(Path(name), formats)
        ]
        return [*self.tables(), *figures]


def _machine_text(records: Sequence[dict[str, Any]]) -> str:
    """The CPU model and kernel capability of each session (``provenance.json``)."""
    shown = []
    for record in records:
        machine = record.get("machine") if isinstance(record, dict) else None
        if not isinstance(machine, dict):
            continue
        if not machine.get("processor") and not machine.get("cpu_capability"):
            continue
        text = str(machine.get("processor") or "?")
        if machine.get("cpu_capability"):
            text += f" ({machine['cpu_capability']})"
        if text not in shown:
            shown.append(text)
    return " + ".join(shown) if shown else "not recorded"


def _flat(config: Any, prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    for key, value in config.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = repr(value)
    return out


def _settings(directory: Path, meta: dict[str, Any], config_of: Callable[[Path], Any]) -> dict:
    """The settings of a run its row's other runs must share (see the module docstring)."""
    settings: dict[str, str] = {}
    cfg = config_of(directory)
    if cfg is not None:
        # a run's files are data: a stored config holds resolved values, and a ``${...}``
        # in one is compared as written, never resolved (docs/guarantees.md)
        plain = OmegaConf.to_container(cfg, resolve=False)
        for key, value in _flat(plain).items():
            if key not in EXECUTION_KEYS and key.split(".", 1)[0] not in EXECUTION_KEYS:
                settings[key] = value
    for key in EVALUATION_KEYS:
        settings[f"evaluation {key}"] = repr(meta.get(key))
    try:
        offset = int(meta["env_seed"]) - int(meta["seed"])
    except (KeyError, TypeError, ValueError):
        offset = None
    settings["evaluation env_seed - seed"] = repr(offset)
    return settings


def _differing(runs: Sequence[dict[str, Any]]) -> str | None:
    """The first setting the runs of one row differ in, with each value's runs. A key some
    runs' configs lack (an option added after they ran, which a run without it trained at
    its default) is not compared, as Table 1's row labels do not compare it."""
    keys = sorted(set.intersection(*(set(r["_settings"]) for r in runs)))
    for key in keys:
        by_value: dict[str, list[str]] = defaultdict(list)
        for run in runs:
            by_value[run["_settings"][key]].append(run["run"])
        if len(by_value) > 1:
            listing = "; ".join(f"{value}: {', '.join(names)}" for value, names in by_value.items())
            return f"{key} ({listing})"
    return None


def _problems(by_row: dict[str, list[dict[str, Any]]], unevaluated: Sequence[str]) -> list[str]:
    """What makes statistics over these runs unsound, one line each."""
    problems = []
    if unevaluated:
        problems.append(
            f"{len(unevaluated)} run(s) have no readable evaluation (evaluation.json and "
            f"evaluation.csv): {', '.join(unevaluated)}; evaluate them "
            "(python -m wcsac_rl.evaluate) or report without them"
        )
    for label, runs in by_row.items():
        seeds: dict[int, int] = defaultdict(int)
        for run in runs:
            seeds[run["seed"]] += 1
        twice = sorted(seed for seed, n in seeds.items() if n > 1)
        if twice:
            problems.append(
                f"row {label} has several runs of seed(s) {', '.join(map(str, twice))}: "
                "statistics over runs count each seed once"
            )
        differing = _differing(runs)
        if differing is not None:
            problems.append(
                f"the runs of row {label} were made with different settings: {differing}; "
                "statistics over runs pool runs of one configuration"
            )
    return problems


def _row_statistics(label: str, runs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    machines: dict[str, int] = defaultdict(int)
    for run in runs:
        machines[run["machine"]] += 1
    row: dict[str, Any] = {
        "label": label,
        "algorithm": row_name(label),
        "runs": len(runs),
        "held_out_runs": sum(run["split"] == "held-out" for run in runs),
        "seed_list": " ".join(str(run["seed"]) for run in runs),
        "machines": "; ".join(f"{m}: {n}" for m, n in sorted(machines.items())),
    }
    for metric in RUN_METRICS:
        values = [run[metric] for run in runs]
        row[f"{metric}_iqm"] = iqm(values)
        row[f"{metric}_lo"], row[f"{metric}_hi"] = iqm_interval(values)
    return row


def _reading(p: float, interval: tuple[float, float], a: dict, b: dict) -> str:
    """Within noise, or which row is lower and whether that is a claim."""
    if not interval_excludes(interval, 0.5):
        return "within noise"
    lower = a["algorithm"] if p > 0.5 else b["algorithm"]
    if a["held_out_runs"] < a["runs"] or b["held_out_runs"] < b["runs"]:
        return f"{lower} lower; not a claim: in-sample runs"
    if min(a["runs"], b["runs"]) < CLAIM_RUNS:
        return f"{lower} lower; not a claim: fewer than {CLAIM_RUNS} held-out runs a row"
    return f"{lower} lower"


def _improvement(a: dict, b: dict, runs_a: list[dict], runs_b: list[dict]) -> list[dict]:
    out = []
    for metric in IMPROVEMENT_METRICS:
        x = [run[metric] for run in runs_a]
        y = [run[metric] for run in runs_b]
        p = probability_of_improvement(x, y)
        lo, hi = improvement_interval(x, y)
        out.append(
            {
                "a": a["label"],
                "b": b["label"],
                "metric": metric,
                "p_a_lower": p,
                "lo": lo,
                "hi": hi,
                "runs_a": a["runs"],
                "runs_b": b["runs"],
                "held_out_a": a["held_out_runs"],
                "held_out_b": b["held_out_runs"],
                "reading": _reading(p, (lo, hi), a, b),
            }
        )
    return out


def _run_record(ev: Any, cost_limit: float, config_of: Callable[[Path], Any]) -> dict[str, Any]:
    seed = int(ev.meta.get("seed", -1))
    directory = Path(ev.directory)
    values = run_values(ev.costs, ev.returns, [e.goal_reached for e in ev.episodes], cost_limit)
    overflowed = [metric for metric in RUN_METRICS if not math.isfinite(values[metric])]
    if overflowed:  # (finite episodes whose sum is not: 1e308 each)
        raise RunStatisticsError(
            f"run {directory.name}: its {', '.join(overflowed)} over its episodes is not a "
            "finite number (the episode values are too large to add up)"
        )
    return {
        "label": ev.label,
        "algorithm": row_name(ev.label),
        "seed": seed,
        "split": "held-out" if is_held_out(seed) else "in-sample",
        "machine": _machine_text(read_provenance(directory)),
        "run": directory.name,
        **values,
        "_settings": _settings(directory, ev.meta, config_of),
    }


def collect_run_statistics(
    evaluations: Sequence[Any],
    unevaluated: Sequence[str],
    *,
    env: str | None,
    cost_limit: float,
    config_of: Callable[[Path], Any],
    improvement: Sequence[tuple[str, str]] = (),
    study: bool = False,
    warn: Callable[[str], None] = lambda _: None,
) -> RunStatistics | None:
    """Check the runs and compute every per-run value and statistic over runs.

    Args:
        evaluations: the report's evaluations (their labels are the report's rows).
        unevaluated: names of runs below the paths without a readable evaluation.
        env: the report's env; cost_limit: its budget d.
        config_of: a run directory → its config (the last session's), ``None`` if none.
        improvement: ``(A, B)`` row pairs for the probability of improvement.
        study: problems are errors (implied by ``improvement``).
        warn: where a plain report's one-line notes go.

    Returns:
        the statistics, or ``None`` when a plain report leaves them out (said in ``warn``).

    Raises:
        RunStatisticsError: in a study, the first problem, a pair naming an absent row or
            one of fewer than 2 runs, or a row of fewer than 2 runs.
    """
    check_improvement_pairs(improvement)
    study = study or bool(improvement)
    if not evaluations:
        if study:
            raise RunStatisticsError("statistics over runs need evaluated runs; found none")
        return None
    runs = [_run_record(ev, cost_limit, config_of) for ev in evaluations]
    runs.sort(key=lambda r: (row_sort_key(r["label"]), r["seed"], r["run"]))
    by_row: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for run in runs:
        by_row[run["label"]].append(run)
    for a, b in improvement:
        for label in (a, b):
            if label not in by_row:
                raise RunStatisticsError(
                    f"--improvement {a}:{b}: no row {label!r} (rows: {', '.join(by_row)})"
                )
    problems = _problems(by_row, unevaluated)
    if problems:
        if study:
            raise RunStatisticsError(problems[0])
        warn(f"per-run statistics skipped: {problems[0]}")
        return None
    single = [label for label, members in by_row.items() if len(members) < 2]
    if single:
        counts = ", ".join(f"{label} ({len(by_row[label])})" for label in single)
        if study:
            raise RunStatisticsError(
                f"statistics over runs need >= 2 runs of a row; found 1 of row(s) {counts}"
            )
        warn(f"row(s) of one run left out of the statistics over runs: {counts}")
    rows = {
        label: _row_statistics(label, members)
        for label, members in by_row.items()
        if label not in single
    }
    improvements = [
        entry
        for a, b in improvement
        for entry in _improvement(rows[a], rows[b], by_row[a], by_row[b])
    ]
    for run in runs:
        del run["_settings"]
    return RunStatistics(env, cost_limit, runs, list(rows.values()), improvements, single)


# --------------------------------------------------------------------------- tables
def _metrics(stats: RunStatistics) -> list[str]:
    """The metrics the tables show: :data:`RUN_METRICS` without goals for an env without
    goals (:func:`~wcsac_rl.evaluation.runs.env_has_layout`)."""
    return [m for m in RUN_METRICS if m != "goals" or env_has_layout(stats.env)]


def _columns(stats: RunStatistics, columns: Sequence[str]) -> list[str]:
    """A CSV's ``columns`` without those of goals for an env without goals."""
    goals = env_has_layout(stats.env)
    return [c for c in columns if goals or not (c == "goals" or c.startswith("goals_"))]


def _title(stats: RunStatistics) -> str:
    env = markdown_text(env_title(stats.env)) if stats.env else "?"
    return f"{env}, budget d = {stats.cost_limit:g}"


def run_values_markdown(stats: RunStatistics) -> str:
    """``run_values.md``: every run on its own line."""
    metrics = _metrics(stats)
    lines = [
        f"# Runs one by one — {_title(stats)}",
        "",
        *markdown_table(
            ["row", "seed", "split", "machine", *metrics, "episodes", "run"],
            "lrll" + "r" * len(metrics) + "rl",
            (
                [
                    *(markdown_cell(run[key]) for key in ("algorithm", "seed", "split", "machine")),
                    *(f"{run[m]:.2f}" for m in metrics),
                    run["episodes"],
                    markdown_cell(run["run"]),
                ]
                for run in stats.runs
            ),
        ),
    ]
    lo, hi = HELD_OUT_SEEDS[0], HELD_OUT_SEEDS[-1]
    lines += [
        "",
        "Each run's deterministic test episodes: EC their mean cost, C0.1 the mean cost of the "
        "worst ⌈n·0.1⌉ of them, ER their mean return"
        + (", goals per episode" if "goals" in metrics else "")
        + ". split: held-out "
        f"(training seeds {lo}-{hi}, fixed before the runs and used to choose nothing) or "
        "in-sample (any other seed). machine: the CPU and the vector instructions of its "
        "kernels, from the run's provenance.json (docs/evaluation_protocol.md).",
        "",
    ]
    return "\n".join(lines)


def _cell(row: dict[str, Any], metric: str) -> str:
    return f"{row[metric + '_iqm']:.2f} [{row[metric + '_lo']:.2f}, {row[metric + '_hi']:.2f}]"


def run_statistics_markdown(stats: RunStatistics) -> str:
    """``run_statistics.md``: IQM over runs per row, and the pairs' P(improvement)."""
    metrics = _metrics(stats)
    lines = [
        f"# Statistics over runs — {_title(stats)}",
        "",
        *markdown_table(
            ["row", "runs (held-out)", *metrics, "machines"],
            "lr" + "r" * len(metrics) + "l",
            (
                [
                    markdown_cell(row["algorithm"]),
                    f"{row['runs']} ({row['held_out_runs']})",
                    *(_cell(row, m) for m in metrics),
                    markdown_cell(row["machines"]),
                ]
                for row in stats.rows
            ),
        ),
        "",
        "Each cell: the interquartile mean over the row's runs of the run's value "
        "(run_values.md), scipy.stats.trim_mean(·, 0.25) as rliable's IQM, and its 95 % "
        "stratified bootstrap interval (the runs resampled, percentile method, seeded).",
    ]
    if stats.single:
        lines.append(
            "Left out (one run: no statistics over runs): "
            + ", ".join(markdown_text(row_name(label)) for label in stats.single)
            + "."
        )
    lines.append("")
    if stats.improvements:
        lines += [
            "## Probability of improvement",
            "",
            *markdown_table(
                ["A", "B", "measure", "P(run of A lower)", "runs A, B (held-out)", "reading"],
                "lllrll",
                (
                    [
                        markdown_cell(row_name(e["a"])),
                        markdown_cell(row_name(e["b"])),
                        e["metric"],
                        f"{e['p_a_lower']:.2f} [{e['lo']:.2f}, {e['hi']:.2f}]",
                        f"{e['runs_a']} ({e['held_out_a']}), {e['runs_b']} ({e['held_out_b']})",
                        markdown_cell(e["reading"]),
                    ]
                    for e in stats.improvements
                ),
            ),
            "",
            "P(run of A lower): the probability that a run of A has a lower value than a run "
            "of B, ties counting half (P(X < Y) + ½ P(X = Y) over all pairs of runs), with "
            "its 95 % bootstrap interval (the runs of each row resampled independently); on "
            "ER, a lower value is the lower return. An ordering is read only where that "
            "interval excludes 0.5, and claimed only from held-out runs, at least "
            f"{CLAIM_RUNS} a row; otherwise: within noise.",
            "",
        ]
    return "\n".join(lines)


def write_run_statistics(
    stats: RunStatistics | None,
    out_dir: Path,
    write_text: Callable[[Path, str], Path],
    *,
    styles: Mapping[str, Any] | None = None,
    formats: Sequence[str] = FIGURE_FORMATS,
) -> list[Path]:
    """Write the tables (with ``write_text``; each Markdown table also as LaTeX) and the two
    figures (each row in its ``styles``, as :func:`~wcsac_rl.evaluation.plots.row_styles`
    gives; each in ``formats``); return the paths (none for ``None``: statistics left out)."""
    from wcsac_rl.evaluation.plots import plot_run_values, plot_score_distribution

    if stats is None:
        return []

    files = [write_text(out_dir / name, text) for name, text in stats.tables().items()]
    title = _title(stats)
    for plot, name in ((plot_run_values, FIG_RUNS), (plot_score_distribution, FIG_SCORE)):
        plot(stats, out_dir / name, title=title, styles=styles, formats=formats)
        files += figure_paths(out_dir / name, formats)
    return files
