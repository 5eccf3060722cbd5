"""Training-time safety: the metrics' one definition, the trainer's running columns
(carried over by a resume), the curves' cumulative-cost panel and the report's table."""

from __future__ import annotations

import csv
import math

import pytest
from _training_helpers import ROOT, compose_config
from omegaconf import OmegaConf

from wcsac_rl.evaluation.plots import CUMULATIVE_PANEL, run_curves_figure
from wcsac_rl.evaluation.reporting import build_report
from wcsac_rl.evaluation.training_safety_table import TRAINING_SAFETY_CSV, TRAINING_SAFETY_MD
from wcsac_rl.training import make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, save_checkpoint
from wcsac_rl.training.progress import read_progress
from wcsac_rl.training.training_safety import (
    TrainingSafety,
    cumulative_cost,
    training_safety,
)

D = 15.0
NAN = math.nan
RUNNING = ("train/cumulative_cost", "train/epochs_over_limit", "train/peak_epoch_cost")


def _columns(costs, episodes, totals, *, epoch_frames=10_000):
    """progress columns of an old run (no cumulative column): cost rate = total / frames."""
    frames = [epoch_frames * (i + 1) for i in range(len(costs))]
    return {
        "frames": [float(f) for f in frames],
        "train/episode_cost": list(costs),
        "train/episodes": list(episodes),
        "train/cost_rate": [total / f for total, f in zip(totals, frames)],
    }


# 10 k-frame epochs. Over d: 10 k (warm-up), 40 k (warm-up), 50 k (ends at the warm-up's
# end: still warm-up), 60 k. Not over: 20 k (no episode), 30 k (= d), 70 k, 80 k (no episode).
COSTS = [40.0, NAN, 15.0, 20.0, 16.0, 50.0, 3.0, NAN]
EPISODES = [2, 0, 3, 1, 2, 2, 4, 0]
TOTALS = [80.0, 80.0, 125.0, 145.0, 177.0, 277.0, 289.0, 289.0]


# ------------------------------------------------------------------ the definition
def test_the_metrics_of_a_progress_table_with_known_costs():
    s = training_safety(_columns(COSTS, EPISODES, TOTALS), D)
    assert s.epochs == 8 and s.frames == 80_000
    assert s.cumulative_cost == pytest.approx(289.0, rel=1e-12)
    assert s.epochs_over_limit == 4
    assert s.epochs_over_limit_after_warmup == 1  # only the epoch ending at 60 k
    assert s.peak_epoch_cost == 50.0
    assert s.safe_from_frames == 60_000  # the last epoch over d ended there
    # another warm-up counts the epochs ending after it
    for warmup, counted in ((0, 4), (45_000, 2)):
        s = training_safety(_columns(COSTS, EPISODES, TOTALS), D, warmup_frames=warmup)
        assert s.epochs_over_limit_after_warmup == counted, warmup


def test_a_run_that_ends_over_d_is_never_safe_for_good_and_one_never_over_d_from_0():
    ends_over = training_safety(_columns([*COSTS, 20.0], [*EPISODES, 1], [*TOTALS, 309.0]), D)
    assert math.isnan(ends_over.safe_from_frames) and ends_over.epochs_over_limit == 5
    safe = training_safety(_columns([3.0, NAN, 15.0], [1, 0, 2], [3.0, 3.0, 33.0]), D)
    assert safe.epochs_over_limit == 0 and safe.safe_from_frames == 0
    assert safe.peak_epoch_cost == 15.0


def test_epochs_without_a_finished_episode_are_neither_over_d_nor_peaks():
    none = training_safety(_columns([NAN, NAN], [0, 0], [5.0, 9.0]), D)
    assert none.epochs_over_limit == 0 and math.isnan(none.peak_epoch_cost)
    assert math.isnan(none.safe_from_frames)  # nothing known
    assert none.cumulative_cost == pytest.approx(9.0, rel=1e-12)  # the steps still cost
    # an epoch with 0 episodes is one without a cost, whatever its cell says
    zero = training_safety(_columns([99.0, 1.0], [0, 1], [99.0, 100.0]), D)
    assert zero.epochs_over_limit == 0 and zero.peak_epoch_cost == 1.0


def test_cumulative_cost_is_the_logged_column_else_cost_rate_times_frames():
    columns = _columns([1.0, 2.0, 3.0], [1, 1, 1], [10.0, 20.0, 30.0])
    # a run resumed by this code: its old rows have an empty cell
    columns["train/cumulative_cost"] = [NAN, 21.5, 30.25]
    assert cumulative_cost(columns) == pytest.approx([10.0, 21.5, 30.25], rel=1e-12)
    assert training_safety(columns, D).cumulative_cost == 30.25
    del columns["train/cost_rate"]
    assert training_safety(columns, D).cumulative_cost == 30.25


def test_the_running_counts_are_the_fold_of_the_rows_so_far():
    columns = _columns(COSTS, EPISODES, TOTALS)
    running = TrainingSafety(D)
    for k, (frames, cost, total) in enumerate(
        zip(columns["frames"], COSTS, cumulative_cost(columns)), start=1
    ):
        running.add_epoch(frames, cost, total)
        prefix = {key: values[:k] for key, values in columns.items()}
        assert _same(running.columns(), training_safety(prefix, D).columns())
    assert TrainingSafety.from_state(running.state_dict()) == running


@pytest.mark.parametrize(
    ("columns", "cost_limit", "message"),
    [
        (
            {"frames": [1.0]},
            D,
            r"lack train/episode_cost, train/cumulative_cost or train/cost_rate",
        ),
        (_columns([1.0, 2.0], [1, 1], [1.0, 3.0]) | {"frames": [1.0]}, D, "differ in length"),
        (_columns([1.0], [1], [1.0]), -1.0, "cost_limit must be >= 0"),
        (_columns([1.0], [1], [1.0]), NAN, "cost_limit must be >= 0"),
    ],
)
def test_bad_input_is_one_clear_error(columns, cost_limit, message):
    with pytest.raises(ValueError, match=message):
        training_safety(columns, cost_limit)


def test_the_committed_runs_old_progress_files_give_the_metrics():
    files = sorted(ROOT.glob("results/*_laptop/runs/*/progress.csv"))
    assert len(files) == 36
    for path in files:
        columns = read_progress(path)
        s = training_safety(columns, D)
        assert s.epochs == len(columns["frames"]) == 20
        # the per-step sum: ≥ the sum of the finished episodes' costs (the episodes still
        # running at the end add the rest; ≤ 0.3 % here)
        episodes = sum(
            c * n for c, n in zip(columns["train/episode_cost"], columns["train/episodes"]) if n
        )
        assert s.cumulative_cost == pytest.approx(episodes, rel=5e-3), path
        assert s.cumulative_cost >= episodes - 1e-6 * s.cumulative_cost, path
    sac_lag = training_safety(
        read_progress(ROOT / "results/static_laptop/runs/sac_lag_static_seed0/progress.csv"), D
    )
    assert sac_lag.cumulative_cost == pytest.approx(18582.0, rel=1e-12)
    assert sac_lag.epochs_over_limit == 9
    assert sac_lag.epochs_over_limit_after_warmup == 5
    assert sac_lag.peak_epoch_cost == pytest.approx(153.6666717529297, rel=1e-12)
    assert math.isnan(sac_lag.safe_from_frames)  # 15.15 > d in the last epoch


# --------------------------------------------------------------------- the trainer
# SAC on the tiny env (100-step episodes, 2 envs, 400-frame epochs): its second epoch's
# episodes cross the hazard; d = 0 makes every epoch with a cost an epoch over d
TINY_SAC = ("algo=sac", "env=tiny", "cost_limit=0")


def _train(run_dir, *overrides):
    trainer = make_trainer(compose_config(*TINY_SAC, *overrides), run_dir)
    try:
        trainer.run()
    finally:
        trainer.close()
    return trainer


def _same(a: dict, b: dict) -> bool:
    """Equal dicts, NaN equal to NaN."""

    def equal(x, y) -> bool:
        both_nan = isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)
        return both_nan or x == y

    return a.keys() == b.keys() and all(equal(a[k], b[k]) for k in a)


def _assert_running_columns(run_dir, cost_limit=0.0):
    """Each row's running columns are the fold of the rows up to it."""
    columns = read_progress(run_dir / "progress.csv")
    for k in range(1, len(columns["frames"]) + 1):
        prefix = {key: values[:k] for key, values in columns.items()}
        logged = {key: columns[key][k - 1] for key in RUNNING}
        assert _same(logged, training_safety(prefix, cost_limit).columns()), k
    return columns


def test_the_trainer_logs_the_running_columns_and_a_resume_continues_them(tmp_path, capsys):
    run_dir = tmp_path / "run"
    first = _train(run_dir)
    columns = _assert_running_columns(run_dir)
    assert columns["train/cumulative_cost"][-1] == first.tracker.total_cost
    assert columns["train/cumulative_cost"][-1] == pytest.approx(
        columns["train/cost_rate"][-1] * 800, rel=1e-12
    )
    assert columns["train/epochs_over_limit"][-1] >= 1, "the test needs an epoch over d"
    saved = load_checkpoint(first.checkpoint_path)["training_safety"]
    assert saved == first.training_safety.state_dict()

    resumed = _train(run_dir, "total_frames=1600", f"resume={run_dir}")
    columns = _assert_running_columns(run_dir)  # rows 3, 4 count on from rows 1, 2
    assert columns["frames"] == [400.0, 800.0, 1200.0, 1600.0]
    assert columns["train/epochs_over_limit"][2] >= columns["train/epochs_over_limit"][1] >= 1
    assert columns["train/cumulative_cost"][-1] == resumed.tracker.total_cost
    assert "warning" not in capsys.readouterr().out.lower()


def test_a_checkpoint_from_before_the_counts_recounts_them_from_progress_csv(tmp_path, capsys):
    run_dir = tmp_path / "run"
    first = _train(run_dir)
    state = load_checkpoint(first.checkpoint_path)
    expected = state.pop("training_safety")
    save_checkpoint(first.checkpoint_path, state)  # as written before this change
    capsys.readouterr()
    resumed = make_trainer(
        compose_config(*TINY_SAC, "total_frames=1600", f"resume={run_dir}"), run_dir
    )
    try:
        assert _same(resumed.training_safety.state_dict(), expected)
        said = capsys.readouterr()
        assert "warning" not in (said.out + said.err).lower()  # nothing alarming
        resumed.run()
    finally:
        resumed.close()
    _assert_running_columns(run_dir)
    # nor without a progress.csv: the counts start again, the cumulative cost is the
    # checkpoint's own
    (run_dir / "progress.csv").unlink()
    save_checkpoint(resumed.checkpoint_path, state)  # back to 800 frames
    again = make_trainer(
        compose_config(*TINY_SAC, "total_frames=1200", f"resume={run_dir}"), run_dir
    )
    try:
        assert again.training_safety.epochs == 0
        again.run()
    finally:
        again.close()
    row = read_progress(run_dir / "progress.csv")
    assert row["train/cumulative_cost"] == [again.tracker.total_cost]


def test_the_progress_bar_shows_the_cumulative_cost_and_epochs_over_d():
    from wcsac_rl.training.trainer import _postfix

    row = {"train/cumulative_cost": 1234.4, "train/epochs_over_limit": 3}
    finished = {"train/episodes": 2, "train/episode_return": 0.5, "train/episode_cost": 12.25}
    assert _postfix({**row, **finished}) == "ret=0.50, cost=12.2, cum_cost=1234, epochs>d=3"
    assert _postfix({**row, "train/episodes": 0}) == (
        "no finished episode, cum_cost=1234, epochs>d=3"
    )


# ---------------------------------------------------------------------- curves.png
def test_curves_have_a_cumulative_cost_panel_also_for_old_runs():
    old = _columns(COSTS, EPISODES, TOTALS)
    for columns in (old, old | {"train/cumulative_cost": TOTALS}):
        fig = run_curves_figure(columns, cost_limit=D)
        titles = [ax.get_title() for ax in fig.axes]
        assert titles[:4] == ["episode return", "episode cost", "cost rate", CUMULATIVE_PANEL]
        line = fig.axes[3].get_lines()[0]
        assert line.get_ydata() == pytest.approx(TOTALS, rel=1e-12)
        # the episode-cost panel has the limit d dashed
        dashed = [ln for ln in fig.axes[1].get_lines() if ln.get_linestyle() == "--"]
        assert [ln.get_ydata()[0] for ln in dashed] == [D]


# ------------------------------------------------------------------------ the report
def _fake_run(root, name, label, seed, columns):
    run_dir = root / name
    run_dir.mkdir(parents=True)
    cfg = {"algo": {"name": label.split("_")[0], "label": label}, "env": {"name": "static"}}
    OmegaConf.save({**cfg, "seed": seed, "cost_limit": D}, run_dir / "config.yaml")
    keys = list(columns)
    with (run_dir / "progress.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["epoch", *keys])
        writer.writerows([i + 1, *row] for i, row in enumerate(zip(*columns.values())))


def test_the_report_writes_the_training_safety_table_in_table_1s_row_order(tmp_path):
    runs = tmp_path / "runs"
    _fake_run(runs, "w_seed10", "wcsac_0.1", 10, _columns([3.0, 2.0], [1, 1], [3.0, 5.0]))
    _fake_run(runs, "w_seed0", "wcsac_0.1", 0, _columns(COSTS, EPISODES, TOTALS))
    sac = _columns([40.0, 30.0], [1, 1], [40.0, 70.0]) | {"train/cumulative_cost": [40.0, 71.0]}
    _fake_run(runs, "sac_seed0", "sac", 0, sac)
    report = build_report([runs], tmp_path / "out", trajectories=False, log=lambda _: None)
    assert {TRAINING_SAFETY_MD, TRAINING_SAFETY_CSV} <= {p.name for p in report.files}
    with (tmp_path / "out" / TRAINING_SAFETY_CSV).open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [(r["label"], r["seed_list"]) for r in rows] == [("sac", "0"), ("wcsac_0.1", "0 10")]
    sac_row, wcsac = rows
    assert float(sac_row["cumulative_cost"]) == 71.0  # the logged column
    assert sac_row["safe_from_frames"] == "nan" and sac_row["epochs_over_limit"] == "2.0"
    assert wcsac["epochs_over_limit_per_seed"] == "4 0"
    assert wcsac["epochs_over_limit_after_warmup_per_seed"] == "1 0"
    assert float(wcsac["epochs_over_limit"]) == 2.0
    assert wcsac["peak_epoch_cost_per_seed"] == "50.0 3.0"
    assert wcsac["safe_from_frames_per_seed"] == "60000.0 0.0"
    assert float(wcsac["safe_from_frames"]) == 30_000
    assert float(wcsac["cumulative_cost"]) == pytest.approx((289.0 + 5.0) / 2, rel=1e-12)
    lines = (tmp_path / "out" / TRAINING_SAFETY_MD).read_text().splitlines()
    assert lines[0] == "# Training safety — StaticEnv, budget d = 15"
    assert lines[4] == "| SAC | 71 | 2 | 0 | 40.00 | never | 20 k (1) |"
    assert lines[5] == (
        "| WCSAC-0.1 | 147 (289 / 5) | 2 (4 / 0) | 0.5 (1 / 0) | 26.50 (50.00 / 3.00) "
        "| 30 k (60 k / 0 k) | 80 k (2) |"
    )


def test_frames_are_written_in_thousands_with_at_most_one_decimal():
    """A mean over seeds of frames (170 k, 90 k, 120 k) is 126.7 k, not 126.667 k."""
    from wcsac_rl.evaluation.training_safety_table import _frames_text

    assert _frames_text((170_000 + 90_000 + 120_000) / 3) == "126.7 k"
    assert _frames_text(130_000 / 3) == "43.3 k"
    assert _frames_text(60_000) == "60 k" and _frames_text(0.0) == "0 k"
    assert _frames_text(math.nan) == "never"


def test_a_run_in_which_no_training_episode_finished_is_a_dash_not_never(tmp_path):
    """Nothing was measured: no peak and no "never" (which says the last epoch was over d)."""
    runs = tmp_path / "runs"
    _fake_run(runs, "short_seed0", "sac", 0, _columns([NAN, NAN], [0, 0], [0.0, 0.0]))
    _fake_run(runs, "short_seed1", "sac", 1, _columns([NAN, NAN], [0, 0], [0.0, 0.0]))
    build_report([runs], tmp_path / "out", trajectories=False, log=lambda _: None)
    lines = (tmp_path / "out" / TRAINING_SAFETY_MD).read_text().splitlines()
    assert lines[4].split(" | ")[4:6] == ["– (– / –)", "– (– / –)"]
    assert "never" not in lines[4]
    assert lines[-1].endswith(" –: no training episode finished in the run (nothing was measured).")
