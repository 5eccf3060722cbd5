"""Bad input to the targets tool (``python -m wcsac_rl.evaluation.targets``): the red team's
cases T1-T18, F9 and F13. Each is answered with exit code 1 and one line on stderr, starting
``error:``, naming the file and what to change; every file is left byte-identical (no
``targets.md`` or ``targets.csv``, partial or empty, and no staged file)."""

from __future__ import annotations

import errno
import os
import re
import textwrap
from pathlib import Path

import pytest
from _hostile_helpers import one_line
from _training_helpers import tree_digests
from test_targets import RUN_VALUES, TRAINING_SAFETY

from wcsac_rl.evaluation.targets import TARGETS_CSV, TARGETS_MD, main

GOOD_TARGETS = "a:\n  C0.1: {at_most: 20}\n"


def _study(tmp_path: Path, targets=GOOD_TARGETS, run_values=RUN_VALUES, safety=TRAINING_SAFETY):
    """A report folder holding ``run_values`` and ``safety``, and a targets file beside it."""
    report = tmp_path / "report"
    report.mkdir()
    for name, data in {"run_values.csv": run_values, "training_safety.csv": safety}.items():
        (report / name).write_bytes(data if isinstance(data, bytes) else data.encode())
    (tmp_path / "targets.yaml").write_text(textwrap.dedent(targets))
    return report, tmp_path / "targets.yaml"


def _refused(tmp_path: Path, capsys, *needles: str, **files) -> str:
    """Run the tool on a study of ``files`` (:func:`_study`), refused (:func:`_refuses`)."""
    return _refuses(tmp_path, capsys, *_study(tmp_path, **files), *needles)


def _refuses(tmp_path: Path, capsys, report: Path, targets: Path, *needles: str) -> str:
    """The tool run on ``report`` and ``targets`` exits 1 with one ``error:`` line holding
    every needle, and nothing under ``tmp_path`` is written or changed."""
    before = tree_digests(tmp_path, skip=())
    assert main([str(report), str(targets)]) == 1
    out, err = capsys.readouterr()
    one_line(err, *needles)
    assert err.startswith("error: ") and out == ""
    assert tree_digests(tmp_path, skip=()) == before
    return err


def test_a_row_named_twice_is_refused(tmp_path, capsys):  # T1
    targets = "a:\n  EC: {at_most: 1}\nb:\n  EC: {at_most: 1}\na:\n  ER: {at_least: 1}\n"
    _refused(
        tmp_path,
        capsys,
        "targets.yaml: line 5",
        "'a' is given twice",
        "first on line 1",
        targets=targets,
    )


def test_a_metric_named_twice_in_a_row_is_refused(tmp_path, capsys):  # T2
    targets = "a:\n  C0.1: {at_most: 20}\n  C0.1: {at_most: 1}\n"
    _refused(
        tmp_path, capsys, "line 3", "'C0.1' is given twice", "first on line 2", targets=targets
    )


def test_a_bound_too_large_for_a_float_is_refused(tmp_path, capsys):  # T3
    targets = "a:\n  C0.1: {at_most: 1" + "0" * 400 + "}\n"
    err = _refused(tmp_path, capsys, "a.C0.1: at_most must be a finite number", targets=targets)
    assert len(err) < 300, err


def test_run_values_without_a_label_column_is_refused(tmp_path, capsys):  # T6
    run_values = RUN_VALUES.replace("label,", "name,", 1)
    _refused(
        tmp_path,
        capsys,
        "run_values.csv has no column label",
        "must include label, seed",
        run_values=run_values,
    )


@pytest.mark.parametrize(
    "seed",
    [
        pytest.param("nan", id="T7-nan"),
        pytest.param("inf", id="T8-inf"),
        pytest.param("100.5", id="T9-not-whole-beside-100"),
    ],
)
def test_a_seed_that_is_not_a_whole_number_is_refused(tmp_path, capsys, seed):  # T7 T8 T9
    run_values = RUN_VALUES.replace("a,A,102,", f"a,A,{seed},")
    _refused(
        tmp_path,
        capsys,
        "run_values.csv: line 4",
        "a seed must be a whole number",
        repr(seed),
        run_values=run_values,
    )


def test_a_run_given_twice_is_refused(tmp_path, capsys):  # T10
    run_values = RUN_VALUES.replace("a,A,102,", "a,A,101,")
    _refused(
        tmp_path,
        capsys,
        "run_values.csv: line 4",
        "row 'a' has seed 101 twice",
        "first on line 3",
        run_values=run_values,
    )


def test_a_seed_list_that_is_not_seeds_is_refused(tmp_path, capsys):  # T11
    safety = TRAINING_SAFETY.replace("a,100 101 102,", "a,100 x 102,")
    _refused(tmp_path, capsys, "training_safety.csv: line 2", "seed_list", "'x'", safety=safety)


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("a,100 101 102,", "a,100 100 102,", "seed_list names a seed twice"),
        ("b,101 100,", "a,101 100,", "line 3: row 'a' is given twice (first on line 2)"),
    ],
    ids=["seed-twice-in-seed_list", "row-twice"],
)
def test_a_training_safety_run_given_twice_is_refused(tmp_path, capsys, old, new, message):
    """Beyond the red team's list: T10's duplicates, in ``training_safety.csv``."""
    _refused(
        tmp_path, capsys, "training_safety.csv", message, safety=TRAINING_SAFETY.replace(old, new)
    )


def test_run_values_that_are_not_utf8_text_is_refused(tmp_path, capsys):  # T16
    run_values = RUN_VALUES.encode() + b"a,A,\xff\xfe\n"
    _refused(tmp_path, capsys, "run_values.csv is not UTF-8 text", run_values=run_values)


def test_a_label_holding_a_pipe_is_escaped_in_the_table(tmp_path, capsys):  # T18
    report, targets = _study(tmp_path, run_values=RUN_VALUES.replace("a,A,", "a,A|x,"))
    assert main([str(report), str(targets)]) == 0
    row = (report / TARGETS_MD).read_text().splitlines()[2]
    assert row.startswith(r"| A\|x | 3 |"), row
    assert len(re.split(r"(?<!\\)\|", row)) == len(re.split(r"\|", "| row | runs | C0.1 |"))


def _failing(monkeypatch, name: str, code: int, when) -> None:
    """Make ``os.<name>`` raise ``OSError(code)`` on the calls ``when(args)`` picks."""
    real = getattr(os, name)

    def fake(*args, **kwargs):
        if when(args):
            raise OSError(code, os.strerror(code))
        return real(*args, **kwargs)

    monkeypatch.setattr(os, name, fake)


def test_a_full_disk_leaves_the_earlier_tables_as_they_were(tmp_path, capsys, monkeypatch):  # F9
    report, targets = _study(tmp_path)
    assert main([str(report), str(targets)]) == 0
    targets.write_text("a:\n  EC: {at_most: 2.5}\n")
    capsys.readouterr()
    calls = []  # the disk fills while the second table (targets.csv) is written
    _failing(monkeypatch, "fsync", errno.ENOSPC, lambda args: calls.append(1) or len(calls) == 2)
    message = f"error: cannot write {report / TARGETS_CSV}: No space left on device"
    _refuses(tmp_path, capsys, report, targets, message)


def test_a_read_only_report_folder_is_one_line(tmp_path, capsys, monkeypatch):  # F13
    report, targets = _study(tmp_path)
    _failing(monkeypatch, "open", errno.EROFS, lambda args: Path(args[0]).parent == report)
    message = f"error: cannot write {report / TARGETS_MD}: Read-only file system"
    _refuses(tmp_path, capsys, report, targets, message)


def test_a_table_that_is_a_symlink_is_replaced_not_written_through(tmp_path, capsys):  # T13
    report, targets = _study(tmp_path)
    victim = tmp_path / "victim.md"
    victim.write_text("a file of another run\n")
    (report / TARGETS_MD).symlink_to(victim)
    assert main([str(report), str(targets)]) == 0
    assert victim.read_text() == "a file of another run\n"
    assert not (report / TARGETS_MD).is_symlink()
    assert "| A | 3 |" in (report / TARGETS_MD).read_text()
