"""provenance.json: the code's commit (and whether it was modified), each session's own file."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from wcsac_rl.training.provenance import (
    PROVENANCE_FILE,
    code_version,
    provenance_files,
    read_provenance,
    session_provenance,
    write_provenance,
)
from wcsac_rl.training.run_dir import check_restartable_run_dir

needs_git = pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")


def _git(repo, *args):
    subprocess.run(
        ["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
        cwd=repo,
        check=True,
        capture_output=True,
    )


@needs_git
def test_code_version_names_the_commit_and_whether_tracked_files_changed(tmp_path):
    repo = tmp_path / "repo"
    (repo / "pkg").mkdir(parents=True)
    (repo / "pkg" / "__init__.py").write_text("")
    (repo / "pkg" / "a.py").write_text("x = 1\n")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "commit", "-q", "-m", "first")
    head = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True
    ).stdout.strip()
    clean = code_version(repo / "pkg")
    assert clean["commit"] == head and clean["dirty"] is False
    (repo / "pkg" / "new.py").write_text("untracked = True\n")  # untracked: still clean
    assert code_version(repo / "pkg")["dirty"] is False
    (repo / "pkg" / "a.py").write_text("x = 2\n")
    assert code_version(repo / "pkg") == {**clean, "dirty": True}
    # a package inside someone else's repository but not tracked there (an installed
    # copy in a virtualenv of that project): that repository's commit is not its own
    installed = repo / ".venv" / "site-packages" / "pkg"
    installed.mkdir(parents=True)
    (installed / "__init__.py").write_text("")
    assert code_version(installed)["commit"] is None


def test_code_version_outside_a_git_checkout_has_no_commit(tmp_path):
    version = code_version(tmp_path)
    assert version["commit"] is None and version["dirty"] is None


def test_a_session_record_is_json_with_the_overrides_and_versions():
    record = session_provenance(
        overrides=["seed=3", "env=tiny"], threads=1, resumed_from_frames=None
    )
    again = json.loads(json.dumps(record))
    assert again["overrides"] == ["seed=3", "env=tiny"] and again["threads"] == 1
    assert again["versions"]["torch"] and again["versions"]["python"]
    assert again["started"].endswith("+00:00")  # UTC


def test_a_session_record_names_the_machine_whose_kernels_made_its_numbers():
    """Runs of one seed on two machines part after the first updates (kernels for other
    vector instructions round differently): the record says which CPU and which of
    torch's kernel sets (the one torch reports) made the numbers."""
    import platform

    import torch

    machine = session_provenance(overrides=None, threads=1, resumed_from_frames=None)["machine"]
    assert machine["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert machine["architecture"] == platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file() and "model name" in cpuinfo.read_text(errors="replace"):
        names = [
            line.partition(":")[2].strip()
            for line in cpuinfo.read_text(errors="replace").splitlines()
            if line.partition(":")[0].strip() == "model name"
        ]
        assert machine["processor"] == names[0]


def test_each_session_writes_its_own_file_and_they_read_back_in_order(tmp_path):
    first = write_provenance(tmp_path, {"session": 0}, resumed=False)
    second = write_provenance(tmp_path, {"session": 1}, resumed=True)
    third = write_provenance(tmp_path, {"session": 2}, resumed=True)
    assert [p.name for p in (first, second, third)] == [
        PROVENANCE_FILE,
        "provenance.resume1.json",
        "provenance.resume2.json",
    ]
    assert provenance_files(tmp_path) == [first, second, third]
    second.write_text("{ torn")  # a half-written file is skipped, not fatal
    assert read_provenance(tmp_path) == [{"session": 0}, {"session": 2}]


def test_a_resumed_run_begun_without_provenance_does_not_claim_its_first_session(tmp_path):
    path = write_provenance(tmp_path, {"session": 1}, resumed=True)
    assert path.name == "provenance.resume1.json"
    assert not (tmp_path / PROVENANCE_FILE).exists()
    assert read_provenance(tmp_path) == [{"session": 1}]


def test_a_run_killed_before_its_first_checkpoint_may_be_started_over(tmp_path):
    write_provenance(tmp_path, {"session": 0}, resumed=False)
    write_provenance(tmp_path, {"session": 1}, resumed=True)
    (tmp_path / "config.yaml").write_text("seed: 0\n")
    check_restartable_run_dir(tmp_path)  # the run's own records: no error


def _train(cfg, run_dir, overrides):
    from wcsac_rl.training import make_trainer

    trainer = make_trainer(cfg, run_dir, overrides=overrides)
    try:
        trainer.run()
    finally:
        trainer.close()
    return trainer


def test_a_session_that_trains_records_itself_and_one_with_nothing_to_do_does_not(tmp_path):
    from _training_helpers import compose_config

    run_dir = tmp_path / "run"
    given = ["env=tiny", "total_frames=400", "epoch_frames=200", "resume=auto"]
    first = _train(compose_config(*given), run_dir, given)
    assert first.provenance_path == run_dir / PROVENANCE_FILE
    assert read_provenance(run_dir)[0]["overrides"] == given
    # the same command again (a sweep run again): the run is finished, nothing is trained
    again = _train(compose_config(*given), run_dir, given)
    assert again.provenance_path is None and again.config_path is None
    assert [p.name for p in provenance_files(run_dir)] == [PROVENANCE_FILE]
    assert not list(run_dir.glob("config.resume*.yaml"))
    # a longer budget trains on: a second session, with its own records
    longer = [*given[:1], "total_frames=600", *given[2:]]
    _train(compose_config(*longer), run_dir, longer)
    records = read_provenance(run_dir)
    assert [r["resumed_from_frames"] for r in records] == [None, 400]
    assert records[1]["overrides"] == longer
    assert (run_dir / "config.resume1.yaml").is_file()
