"""How many runs of each row meet the targets a study set for it (``targets.md`` / ``.csv``).

A study states its targets once, in a YAML file: per row label, per metric, a bound::

    wcsac_0.1:
      cumulative_cost: {at_most: 4000}
      C0.1: {at_most: 20}
      ER: {at_least: 0.5}
    sac_lag:
      EC: {at_most: 15}

A metric is a per-run value of the report's ``run_values.csv`` (EC, C0.1, ER, goals,
over_budget) or of its ``training_safety.csv`` (cumulative_cost, epochs_over_limit,
epochs_over_limit_after_warmup, peak_epoch_cost, safe_from_frames: one value per seed).
:func:`write_targets` reads both files of a report directory and writes

* ``targets.md``: one line per row, one column per metric, each cell "k of n" (the runs
  that meet the row's bound of n runs) with the bound;
* ``targets.csv``: one line per run and metric: its value, the bound, met or not.

A bound is met by a value equal to it. A row's runs are its lines in ``run_values.csv``;
a metric with no value for one of them (a NaN ``safe_from_frames``: the run ended over
d) counts as not met. Bad input (a file that is not such a mapping, a row or a metric the
report does not have, a bound that is not a number) is one :class:`TargetsError` line, and
nothing is written.

Command line: ``python -m wcsac_rl.evaluation.targets REPORT_DIR TARGETS.yaml``.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from wcsac_rl._messages import first_line
from wcsac_rl.evaluation.run_statistics import RUN_METRICS
from wcsac_rl.training.run_dir import replace_file

__all__ = [
    "TARGETS_CSV",
    "TARGETS_MD",
    "Target",
    "TargetsError",
    "read_targets",
    "targets_tables",
    "write_targets",
]

TARGETS_MD = "targets.md"
TARGETS_CSV = "targets.csv"
RUN_VALUES_FILE = "run_values.csv"
TRAINING_SAFETY_FILE = "training_safety.csv"

RUN_VALUE_METRICS = (*RUN_METRICS, "over_budget")
"""The metrics read from ``run_values.csv``."""

TRAINING_SAFETY_METRICS = (
    "cumulative_cost",
    "epochs_over_limit",
    "epochs_over_limit_after_warmup",
    "peak_epoch_cost",
    "safe_from_frames",
)
"""The metrics read from ``training_safety.csv`` (its ``<metric>_per_seed`` columns)."""

BOUNDS = {"at_most": "≤", "at_least": "≥"}

TITLES = {
    "over_budget": "episodes over d",
    "cumulative_cost": "cumulative training cost",
    "epochs_over_limit": "epochs over d",
    "epochs_over_limit_after_warmup": "epochs over d after the warm-up",
    "peak_epoch_cost": "peak epoch cost",
    "safe_from_frames": "≤ d for good from (frames)",
}
"""The column titles of ``targets.md`` (a metric not here is its own title)."""


class TargetsError(ValueError):
    """A targets file or a report this module cannot read: one line saying which and why."""


@dataclass(frozen=True)
class Target:
    """One row's bound on one metric: ``value`` met by ``at_most`` (≤) or ``at_least`` (≥)."""

    metric: str
    bound: str
    value: float

    def met(self, value: float) -> bool:
        if math.isnan(value):
            return False
        return value <= self.value if self.bound == "at_most" else value >= self.value

    def text(self) -> str:
        return f"{BOUNDS[self.bound]} {self.value:g}"


def read_targets(path: Path) -> dict[str, list[Target]]:
    """The targets of ``path`` (the YAML above), in the file's order."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except OSError as err:
        raise TargetsError(f"cannot read the targets file {path}: {err.strerror or err}") from None
    except yaml.YAMLError as err:
        raise TargetsError(f"the targets file {path} is not YAML: {first_line(err)}") from None
    if not isinstance(data, Mapping) or not data:
        raise TargetsError(f"the targets file {path} must map row labels to their targets")
    targets: dict[str, list[Target]] = {}
    for label, metrics in data.items():
        if not isinstance(metrics, Mapping) or not metrics:
            raise TargetsError(f"{path}: row {label!r} must map metrics to bounds")
        targets[str(label)] = [_target(path, str(label), m, b) for m, b in metrics.items()]
    return targets


def _target(path: Path, label: str, metric: Any, bound: Any) -> Target:
    where = f"{path}: {label}.{metric}"
    if metric not in (*RUN_VALUE_METRICS, *TRAINING_SAFETY_METRICS):
        known = ", ".join((*RUN_VALUE_METRICS, *TRAINING_SAFETY_METRICS))
        raise TargetsError(f"{where}: no such metric (the metrics: {known})")
    if not isinstance(bound, Mapping) or len(bound) != 1 or next(iter(bound)) not in BOUNDS:
        raise TargetsError(f"{where} must be {{at_most: <number>}} or {{at_least: <number>}}")
    kind, value = next(iter(bound.items()))
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise TargetsError(f"{where}: {kind} must be a finite number, got {value!r}")
    return Target(str(metric), kind, float(value))


def _read_csv(path: Path) -> list[dict[str, str]]:
    try:
        with path.open(newline="", encoding="utf-8") as f:
            return list(csv.DictReader(f))
    except OSError as err:
        raise TargetsError(
            f"cannot read {path}: {err.strerror or err} (write the report with --study first)"
        ) from None


def _number(text: str | None, where: str) -> float:
    try:
        return float(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise TargetsError(f"{where}: not a number: {text!r}") from None


def _per_run_values(report: Path) -> tuple[dict[str, dict[int, dict[str, float]]], dict]:
    """Row label → seed → metric → value, from the report's two CSV files; and row label →
    the row's name (its ``algorithm`` column)."""
    values: dict[str, dict[int, dict[str, float]]] = {}
    names: dict[str, str] = {}
    path = report / RUN_VALUES_FILE
    for line in _read_csv(path):
        names[line["label"]] = line.get("algorithm") or line["label"]
        seed = int(_number(line.get("seed"), f"{path}: seed"))
        values.setdefault(line["label"], {})[seed] = {
            m: _number(line.get(m), f"{path}: {line['label']} seed {seed} {m}")
            for m in RUN_VALUE_METRICS
        }
    path = report / TRAINING_SAFETY_FILE
    for line in _read_csv(path):
        label, seeds = line["label"], line.get("seed_list", "").split()
        for metric in TRAINING_SAFETY_METRICS:
            per_seed = line.get(f"{metric}_per_seed", "").split()
            if len(per_seed) != len(seeds):
                raise TargetsError(f"{path}: {label}'s {metric}_per_seed has not one per seed")
            for seed, text in zip(seeds, per_seed, strict=True):
                run = values.get(label, {}).get(int(seed))
                if run is not None:
                    run[metric] = _number(text, f"{path}: {label} seed {seed} {metric}")
    return values, names


def targets_tables(report: Path, targets: Mapping[str, Sequence[Target]]) -> dict[str, str]:
    """File name → text of ``targets.md`` and ``targets.csv`` for the report in ``report``."""
    values, names = _per_run_values(Path(report))
    for label, row_targets in targets.items():
        if label not in values:
            raise TargetsError(f"no row {label!r} in the report (rows: {', '.join(values)})")
        for target in row_targets:
            missing = [s for s, run in values[label].items() if target.metric not in run]
            if missing:
                raise TargetsError(
                    f"row {label!r} has no {target.metric} for seed {missing[0]} "
                    f"(not in {TRAINING_SAFETY_FILE})"
                )
    metrics = list(dict.fromkeys(t.metric for ts in targets.values() for t in ts))
    lines = [
        "| row | runs | " + " | ".join(TITLES.get(m, m) for m in metrics) + " |",
        "|---|---:|" + "---|" * len(metrics),
    ]
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["label", "seed", "metric", "value", "bound", "target", "met"])
    for label, row_targets in targets.items():
        runs = values[label]
        cells = dict.fromkeys(metrics, "")
        for target in row_targets:
            met = 0
            for seed in sorted(runs):
                value = runs[seed][target.metric]
                met += target.met(value)
                writer.writerow(
                    [
                        label,
                        seed,
                        target.metric,
                        repr(value),
                        target.bound,
                        repr(target.value),
                        int(target.met(value)),
                    ]
                )
            cells[target.metric] = f"{met} of {len(runs)} ({target.text()})"
        lines.append(f"| {names[label]} | {len(runs)} | " + " | ".join(cells.values()) + " |")
    markdown = "\n".join(lines) + "\n"
    return {TARGETS_MD: markdown, TARGETS_CSV: buf.getvalue()}


def write_targets(report: Path, targets_file: Path) -> list[Path]:
    """Write ``targets.md`` and ``targets.csv`` into ``report`` (all checked first)."""
    tables = targets_tables(Path(report), read_targets(Path(targets_file)))
    written = []
    for name, text in tables.items():
        written.append(replace_file(Path(report) / name, text))
    return written


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m wcsac_rl.evaluation.targets",
        description="Count the runs of each row that meet a study's targets.",
    )
    parser.add_argument("report", type=Path, help="a report directory (wcsac-report --study)")
    parser.add_argument("targets", type=Path, help="the study's targets (YAML)")
    args = parser.parse_args(argv)
    try:
        written = write_targets(args.report, args.targets)
    except TargetsError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    print(written[0].read_text(encoding="utf-8"), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
