"""A run's frame schedule: whole collector batches, said in one line; a warm-up-only budget
warned of in one line naming both numbers (wcsac_rl/training/schedule.py)."""

from __future__ import annotations

from _training_helpers import compose_config

from wcsac_rl.training import make_trainer
from wcsac_rl.training.progress import read_progress
from wcsac_rl.training.schedule import epoch_frames, schedule_notes

WARM_UP = (
    "warning: total_frames={total} is at or under algo.collector.init_random_frames={init} "
    "(the random warm-up): no frame is collected by the policy, which trains after the "
    "last batch if at all; raise total_frames or lower algo.collector.init_random_frames"
)


def _cfg(*overrides: str):
    return compose_config("env=tiny", "algo.collector.frames_per_batch=400", *overrides)


def test_frames_that_are_not_whole_batches_are_rounded_up_in_one_line_each():
    cfg = _cfg("total_frames=3000", "epoch_frames=1000")
    assert epoch_frames(cfg) == 1200
    assert schedule_notes(cfg) == [
        "total_frames=3000 is rounded up to 3200 (whole collector batches of 400 frames)",
        "epoch_frames=1000 is rounded up to 1200 (whole collector batches of 400 frames)",
    ]
    # a resume rounds what is left after the frames collected so far
    assert schedule_notes(cfg, frames_done=2800)[0].startswith(
        "total_frames=3000 is rounded up to 3200 "
    )
    assert schedule_notes(cfg, frames_done=3200) == []  # nothing left to collect
    assert schedule_notes(_cfg("total_frames=2400", "epoch_frames=800")) == []


def test_a_budget_at_or_under_the_random_warm_up_is_warned_of_naming_both_numbers():
    cfg = _cfg("total_frames=2000", "epoch_frames=400")
    assert schedule_notes(cfg, init_random_frames=2000) == [WARM_UP.format(total=2000, init=2000)]
    # the collector rounds both to whole batches: 1 000 random frames fill 3 batches
    cfg = _cfg("total_frames=1100", "epoch_frames=400", "algo.collector.init_random_frames=1000")
    assert schedule_notes(cfg, init_random_frames=1000)[-1] == WARM_UP.format(total=1100, init=1000)
    # one batch of policy frames after the warm-up: no warning; no warm-up: no warning
    assert (
        schedule_notes(_cfg("total_frames=2400", "epoch_frames=400"), init_random_frames=2000) == []
    )
    assert schedule_notes(cfg, init_random_frames=0)[-1].startswith("total_frames=1100 is rounded")


def test_epochs_are_whole_and_even_when_epoch_frames_is_not_a_multiple_of_the_batch(
    tmp_path, capsys
):
    """``epoch_frames=300`` over batches of 200: epochs of 400 frames (not 400, 600,
    1 000, 1 200 as the first batch boundary past each multiple of 300 would give)."""
    cfg = compose_config(
        "env=tiny",
        "algo=random",
        "algo.collector.num_envs=2",
        "algo.collector.frames_per_batch=200",
        "total_frames=1200",
        "epoch_frames=300",
    )
    run_dir = make_trainer(cfg, tmp_path / "run").run()
    out = capsys.readouterr().out
    line = "epoch_frames=300 is rounded up to 400 (whole collector batches of 200 frames)"
    assert out.count(line) == 1 and "total_frames=1200 is rounded" not in out
    assert read_progress(run_dir / "progress.csv")["frames"] == [400.0, 800.0, 1200.0]


def test_the_trainer_warns_of_a_warm_up_only_budget_on_stderr(tmp_path, capsys):
    cfg = compose_config("env=tiny", "total_frames=400", "algo.collector.init_random_frames=400")
    make_trainer(cfg, tmp_path / "run").close()
    captured = capsys.readouterr()
    assert WARM_UP.format(total=400, init=400) in captured.err.splitlines()
    # a random policy has no warm-up to warn of
    cfg = compose_config("env=tiny", "algo=random", "total_frames=400")
    make_trainer(cfg, tmp_path / "random").close()
    assert "warm-up" not in capsys.readouterr().err
