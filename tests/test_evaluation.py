"""``python -m wcsac_rl.evaluate``: test episodes of real (tiny) runs → evaluation.csv/json.

Tolerances: the metrics are float64 means of the per-episode sums written to the CSV
(repr round-trips exactly); approx's default ``rel=1e-6`` covers a different summation
order of ≤ 10 values (10 × 2⁻⁵²).
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import pytest
from _evaluation_helpers import EPISODE_STEPS, copy_sweep, run_dirs
from _training_helpers import ROOT

from wcsac_rl.evaluation.evaluator import (
    CSV_COLUMNS,
    DEFAULT_SEED_OFFSET,
    Evaluation,
    EvaluationExistsError,
    evaluate_random_policy,
    evaluate_run,
    read_evaluation,
    summarize,
    write_evaluation,
)
from wcsac_rl.evaluation.metrics import METRIC_KEYS
from wcsac_rl.evaluation.runs import find_evaluated_dirs, find_run_dirs
from wcsac_rl.rollouts.episodes import EpisodeResult
from wcsac_rl.training import ConfigError

EPISODES = 4


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    """A copy of the tiny sweep with every run evaluated (4 episodes each)."""
    sweep = copy_sweep(tmp_path_factory.mktemp("evaluated"))
    evaluations = [evaluate_run(d, episodes=EPISODES, progress=False) for d in run_dirs(sweep)]
    return sweep, evaluations


def test_evaluation_files_beside_each_run(evaluated):
    sweep, evaluations = evaluated
    for run_dir, ev in zip(run_dirs(sweep), evaluations):
        assert ev.directory == run_dir.resolve()
        with (run_dir / "evaluation.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
        assert tuple(rows[0]) == CSV_COLUMNS
        assert [int(r["episode"]) for r in rows] == list(range(EPISODES))
        for row in rows:
            assert 1 <= int(row["length"]) <= EPISODE_STEPS
            assert float(row["cost"]) >= 0 and int(row["numerical_failure"]) in (0, 1)
        data = json.loads((run_dir / "evaluation.json").read_text())
        assert tuple(data["metrics"]) == METRIC_KEYS
        assert data["metrics"]["episodes"] == EPISODES == data["episodes"]
        assert data["env"] == "tiny" and data["cost_limit"] == 15.0
        assert data["trained_frames"] == 800
        assert data["env_seed"] == data["seed"] + DEFAULT_SEED_OFFSET
        assert data["max_episode_steps"] == EPISODE_STEPS
        costs = [float(r["cost"]) for r in rows]
        returns = [float(r["return"]) for r in rows]
        assert data["metrics"]["EC"] == pytest.approx(sum(costs) / EPISODES)
        assert data["metrics"]["ER"] == pytest.approx(sum(returns) / EPISODES)
        assert data["metrics"]["C0.1"] == pytest.approx(max(costs))
    labels = [(ev.meta["label"], ev.meta["seed"], ev.meta["policy"]) for ev in evaluations]
    assert labels == [
        ("wcsac_0.5", 0, "trained (deterministic)"),
        ("wcsac_0.5", 1, "trained (deterministic)"),
        ("random", 0, "uniform random"),
        ("random", 1, "uniform random"),
    ]


def test_read_evaluation_round_trips(evaluated):
    sweep, evaluations = evaluated
    for ev in evaluations:
        back = read_evaluation(ev.directory)
        assert back.episodes == ev.episodes
        assert back.meta == json.loads(json.dumps(ev.meta))
        assert back.summary == json.loads(json.dumps(ev.summary))
    assert find_evaluated_dirs([sweep.parent.parent]) == [ev.directory for ev in evaluations]


def test_same_seed_same_episodes_and_deterministic_policy(evaluated, tmp_path):
    sweep, evaluations = evaluated
    again = evaluate_run(run_dirs(sweep)[0], episodes=EPISODES, progress=False, force=True)
    assert again.episodes == evaluations[0].episodes
    other = evaluate_run(
        run_dirs(sweep)[0], episodes=EPISODES, progress=False, force=True, seed_offset=7
    )
    assert other.meta["env_seed"] == 7
    assert other.episodes != evaluations[0].episodes  # other start states


def test_random_policy_without_a_run_matches_a_random_run(evaluated, tmp_path):
    _, evaluations = evaluated
    random_run = evaluations[2]  # algo=random, seed 0
    ev = evaluate_random_policy(
        "tiny",
        tmp_path / "random_tiny_seed0",
        seed=0,
        episodes=EPISODES,
        max_episode_steps=EPISODE_STEPS,
        progress=False,
    )
    assert ev.episodes == random_run.episodes
    assert ev.meta["label"] == "random" and ev.meta["trained_frames"] == 0
    assert (tmp_path / "random_tiny_seed0" / "evaluation.csv").is_file()


def test_existing_evaluation_is_not_overwritten_without_force(evaluated):
    sweep, _ = evaluated
    run_dir = run_dirs(sweep)[1]
    before = {p: p.read_bytes() for p in (run_dir / "evaluation.csv", run_dir / "evaluation.json")}
    with pytest.raises(EvaluationExistsError, match="pass --force to overwrite"):
        evaluate_run(run_dir, episodes=1, progress=False)
    assert {p: p.read_bytes() for p in before} == before


def test_run_dir_without_checkpoint_is_one_clear_error(tmp_path):
    run_dir = tmp_path / "broken_run"
    run_dir.mkdir()
    (run_dir / "config.yaml").write_text("seed: 0\n")
    (run_dir / "progress.csv").write_text("epoch,frames\n")
    with pytest.raises(ConfigError, match="holds no checkpoint"):
        evaluate_run(run_dir, episodes=1, progress=False)
    assert not (run_dir / "evaluation.json").exists()
    found, errors = find_run_dirs([run_dir])
    assert found == [] and errors == [
        f"{run_dir}: run directory without a checkpoint "
        f"(expected {run_dir / 'checkpoints' / 'last.pt'})"
    ]


def test_corrupt_checkpoint_is_one_clear_error(tmp_path):
    run_dir = tmp_path / "corrupt"
    (run_dir / "checkpoints").mkdir(parents=True)
    (run_dir / "checkpoints" / "last.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="cannot read checkpoint"):
        evaluate_run(run_dir, episodes=1, progress=False)


def test_checkpoint_without_a_policy_is_not_evaluated_as_random(evaluated, monkeypatch):
    from wcsac_rl.training.off_policy import OffPolicyTrainer

    monkeypatch.setattr(OffPolicyTrainer, "restore_policy", classmethod(lambda *a: None))
    sweep, _ = evaluated
    with pytest.raises(ConfigError, match=r"no policy could be restored .* algo 'wcsac'"):
        evaluate_run(run_dirs(sweep)[0], episodes=1, progress=False, force=True)


def _touch_run(path: Path, checkpoint: bool) -> Path:
    path.mkdir(parents=True)
    (path / "config.yaml").write_text("seed: 0\n")
    (path / "progress.csv").write_text("epoch\n")
    if checkpoint:
        (path / "checkpoints").mkdir()
        (path / "checkpoints" / "last.pt").write_bytes(b"")
    return path


def test_find_run_dirs_in_sweeps(tmp_path):
    sweep = tmp_path / "multirun" / "2026-01-01" / "00-00-00"
    a = _touch_run(sweep / "0_sac_static_seed0", checkpoint=True)
    b = _touch_run(sweep / "1_sac_static_seed10", checkpoint=True)
    c = _touch_run(sweep / "2_sac_static_seed20", checkpoint=False)  # crashed early
    (sweep / ".hydra").mkdir()  # Hydra's own files are not runs
    (sweep / "multirun.yaml").write_text("")
    found, errors = find_run_dirs([tmp_path / "multirun", a, a / "checkpoints" / "last.pt"])
    assert found == [a.resolve(), b.resolve()]  # each once, in order
    assert errors == [f"{c}: run directory without a checkpoint (expected {c}/checkpoints/last.pt)"]
    found, errors = find_run_dirs([tmp_path / "nope", sweep / "multirun.yaml", sweep / ".hydra"])
    assert found == []
    assert errors == [
        f"{tmp_path / 'nope'}: no such file or directory",
        f"{sweep / 'multirun.yaml'}: not a run directory (expected a directory)",
        f"{sweep / '.hydra'}: no run directories with checkpoints/last.pt",
    ]


def test_write_and_read_synthetic_evaluation(tmp_path):
    episodes = [EpisodeResult(1.5, 20.0, 10, 1, False), EpisodeResult(-0.5, 0.0, 7, 0, True)]
    meta = {"label": "sac", "env": "static", "seed": 0, "cost_limit": 15.0}
    ev = Evaluation(tmp_path / "ev", meta, episodes, summarize(episodes, 15.0))
    write_evaluation(ev)
    back = read_evaluation(tmp_path / "ev")
    assert back.episodes == episodes and back.meta == meta
    assert back.summary["metrics"]["over_budget"] == 0.5
    assert back.summary["numerical_failures"] == 1 and back.summary["goals_per_episode"] == 0.5
    with pytest.raises(EvaluationExistsError):
        write_evaluation(ev)
    write_evaluation(ev, force=True)
    (tmp_path / "ev" / "evaluation.csv").unlink()
    with pytest.raises(ConfigError, match="incomplete evaluation"):
        read_evaluation(tmp_path / "ev")


def test_evaluate_cli_evaluates_the_good_runs_and_reports_the_bad_one(tmp_path):
    sweep = copy_sweep(tmp_path)
    broken = _touch_run(sweep / "4_sac_tiny_seed0", checkpoint=False)
    out = tmp_path / "random_eval"
    cmd = [sys.executable, "-m", "wcsac_rl.evaluate", str(sweep.parent), "--episodes", "2"]
    cmd += ["--random-policy", "tiny", "--random-seeds", "3", "--out", str(out)]
    cmd += ["--max-episode-steps", "20"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stderr
    error_lines = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert error_lines == [
        f"error: {broken}: run directory without a checkpoint "
        f"(expected {broken}/checkpoints/last.pt)"
    ]
    assert "5 evaluated, 0 skipped" in proc.stdout and "1 failed" in proc.stdout
    assert "Traceback" not in proc.stderr
    assert "ep/s" in proc.stderr  # the tqdm progress bar
    for run_dir in run_dirs(sweep):
        if run_dir != broken:
            data = json.loads((run_dir / "evaluation.json").read_text())
            assert data["episodes"] == 2 and data["max_episode_steps"] == 20
    random_dir = out / "random_tiny_seed3"
    assert json.loads((random_dir / "evaluation.json").read_text())["seed"] == 3

    # again, without --force: everything is skipped, nothing rewritten
    before = (random_dir / "evaluation.csv").read_bytes()
    cmd = [sys.executable, "-m", "wcsac_rl.evaluate", "--no-progress"]
    cmd += ["--random-policy", "tiny", "--random-seeds", "3", "--out", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "already has evaluation.csv, evaluation.json; pass --force to overwrite" in proc.stderr
    assert "0 evaluated, 1 skipped" in proc.stdout
    assert (random_dir / "evaluation.csv").read_bytes() == before


def test_evaluate_cli_usage_errors():
    from wcsac_rl.evaluate import parse_args

    with pytest.raises(SystemExit):
        parse_args([])
    with pytest.raises(SystemExit):
        parse_args(["somewhere", "--episodes", "0"])
    args = parse_args(["a", "b"])
    assert args.episodes == 100 and args.seed == DEFAULT_SEED_OFFSET and not args.force


def test_evaluate_archive_keeps_each_runs_records_and_refuses_to_replace_others(tmp_path, capsys):
    """``--archive DIR``: every evaluated run's records (no checkpoint) in DIR/<run>,
    byte for byte; a report of DIR alone makes the runs' own Table 1; an archived file
    with other bytes is not replaced without --force."""
    from wcsac_rl.evaluate import main
    from wcsac_rl.evaluation.archive import ArchiveError, archive_run, archived_records
    from wcsac_rl.evaluation.reporting import TABLE_MD, build_report
    from wcsac_rl.evaluation.training_safety_table import TRAINING_SAFETY_MD

    sweep = copy_sweep(tmp_path)
    kept = tmp_path / "kept"
    args = [str(sweep), "--episodes", "2", "--no-progress", "--archive", str(kept)]
    assert main(args) == 0
    runs = run_dirs(sweep)
    assert f"{len(runs)} archived in {kept}" in capsys.readouterr().out
    assert sorted(p.name for p in kept.iterdir()) == [d.name for d in runs]
    for run in runs:
        records = archived_records(run)
        names = {p.name for p in records}
        assert {"evaluation.json", "evaluation.csv", "config.yaml", "progress.csv"} <= names
        assert sorted(p.name for p in (kept / run.name).iterdir()) == sorted(names)
        for path in records:
            assert (kept / run.name / path.name).read_bytes() == path.read_bytes()
    # the archive alone gives the runs' own tables
    quiet = {"trajectories": False, "log": lambda _: None}
    from_runs = build_report([sweep], tmp_path / "from_runs", **quiet)
    from_kept = build_report([kept], tmp_path / "from_kept", **quiet)
    for name in (TABLE_MD, TRAINING_SAFETY_MD):
        made = (tmp_path / "from_kept" / name).read_text()
        assert made == (tmp_path / "from_runs" / name).read_text()
    assert from_kept.warnings == from_runs.warnings == []

    # again: every run skipped (already evaluated), its archive left as it is
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "0 evaluated" in out and f"{len(runs)} archived" in out
    # an archived evaluation with other bytes (e.g. of another run of that name) stays
    tampered = kept / runs[0].name / "evaluation.json"
    tampered.write_text("{}")
    assert main(args) == 1
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "pass --force" in lines[0] and runs[0].name in lines[0]
    assert "Traceback" not in err and tampered.read_text() == "{}"
    # --force evaluates again and replaces the archived files with the new ones
    assert main([*args, "--force"]) == 0
    capsys.readouterr()
    assert tampered.read_bytes() == (runs[0] / "evaluation.json").read_bytes()

    unevaluated = tmp_path / "fresh"
    unevaluated.mkdir()
    (unevaluated / "config.yaml").write_text("seed: 0\n")
    with pytest.raises(ArchiveError, match="not evaluated"):
        archive_run(unevaluated, kept)
    assert not (kept / "fresh").exists()
