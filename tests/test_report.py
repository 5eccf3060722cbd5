"""``python -m wcsac_rl.report``: Table 1 and Figures 4-6 from real (tiny) runs.

Tolerances: Table-1 cells are float64 metrics written with repr (exact round trip);
approx's default ``rel=1e-6`` covers another summation order of ≤ 20 values
(20 × 2⁻⁵²). Layout comparisons are float64 copies (``np.allclose``: 1e-8 absolute).
"""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest
from _evaluation_helpers import EPISODE_STEPS, copy_sweep, png_size, run_dirs
from _training_helpers import ROOT
from PIL import Image

from wcsac_rl.evaluation import plots
from wcsac_rl.evaluation.evaluator import evaluate_random_policy, evaluate_run, read_evaluation
from wcsac_rl.evaluation.metrics import aggregate_seeds
from wcsac_rl.evaluation.reporting import ReportError, build_report

EPISODES = 6
TRAJECTORY_EPISODES = 2
FIG4_PX = (1500, 450)
FIG6_PX = (1300, 480)
PANEL_PX = 550
# the runs one by one and the statistics over them (no --improvement: no improvement.csv)
RUN_STATISTICS_FILES = (
    "run_values.md",
    "run_values.csv",
    "run_values.tex",
    "run_statistics.md",
    "run_statistics.csv",
    "run_statistics.tex",
    "fig_runs.png",
    "fig_runs.pdf",
    "fig_score_distribution.png",
    "fig_score_distribution.pdf",
)
# every figure as PNG and PDF, every table as Markdown (+ LaTeX) and CSV
TABLE_FILES = ("table1.md", "table1.csv", "table1.tex")
# each run's test episodes by outcome: a table and one stacked bar per run
OUTCOME_FILES = (
    "outcomes.md",
    "outcomes.csv",
    "outcomes.tex",
    "fig_outcomes.png",
    "fig_outcomes.pdf",
)
TRAINING_FILES = (
    "runs.md",
    "runs.tex",
    "training_safety.md",
    "training_safety.csv",
    "training_safety.tex",
)


def _figure(stem):
    return (f"{stem}.png", f"{stem}.pdf")


def _px(size_in: tuple[float, float]) -> tuple[int, int]:
    return round(size_in[0] * plots.DPI), round(size_in[1] * plots.DPI)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    """A copy of the tiny sweep (2 rows × 2 seeds), every run evaluated."""
    sweep = copy_sweep(tmp_path_factory.mktemp("report"))
    for run_dir in run_dirs(sweep):
        evaluate_run(run_dir, episodes=EPISODES, progress=False)
    return sweep


@pytest.fixture(scope="module")
def figures():
    """file name → the matplotlib Figure the report saved there (filled by ``report``)."""
    return {}


@pytest.fixture(scope="module")
def report(sweep, figures, tmp_path_factory):
    out = tmp_path_factory.mktemp("report_out") / "report"
    lines: list[str] = []
    save = plots.save_figure

    def keep(fig, path, **kwargs):  # every figure of the report goes through save_figure
        figures[path.name] = fig
        return save(fig, path, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(plots, "save_figure", keep)
        result = build_report(
            [sweep.parents[2]], out, trajectory_episodes=TRAJECTORY_EPISODES, log=lines.append
        )
    return result, lines


def _assert_png(path, size):
    assert png_size(path) == size
    image = np.asarray(Image.open(path).convert("L"), dtype=np.float64)
    assert image.std() > 10  # something is drawn, not a blank canvas


def test_report_writes_every_file(report):
    result, lines = report
    names = sorted(p.name for p in result.files)
    assert names == sorted(
        [
            *TABLE_FILES,
            *_figure("fig4_training_curves"),
            *_figure("fig5_trajectories"),
            *_figure("fig5_wcsac_0.5_seed0"),
            *_figure("fig5_random_seed0"),
            *_figure("fig6_evaluation"),
            *_figure("fig_cost_return"),
            *OUTCOME_FILES,
            *TRAINING_FILES,
            *RUN_STATISTICS_FILES,
        ]
    )
    assert sorted(p.name for p in result.out_dir.iterdir()) == names
    assert result.warnings == []
    assert [line for line in lines if line.startswith("wrote ")] == [
        f"wrote {p}" for p in result.files
    ]


def test_every_figure_is_png_and_pdf_and_every_table_markdown_csv_and_latex(report):
    result, _ = report
    out = result.out_dir
    pngs = sorted(out.glob("*.png"))
    assert len(pngs) == 9
    for png in pngs:
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert png.with_suffix(".pdf").read_bytes()[:5] == b"%PDF-", png.name
    tables = sorted(out.glob("*.md"))
    assert [p.stem for p in tables] == [
        "outcomes", "run_statistics", "run_values", "runs", "table1", "training_safety",
    ]  # fmt: skip
    for md in tables:
        tex = md.with_suffix(".tex").read_text()
        body = [line for line in md.read_text().splitlines() if line.startswith("| ")]
        rows = [line for line in tex.splitlines() if line.endswith(r" \\")]
        # every Markdown row (header included) is a LaTeX row, between booktabs rules
        assert len(rows) == len(body) and tex.count(r"\toprule") == tex.count(r"\bottomrule")
        assert tex.count(r"\midrule") == tex.count(r"\toprule") >= 1
        content = tex.split("\n", 1)[1]  # (after the comment line)
        assert "_" not in content.replace(r"\_", "") and "%" not in content.replace(r"\%", "")
        if md.stem != "runs":
            assert md.with_suffix(".csv").is_file()
    table1 = (out / "table1.tex").read_text()
    assert r"\caption{Table 1 --- TinyHazard, budget d = 15}" in table1
    assert r"Algorithm & EC & C0.9 & C0.5 & C0.1 & ER & goals & over budget" in table1
    assert r"\begin{tabular}{lrrrrrrrr}" in table1
    first = [c.strip() for c in (out / "table1.md").read_text().splitlines()[4].split("|")[1:-1]]
    row = next(line for line in table1.splitlines() if line.startswith("WCSAC-0.5 & "))
    cells = [c.strip() for c in row.removesuffix(r" \\").split(" & ")]
    bold, interval = first[3].split(" ", 1)  # "**0.12** [0.00, 0.50]": the constrained C0.5
    assert cells[3] == r"\textbf{" + bold.strip("*") + "} " + interval
    assert cells[7] == first[7].replace("%", r"\%")


def _row_colours(figures):
    """figure → {row name: (colour, marker)} as its artists draw the rows."""
    from matplotlib.colors import to_hex

    drawn = {}
    ax = figures["fig4_training_curves.png"].axes[0]
    drawn["fig4"] = {
        line.get_label().rsplit(" (", 1)[0]: (to_hex(line.get_color()), line.get_marker())
        for line in ax.get_lines()
        if not line.get_label().startswith("_")
    }
    box_ax = figures["fig6_evaluation.png"].axes[0]
    names = [t.get_text().replace("\n", " ") for t in box_ax.get_xticklabels()]
    drawn["fig6"] = {  # (the boxes are its only patches)
        name: (to_hex(patch.get_facecolor(), keep_alpha=False), None)
        for name, patch in zip(names, box_ax.patches, strict=True)
    }
    ax = figures["fig_runs.png"].axes[0]
    names = [t.get_text() for t in ax.get_xticklabels()]
    drawn["fig_runs"] = {
        names[round(line.get_xdata()[0])]: (to_hex(line.get_markeredgecolor()), line.get_marker())
        for line in ax.get_lines()  # (in black: the IQM and its interval's caps)
        if line.get_linestyle() == "None" and to_hex(line.get_markeredgecolor()) != "#000000"
    }
    ax = figures["fig_score_distribution.png"].axes[0]
    drawn["fig_score"] = {
        line.get_label().rsplit(" (", 1)[0]: (to_hex(line.get_color()), line.get_marker())
        for line in ax.get_lines()
        if "budget" not in line.get_label()
    }
    ax = figures["fig_cost_return.png"].axes[0]
    drawn["fig_cost_return"] = {
        c.get_label(): (to_hex(c.lines[0].get_color()), c.lines[0].get_marker())
        for c in ax.containers
    }
    for name in ("fig5_trajectories.png", "fig5_wcsac_0.5_seed0.png", "fig5_random_seed0.png"):
        drawn[name] = {
            ax.get_title().rsplit(", seed", 1)[0]: (to_hex(ax.spines["left"].get_edgecolor()), None)
            for ax in figures[name].axes
            if ax.get_title()
        }
    return drawn


def test_every_row_has_one_colour_and_marker_in_every_figure(report, figures):
    """Read from the figures' artists: each row of the sweep is drawn in one colour (and
    one marker where a figure draws markers) in all of them, and the rows' colours differ."""
    result, _ = report
    drawn = _row_colours(figures)
    rows = [row["algorithm"] for row in result.rows]
    assert rows == ["WCSAC-0.5", "Random Policy"]
    wcsac, random = rows
    assert {figure: sorted(by_row) for figure, by_row in drawn.items()} == {
        **{figure: sorted(rows) for figure in drawn},
        "fig6": [wcsac],  # Figure 6 leaves the random policy out
        "fig5_wcsac_0.5_seed0.png": [wcsac],
        "fig5_random_seed0.png": [random],
    }
    colour = {row: {by_row[row][0] for by_row in drawn.values() if row in by_row} for row in rows}
    assert all(len(colours) == 1 for colours in colour.values()), colour
    assert len({colours.pop() for colours in colour.values()}) == len(rows)
    for row in rows:
        markers = {by_row[row][1] for by_row in drawn.values() if by_row.get(row, (0, None))[1]}
        assert len(markers) == 1, (row, markers)


def test_the_box_plot_shows_every_row_s_interquartile_box(report, figures, sweep):
    box_ax = figures["fig6_evaluation.png"].axes[0]
    low, high = box_ax.get_ylim()
    costs = [c for d in run_dirs(sweep)[:2] for c in read_evaluation(d).costs]  # WCSAC-0.5
    q1, q3 = np.percentile(costs, [25, 75])
    assert low <= q1 and q3 <= high and low <= 0 <= 15 <= high


def test_runs_md_lists_each_run_with_its_frames_wall_time_and_commit(report, sweep):
    result, _ = report
    lines = (result.out_dir / "runs.md").read_text().splitlines()
    assert lines[0] == "# Training runs — TinyHazard"
    assert lines[2] == "| run | row | seed | frames | training wall time | sessions | code |"
    body = [line for line in lines[4:] if line.startswith("| ")]
    assert [line.split(" | ")[0].lstrip("| ") for line in body] == [
        d.name for d in run_dirs(sweep)
    ]  # WCSAC-0.5 seeds 0, 1, then the random policy's: the table's order
    total = 0.0
    for line, run_dir in zip(body, run_dirs(sweep)):
        cells = [c.strip() for c in line.strip("|").split("|")]
        progress = list(csv.DictReader((run_dir / "progress.csv").open()))
        seconds = float(progress[-1]["time_s"])
        total += seconds
        minutes = round(seconds / 60)
        assert cells[3] == progress[-1]["frames"] == "800"
        assert cells[4] == f"{minutes // 60} h {minutes % 60:02d} min" and cells[5] == "1"
        commit = json.loads((run_dir / "provenance.json").read_text())["code"]["commit"]
        assert cells[6].startswith(commit[:7] if commit else "package ")
    minutes = round(total / 60)
    assert f"Total training wall time: {minutes // 60} h {minutes % 60:02d} min over 4 runs" in (
        "\n".join(lines)
    )


def test_runs_md_says_which_sessions_have_no_record(tmp_path):
    from wcsac_rl.evaluation.reporting import RunRecord, runs_markdown

    def run(name, sessions, provenance):
        return RunRecord(
            tmp_path / name,
            "sac",
            "static",
            0,
            15.0,
            {"frames": [1e5], "time_s": [3725.0]},
            sessions=sessions,
            provenance=provenance,
        )

    sha = "0123456789abcdef"
    text = runs_markdown(
        [
            run("old", 2, []),
            run("half", 2, [{"code": {"commit": sha, "dirty": True}}]),
            run("wheel", 1, [{"code": {"commit": None, "version": "0.1.0"}}]),
        ],
        "static",
    )
    assert "| old | SAC | 0 | 100000 | 1 h 02 min | 2 | not recorded |" in text
    assert "| half | SAC | 0 | 100000 | 1 h 02 min | 2 | 0123456 + local changes, " in text
    assert "not recorded (1 of 2 sessions) |" in text
    assert "| wheel | SAC | 0 | 100000 | 1 h 02 min | 1 | package 0.1.0 (no git checkout) |" in text
    assert "Total training wall time: 3 h 06 min over 3 runs" in text


def test_png_sizes(report):
    result, _ = report
    out = result.out_dir
    for name in ("fig4_training_curves.png", "fig6_evaluation.png", "fig5_trajectories.png"):
        with Image.open(out / name) as image:
            assert image.mode == "P"  # 256-colour palette: a third of the RGBA file
            # white stays white (the background is not shifted by the palette)
            assert image.convert("RGB").getpixel((0, 0)) == (255, 255, 255)
    assert _px(plots.FIG4_SIZE) == FIG4_PX and _px(plots.FIG6_SIZE) == FIG6_PX
    _assert_png(out / "fig4_training_curves.png", FIG4_PX)
    _assert_png(out / "fig6_evaluation.png", FIG6_PX)
    _assert_png(out / "fig5_trajectories.png", (2 * PANEL_PX, PANEL_PX))  # one panel per row
    _assert_png(out / "fig5_wcsac_0.5_seed0.png", (PANEL_PX, PANEL_PX))
    _assert_png(out / "fig5_random_seed0.png", (PANEL_PX, PANEL_PX))


def test_table1_pools_the_seeds_of_each_row_in_the_papers_order(report, sweep):
    result, _ = report
    with (result.out_dir / "table1.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["label"] for r in rows] == ["wcsac_0.5", "random"]
    assert [r["algorithm"] for r in rows] == ["WCSAC-0.5", "Random Policy"]
    evaluations = [read_evaluation(d) for d in run_dirs(sweep)]
    for row, evs in zip(rows, (evaluations[:2], evaluations[2:])):
        expected = aggregate_seeds([e.costs for e in evs], [e.returns for e in evs], 15.0)
        for key, value in expected.items():
            assert float(row[key]) == pytest.approx(value), key
        assert row["episodes"] == str(2 * EPISODES) and row["seeds"] == row["runs"] == "2"
        assert row["seed_list"] == "0 1" and row["env"] == "tiny" and row["cost_limit"] == "15.0"
    md = (result.out_dir / "table1.md").read_text()
    lines = md.splitlines()
    assert lines[0] == "# Table 1 — TinyHazard, budget d = 15"
    assert lines[2] == (
        "| Algorithm | EC | C0.9 | C0.5 | C0.1 | ER | goals | over budget | episodes (seeds) |"
    )
    wcsac, random = lines[4], lines[5]
    assert wcsac.startswith("| WCSAC-0.5 | ") and random.startswith("| Random Policy | ")
    cells = [c.strip() for c in wcsac.strip("|").split("|")]
    # the constrained column in bold, each metric with its interval
    c05 = f"**{float(rows[0]['C0.5']):.2f}** "
    assert cells[3] == c05 + f"[{float(rows[0]['C0.5_lo']):.2f}, {float(rows[0]['C0.5_hi']):.2f}]"
    for row in rows:
        for metric in ("EC", "C0.9", "C0.5", "C0.1", "ER", "goals"):
            assert float(row[metric + "_lo"]) <= float(row[metric]) + 1e-12, metric
            assert float(row[metric]) <= float(row[metric + "_hi"]) + 1e-12, metric
    assert cells[-1] == f"{2 * EPISODES} (2 seeds)"
    assert "strictly above d = 15" in md


def test_existing_report_is_not_overwritten_without_force(report, sweep):
    result, _ = report
    before = {p: p.read_bytes() for p in result.files}
    with pytest.raises(ReportError, match=r"already has .*table1\.md.*pass --force to overwrite"):
        build_report([sweep], result.out_dir, log=lambda _: None)
    assert {p: p.read_bytes() for p in before} == before
    # --force rewrites (without trajectories this time: only those files are planned)
    again = build_report(
        [sweep], result.out_dir, force=True, trajectories=False, log=lambda _: None
    )
    assert {p.name for p in again.files} == {
        *TABLE_FILES,
        *_figure("fig4_training_curves"),
        *_figure("fig6_evaluation"),
        *_figure("fig_cost_return"),
        *OUTCOME_FILES,
        *TRAINING_FILES,
        *RUN_STATISTICS_FILES,
    }
    assert (result.out_dir / "table1.csv").read_bytes() == before[result.out_dir / "table1.csv"]


def test_chosen_trajectory_runs(sweep, tmp_path):
    chosen = run_dirs(sweep)[1]  # wcsac_0.5, seed 1
    result = build_report(
        [sweep], tmp_path / "out", trajectory_runs=[chosen], trajectory_episodes=1,
        trajectory_max_steps=10, log=lambda _: None,
    )  # fmt: skip
    names = {p.name for p in result.files}
    assert {"fig5_trajectories.png", "fig5_wcsac_0.5_seed1.png"} <= names
    assert "fig5_random_seed0.png" not in names
    with pytest.raises(ReportError, match="not a run directory with a checkpoint"):
        build_report([sweep], tmp_path / "out2", trajectory_runs=[tmp_path], log=lambda _: None)


def test_unevaluated_runs_give_curves_and_a_warning(tmp_path):
    sweep = copy_sweep(tmp_path)
    lines: list[str] = []
    result = build_report([sweep], tmp_path / "out", trajectories=False, log=lines.append)
    assert [p.name for p in result.files] == [*TRAINING_FILES, *_figure("fig4_training_curves")]
    assert any("4 training run(s) have no evaluation" in w for w in result.warnings)
    assert any("Table 1 and Figure 6 skipped" in w for w in result.warnings)
    assert all(line.startswith(("warning: ", "wrote ")) for line in lines)


def test_nothing_to_report_and_mixed_envs_are_clear_errors(sweep, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ReportError, match="nothing to report under"):
        build_report([tmp_path / "empty"], tmp_path / "out", log=lambda _: None)
    with pytest.raises(ReportError, match="no such directory"):
        build_report([tmp_path / "missing"], tmp_path / "out", log=lambda _: None)
    static = tmp_path / "static_random"
    evaluate_random_policy("static", static, episodes=1, max_episode_steps=5, progress=False)
    with pytest.raises(ReportError, match=r"several envs \(static, tiny\); choose one with --env"):
        build_report([sweep, static], tmp_path / "out", log=lambda _: None)
    result = build_report(
        [sweep, static], tmp_path / "out", env="static", cost_limit=10, log=lambda _: None
    )
    table = (tmp_path / "out" / "table1.md").read_text()
    assert "StaticEnv, budget d = 10" in table and "| Random Policy |" in table
    assert "| WCSAC" not in table
    assert "fig4_training_curves.png" not in {p.name for p in result.files}  # no training run
    assert any("Figure 4 skipped" in w for w in result.warnings)
    assert not (tmp_path / "out" / "fig5_random_seed0.gif").exists()


def test_static_trajectories_and_gif_video(tmp_path):
    pytest.importorskip("mujoco")
    static = tmp_path / "random_static_seed0"
    evaluate_random_policy("static", static, episodes=2, max_episode_steps=30, progress=False)
    try:
        result = build_report(
            [static],
            tmp_path / "out",
            trajectory_episodes=3,
            video=True,
            video_format="gif",
            log=lambda _: None,
        )
    except Exception as err:  # no GL backend on this machine
        if "OpenGL" in str(err) or "MUJOCO_GL" in str(err):
            pytest.skip(f"MuJoCo rendering unavailable: {err}")
        raise
    out = tmp_path / "out"
    _assert_png(out / "fig5_trajectories.png", (PANEL_PX, PANEL_PX))
    gif = Image.open(out / "fig5_random_seed0.gif")
    assert gif.size == (480, 480)
    assert 2 <= gif.n_frames <= 31  # start + up to 30 steps
    assert out / "fig5_random_seed0.gif" in result.files


def test_trajectories_follow_the_layout_and_paths(tmp_path):
    from wcsac_rl.envs import make_env
    from wcsac_rl.evaluation.trajectories import collect_trajectories

    env = make_env("dynamic", seed=3, max_episode_steps=20)
    try:
        layout, trajs = collect_trajectories(env, None, 3, max_steps=20)
        # every episode replays the first one's hazards and goal (one picture per run)
        assert np.allclose(env.base_env._env.unwrapped.hazards_xy, layout["hazards_xy"])
    finally:
        env.close()
    assert layout["hazards_xy"].shape == (3, 2) and layout["hazards_size"] == 0.3
    for traj in trajs:
        assert traj.xy.shape == (traj.length + 1, 2) and traj.in_hazard.shape == (traj.length,)
        assert np.allclose(traj.goals[0], layout["goal_xy"])
        assert traj.cost == float(traj.in_hazard.sum())
    assert not np.allclose(trajs[0].xy[0], trajs[1].xy[0])  # fresh random starts
    out = plots.plot_trajectories([("dynamic", layout, trajs)], tmp_path / "t.png")
    _assert_png(out, (PANEL_PX, PANEL_PX))


def test_video_errors_come_before_any_work(sweep, tmp_path, monkeypatch):
    import wcsac_rl.evaluation.trajectories as trajectories

    monkeypatch.setattr(trajectories, "ffmpeg_executable", lambda: None)
    static = tmp_path / "static_random"
    evaluate_random_policy("static", static, episodes=1, max_episode_steps=5, progress=False)
    with pytest.raises(ReportError, match=r"pip install imageio-ffmpeg.*--video-format gif"):
        build_report([static], tmp_path / "out", video=True, log=lambda _: None)
    with pytest.raises(ReportError, match="the tiny env does not render"):
        build_report([sweep], tmp_path / "out", video=True, video_format="gif", log=print)
    assert not (tmp_path / "out").exists()
    with pytest.raises(trajectories.VideoError, match="pip install imageio-ffmpeg"):
        trajectories.write_video(np.zeros((2, 4, 4, 3), np.uint8), tmp_path / "v.mp4")


def test_mp4_when_ffmpeg_is_installed(tmp_path):
    from wcsac_rl.evaluation.trajectories import ffmpeg_executable, write_video

    if ffmpeg_executable() is None:
        pytest.skip("no ffmpeg (pip install imageio-ffmpeg): mp4 videos unavailable")
    frames = np.random.default_rng(0).integers(0, 255, size=(10, 48, 64, 3), dtype=np.uint8)
    out = write_video(frames, tmp_path / "v.mp4")
    data = out.read_bytes()
    assert len(data) > 100 and data[4:8] == b"ftyp"


def test_figure6_synthetic_heavy_tail(tmp_path):
    rng = np.random.default_rng(0)
    costs = {
        "sac": list(rng.normal(20, 5, 300).clip(0)),
        "sac_lag": [0.0] * 280 + [150.0] * 20,
        "wcsac_0.1": list(rng.exponential(1.5, 300)),
    }
    out = plots.plot_cost_distribution(costs, tmp_path / "f6.png", cost_limit=15, ymax=60)
    _assert_png(out, FIG6_PX)
    progress = {
        "frames": [1000.0, 2000.0, 3000.0],
        "train/episode_return": [0.0, float("nan"), 1.0],
        "train/episode_cost": [30.0, 20.0, 10.0],
        "train/cost_rate": [0.03, 0.025, 0.02],
    }
    out = plots.plot_training_curves({"sac": [progress, progress]}, tmp_path / "f4.png")
    _assert_png(out, FIG4_PX)


def test_report_cli(sweep, tmp_path, capsys):
    out = tmp_path / "cli_report"
    cmd = [sys.executable, "-m", "wcsac_rl.report", str(sweep), "--out", str(out)]
    cmd += ["--trajectory-episodes", "1", "--trajectory-max-steps", str(EPISODE_STEPS // 2)]
    cmd += ["--fig6-rows", "random", "wcsac_0.5"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "# Table 1 — TinyHazard, budget d = 15" in proc.stdout
    assert "| WCSAC-0.5 |" in proc.stdout
    # Figures 4, 5 (3 files), 6; runs, scores, cost-return: each as PNG and PDF
    assert len(list(out.glob("*.png"))) == len(list(out.glob("*.pdf"))) == 9
    # the same again without --force: one error line, exit code 1 (in-process: fast)
    from wcsac_rl.report import main

    assert main([str(sweep), "--out", str(out), "--no-trajectories"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "pass --force" in err[0]
    assert json.loads((run_dirs(sweep)[0] / "evaluation.json").read_text())["episodes"] == EPISODES


def test_an_archived_report_is_made_again_from_its_archive_alone(sweep, tmp_path):
    """``archive=True`` copies what the table and Figures 4 and 6 need (no checkpoint);
    a report of the copies alone writes the same table, byte for byte, and a report of
    the original sweep does not count the copies a second time."""
    root = tmp_path / "root"
    shutil.copytree(sweep, root / "sweep")
    measured = root / "sweep" / run_dirs(sweep)[0].name / "calibration.json"
    measured.write_text('{"episodes": 3}\n')  # kept when there (the calibration CLI's file)
    out = root / "report"  # inside the reported tree, as the default --out is
    first = build_report([root], out, trajectories=False, archive=True, log=lambda _: None)
    archive = out / "runs"
    archived = sorted(p.relative_to(archive).as_posix() for p in archive.rglob("*") if p.is_file())
    names = [d.name for d in run_dirs(sweep)]
    files = ("config.yaml", "evaluation.csv", "evaluation.json", "progress.csv", "provenance.json")
    assert archived == sorted(
        [f"{name}/{f}" for name in names for f in files] + [f"{names[0]}/calibration.json"]
    )
    assert (archive / names[0] / "calibration.json").read_text() == measured.read_text()
    again = build_report([archive], tmp_path / "again", trajectories=False, log=lambda _: None)
    assert again.warnings == []
    for name in ("table1.md", "table1.csv", "runs.md", "training_safety.md", "training_safety.csv"):
        assert (tmp_path / "again" / name).read_bytes() == (out / name).read_bytes()
    lines: list[str] = []
    rerun = build_report([root], out, trajectories=False, force=True, log=lines.append)
    assert rerun.warnings == [] and rerun.rows == first.rows  # 2 seeds per row, not 4
    # two runs of one name cannot share the archive: refused before anything is written
    twin = tmp_path / "twin"
    shutil.copytree(run_dirs(sweep)[0], twin / run_dirs(sweep)[0].name)
    with pytest.raises(ReportError, match="both would be"):
        build_report([sweep, twin], tmp_path / "clash", archive=True, log=lambda _: None)
    assert not (tmp_path / "clash").exists()


def test_report_archive_leaves_identical_copies_and_refuses_other_bytes(sweep, tmp_path):
    """After ``wcsac-evaluate --archive <out>/runs`` (byte-equal copies), ``report
    --archive --out <out>`` is not refused for them; an archived file with other bytes
    still is, before anything is written."""
    from wcsac_rl.evaluation.archive import archive_run

    out = tmp_path / "study"
    for run in run_dirs(sweep):
        archive_run(run, out / "runs")
    before = {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*") if p.is_file()}
    build_report([sweep], out, trajectories=False, archive=True, log=lambda _: None)
    assert (out / "table1.md").is_file()
    assert {p: p.stat().st_mtime_ns for p in (out / "runs").rglob("*") if p.is_file()} == before

    other = tmp_path / "other"
    first = run_dirs(sweep)[0]
    archive_run(first, other / "runs")
    (other / "runs" / first.name / "progress.csv").write_text("epoch,frames\n")
    with pytest.raises(ReportError, match=rf"already has runs/{first.name}/progress\.csv;"):
        build_report([sweep], other, trajectories=False, archive=True, log=lambda _: None)
    assert not (other / "table1.md").exists()
    assert (other / "runs" / first.name / "progress.csv").read_text() == "epoch,frames\n"


def test_runs_read_at_another_ensemble_reading_are_another_row():
    """Two runs of one label whose safety-critic ensembles are read differently are two
    rows of Table 1; a run whose records lack the option (made before it) is not split."""
    from wcsac_rl.evaluation.reporting import POOLED_KEYS, row_labels

    assert {"algo.ensemble_reading", "algo.num_safety_nets", "algo.prior_scale"} <= set(POOLED_KEYS)
    members = {
        "wcsac_0.1": [
            ("max_run", {"algo.ensemble_reading": "'max'"}),
            ("ucb_run", {"algo.ensemble_reading": "'ucb'"}),
            ("older_run", {}),
        ]
    }
    labels, warnings = row_labels(members)
    assert labels["max_run"] != labels["ucb_run"]
    assert warnings == [
        "row wcsac_0.1: its runs differ in algo.ensemble_reading (max: 1 run; ucb: 1 run), "
        "shown as one row per setting"
    ]
