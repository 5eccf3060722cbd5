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
nothing is written. So is a key the targets file gives twice (YAML would keep the last
silently), a report line whose seed is not a whole number or whose run (row and seed) an
earlier line gives, a file that is not UTF-8 text, and a table that cannot be written (a
full disk, a read-only folder): both tables are staged beside their places first, then
renamed into them.

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
from wcsac_rl.evaluation.latex import markdown_table
from wcsac_rl.evaluation.run_report import RUN_VALUES_CSV as RUN_VALUES_FILE
from wcsac_rl.evaluation.run_statistics import RUN_METRICS
from wcsac_rl.evaluation.training_safety_table import METRICS
from wcsac_rl.evaluation.training_safety_table import TRAINING_SAFETY_CSV as TRAINING_SAFETY_FILE
from wcsac_rl.training.run_dir import replace_files

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

RUN_VALUE_METRICS = (*RUN_METRICS, "over_budget")
"""The metrics read from ``run_values.csv``."""

TRAINING_SAFETY_METRICS = tuple(m for m in METRICS if m not in ("frames", "epochs"))
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


class _DuplicateKey(Exception):
    """A mapping of the targets file names ``key`` on ``line`` and again on ``again``."""

    def __init__(self, key: Any, line: int, again: int) -> None:
        super().__init__(key, line, again)
        self.key, self.line, self.again = key, line, again


def _unique_key_loader():
    """A YAML safe loader that refuses a mapping giving one key twice (YAML keeps the last)."""
    import yaml

    class UniqueKeyLoader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            seen: dict[Any, int] = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key, line = self.construct_object(key_node, deep=True), key_node.start_mark.line
                try:
                    if key in seen:
                        raise _DuplicateKey(key, seen[key] + 1, line + 1)
                    seen[key] = line
                except TypeError:  # an unhashable key: the safe loader's own error
                    break
            return super().construct_mapping(node, deep=deep)

    return UniqueKeyLoader


def _load_targets_yaml(path: Path) -> Any:
    import yaml

    try:
        text = Path(path).read_bytes().decode("utf-8")
        return yaml.load(text, Loader=_unique_key_loader())
    except OSError as err:
        raise TargetsError(f"cannot read the targets file {path}: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise TargetsError(
            f"the targets file {path} is not UTF-8 text ({err.reason} at byte {err.start})"
        ) from None
    except _DuplicateKey as dup:
        raise TargetsError(
            f"{path}: line {dup.again}: {dup.key!r} is given twice (first on line {dup.line}); "
            "give each row, and each metric of a row, once"
        ) from None
    except (yaml.YAMLError, ValueError, RecursionError) as err:
        raise TargetsError(f"the targets file {path} is not YAML: {_yaml_problem(err)}") from None


def _yaml_problem(err: Exception) -> str:
    """What a YAML error says is wrong, with its line where it has one."""
    import yaml

    mark = getattr(err, "problem_mark", None)
    if isinstance(err, yaml.MarkedYAMLError) and err.problem and mark is not None:
        return f"line {mark.line + 1}: {err.problem}"
    return first_line(err)


def read_targets(path: Path) -> dict[str, list[Target]]:
    """The targets of ``path`` (the YAML above), in the file's order."""
    data = _load_targets_yaml(path)
    if not isinstance(data, Mapping) or not data:
        raise TargetsError(f"the targets file {path} must map row labels to their targets")
    targets: dict[str, list[Target]] = {}
    for label, metrics in data.items():
        if not isinstance(metrics, Mapping) or not metrics:
            raise TargetsError(f"{path}: row {label!r} must map metrics to bounds")
        if str(label) in targets:
            raise TargetsError(f"{path}: row {str(label)!r} is given twice (as {label!r})")
        targets[str(label)] = [_target(path, str(label), m, b) for m, b in metrics.items()]
    return targets


def _shown(value: Any, limit: int = 40) -> str:
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}… ({len(text)} characters)"


def _target(path: Path, label: str, metric: Any, bound: Any) -> Target:
    where = f"{path}: {label}.{metric}"
    if metric not in (*RUN_VALUE_METRICS, *TRAINING_SAFETY_METRICS):
        known = ", ".join((*RUN_VALUE_METRICS, *TRAINING_SAFETY_METRICS))
        raise TargetsError(f"{where}: no such metric (the metrics: {known})")
    if not isinstance(bound, Mapping) or len(bound) != 1 or next(iter(bound)) not in BOUNDS:
        raise TargetsError(f"{where} must be {{at_most: <number>}} or {{at_least: <number>}}")
    kind, value = next(iter(bound.items()))
    number = math.nan
    if isinstance(value, int | float) and not isinstance(value, bool):
        try:
            number = float(value)
        except OverflowError:  # an integer past the largest float
            pass
    if not math.isfinite(number):
        raise TargetsError(f"{where}: {kind} must be a finite number, got {_shown(value)}")
    return Target(str(metric), kind, number)


Rows = list[tuple[int, dict[str, str]]]


def _read_csv(path: Path, required: Sequence[str]) -> Rows:
    """The lines of the CSV file ``path`` as (line number, column → text); its header must
    hold the ``required`` columns."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            rows = [(reader.line_num, line) for line in reader]
            columns = reader.fieldnames or []
    except OSError as err:
        raise TargetsError(
            f"cannot read {path}: {err.strerror or err} (write the report with --study first)"
        ) from None
    except UnicodeDecodeError as err:
        raise TargetsError(f"{path} is not UTF-8 text ({err.reason} at byte {err.start})") from None
    except csv.Error as err:
        raise TargetsError(f"{path}: line {reader.line_num}: not CSV: {first_line(err)}") from None
    missing = [c for c in required if c not in columns]
    if missing:
        raise TargetsError(
            f"{path} has no column {', '.join(missing)} (its columns must include "
            f"{', '.join(required)})"
        )
    return rows


def _number(text: str | None, where: str) -> float:
    try:
        return float(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise TargetsError(f"{where}: not a number: {text!r}") from None


def _seed(text: str | None, where: str) -> int:
    """A seed's text as its integer: a whole, finite number (``100`` or ``100.0``)."""
    try:
        return int(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        pass
    value = math.nan
    try:
        value = float(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        pass
    if not math.isfinite(value) or not value.is_integer():
        raise TargetsError(f"{where}: a seed must be a whole number, got {_shown(text)}")
    return int(value)


RunValues = dict[str, dict[int, dict[str, float]]]


def _run_values(path: Path) -> tuple[RunValues, dict[str, str]]:
    """Row label → seed → metric → value, from ``run_values.csv``; and row label → the
    row's name (its ``algorithm`` column)."""
    values: RunValues = {}
    names: dict[str, str] = {}
    first: dict[tuple[str, int], int] = {}
    for n, line in _read_csv(path, ("label", "seed", *RUN_VALUE_METRICS)):
        label = line["label"]
        seed = _seed(line["seed"], f"{path}: line {n}: row {label!r}")
        if (label, seed) in first:
            raise TargetsError(
                f"{path}: line {n}: row {label!r} has seed {seed} twice "
                f"(first on line {first[label, seed]}); give each run one line"
            )
        first[label, seed] = n
        names[label] = line.get("algorithm") or label
        values.setdefault(label, {})[seed] = {
            m: _number(line[m], f"{path}: line {n}: {label} seed {seed} {m}")
            for m in RUN_VALUE_METRICS
        }
    return values, names


def _seed_list(text: str | None, where: str) -> list[int]:
    """The seeds of a ``seed_list`` cell ("100 101 102"), each once."""
    seeds = [_seed(s, f"{where}: seed_list") for s in (text or "").split()]
    if len(set(seeds)) != len(seeds):
        raise TargetsError(f"{where}: seed_list names a seed twice: {text!r}")
    return seeds


def _add_training_safety(path: Path, values: RunValues) -> None:
    """Add the per-seed metrics of ``training_safety.csv`` to the runs of ``values``."""
    first: dict[str, int] = {}
    for n, line in _read_csv(path, ("label", "seed_list")):
        label = line["label"]
        where = f"{path}: line {n}: row {label!r}"
        if label in first:
            raise TargetsError(f"{where} is given twice (first on line {first[label]})")
        first[label] = n
        seeds = _seed_list(line["seed_list"], where)
        for metric in TRAINING_SAFETY_METRICS:
            per_seed = (line.get(f"{metric}_per_seed") or "").split()
            if len(per_seed) != len(seeds):
                raise TargetsError(f"{where}: {metric}_per_seed has not one per seed")
            for seed, text in zip(seeds, per_seed, strict=True):
                run = values.get(label, {}).get(seed)
                if run is not None:
                    run[metric] = _number(text, f"{where}: seed {seed} {metric}")


def _per_run_values(report: Path) -> tuple[RunValues, dict[str, str]]:
    """Row label → seed → metric → value, from the report's two CSV files; and row label →
    the row's name (its ``algorithm`` column)."""
    values, names = _run_values(report / RUN_VALUES_FILE)
    _add_training_safety(report / TRAINING_SAFETY_FILE, values)
    return values, names


def _cell(text: str) -> str:
    """``text`` as one Markdown table cell: its ``|`` (and ``\\``) escaped, on one line."""
    one_line = " ".join(text.splitlines())
    return one_line.replace("\\", "\\\\").replace("|", "\\|")


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
    rows = []
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
        rows.append([_cell(names[label]), len(runs), *cells.values()])
    header = ["row", "runs", *(TITLES.get(m, m) for m in metrics)]
    markdown = "\n".join(markdown_table(header, "lr" + "l" * len(metrics), rows)) + "\n"
    return {TARGETS_MD: markdown, TARGETS_CSV: buf.getvalue()}


def write_targets(report: Path, targets_file: Path) -> list[Path]:
    """Write ``targets.md`` and ``targets.csv`` into ``report`` (all checked first), both
    or neither (:func:`~wcsac_rl.training.run_dir.replace_files`): a failed write (a full
    disk, a read-only folder) leaves the earlier tables and no staged file, one
    :class:`TargetsError`."""
    report = Path(report)
    tables = targets_tables(report, read_targets(Path(targets_file)))
    try:
        return replace_files({report / name: text for name, text in tables.items()})
    except OSError as err:
        raise TargetsError(f"cannot write {err.filename}: {err.strerror or err}") from None


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
