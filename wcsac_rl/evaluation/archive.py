"""A run's records without its checkpoints: what a results folder keeps of a run.

``python -m wcsac_rl.report --archive`` copies them for every reported run;
``python -m wcsac_rl.evaluate --archive DIR`` copies them as soon as each run is
evaluated, so a study whose run directories may not last (a cluster's scratch space,
a machine that is reset) keeps each finished run's records. A report of the archive
alone makes the same Table 1, training-safety table and Figures 4 and 6 as a report of
the runs themselves (no Figure 5: it needs the checkpoints).
"""

from __future__ import annotations

import filecmp
import os
from pathlib import Path

from wcsac_rl.evaluation.runs import EVALUATION_CSV, EVALUATION_JSON
from wcsac_rl.training.config import ConfigError
from wcsac_rl.training.run_dir import replace_file

__all__ = ["ARCHIVED_FILES", "ArchiveError", "archive_run", "archived_records", "needs_copy"]

ARCHIVED_FILES = (
    EVALUATION_JSON,
    EVALUATION_CSV,
    "config.yaml",
    "config.resume*.yaml",
    "provenance*.json",
    "progress.csv",
    "calibration.json",
)
"""What an archived run keeps (names and glob patterns): enough to make the table,
``runs.md`` and Figures 4 and 6 again (no checkpoint, so no Figure 5, and no replay
buffer), and the safety critic's calibration when ``python -m wcsac_rl.calibration``
measured it."""


class ArchiveError(ConfigError):
    """A run's records cannot be archived as asked; the message says why."""


def archived_records(directory: Path) -> list[Path]:
    """The files of run ``directory`` that an archive keeps (:data:`ARCHIVED_FILES`)."""
    directory = Path(directory)
    return [
        path
        for pattern in ARCHIVED_FILES
        for path in sorted(directory.glob(pattern))
        if path.is_file()
    ]


def needs_copy(source: Path, target: Path) -> bool:
    """Whether archiving ``source`` to ``target`` would write anything: ``target`` is
    missing, or holds other bytes."""
    return not (target.is_file() and filecmp.cmp(source, target, shallow=False))


def archive_run(directory: Path, archive_dir: Path, *, force: bool = False) -> Path:
    """Copy the records of run ``directory`` into ``archive_dir/<its name>`` and return
    that folder. Files already there with the same bytes are left as they are; a file
    there with other bytes (a run evaluated again, or trained further) is replaced only
    with ``force`` — otherwise :class:`ArchiveError`, before anything is copied.
    """
    directory = Path(directory)
    records = archived_records(directory)
    if not any(path.name == EVALUATION_JSON for path in records):
        raise ArchiveError(f"{directory}: not evaluated (no {EVALUATION_JSON}): nothing to archive")
    target = Path(archive_dir).expanduser() / directory.resolve().name
    if target.is_symlink() or (target.exists() and not target.is_dir()):
        what = f"a symbolic link (to {os.readlink(target)})" if target.is_symlink() else "a file"
        raise ArchiveError(
            f"{target} is {what}; an archived run's records go into a folder of its own: "
            "remove it or archive elsewhere"
        )
    # the records not already there byte for byte; of those, the ones there with other bytes
    pending = [path for path in records if needs_copy(path, target / path.name)]
    differing = [path.name for path in pending if (target / path.name).is_file()]
    if differing and not force:
        raise ArchiveError(
            f"{target} already has other {', '.join(differing)} (another evaluation or a "
            "longer run of that name); pass --force to replace them"
        )
    target.mkdir(parents=True, exist_ok=True)
    for path in pending:
        replace_file(target / path.name, path.read_bytes())
    return target
