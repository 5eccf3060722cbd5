"""Hostile and careless inputs, the second suite: none of them is in test_red_team.py.

Every entry point is given values a careless or hostile user would type: ``train.py``
overrides (in process through ``make_trainer`` for the config, ``check_command_line``
for the command line's syntax, a subprocess where only the command line shows the
behaviour), resume of files that are not checkpoints or hold fields of the wrong
type, the flags and input files of ``python -m wcsac_rl.evaluate``,
``wcsac_rl.calibration``, ``wcsac_rl.report`` and ``paper.compare``,
and the Python API (the losses' arguments and batches, the n-step transform, the
episode-cost window, the envs' constructors).

Each case names its class (``_hostile_helpers.CLASSES``): a clear error (one line naming
the option or file, a non-zero exit, no traceback), handled (the right thing done,
asserted), fixed (it was a failure and is now one line), or xfail (still a failure:
the test asserts the line it should give, ``xfail(strict=True)`` with the fix). The
shared run is hashed before and after every test; a refused command leaves the files it
was given byte-identical. docs/guarantees.md counts these cases by category; a test
here keeps that table in step with this file.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import pytest
import torch
from _hostile_helpers import (
    TINY,
    copy_run,
    error_lines,
    evaluated_tiny_run,
    files_unchanged,
    one_line,
    parametrize,
    train_py,
)
from _loss_helpers import make_batch, make_loss
from _training_helpers import ROOT, compose_config, tree_digests

from paper.compare import main as compare_main
from wcsac_rl.calibration import main as calibration_main
from wcsac_rl.envs import TinyHazardEnv, make_env
from wcsac_rl.evaluate import main as evaluate_main
from wcsac_rl.objectives import EpisodeCostWindow, NStepCost
from wcsac_rl.report import main as report_main
from wcsac_rl.training import ConfigError, make_trainer
from wcsac_rl.training.checkpoint import load_checkpoint, resume_config
from wcsac_rl.training.restore import load_run

snapshot = tree_digests


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """A finished tiny WCSAC run (α = 0.5, 400 frames, evaluated), shared by every test and never written to by one."""
    return evaluated_tiny_run(tmp_path_factory.mktemp("hostile") / "runs")


@pytest.fixture(autouse=True)
def unchanged(request):
    yield from files_unchanged(request, "runs", "a command changed a file of the shared run")


# ------------------------------------------------------------ train (in process)
CONFIG = [
    ("algo.lr=inf", "error", "algo.lr must be > 0 (a number), got inf"),
    ("algo.lr=1e400", "error", "algo.lr must be > 0 (a number), got inf"),
    ("algo.lr=[1,2]", "error", "algo.lr must be > 0 (a number), got [1, 2]"),
    ("algo.lr={a:1}", "error", "algo.lr must be > 0 (a number), got {'a': 1}"),
    ("algo.lr=null", "error", "algo.lr must be > 0 (a number), got None"),
    ("algo.gamma=nan", "error", "algo.gamma must be in [0, 1] (a number), got nan"),
    ("algo.tau=inf", "error", "algo.tau must be in (0, 1] (a number), got inf"),
    ("algo.batch_size=1.5", "error", "algo.batch_size must be an integer > 0, got 1.5"),
    ("algo.buffer_size=abc", "error", "algo.buffer_size must be an integer > 0, got 'abc'"),
    ("algo.collector.num_envs=-2", "error", "algo.collector.num_envs must be an integer > 0"),
    (
        "algo.collector.init_random_frames=-1",
        "error",
        "algo.collector.init_random_frames must be an integer >= 0, got -1",
    ),
    ("algo.collector.utd_ratio=inf", "error", "algo.collector.utd_ratio must be > 0"),
    (
        "algo.network.width=1.5",
        "error",
        "algo.network.width must be an integer in [1, 16384], got 1.5",
    ),
    ("algo.network.log_std_max=nan", "error", "algo.network.log_std_max must be a finite"),
    ("algo.alpha_init=inf", "error", "algo.alpha_init must be in (0, 1e+06] (a number), got inf"),
    ("algo.kappa_init=nan", "error", "algo.kappa_init must be in [0, 1e+06] (a number), got nan"),
    ("algo.damp_scale=nan", "error", "algo.damp_scale must be in [0, 1e+06] (a number), got nan"),
    ("algo.variance=2", "error", "algo.variance must be true or false, got 2"),
    ("algo.target_entropy=inf", "error", "algo.target_entropy must be auto (-|A|) or a finite"),
    ("risk_level=[0.1]", "error", "risk_level α must be a number in (0, 1], got [0.1]"),
    ("risk_level=inf", "error", "risk_level α must be a number in (0, 1], got inf"),
    ("cost_limit=inf", "error", "cost_limit must be >= 0 (an episodic cost budget), got inf"),
    ("cost_limit=true", "error", "cost_limit must be a number (an episodic cost budget)"),
    ("total_frames=1e3", "error", "total_frames must be an integer > 0, got 1000.0"),
    ("epoch_frames=-400", "error", "epoch_frames must be an integer > 0, got -400"),
    ("seed=true", "error", "seed must be an integer >= 0, got True"),
    ("seed=null", "error", "seed must be an integer >= 0, got None"),
    ("threads=abc", "error", "threads must be an integer > 0, got 'abc'"),
    ("eval_episodes=1.5", "error", "eval_episodes must be an integer >= 0, got 1.5"),
    ("keep_checkpoints_at=5", "error", "keep_checkpoints_at must be a list of epochs >= 1"),
    ("keep_checkpoints_at=[1.5]", "error", "keep_checkpoints_at must be a list of epochs >= 1"),
    ("checkpoint_every_epochs=0", "error", "checkpoint_every_epochs must be an integer > 0"),
    ("progress_bar=maybe", "error", "progress_bar must be true or false, got 'maybe'"),
    ("save_replay_buffer=maybe", "error", "save_replay_buffer must be true or false"),
    ("device=cuda:-1", "error", "device must be cpu, cuda[:N] or mps, got 'cuda:-1'"),
    ("device=null", "error", "device must be cpu, cuda[:N] or mps, got None"),
    ("logger.backend=null", "error", "logger.backend must be csv, wandb, tensorboard or none"),
    (
        "env.max_episode_steps=1.5",
        "error",
        "env.max_episode_steps must be an integer in [1, 1000000]",
    ),
    ("env.name=null", "error", "unknown env None; choose one of static"),
    ("+env.kwargs.hazard_cost=-1", "fixed", "env.kwargs of env=tiny: hazard_cost must be >= 0"),
    ("+env.kwargs.render_mode=human", "fixed", "env.kwargs of env=tiny: TinyHazardEnv does not"),
    (
        "+env.kwargs.speed=abc",
        "fixed",
        "env.kwargs of env=tiny: speed must be a finite number > 0, got 'abc'",
    ),
    ("+env.kwargs.speed=-1", "fixed", "env.kwargs of env=tiny: speed must be a finite number"),
    ("+env.kwargs.goal_size=0", "fixed", "env.kwargs of env=tiny: goal_size must be a finite"),
    (
        "+env.kwargs.goal_xy=[1]",
        "fixed",
        "env.kwargs of env=tiny: goal_xy must be a pair (x, y) of finite numbers, got [1]",
    ),
    ("+foo.bar=1", "error", "unknown config key foo: not a key of the algo=wcsac env=tiny"),
    ("+logger.foo=1", "error", "unknown config key logger.foo"),
    ("run_name=..", "error", "run_name must be a name without '/'"),
    ("risk_level=${risk_level}", "error", "algo.risk_level=${risk_level} cannot be resolved"),
    ("cost_limit=${nope}", "error", "cost_limit=${nope} cannot be resolved: Interpolation key"),
    ("cost_limit=${oc.decode:abc}", "error", "cost_limit must be a number (an episodic cost"),
    ("seed=${oc.env:HOME}", "fixed", "seed must be an integer >= 0, got '/"),
    ("resume=", "fixed", "resume='' names no run: give resume=<run directory>"),
    ("env=gymnasium", "error", "env=gymnasium needs env.id=<registered gymnasium id"),
    ("env=gymnasium env.id=os:nosuch", "fixed", "module 'os' has no callable 'nosuch'"),
    ("env=gymnasium env.id=CartPole-v1", "fixed", "env.id=CartPole-v1 has a Discrete action"),
    ("env=gymnasium env.id=Pendulum-v1", "fixed", "env.id=Pendulum-v1 reported no cost at step 1"),
    (
        "env=gymnasium env.id=Pendulum-v1 env.cost_key=",
        "error",
        "env.cost_key must name the info entry of the cost, got ''",
    ),
]

CONFIG_FIXES: dict[str, str] = {}


@parametrize(("override", "kind", "message"), CONFIG, CONFIG_FIXES)
def test_train_config(tmp_path, override, kind, message):
    with pytest.raises(ConfigError) as err:
        make_trainer(compose_config(*TINY, *override.split()), tmp_path / "run")
    one_line(str(err.value), message)
    assert not (tmp_path / "run").exists()  # refused before anything was built


# ------------------------------------------------------- train.py's command line
COMMAND_LINE = [
    ("seed", "error", "cannot read the override 'seed' (Error parsing override 'seed')"),
    ("seed=choice()", "error", "cannot read the override 'seed=choice()'"),
    ("algo.lr", "error", "cannot read the override 'algo.lr'"),
    ("algo.network.widht=8", "error", "(did you mean algo.network.width?)"),
    ("algo=nope", "fixed", "unknown algo 'nope': conf/algo/ has no nope.yaml"),
    ("=5", "fixed", "'=5'"),
    ("algo.lr=1,2", "fixed", "algo.lr=1,2"),
    ("-m seed=1,abc", "fixed", "seed must be an integer >= 0, got 'abc'"),
]

COMMAND_LINE_FIXES: dict[str, str] = {}


@parametrize(("override", "kind", "message"), COMMAND_LINE, COMMAND_LINE_FIXES)
def test_train_command_line(override, kind, message):
    """What ``train.py`` checks before Hydra reads the command line (in process)."""
    from wcsac_rl.train import check_command_line

    words = override.split()
    flags = [w for w in words if w.startswith("-")]
    with pytest.raises(SystemExit) as stop:
        check_command_line([*flags, *TINY, *[w for w in words if w not in flags]])
    one_line(str(stop.value), "error: ", message)


TRAIN_PY = [("hydra.run.dir=", "fixed", "already holds a run")]

TRAIN_PY_FIXES: dict[str, str] = {}


@parametrize(("command", "kind", "message"), TRAIN_PY, TRAIN_PY_FIXES)
def test_train_py(tmp_path, command, kind, message):
    """``python train.py`` (a subprocess: only the command line shows this): one
    ``error:`` line, exit code 1, and the directory it ran in as it was."""
    (tmp_path / "notes.txt").write_text("a user's notes\n")
    before = snapshot(tmp_path)
    result = train_py(tmp_path, *TINY, command)
    assert result.returncode == 1, result.stderr[-2000:]
    assert "Traceback" not in result.stderr
    (error,) = error_lines(result.stderr)
    one_line(error, message)
    assert snapshot(tmp_path) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


# ------------------------------------------------------------------------- resume
def _resume(target: Path | str, *overrides: str):
    """What ``train.py resume=<target> <overrides>`` builds (the run's own config)."""
    given = [f"resume={target}", *overrides]
    trainer = make_trainer(resume_config(compose_config(*given, small=False), given), Path("x"))
    trainer.close()


def _crafted(edit):
    def make(run: Path, tmp_path: Path) -> Path:
        path = run / "checkpoints" / "last.pt"
        state = load_checkpoint(path)
        edit(state)
        torch.save(state, path)
        return run

    return make


def _replaced(name: str, data: bytes | None):
    def make(run: Path, tmp_path: Path) -> Path:
        path = run / name
        if data is None:
            path.unlink()
        else:
            path.write_bytes(data)
        return run

    return make


def _file(name: str, data: bytes):
    """A file (or ``<dir>/checkpoints/last.pt``) outside the run."""

    def make(run: Path, tmp_path: Path) -> Path:
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        return path.parents[1] if path.parent.name == "checkpoints" else path

    return make


def _saved(name: str, value):
    def make(run: Path, tmp_path: Path) -> Path:
        path = tmp_path / name / "checkpoints" / "last.pt"
        path.parent.mkdir(parents=True)
        torch.save(value, path)
        return path.parents[1]

    return make


RESUME_TARGETS = {
    "resume=notes.txt": _file("notes.txt", b"x"),
    "resume=a text file as last.pt": _file("text/checkpoints/last.pt", b"not a pickle"),
    "resume=an empty last.pt": _file("empty/checkpoints/last.pt", b""),
    "resume=a last.pt holding a list": _saved("list", [1, 2]),
    "resume=a last.pt holding frames only": _saved("frames", {"frames": 400}),
    "resume=RUN/checkpoints": lambda run, tmp: run / "checkpoints",
    "resume=RUN/config.yaml": lambda run, tmp: run / "config.yaml",
    "frames: -400": _crafted(lambda s: s.update(frames=-400)),
    "frames: 1.5": _crafted(lambda s: s.update(frames=1.5)),
    "frames: true": _crafted(lambda s: s.update(frames=True)),
    "learner: 5": _crafted(lambda s: s.update(learner=5)),
    "rng: 5": _crafted(lambda s: s.update(rng=5)),
    "config.seed: abc": _crafted(lambda s: s["config"].update(seed="abc")),
    "config.algo.lr: -1": _crafted(lambda s: s["config"]["algo"].update(lr=-1)),
    "config.algo: 5": _crafted(lambda s: s["config"].update(algo=5)),
    "config without algo": _crafted(lambda s: s["config"].pop("algo")),
    "config.env: [tiny]": _crafted(lambda s: s["config"].update(env=["tiny"])),
    "progress.csv of other columns": _replaced("progress.csv", b"a,b\n1,2\n"),
    "RUN total_frames=abc": lambda run, tmp: run,
    "RUN risk_level=0.1": lambda run, tmp: run,
    "RUN env=static": lambda run, tmp: run,
    "RUN seed=3": lambda run, tmp: run,
    "RUN threads=1000": lambda run, tmp: run,
    "RUN algo.lr=abc": lambda run, tmp: run,
}

RESUME = [
    ("resume=notes.txt", "error", "notes.txt is not inside a run's checkpoints/ directory"),
    ("resume=a text file as last.pt", "error", "cannot read checkpoint"),
    ("resume=an empty last.pt", "error", "last.pt: EOFError"),
    ("resume=a last.pt holding a list", "error", "it holds a list, not the dict train.py"),
    ("resume=a last.pt holding frames only", "error", "(no 'config', 'learner' entry)"),
    ("resume=RUN/checkpoints", "error", "checkpoints holds no checkpoint (expected"),
    ("resume=RUN/config.yaml", "error", "config.yaml is not inside a run's checkpoints/"),
    ("frames: -400", "error", "its 'frames' entry must be a whole number >= 0, got -400"),
    ("frames: 1.5", "error", "its 'frames' entry must be a whole number >= 0, got 1.5"),
    ("frames: true", "error", "its 'frames' entry must be a whole number >= 0, got True"),
    ("learner: 5", "error", "its 'learner' entry must hold the networks' states, got int"),
    ("rng: 5", "error", "its 'rng' entry is not the RNG states train.py saves"),
    ("config.seed: abc", "error", "seed must be an integer >= 0, got 'abc'"),
    ("config.algo.lr: -1", "error", "algo.lr must be > 0 (a number), got -1"),
    ("config.algo: 5", "fixed", "its config's 'algo' entry must be a mapping of settings, got 5"),
    ("config without algo", "fixed", "its config's 'algo' entry must be a mapping of settings"),
    ("config.env: [tiny]", "fixed", "its config's 'env' entry must be a mapping of settings"),
    ("progress.csv of other columns", "fixed", "progress.csv: its header has no 'epoch' column"),
    ("RUN total_frames=abc", "error", "total_frames must be an integer > 0, got 'abc'"),
    ("RUN risk_level=0.1", "error", "risk_level: run=0.5, now=0.1 cannot change on resume"),
    ("RUN env=static", "error", "made by another configuration (env.name: checkpoint='tiny'"),
    ("RUN seed=3", "error", "seed: run=0, now=3 cannot change on resume"),
    ("RUN threads=1000", "error", "threads=1000 is more than this machine's"),
    ("RUN algo.lr=abc", "error", "algo.lr must be > 0 (a number), got 'abc'"),
]


@parametrize(("case", "kind", "message"), RESUME, {})
def test_resume(runs, tmp_path, case, kind, message):
    run = copy_run(runs / "wcsac", tmp_path)
    target = RESUME_TARGETS[case](run, tmp_path)
    overrides = case.split()[1:] if case.startswith("RUN ") else []
    before = snapshot(tmp_path)
    with pytest.raises(ConfigError) as err:
        _resume(target, *overrides)
    one_line(str(err.value), message)
    assert snapshot(tmp_path) == before
    assert not list(run.glob("config.resume*")) and not list(run.glob("provenance.resume*"))


# ------------------------------------------------- evaluate, calibration, report
def _cli(main, args: list[str], capsys) -> tuple[int, str]:
    """Run a command's ``main``; its exit code and everything it printed."""
    try:
        code = main(args)
    except SystemExit as stop:  # argparse (2), compare's sys.exit("error: ...")
        code = stop.code
    captured = capsys.readouterr()
    text = captured.err + captured.out
    if isinstance(code, str):
        text, code = text + code + "\n", 1
    return code or 0, text


def _args(args: str, runs: Path, tmp_path: Path) -> list[str]:
    (tmp_path / "notes.txt").write_text("x")
    places = {
        "RUN": str(runs / "wcsac"),
        "CKPT": str(runs / "wcsac" / "checkpoints" / "last.pt"),
        "FILE": str(tmp_path / "notes.txt"),
        "DIR": str(tmp_path),
        "OUT": str(tmp_path / "out"),
    }
    return [places.get(word, word) for word in args.split()]


def _refused(main, args, runs, tmp_path, capsys, message, code=None):
    args = _args(args, runs, tmp_path)
    before = snapshot(tmp_path)
    got, text = _cli(main, args, capsys)
    assert got == code if code is not None else got in (1, 2), text
    assert "Traceback" not in text
    errors = [line for line in text.splitlines() if "error: " in line]
    assert len(errors) == 1, text
    one_line(errors[0], message)
    assert snapshot(tmp_path) == before


EVALUATE = [
    ("RUN --episodes abc", "error", "argument --episodes: invalid int value: 'abc'"),
    ("RUN --episodes 1.5", "error", "argument --episodes: invalid int value: '1.5'"),
    ("RUN --seed abc", "error", "argument --seed: invalid int value: 'abc'"),
    ("RUN --max-episode-steps -5", "error", "--max-episode-steps must be >= 1, got -5"),
    ("RUN --threads 0", "fixed", "--threads must be a whole number in [1, "),
    ("RUN --threads 1000", "fixed", "(this machine's cores), got 1000"),
    ("FILE", "error", "notes.txt: not a run directory (expected a directory)"),
    ("", "error", "give run or sweep directories, or --random-policy ENV"),
    ("--random-policy mars --out OUT", "fixed", "unknown env 'mars'; choose one of static"),
    ("--random-policy tiny --random-seeds -1 --out OUT", "fixed", "--random-seeds must be a"),
    ("--random-policy tiny --cost-limit nan --out OUT", "fixed", "cost limit must be a number"),
    ("--random-policy tiny --cost-limit -2 --out OUT", "fixed", "got -2.0"),
    ("--random-policy tiny --out FILE", "fixed", "notes.txt is a file, not a directory"),
    ("RUN --archive FILE", "error", "error: archive: [Errno 20] Not a directory"),
]


@parametrize(("args", "kind", "message"), EVALUATE, {})
def test_evaluate(runs, tmp_path, capsys, args, kind, message):
    _refused(evaluate_main, f"{args} --no-progress --episodes 1", runs, tmp_path, capsys, message)
    assert not (tmp_path / "out").exists()


CALIBRATION = [
    ("RUN --episodes -1", "error", "--episodes must be >= 1, got -1"),
    ("RUN --max-episode-steps 0", "error", "--max-episode-steps must be >= 1, got 0"),
    ("RUN --seed -5", "error", "--seed must be a whole number in [0, 2**63 - 1], got -5"),
    ("RUN --threads 0", "fixed", "--threads must be a whole number in [1, "),
    ("RUN --threads -3", "fixed", "got -3"),
    ("FILE", "error", "notes.txt is not inside a run's checkpoints/ directory"),
    ("DIR", "error", "holds no checkpoint (expected"),
]


@parametrize(("args", "kind", "message"), CALIBRATION, {})
def test_calibration(runs, tmp_path, capsys, args, kind, message):
    episodes = "" if "--episodes" in args else " --episodes 1"
    _refused(calibration_main, f"{args} --no-progress{episodes}", runs, tmp_path, capsys, message)


REPORT = [
    ("RUN --out FILE --no-trajectories", "fixed", "notes.txt is a file, not a directory"),
    ("FILE --out OUT --no-trajectories", "error", "notes.txt: no such directory"),
    ("RUN --out OUT --no-trajectories --fig6-ymax nan", "fixed", "--fig6-ymax must be a finite"),
    ("RUN --out OUT --no-trajectories --fig6-ymax -1", "fixed", "number > 0 (a cost), got -1.0"),
    ("RUN --out OUT --trajectory-episodes -1", "error", "--trajectory-episodes must be >= 1"),
    ("RUN --out OUT --trajectory-max-steps 0", "error", "--trajectory-max-steps must be >= 1"),
    ("RUN --out OUT --no-trajectories --improvement abc", "error", "--improvement takes A:B"),
    ("RUN --out OUT --no-trajectories --improvement a:b", "error", "no row 'a' (rows: wcsac_0.5)"),
    ("RUN --out OUT --no-trajectories --study", "error", "need >= 2 runs of a row; found 1"),
    ("RUN --out OUT --no-trajectories --threads 0", "fixed", "--threads must be a whole number"),
    ("RUN --out OUT --trajectory-runs FILE", "error", "not a run directory with a checkpoint"),
    ("RUN --out OUT --no-trajectories --cost-limit inf", "error", "cost limit must be a number"),
    ("RUN --out OUT --no-trajectories --cost-limit abc", "error", "invalid float value: 'abc'"),
    ("RUN --out OUT --trajectory-seed -1", "error", "--trajectory-seed must be a whole number"),
    ("RUN --out OUT --no-trajectories --video", "error", "the tiny env does not render"),
]


@parametrize(("args", "kind", "message"), REPORT, {})
def test_report(runs, tmp_path, capsys, args, kind, message):
    _refused(report_main, args, runs, tmp_path, capsys, message)
    out = tmp_path / "out"
    assert not out.exists() or not [p for p in out.rglob("*") if p.name.endswith(".tmp")]


def _edited(name: str, text: str | None):
    def make(run: Path) -> None:
        if text is None:
            (run / name).unlink()
        else:
            (run / name).write_text(text)

    return make


COMPARE_EDITS = {
    "FILE": None,
    "RUN --out DIR": None,
    "evaluation.json holding 5": _edited("evaluation.json", "5"),
    'evaluation.json holding {"metrics": 5}': _edited("evaluation.json", '{"metrics": 5}'),
    "an empty evaluation.json": _edited("evaluation.json", ""),
    "calibration.json holding 5": _edited("calibration.json", "5"),
    "no evaluation.json": _edited("evaluation.json", None),
    "progress.csv of other columns": _edited("progress.csv", "a,b\n1,2\n"),
}

COMPARE = [
    ("FILE", "error", "notes.txt: no evaluation.json (run python -m wcsac_rl.evaluate)"),
    ("RUN --out DIR", "fixed", "is a directory; name the file to write the table to"),
    (
        "evaluation.json holding 5",
        "fixed",
        "evaluation.json: not a record of wcsac_rl (a JSON object",
    ),
    (
        'evaluation.json holding {"metrics": 5}',
        "fixed",
        "evaluation.json: not a record of wcsac_rl",
    ),
    ("an empty evaluation.json", "fixed", "evaluation.json: not JSON (Expecting value"),
    ("calibration.json holding 5", "fixed", "calibration.json: not a record of wcsac_rl"),
    ("no evaluation.json", "error", "no evaluation.json (run python -m wcsac_rl.evaluate)"),
    ("progress.csv of other columns", "error", "error: 'time_s' missing"),
]


@parametrize(("case", "kind", "message"), COMPARE, {})
def test_compare(runs, tmp_path, capsys, case, kind, message):
    edit = COMPARE_EDITS[case]
    if edit is None:
        args = case
    else:
        run = copy_run(runs / "wcsac", tmp_path)
        (run / "calibration.json").write_text(json.dumps({"metrics": {}}))
        edit(run)
        args = str(run)
    _refused(compare_main, args, runs, tmp_path, capsys, message, code=1 if edit else None)


# ------------------------------------------------------------------ the Python API
LOSS_ARGUMENTS = [
    ("cost_limit=-1.0", "error", "cost_limit must be >= 0 (an episodic cost budget), got -1.0"),
    ("cost_limit='abc'", "error", "cost_limit must be a number (an episodic cost budget)"),
    ("max_episode_steps=0", "error", "max_episode_steps must be a positive integer, got 0"),
    ("max_episode_steps=1.5", "error", "max_episode_steps must be a positive integer, got 1.5"),
    ("kappa_init=nan", "error", "kappa_init must be in [0, 1e+06] (a number), got nan"),
    ("kappa_max=-1.0", "error", "kappa_max must be null or in (0, 1e+06] (a number), got -1.0"),
    ("huber_kappa=-1.0", "error", "huber_kappa must be in (0, 1e+06] (a number), got -1.0"),
    ("k_ucb=nan", "error", "k_ucb must be in [0, 1e+06] (a number), got nan"),
    ("num_quantiles=0", "error", "num_quantiles must be an integer >= 1, got 0"),
    ("num_safety_nets=0", "error", "num_safety_nets must be an integer >= 1, got 0"),
    ("kappa_signal_every=0", "error", "kappa_signal_every must be an integer >= 1 (updates)"),
    ("pid=5", "error", "pid must be a PIDGains or a mapping of its fields, got 5"),
    ("risk_level='0.5'", "error", "risk_level α must be a number in (0, 1], got '0.5'"),
    ("cost_threshold='1'", "error", "cost_threshold must be >= 0 (a finite number), got '1'"),
    ("num_qvalue_nets=0", "fixed", "num_qvalue_nets must be an integer >= 1, got 0"),
]

LOSS_FIXES: dict[str, str] = {}


def _keywords(text: str) -> dict:
    name, value = text.split("=", 1)
    return {name: eval(value, {"nan": math.nan})}  # (a literal of this file)


@parametrize(("arguments", "kind", "message"), LOSS_ARGUMENTS, LOSS_FIXES)
def test_loss_arguments(arguments, kind, message):
    with pytest.raises(ValueError) as err:
        make_loss(**_keywords(arguments))
    one_line(str(err.value).split(". α is")[0], message)


def _set(key, make):
    def edit(batch):
        batch[key] = make(batch)

    return edit


def _delete(key):
    def edit(batch):
        del batch[key]

    return edit


LOSS_BATCH_EDITS = {
    "no ('next', 'cost')": _delete(("next", "cost")),
    "no ('next', 'reward')": _delete(("next", "reward")),
    "a float ('next', 'terminated')": _set(
        ("next", "terminated"), lambda b: b["next", "done"].float()
    ),
    "a plain dict": None,
    "no 'action'": _delete("action"),
    "an action of 3 numbers (the actor's is 2)": _set("action", lambda b: torch.zeros(16, 3)),
    "a float64 observation": _set("observation", lambda b: b["observation"].double()),
}

LOSS_BATCHES = [
    ("no ('next', 'cost')", "error", KeyError, "needs the per-step cost at ('next', 'cost')"),
    ("no ('next', 'reward')", "error", KeyError, "the batch has no ('next', 'reward') entry"),
    (
        "a float ('next', 'terminated')",
        "error",
        TypeError,
        "batch entry ('next', 'terminated') must be boolean (torch.bool), got torch.float32",
    ),
    ("a plain dict", "fixed", TypeError, "WCSACLoss takes a TensorDict batch, got dict"),
    ("no 'action'", "fixed", KeyError, "the batch has no ('action',) entry"),
    ("an action of 3 numbers (the actor's is 2)", "fixed", ValueError, "'action'"),
    ("a float64 observation", "fixed", TypeError, "'observation'"),
]

LOSS_BATCH_FIXES: dict[str, str] = {}


@parametrize(("case", "kind", "error", "message"), LOSS_BATCHES, LOSS_BATCH_FIXES)
def test_loss_batch(case, kind, error, message):
    loss = make_loss()
    edit = LOSS_BATCH_EDITS[case]
    if edit is None:
        batch = {"observation": torch.zeros(3, 5)}
    else:
        batch = make_batch(16)
        edit(batch)
    with pytest.raises(error) as err:
        loss(batch)
    assert message in str(err.value)


def _nstep_batch(edit=None):
    batch = make_batch(16).unsqueeze(0).expand(2, 16).clone()
    if edit is not None:
        edit(batch)
    return batch


TRANSFORMS = [
    ("NStepCost(0, 0.99)", "error", "n_steps must be an integer >= 1, got 0"),
    ("NStepCost(1.5, 0.99)", "error", "n_steps must be an integer >= 1, got 1.5"),
    ("NStepCost(3, 1.5)", "error", "gamma must be in [0, 1] (a number), got 1.5"),
    ("NStepCost(3, nan)", "error", "gamma must be in [0, 1] (a number), got nan"),
    ("NStepCost('3', 0.99)", "error", "n_steps must be an integer >= 1"),
    ("NStepCost(True, 0.99)", "fixed", "n_steps must be an integer >= 1, got True"),
    ("NStepCost(3, 0.99) of a batch without ('next', 'cost')", "fixed", "('next', 'cost')"),
    ("NStepCost(3, 0.99) of a batch without ('next', 'done')", "fixed", "('next', 'done')"),
    ("EpisodeCostWindow(0.5, window=1.5)", "error", "window must be an integer >= 1 (episodes)"),
    ("EpisodeCostWindow(2.0)", "error", "risk_level α must be a number in (0, 1], got 2.0"),
    ("EpisodeCostWindow(0.5, test_window=-1)", "error", "test_window must be an integer >= 0"),
    ("EpisodeCostWindow(0.5, test_risk_level=5.0)", "error", "test_risk_level α must be a"),
    ("EpisodeCostWindow(0.5, horizon=1.5)", "error", "horizon must be an integer >= 1 (steps)"),
]

TRANSFORM_FIXES: dict[str, str] = {}


@parametrize(("call", "kind", "message"), TRANSFORMS, TRANSFORM_FIXES)
def test_transforms(call, kind, message):
    construct, _, batch = call.partition(" of a batch without ")
    with pytest.raises((ValueError, KeyError)) as err:
        made = eval(construct, {"NStepCost": NStepCost, "EpisodeCostWindow": EpisodeCostWindow,
                                "nan": math.nan})  # fmt: skip
        if batch:
            key = tuple(re.findall(r"'(\w+)'", batch))
            made(_nstep_batch(_delete(key)))
    one_line(str(err.value).split(". α is")[0], message)


ENVS = [
    ("TinyHazardEnv(speed=-1.0)", "fixed", "speed must be a finite number > 0, got -1.0"),
    ("TinyHazardEnv(speed=nan)", "fixed", "speed must be a finite number > 0, got nan"),
    ("TinyHazardEnv(goal_size=0.0)", "fixed", "goal_size must be a finite number > 0, got 0.0"),
    ("TinyHazardEnv(hazard_size=-1.0)", "fixed", "hazard_size must be a finite number >= 0"),
    ("TinyHazardEnv(start_noise=-1.0)", "fixed", "start_noise must be a finite number >= 0"),
    ("TinyHazardEnv(start_noise=inf)", "fixed", "start_noise must be a finite number >= 0"),
    ("TinyHazardEnv(reward_goal=nan)", "fixed", "reward_goal must be a finite number, got nan"),
    ("TinyHazardEnv(goal_xy=(1.0,))", "fixed", "goal_xy must be a pair (x, y) of finite"),
    ("TinyHazardEnv(start_xy='ab')", "fixed", "start_xy must be a pair (x, y) of finite"),
    ("TinyHazardEnv(hazard_xy=(0.0, nan))", "fixed", "hazard_xy must be a pair (x, y)"),
    ("TinyHazardEnv(max_episode_steps='abc')", "fixed", "max_episode_steps must be an integer"),
    ("TinyHazardEnv(hazard_cost=nan)", "error", "hazard_cost must be >= 0, got nan"),
    ("TinyHazardEnv(hazard_cost_prob=nan)", "error", "hazard_cost_prob must be in [0, 1]"),
    ("TinyHazardEnv(foo=1)", "error", "got an unexpected keyword argument 'foo'"),
    ("make_env('mars')", "error", "unknown env 'mars'; valid names are"),
    ("make_env('tiny', num_workers=-1)", "error", "num_workers must be a positive int, got -1"),
    ("make_env('tiny', foo=1)", "error", "bad keyword for env 'tiny'"),
    ("make_env('gymnasium')", "error", "missing 1 required positional argument: 'env_id'"),
]


@parametrize(("call", "kind", "message"), ENVS, {})
def test_envs(call, kind, message):
    names = {"TinyHazardEnv": TinyHazardEnv, "make_env": make_env, "nan": math.nan}
    names["inf"] = math.inf
    with pytest.raises((ValueError, TypeError)) as err:
        env = eval(call, names)  # (a literal of this file)
        env.close()
    one_line(str(err.value), message)


# -------------------------------------------------------- handled: the right thing
def _already_evaluated(runs, tmp_path, capsys):
    code, text = _cli(evaluate_main, [str(runs / "wcsac"), "--episodes", "1"], capsys)
    assert code == 0, text
    one_line(text.splitlines()[0], "skipped: ", "already has evaluation.csv", "--force")


def _unknown_fig6_row(runs, tmp_path, capsys):
    out = tmp_path / "out"
    args = [str(runs / "wcsac"), "--out", str(out), "--no-trajectories", "--fig6-rows", "nope"]
    code, text = _cli(report_main, args, capsys)
    assert code == 0 and (out / "table1.md").is_file(), text
    (warning,) = [line for line in text.splitlines() if "Figure 6" in line]
    one_line(warning, "warning: Figure 6: no evaluated row(s) nope")


def _random_seed_twice(runs, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["--random-policy", "tiny", "--random-seeds", "5", "5", "--out", str(out)]
    code, text = _cli(evaluate_main, [*args, "--episodes", "1", "--no-progress"], capsys)
    assert code == 0, text
    assert [p.name for p in out.iterdir()] == ["random_tiny_seed5"]  # one evaluation
    assert json.loads((out / "random_tiny_seed5" / "evaluation.json").read_text())["seed"] == 5


def _resume_builds(edit):
    def case(runs, tmp_path, capsys):
        run = copy_run(runs / "wcsac", tmp_path)
        edit(run)
        before = snapshot(run)
        _resume(run)
        assert snapshot(run) == before  # (building a resume writes nothing)

    return case


def _extra_config_key(run: Path) -> None:
    path = run / "checkpoints" / "last.pt"
    state = load_checkpoint(path)
    state["config"]["notes"] = "a key the kit does not know"
    torch.save(state, path)


def _load_run_of_a_string_path(runs, tmp_path, capsys):
    restored = load_run(str(runs / "wcsac"))
    try:
        assert restored.frames == 400 and restored.cfg.algo.risk_level == 0.5
    finally:
        restored.env.close()


def _integer_costs(runs, tmp_path, capsys):
    """Costs given as integers: the same losses as the same costs as floats."""
    batch = make_batch(16)
    integer = batch.clone()
    integer["next", "cost"] = batch["next", "cost"].long()
    outputs = []
    for given in (batch, integer):
        loss = make_loss(seed=0)
        torch.manual_seed(3)
        outputs.append(loss(given))
    for key in outputs[0].keys():
        if key.startswith("loss_"):
            assert torch.equal(outputs[0][key], outputs[1][key]), key


def _nstep_of_an_empty_batch(runs, tmp_path, capsys):
    out = NStepCost(3, 0.99)(make_batch(0).unsqueeze(0))
    assert out["nstep", "cost"].shape[:2] == (1, 0)


def _random_ignores_risk_level(runs, tmp_path, capsys):
    trainer = make_trainer(compose_config(*TINY, "algo=random", "risk_level=0.1"), tmp_path / "r")
    trainer.close()  # (the random policy has no risk level to read: built, not refused)


HANDLED = [
    ("evaluate RUN (evaluated, no --force)", "handled", _already_evaluated),
    ("report --fig6-rows nope", "handled", _unknown_fig6_row),
    ("evaluate --random-policy tiny --random-seeds 5 5", "handled", _random_seed_twice),
    (
        "resume of a run without config.yaml",
        "handled",
        _resume_builds(lambda run: (run / "config.yaml").unlink()),
    ),
    (
        "resume of a checkpoint with a key the kit does not know",
        "handled",
        _resume_builds(_extra_config_key),
    ),
    (
        "resume of a run with an empty progress.csv",
        "handled",
        _resume_builds(lambda run: (run / "progress.csv").write_text("")),
    ),
    ("load_run(str path)", "handled", _load_run_of_a_string_path),
    ("WCSACLoss of integer costs", "handled", _integer_costs),
    ("NStepCost of an empty batch", "handled", _nstep_of_an_empty_batch),
    ("algo=random risk_level=0.1", "handled", _random_ignores_risk_level),
]


@parametrize(("case", "kind", "check"), HANDLED, {})
def test_handled(runs, tmp_path, capsys, case, kind, check):
    check(runs, tmp_path, capsys)


# ----------------------------------------------------- the table in docs/guarantees.md
CATEGORIES = {
    "train (config)": CONFIG,
    "train.py command line": COMMAND_LINE,
    "train.py (subprocess)": TRAIN_PY,
    "resume": RESUME,
    "evaluate": EVALUATE,
    "calibration": CALIBRATION,
    "report": REPORT,
    "compare": COMPARE,
    "loss arguments": LOSS_ARGUMENTS,
    "loss batches": LOSS_BATCHES,
    "n-step and episode window": TRANSFORMS,
    "envs": ENVS,
    "handled": HANDLED,
}

TABLE = "## Hostile inputs by class"


def _documented() -> dict[str, tuple[int, list[str]]]:
    """``category -> (count, inputs)`` from the table of that section."""
    text = (ROOT / "docs" / "guarantees.md").read_text().split(TABLE, 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in text.splitlines():
        match = re.fullmatch(r"\| (.+?) \| (\d+) \| (.+) \|", line.strip())
        if match:
            rows[match.group(1)] = (int(match.group(2)), re.findall(r"`([^`]+)`", match.group(3)))
    return rows


def _classes(cases) -> dict[str, int]:
    counts = dict.fromkeys(("error", "handled", "fixed", "xfail"), 0)
    for case in cases:
        counts[case[1]] += 1
    return counts


def test_the_documented_table_is_this_suites():
    documented = _documented()
    assert set(documented) == set(CATEGORIES) | {"all"}
    source = Path(__file__).read_text()
    for category, cases in CATEGORIES.items():
        count, inputs = documented[category]
        assert count == len(cases), category
        for example in inputs:
            missing = [word for word in example.split() if word not in source]
            assert not missing, f"{category}: {example!r} is not an input of this suite"
    every = [case for cases in CATEGORIES.values() for case in cases]
    assert documented["all"][0] == len(every) >= 100
    text = (ROOT / "docs" / "guarantees.md").read_text().split(TABLE, 1)[1].split("\n## ", 1)[0]
    classes = _classes(every)  # the sentence under the table says the classes
    classes["error"] += classes.pop("fixed")  # (a fixed case is an error of one line)
    said = ", ".join(f"{count} {kind}" for kind, count in classes.items())
    assert f"Of these {len(every)} inputs: {said}." in text


def test_no_input_is_also_in_the_red_team_suite():
    """Each input of this file is new: none is a case of test_red_team.py."""
    red_team = (ROOT / "tests" / "test_red_team.py").read_text()
    for cases in CATEGORIES.values():
        for case in cases:
            pattern = r'^\s*\(\s*"' + re.escape(case[0]) + '",'
            assert not re.search(pattern, red_team, re.MULTILINE), case[0]
