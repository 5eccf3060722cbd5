"""Reports of small training budgets do not mislead: the env-step axes of short runs
show whole steps (never ``200 m``), a panel no training episode reached says so inside
it, the ± std bands of a cost end at 0, a name with ``$`` is drawn as written (not
parsed as a formula), and ``wcsac-evaluate`` warns of a run evaluated before its
``total_frames``. (The figures' style: tests/test_figures.py.)"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from _evaluation_helpers import train_run
from _training_helpers import compose_config
from matplotlib.backends.backend_agg import FigureCanvasAgg
from omegaconf import OmegaConf

from wcsac_rl.evaluation import plots
from wcsac_rl.evaluation.runs import row_name
from wcsac_rl.training.checkpoint import load_checkpoint
from wcsac_rl.training.progress import read_progress

DOLLAR = "s$\\frac{1}{$x"  # a row label matplotlib's mathtext cannot parse
STOPPED_TOTAL = 3_000_000  # the stopped run's config: far more frames than it trained


def _drawn(fig):
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig


def _captured(monkeypatch, name="_save"):
    """The figures a plotting function makes, by their file name (nothing written)."""
    figures = {}

    def keep(fig, out, formats=("png",)):
        figures[Path(out).name] = fig
        return Path(out)

    monkeypatch.setattr(plots, name, keep)
    return figures


def _tick_texts(ax):
    return [t.get_text() for t in ax.get_xticklabels() if t.get_text()]


WHOLE_STEPS = re.compile(r"−?\d+|\d+(\.\d+)? [kMG]")  # 0, 200, 1.5 k, 3 M: never "200 m"


def _assert_whole_step_ticks(ax):
    texts = _tick_texts(ax)
    assert texts, ax.get_title()
    assert all(WHOLE_STEPS.fullmatch(text) for text in texts), (ax.get_title(), texts)


# ------------------------------------------------------------------ short runs' axes
@pytest.fixture(scope="module")
def unfinished_episodes(tmp_path_factory):
    """A real run of 800 frames whose 1000-step episodes never end: no training
    episode finished in any epoch."""
    run_dir = tmp_path_factory.mktemp("short") / "random_tiny_seed0"
    train_run(run_dir, "random", 0, "env.max_episode_steps=1000")
    return read_progress(run_dir / "progress.csv")


def test_a_short_run_without_a_finished_episode_says_so_and_counts_whole_steps(
    unfinished_episodes, tmp_path, monkeypatch
):
    columns = unfinished_episodes
    assert columns["frames"] == [400.0, 800.0]
    assert all(math.isnan(v) for v in columns["train/episode_return"])  # (what it tests)
    figures = _captured(monkeypatch)
    plots.plot_training_curves({"random": [columns]}, tmp_path / "f4.png", cost_limit=15)
    fig = _drawn(figures["f4.png"])
    texts = {ax.get_title(): [t.get_text() for t in ax.texts] for ax in fig.axes}
    assert texts == {
        "(a) Average episodic return": [plots.NO_TRAINING_EPISODES],
        "(b) Average episodic cost": [plots.NO_TRAINING_EPISODES],
        "(c) Cost rate": [],  # (per env step: drawn)
    }
    assert plots.NO_TRAINING_EPISODES == "no finished training episodes"
    for ax in fig.axes:
        _assert_whole_step_ticks(ax)
        low, high = ax.get_xlim()
        assert low < 400 and high > 800  # the runs' env steps, as the drawn panel's
    # the empty cost panel still shows where the budget d lies
    cost = fig.axes[1]
    assert cost.get_ylim() == (0.0, 22.5) and cost.get_yticks().size > 0
    # a run's own curves: its return and cost panels say it too, under the test
    # episodes' curves (those, at most 1000 steps, ended) ...
    assert not math.isnan(columns["eval/episode_return"][0])
    fig = _drawn(plots.run_curves_figure(columns, cost_limit=15))
    by_title = {ax.get_title(): ax for ax in fig.axes}
    for title in ("episode return", "episode cost"):
        ax = by_title[title]
        assert [t.get_text() for t in ax.texts] == [plots.NO_TRAINING_EPISODES], title
        assert ax.get_lines()[0].get_label() == "test (deterministic)"
    for ax in fig.axes:
        _assert_whole_step_ticks(ax)
    # ... and, without a test episode either, inside the empty panel
    no_tests = {**columns, "eval/episode_return": [math.nan] * 2}
    no_tests["eval/episode_cost"] = [math.nan] * 2
    fig = _drawn(plots.run_curves_figure(no_tests, cost_limit=15))
    by_title = {ax.get_title(): ax for ax in fig.axes}
    for title in ("episode return", "episode cost"):
        assert [t.get_text() for t in by_title[title].texts] == [plots.NO_EPISODES], title
    for ax in fig.axes:
        _assert_whole_step_ticks(ax)


@pytest.mark.parametrize(
    "frames",
    [[200.0], [400.0, 800.0], [400.0 * i for i in range(1, 9)], [50.0, 100.0], [1.0, 2.0]],
)
def test_the_env_step_ticks_of_a_short_run_are_never_fractions_of_a_step(
    frames, tmp_path, monkeypatch
):
    """Runs of one to eight epochs, down to a few steps: whole-step labels only, whether
    a panel is drawn or empty."""
    n = len(frames)
    columns = {
        "frames": frames,
        "train/episode_return": [math.nan] * (n - 1) + [-3.0],
        "train/episode_cost": [math.nan] * n,
        "train/cost_rate": [0.01] * n,
    }
    figures = _captured(monkeypatch)
    plots.plot_training_curves({"sac": [columns]}, tmp_path / "f4.png", cost_limit=15)
    for fig in (_drawn(figures["f4.png"]), _drawn(plots.run_curves_figure(columns))):
        for ax in fig.axes:
            _assert_whole_step_ticks(ax)


def test_the_frames_formatter_writes_whole_steps_then_engineering_units():
    label = plots.frames_formatter()
    assert [label(v) for v in (0.0, 0.2, 200.0, 999.0)] == ["0", "0", "200", "999"]
    assert [label(v) for v in (1000.0, 1500.0, 50_000.0, 3_000_000.0)] == [
        "1 k",
        "1.5 k",
        "50 k",
        "3 M",
    ]
    assert label(-20.0) == "−20"  # (matplotlib's minus, as its other labels)


# ------------------------------------------------------------------------ cost bands
def _band_lows(ax):
    """The lowest y of each ± std band (a PolyCollection) of a panel."""
    return [min(path.vertices[:, 1].min() for path in c.get_paths()) for c in ax.collections]


def test_the_std_bands_of_a_cost_end_at_zero_and_those_of_a_return_do_not(tmp_path, monkeypatch):
    """Three seeds with costs 0, 0, 10: mean 3.3, std 4.7; a band at mean - std would
    reach -1.4, a cost no episode can have. The return panel keeps its negative band."""
    runs = [
        {
            "frames": [400.0, 800.0],
            "train/episode_return": [value, value],
            "train/episode_cost": [value, value],
            "train/cost_rate": [value / 100, value / 100],
        }
        for value in (0.0, 0.0, 10.0)
    ]
    mean, std = np.mean([0, 0, 10]), np.std([0, 0, 10])
    assert mean - std < -1
    figures = _captured(monkeypatch)
    plots.plot_training_curves({"wcsac_0.1": runs}, tmp_path / "f4.png", cost_limit=15)
    ret, cost, rate = figures["f4.png"].axes
    assert _band_lows(ret) == [pytest.approx(mean - std)]
    assert _band_lows(cost) == [0.0] and _band_lows(rate) == [0.0]
    # the upper edge is still mean + std
    top = max(path.vertices[:, 1].max() for path in cost.collections[0].get_paths())
    assert top == pytest.approx(mean + std)


# --------------------------------------------------------------- names with a dollar
def _all_texts(fig):
    """The texts ``fig`` draws (a tick's hidden second label is not drawn)."""
    return fig.findobj(lambda a: hasattr(a, "get_parse_math") and a.get_visible())


def _literal(fig, text):
    """The texts of ``fig`` that show ``text``; each drawn as written."""
    found = [t for t in _all_texts(fig) if text in t.get_text()]
    assert found, text
    for t in found:
        assert not t.get_parse_math() and not t.get_usetex(), t.get_text()
    return found


def test_a_row_label_with_a_dollar_is_drawn_as_written_in_every_figure(tmp_path):
    """Figure 4, 6 and 5, fig_runs and the score distribution of a row ``s$\\frac{1}{$x``
    are written (PNG and PDF) without a mathtext error, the name shown as written."""
    from test_figures import _statistics

    from wcsac_rl.evaluation.plots import plot_run_values, plot_score_distribution

    name = row_name(DOLLAR)
    assert "$" in name
    progress = {
        "frames": [400.0, 800.0],
        "train/episode_return": [1.0, 2.0],
        "train/episode_cost": [3.0, 1.0],
        "train/cost_rate": [0.01, 0.01],
    }
    made = {}

    def keep(fig, out, formats=plots.FIGURE_FORMATS):
        made[Path(out).name] = fig
        return plots.save_figure(fig, out, formats=formats)

    original = plots._save
    plots._save = keep
    try:
        title = f"study {DOLLAR}"
        plots.plot_training_curves(
            {DOLLAR: [progress], "sac": [progress]},
            tmp_path / "f4.png",
            title=title,
            formats=plots.FIGURE_FORMATS,
        )
        plots.plot_cost_distribution(
            {DOLLAR: [1.0, 2.0], "sac": [3.0]},
            tmp_path / "f6.png",
            cost_limit=15,
            title=title,
            formats=plots.FIGURE_FORMATS,
        )
        layout = {
            "placement_extents": [-1, -1, 1, 1],
            "hazards_xy": [[0.5, 0.5]],
            "hazards_size": 0.2,
            "goal_xy": [0.0, 0.8],
            "goal_size": 0.1,
        }

        class Trajectory:
            xy = np.array([[0.0, 0.0], [0.1, 0.2]])
            goals = np.array([[0.0, 0.8]])
            cost, ret = 1.0, 0.5

        plots.plot_trajectories(
            [(f"{name}, seed 0", layout, [Trajectory()])],
            tmp_path / "f5.png",
            title=title,
            rows=[DOLLAR],
            formats=plots.FIGURE_FORMATS,
        )
    finally:
        plots._save = original
    for out in ("f4.png", "f6.png", "f5.png"):
        for path in plots.figure_paths(tmp_path / out):
            assert path.stat().st_size > 0, path
        _literal(made[out], DOLLAR)  # the title and the row's name
    legend = made["f4.png"].legends[0]
    assert f"{name} (1 seed)" in [t.get_text() for t in legend.get_texts()]
    assert name in [t.get_text() for t in made["f6.png"].axes[0].get_xticklabels()]
    assert made["f5.png"].axes[0].get_title() == f"{name}, seed 0"

    stats = _statistics(["sac", DOLLAR])
    runs = plot_run_values(stats, tmp_path / "runs.png", title=title, formats=plots.FIGURE_FORMATS)
    score = plot_score_distribution(
        stats, tmp_path / "score.png", title=title, formats=plots.FIGURE_FORMATS
    )
    for out in (runs, score):
        for path in plots.figure_paths(out):
            assert path.stat().st_size > 0, path


@pytest.mark.parametrize("which", ["runs", "score"])
def test_a_dollar_in_the_runs_figures_is_drawn_as_written(which, tmp_path, monkeypatch):
    from test_figures import _statistics

    figures = _captured(monkeypatch, "save_figure")
    stats = _statistics(["sac", DOLLAR])
    plot = plots.plot_run_values if which == "runs" else plots.plot_score_distribution
    plot(stats, tmp_path / f"{which}.png", title=f"study {DOLLAR}")
    fig = _drawn(figures[f"{which}.png"])
    texts = _literal(fig, "\\frac{1}{$")  # (the panels' own formulas stay formulas)
    assert any(t.get_text().endswith(f"study {DOLLAR}") for t in texts)
    assert any(row_name(DOLLAR) in t.get_text() for t in texts)  # a tick or legend entry


def test_a_run_named_with_a_dollar_titles_its_curves_as_written(tmp_path):
    progress = tmp_path / f"run {DOLLAR}" / "progress.csv"
    progress.parent.mkdir()
    progress.write_text(
        "epoch,frames,train/episode_return,train/episode_cost,train/cost_rate\n"
        "1,400,1.0,2.0,0.01\n2,800,2.0,1.0,0.01\n"
    )
    out = plots.plot_run_curves(progress, tmp_path / "curves.png", cost_limit=15)
    assert out.stat().st_size > 0
    fig = plots.run_curves_figure(read_progress(progress), title=f"run {DOLLAR}")
    [title] = _literal(_drawn(fig), DOLLAR)
    assert title.get_text() == f"run {DOLLAR}"


# ------------------------------------------------------------- evaluating early runs
def _stopped_run(run_dir: Path) -> int:
    """A real run of ``algo=random`` stopped (Ctrl-C) after its first batch, long before
    its ``total_frames``; its checkpoint's frames."""
    from wcsac_rl.training.registry import trainer_class

    class StopsAfterOneBatch(trainer_class("random")):
        def learn(self, batch):
            super().learn(batch)
            raise KeyboardInterrupt

    cfg = compose_config(
        "algo=random",
        "env=tiny",
        "env.max_episode_steps=50",
        "seed=0",
        f"total_frames={STOPPED_TOTAL}",
        "epoch_frames=400",
    )
    trainer = StopsAfterOneBatch(cfg, run_dir)
    try:
        with pytest.raises(KeyboardInterrupt):
            trainer.run()
    finally:
        trainer.close()
    return int(load_checkpoint(run_dir / "checkpoints" / "last.pt")["frames"])


@pytest.fixture(scope="module")
def early_and_done(tmp_path_factory):
    """``(stopped run, its frames, finished run)``, made once; tests copy them."""
    root = tmp_path_factory.mktemp("evaluate_early")
    stopped = root / "stopped_random_tiny_seed0"
    frames = _stopped_run(stopped)
    assert 0 < frames < STOPPED_TOTAL
    done = train_run(root / "done_random_tiny_seed0", "random", 0)
    return stopped, frames, done


def _warnings(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("warning:")]


def test_evaluating_an_unfinished_run_warns_in_one_line_and_still_evaluates(
    early_and_done, tmp_path, capsys
):
    from wcsac_rl.evaluate import main as evaluate

    stopped, frames, _ = early_and_done
    run_dir = Path(shutil.copytree(stopped, tmp_path / stopped.name))
    capsys.readouterr()
    assert evaluate([str(run_dir), "--episodes", "2", "--no-progress"]) == 0
    out, err = capsys.readouterr()
    assert _warnings(err) == [
        f"warning: {run_dir}: evaluated at {frames} of its {STOPPED_TOTAL} frames "
        f"(training unfinished: resume it to finish, resume={run_dir})"
    ]
    assert "1 evaluated, 0 skipped" in out and "Traceback" not in err
    meta = json.loads((run_dir / "evaluation.json").read_text())
    assert meta["trained_frames"] == frames and meta["episodes"] == 2


def test_evaluating_a_finished_run_warns_of_nothing(early_and_done, tmp_path, capsys):
    from wcsac_rl.evaluate import main as evaluate

    _, _, done = early_and_done
    run_dir = Path(shutil.copytree(done, tmp_path / done.name))
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["frames"] == 800
    capsys.readouterr()
    assert evaluate([str(run_dir), "--episodes", "2", "--no-progress"]) == 0
    out, err = capsys.readouterr()
    assert _warnings(err) == [] and "1 evaluated" in out


def test_an_unfinished_sweep_job_is_warned_of_once(early_and_done, tmp_path, capsys):
    """In a sweep, the job's own line (``warning: sweep job ... unfinished``) says it:
    no second line for the same run."""
    from wcsac_rl.evaluate import main as evaluate

    stopped, frames, _ = early_and_done
    root = tmp_path / "sweep"
    root.mkdir()
    OmegaConf.save(
        {
            "hydra": {
                "sweeper": {
                    "_target_": "hydra._internal.core_plugins.basic_sweeper.BasicSweeper",
                    "max_batch_size": None,
                    "params": {"seed": "0"},
                },
                "overrides": {"task": []},
            }
        },
        root / "multirun.yaml",
    )
    run_dir = Path(shutil.copytree(stopped, root / "0_random_tiny_seed0"))
    (run_dir / ".hydra").mkdir()
    OmegaConf.save(OmegaConf.create(["seed=0"]), run_dir / ".hydra" / "overrides.yaml")
    capsys.readouterr()
    assert evaluate([str(root), "--episodes", "2", "--no-progress"]) == 0
    _, err = capsys.readouterr()
    [line] = _warnings(err)
    assert line.startswith("warning: sweep job ") and f"{frames} of {STOPPED_TOTAL}" in line


def test_unfinished_training_reads_the_frames_against_total_frames(tmp_path):
    from wcsac_rl.evaluation.evaluator import Evaluation, unfinished_training

    def evaluation(trained, total):
        return Evaluation(tmp_path, {"trained_frames": trained}, [], total_frames=total)

    assert unfinished_training(evaluation(3200, 3_000_000)) == (
        f"{tmp_path}: evaluated at 3200 of its 3000000 frames (training unfinished: "
        f"resume it to finish, resume={tmp_path})"
    )
    assert unfinished_training(evaluation(3_000_000, 3_000_000)) is None
    assert unfinished_training(evaluation(3_000_200, 3_000_000)) is None  # (whole batches)
    assert unfinished_training(evaluation(0, None)) is None  # the random policy: no run


def test_a_dollar_in_the_cost_return_and_outcome_figures_is_drawn_as_written(tmp_path):
    from wcsac_rl.evaluation.outcomes import outcome_classes, plot_outcomes
    from wcsac_rl.evaluation.plots import plot_cost_return

    name = row_name(DOLLAR)
    row = {"label": DOLLAR, "algorithm": name, "EC": 2.0, "ER": 0.5}
    row |= {f"{m}_{end}": v for m in ("EC", "ER") for end, v in (("lo", 0.0), ("hi", 3.0))}
    plot_cost_return([row], tmp_path / "cr.png", cost_limit=15.0, title=f"t {DOLLAR}")
    counts = dict.fromkeys(outcome_classes(True), 0) | {outcome_classes(True)[0]: 5}
    outcome = {"algorithm": name, "seed": 0, "counts": counts}
    plot_outcomes([outcome], tmp_path / "o.png", title=f"t {DOLLAR}", has_goals=True)
    assert (tmp_path / "cr.png").stat().st_size > 0 and (tmp_path / "o.png").stat().st_size > 0
