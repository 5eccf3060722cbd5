"""A study's targets counted over its runs (wcsac_rl.evaluation.targets)."""

from __future__ import annotations

import csv
import textwrap
from pathlib import Path

import pytest
from _training_helpers import tree_digests

from wcsac_rl.evaluation.targets import (
    TARGETS_CSV,
    TARGETS_MD,
    Target,
    TargetsError,
    main,
    read_targets,
    targets_tables,
    write_targets,
)

RUN_VALUES = """\
label,algorithm,seed,split,machine,run,EC,C0.1,ER,goals,over_budget,episodes
a,A,100,held-out,cpu,a100,1.0,10.0,0.6,0.9,0.0,100
a,A,101,held-out,cpu,a101,3.0,20.0,0.4,0.8,0.1,100
a,A,102,held-out,cpu,a102,2.5,30.0,0.5,0.7,0.2,100
b,B,100,held-out,cpu,b100,20.0,50.0,1.0,1.0,0.3,100
b,B,101,held-out,cpu,b101,10.0,40.0,1.0,1.0,0.2,100
"""
# seed order 100 101 102 for a, 101 100 for b (the per-seed lists follow seed_list)
TRAINING_SAFETY = """\
label,seed_list,cumulative_cost_per_seed,epochs_over_limit_per_seed,\
epochs_over_limit_after_warmup_per_seed,peak_epoch_cost_per_seed,safe_from_frames_per_seed
a,100 101 102,100.0 5000.0 4000.0,1 2 3,0 1 0,10.0 20.0 30.0,50000.0 nan 60000.0
b,101 100,9000.0 11000.0,4 5,2 3,40.0 50.0,nan nan
"""


@pytest.fixture
def report(tmp_path: Path) -> Path:
    (tmp_path / "run_values.csv").write_text(RUN_VALUES)
    (tmp_path / "training_safety.csv").write_text(TRAINING_SAFETY)
    return tmp_path


def _targets(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "targets.yaml"
    path.write_text(textwrap.dedent(text))
    return path


def test_each_cell_counts_the_runs_that_meet_the_bound(report, tmp_path):
    path = _targets(
        tmp_path,
        """
        a:
          cumulative_cost: {at_most: 4000}
          epochs_over_limit_after_warmup: {at_most: 0}
          EC: {at_most: 2.5}
          ER: {at_least: 0.5}
          safe_from_frames: {at_most: 60000}
        b:
          cumulative_cost: {at_most: 10000}
          EC: {at_most: 15}
        """,
    )
    tables = targets_tables(report, read_targets(path))
    assert tables[TARGETS_MD].splitlines() == [
        "| row | runs | cumulative training cost | epochs over d after the warm-up | EC | ER "
        "| ≤ d for good from (frames) |",
        "|---|---:|---|---|---|---|---|",
        # 100 and 4000 ≤ 4000 (a bound is met by its value); 0 and 0; 1.0 and 2.5; 0.6 and
        # 0.5; 50 000 and 60 000 (seed 101's NaN: it ended over d, not met)
        "| A | 3 | 2 of 3 (≤ 4000) | 2 of 3 (≤ 0) | 2 of 3 (≤ 2.5) | 2 of 3 (≥ 0.5) "
        "| 2 of 3 (≤ 60000) |",
        # seed 101's 9000 (the first of seed_list 101 100), not seed 100's 11 000
        "| B | 2 | 1 of 2 (≤ 10000) |  | 1 of 2 (≤ 15) |  |  |",
    ]
    lines = list(csv.DictReader(tables[TARGETS_CSV].splitlines()))
    assert len(lines) == 3 * 5 + 2 * 2
    b_cost = [(ln["seed"], ln["value"], ln["met"]) for ln in lines[15:17]]
    assert b_cost == [("100", "11000.0", "0"), ("101", "9000.0", "1")]


def test_a_bound_reads_both_ways():
    assert Target("EC", "at_most", 2.0).met(2.0) and not Target("EC", "at_most", 2.0).met(2.1)
    assert Target("ER", "at_least", 0.5).met(0.5) and not Target("ER", "at_least", 0.5).met(0.4)
    assert not Target("EC", "at_most", 2.0).met(float("nan"))


BAD = [
    ("[1, 2]\n", "must map row labels to their targets"),
    ("a: 3\n", "row 'a' must map metrics to bounds"),
    ("a: {C0.2: {at_most: 1}}\n", "a.C0.2: no such metric"),
    ("a: {EC: {below: 1}}\n", "a.EC must be {at_most: <number>} or {at_least: <number>}"),
    ("a: {EC: {at_most: abc}}\n", "a.EC: at_most must be a finite number, got 'abc'"),
    ("a: {EC: {at_most: .nan}}\n", "at_most must be a finite number, got nan"),
    ("a: {EC: {at_most: 1, at_least: 0}}\n", "must be {at_most: <number>}"),
    ("a: [\n", "is not YAML"),
    ("c: {EC: {at_most: 1}}\n", "no row 'c' in the report (rows: a, b)"),
]


@pytest.mark.parametrize(("text", "message"), BAD, ids=[m for _, m in BAD])
def test_bad_targets_are_one_line_and_nothing_is_written(report, tmp_path, capsys, text, message):
    path = tmp_path / "t.yaml"
    path.write_text(text)
    before = tree_digests(report, skip=())
    assert main([str(report), str(path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err and message in err, err
    assert tree_digests(report, skip=()) == before


def test_a_report_without_its_training_safety_table_is_one_line(report, tmp_path):
    (report / "training_safety.csv").unlink()
    path = _targets(tmp_path, "a: {EC: {at_most: 1}}\n")
    with pytest.raises(TargetsError, match=r"cannot read .*training_safety\.csv"):
        write_targets(report, path)
    assert not (report / TARGETS_MD).exists()


def test_a_training_safety_metric_missing_for_a_run_is_refused(report, tmp_path):
    (report / "training_safety.csv").write_text(
        TRAINING_SAFETY.replace("b,101 100,9000.0 11000.0,4 5,2 3,40.0 50.0,nan nan\n", "")
    )
    path = _targets(tmp_path, "b: {cumulative_cost: {at_most: 1}}\n")
    with pytest.raises(TargetsError, match="row 'b' has no cumulative_cost for seed 100"):
        targets_tables(report, read_targets(path))


def test_the_command_writes_both_tables(report, tmp_path, capsys):
    path = _targets(tmp_path, "a: {C0.1: {at_most: 20}}\n")
    assert main([str(report), str(path)]) == 0
    assert "| A | 3 | 2 of 3 (≤ 20) |" in capsys.readouterr().out
    assert (report / TARGETS_MD).is_file() and (report / TARGETS_CSV).is_file()
