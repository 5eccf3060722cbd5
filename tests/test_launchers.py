"""Sweeps through real Hydra launchers: submitit's local executor (the SLURM preset's
jobs as local processes, end to end with evaluate + report on the sweep root) and a
local Ray instance; a job killed mid-run and continued by the same command; submitit's
preemption signal requeueing a job; Ray retrying a run whose worker was killed. Also
the presets' settings. Each launcher's tests are skipped only where its extra is not
installed (`make install` installs both).

Every sweep runs in its own session (process group) and is killed with everything it
started (submitit's job processes, a local Ray instance) when a test ends early."""

from __future__ import annotations

import contextlib
import csv
import importlib.util
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _training_helpers import CONF, ROOT, TINY_CLI
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from wcsac_rl.evaluation.sweeps import sweep_jobs
from wcsac_rl.training.checkpoint import load_checkpoint


def _installed(plugin: str) -> bool:
    return importlib.util.find_spec(f"hydra_plugins.{plugin}") is not None


needs_submitit = pytest.mark.skipif(
    not _installed("hydra_submitit_launcher"), reason='needs pip install -e ".[slurm]"'
)
needs_ray = pytest.mark.skipif(
    not _installed("hydra_ray_launcher"), reason='needs pip install -e ".[ray]"'
)

# the kill / requeue tests: 10 epochs of 400 frames, stopped after the second
FRAMES, EPOCHS = 4000, 10

# a tiny sweep entry: 2 envs, 200 frames per batch, 16-unit networks
TINY = [*TINY_CLI, "resume=auto"]


SWEEP_EXPERIMENTS = (
    "table1_static",
    "table1_static_reduced",
    "table1_static_laptop",
    "table1_dynamic",
    "table1_dynamic_laptop",
    "training_safety_static",
    "training_safety_dynamic",
    "evidence_static",
)


def _sweep(sweep_dir: Path, *overrides: str, launcher: str = "slurm_local") -> list[str]:
    return [
        sys.executable,
        str(ROOT / "train.py"),
        "-m",
        f"hydra/launcher={launcher}",
        *TINY,
        *overrides,
        f"hydra.sweep.dir={sweep_dir}",
    ]


def _env() -> dict[str, str]:
    # the jobs (submitit's job processes too) import this checkout's package, whichever
    # copy of it is installed
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
    return {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": path}


@contextlib.contextmanager
def _started(command: list[str], cwd: Path):
    """The sweep ``command`` running in a new session; on leaving, it and every process
    of its group (the jobs, Ray's processes) are stopped if still there."""
    process = subprocess.Popen(
        command,
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        start_new_session=True,
    )
    try:
        yield process
    finally:
        _stop_group(process)


def _stop_group(process: subprocess.Popen) -> None:
    for signum, wait in ((signal.SIGTERM, 20), (signal.SIGKILL, 10)):
        try:
            os.killpg(process.pid, signum)  # the group outlives its leader
        except ProcessLookupError:
            break
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.communicate(timeout=wait)


def _run(command: list[str], cwd: Path) -> subprocess.CompletedProcess:
    with _started(command, cwd) as process:
        stdout, stderr = process.communicate(timeout=600)
    return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)


def _rows(run_dir: Path) -> list[dict[str, str]]:
    with (run_dir / "progress.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _job_pid(run_dir: Path, *, rows: int, process: subprocess.Popen, timeout: float = 300) -> int:
    """The pid of the job training in ``run_dir`` (from its lock file) once it has logged
    ``rows`` epochs."""
    progress, lock = run_dir / "progress.csv", run_dir / ".lock"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert process.poll() is None, process.communicate()[1][-3000:]
        if progress.is_file() and lock.is_file() and len(progress.read_text().splitlines()) > rows:
            holder = lock.read_text()  # "host h, pid N"
            if "pid" in holder:
                return int(holder.rsplit("pid", 1)[1].strip())
        time.sleep(0.05)
    raise AssertionError(f"{run_dir} logged fewer than {rows} epochs in {timeout} s")


def _assert_continuous(run_dir: Path, *, epochs: int, epoch_frames: int) -> None:
    rows = _rows(run_dir)
    assert [int(r["epoch"]) for r in rows] == list(range(1, epochs + 1))
    assert [int(r["frames"]) for r in rows] == [epoch_frames * (k + 1) for k in range(epochs)]
    checkpoint = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    assert checkpoint["frames"] == epochs * epoch_frames


def _two_job_sweep(tmp_path: Path, launcher: str) -> Path:
    """A 2-job sweep (two Table-1 rows) through ``launcher``: two run dirs with
    progress.csv and checkpoints, both finished."""
    sweep = tmp_path / "sweep"
    overrides = ("+row=sac,sac_lag", "seed=0", "total_frames=800", "epoch_frames=400")
    result = _run(_sweep(sweep, *overrides, launcher=launcher), tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    jobs = sorted(p.name for p in sweep.iterdir() if not p.name.startswith("."))
    assert jobs == ["0_sac_tiny_seed0", "1_sac_lag_tiny_seed0", "multirun.yaml"]
    for name in jobs[:2]:
        _assert_continuous(sweep / name, epochs=2, epoch_frames=400)
    assert [job.status for job in sweep_jobs(sweep)] == ["finished", "finished"]
    return sweep


@needs_submitit
@pytest.mark.slow
def _signal_job(command, tmp_path, run_dir, signum):
    """Start the sweep, send ``signum`` to its job once it has logged two epochs, and
    wait for the sweep command: ``(its process, its stderr)``."""
    with _started(command, tmp_path) as process:
        os.kill(_job_pid(run_dir, rows=2, process=process), signum)
        _, stderr = process.communicate(timeout=300)
    return process, stderr


def test_submitit_local_sweep_then_evaluate_and_report_name_every_job(tmp_path):
    """The sweep, then evaluate + report on its root: Table 1; a job whose directory is
    gone is named."""
    from wcsac_rl.evaluate import main as evaluate
    from wcsac_rl.report import main as report

    sweep = _two_job_sweep(tmp_path, "slurm_local")
    assert (sweep / ".submitit").is_dir()  # the jobs went through submitit
    assert evaluate([str(sweep), "--episodes", "3", "--no-progress"]) == 0
    assert report([str(sweep), "--no-trajectories"]) == 0
    table = (sweep / "report" / "table1.md").read_text()
    assert "| SAC |" in table and "| SAC-Lag |" in table
    assert "not finished" not in table

    # a job whose directory is gone (it never started) is named, not dropped
    import shutil

    shutil.rmtree(sweep / "1_sac_lag_tiny_seed0")
    assert evaluate([str(sweep), "--episodes", "3", "--no-progress"]) == 1
    assert report([str(sweep), "--no-trajectories", "--force"]) == 0
    table = (sweep / "report" / "table1.md").read_text()
    assert "| SAC-Lag |" not in table
    assert "## Sweep jobs not finished (1)" in table
    assert "| job 1 (+row=sac_lag) | missing |" in table


@needs_submitit
@pytest.mark.slow
def test_a_job_killed_with_sigterm_is_continued_by_the_same_sweep_command(tmp_path):
    sweep = tmp_path / "sweep"
    command = _sweep(sweep, "algo=sac", "seed=0", f"total_frames={FRAMES}", "epoch_frames=400")
    run_dir = sweep / "0_sac_tiny_seed0"
    first, stderr = _signal_job(command, tmp_path, run_dir, signal.SIGTERM)
    assert first.returncode != 0  # the sweep reports the stopped job ...
    assert "stopped by SIGTERM" in stderr
    stopped = load_checkpoint(run_dir / "checkpoints" / "last.pt")["frames"]
    assert 800 <= stopped < FRAMES  # ... which checkpointed mid-run
    [job] = sweep_jobs(sweep)
    assert job.status == "unfinished" and f"{stopped} of {FRAMES} frames" in job.detail

    again = _run(command, tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    _assert_continuous(run_dir, epochs=EPOCHS, epoch_frames=400)  # one continuous progress.csv
    assert (run_dir / "config.resume1.yaml").is_file()
    assert [job.status for job in sweep_jobs(sweep)] == ["finished"]


@needs_submitit
@pytest.mark.slow
def test_submitits_preemption_signal_requeues_the_job_which_resumes(tmp_path):
    """SLURM's signal before the time limit (submitit asks for USR2): the job checkpoints,
    submitit requeues it, and the requeued job continues from the checkpoint — all within
    the one sweep command, as on a cluster."""
    sweep = tmp_path / "sweep"
    command = _sweep(sweep, "algo=sac", "seed=0", f"total_frames={FRAMES}", "epoch_frames=400")
    run_dir = sweep / "0_sac_tiny_seed0"
    first, stderr = _signal_job(command, tmp_path, run_dir, signal.SIGUSR2)
    assert first.returncode == 0, stderr[-3000:]
    _assert_continuous(run_dir, epochs=EPOCHS, epoch_frames=400)
    assert (run_dir / "config.resume1.yaml").is_file()
    logs = "".join(p.read_text() for p in (sweep / ".submitit").rglob("*_log.out"))
    assert "SIGUSR2: checkpoint written to" in logs and "Requeued job" in logs


def _hydra_config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides), return_hydra_config=True)


@needs_submitit
def test_slurm_preset_asks_for_one_cpu_the_measured_memory_and_time(monkeypatch):
    monkeypatch.setenv("WCSAC_SLURM_PARTITION", "cpu_long")
    monkeypatch.delenv("WCSAC_SLURM_ACCOUNT", raising=False)
    cfg = _hydra_config("experiment=table1_static", "hydra/launcher=slurm")
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("SlurmLauncher")
    assert (launcher.cpus_per_task, launcher.tasks_per_node, launcher.nodes) == (1, 1, 1)
    assert launcher.mem_gb == 2 and launcher.timeout_min == 900
    assert launcher.max_num_timeout >= 1 and launcher.signal_delay_s >= 120
    assert launcher.partition == "cpu_long" and launcher.account is None
    assert cfg.threads == 1 and cfg.resume == "auto"
    # the experiment's sweep directory is named after it, not a timestamp, and each
    # job's after its run (row, env, seed), not its position among the command's jobs
    sweep = OmegaConf.to_container(cfg.hydra.sweep, resolve=False)
    assert sweep["subdir"] == "${run_name}"
    assert cfg.hydra.runtime.choices.experiment == "table1_static"
    for experiment in SWEEP_EXPERIMENTS:  # resolvable before Hydra's runtime exists
        assert _hydra_config(f"experiment={experiment}").hydra.sweep.dir == f"multirun/{experiment}"
    local = _hydra_config("experiment=table1_static", "hydra/launcher=slurm_local").hydra
    assert local.launcher._target_.endswith("LocalLauncher")
    assert local.launcher.cpus_per_task == 1
    dynamic = _hydra_config("experiment=table1_dynamic")
    assert dynamic.env.name == "dynamic" and dynamic.total_frames == 3_000_000
    assert dynamic.hydra.launcher.n_jobs == 2  # the default here: joblib, two at a time


def test_laptop_table_sweeps_hold_every_paper_row_on_two_seeds_with_kept_stages():
    paper_rows = {"sac", "sac_lag", "wcsac_0.9", "wcsac_0.5", "wcsac_0.1", "cpo", "random"}
    for experiment, env in (
        ("table1_static_laptop", "static"),
        ("table1_dynamic_laptop", "dynamic"),
    ):
        cfg = _hydra_config(f"experiment={experiment}")
        params = cfg.hydra.sweeper.params
        rows = set(params["+row"].split(","))
        assert paper_rows <= rows and rows - paper_rows == {"sac_lag_paper"}
        assert all((CONF / "row" / f"{row}.yaml").is_file() for row in rows)
        assert params.seed == "0,10"
        assert cfg.env.name == env and cfg.total_frames == 200_000
        assert list(cfg.keep_checkpoints_at) == [1, 10] and cfg.epoch_frames == 10_000
        assert cfg.threads == 1 and cfg.hydra.launcher.n_jobs == 2 and cfg.resume == "auto"
        assert cfg.hydra.runtime.choices.experiment == experiment


def test_training_safety_sweeps_hold_the_studys_rows_seeds_and_budgets():
    for experiment, env, rows, frames in (
        ("training_safety_static", "static", {"wcsac_0.1", "sac_lag"}, 200_000),
        ("training_safety_dynamic", "dynamic", {"wcsac_0.1", "wcsac_0.5", "sac_lag", "sac"}, 10**6),
    ):
        cfg = _hydra_config(f"experiment={experiment}")
        params = cfg.hydra.sweeper.params
        assert set(params["+row"].split(",")) == rows and params.seed == "0,10,20"
        assert cfg.env.name == env and cfg.total_frames == frames
        assert cfg.threads == 1 and cfg.hydra.launcher.n_jobs == 2 and cfg.resume == "auto"
    # a job longer than a working session continues with its replay buffer
    assert _hydra_config("experiment=training_safety_dynamic").save_replay_buffer is True


def test_the_evidence_sweep_holds_every_learning_row_on_three_seeds_and_the_control():
    cfg = _hydra_config("experiment=evidence_static")
    params = cfg.hydra.sweeper.params
    rows = params["+row"].split(",")
    assert {"sac", "sac_lag", "wcsac_0.9", "wcsac_0.5", "wcsac_0.1", "random"} <= set(rows)
    assert params.seed == "0,10,20" and cfg.total_frames == 200_000 and cfg.resume == "auto"
    for alpha, row in ((0.9, "sac_lag_d13.5"), (0.5, "sac_lag_d7.5"), (0.1, "sac_lag_d1.5")):
        assert row in rows
        job = _hydra_config("experiment=evidence_static", f"+row={row}", "seed=0")
        # the matched-mean control: SAC-Lag holding EC at α·d of the env's d = 15
        assert job.algo.name == "sac_lag" and job.cost_limit == pytest.approx(alpha * 15)
        assert job.algo.label == row and job.run_name == f"{row}_static_seed0"


@needs_ray
@pytest.mark.slow
def test_ray_local_instance_sweep(tmp_path):
    _two_job_sweep(tmp_path, "ray_cluster")  # (evaluate + report: the submitit test)


@needs_ray
@pytest.mark.slow
def test_ray_retries_a_run_whose_worker_was_killed_and_it_resumes(tmp_path):
    """A node loss: the worker dies at once (SIGKILL, nothing saved then); Ray starts the
    task again and the run continues from its last periodic checkpoint, all within the
    one sweep command (a second session of the run: config.resume1.yaml)."""
    sweep = tmp_path / "sweep"
    command = _sweep(
        sweep,
        "algo=sac",
        "seed=0",
        f"total_frames={FRAMES}",
        "epoch_frames=400",
        "checkpoint_every_epochs=1",
        launcher="ray_cluster",
    )
    run_dir = sweep / "0_sac_tiny_seed0"
    first, stderr = _signal_job(command, tmp_path, run_dir, signal.SIGKILL)
    assert first.returncode == 0, stderr[-3000:]
    _assert_continuous(run_dir, epochs=EPOCHS, epoch_frames=400)
    assert (run_dir / "config.resume1.yaml").is_file()


@needs_ray
def test_ray_preset_uses_a_given_cluster_or_a_local_instance_one_cpu_per_run(monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    ray = _hydra_config("experiment=table1_static", "hydra/launcher=ray_cluster").hydra.launcher
    assert ray._target_.endswith("RayLauncher")
    assert ray.ray.init.address is None  # a local instance
    assert ray.ray.init.object_store_memory is None  # refused with an address otherwise
    assert ray.ray.remote.num_cpus == 1 and ray.ray.remote.max_retries >= 1
    monkeypatch.setenv("RAY_ADDRESS", "ray://head:10001")
    ray = _hydra_config("experiment=table1_static", "hydra/launcher=ray_cluster").hydra.launcher
    assert ray.ray.init.address == "ray://head:10001"
