"""The training loop: every algorithm end to end, logs, checkpoints, resume, errors, sweeps."""

from __future__ import annotations

import csv
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _tolerance import assert_close_f32
from _training_helpers import COMMON_COLUMNS, ROOT, TINY_CLI, compose_config

from wcsac_rl.evaluation.plots import plot_run_curves
from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint

WCSAC_COLUMNS = {
    "loss/loss_actor",
    "loss/loss_qvalue",
    "loss/loss_alpha",
    "loss/loss_cost_value",
    "loss/loss_cost_variance",
    "loss/loss_kappa",
    "loss/alpha",
    "loss/kappa",
    "loss/entropy",
    "loss/cost_value",
    "loss/cost_variance",
    "loss/cvar",
    "loss/cost_threshold",
}


def _rows(run_dir: Path) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _train(tmp_path: Path, *overrides: str, name: str = "run"):
    trainer = make_trainer(compose_config(*overrides), tmp_path / name)
    try:
        run_dir = trainer.run()
    finally:
        trainer.close()
    return trainer, run_dir


# the recipes' (wcsac.yaml, sac_lag.yaml): κ also reads the episode window (its CVaR, and the larger of both)
WINDOW_COLUMNS = {"loss/episode_cvar", "loss/constraint_cvar"}
# the IQN critic's one TD loss (its cost_value / cost_variance: the quantiles' mean and variance)
IQN_COLUMNS = WCSAC_COLUMNS - {"loss/loss_cost_value", "loss/loss_cost_variance"} | {
    "loss/loss_cost_quantile"
}


# the loss's own safety critic and κ signal (the Gaussian critic on Γ alone), where the
# recipes read the IQN critic and the episode window
LOSS_DEFAULTS = ("algo.safety_critic=gaussian", "algo.kappa_signal=critic")


@pytest.mark.parametrize(
    ("algo", "overrides", "extra_columns", "absent"),
    [
        ("wcsac", (), IQN_COLUMNS | WINDOW_COLUMNS, {"loss/loss_cost_value"}),
        (
            "wcsac",
            LOSS_DEFAULTS,
            WCSAC_COLUMNS,
            {"loss/constraint_cvar", "loss/loss_cost_quantile"},
        ),
        (
            "sac_lag",
            (),
            WCSAC_COLUMNS - {"loss/loss_cost_variance", "loss/cost_variance"} | WINDOW_COLUMNS,
            {"loss/cost_variance", "loss/loss_cost_quantile"},
        ),
        (
            "sac_lag",
            LOSS_DEFAULTS,
            WCSAC_COLUMNS - {"loss/loss_cost_variance", "loss/cost_variance"},
            {"loss/cost_variance", "loss/constraint_cvar"},
        ),
        ("sac", (), {"loss/loss_actor", "loss/loss_qvalue", "loss/alpha"}, {"loss/kappa"}),
        ("random", (), set(), {"loss/loss_actor"}),
    ],
    ids=["wcsac", "wcsac-loss-defaults", "sac_lag", "sac_lag-loss-defaults", "sac", "random"],
)
def test_each_algorithm_trains_on_the_tiny_env_and_logs_the_documented_columns(
    tmp_path, algo, overrides, extra_columns, absent
):
    trainer, run_dir = _train(tmp_path, f"algo={algo}", "env=tiny", *overrides)
    rows = _rows(run_dir)
    assert [int(r["frames"]) for r in rows] == [400, 800]
    columns = set(rows[0])
    assert COMMON_COLUMNS | extra_columns <= columns
    assert not (absent & columns)
    # 100-step episodes: 2 envs × 400 frames per epoch finish 4 episodes
    assert [int(r["train/episodes"]) for r in rows] == [4, 4]
    assert all(float(r["train/episode_length"]) == 100 for r in rows)
    # updates start right after the 200 random frames: 50 after each of 4 batches
    expected_updates = 0 if algo == "random" else 4 * 50
    assert int(rows[-1]["updates"]) == expected_updates
    checkpoint = load_checkpoint(trainer.checkpoint_path)
    assert checkpoint["frames"] == 800 and checkpoint["updates"] == expected_updates
    assert checkpoint["config"]["algo"]["name"] == algo
    # the logger backend (csv) wrote its scalars too
    assert list((run_dir / "logs").rglob("*.csv"))
    # and its progress.csv draws as train.py draws it
    curves = plot_run_curves(run_dir / "progress.csv", tmp_path / "curves.png", cost_limit=15.0)
    png = curves.read_bytes()
    assert png.startswith(b"\x89PNG") and len(png) > 10_000


def test_wcsac_trains_on_static_env_with_the_paper_networks(tmp_path):
    trainer, run_dir = _train(
        tmp_path, "env=static", "algo.network.width=256", "total_frames=400", "epoch_frames=400"
    )
    row = _rows(run_dir)[-1]
    assert int(row["updates"]) == 100  # 2 batches of 200 frames, 50 updates after each
    # κ holds the CVaR of the episode's (undiscounted) cost at start states under d
    # itself (the paper's per-step threshold 1.49994: tests/test_config_defaults.py)
    assert float(row["loss/cost_threshold"]) == 15.0
    assert float(row["eval/episode_length"]) <= 1000
    # the recipe (wcsac.yaml): the IQN critic, κ also held by the episode window
    assert trainer.loss.safety_critic_kind == "iqn" and trainer.loss.risk_level == 0.5
    # (no 1 000-step episode has ended in 400 frames: the window reads NaN, κ the critic)
    assert trainer.loss.kappa_signal == "max" and math.isnan(float(row["loss/episode_cvar"]))


def test_cost_rate_is_total_cost_over_frames(tmp_path):
    trainer, run_dir = _train(tmp_path, "algo=random", "env=tiny")
    rows = _rows(run_dir)
    # the same float64 division of the same numbers (repr round-trips through the CSV)
    assert float(rows[-1]["train/cost_rate"]) == pytest.approx(trainer.tracker.total_cost / 800)


def test_same_seed_gives_identical_logs(tmp_path):
    _, first = _train(tmp_path, "env=tiny", "seed=3", name="a")
    _, second = _train(tmp_path, "env=tiny", "seed=3", name="b")
    _, other = _train(tmp_path, "env=tiny", "seed=4", name="c")

    def values(run_dir):
        return [
            {k: v for k, v in row.items() if not k.startswith("time")} for row in _rows(run_dir)
        ]

    assert values(first) == values(second)
    assert values(first) != values(other)


def test_resume_continues_the_frame_counter_and_appends_to_the_log(tmp_path):
    trainer, run_dir = _train(tmp_path, "env=tiny")
    before = load_checkpoint(trainer.checkpoint_path)
    resumed, same_dir = _train(
        tmp_path, "env=tiny", "total_frames=1200", f"resume={run_dir}", name="ignored"
    )
    assert same_dir == run_dir
    assert [int(r["frames"]) for r in _rows(run_dir)] == [400, 800, 1200]
    after = load_checkpoint(resumed.checkpoint_path)
    assert after["frames"] == 1200 and after["epoch"] == 3
    # no saved buffer: 200 frames (init_random_frames) refill it, then updates continue:
    # batches end at 1000 and 1200 frames, 50 updates after each
    assert after["updates"] == before["updates"] + 100
    for key, value in before["learner"]["loss"].items():
        if key.startswith(("actor_network_params", "qvalue_network_params")):
            assert not torch.equal(value, after["learner"]["loss"][key]), key  # training went on


def test_resume_with_saved_replay_buffer_updates_at_once(tmp_path):
    trainer, run_dir = _train(tmp_path, "env=tiny", "save_replay_buffer=true")
    assert (run_dir / "checkpoints" / "buffers-800" / "replay_buffer").is_dir()
    resumed, _ = _train(
        tmp_path,
        "env=tiny",
        "save_replay_buffer=true",
        "total_frames=1000",
        "algo.lr=3e-4",
        f"resume={run_dir}",
    )
    assert len(resumed.replay_buffer) == 1000
    assert resumed.updates == trainer.updates + 50
    # the warm-up threshold is the uninterrupted run's, and a new learning rate applies
    assert resumed.update_start_frames == 200
    assert all(
        group["lr"] == pytest.approx(3e-4)
        for key, optimizer in resumed.optimizers.items()
        if key != "kappa"
        for group in optimizer.param_groups
    )
    assert resumed.optimizers["actor"].state_dict()["state"]  # Adam's moments came back


def test_start_states_and_nstep_cost_entries_reach_the_loss_through_the_trainer(tmp_path):
    options = ("env=tiny", "algo.kappa_states=initial", "algo.cost_n_steps=4")
    trainer, run_dir = _train(tmp_path, *options, "save_replay_buffer=true")
    loss = trainer.loss
    assert float(loss.cost_threshold) == pytest.approx(15.0)  # Γ(s₀) is held under d itself
    starts = trainer.initial_state_buffer[:]
    # each env began ≥ 4 episodes of ≤ 100 steps in 400 frames; the tiny env starts
    # within 0.2 of (−1, 0), and nothing else is in the buffer
    assert len(starts) >= 2 * 4
    assert bool((starts["observation"][:, 0] - (-1.0)).abs().le(0.2 + 1e-6).all())
    batch = trainer.sample()
    assert batch["initial", "observation"].shape == batch["observation"].shape
    stored = trainer.replay_buffer[:]
    steps = stored["nstep", "steps"]
    assert 1 <= int(steps.min()) and int(steps.max()) == 4
    out = trainer.update(batch)
    assert torch.isfinite(out["loss_kappa"]) and torch.isfinite(out["loss_cost_quantile"])
    # both buffers come back on resume
    resumed, _ = _train(tmp_path, *options, "save_replay_buffer=true", f"resume={run_dir}")
    assert len(resumed.initial_state_buffer) == len(starts)


def test_incompatible_checkpoint_and_occupied_run_dir_are_refused(tmp_path):
    _, run_dir = _train(tmp_path, "env=tiny")
    with pytest.raises(ConfigError, match=r"algo\.network: checkpoint="):
        make_trainer(
            compose_config("env=tiny", "algo.network.width=16", f"resume={run_dir}"), tmp_path / "x"
        )
    with pytest.raises(ConfigError, match=r"algo\.name"):
        make_trainer(compose_config("env=tiny", "algo=sac", f"resume={run_dir}"), tmp_path / "x")
    with pytest.raises(ConfigError, match="already holds a run"):
        make_trainer(compose_config("env=tiny"), run_dir)
    stray = tmp_path / "stray.pt"
    stray.write_bytes((run_dir / "checkpoints" / "last.pt").read_bytes())
    with pytest.raises(ConfigError, match="not inside a run's checkpoints/ directory"):
        make_trainer(compose_config("env=tiny", f"resume={stray}"), tmp_path / "z")
    with pytest.raises(ConfigError, match="no such run directory"):
        make_trainer(compose_config("env=tiny", f"resume={tmp_path / 'missing'}"), tmp_path / "y")
    # the finished run is untouched
    assert [int(r["frames"]) for r in _rows(run_dir)] == [400, 800]


def test_keyboard_interrupt_writes_a_checkpoint_and_flushed_logs(tmp_path, monkeypatch):
    trainer = make_trainer(compose_config("env=tiny", "total_frames=1600"), tmp_path / "run")
    real_update = trainer.update

    def interrupting_update(batch):
        if trainer.updates == 120:
            raise KeyboardInterrupt
        return real_update(batch)

    monkeypatch.setattr(trainer, "update", interrupting_update)
    with pytest.raises(KeyboardInterrupt):
        trainer.run()
    trainer.close()
    checkpoint = load_checkpoint(trainer.checkpoint_path)
    # interrupted during the updates after the third batch of 200 frames
    assert checkpoint["updates"] == 120
    assert checkpoint["frames"] == 600
    assert [int(r["frames"]) for r in _rows(tmp_path / "run")] == [400]


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("risk_level=1.5", "risk_level α must be a number in (0, 1]"),
        ("risk_level=0", "tail fraction"),
        ("total_frames=-5", "total_frames must be an integer > 0"),
        ("cost_limit=-1", "cost_limit must be >= 0"),
        ("cost_limit=abc", "cost_limit must be a number"),
        ("env.name=moon", "unknown env 'moon'"),
        ("algo.collector.frames_per_batch=201", "must be a multiple"),
        ("algo.variance_loss=W2", "algo.variance_loss must be one of w2, mse, glm"),
        ("algo.kappa_actions=target", "algo.kappa_actions must be one of replay, policy"),
        ("algo.kappa_init=0", "algo.kappa_init must be > 0"),
        ("algo.damp_scale=-1", "algo.damp_scale must be in [0, 1e+06]"),
        ("algo.kappa_lr_scale=0", "algo.kappa_lr_scale must be in (0, 1e+06]"),
        ("algo.kappa_states=start", "algo.kappa_states must be one of replay, initial"),
        ("algo.variance_target=mean", "algo.variance_target must be one of moment, td"),
        ("algo.cost_gamma=1.2", "algo.cost_gamma must be null or in [0, 1]"),
        ("algo.cost_n_steps=0", "algo.cost_n_steps must be an integer >= 1"),
        ("algo.nonnegative_cost=yes", "algo.nonnegative_cost must be true or false"),
        ("algo.cost_bootstrap_truncated=maybe", "algo.cost_bootstrap_truncated must be null"),
        ("retain_freed_memory=maybe", "retain_freed_memory must be true or false, got 'maybe'"),
        ("compile=2", "compile must be true or false, got 2"),
    ],
)
def test_bad_config_fails_before_any_work_with_one_clear_message(tmp_path, override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        make_trainer(compose_config("env=tiny", override), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def _train_py(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


SMALL_CLI = [*TINY_CLI, "total_frames=400", "epoch_frames=200"]


def test_train_py_runs_with_overrides_and_says_where_its_outputs_are(tmp_path):
    run_dir = tmp_path / "cli_run"
    result = _train_py(
        *SMALL_CLI, "algo=wcsac", "risk_level=0.1", f"hydra.run.dir={run_dir}", cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"run directory: {run_dir}" in result.stdout
    assert f"training curves:             {run_dir / 'curves.png'}" in result.stdout
    assert (run_dir / "checkpoints" / "last.pt").is_file()
    assert (run_dir / "curves.png").read_bytes().startswith(b"\x89PNG")  # drawn by train.py
    assert (run_dir / ".hydra" / "config.yaml").is_file()
    rows = _rows(run_dir)
    assert len(rows) == 2
    assert float(rows[-1]["loss/cost_threshold"]) > 0
    saved = load_checkpoint(run_dir / "checkpoints" / "last.pt")["config"]
    assert saved["algo"]["risk_level"] == 0.1 and saved["algo"]["label"] == "wcsac_0.1"


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("risk_level=2", "error: risk_level α must be a number in (0, 1]"),
        (
            "algo=nope",
            "error: unknown algo 'nope': conf/algo/ has no nope.yaml; choose one of cal, cpo, "
            "random, sac, sac_lag, sac_lag_paper, wcsac, wcsac_paper",
        ),
        (
            "env=nope",
            "error: unknown env 'nope': conf/env/ has no nope.yaml; choose one of dynamic, "
            "gymnasium, point_goal1, point_goal2, static, tiny",
        ),
        (
            "+row=sac,nope",
            "error: unknown row 'nope': conf/row/ has no nope.yaml; choose one of "
            + ", ".join(sorted(p.stem for p in (ROOT / "conf" / "row").glob("*.yaml"))),
        ),
    ],
)
def test_train_py_rejects_bad_input_with_one_line(tmp_path, override, message):
    result = _train_py(*SMALL_CLI, override, f"hydra.run.dir={tmp_path / 'r'}", cwd=tmp_path)
    assert result.returncode != 0
    if override.startswith("risk_level"):
        assert message in result.stderr
    else:  # (the config-group choices: the whole of stderr)
        assert result.stderr.strip().splitlines() == [message]
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "r").exists()


def test_multirun_sweep_produces_one_run_dir_per_seed(tmp_path):
    sweep_dir = tmp_path / "sweep"
    result = _train_py(
        "-m", *SMALL_CLI, "algo=sac", "seed=0,1", f"hydra.sweep.dir={sweep_dir}", cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr[-2000:]
    runs = sorted(p.parent for p in sweep_dir.rglob("progress.csv"))
    assert [p.name for p in runs] == ["0_sac_tiny_seed0", "1_sac_tiny_seed1"]
    first, second = (_rows(p) for p in runs)
    assert len(first) == len(second) == 2
    assert first[-1]["loss/loss_qvalue"] != second[-1]["loss/loss_qvalue"]  # different seeds


def test_load_run_restores_the_trained_policy_exactly(tmp_path):
    from tensordict import TensorDict
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from wcsac_rl.training.restore import load_run

    trainer, run_dir = _train(tmp_path, "env=tiny")
    restored = load_run(run_dir)
    assert restored.cfg.algo.name == "wcsac" and restored.frames == 800
    obs = TensorDict({"observation": torch.randn(7, 6)}, [7])
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        expected = trainer.agent.actor(obs.clone())["action"]
        got = restored.policy(obs.clone())["action"]
    # the fast TanhNormalPolicy against the ProbabilisticActor: the same 32-wide MLP then
    # tanh, relative to the largest action (see _tolerance.py)
    assert_close_f32(got, expected, ops=32)
    restored.env.close()
    random_run = load_run(_train(tmp_path, "algo=random", "env=tiny", name="rnd")[1])
    assert random_run.policy is None
    with pytest.raises(ConfigError, match="holds no checkpoint"):
        load_run(tmp_path)


def test_progress_csv_gains_columns_that_first_appear_in_a_later_epoch(tmp_path):
    from wcsac_rl.training.progress import ProgressWriter, read_progress

    path = tmp_path / "progress.csv"
    ProgressWriter(path).write({"epoch": 1, "time/collect_s": 0.5})
    writer = ProgressWriter(path)  # a resumed run reopens the file
    writer.write({"epoch": 2, "time/collect_s": 0.4, "time/update_s": 2.0})
    writer.write({"epoch": 3, "time/update_s": 1.0})
    columns = read_progress(path)
    assert list(columns) == ["epoch", "time/collect_s", "time/update_s"]
    assert columns["epoch"] == [1, 2, 3]
    assert columns["time/update_s"][1:] == [2.0, 1.0]
    assert math.isnan(columns["time/update_s"][0]) and math.isnan(columns["time/collect_s"][2])


@pytest.mark.slow
def test_compile_option_trains_with_the_compiled_update(tmp_path):
    trainer, run_dir = _train(tmp_path, "env=tiny", "compile=true")
    # the update went through torch.compile (the whole of it: tests/test_compiled_update.py)
    assert getattr(trainer._update_step, "_torchdynamo_orig_callable", None) is not None
    rows = _rows(run_dir)
    assert [int(r["updates"]) for r in rows] == [100, 200]
    for row in rows:
        for key in ("loss/loss_actor", "loss/loss_qvalue", "loss/loss_cost_quantile"):
            assert math.isfinite(float(row[key])), key


def test_actor_lr_sets_the_actors_rate_only(tmp_path):
    from wcsac_rl.training.builders import make_optimizers

    overrides = ("env=tiny", "algo.actor_lr=5e-4", "algo.kappa_rule=gradient")  # (κ's Adam too)
    trainer = make_trainer(compose_config(*overrides), tmp_path / "run")
    try:
        rates = {
            k: o.param_groups[0]["lr"]
            for k, o in make_optimizers(trainer.cfg, trainer.loss).items()
        }
    finally:
        trainer.close()
    # κ's: lr × kappa_lr_scale (0.3 in the recipe, wcsac.yaml)
    assert rates == {"actor": 5e-4, "critic": 1e-3, "alpha": 1e-3, "kappa": pytest.approx(3e-4)}


@pytest.mark.parametrize("value", ["0", "-1e-4", "abc", "true"])
def test_a_bad_actor_lr_is_one_line(tmp_path, value):
    with pytest.raises(
        ConfigError, match=re.escape("algo.actor_lr must be null or > 0 (a number), got ")
    ):
        make_trainer(compose_config("env=tiny", f"algo.actor_lr={value}"), tmp_path / "run")
