"""The red-team suite: bad inputs a hostile or careless user gives every command.

Each case asserts that the command stops — a non-zero exit code, or the named exception —
with the offending key, value or file in one line and no traceback, and that every file
that existed before is byte-identical afterwards (the shared runs are hashed before and
after every test; a run directory's ``.lock`` names its last holder and is left out).

Commands: ``train.py`` (through a subprocess for a representative few, ~4 s each; in
process, ``make_trainer``, for the rest), resume, ``python -m wcsac_rl.evaluate``,
``python -m wcsac_rl.calibration``, ``python -m wcsac_rl.report``, and the loss API
(``WCSACLoss``). docs/guarantees.md lists these inputs by category; a test here keeps
that table in step with this file.
"""

from __future__ import annotations

import csv
import errno
import hashlib
import json
import math
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch
from _hostile_helpers import TINY, copy_run, error_lines, files_unchanged, one_line, train_tiny
from _loss_helpers import make_batch, make_loss
from _training_helpers import ROOT, compose_config, tree_digests
from omegaconf import OmegaConf

from wcsac_rl.calibration import main as calibration_main
from wcsac_rl.evaluate import main as evaluate_main
from wcsac_rl.evaluation.evaluator import evaluate_run
from wcsac_rl.report import main as report_main
from wcsac_rl.training import ConfigError, TrainingError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, resume_config
from wcsac_rl.training.restore import load_run

snapshot = tree_digests


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Finished tiny runs shared by every test (never written to by a refused command):
    ``wcsac`` (α = 0.5, 800 frames, ``frames-400.pt`` kept, evaluated), ``sac_lag``
    (400 frames) and ``random`` (400 frames)."""
    root = tmp_path_factory.mktemp("red_team") / "runs"
    train_tiny(root / "wcsac", "risk_level=0.5", "keep_checkpoints_at=[1]")
    evaluate_run(root / "wcsac", episodes=2, progress=False)
    train_tiny(root / "sac_lag", "algo=sac_lag", "total_frames=400")
    train_tiny(root / "random", "algo=random", "total_frames=400")
    return root


@pytest.fixture(autouse=True)
def unchanged(request):
    yield from files_unchanged(request, "runs", "a refused command changed a file of the runs")


# ------------------------------------------------------------- train.py (subprocess)
TRAIN_PY = [
    ("algo.lr=abc", "algo.lr must be > 0 (a number), got 'abc'"),
    ("+risk_levl=0.1", "unknown config key risk_levl (did you mean risk_level?)"),
    ("algo.batchsize=64", "unknown config key algo.batchsize (did you mean algo.batch_size?)"),
    ("seed=18446744073709551616", "seed must be at most 2**63 - 1"),
    ("resume=KEPT", "is at 400 frames but the run"),
    (
        "hydra.run.dir=${oc.env:WCSAC_UNSET}/x",
        "hydra.run.dir=${oc.env:WCSAC_UNSET}/x: the environment variable WCSAC_UNSET is not set",
    ),
    ("seed=${seed}", "seed=${seed} refers to itself; give seed a value"),
    ("run_name=../../../x", "run_name must be a name without '/'"),
]


@pytest.mark.parametrize(("override", "message"), TRAIN_PY, ids=[o for o, _ in TRAIN_PY])
def test_train_py(runs, tmp_path, override, message):
    override = override.replace("KEPT", str(runs / "wcsac" / "checkpoints" / "frames-400.pt"))
    session = tmp_path / "session"
    environment = {k: v for k, v in os.environ.items() if k != "WCSAC_UNSET"}
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *TINY, override, f"hydra.run.dir={session}"],
        cwd=tmp_path,
        env=environment,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 1, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    errors = error_lines(result.stderr)
    assert len(errors) == 1
    one_line(errors[0], message)
    assert not session.exists()  # a refused command leaves no run directory
    assert list(tmp_path.iterdir()) == []  # nor any other (run_name=../../../x: none outside)


# ------------------------------------------------------------- train (in process)
CONFIG = [
    ("algo.lr=nan", "algo.lr must be > 0 (a number), got nan"),
    ("algo.lr=-1", "algo.lr must be > 0 (a number), got -1"),
    ("algo.tau=abc", "algo.tau must be in (0, 1] (a number), got 'abc'"),
    ("algo.tau=0", "algo.tau must be in (0, 1] (a number), got 0"),
    ("algo.gamma=1.5", "algo.gamma must be in [0, 1] (a number), got 1.5"),
    ("algo.collector.utd_ratio=abc", "algo.collector.utd_ratio must be > 0 (a number)"),
    ("algo.collector.num_envs=3", "algo.collector.frames_per_batch (200) must be a multiple"),
    ("algo.collector.env_backend=threads", "algo.collector.env_backend must be 'serial'"),
    ("algo.target_entropy=abc", "algo.target_entropy must be auto (-|A|) or a finite number"),
    ("algo.network.width=0", "algo.network.width must be an integer in [1, 16384], got 0"),
    ("algo.network.depth=-1", "algo.network.depth must be an integer in [0, 64], got -1"),
    ("algo.network.activation=foo", "algo.network.activation must be one of relu"),
    ("algo.network.log_std_min=5", "algo.network.log_std_min (5) must be < algo.network"),
    ("algo.alpha_init=-1", "algo.alpha_init must be in (0, 1e+06] (a number), got -1"),
    ("algo.kappa_init=0", "algo.kappa_init must be > 0 with the gradient rule"),
    ("algo.kappa_lr_scale=0", "algo.kappa_lr_scale must be in (0, 1e+06] (a number), got 0"),
    ("algo.damp_scale=-1", "algo.damp_scale must be in [0, 1e+06] (a number), got -1"),
    ("algo.cost_gamma=2", "algo.cost_gamma must be null or in [0, 1] (a number), got 2"),
    ("algo.variance=maybe", "algo.variance must be true or false, got 'maybe'"),
    ("algo.kappa_rule=pi", "algo.kappa_rule must be one of gradient, pid, got 'pi'"),
    ("+algo.pid.kq=1", "unknown PID option algo.pid.kq"),
    ("algo.batch_size=20000", "algo.batch_size (20000) must be <= algo.buffer_size (10000)"),
    ("algo.name=foo", "unknown algo 'foo'"),
    ("env.name=mars", "unknown env 'mars'"),
    ("env.max_episode_steps=0", "env.max_episode_steps must be an integer in [1, 1000000], got 0"),
    ("seed=-1", "seed must be an integer >= 0, got -1"),
    ("seed=1.5", "seed must be an integer >= 0, got 1.5"),
    ("risk_level=true", "risk_level α must be a number in (0, 1], got True"),
    ("risk_level=0", "risk_level α must be a number in (0, 1], got 0"),
    ("risk_level=nan", "risk_level α must be a number in (0, 1], got nan"),
    ("risk_level=1e-300", "risk_level α=1e-300 is below the smallest supported"),
    ("cost_limit=-1", "cost_limit must be >= 0 (an episodic cost budget), got -1"),
    ("cost_limit=nan", "cost_limit must be >= 0 (an episodic cost budget), got nan"),
    ("total_frames=0", "total_frames must be an integer > 0, got 0"),
    ("epoch_frames=abc", "epoch_frames must be an integer > 0, got 'abc'"),
    ("threads=0", "threads must be an integer > 0, got 0"),
    ("threads=1000", "threads=1000 is more than this machine's"),
    ("eval_episodes=-1", "eval_episodes must be an integer >= 0, got -1"),
    ("keep_checkpoints_at=[0]", "keep_checkpoints_at must be a list of epochs >= 1"),
    ("compile=yes", "compile must be true or false, got 'yes'"),
    ("max_nonfinite_updates=0", "max_nonfinite_updates must be an integer > 0, got 0"),
    ("device=tpu", "device must be cpu, cuda[:N] or mps, got 'tpu'"),
    ("logger.backend=nope", "logger.backend must be csv, wandb, tensorboard or none"),
    ("+algo.batchsize=64", "unknown config key algo.batchsize (did you mean algo.batch_size?)"),
    (
        "cost_limit=${oc.env:WCSAC_UNSET}",
        "cost_limit=${oc.env:WCSAC_UNSET} cannot be resolved: Environment variable 'WCSAC_UNSET'",
    ),
    ("seed=${seed}", "seed=${seed} cannot be resolved: Recursive interpolation detected"),
    ("+env.kwargs.foo=1", "env.kwargs.foo: env tiny has no option 'foo' (its options: goal_size"),
    ("run_name=../x", "run_name must be a name without '/' (it names the run's directory"),
]


@pytest.mark.parametrize(("override", "message"), CONFIG, ids=[o for o, _ in CONFIG])
def test_train_config(tmp_path, monkeypatch, override, message):
    monkeypatch.delenv("WCSAC_UNSET", raising=False)
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config(*TINY, override), tmp_path / "run")
    one_line(str(err.value), message)
    assert not (tmp_path / "run").exists()  # refused before anything was built


# ------------------------------------------------------------------------- resume
def _resume(target: Path | str, *overrides: str):
    """What ``train.py resume=<target> <overrides>`` builds (the run's own config)."""
    given = [f"resume={target}", *overrides]
    return make_trainer(resume_config(compose_config(*given, small=False), given), Path("x"))


def _truncated(run: Path) -> Path:
    path = run / "checkpoints" / "last.pt"
    path.write_bytes(path.read_bytes()[:1000])
    return path


def _foreign_checkpoint(runs: Path, tmp_path: Path) -> Path:
    run = copy_run(runs / "sac_lag", tmp_path)
    shutil.copyfile(runs / "wcsac" / "checkpoints" / "last.pt", run / "checkpoints" / "last.pt")
    return run


RESUME = [
    ("resume=RUN/checkpoints/frames-400.pt", "is at 400 frames but the run"),
    ("resume=RUN algo.tau=0.01", "algo.tau: run=0.005, now=0.01 cannot change on resume"),
    ("resume=RUN +algo.batchsize=64", "unknown config key algo.batchsize"),
    ("resume=RUN epoch_frames=100", "epoch_frames: run=400, now=100 cannot change"),
    ("resume=RUN experiment=quickstart", "experiment=... cannot be given on resume"),
    ("resume=RUN ~seed", "~seed: nothing can be removed from a run's config on resume"),
    ("resume=MISSING", "no such run directory or checkpoint"),
    ("resume=OUTSIDE.pt", "is not inside a run's checkpoints/ directory"),
    ("resume=TRUNCATED", "cannot read checkpoint"),
    ("resume=FOREIGN", "does not belong to the run"),
    ("resume=CONFIG_5", "last.pt: its config is not a mapping of settings (got int)"),
    ("resume=CONFIG_TEXT", "last.pt: its config is not a mapping of settings (got str)"),
    ("resume=FRAMES_ABC", "its 'frames' entry must be a whole number >= 0, got 'abc'"),
    ("resume=NAN_WEIGHTS", "its networks hold non-finite weights: actor_network_params"),
    ("resume=PROGRESS_SYMLINK", "progress.csv is a symbolic link (to "),
    ("resume=DUPLICATE_EPOCHS", "progress.csv: line 4 logs epoch 1 again"),
]

CRAFTED = {
    "CONFIG_5": lambda state: state.update(config=5),
    "CONFIG_TEXT": lambda state: state.update(config="algo: {name: wcsac"),
    "FRAMES_ABC": lambda state: state.update(frames="abc"),
    "NAN_WEIGHTS": lambda state: next(
        v for k, v in state["learner"]["loss"].items() if k.startswith("actor_network_params")
    ).fill_(math.nan),
}
"""Checkpoint fields a hostile or careless hand edited (``CRAFTED[kind](state)``)."""


def _crafted(runs: Path, tmp_path: Path, kind: str) -> Path:
    run = copy_run(runs / "wcsac", tmp_path)
    path = run / "checkpoints" / "last.pt"
    state = load_checkpoint(path)
    CRAFTED[kind](state)
    torch.save(state, path)
    return run


@pytest.mark.parametrize(("command", "message"), RESUME, ids=[c for c, _ in RESUME])
def test_resume(runs, tmp_path, command, message):
    target, *overrides = command.split()
    target = target.removeprefix("resume=")
    run = runs / "wcsac"
    if target == "MISSING":
        target = str(tmp_path / "missing")
    elif target == "OUTSIDE.pt":
        target = str(tmp_path / "last.pt")
        shutil.copyfile(run / "checkpoints" / "last.pt", target)
    elif target == "TRUNCATED":
        copy = copy_run(runs / "wcsac", tmp_path)
        _truncated(copy)
        target = str(copy)
    elif target == "FOREIGN":
        target = str(_foreign_checkpoint(runs, tmp_path))
    elif target in CRAFTED:
        target = str(_crafted(runs, tmp_path, target))
    elif target in ("PROGRESS_SYMLINK", "DUPLICATE_EPOCHS"):
        copy = copy_run(runs / "wcsac", tmp_path)
        progress = copy / "progress.csv"
        if target == "PROGRESS_SYMLINK":  # (a resume would append to the outside file)
            outside = tmp_path / "outside.csv"
            progress.rename(outside)
            progress.symlink_to(outside)
        else:  # epochs 1, 2, 1: a row logged twice
            lines = progress.read_text().splitlines(keepends=True)
            progress.write_text("".join([*lines, lines[1]]))
        target = str(copy)
    else:
        target = target.replace("RUN", str(run))
    before = snapshot(tmp_path)
    with pytest.raises(ConfigError) as err:
        _resume(target, *overrides)
    one_line(str(err.value), message)
    assert snapshot(tmp_path) == before


def test_resume_auto_of_another_algorithm(runs):
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config(*TINY, "algo=sac_lag", "resume=auto"), runs / "wcsac")
    one_line(str(err.value), "another configuration (algo.name: checkpoint='wcsac'")


# ----------------------------------------------------------------------- evaluate
def _wider_networks(run: Path) -> Path:
    path = run / "checkpoints" / "last.pt"
    state = load_checkpoint(path)
    state["config"]["algo"]["network"]["width"] = 64
    torch.save(state, path)
    return path


EVALUATE = [
    ("MISSING", "no such file or directory"),
    ("TRUNCATED", "cannot read checkpoint"),
    ("WIDER", "its networks do not fit its config: actor_network_params"),
    ("EMPTY_DIR", "no run directories with checkpoints/last.pt"),
]


def _target(runs: Path, tmp_path: Path, kind: str, name: str = "wcsac") -> Path:
    if kind == "MISSING":
        return tmp_path / "missing"
    if kind == "EMPTY_DIR":
        (tmp_path / "empty").mkdir()
        return tmp_path / "empty"
    if kind == "NOT_A_RUN_FILE":
        (tmp_path / "notes.txt").write_text("x")
        return tmp_path / "notes.txt"
    run = copy_run(runs / name, tmp_path)
    if kind == "TRUNCATED":
        _truncated(run)
    elif kind == "WIDER":
        _wider_networks(run)
    return run


@pytest.mark.parametrize(("kind", "message"), EVALUATE, ids=[k for k, _ in EVALUATE])
def test_evaluate(runs, tmp_path, capsys, kind, message):
    target = _target(runs, tmp_path, kind)
    before = snapshot(tmp_path)
    code = evaluate_main([str(target), "--episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    errors = error_lines(err)
    assert len(errors) == 1
    one_line(errors[0], message, str(target))
    assert snapshot(tmp_path) == before


# --------------------------------------------------------------------- calibration
CALIBRATION = [
    ("MISSING", "wcsac", "no such run directory or checkpoint"),
    ("TRUNCATED", "wcsac", "cannot read checkpoint"),
    ("WIDER", "wcsac", "its networks do not fit its config"),
    ("RANDOM", "random", "algo 'random' has no safety critic to calibrate"),
]


@pytest.mark.parametrize(("kind", "name", "message"), CALIBRATION, ids=[k for k, *_ in CALIBRATION])
def test_calibration(runs, tmp_path, capsys, kind, name, message):
    target = _target(runs, tmp_path, kind, name)
    before = snapshot(tmp_path)
    code = calibration_main([str(target), "--episodes", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    errors = error_lines(err)
    assert len(errors) == 1
    one_line(errors[0], message)
    assert snapshot(tmp_path) == before


# -------------------------------------------------------------------------- report
def _two_cost_limits(runs: Path, tmp_path: Path) -> Path:
    """The evaluated WCSAC run twice, the second made with d = 25."""
    for name, limit in (("seed0", None), ("seed1", 25.0)):
        run = tmp_path / "sweep" / name
        shutil.copytree(runs / "wcsac", run)
        if limit is not None:
            config = run / "config.yaml"
            config.write_text(config.read_text().replace("cost_limit: 15.0", "cost_limit: 25.0"))
            meta = json.loads((run / "evaluation.json").read_text())
            (run / "evaluation.json").write_text(json.dumps({**meta, "cost_limit": limit}))
    return tmp_path / "sweep"


REPORT = [
    ("MISSING", [], "no such directory"),
    ("EMPTY_DIR", [], "nothing to report under"),
    (
        "TWO_LIMITS",
        [],
        "the runs use several cost limits (15.0, 25.0); choose one with --cost-limit",
    ),
    ("RUN", ["--cost-limit", "-1"], "cost limit must be a number >= 0, got -1.0"),
    ("RUN", ["--cost-limit", "nan"], "cost limit must be a number >= 0, got nan"),
    ("RUN", ["--env", "mars"], "nothing to report under"),
    ("RUN", ["--trajectory-runs", "MISSING"], "not a run directory with a checkpoint"),
]


@pytest.mark.parametrize(
    ("kind", "args", "message"), REPORT, ids=[f"{k}{' '.join(a)}" for k, a, _ in REPORT]
)
def test_report(runs, tmp_path, capsys, kind, args, message):
    if kind == "TWO_LIMITS":
        target = _two_cost_limits(runs, tmp_path)
    elif kind == "RUN":
        target = runs / "wcsac"
    else:
        target = _target(runs, tmp_path, kind)
    args = [str(tmp_path / "missing") if a == "MISSING" else a for a in args]
    out = tmp_path / "report"
    before = snapshot(tmp_path)
    draw = [] if "--trajectory-runs" in args else ["--no-trajectories"]
    code = report_main([str(target), "--out", str(out), *draw, *args])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    errors = error_lines(err)
    assert len(errors) == 1
    one_line(errors[0], message)
    assert snapshot(tmp_path) == before
    assert not out.exists() or not [p for p in out.rglob("*") if p.name.endswith(".tmp")]


EVALUATION_FILES = [
    ("evaluation.json: 5", "evaluation.json: not an evaluation (a JSON object), got int"),
    ('"env": ["tiny"]', "evaluation.json: 'env' must be a string, got ['tiny']"),
    ('"cost_limit": "abc"', "evaluation.json: 'cost_limit' must be a number >= 0, got 'abc'"),
    ("evaluation.csv: a NaN cost", "evaluation.csv: episode row 0: cost must be a finite number"),
]


def _edit_evaluation(run: Path, case: str) -> None:
    meta_path, rows_path = run / "evaluation.json", run / "evaluation.csv"
    meta = json.loads(meta_path.read_text())
    if case.startswith("evaluation.json"):
        meta_path.write_text("5")
    elif case.startswith('"env"'):
        meta_path.write_text(json.dumps({**meta, "env": ["tiny"]}))
    elif case.startswith('"cost_limit"'):
        meta_path.write_text(json.dumps({**meta, "cost_limit": "abc"}))
    else:
        header, first, *rest = rows_path.read_text().splitlines()
        cells = first.split(",")
        cells[header.split(",").index("cost")] = "nan"
        rows_path.write_text("\n".join([header, ",".join(cells), *rest]) + "\n")


@pytest.mark.parametrize(
    ("case", "message"), EVALUATION_FILES, ids=[c for c, _ in EVALUATION_FILES]
)
def test_report_reads_only_valid_evaluations(runs, tmp_path, capsys, case, message):
    """An evaluation whose fields are not what ``wcsac-evaluate`` writes is skipped with one
    warning naming the file and the field; with nothing else to report, one error line."""
    run = copy_run(runs / "wcsac", tmp_path)
    _edit_evaluation(run, case)
    (run / "progress.csv").unlink()  # (the evaluation alone: nothing else to report)
    before = snapshot(tmp_path)
    code = report_main([str(run), "--out", str(tmp_path / "report"), "--no-trajectories"])
    captured = capsys.readouterr()
    assert code == 1 and "Traceback" not in captured.err + captured.out
    (error,) = error_lines(captured.err)
    one_line(error, "nothing to report under")
    (warning,) = [line for line in captured.out.splitlines() if line.startswith("warning:")]
    one_line(warning, "warning: skipped: ", message)
    assert snapshot(tmp_path) == before


def test_report_resolves_nothing_in_a_runs_config(runs, tmp_path, capsys, monkeypatch):
    """A config.yaml whose seed is ``${oc.env:WCSAC_SECRET}``: the report reads no
    environment variable for it; the run's curves are skipped with one warning."""
    run = copy_run(runs / "wcsac", tmp_path)
    config = run / "config.yaml"
    config.write_text(config.read_text().replace("seed: 0", "seed: ${oc.env:WCSAC_SECRET}"))
    monkeypatch.setenv("WCSAC_SECRET", "0")
    code = report_main([str(run), "--out", str(tmp_path / "report"), "--no-trajectories"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    (warning,) = [line for line in captured.out.splitlines() if "interpolation" in line]
    one_line(warning, "warning: skipped ", "its config holds an interpolation at seed")


def test_report_refuses_a_progress_csv_that_logs_an_epoch_twice(runs, tmp_path, capsys):
    """Epochs 1, 2, 1: the run's curves and runs.md entry are skipped with one warning
    (its frames and time would be read from a repeated row)."""
    run = copy_run(runs / "wcsac", tmp_path)
    progress = run / "progress.csv"
    lines = progress.read_text().splitlines(keepends=True)
    progress.write_text("".join([*lines, lines[1]]))
    code = report_main([str(run), "--out", str(tmp_path / "report"), "--no-trajectories"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    (warning,) = [line for line in captured.out.splitlines() if "logs epoch" in line]
    one_line(warning, "warning: skipped ", "progress.csv: line 4 logs epoch 1 again")
    assert not (tmp_path / "report" / "runs.md").exists()  # (its only run was skipped)


def test_calibration_of_a_run_whose_env_module_is_gone(runs, tmp_path, capsys):
    """A run of an own env whose module no longer imports: one line naming the module."""
    run = copy_run(runs / "wcsac", tmp_path)
    path = run / "checkpoints" / "last.pt"
    state = load_checkpoint(path)
    state["config"]["env"] = {
        "name": "gymnasium",
        "id": "gone_envs:make",
        "cost_key": "cost",
        "max_episode_steps": 50,
        "kwargs": {},
    }
    torch.save(state, path)
    before = snapshot(tmp_path)
    args = [str(run), "--episodes", "1", "--no-progress", "--trust-env-code"]
    code, lines, text = _cli(calibration_main, args, capsys)
    assert code == 1 and "Traceback" not in text and len(lines) == 1, text
    one_line(lines[0], "env.id=gone_envs:make: no module named 'gone_envs' on the Python path")
    assert snapshot(tmp_path) == before


def test_report_splits_a_label_whose_runs_differ_in_a_setting(runs, tmp_path, capsys):
    """Runs of one label made with two budgets are two rows, said in one warning line."""
    target = _two_cost_limits(runs, tmp_path)
    out = tmp_path / "report"
    code = report_main([str(target), "--out", str(out), "--no-trajectories", "--cost-limit", "15"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    lines = (captured.out + captured.err).splitlines()
    warnings = [line for line in lines if "differ in" in line]
    assert warnings == [
        "warning: row wcsac_0.5: its runs differ in cost_limit (15.0: 1 run; 25.0: 1 run), "
        "shown as one row per setting"
    ]
    rows = list(csv.DictReader((out / "table1.csv").open(newline="")))
    assert [(r["label"], r["cost_limit"], r["seeds"]) for r in rows] == [
        ("wcsac_0.5[cost_limit=15.0]", "15.0", "1"),
        ("wcsac_0.5[cost_limit=25.0]", "25.0", "1"),
    ]
    table = (out / "table1.md").read_text()
    assert "| WCSAC-0.5 (cost_limit=15.0) | " in table
    assert "| WCSAC-0.5 (cost_limit=25.0) | " in table


def test_report_counts_seeds_not_runs(runs, tmp_path, capsys):
    """Four runs of seed 0 are never called four seeds."""
    for i in range(4):
        shutil.copytree(runs / "wcsac", tmp_path / "sweep" / f"copy{i}")
    out = tmp_path / "report"
    code = report_main([str(tmp_path / "sweep"), "--out", str(out), "--no-trajectories"])
    assert code == 0, capsys.readouterr().err
    (row,) = csv.DictReader((out / "table1.csv").open(newline=""))
    assert (row["seeds"], row["runs"], row["seed_list"]) == ("1", "4", "0 0 0 0")
    assert "(4 runs, 1 seed) |" in (out / "table1.md").read_text()


def test_report_does_not_overwrite_without_force(runs, tmp_path, capsys):
    out = tmp_path / "report"
    out.mkdir()
    (out / "table1.md").write_text("mine\n")
    before = snapshot(tmp_path)
    code = report_main([str(runs / "wcsac"), "--out", str(out), "--no-trajectories"])
    errors = error_lines(capsys.readouterr().err)
    assert code == 1 and len(errors) == 1
    one_line(errors[0], "already has table1.md", "pass --force to overwrite")
    assert snapshot(tmp_path) == before


# ------------------------------------------- code named by a run's files (env.id)
OWN_ENV = textwrap.dedent(
    """
    import gymnasium as gym
    import numpy as np


    class Walk(gym.Env):
        # x moves by the action; every step costs 0.1

        def __init__(self, limit=20):
            self.limit = self.max_episode_steps = limit
            self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float64)
            self.t = 0

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.t = 0
            return np.zeros(3), {}

        def step(self, action):
            self.t += 1
            obs = np.full(3, float(self.t))
            return obs, 1.0, False, self.t >= self.limit, {"cost": 0.1}


    def make(limit=20):
        return Walk(limit=limit)
    """
)


def _name_os_system(run: Path, marker: Path) -> None:
    """Make ``run`` (a copy of a finished tiny run) say, in its checkpoints, config.yaml
    and .hydra/config.yaml, that its env is ``os:system`` called with a shell command;
    its evaluation.json names the edited checkpoint's hash (as a hostile sender would)."""
    env = {
        "name": "gymnasium",
        "id": "os:system",
        "cost_key": "cost",
        "max_episode_steps": 50,
        "kwargs": {"command": f"touch {marker}"},
    }
    last = run / "checkpoints" / "last.pt"
    for path in [last, *(run / "checkpoints").glob("frames-*.pt")]:
        state = load_checkpoint(path)
        state["config"]["env"] = env
        torch.save(state, path)
    for name in ("config.yaml", ".hydra/config.yaml"):
        path = run / name
        if path.is_file():
            cfg = OmegaConf.load(path)
            cfg.env = env
            path.write_text(OmegaConf.to_yaml(cfg))
    meta = json.loads((run / "evaluation.json").read_text())
    meta["env"] = "gymnasium"
    meta["checkpoint_sha256"] = hashlib.sha256(last.read_bytes()).hexdigest()
    (run / "evaluation.json").write_text(json.dumps(meta))


@pytest.fixture
def hostile(runs, tmp_path) -> tuple[Path, Path]:
    """A run directory whose files name ``env.id=os:system``, and the marker file its
    command would create."""
    run = copy_run(runs / "wcsac", tmp_path)
    marker = tmp_path / "MARKER"
    _name_os_system(run, marker)
    return run, marker


UNTRUSTED = "the run's config names code to run (env.id=os:system imports the module 'os'"


def _cli(main, args: list[str], capsys) -> tuple[int, list[str], str]:
    code = main(args)
    err = capsys.readouterr().err
    return code, error_lines(err), err


CODE_FROM_RUN_FILES = [
    (
        "evaluate --force",
        "nothing was imported. If you trust this run's code, pass --trust-env-code",
    ),
    ("calibration", "pass --trust-env-code"),
    ("report", "Figure 5 (trajectories) skipped"),  # (the only part that would load the env)
    ("resume", "add trust_env_code=true to the command line"),
    ("load_run", "(in Python: trust_env_code=True)"),
]


@pytest.mark.parametrize(
    ("command", "message"), CODE_FROM_RUN_FILES, ids=[c for c, _ in CODE_FROM_RUN_FILES]
)
def test_code_named_by_a_run_is_not_run(hostile, tmp_path, capsys, command, message):
    """No command imports or calls the env a run's files name without the user's word:
    the shell command never runs (no marker file), one line says how to allow it, and
    no file changes."""
    run, marker = hostile
    before = snapshot(tmp_path)
    if command in ("resume", "load_run"):
        with pytest.raises(ConfigError) as err:
            _resume(run) if command == "resume" else load_run(run)
        lines, text = [str(err.value)], str(err.value)
    else:
        main, args = {
            "evaluate --force": (evaluate_main, [str(run), "--force", "--episodes", "1"]),
            "calibration": (calibration_main, [str(run), "--episodes", "1"]),
            "report": (report_main, [str(run), "--out", str(tmp_path / "report")]),
        }[command]
        code, lines, text = _cli(main, args, capsys)
        if command == "report":  # (a run without a layout: its env is never loaded)
            assert code == 0 and "Traceback" not in text, text
            assert (tmp_path / "report" / "table1.md").is_file()
            assert not marker.exists(), "the command in the run's files ran"
            return
        assert code == 1 and "Traceback" not in text
    assert not marker.exists(), "the command in the run's files ran"
    assert len(lines) == 1, text
    one_line(lines[0], UNTRUSTED, message)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("given", ["false", "true", 1, "yes", None])
def test_only_true_trusts_a_runs_code(hostile, tmp_path, given):
    """Trust is a bool: a string (``"false"`` read from an environment variable), a number
    or None is refused in one line naming it; the run's code never runs."""
    run, marker = hostile
    before = snapshot(tmp_path)
    with pytest.raises(ConfigError) as err:
        load_run(run, trust_env_code=given)
    one_line(str(err.value), f"trust_env_code must be True or False (a bool), got {given!r}")
    assert not marker.exists(), "the command in the run's files ran"
    assert snapshot(tmp_path) == before


def test_train_py_resume_of_a_run_naming_code_runs_nothing(hostile, tmp_path):
    """``train.py resume=RUN`` (a subprocess: what a user types) refuses in one line."""
    run, marker = hostile
    before = snapshot(tmp_path)
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), f"resume={run}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-2000:]
    errors = error_lines(result.stderr)
    assert len(errors) == 1, result.stderr
    one_line(errors[0], UNTRUSTED, "add trust_env_code=true to the command line")
    assert not marker.exists()
    assert snapshot(tmp_path) == before  # (and no outputs/ directory)


def test_a_stored_config_is_never_resolved(runs, tmp_path, monkeypatch):
    """``${oc.env:...}`` in a checkpoint's config is refused naming the key: no
    environment variable is read because a file says so."""
    run = copy_run(runs / "wcsac", tmp_path)
    path = run / "checkpoints" / "last.pt"
    state = load_checkpoint(path)
    state["config"]["cost_limit"] = "${oc.env:WCSAC_SECRET}"
    torch.save(state, path)
    monkeypatch.setenv("WCSAC_SECRET", "15.0")
    before = snapshot(tmp_path)
    for call in (lambda: _resume(run), lambda: load_run(run)):
        with pytest.raises(ConfigError) as err:
            call()
        one_line(
            str(err.value),
            "its config holds an interpolation at cost_limit ('${oc.env:WCSAC_SECRET}')",
        )
    assert snapshot(tmp_path) == before


@pytest.fixture
def own_env_run(tmp_path, monkeypatch) -> Path:
    """A finished run of the user's own env (``own_envs:make``, on the Python path)."""
    module_dir = tmp_path / "own"
    module_dir.mkdir()
    (module_dir / "own_envs.py").write_text(OWN_ENV)
    monkeypatch.syspath_prepend(str(module_dir))
    sys.modules.pop("own_envs", None)
    run = tmp_path / "run"
    trainer = make_trainer(
        compose_config("env=gymnasium", "env.id=own_envs:make", "total_frames=400"), run
    )
    try:
        trainer.run()
    finally:
        trainer.close()
    yield run
    sys.modules.pop("own_envs", None)


def test_the_users_own_env_runs_with_the_flag(own_env_run, tmp_path, capsys):
    """Without the user's word a run of their own env is refused like any other; with
    it (the flag, or the same env.id on resume's command line) the run evaluates,
    calibrates, reports, resumes and loads."""
    run = own_env_run
    for main, args in (
        (evaluate_main, [str(run), "--episodes", "2", "--no-progress"]),
        (calibration_main, [str(run), "--episodes", "2", "--no-progress"]),
        (report_main, [str(run), "--out", str(tmp_path / "report"), "--no-trajectories"]),
    ):
        if main is not report_main:  # (a report without Figure 5 reads records only)
            code, lines, text = _cli(main, args, capsys)
            assert code == 1 and len(lines) == 1, text
            one_line(lines[0], "env.id=own_envs:make imports the module 'own_envs'")
        code, lines, text = _cli(main, [*args, "--trust-env-code"], capsys)
        assert code == 0, text
    assert json.loads((run / "evaluation.json").read_text())["env"] == "gymnasium"
    assert (run / "calibration.json").is_file()
    restored = load_run(run, trust_env_code=True)
    try:
        assert restored.cfg.env.id == "own_envs:make" and restored.frames == 400
    finally:
        restored.env.close()
    for overrides in (["trust_env_code=true"], ["env=gymnasium", "env.id=own_envs:make"]):
        _resume(run, *overrides).close()
    with pytest.raises(ConfigError, match="add trust_env_code=true"):
        _resume(run)


FAILING_ENV = textwrap.dedent(
    """
    import gymnasium as gym
    import numpy as np


    class Fails(gym.Env):
        # fails (how: "step", "reset" or "shape") once it has taken `after` steps in all
        steps = 0

        def __init__(self, how="step", after=250):
            self.how, self.after, self.max_episode_steps = how, after, 20
            self.action_space = gym.spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
            self.observation_space = gym.spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float64)
            self.t = 0

        def _late(self):
            return Fails.steps >= self.after

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            if self.how == "reset" and self._late():
                raise RuntimeError("the simulator lost its licence")
            self.t = 0
            return np.zeros(3), {}

        def step(self, action):
            Fails.steps += 1
            self.t += 1
            if self.how == "step" and self._late():
                raise RuntimeError("the simulator lost its licence")
            size = 4 if self.how == "shape" and self._late() else 3
            return np.zeros(size), 1.0, False, self.t >= 20, {"cost": 0.1}


    def make(how="step", after=250):
        Fails.steps = 0
        return Fails(how, after)
    """
)

OWN_ENV_FAILS = [
    (
        "step",
        "env.id=failing_envs:make: step() raised RuntimeError: the simulator lost its licence",
    ),
    (
        "reset",
        "env.id=failing_envs:make: reset() raised RuntimeError: the simulator lost its licence",
    ),
    ("shape", "env.id=failing_envs:make: an observation has 4 numbers (shape (4,))"),
]


@pytest.mark.parametrize(("how", "message"), OWN_ENV_FAILS, ids=[h for h, _ in OWN_ENV_FAILS])
def test_an_own_env_that_fails_mid_run_stops_in_one_line(tmp_path, monkeypatch, how, message):
    """Your env raising in step or reset, or changing its observation's shape, during
    training: one line naming the env, the call and the frames (never a traceback)."""
    (tmp_path / "failing_envs.py").write_text(FAILING_ENV)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("failing_envs", None)
    cfg = compose_config(
        "env=gymnasium", "env.id=failing_envs:make", f"+env.kwargs.how={how}", "total_frames=800"
    )
    trainer = make_trainer(cfg, tmp_path / "run")
    try:
        with pytest.raises(TrainingError) as err:
            trainer.run()
    finally:
        trainer.close()
        sys.modules.pop("failing_envs", None)
    one_line(str(err.value), message, "training stopped ")


def _failing_env(tmp_path: Path, monkeypatch) -> None:
    (tmp_path / "failing_envs.py").write_text(FAILING_ENV)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("failing_envs", None)


@pytest.mark.parametrize("how", ["step", "reset", "shape"])
def test_an_own_env_that_fails_before_the_first_checkpoint_leaves_nothing(
    tmp_path, monkeypatch, how
):
    """Stopped before its first checkpoint, a fresh run has nothing to continue from:
    the directory it made is gone, and the one line says so; a directory the user made
    keeps what it held."""
    from wcsac_rl.train import run_training

    _failing_env(tmp_path, monkeypatch)
    overrides = ("env=gymnasium", "env.id=failing_envs:make", f"+env.kwargs.how={how}")
    cfg = compose_config(*overrides, "+env.kwargs.after=30", "total_frames=800")
    mine = tmp_path / "mine"
    mine.mkdir()
    for run_dir in (tmp_path / "new" / "run", mine):
        with pytest.raises(TrainingError) as err:
            run_training(cfg, run_dir)
        one_line(str(err.value), f"{how}" if how != "shape" else "4 numbers", "removed")
        assert "no checkpoint had been written yet" in str(err.value)
    assert not (tmp_path / "new" / "run").exists()
    assert mine.is_dir() and not any(mine.iterdir())
    sys.modules.pop("failing_envs", None)


def test_an_own_env_that_fails_after_a_checkpoint_keeps_the_run(tmp_path, monkeypatch):
    """Stopped after a checkpoint, the run keeps its directory: resume=auto continues it."""
    from wcsac_rl.train import run_training

    _failing_env(tmp_path, monkeypatch)
    cfg = compose_config(
        "env=gymnasium",
        "env.id=failing_envs:make",
        "+env.kwargs.how=step",
        "+env.kwargs.after=600",
        "epoch_frames=400",
        "checkpoint_every_epochs=1",
        "algo.collector.init_random_frames=400",
        "total_frames=800",
    )
    with pytest.raises(TrainingError) as err:
        run_training(cfg, tmp_path / "run")
    sys.modules.pop("failing_envs", None)
    one_line(str(err.value), "step() raised RuntimeError", "is kept")
    assert "removed" not in str(err.value)
    assert (tmp_path / "run" / "checkpoints").is_dir()
    assert (tmp_path / "run" / "progress.csv").is_file()


def test_train_py_removes_the_run_directory_of_a_run_stopped_before_any_checkpoint(tmp_path):
    """The same from the command line, in Hydra's own dated directory and in a
    ``hydra.run.dir`` that did not exist."""
    (tmp_path / "failing_envs.py").write_text(FAILING_ENV)
    overrides = ["env=gymnasium", "env.id=failing_envs:make", "+env.kwargs.how=reset"]
    overrides += ["+env.kwargs.after=30", "total_frames=800", "progress_bar=false"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    for where in ([], [f"hydra.run.dir={tmp_path / 'D'}"]):
        result = subprocess.run(
            [sys.executable, str(ROOT / "train.py"), *overrides, *where],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
            env=env,
        )
        assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
        (error,) = error_lines(result.stderr)
        one_line(error, "reset() raised RuntimeError", "is removed")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["failing_envs.py"]


# ------------------------------------- a refused command changes nothing that existed
def _train_py(cwd: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *overrides],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=600,
    )


def _everything(root: Path) -> tuple[list[str], dict[str, str]]:
    """Every path below ``root`` (directories too) and every file's SHA-256 (the lock too)."""
    return sorted(str(p.relative_to(root)) for p in root.rglob("*")), tree_digests(root, skip=())


def _hydra_records(run: Path) -> None:
    """What Hydra wrote into ``run`` when it was started (the shared runs are trained in
    process, without Hydra)."""
    (run / ".hydra").mkdir(exist_ok=True)
    for name in ("config.yaml", "hydra.yaml", "overrides.yaml"):
        (run / ".hydra" / name).write_text(f"# the first command's {name}\nseed: 0\n")


KEEPS_WHAT_EXISTED = [
    ("algo.lr=abc hydra.run.dir=D", "D: a user's directory holding notes.log"),
    ("seed=5 hydra.run.dir=RUN", "RUN: a finished run"),
    ("seed=5 hydra.run.dir=RUN", "RUN: a run still training (its lock held)"),
]
"""train.py command lines refused in a directory that existed (the tests below)."""


def test_a_refused_run_keeps_a_directory_it_did_not_create(tmp_path):
    """``mkdir D && echo precious > D/notes.log``, then a refused ``train.py ...
    hydra.run.dir=D``: D and notes.log are as they were (no lock, no log, no records)."""
    directory = tmp_path / "D"
    directory.mkdir()
    (directory / "notes.log").write_text("precious\n")
    before = _everything(directory)
    result = _train_py(tmp_path, *TINY, "algo.lr=abc", f"hydra.run.dir={directory}")
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-2000:]
    (error,) = error_lines(result.stderr)
    one_line(error, "algo.lr must be > 0 (a number), got 'abc'")
    assert _everything(directory) == before


@pytest.mark.parametrize("live", [False, True], ids=["finished", "still training"])
def test_a_refused_run_writes_no_records_into_another_run(runs, tmp_path, live):
    """A new run pointed at a finished run's directory, or at one still training (its
    lock held), is refused, and that run's Hydra records still say what they said."""
    from wcsac_rl.training.run_dir import RunLock

    run = copy_run(runs / "wcsac", tmp_path)
    _hydra_records(run)
    lock = RunLock(run) if live else None
    try:
        before = snapshot(run)
        result = _train_py(tmp_path, *TINY, "seed=5", f"hydra.run.dir={run}")
    finally:
        if lock is not None:
            lock.release()
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr[-2000:]
    (error,) = error_lines(result.stderr)
    one_line(error, "is in use by another run" if live else "already holds a run")
    assert snapshot(run) == before
    assert not [p for p in run.iterdir() if p.name.startswith(".hydra-")]


def test_an_accepted_run_keeps_hydras_records(tmp_path):
    """The records Hydra writes for a run that starts are in its ``.hydra/`` (staged
    while the command could still be refused)."""
    session = tmp_path / "session"
    result = _train_py(
        tmp_path, *TINY, "algo=random", "total_frames=200", "epoch_frames=200",
        "eval_episodes=0", "progress_bar=false", f"hydra.run.dir={session}",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    records = sorted(p.name for p in (session / ".hydra").iterdir())
    assert records == ["config.yaml", "hydra.yaml", "overrides.yaml"]
    assert "seed: 0" in (session / ".hydra" / "config.yaml").read_text()
    assert not [p for p in session.iterdir() if p.name.startswith(".hydra-")]


# ------------------------------------------------------------------------ loss API
LOSS_ARGUMENTS = [
    ("cost_threshold=nan", {"cost_threshold": math.nan}, "cost_threshold must be >= 0"),
    ("cost_threshold=inf", {"cost_threshold": math.inf}, "cost_threshold must be >= 0"),
    ("cost_threshold=-1", {"cost_threshold": -1.0}, "cost_threshold must be >= 0"),
    ("cost_limit=nan", {"cost_limit": math.nan}, "cost_limit must be >= 0"),
    ("risk_level=nan", {"risk_level": math.nan}, "risk_level α must be a number in (0, 1]"),
    ("risk_level=True", {"risk_level": True}, "risk_level α must be a number in (0, 1]"),
    ("risk_level=1e-300", {"risk_level": 1e-300}, "risk_level α=1e-300 is below"),
]


@pytest.mark.parametrize(
    ("name", "kwargs", "message"), LOSS_ARGUMENTS, ids=[n for n, *_ in LOSS_ARGUMENTS]
)
def test_loss_arguments(name, kwargs, message):
    with pytest.raises(ValueError) as err:
        make_loss(**kwargs)
    assert message in str(err.value)


def _poisoned(key, value):
    batch = make_batch(16)
    entry = batch[key].clone()
    entry.view(-1)[0] = value
    batch[key] = entry
    return batch


LOSS_BATCHES = [
    ("empty batch", None, "WCSACLoss got an empty batch (batch_size=[0])"),
    ("('next', 'cost')=nan", (("next", "cost"), math.nan), "batch entry ('next', 'cost')"),
    ("('next', 'reward')=inf", (("next", "reward"), math.inf), "batch entry ('next', 'reward')"),
    ("observation=nan", (("observation",), math.nan), "batch entry 'observation'"),
    (
        "('next', 'cost')=1e30",
        (("next", "cost"), 1e30),
        "loss_cost_value is inf although the batch is finite; its largest magnitudes:",
    ),
    ("('next', 'cost')=3e38", (("next", "cost"), 3e38), "('next', 'cost') 3e+38"),
]


@pytest.mark.parametrize(
    ("name", "poison", "message"), LOSS_BATCHES, ids=[n for n, *_ in LOSS_BATCHES]
)
def test_loss_batch(name, poison, message):
    loss = make_loss(check_finite=True)
    if poison is None:
        batch = make_batch(0)
    else:
        key, value = poison
        batch = _poisoned(key if len(key) > 1 else key[0], value)
    before = {k: v.detach().clone() for k, v in loss.state_dict().items()}
    with pytest.raises(ValueError) as err:
        loss(batch)
    assert message in str(err.value)
    assert all(torch.equal(before[k], v) for k, v in loss.state_dict().items())


def _without_next_observation():
    batch = make_batch(16)
    del batch["next", "observation"]
    return batch


def _float_done():
    batch = make_batch(16)
    batch["next", "done"] = batch["next", "done"].float()
    return batch


LOSS_BATCH_ENTRIES = [
    (
        "no ('next', 'observation')",
        _without_next_observation,
        KeyError,
        "WCSACLoss: the batch has no ('next', 'observation') entry, which the loss reads",
    ),
    (
        "a float ('next', 'done')",
        _float_done,
        TypeError,
        "WCSACLoss: batch entry ('next', 'done') must be boolean (torch.bool), got torch.float32",
    ),
]


@pytest.mark.parametrize(
    ("name", "make", "kind", "message"), LOSS_BATCH_ENTRIES, ids=[n for n, *_ in LOSS_BATCH_ENTRIES]
)
def test_loss_batch_entries(name, make, kind, message):
    """A batch without an entry the loss reads, or with a done flag that is not bool,
    is one error naming the entry (keys and dtypes only: no host synchronisation)."""
    loss = make_loss()
    with pytest.raises(kind) as err:
        loss(make())
    assert message in str(err.value)


# ------------------------------------------------------------------- minor ones
def _full_disk_first_checkpoint(tmp_path, monkeypatch, capsys) -> str:
    from wcsac_rl.training.checkpoint import save_checkpoint
    from wcsac_rl.training.config import TrainingError

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(TrainingError) as err:
        save_checkpoint(tmp_path / "checkpoints" / "last.pt", {"frames": 400})
    assert list((tmp_path / "checkpoints").iterdir()) == []
    return str(err.value)


def _unreadable_path(tmp_path, monkeypatch, capsys) -> str:
    from wcsac_rl.train import check_command_line

    with pytest.raises(SystemExit) as stop:
        check_command_line([*TINY, f"hydra.run.dir={tmp_path}/runü"])
    return str(stop.value)


def _seed_overflow(main, option: str):
    def case(tmp_path, monkeypatch, capsys) -> str:
        before = snapshot(tmp_path)
        with pytest.raises(SystemExit) as stop:
            main([str(tmp_path), option, "99999999999999999999999"])
        assert stop.value.code == 2 and snapshot(tmp_path) == before
        (line,) = capsys.readouterr().err.strip().splitlines()[-1:]
        return line

    return case


def _stopped_under_wcsac_train(tmp_path, monkeypatch, capsys) -> str:
    from wcsac_rl.training.preemption import Preempted

    monkeypatch.setattr(sys, "argv", ["/venv/bin/wcsac-train", "env=tiny"])
    return str(Preempted(15, tmp_path / "run" / "checkpoints" / "last.pt", 400))


MINOR = [
    (
        "a full disk at the first checkpoint",
        _full_disk_first_checkpoint,
        "no checkpoint had been written yet",
    ),
    ("hydra.run.dir=runü", _unreadable_path, "error: cannot read the override 'hydra.run.dir="),
    *(
        (
            f"{command} {option} 99999999999999999999999",
            _seed_overflow(main, option),
            f"error: {option} must be a whole number in [0, 2**63 - 1]",
        )
        for command, main, option in (
            ("wcsac-evaluate", evaluate_main, "--seed"),
            ("wcsac-calibration", calibration_main, "--seed"),
            ("wcsac-report", report_main, "--trajectory-seed"),
        )
    ),
    (
        "SIGTERM under wcsac-train",
        _stopped_under_wcsac_train,
        "continue it with: wcsac-train resume=",
    ),
]


@pytest.mark.parametrize(("name", "case", "message"), MINOR, ids=[n for n, *_ in MINOR])
def test_minor(tmp_path, monkeypatch, capsys, name, case, message):
    """The full-disk message says what is kept, Hydra's lexer errors and a seed that
    overflows are one line naming the option, a stopped run names the command it ran."""
    one_line(case(tmp_path, monkeypatch, capsys), message)


# ----------------------------------------------------- the table in docs/guarantees.md
CATEGORIES = {
    "env code in a run's files": CODE_FROM_RUN_FILES,
    "a directory that existed": KEEPS_WHAT_EXISTED,
    "train.py": TRAIN_PY,
    "train (config)": CONFIG,
    "resume": RESUME,
    "evaluate": EVALUATE,
    "calibration": CALIBRATION,
    "report": REPORT,
    "loss arguments": LOSS_ARGUMENTS,
    "loss batches": LOSS_BATCHES,
    "loss batch entries": LOSS_BATCH_ENTRIES,
    "report readers": EVALUATION_FILES,
    "minor": MINOR,
    "own env mid-run": OWN_ENV_FAILS,
}


def _documented() -> dict[str, tuple[int, list[str]]]:
    """``category -> (count, inputs)`` from the table of docs/guarantees.md."""
    text = (ROOT / "docs" / "guarantees.md").read_text()
    rows = {}
    section = text.split("## The bad inputs the tests try", 1)[1].split("\n## ", 1)[0]
    for line in section.splitlines():
        match = re.fullmatch(r"\| (.+?) \| (\d+) \| (.+) \|", line.strip())
        if match:
            rows[match.group(1)] = (int(match.group(2)), re.findall(r"`([^`]+)`", match.group(3)))
    return rows


def test_the_documented_table_is_this_suites():
    documented = _documented()
    assert set(documented) == set(CATEGORIES)
    source = Path(__file__).read_text()
    for category, cases in CATEGORIES.items():
        count, inputs = documented[category]
        assert count == len(cases), category
        for example in inputs:  # (each word of it: a command line's words are listed apart)
            missing = [word for word in example.split() if word not in source]
            assert not missing, f"{category}: {example!r} is not an input of this suite"
    assert sum(len(cases) for cases in CATEGORIES.values()) >= 40
