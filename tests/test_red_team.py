"""The red-team suite (issue 33): bad inputs a hostile or careless user gives every command.

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
import json
import math
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from _loss_helpers import make_batch, make_loss
from _training_helpers import ROOT, compose_config, tree_digests

from wcsac_rl.calibration import main as calibration_main
from wcsac_rl.evaluate import main as evaluate_main
from wcsac_rl.evaluation.evaluator import evaluate_run
from wcsac_rl.report import main as report_main
from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, resume_config

TINY = ("env=tiny", "env.max_episode_steps=50")


def _train(run_dir: Path, *overrides: str) -> Path:
    trainer = make_trainer(compose_config(*TINY, *overrides), run_dir)
    try:
        trainer.run()
    finally:
        trainer.close()
    return run_dir


snapshot = tree_digests


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Finished tiny runs shared by every test (never written to by a refused command):
    ``wcsac`` (α = 0.5, 800 frames, ``frames-400.pt`` kept, evaluated), ``sac_lag``
    (400 frames) and ``random`` (400 frames)."""
    root = tmp_path_factory.mktemp("red_team") / "runs"
    _train(root / "wcsac", "risk_level=0.5", "keep_checkpoints_at=[1]")
    evaluate_run(root / "wcsac", episodes=2, progress=False)
    _train(root / "sac_lag", "algo=sac_lag", "total_frames=400")
    _train(root / "random", "algo=random", "total_frames=400")
    return root


@pytest.fixture(autouse=True)
def unchanged(request):
    """Every file of the shared runs is byte-identical after each test."""
    if "runs" not in request.fixturenames:
        yield
        return
    root = request.getfixturevalue("runs")
    before = snapshot(root)
    yield
    assert snapshot(root) == before, "a refused command changed a file of the runs"


def _one_line(message: str, *needles: str) -> None:
    assert "\n" not in message.strip(), message
    assert "Traceback" not in message
    for needle in needles:
        assert needle in message, f"{needle!r} not in {message!r}"


def _error_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.startswith("error:")]


def _copy(runs: Path, name: str, tmp_path: Path) -> Path:
    target = tmp_path / name
    shutil.copytree(runs / name, target)
    return target


# ------------------------------------------------------------- train.py (subprocess)
TRAIN_PY = [
    ("algo.lr=abc", "algo.lr must be > 0 (a number), got 'abc'"),
    ("+risk_levl=0.1", "unknown config key risk_levl (did you mean risk_level?)"),
    ("algo.batchsize=64", "unknown config key algo.batchsize (did you mean algo.batch_size?)"),
    ("seed=18446744073709551616", "seed must be at most 2**63 - 1"),
    ("resume=KEPT", "is at 400 frames but the run"),
]


@pytest.mark.parametrize(("override", "message"), TRAIN_PY, ids=[o for o, _ in TRAIN_PY])
def test_train_py(runs, tmp_path, override, message):
    override = override.replace("KEPT", str(runs / "wcsac" / "checkpoints" / "frames-400.pt"))
    session = tmp_path / "session"
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *TINY, override, f"hydra.run.dir={session}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 1, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    errors = _error_lines(result.stderr)
    assert len(errors) == 1
    _one_line(errors[0], message)
    assert not session.exists()  # a refused command leaves no run directory


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
    ("algo.network.width=0", "algo.network.width must be an integer > 0, got 0"),
    ("algo.network.depth=-1", "algo.network.depth must be an integer >= 0, got -1"),
    ("algo.network.activation=foo", "algo.network.activation must be one of relu"),
    ("algo.network.log_std_min=5", "algo.network.log_std_min (5) must be < algo.network"),
    ("algo.alpha_init=-1", "algo.alpha_init must be > 0 (a number), got -1"),
    ("algo.kappa_init=0", "algo.kappa_init must be > 0 with the gradient rule"),
    ("algo.kappa_lr_scale=0", "algo.kappa_lr_scale must be > 0 (a number), got 0"),
    ("algo.damp_scale=-1", "algo.damp_scale must be >= 0 (a number), got -1"),
    ("algo.cost_gamma=2", "algo.cost_gamma must be null or in [0, 1] (a number), got 2"),
    ("algo.variance=maybe", "algo.variance must be true or false, got 'maybe'"),
    ("algo.kappa_rule=pi", "algo.kappa_rule must be one of gradient, pid, got 'pi'"),
    ("+algo.pid.kq=1", "unknown PID option algo.pid.kq"),
    ("algo.batch_size=20000", "algo.batch_size (20000) must be <= algo.buffer_size (10000)"),
    ("algo.name=foo", "unknown algo 'foo'"),
    ("env.name=mars", "unknown env 'mars'"),
    ("env.max_episode_steps=0", "env.max_episode_steps must be an integer > 0, got 0"),
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
    ("eval_episodes=-1", "eval_episodes must be an integer >= 0, got -1"),
    ("keep_checkpoints_at=[0]", "keep_checkpoints_at must be a list of epochs >= 1"),
    ("compile=yes", "compile must be true or false, got 'yes'"),
    ("max_nonfinite_updates=0", "max_nonfinite_updates must be an integer > 0, got 0"),
    ("device=tpu", "device must be cpu, cuda[:N] or mps, got 'tpu'"),
    ("logger.backend=nope", "logger.backend must be csv, wandb, tensorboard or none"),
    ("+algo.batchsize=64", "unknown config key algo.batchsize (did you mean algo.batch_size?)"),
]


@pytest.mark.parametrize(("override", "message"), CONFIG, ids=[o for o, _ in CONFIG])
def test_train_config(tmp_path, override, message):
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config(*TINY, override), tmp_path / "run")
    _one_line(str(err.value), message)
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
    run = _copy(runs, "sac_lag", tmp_path)
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
]


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
        copy = _copy(runs, "wcsac", tmp_path)
        _truncated(copy)
        target = str(copy)
    elif target == "FOREIGN":
        target = str(_foreign_checkpoint(runs, tmp_path))
    else:
        target = target.replace("RUN", str(run))
    before = snapshot(tmp_path)
    with pytest.raises(ConfigError) as err:
        _resume(target, *overrides)
    _one_line(str(err.value), message)
    assert snapshot(tmp_path) == before


def test_resume_auto_of_another_algorithm(runs):
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config(*TINY, "algo=sac_lag", "resume=auto"), runs / "wcsac")
    _one_line(str(err.value), "another configuration (algo.name: checkpoint='wcsac'")


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
    run = _copy(runs, name, tmp_path)
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
    errors = _error_lines(err)
    assert len(errors) == 1
    _one_line(errors[0], message, str(target))
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
    errors = _error_lines(err)
    assert len(errors) == 1
    _one_line(errors[0], message)
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
    errors = _error_lines(err)
    assert len(errors) == 1
    _one_line(errors[0], message)
    assert snapshot(tmp_path) == before
    assert not out.exists() or not [p for p in out.rglob("*") if p.name.endswith(".tmp")]


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
    errors = _error_lines(capsys.readouterr().err)
    assert code == 1 and len(errors) == 1
    _one_line(errors[0], "already has table1.md", "pass --force to overwrite")
    assert snapshot(tmp_path) == before


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


# ----------------------------------------------------- the table in docs/guarantees.md
CATEGORIES = {
    "train.py": TRAIN_PY,
    "train (config)": CONFIG,
    "resume": RESUME,
    "evaluate": EVALUATE,
    "calibration": CALIBRATION,
    "report": REPORT,
    "loss arguments": LOSS_ARGUMENTS,
    "loss batches": LOSS_BATCHES,
}


def _documented() -> dict[str, tuple[int, list[str]]]:
    """``category -> (count, inputs)`` from the table of docs/guarantees.md."""
    text = (ROOT / "docs" / "guarantees.md").read_text()
    rows = {}
    for line in text.split("## The bad inputs the tests try", 1)[1].splitlines():
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
