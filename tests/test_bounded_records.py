"""A run's records are bounded before they are read: a YAML alias bomb in config.yaml, a
JSON file nested past the parser's recursion, a huge (sparse) checkpoint. Each answers
in seconds with one line naming the file, through the commands a user runs (evaluate,
resume, report), and nothing of the run changes."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _hostile_helpers import copy_run, files_unchanged, one_line, train_tiny
from _training_helpers import ROOT

from wcsac_rl.evaluate import main as evaluate_main
from wcsac_rl.evaluation.evaluator import evaluate_run
from wcsac_rl.report import main as report_main
from wcsac_rl.training import ConfigError
from wcsac_rl.training.checkpoint import checkpoint_digest, load_checkpoint
from wcsac_rl.training.safe_load import (
    MAX_CHECKPOINT_BYTES,
    MAX_YAML_NODES,
    UnreadableRecord,
    load_json,
    load_yaml,
)

SECONDS = 10.0  # (each case answers in a fraction of this; unbounded, they ran for minutes)


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """One finished, evaluated tiny WCSAC run (never written to by a refused command)."""
    root = tmp_path_factory.mktemp("bounded") / "runs"
    train_tiny(root / "wcsac", "risk_level=0.5")
    evaluate_run(root / "wcsac", episodes=2, progress=False)
    return root


@pytest.fixture(autouse=True)
def unchanged(request):
    yield from files_unchanged(request, "runs", "a refused command changed a file of the runs")


def alias_bomb() -> str:
    """Ten lines that a YAML loader expands to 9**9 (3.9e8) nodes."""
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    for prev, name in zip("abcdefgh", "bcdefghi"):
        lines.append(f"{name}: &{name} [{', '.join([f'*{prev}'] * 9)}]")
    return "\n".join([*lines, "seed: *i"]) + "\n"


def test_the_readers_refuse_a_bomb_and_deep_nesting_and_read_a_record(tmp_path):
    bomb, deep_json = tmp_path / "config.yaml", tmp_path / "evaluation.json"
    bomb.write_text(alias_bomb())
    deep_json.write_text("[" * 200_000 + "]" * 200_000)
    deep_yaml = tmp_path / "deep.yaml"
    deep_yaml.write_text("[" * 100_000 + "]" * 100_000)
    for read, path, words in (
        (load_yaml, bomb, f"its aliases expand to more than {MAX_YAML_NODES} nodes"),
        (load_json, deep_json, "nested too deeply to read"),
        (load_yaml, deep_yaml, "nested too deeply to read"),
    ):
        start = time.perf_counter()
        with pytest.raises(UnreadableRecord) as err:
            read(path)
        assert time.perf_counter() - start < SECONDS
        assert str(err.value).startswith(f"{path}: ") and words in str(err.value)
        assert "\n" not in str(err.value)
    # a record with a few aliases and interpolations reads as OmegaConf.load reads it
    fine = tmp_path / "fine.yaml"
    fine.write_text("a: &a [1, 2]\nb: *a\nc: ${seed}\nseed: 3\n")
    cfg = load_yaml(fine)
    assert cfg.b == [1, 2] and cfg.c == 3


def _bombed(runs: Path, tmp_path: Path) -> Path:
    run = copy_run(runs / "wcsac", tmp_path)
    (run / "config.yaml").write_text(alias_bomb())
    return run


def test_evaluate_of_a_run_whose_config_is_a_bomb_answers_at_once(runs, tmp_path, capsys):
    """B1: the seed is read from the checkpoint's own config instead (config.yaml is not
    expanded), and the evaluation runs."""
    run = _bombed(runs, tmp_path)
    start = time.perf_counter()
    code = evaluate_main([str(run), "--episodes", "1", "--no-progress", "--force"])
    assert time.perf_counter() - start < 60.0  # (one tiny episode and the env's start)
    capsys.readouterr()
    assert code == 0


def test_resume_of_a_run_whose_config_is_a_bomb_continues_from_its_checkpoint(runs, tmp_path):
    """B2: ``train.py resume=RUN`` does not expand the bomb; the run continues from its
    checkpoint's own config (the record it keeps of itself)."""
    run = _bombed(runs, tmp_path)
    done = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), f"resume={run}", "total_frames=1200",
         "progress_bar=false"],
        capture_output=True, text=True, timeout=300, cwd=tmp_path,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert load_checkpoint(run / "checkpoints" / "last.pt")["frames"] == 1200


def test_report_of_a_run_whose_config_is_a_bomb_is_one_line(runs, tmp_path, capsys):
    """B3: the report reads the run's evaluation and says in one line why not its config."""
    run = _bombed(runs, tmp_path)
    _report_refuses(run, tmp_path, capsys, "its aliases expand to more than")


def test_report_of_a_deeply_nested_evaluation_is_one_line(runs, tmp_path, capsys):
    """J1: the report reads the run's training records and says in one line why not its
    evaluation."""
    run = copy_run(runs / "wcsac", tmp_path)
    (run / "evaluation.json").write_text("[" * 200_000 + "]" * 200_000)
    _report_refuses(run, tmp_path, capsys, "nested too deeply to read")


def test_report_skips_a_deeply_nested_provenance_record(runs, tmp_path, capsys):
    """J3: a session record that cannot be read says nothing (as a half-written one);
    the report is made from the rest."""
    run = copy_run(runs / "wcsac", tmp_path)
    (run / "provenance.json").write_text('{"a":' * 100_000 + "1" + "}" * 100_000)
    start = time.perf_counter()
    code = report_main([str(run), "--out", str(tmp_path / "report"), "--no-trajectories"])
    capsys.readouterr()
    assert code == 0 and time.perf_counter() - start < 120.0


def test_a_huge_sparse_checkpoint_is_refused_by_its_size(runs, tmp_path):
    """HF1: refused from its size, before a byte is read (a sparse file costs no disk)."""
    run = copy_run(runs / "wcsac", tmp_path)
    checkpoint = run / "checkpoints" / "last.pt"
    with checkpoint.open("r+b") as f:
        f.truncate(MAX_CHECKPOINT_BYTES + 1)
    for read in (checkpoint_digest, load_checkpoint):
        start = time.perf_counter()
        with pytest.raises(ConfigError) as err:
            read(checkpoint)
        assert time.perf_counter() - start < SECONDS
        assert str(err.value).startswith(f"{checkpoint}: ") and "not read" in str(err.value)


def _report_refuses(run: Path, tmp_path: Path, capsys, words: str) -> None:
    """The report answers in seconds; the unreadable record is skipped with one warning
    line naming it, and the report is made from the run's other records."""
    out = tmp_path / "report"
    start = time.perf_counter()
    code = report_main([str(run), "--out", str(out), "--no-trajectories"])
    printed = capsys.readouterr()
    said = printed.out + printed.err
    assert time.perf_counter() - start < SECONDS
    assert code == 0 and "Traceback" not in said
    named = [line for line in said.splitlines() if words in line]
    assert len(named) == 1 and named[0].startswith("warning: skipped")
    one_line(named[0], str(run))


def _stored(run: Path, key: str, value: int) -> Path:
    """``run``'s checkpoint with its stored config's ``key`` set to ``value``."""
    import torch

    checkpoint = run / "checkpoints" / "last.pt"
    state = torch.load(checkpoint, weights_only=True)
    node = state["config"]
    *parents, leaf = key.split(".")
    for part in parents:
        node = node[part]
    node[leaf] = value
    torch.save(state, checkpoint)
    return checkpoint


@pytest.mark.parametrize(
    ("key", "value", "words"),
    [
        ("algo.network.width", 200_000, "algo.network.width must be an integer in [1, 16384]"),
        (
            "env.max_episode_steps",
            10**12,
            "env.max_episode_steps must be an integer in [1, 1000000]",
        ),
    ],
    ids=["LC1-width", "LC4-episode"],
)
def test_a_stored_size_nothing_could_build_or_run_is_refused_before_building(
    runs, tmp_path, capsys, key, value, words
):
    """LC1, LC4: checked before a network is built or an episode run."""
    run = copy_run(runs / "wcsac", tmp_path)
    checkpoint = _stored(run, key, value)
    start = time.perf_counter()
    code = evaluate_main([str(run), "--episodes", "1", "--no-progress", "--force"])
    err = capsys.readouterr().err
    assert time.perf_counter() - start < SECONDS
    assert code == 1 and "Traceback" not in err
    (line,) = [line for line in err.splitlines() if line.startswith("error:")]
    one_line(line, f"{checkpoint}: its config's {words}, got {value}: not built")
