"""What a stopped run tells its user continues it: after SIGTERM and after Ctrl-C the
printed command, followed as printed, continues the run in its own directory and leaves
no other directory behind; resume=auto where nothing can be continued is refused, and a
resume that cannot update says so."""

from __future__ import annotations

import csv
import os
import re
import shlex
import signal
import subprocess
import sys
import time

import pytest
from _training_helpers import ROOT, TINY_CLI

TRAIN = [sys.executable, str(ROOT / "train.py")]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def _train(cwd, *args, **kwargs):
    return subprocess.run(
        [*TRAIN, *args], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=300, **kwargs
    )


def _ctrl_c_as_in_a_terminal():
    """SIGINT at its default in the child (a test worker may ignore it, and an ignored
    signal stays ignored across exec: Python would then never raise KeyboardInterrupt)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _stopped_run(tmp_path, signum):
    """A tiny run in ``tmp_path/run`` stopped by ``signum`` after its first checkpoint:
    the stop's message (stderr) and the frames it names."""
    run_dir = tmp_path / "run"
    proc = subprocess.Popen(
        [*TRAIN, *TINY_CLI, "algo=sac", "epoch_frames=400", "total_frames=400000",
         f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=_ctrl_c_as_in_a_terminal,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 240
        while not (run_dir / "checkpoints" / "last.pt").is_file() and proc.poll() is None:
            assert time.monotonic() < deadline, "no checkpoint in 240 s"
            time.sleep(0.5)
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    expected = 130 if signum == signal.SIGINT else 128 + signum  # (Ctrl-C: the shell's 130)
    assert proc.returncode == expected, (proc.returncode, err[-4000:])
    lines = [line for line in err.splitlines() if "continue it with: " in line]
    assert len(lines) == 1, err[-4000:]
    line = lines[0]
    frames = int(re.search(r"at (\d+) frames", line).group(1))
    return run_dir, line, frames


def _follow(tmp_path, line, *extra):
    """Run the command ``line`` names (``python train.py ...``) as printed, plus ``extra``."""
    command = shlex.split(line.split("continue it with: ", 1)[1].split(" (or ")[0])
    assert command[:2] == ["python", "train.py"], command
    return _train(tmp_path, *command[2:], *extra)


def _epochs(run_dir):
    with (run_dir / "progress.csv").open(newline="") as f:
        return [int(row["epoch"]) for row in csv.DictReader(f)]


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["sigterm", "ctrl_c"])
def test_the_printed_command_continues_the_run_in_its_own_directory(tmp_path, signum):
    run_dir, line, frames = _stopped_run(tmp_path, signum)
    assert f"resume={run_dir}" in line
    before = _epochs(run_dir)
    done = _follow(tmp_path, line, f"total_frames={frames + 400}")
    assert done.returncode == 0, done.stderr
    assert len(_epochs(run_dir)) > len(before)
    assert _epochs(run_dir) == list(range(1, len(_epochs(run_dir)) + 1))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # (no outputs/<date>/...)
    assert "this session stops" not in done.stdout


@pytest.mark.slow
def test_a_resume_shorter_than_the_refill_says_it_makes_no_update(tmp_path):
    _, line, frames = _stopped_run(tmp_path, signal.SIGTERM)
    done = _follow(tmp_path, line, f"total_frames={frames + 100}")
    assert done.returncode == 0, done.stderr
    notice = [x for x in done.stdout.splitlines() if x.startswith("resume: the replay buffer")]
    assert len(notice) == 1, done.stdout
    assert f"this session stops at total_frames={frames + 100}: no update" in notice[0]


def test_resume_auto_in_a_new_timestamped_directory_is_refused(tmp_path):
    done = _train(tmp_path, *TINY_CLI, "algo=sac", "resume=auto", "total_frames=400")
    assert done.returncode == 1
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: resume=auto continues the run"), lines
    assert "hydra.run.dir=outputs/my_run resume=auto" in lines[0]
    assert list(tmp_path.iterdir()) == []
