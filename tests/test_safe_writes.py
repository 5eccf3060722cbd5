"""Every record the kit writes is a new file renamed into place
(``wcsac_rl.training.run_dir.replace_file``): a symbolic or hard link where it writes is
replaced, never written through, so no command writes into a file outside its target."""

from __future__ import annotations

import os

import pytest
from test_targets import RUN_VALUES, TRAINING_SAFETY

from wcsac_rl.evaluation.archive import ArchiveError, archive_run
from wcsac_rl.evaluation.targets import TARGETS_MD, write_targets
from wcsac_rl.training.run_dir import replace_file

VICTIM = "a file of another run\n"


def test_a_link_where_a_record_is_written_is_replaced_not_written_through(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text(VICTIM)
    symlinked, hardlinked = tmp_path / "a.md", tmp_path / "b.md"
    symlinked.symlink_to(victim)
    os.link(victim, hardlinked)
    replace_file(symlinked, "new\n")
    replace_file(hardlinked, b"new\n")
    assert victim.read_text() == VICTIM
    for path in (symlinked, hardlinked):
        assert not path.is_symlink() and path.read_text() == "new\n"
    assert os.stat(victim).st_nlink == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.md", "b.md", "victim.txt"]


def test_a_leftover_temporary_file_of_this_pid_does_not_stop_a_write(tmp_path):
    """A process killed mid-write leaves ``.<name>.<pid>.tmp``; a later process with the
    same pid (a container's processes start at the same pids) still writes, and a link
    left there is removed, not written through."""
    victim = tmp_path / "victim.txt"
    victim.write_text(VICTIM)
    target = tmp_path / "last.pt"
    target.write_bytes(b"old")
    leftover = tmp_path / f".last.pt.{os.getpid()}.tmp"
    leftover.write_bytes(b"half a checkpoint")
    replace_file(target, b"new")
    assert target.read_bytes() == b"new" and not leftover.exists()
    leftover.symlink_to(victim)
    replace_file(target, lambda f: f.write(b"newer"))
    assert target.read_bytes() == b"newer" and victim.read_text() == VICTIM
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.pt", "victim.txt"]


def test_the_targets_table_is_not_written_through_a_symlink(tmp_path):
    report = tmp_path / "report"
    report.mkdir()
    (report / "run_values.csv").write_text(RUN_VALUES)
    (report / "training_safety.csv").write_text(TRAINING_SAFETY)
    victim = tmp_path / "victim.md"
    victim.write_text(VICTIM)
    (report / TARGETS_MD).symlink_to(victim)
    targets = tmp_path / "targets.yaml"
    targets.write_text("a:\n  EC: {at_most: 2.5}\n")
    write_targets(report, targets)
    assert victim.read_text() == VICTIM
    assert not (report / TARGETS_MD).is_symlink() and "EC" in (report / TARGETS_MD).read_text()


def _evaluated_run(directory):
    directory.mkdir()
    for name, text in {
        "evaluation.json": '{"label": "sac", "env": "tiny", "cost_limit": 15.0}\n',
        "evaluation.csv": "episode,return,cost,length,goals,numerical_failure\n",
        "config.yaml": "seed: 0\n",
        "progress.csv": "epoch,frames\n1,400\n",
    }.items():
        (directory / name).write_text(text)
    return directory


def test_an_archive_folder_that_is_a_symlink_is_refused_and_nothing_is_written(tmp_path):
    run = _evaluated_run(tmp_path / "sac_tiny_seed0")
    archive, elsewhere = tmp_path / "archive", tmp_path / "elsewhere"
    archive.mkdir()
    elsewhere.mkdir()
    (elsewhere / "config.yaml").write_text(VICTIM)
    (archive / run.name).symlink_to(elsewhere)
    with pytest.raises(ArchiveError) as err:
        archive_run(run, archive, force=True)
    message = str(err.value)
    assert "\n" not in message and "is a symbolic link" in message
    assert sorted(p.name for p in elsewhere.iterdir()) == ["config.yaml"]
    assert (elsewhere / "config.yaml").read_text() == VICTIM


def test_an_archived_file_that_is_a_link_is_replaced_by_the_runs_own(tmp_path):
    run = _evaluated_run(tmp_path / "sac_tiny_seed0")
    archive = tmp_path / "archive"
    (archive / run.name).mkdir(parents=True)
    victim = tmp_path / "victim.yaml"
    victim.write_text(VICTIM)
    (archive / run.name / "config.yaml").symlink_to(victim)
    archive_run(run, archive, force=True)
    assert victim.read_text() == VICTIM
    assert (archive / run.name / "config.yaml").read_text() == "seed: 0\n"
