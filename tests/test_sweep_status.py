"""Every job of a sweep accounted for (finished, unfinished, failed, missing), from the
layout any Hydra launcher writes. (Real sweeps: tests/test_launchers.py.)"""

from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

from wcsac_rl.evaluation.sweeps import find_sweep_roots, incomplete_jobs, sweep_jobs
from wcsac_rl.training.checkpoint import save_checkpoint

JOBS = [  # in the basic sweeper's order: params first, then the command line's overrides
    ["+row=sac", "env=tiny", "seed=0"],
    ["+row=sac", "env=tiny", "seed=10"],
    ["+row=wcsac_0.1", "env=tiny", "seed=0"],
    ["+row=wcsac_0.1", "env=tiny", "seed=10"],
]


def _sweep(
    root: Path,
    sweeper: str = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper",
    rows: str = "sac,wcsac_0.1",
    seeds: str = "0,10",
):
    root.mkdir(parents=True)
    OmegaConf.save(
        {
            "hydra": {
                "sweeper": {
                    "_target_": sweeper,
                    "max_batch_size": None,
                    "params": {"+row": rows},
                },
                "overrides": {"task": ["env=tiny", f"seed={seeds}"]},
            }
        },
        root / "multirun.yaml",
    )
    (root / ".submitit" / "123").mkdir(parents=True)  # a launcher's own files are skipped


def _job(root: Path, name: str, overrides: list[str], frames: int | None, total: int = 800):
    directory = root / name
    (directory / ".hydra").mkdir(parents=True)
    OmegaConf.save(OmegaConf.create(overrides), directory / ".hydra" / "overrides.yaml")
    if frames is not None:
        config = {"total_frames": total, "algo": {"name": "sac"}, "env": {"name": "tiny"}}
        state = {"config": config, "frames": frames, "learner": {}}
        save_checkpoint(directory / "checkpoints" / "last.pt", state)
    return directory


def test_each_job_is_finished_unfinished_failed_or_missing_and_named(tmp_path):
    root = tmp_path / "multirun" / "table1"
    _sweep(root)
    _job(root, "0_sac_tiny_seed0", JOBS[0], frames=800)
    _job(root, "1_sac_tiny_seed10", JOBS[1], frames=400)
    _job(root, "2_wcsac_0.1_tiny_seed0", JOBS[2], frames=None)  # died before a checkpoint
    jobs = sweep_jobs(root)
    assert [job.overrides for job in jobs] == JOBS
    assert [job.status for job in jobs] == ["finished", "unfinished", "failed", "missing"]
    assert [job.name for job in jobs] == [
        "0_sac_tiny_seed0",
        "1_sac_tiny_seed10",
        "2_wcsac_0.1_tiny_seed0",
        "job 3 (+row=wcsac_0.1 seed=10)",  # only the swept values
    ]
    assert "checkpoint at 400 of 800 frames" in jobs[1].detail
    assert "no checkpoint" in jobs[2].detail
    # from any directory above the sweep
    assert find_sweep_roots([tmp_path]) == [root.resolve()]
    assert [job.name for job in incomplete_jobs([tmp_path])] == [j.name for j in jobs[1:]]


def test_a_job_of_an_earlier_sweep_into_the_same_directory_is_listed_after_the_sweeps(
    tmp_path,
):
    root = tmp_path / "sweep"
    _sweep(root)
    for k, overrides in enumerate(JOBS):
        _job(root, f"{k}_job", overrides, frames=800)
    _job(root, "9_old", ["+row=sac", "env=tiny", "seed=99"], frames=100)
    jobs = sweep_jobs(root)
    assert [job.num for job in jobs] == [0, 1, 2, 3, None]
    assert jobs[-1].name == "9_old" and jobs[-1].status == "unfinished"


def test_another_sweepers_jobs_are_classified_and_none_is_called_missing(tmp_path):
    root = tmp_path / "optuna"
    _sweep(root, sweeper="hydra_plugins.hydra_optuna_sweeper.optuna_sweeper.OptunaSweeper")
    _job(root, "0_a", JOBS[0], frames=800)
    _job(root, "1_b", JOBS[1], frames=None)
    assert [(job.name, job.status) for job in sweep_jobs(root)] == [
        ("0_a", "finished"),
        ("1_b", "failed"),
    ]


def _started(directory: Path) -> Path:
    """What a run writes before its first checkpoint."""
    (directory / "config.yaml").write_text("seed: 0\n")
    (directory / "progress.csv").write_text("epoch,frames\n")
    return directory


def test_a_job_whose_run_directory_is_locked_is_running(tmp_path):
    """A job training (before its first checkpoint or after one) holds its run
    directory's lock, as the trainer does: ``running``, not ``failed`` or ``unfinished``;
    once the lock is free (the process ended) the files decide."""
    from wcsac_rl.training.run_dir import RunLock

    root = tmp_path / "sweep"
    _sweep(root)
    before = _started(_job(root, "job0", JOBS[0], frames=None))
    after = _job(root, "job1", JOBS[1], frames=400)
    locks = [RunLock(before), RunLock(after)]
    try:
        jobs = sweep_jobs(root)
        assert [job.status for job in jobs[:2]] == ["running", "running"]
        assert "pid" in jobs[0].detail and "pid" in jobs[1].detail
    finally:
        for lock in locks:
            lock.release()
    assert [job.status for job in sweep_jobs(root)][:2] == ["failed", "unfinished"]


def test_evaluate_warns_of_a_running_job_and_fails_on_a_failed_one_in_one_line(tmp_path, capsys):
    """During a sweep a job before its first checkpoint is one warning (exit 0); after
    it died there, one error line (exit 1), not also a 'without a checkpoint' one."""
    from wcsac_rl.evaluate import main as evaluate
    from wcsac_rl.training.run_dir import RunLock

    root = tmp_path / "sweep"
    _sweep(root, rows="sac", seeds="0")  # one job
    directory = _started(_job(root, "job0", JOBS[0], frames=None))
    lock = RunLock(directory)
    try:
        assert evaluate([str(root), "--no-progress"]) == 0
    finally:
        lock.release()
    err = capsys.readouterr().err
    assert err.count("job0") == 1 and "warning: sweep job" in err and "running" in err
    assert evaluate([str(root), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err.count("job0") == 1 and "error: sweep job" in err and "failed" in err


def test_a_job_without_checkpoint_but_evaluated_is_finished(tmp_path):
    root = tmp_path / "sweep"
    _sweep(root)
    directory = _job(root, "job0", JOBS[0], frames=None)
    (directory / "evaluation.json").write_text('{"trained_frames": 800}')
    [job, *_] = sweep_jobs(root)
    assert job.status == "finished" and "evaluated" in job.detail
