"""A run directory has one owner: of several processes started at once on one directory
exactly one trains, the others exit with one line and delete nothing they did not make;
a run copied with hard links never writes into the original."""

from __future__ import annotations

import csv
import hashlib
import os
import signal
import subprocess
import sys
import time

import pytest
from _training_helpers import ROOT, TINY_CLI

TRAIN = [sys.executable, str(ROOT / "train.py"), *TINY_CLI, "algo=sac", "epoch_frames=400"]


def _start(run_dir, *extra):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(
        [*TRAIN, "total_frames=400000", f"hydra.run.dir={run_dir}", *extra],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("resume", [[], ["resume=auto"]], ids=["new", "resume_auto"])
def test_of_three_processes_started_at_once_on_one_directory_exactly_one_trains(tmp_path, resume):
    run_dir = tmp_path / "run"
    procs = [_start(run_dir, *resume) for _ in range(3)]
    try:
        deadline = time.monotonic() + 240
        # two exit on their own; the one that trains would go on for minutes
        while sum(p.poll() is not None for p in procs) < 2 and time.monotonic() < deadline:
            time.sleep(0.5)
        losers = [p for p in procs if p.poll() is not None]
        assert len(losers) == 2, "two processes should have been refused"
        (winner,) = [p for p in procs if p.poll() is None]
        # the winner trains on: a checkpointed epoch, then it is stopped as a scheduler would
        while not (run_dir / "checkpoints" / "last.pt").is_file() and winner.poll() is None:
            time.sleep(0.5)
        assert winner.poll() is None
        winner.send_signal(signal.SIGTERM)
        winner.wait(timeout=120)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
    for loser in losers:
        _, err = loser.communicate()
        assert loser.returncode == 1
        lines = [line for line in err.splitlines() if line.strip()]
        assert len(lines) == 1 and "is in use by another run" in lines[0], err
    # the winner's records are whole: Hydra's, the run's, its lock; no other command's
    names = {p.name for p in run_dir.iterdir()}
    assert {".hydra", "config.yaml", "provenance.json", "train.log", "progress.csv",
            "checkpoints", ".lock"} <= names  # fmt: skip
    assert not [n for n in names if n.startswith(".hydra-pending-")]
    assert {"config.yaml", "overrides.yaml"} <= {p.name for p in (run_dir / ".hydra").iterdir()}
    with (run_dir / "progress.csv").open(newline="") as f:
        epochs = [int(row["epoch"]) for row in csv.DictReader(f)]
    assert epochs == list(range(1, len(epochs) + 1)) and epochs


def _digests(root):
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != ".lock"
    }


@pytest.mark.parametrize("resume", ["resume=auto", "resume=COPY"])
def test_a_run_copied_with_hard_links_resumes_without_touching_the_original(tmp_path, resume):
    """``cp -al RUN COPY`` then a resume of COPY (in its own directory, where Hydra's job
    log is COPY/train.log, or by naming it): RUN stays byte for byte as it was."""
    run, copy = tmp_path / "run", tmp_path / "copy"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}

    def train(*args):
        done = subprocess.run(
            [*TRAIN, *args], cwd=tmp_path, env=env, capture_output=True, text=True
        )
        assert done.returncode == 0, done.stderr

    train("total_frames=400", f"hydra.run.dir={run}")
    before = _digests(run)
    subprocess.run(["cp", "-al", str(run), str(copy)], check=True)  # (GNU cp: hard links)
    assert (copy / "progress.csv").stat().st_nlink == 2
    if resume == "resume=auto":
        train("total_frames=800", "resume=auto", f"hydra.run.dir={copy}")
    else:
        train("total_frames=800", f"resume={copy}")
    assert _digests(run) == before  # the original: byte for byte as it was
    with (copy / "progress.csv").open(newline="") as f:
        assert [int(row["epoch"]) for row in csv.DictReader(f)] == [1, 2]
    shared = [p for p in copy.rglob("*") if p.is_file() and p.stat().st_nlink > 1]
    assert shared == []
