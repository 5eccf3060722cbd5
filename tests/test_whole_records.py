"""Readers of a run's records read only whole data: a row a killed process left
half-written is skipped with one warning line, never parsed into a wrong number; the
report never pools runs of different configurations into one row, reports a run whose
name is not UTF-8, and leaves no temporary file on an error."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import pytest
from _evaluation_helpers import copy_sweep, run_dirs

from wcsac_rl.evaluation.evaluator import evaluate_run
from wcsac_rl.evaluation.reporting import build_report
from wcsac_rl.training.progress import read_progress

HEADER = "epoch,frames,train/episode_cost\r\n"
WHOLE = "1,400,3.5\r\n2,800,2.25\r\n"


@pytest.mark.parametrize(
    ("tail", "why"),
    [
        ("3,1200,1.", "a number cut short (no line end)"),
        ("3,1200,12\r\n"[:-2], "the last row without its line end"),
        ("3,12\r\n", "fewer fields"),
        ("3,1200,1.5,9\r\n", "more fields"),
        ("3,1200,1.2e\r\n", "not a number"),
    ],
)
def test_a_half_written_last_row_is_skipped_with_one_warning_line(tmp_path, capsys, tail, why):
    path = tmp_path / "progress.csv"
    path.write_text(HEADER + WHOLE + tail, newline="")
    columns = read_progress(path)
    assert columns["frames"] == [400.0, 800.0], why
    assert columns["train/episode_cost"] == [3.5, 2.25]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warning: {path}: skipped 1 incomplete row")
    read_progress(path, warn=False)
    assert capsys.readouterr().err == ""


def test_whole_rows_and_empty_cells_read_without_a_warning(tmp_path, capsys):
    path = tmp_path / "progress.csv"
    path.write_text(HEADER + WHOLE + "3,1200,\r\n", newline="")
    columns = read_progress(path)
    assert columns["frames"] == [400.0, 800.0, 1200.0]
    assert math.isnan(columns["train/episode_cost"][2])
    assert capsys.readouterr().err == ""
    path.write_text("epoch,fra", newline="")  # killed while writing the header
    assert read_progress(path) == {}


# ------------------------------------------------------------------ the report
@pytest.fixture(scope="module")
def evaluated_sweep(tmp_path_factory):
    """The tiny sweep (WCSAC α = 0.5 and random, two seeds each), every run evaluated."""
    sweep = copy_sweep(tmp_path_factory.mktemp("records"))
    for run_dir in run_dirs(sweep):
        evaluate_run(run_dir, episodes=2, progress=False)
    return sweep


@pytest.fixture
def sweep(evaluated_sweep, tmp_path):
    copy = tmp_path / "sweep"
    shutil.copytree(evaluated_sweep, copy)
    return copy


def _tmp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.name.endswith(".tmp") or p.name.startswith(".tmp")]


def _report(sweep: Path, out: Path, **kwargs):
    lines: list[str] = []
    result = build_report([sweep], out, trajectories=False, log=lines.append, **kwargs)
    return result, lines


def test_the_report_reads_only_the_whole_rows_of_a_half_written_progress_csv(
    sweep, tmp_path, capsys
):
    run = run_dirs(sweep)[0]
    progress = run / "progress.csv"
    text = progress.read_text()
    progress.write_text(text + text.splitlines()[-1][:7], newline="")  # killed mid-row
    _result, _ = _report(sweep, tmp_path / "out")
    warnings = [line for line in capsys.readouterr().err.splitlines() if "incomplete row" in line]
    assert warnings == [
        f"warning: {progress}: skipped 1 incomplete row(s) (a process stopped while writing it); the whole rows are read"
    ]
    runs_md = (tmp_path / "out" / "runs.md").read_text()
    assert f"| {run.name} | WCSAC-0.5 | 0 | 800 |" in runs_md  # the last whole row


@pytest.mark.parametrize(
    ("key", "edit", "settings", "counts"),
    [
        ("cost_limit", "cost_limit: 25.0", ("cost_limit=15.0", "cost_limit=25.0"), "15.0: 1 run; 25.0: 1 run"),
        ("total_frames", "total_frames: 1200", ("total_frames=800", "total_frames=1200"), "800: 1 run; 1200: 1 run"),
        ("algo.gamma", "  gamma: 0.9", ("algo.gamma=0.99", "algo.gamma=0.9"), "0.99: 1 run; 0.9: 1 run"),
    ],
)  # fmt: skip
def test_runs_of_different_configurations_are_never_pooled_into_one_row(
    sweep, tmp_path, key, edit, settings, counts
):
    """Even under --cost-limit: a row pools the seeds of one configuration; runs of one
    label that differ in a setting are rows of their own, said in one warning line."""
    run = run_dirs(sweep)[1]
    config = run / "config.yaml"
    lines = config.read_text().splitlines()
    name = edit.strip().split(":")[0]
    index = next(i for i, line in enumerate(lines) if line.startswith(edit.split(":")[0] + ":"))
    assert lines[index].strip().split(":")[0] == name
    lines[index] = edit
    config.write_text("\n".join(lines) + "\n")
    if key == "cost_limit":
        meta = json.loads((run / "evaluation.json").read_text())
        (run / "evaluation.json").write_text(json.dumps({**meta, "cost_limit": 25.0}))
    result, _ = _report(sweep, tmp_path / "out", cost_limit=15.0)
    split = [w for w in result.warnings if "differ in" in w]
    assert split == [
        f"row wcsac_0.5: its runs differ in {key} ({counts}), shown as one row per setting"
    ]
    labels = [row["label"] for row in result.rows if row["label"].startswith("wcsac_0.5")]
    assert sorted(labels) == sorted(f"wcsac_0.5[{setting}]" for setting in settings)
    assert all(row["seeds"] == 1 for row in result.rows if row["label"] in labels)


def test_a_run_directory_whose_name_is_not_utf8_is_reported(sweep, tmp_path):
    run = run_dirs(sweep)[2]
    strange = Path(os.fsdecode(os.fsencode(run.parent) + b"/2_random_\xff_seed0"))
    run.rename(strange)
    out = tmp_path / "out"
    _result, lines = _report(sweep, out)
    runs_md = (out / "runs.md").read_text(encoding="utf-8")
    assert "| 2_random_\ufffd_seed0 | Random Policy | 0 |" in runs_md
    assert all(line.encode("utf-8") for line in lines)  # printable
    assert _tmp_files(out) == []


def test_a_failed_write_leaves_no_temporary_file(sweep, tmp_path, monkeypatch):
    from wcsac_rl.evaluation import reporting

    def full_disk(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(reporting.os, "replace", full_disk)
    out = tmp_path / "out"
    with pytest.raises(reporting.ReportError, match="No space left on device"):
        _report(sweep, out)  # (one line: the report is written whole or not at all)
    assert _tmp_files(out) == [] and not out.exists()
