"""What became of each job of a sweep, whichever launcher ran it.

Every Hydra multirun writes ``<sweep dir>/multirun.yaml`` and one directory per job
holding ``.hydra/overrides.yaml``. :func:`sweep_jobs` expands the sweep as Hydra's basic
sweeper does and matches each job to its directory by its overrides, so a job that never
started is named too (docs/reproduce.md). A job's status:

==============  =============================================================
``running``     a live process holds the run directory's lock
                (:func:`~wcsac_rl.training.run_dir.lock_holder`)
``finished``    ``checkpoints/last.pt`` at ``total_frames`` or more, or no
                checkpoint but an ``evaluation.json``
``unfinished``  a checkpoint before ``total_frames`` (``resume=auto`` continues it)
``failed``      a directory without a checkpoint
``missing``     no directory: the job never started
==============  =============================================================

Sweeps with another sweeper (Optuna, ...) cannot be expanded: their job directories
are still classified, and no job is reported missing.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from omegaconf import OmegaConf

from wcsac_rl.training.checkpoint import CHECKPOINT_DIR, LAST_CHECKPOINT
from wcsac_rl.training.safe_load import load_yaml

__all__ = [
    "MULTIRUN_YAML",
    "SweepJob",
    "all_sweep_jobs",
    "find_sweep_roots",
    "incomplete_jobs",
    "sweep_jobs",
]

MULTIRUN_YAML = "multirun.yaml"
BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"


@dataclass
class SweepJob:
    """One job of a sweep: its number, overrides, directory (if any) and status."""

    sweep: Path
    num: int | None
    overrides: list[str]
    directory: Path | None
    status: str  # running | finished | unfinished | failed | missing
    detail: str = ""
    swept: list[str] | None = None  # its values of the swept keys (``+row=sac seed=10``)

    @property
    def name(self) -> str:
        """The job's directory name, or its number and swept values when it has none."""
        if self.directory is not None:
            return self.directory.name
        return f"job {self.num} ({' '.join(self.swept or self.overrides)})"

    @property
    def complete(self) -> bool:
        return self.status == "finished"

    @property
    def has_checkpoint(self) -> bool:
        from wcsac_rl.evaluation.runs import has_checkpoint

        return self.directory is not None and has_checkpoint(self.directory)

    def describe(self) -> str:
        """One line: ``<sweep>: <name> <status>: <detail>``."""
        return f"{self.sweep}: {self.name} {self.status}" + (
            f": {self.detail}" if self.detail else ""
        )


def find_sweep_roots(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Directories at or below ``paths`` holding ``multirun.yaml`` (sorted, unique)."""
    found: list[Path] = []
    for raw in paths:
        path = Path(raw).expanduser()
        if not path.is_dir():
            continue
        for dirpath, dirnames, filenames in os.walk(path):
            dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
            if MULTIRUN_YAML in filenames:
                found.append(Path(dirpath))
                dirnames[:] = []  # jobs below a sweep are not sweeps
    return sorted(dict.fromkeys(p.resolve() for p in found))


def expected_overrides(multirun: Path) -> list[tuple[list[str], list[str]]] | None:
    """Each job's overrides and, of those, its values of the swept keys, in job order, as
    Hydra's basic sweeper makes them from ``multirun.yaml`` (``None``: another sweeper,
    which cannot be expanded)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    cfg = load_yaml(multirun)
    sweeper = OmegaConf.select(cfg, "hydra.sweeper", default=None)
    if sweeper is None or sweeper.get("_target_") != BASIC_SWEEPER:
        return None
    params = sweeper.get("params") or {}
    arguments = [f"{key}={value}" for key, value in params.items()]
    arguments += list(OmegaConf.select(cfg, "hydra.overrides.task", default=None) or [])
    parsed = OverridesParser.create().parse_overrides(arguments)
    swept = {o.get_key_element() for o in parsed if o.is_sweep_override()}
    batches = BasicSweeper.split_arguments(parsed, None)
    return [
        (list(job), [o for o in job if o.split("=", 1)[0] in swept])
        for batch in batches
        for job in batch
    ]


def _job_dirs(root: Path) -> dict[tuple[str, ...], Path]:
    """Job directories below a sweep root, by their overrides (``.hydra/overrides.yaml``)."""
    jobs: dict[tuple[str, ...], Path] = {}
    for dirpath, dirnames, _files in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d not in (".submitit", CHECKPOINT_DIR))
        if ".hydra" in dirnames and (Path(dirpath) / ".hydra" / "overrides.yaml").is_file():
            overrides = load_yaml(Path(dirpath) / ".hydra" / "overrides.yaml")
            jobs.setdefault(tuple(str(o) for o in overrides), Path(dirpath))
            dirnames[:] = []
    return jobs


def _classify(directory: Path) -> tuple[str, str]:
    """``(status, detail)`` of a job directory (see the module's table)."""
    from wcsac_rl.evaluation.runs import EVALUATION_JSON
    from wcsac_rl.training.checkpoint import load_checkpoint
    from wcsac_rl.training.config import ConfigError
    from wcsac_rl.training.run_dir import lock_holder

    checkpoint = directory / CHECKPOINT_DIR / LAST_CHECKPOINT
    holder = lock_holder(directory)
    if holder is not None:
        return "running", f"training ({holder})"
    if not checkpoint.is_file():
        evaluation = directory / EVALUATION_JSON
        if evaluation.is_file():
            return "finished", f"no checkpoint, but evaluated ({EVALUATION_JSON})"
        return "failed", (
            f"no checkpoint ({CHECKPOINT_DIR}/{LAST_CHECKPOINT}): it ended before its first "
            "one or on an error; see its train.log and the launcher's logs"
        )
    try:
        state = load_checkpoint(checkpoint)
    except ConfigError as err:
        return "failed", str(err)
    frames = int(state["frames"])
    total = int(state["config"].get("total_frames", 0))
    if frames < total:
        return "unfinished", (
            f"checkpoint at {frames} of {total} frames; run the sweep command again to "
            "continue it (resume=auto); if it stopped on an error (its train.log, the "
            "launcher's logs), fix that first"
        )
    return "finished", f"{frames} frames"


def sweep_jobs(root: str | os.PathLike) -> list[SweepJob]:
    """Every job of the sweep at ``root`` (the directory holding ``multirun.yaml``), in job
    order, each with its status; jobs found on disk that the sweep does not list (an
    earlier sweep into the same directory) come last."""
    root = Path(root).expanduser().resolve()
    found = _job_dirs(root)
    expected = expected_overrides(root / MULTIRUN_YAML)
    jobs: list[SweepJob] = []
    seen: set[tuple[str, ...]] = set()
    for num, (overrides, swept) in enumerate(expected or []):
        key = tuple(overrides)
        seen.add(key)
        directory = found.get(key)
        if directory is None:
            status, detail = "missing", "no run directory: it never started"
        else:
            status, detail = _classify(directory)
        jobs.append(SweepJob(root, num, overrides, directory, status, detail, swept))
    for key, directory in sorted(found.items(), key=lambda item: str(item[1])):
        if key not in seen:
            status, detail = _classify(directory)
            jobs.append(SweepJob(root, None, list(key), directory, status, detail))
    return jobs


def all_sweep_jobs(paths: Iterable[str | os.PathLike]) -> list[SweepJob]:
    """The jobs of every sweep at or below ``paths``."""
    return [job for root in find_sweep_roots(paths) for job in sweep_jobs(root)]


def incomplete_jobs(paths: Iterable[str | os.PathLike]) -> list[SweepJob]:
    """The jobs of every sweep at or below ``paths`` that are not ``finished``."""
    return [job for job in all_sweep_jobs(paths) if not job.complete]
