"""Bad inputs to the report, calibration and evaluate commands, each answered in one
``error:`` line (exit code 1) or handled: never a traceback, never a wrong number, and a
report written whole or not at all.

* names and records that reach a table (a run directory named ``wcsac|x`` or with a line
  break, a machine's name holding LaTeX) are escaped in its Markdown and LaTeX (P1-P3);
* an evaluation that is not its run's (ST3), episode values whose sums overflow (ST4),
  a row set against itself or a pair asked for twice (ST8) are refused in one line;
* a full disk or a read-only file system is one line naming what could not be written,
  and leaves no file of the command behind (F6-F8, F11, F12); a huge checkpoint is
  refused by its size (HF2).

Full and read-only disks are simulated (the suite runs as root, for whom permission bits
block nothing): the write that would fail raises the ``OSError`` it would. The report
cases use committed archived runs (results/evidence_static/runs), the evaluate and
calibration cases one tiny run trained for this module.
"""

from __future__ import annotations

import csv
import errno
import json
import os
import shutil
import time
from pathlib import Path

import pytest
from _hostile_helpers import (
    copy_run,
    copy_study,
    error_lines,
    evaluated_tiny_run,
    files_unchanged,
    one_line,
)
from _training_helpers import ROOT, tree_digests

from wcsac_rl.calibration import main as calibration_main
from wcsac_rl.evaluate import main as evaluate_main
from wcsac_rl.evaluation import reporting
from wcsac_rl.evaluation.latex import markdown_cell, markdown_text, markdown_to_latex
from wcsac_rl.evaluation.reporting import build_report
from wcsac_rl.evaluation.runs import ROW_ORDER, find_evaluated_dirs, row_name
from wcsac_rl.report import main as report_main
from wcsac_rl.training.safe_load import MAX_CHECKPOINT_BYTES

RUNS = ROOT / "results" / "evidence_static" / "runs"
SECONDS = 10.0


@pytest.fixture
def study(tmp_path) -> Path:
    """Two rows of three archived runs each (WCSAC-0.1, SAC-Lag; seeds 0, 10, 20)."""
    return copy_study(tmp_path / "study")


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """A finished, evaluated tiny WCSAC run (never written to by a test)."""
    return evaluated_tiny_run(tmp_path_factory.mktemp("report_inputs") / "runs")


@pytest.fixture(autouse=True)
def unchanged(request):
    yield from files_unchanged(request, "runs", "a command changed a file of the shared run")


def _report(study: Path, out: Path, capsys, *args: str) -> tuple[int, str, str]:
    code = report_main([str(study), "--out", str(out), "--no-trajectories", *args])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _one_error(code: int, err: str, *needles: str) -> str:
    """Exit code 1, no traceback, exactly one ``error:`` line holding ``needles``."""
    assert code == 1 and "Traceback" not in err, err
    errors = error_lines(err)
    assert len(errors) == 1, err
    one_line(errors[0], *needles)
    return errors[0]


def _refused(study: Path, tmp_path: Path, capsys, args: list[str], *needles: str) -> str:
    """The report refuses in one line; nothing below ``tmp_path`` changed, no report."""
    out = tmp_path / "out"
    before = tree_digests(tmp_path)
    code, _, err = _report(study, out, capsys, *args)
    line = _one_error(code, err, *needles)
    assert tree_digests(tmp_path) == before and not out.exists()
    return line


def _no_staging_left(root: Path) -> None:
    assert not [p for p in root.rglob("*.partial")], "a report's staging directory was left"


def _tables_whole(out: Path) -> None:
    """Every Markdown table the report wrote has its LaTeX table beside it, made from it
    (which checks that each row has its header's number of cells), and no line of either
    is broken by a name."""
    pairs = [(md, md.with_suffix(".tex")) for md in sorted(out.glob("*.md"))]
    assert len(pairs) >= 6
    for md, tex in pairs:
        assert tex.read_text() == markdown_to_latex(md.read_text()), md.name


def _csv_column(path: Path, column: str) -> list[str]:
    with path.open(newline="") as f:
        return [row[column] for row in csv.DictReader(f)]


# ------------------------------------------------------------- escaped names (P1-P3)
def test_ordinary_labels_and_names_are_cells_unchanged():
    """The escaping leaves every ordinary label alone (the committed tables are made again
    byte for byte: tests/test_committed_results.py)."""
    texts = [*ROW_ORDER, *map(row_name, ROW_ORDER), "sac_lag[cost_limit=1.5]",
             "wcsac_0.1_static_seed0", "f6fde13 + local changes", "EPYC 7B13 (AVX2)"]  # fmt: skip
    assert [markdown_cell(t) for t in texts] == texts
    assert markdown_cell("a|b\nc\td\x1b") == "a\\|b\\nc\\td\\x1b"
    assert markdown_text("a|b\nc") == "a|b\\nc"


def test_a_machine_name_holding_bars_latex_and_a_line_break_is_escaped(study, tmp_path, capsys):
    """P1: the name is shown as written, one cell, in the Markdown and the LaTeX tables;
    nothing of it is LaTeX code. The CSV keeps it as it is."""
    processor = "EPYC | \\input{/etc/passwd}\n| x | y"
    record = study / "sac_lag_static_seed0" / "provenance.json"
    data = json.loads(record.read_text())
    record.write_text(json.dumps({**data, "machine": {"processor": processor}}))
    out = tmp_path / "out"
    code, _, err = _report(study, out, capsys, "--study")
    assert code == 0, err
    _tables_whole(out)
    for name in ("run_values", "run_statistics"):
        md, tex = (out / f"{name}.md").read_text(), (out / f"{name}.tex").read_text()
        assert "| EPYC \\| \\input{/etc/passwd}\\n\\| x \\| y" in md
        assert "EPYC | \\textbackslash{}input\\{/etc/passwd\\}\\textbackslash{}n| x | y" in tex
        assert "\\input" not in tex
    assert processor in _csv_column(out / "run_values.csv", "machine")


@pytest.mark.parametrize("name", ["wcsac|x", "wcsac\nx"], ids=["P2-bar", "P3-line-break"])
def test_a_run_directory_named_with_a_bar_or_a_line_break_is_escaped(study, tmp_path, capsys, name):
    """P2, P3: the run's name is one cell of runs.md, run_values.md and outcomes.md (and
    their .tex); the CSVs hold it as it is."""
    (study / "sac_lag_static_seed0").rename(study / name)
    out = tmp_path / "out"
    code, _, err = _report(study, out, capsys, "--study")
    assert code == 0, err
    _tables_whole(out)
    cell = markdown_cell(name)
    for table in ("runs", "run_values", "outcomes"):
        assert f" {cell} |" in (out / f"{table}.md").read_text(), table
    assert name in _csv_column(out / "run_values.csv", "run")
    assert name in _csv_column(out / "outcomes.csv", "run")


def test_a_report_that_fails_midway_leaves_nothing(study, tmp_path, monkeypatch):
    """P3: a report that fails after some of its files are made (its Table 1 and
    statistics, before runs.md) leaves none of them: no new directory, no file replaced
    in an existing one, no staging directory."""

    def fail(*_args, **_kwargs):
        raise ValueError("a table cannot be made")

    monkeypatch.setattr(reporting, "runs_markdown", fail)
    out = tmp_path / "out"
    with pytest.raises(ValueError, match="a table cannot be made"):
        build_report([study], out, trajectories=False, log=lambda _: None)
    assert not out.exists()
    _no_staging_left(tmp_path)
    monkeypatch.undo()
    build_report([study], out, trajectories=False, log=lambda _: None)
    before = tree_digests(out)
    monkeypatch.setattr(reporting, "runs_markdown", fail)
    with pytest.raises(ValueError, match="a table cannot be made"):
        build_report([study], out, trajectories=False, force=True, log=lambda _: None)
    assert tree_digests(out) == before
    _no_staging_left(tmp_path)


def test_a_staging_directory_a_killed_report_left_is_not_searched_for_runs(study):
    """P3: its archived copies are not counted again by a later report."""
    left = study / ".report.123.0a1b2c3d.partial" / "runs" / "sac_lag_static_seed0"
    shutil.copytree(study / "sac_lag_static_seed0", left)
    assert left.resolve() not in find_evaluated_dirs([study])
    assert len(find_evaluated_dirs([study])) == 6


# ------------------------------------------------------------ records that lie (ST*)
@pytest.mark.parametrize(
    ("edit", "needles"),
    [
        ({"seed": 100, "env_seed": 2_000_103}, ("has seed 100", "config.yaml seed 0")),
        ({"label": "wcsac_0.1"}, ("has label 'wcsac_0.1'", "config.yaml algo.label 'sac_lag'")),
        ({"algo": "wcsac"}, ("has algo 'wcsac'", "config.yaml algo.name 'sac_lag'")),
    ],
    ids=["seed", "label", "algo"],
)
def test_an_evaluation_that_is_not_its_runs_is_refused(study, tmp_path, capsys, edit, needles):
    """ST3: an in-sample run's evaluation.json rewritten to a held-out seed (or another
    row) is refused, naming the file, the field and both values."""
    path = study / "sac_lag_static_seed0" / "evaluation.json"
    path.write_text(json.dumps({**json.loads(path.read_text()), **edit}, indent=2))
    _refused(study, tmp_path, capsys, ["--study"], str(path), *needles)
    _refused(study, tmp_path, capsys, [], str(path), *needles)  # a plain report too


def test_episode_values_whose_sum_overflows_are_refused_naming_the_run(study, tmp_path, capsys):
    """ST4: every episode cost 1e308 (finite; their mean is not) is one line naming the
    run; the warning line says which value."""
    path = study / "sac_lag_static_seed0" / "evaluation.csv"
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows({**row, "cost": "1e308"} for row in rows)
    out = tmp_path / "out"
    code, printed, err = _report(study, out, capsys, "--study")
    _one_error(code, err, "1 run(s) have no readable evaluation", "sac_lag_static_seed0")
    assert not out.exists()
    skipped = [line for line in printed.splitlines() if "1e308" in line]
    assert len(skipped) == 1
    one_line(skipped[0], str(path), "episode row 0: cost '1e308' is larger than any episode's")


@pytest.mark.parametrize(
    ("pairs", "needle"),
    [
        (["wcsac_0.1:wcsac_0.1"], "--improvement wcsac_0.1:wcsac_0.1 sets row 'wcsac_0.1' "
         "against itself"),
        (["wcsac_0.1:sac_lag", "wcsac_0.1:sac_lag"], "--improvement wcsac_0.1:sac_lag is given "
         "twice"),
    ],
    ids=["itself", "twice"],
)  # fmt: skip
def test_a_row_against_itself_or_a_pair_given_twice_is_refused(
    study, tmp_path, capsys, pairs, needle
):
    """ST8."""
    args = [word for pair in pairs for word in ("--improvement", pair)]
    _refused(study, tmp_path, capsys, args, needle)


# ---------------------------------------------------------- full and read-only disks
def _failing(monkeypatch, code: int, when=lambda _dst: True) -> None:
    """Every rename into place (how the kit writes a file: the last step of
    ``replace_file``) fails with ``code`` where ``when(destination)``."""
    real = os.replace

    def replace(src, dst, *args, **kwargs):
        if when(str(dst)):
            raise OSError(code, os.strerror(code))
        return real(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)


def _read_only(monkeypatch, root: Path) -> None:
    """Below ``root`` no file or directory can be created (``EROFS``), as on a file system
    mounted read-only; reading is as before."""
    real_open, real_mkdir = os.open, os.mkdir
    writing = os.O_WRONLY | os.O_RDWR | os.O_CREAT

    def below(path) -> bool:
        path = Path(os.fsdecode(path)).absolute()
        return path == root or root in path.parents

    def open_(path, flags, *args, **kwargs):
        if flags & writing and below(path):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fsdecode(path))
        return real_open(path, flags, *args, **kwargs)

    def mkdir(path, *args, **kwargs):
        if below(path):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fsdecode(path))
        return real_mkdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "open", open_)
    monkeypatch.setattr(os, "mkdir", mkdir)


DISKS = [errno.ENOSPC, errno.EROFS]


@pytest.mark.parametrize("code", DISKS, ids=["full", "read-only"])
@pytest.mark.parametrize("which", ["evaluation.csv", "evaluation.json"])
def test_evaluate_on_a_full_or_read_only_disk_is_one_line_and_leaves_nothing(
    runs, tmp_path, capsys, monkeypatch, code, which
):
    """F6: whichever of the two files cannot be written, the run keeps its previous
    evaluation byte for byte (both files or neither are replaced) and no temporary file."""
    run = copy_run(runs / "wcsac", tmp_path)
    before = tree_digests(run)
    _failing(monkeypatch, code, when=lambda dst: which in dst)
    got = evaluate_main([str(run), "--force", "--episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    _one_error(got, err, f"error: cannot write {run / which}: {os.strerror(code)}")
    assert tree_digests(run) == before


def test_evaluate_into_a_read_only_run_is_refused_before_its_episodes(
    runs, tmp_path, capsys, monkeypatch
):
    """F6: the run directory is found unwritable before the test episodes run."""
    run = copy_run(runs / "wcsac", tmp_path)
    before = tree_digests(run)
    _read_only(monkeypatch, run.absolute())
    got = evaluate_main([str(run), "--force", "--episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    _one_error(got, err, f"cannot write {run}: Read-only file system")
    assert tree_digests(run) == before


@pytest.mark.parametrize("code", DISKS, ids=["F7-full", "F11-read-only"])
def test_calibration_on_a_full_or_read_only_disk_is_one_line_and_leaves_nothing(
    runs, tmp_path, capsys, monkeypatch, code
):
    """F7, F11: ``calibration.json`` that cannot be written is one line naming it; no
    temporary file is left."""
    run = copy_run(runs / "wcsac", tmp_path)
    before = tree_digests(run)
    _failing(monkeypatch, code)
    got = calibration_main([str(run), "--episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    _one_error(got, err, f"error: cannot write {run / 'calibration.json'}: {os.strerror(code)}")
    assert tree_digests(run) == before


def test_calibration_of_a_read_only_run_is_refused_before_its_episodes(
    runs, tmp_path, capsys, monkeypatch
):
    """F11."""
    run = copy_run(runs / "wcsac", tmp_path)
    before = tree_digests(run)
    _read_only(monkeypatch, run.absolute())
    got = calibration_main([str(run), "--episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    _one_error(got, err, f"error: cannot write {run}: Read-only file system")
    assert tree_digests(run) == before


@pytest.mark.parametrize("code", DISKS, ids=["F8-full", "F12-read-only"])
def test_a_report_on_a_full_or_read_only_disk_is_one_line_and_leaves_nothing(
    study, tmp_path, capsys, monkeypatch, code
):
    """F8, F12: into a new directory (none is made) and over an existing report with
    --force (each of its files byte-identical)."""
    out = tmp_path / "out"
    _failing(monkeypatch, code)
    _refused(study, tmp_path, capsys, [], f"error: cannot write {out}: {os.strerror(code)}")
    _no_staging_left(tmp_path)
    monkeypatch.undo()
    assert _report(study, out, capsys)[0] == 0
    before = tree_digests(tmp_path)
    _failing(monkeypatch, code)
    got, _, err = _report(study, out, capsys, "--force")
    _one_error(got, err, f"cannot write {out}: {os.strerror(code)}")
    assert tree_digests(tmp_path) == before
    _no_staging_left(tmp_path)


def test_a_report_into_a_read_only_study_is_refused_before_anything(
    study, tmp_path, capsys, monkeypatch
):
    """F12: the default --out (STUDY/report) of a study on a read-only file system, and
    an existing report there with --force."""
    before = tree_digests(tmp_path)
    _read_only(monkeypatch, study.absolute())
    code = report_main([str(study), "--no-trajectories"])
    _one_error(code, capsys.readouterr().err,
               f"error: cannot write {study / 'report'}: {study.absolute()}: Read-only file system")  # fmt: skip
    assert tree_digests(tmp_path) == before and not (study / "report").exists()
    monkeypatch.undo()
    assert report_main([str(study), "--no-trajectories"]) == 0
    capsys.readouterr()
    before = tree_digests(tmp_path)
    _read_only(monkeypatch, study.absolute())
    code = report_main([str(study), "--no-trajectories", "--force"])
    _one_error(code, capsys.readouterr().err,
               f"error: cannot write {study / 'report'}: Read-only file system")  # fmt: skip
    assert tree_digests(tmp_path) == before


# ------------------------------------------------------------------- huge checkpoint
def test_evaluate_of_a_huge_sparse_checkpoint_names_it_and_its_size(runs, tmp_path, capsys):
    """HF2: refused from its size, before a byte is read (as HF1 for the report), with
    --force and without (where the checkpoint is first compared with its evaluation)."""
    run = copy_run(runs / "wcsac", tmp_path)
    checkpoint = run / "checkpoints" / "last.pt"
    with checkpoint.open("r+b") as f:
        f.truncate(MAX_CHECKPOINT_BYTES + 1)
    before = tree_digests(run, skip=(".lock", checkpoint.name))  # (not read: 4 GiB)
    for force in (["--force"], []):
        start = time.perf_counter()
        code = evaluate_main([str(run), *force, "--episodes", "1", "--no-progress"])
        assert time.perf_counter() - start < SECONDS
        _one_error(code, capsys.readouterr().err, f"{checkpoint}: 4.00 GiB, larger than any "
                   "checkpoint the kit writes (at most 4 GiB read): not read")  # fmt: skip
        assert tree_digests(run, skip=(".lock", checkpoint.name)) == before
