"""keep_checkpoints_at: the policy during training, kept and drawn by ``report`` (Figure 5's stages)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _evaluation_helpers import png_size, train_run
from _training_helpers import compose_config

from wcsac_rl.evaluation import plots
from wcsac_rl.evaluation.evaluator import load_policy
from wcsac_rl.evaluation.reporting import _kept_trajectories, build_report
from wcsac_rl.training import ConfigError, TrainingError, validate_config
from wcsac_rl.training.checkpoint import keep_checkpoint, kept_checkpoints, load_checkpoint

PANEL_PX = round(plots.TRAJECTORY_PANEL * plots.DPI)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny WCSAC run of 3 epochs (400 frames each) keeping epochs 1 and 2."""
    run_dir = tmp_path_factory.mktemp("kept") / "run"
    return train_run(
        run_dir,
        "wcsac",
        0,
        "total_frames=1200",
        "keep_checkpoints_at=[1,2]",
        "checkpoint_every_epochs=5",
    )


def test_the_chosen_epochs_are_kept_beside_the_last_checkpoint(run):
    kept = kept_checkpoints(run)
    assert [frames for frames, _ in kept] == [400, 800]
    for frames, path in kept:
        assert path.name == f"frames-{frames}.pt"
        assert load_checkpoint(path)["frames"] == frames
    assert load_checkpoint(run / "checkpoints" / "last.pt")["frames"] == 1200
    assert not list((run / "checkpoints").glob(".tmp-*"))


def test_a_kept_checkpoint_restores_the_policy_of_its_time(run):
    policies = [load_policy(path, 0) for _, path in kept_checkpoints(run)]
    policies.append(load_policy(run, 0))
    try:
        weights = [torch.cat([p.flatten() for p in r.policy.actor.parameters()]) for r in policies]
        assert [r.frames for r in policies] == [400, 800, 1200]
        # three different policies (training moved the actor between them)
        assert not torch.equal(weights[0], weights[1]) and not torch.equal(weights[1], weights[2])
    finally:
        for r in policies:
            r.env.close()


def test_report_draws_one_panel_per_kept_checkpoint_and_the_end(run, tmp_path):
    lines: list[str] = []
    result = build_report(
        [run], tmp_path / "out", trajectory_runs=[run], trajectory_episodes=2,
        trajectory_max_steps=20, log=lines.append,
    )  # fmt: skip
    stages = result.out_dir / "fig5_stages.png"
    assert stages in result.files
    assert png_size(stages) == (3 * PANEL_PX, PANEL_PX)  # one run: 400, 800, 1200 frames
    assert any("at 400 frames" in line for line in lines)
    assert any("at 800 frames" in line for line in lines)
    # the panels are the kept policies' own paths: the first differs from the end's
    _, path_400 = kept_checkpoints(run)[0]
    _, early = _kept_trajectories(path_400, 7, 1, 20)
    final = load_policy(run, 7)
    try:
        from wcsac_rl.evaluation.trajectories import collect_trajectories

        torch.manual_seed(7)
        _, late = collect_trajectories(final.env, final.policy, 1, max_steps=20)
    finally:
        final.env.close()
    assert np.allclose(early[0].xy[0], late[0].xy[0])  # same start (same env seed)
    assert not np.allclose(early[0].xy, late[0].xy)  # different policies, different paths


def test_stage_rows_choose_which_drawn_runs_get_stage_panels(run, tmp_path):
    common = {"trajectory_runs": [run], "trajectory_episodes": 1, "trajectory_max_steps": 5}
    lines: list[str] = []
    other = build_report(
        [run], tmp_path / "other", stage_rows=["sac_lag"], log=lines.append, **common
    )
    assert not (other.out_dir / "fig5_stages.png").exists()  # the drawn run is WCSAC-0.5
    assert (other.out_dir / "fig5_trajectories.png").is_file()
    assert not any("at 400 frames" in line for line in lines)  # kept policies not rolled out
    assert "Figure 5 stages: no drawn run of row(s) sac_lag" in other.warnings
    chosen = build_report(
        [run], tmp_path / "chosen", stage_rows=["wcsac_0.5"], log=lambda _: None, **common
    )
    assert png_size(chosen.out_dir / "fig5_stages.png") == (3 * PANEL_PX, PANEL_PX)
    assert not any("Figure 5 stages" in w for w in chosen.warnings)


def test_bad_settings_and_write_failures_are_clear(tmp_path):
    for value in ("[0]", "3", "[a]"):
        with pytest.raises(ConfigError, match="keep_checkpoints_at must be a list of epochs"):
            validate_config(compose_config("env=tiny", f"keep_checkpoints_at={value}"))
    source = tmp_path / "checkpoints" / "last.pt"
    source.parent.mkdir()
    source.write_bytes(b"x")
    (tmp_path / "checkpoints" / "frames-5.pt").mkdir()  # a directory where the copy goes
    with pytest.raises(TrainingError, match="cannot keep checkpoint"):
        keep_checkpoint(source, 5)
    assert sorted(p.name for p in source.parent.iterdir()) == ["frames-5.pt", "last.pt"]
