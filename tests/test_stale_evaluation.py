"""An evaluation records its checkpoint; a run trained further is evaluated again and
its stale numbers never enter Table 1."""

from __future__ import annotations

import json

import pytest
from _evaluation_helpers import EPISODE_STEPS, train_run

from wcsac_rl.evaluation.evaluator import (
    EvaluationExistsError,
    evaluate_run,
    read_evaluation,
    stale_evaluation,
)
from wcsac_rl.evaluation.reporting import ReportError, build_report
from wcsac_rl.training.checkpoint import checkpoint_digest


def _resume_to(run_dir, frames):
    train_run(run_dir, "wcsac", 0, f"total_frames={frames}", f"resume={run_dir}")


def test_a_resumed_run_is_evaluated_again_and_an_unchanged_one_skipped(tmp_path):
    run_dir = tmp_path / "sweep" / "0_wcsac_0.5_tiny_seed0"
    train_run(run_dir, "wcsac", 0)
    first = evaluate_run(run_dir, episodes=2, progress=False)
    meta = json.loads((run_dir / "evaluation.json").read_text())
    assert meta["trained_frames"] == 800
    assert meta["checkpoint_sha256"] == checkpoint_digest(run_dir / "checkpoints" / "last.pt")
    assert stale_evaluation(run_dir) is None
    with pytest.raises(EvaluationExistsError):  # up to date: skipped
        evaluate_run(run_dir, episodes=2, progress=False)
    _resume_to(run_dir, 1200)
    assert stale_evaluation(run_dir) == "evaluated at 800 frames, its checkpoint now has 1200"
    notes = []
    again = evaluate_run(run_dir, episodes=2, progress=False, log=notes.append)
    assert notes == [
        f"{run_dir}: evaluating again (evaluated at 800 frames, its checkpoint now has 1200)"
    ]
    assert again.meta["trained_frames"] == 1200 and first.meta["trained_frames"] == 800
    assert read_evaluation(run_dir).meta["trained_frames"] == 1200
    assert stale_evaluation(run_dir) is None


def test_an_old_evaluation_without_a_hash_is_compared_by_frames(tmp_path):
    run_dir = tmp_path / "run"
    train_run(run_dir, "wcsac", 0)
    evaluate_run(run_dir, episodes=1, progress=False)
    path = run_dir / "evaluation.json"
    meta = json.loads(path.read_text())
    del meta["checkpoint_sha256"]
    path.write_text(json.dumps(meta))
    assert stale_evaluation(run_dir) is None
    _resume_to(run_dir, 1200)
    assert "its checkpoint now has 1200" in stale_evaluation(run_dir)


def test_report_refuses_stale_evaluations_by_run_name(tmp_path):
    sweep = tmp_path / "sweep"
    runs = [sweep / "0_wcsac_0.5_tiny_seed0", sweep / "1_wcsac_0.5_tiny_seed1"]
    for seed, run_dir in enumerate(runs):
        train_run(run_dir, "wcsac", seed)
        evaluate_run(run_dir, episodes=2, progress=False, max_episode_steps=EPISODE_STEPS)
    _resume_to(runs[0], 1200)
    with pytest.raises(ReportError) as err:
        build_report([sweep], tmp_path / "report", trajectories=False, log=lambda m: None)
    message = str(err.value)
    assert "1 evaluation(s) no longer match their run's checkpoint" in message
    assert "0_wcsac_0.5_tiny_seed0 (evaluated at 800 frames" in message
    assert "1_wcsac_0.5_tiny_seed1" not in message
    assert not (tmp_path / "report" / "table1.md").exists()
    evaluate_run(runs[0], episodes=2, progress=False)
    # evaluated again, it is no longer stale; but a 1200-frame run and an 800-frame one
    # are never pooled into one row: each is a row of its own
    both = build_report([sweep], tmp_path / "both", trajectories=False, log=lambda m: None)
    assert [row["label"] for row in both.rows] == [
        "wcsac_0.5[total_frames=1200]",
        "wcsac_0.5[total_frames=800]",
    ]
    report = build_report([runs[0]], tmp_path / "report", trajectories=False, log=lambda m: None)
    assert (report.out_dir / "table1.md").exists()
