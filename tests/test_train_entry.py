"""The training entry point (``wcsac-train``, ``python -m wcsac_rl.train``, ``train.py``)
and its Python API: ``--help`` without torch, train.log, the warning for options the
algorithm does not read, ``compose_config`` / ``run_training``, the entry module's size
and the command line read once for all its checks."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import pytest
from _training_helpers import ROOT, TINY_CLI

from wcsac_rl.train import compose_config, run_training
from wcsac_rl.training import ConfigError
from wcsac_rl.training.applicability import inapplicable, warn_inapplicable
from wcsac_rl.training.run_records import ConsoleLog

HELP_PROBE = """
import runpy, sys
sys.argv = ["wcsac-train", "--help"]
try:
    runpy.{how}
except SystemExit as stop:
    assert stop.code in (None, 0), stop.code
print("torch imported:", "torch" in sys.modules, file=sys.stderr)
"""


@pytest.mark.parametrize(
    "how",
    [
        "run_module('wcsac_rl.train', run_name='__main__')",
        f"run_path({str(ROOT / 'train.py')!r}, run_name='__main__')",
    ],
    ids=["module", "train.py"],
)
def test_help_answers_without_importing_torch(how, tmp_path):
    """Hydra's help (the config groups and the composed config) needs no torch: the
    entry point and the package import it only when a run starts."""
    result = subprocess.run(
        [sys.executable, "-c", HELP_PROBE.format(how=how)],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert (
        "== Configuration groups ==" in result.stdout and "env: dynamic, gymnasium" in result.stdout
    )
    assert "torch imported: False" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_console_log_keeps_each_streams_lines_in_their_last_state(tmp_path, monkeypatch):
    out, err = io.StringIO(), io.StringIO()
    monkeypatch.setattr(sys, "stdout", out)
    monkeypatch.setattr(sys, "stderr", err)
    log_path = tmp_path / "train.log"
    with ConsoleLog() as log:
        print("held before the file is named")
        sys.stderr.write("\rbar 10%")
        print("a line of stdout while the bar is drawn")
        sys.stderr.write("\rbar 50%\rbar 100%\n")
        log.attach(log_path)
        print("after", end="")
        print(" attach")
        sys.stderr.write("\rsecond bar 30%")  # never finished: its last state is kept
    assert sys.stdout is out and sys.stderr is err  # the streams are given back
    assert log_path.read_text().splitlines() == [
        "held before the file is named",
        "a line of stdout while the bar is drawn",
        "bar 100%",
        "after attach",
        "second bar 30%",
    ]
    assert err.getvalue() == "\rbar 10%\rbar 50%\rbar 100%\n\rsecond bar 30%"  # unchanged
    print("not logged after the with block")
    assert "not logged" not in log_path.read_text()


def test_console_log_never_attached_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    with ConsoleLog():
        print("a refused command's line")
    assert list(tmp_path.iterdir()) == []


def test_an_option_the_algorithm_does_not_read_is_one_warning_line(capsys):
    for algo, overrides, expected in [
        ("sac", ["risk_level=0.1"], ["risk_level=0.1 does not apply to algo=sac"]),
        ("sac_lag", ["seed=1", "risk_level=0.3"], ["risk_level=0.3 does not apply"]),
        ("cpo", ["save_replay_buffer=true"], ["save_replay_buffer=true does not apply"]),
        ("random", ["compile=true", "risk_level=0.1"], ["compile=true", "risk_level=0.1"]),
        ("wcsac", ["risk_level=0.1", "compile=true", "save_replay_buffer=true"], []),
        ("sac", ["cost_limit=5"], []),  # cost_limit: every algorithm's training-safety columns
    ]:
        cfg = compose_config(f"algo={algo}")
        lines = inapplicable(cfg, overrides)
        assert len(lines) == len(expected), (algo, lines)
        for line, part in zip(lines, expected):
            assert line.startswith("warning: ") and part in line and line.endswith("; ignored")
    warn_inapplicable(compose_config("algo=sac"), ["risk_level=0.1"])
    assert capsys.readouterr().err == (
        "warning: risk_level=0.1 does not apply to algo=sac (only algo=wcsac reads it); ignored\n"
    )


def test_an_algorithm_replacing_a_rows_is_said_in_one_warning():  # red-team E1
    overrides = ["+row=wcsac_0.1", "algo=sac_lag"]
    (line,) = inapplicable(compose_config(*overrides), overrides)
    assert line.startswith("warning: algo=sac_lag replaces the algorithm of row=wcsac_0.1")
    assert "(algo=wcsac): this run is sac_lag, labelled sac_lag" in line
    for same in (["+row=wcsac_0.1"], ["+row=wcsac_0.1", "algo=wcsac"]):
        assert inapplicable(compose_config(*same), same) == []


def test_an_option_some_jobs_of_an_experiment_lack_is_refused_before_any_starts(tmp_path):
    """red-team E6: the random and CPO rows have no algo.collector.init_random_frames;
    one line naming a job that lacks it, and no sweep directory."""
    done = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "experiment=table1_static_reduced",
         "total_frames=400", "algo.collector.init_random_frames=200"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )  # fmt: skip
    assert done.returncode == 1
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "algo.collector.init_random_frames" in lines[0], lines
    assert "experiment=table1_static_reduced +row=" in lines[0]
    assert list(tmp_path.iterdir()) == []


def test_compose_config_refuses_an_unknown_key_naming_the_closest():
    with pytest.raises(ConfigError, match=r"algo\.batchsize \(did you mean algo\.batch_size\?\)"):
        compose_config("algo.batchsize=64")


def test_run_training_trains_and_returns_the_run_directory(tmp_path, monkeypatch, capsys):
    """The notebook path: the same run as the command line, train.log included."""
    monkeypatch.chdir(tmp_path)
    cfg = compose_config(
        *TINY_CLI, "algo=sac_lag", "total_frames=400", "epoch_frames=200", "logger=none"
    )
    run_dir = run_training(cfg, tmp_path / "run")
    assert run_dir == tmp_path / "run"
    progress = (run_dir / "progress.csv").read_text().splitlines()
    assert progress[0].startswith("epoch,frames") and len(progress) == 3
    assert (run_dir / "checkpoints" / "last.pt").is_file()
    assert f"run directory: {run_dir}" in (run_dir / "train.log").read_text()
    assert f"run directory: {run_dir}" in capsys.readouterr().out


def test_run_training_refuses_a_bad_config_and_leaves_no_directory(tmp_path):
    cfg = compose_config(*TINY_CLI, "risk_level=2")
    with pytest.raises(ConfigError, match="risk_level"):
        run_training(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_run_training_refused_in_a_directory_of_the_users_keeps_what_it_held(tmp_path):
    """Only what the refused call made goes (its lock file): the user's files stay."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("a user's notes\n")
    with pytest.raises(ConfigError, match="risk_level"):
        run_training(compose_config(*TINY_CLI, "risk_level=2"), mine)
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]


def test_the_entry_module_stays_thin():
    """wcsac_rl/train.py is the entry point only (at most 250 lines): the command line's
    checks live in command_line.py, the console log and Hydra's records with the run
    directory code (training/run_records.py)."""
    lines = (ROOT / "wcsac_rl" / "train.py").read_text().splitlines()
    assert len(lines) <= 250, len(lines)


@pytest.mark.parametrize(
    ("flags", "overrides", "runs"),
    [
        ([], ["seed=3"], True),
        (["-m"], ["seed=1,2"], True),
        ([], ["algo.network.widht=8"], "did you mean algo.network.width?"),
        ([], ["seed"], "cannot read the override 'seed'"),
        (["--help"], [], False),
        (["--cfg", "job"], [], False),
    ],
    ids=["run", "sweep", "unknown-key", "syntax", "help", "cfg"],
)
def test_the_command_line_is_read_once_by_hydras_grammar(monkeypatch, flags, overrides, runs):
    """check_command_line reads the overrides once with Hydra's grammar and hands that
    reading to every check; it says whether a job runs (Hydra answers --help, --cfg)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from wcsac_rl.train import check_command_line

    command_line = [*TINY_CLI, *overrides]
    reads = []
    parse = OverridesParser.parse_overrides

    def counted(self, overrides):  # (Hydra's own loader names the argument)
        reads.append(list(overrides) == command_line)
        return parse(self, overrides)

    monkeypatch.setattr(OverridesParser, "parse_overrides", counted)
    if isinstance(runs, str):
        with pytest.raises(SystemExit) as stop:
            check_command_line([*flags, *command_line])
        assert str(stop.value).startswith("error: ") and runs in str(stop.value)
    else:
        assert check_command_line([*flags, *command_line]) is runs
    assert reads.count(True) == (0 if runs is False else 1)
