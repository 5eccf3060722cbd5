"""Side-by-side table of evaluated runs: final test cost/return and safety-critic calibration.

For each run directory (already evaluated by ``python -m wcsac_rl.evaluate`` and,
for WCSAC / SAC-Lag runs, ``python -m wcsac_rl.calibration``) one row: the Table-1
metrics of its test episodes (EC, C0.9, C0.5, C0.1, ER, share over budget), the κ, training
cost rate (cost of all training episodes per frame) and wall time at the end of
training, and the calibration of the start-state estimate (predicted
Γ_α(s0), and the CVaR_α of the critic's start-state distributions mixed over the
episodes, vs the realised CVaR_α of the discounted cost-to-go, with their ratios, Q^c(s0) vs
the realised mean, the share of visited states with Q^c < 0, √V^c(s0) vs the spread
of realised costs). Then one row per label: the mean over its seeds.

``python -m paper.compare RUN_DIR ... [--out table.md]`` prints (and
writes) the markdown table that docs/defaults.md quotes.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

from wcsac_rl.training.progress import read_progress
from wcsac_rl.training.safe_load import load_json

__all__ = ["COLUMNS", "compare_runs", "format_table", "run_row"]

COLUMNS = (
    ("label", "row"),
    ("seed", "seed"),
    ("frames", "frames"),
    ("minutes", "wall min"),
    ("EC", "EC"),
    ("C0.9", "C0.9"),
    ("C0.5", "C0.5"),
    ("C0.1", "C0.1"),
    ("ER", "ER"),
    ("over_budget", "> d"),
    ("kappa", "κ end"),
    ("cost_rate", "cost rate"),
    ("start_cvar", "Γ(s0)"),
    ("start_realised_cvar", "CVaR real"),
    ("start_cvar_ratio", "ratio"),
    ("start_tail_cvar", "mixture Γ"),
    ("start_tail_ratio", "mix ratio"),
    ("start_cost_value", "Q^c(s0)"),
    ("start_realised_cost_to_go", "mean real"),
    ("start_std", "√V(s0)"),
    ("realised_spread", "spread"),
    ("negative_share", "Q^c<0"),
)


def _read_json(path: Path) -> dict | None:
    """A record's JSON object (``None`` when the file is absent); one that is not an
    object with a ``metrics`` object is a ``ValueError`` naming the file."""
    if not path.exists():
        return None
    try:
        record = load_json(path)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not JSON ({err})") from None
    if not isinstance(record, dict) or not isinstance(record.get("metrics"), dict):
        raise ValueError(f"{path}: not a record of wcsac_rl (a JSON object with 'metrics')")
    return record


def run_row(run_dir: Path) -> dict[str, float | str]:
    """One run's numbers (NaN where an evaluation or calibration is missing)."""
    run_dir = Path(run_dir)
    evaluation = _read_json(run_dir / "evaluation.json")
    if evaluation is None:
        raise FileNotFoundError(f"{run_dir}: no evaluation.json (run python -m wcsac_rl.evaluate)")
    row: dict[str, float | str] = {
        "label": evaluation.get("label", run_dir.name),
        "seed": evaluation.get("seed", math.nan),
        "frames": evaluation.get("trained_frames", math.nan),
    }
    metrics = evaluation["metrics"]
    row.update({k: metrics[k] for k in ("EC", "C0.9", "C0.5", "C0.1", "ER", "over_budget")})
    progress = read_progress(run_dir / "progress.csv")
    row["minutes"] = progress["time_s"][-1] / 60 if progress else math.nan
    row["kappa"] = progress.get("loss/kappa", [math.nan])[-1] if progress else math.nan
    # the paper's training cost rate: all training cost so far / frames
    row["cost_rate"] = progress.get("train/cost_rate", [math.nan])[-1] if progress else math.nan
    calibration = _read_json(run_dir / "calibration.json")
    for key, _ in COLUMNS:
        if key not in row:
            value = None if calibration is None else calibration["metrics"].get(key)
            row[key] = math.nan if value is None else value
    return row


def compare_runs(run_dirs: Sequence[Path]) -> tuple[list[dict], list[dict]]:
    """Per-run rows, and per-label means over seeds (in order of first appearance)."""
    rows = [run_row(d) for d in run_dirs]
    groups: dict[str, list[dict]] = defaultdict(list)
    for row in rows:
        groups[str(row["label"])].append(row)
    means = []
    for label, members in groups.items():
        mean: dict[str, float | str] = {"label": label, "seed": f"mean of {len(members)}"}
        for key, _ in COLUMNS[2:]:
            values = [float(m[key]) for m in members if not math.isnan(float(m[key]))]
            mean[key] = statistics.fmean(values) if values else math.nan
        means.append(mean)
    return rows, means


def _fmt(value) -> str:
    if isinstance(value, str):
        return value
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    if isinstance(value, int) or (float(value).is_integer() and abs(value) >= 1000):
        return f"{int(value)}"
    return f"{value:.2f}"


def format_table(rows: list[dict], means: list[dict]) -> str:
    """A markdown table: every run, then the per-label means in bold-free summary rows."""
    lines = [
        "| " + " | ".join(title for _, title in COLUMNS) + " |",
        "|" + "---|" * len(COLUMNS),
    ]
    for row in [*rows, *means]:
        lines.append("| " + " | ".join(_fmt(row[key]) for key, _ in COLUMNS) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m paper.compare")
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=None, help="also write the table here")
    args = parser.parse_args(argv)
    if args.out is not None and args.out.is_dir():
        parser.error(f"--out {args.out} is a directory; name the file to write the table to")
    try:
        table = format_table(*compare_runs(args.runs))
    except (OSError, ValueError, KeyError) as err:  # a run not evaluated, a torn file
        detail = f"{err.args[0]!r} missing" if isinstance(err, KeyError) else str(err)
        sys.exit(f"error: {detail}")
    print(table)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(table + "\n")


if __name__ == "__main__":
    main()
