"""Where a run's numbers came from: one ``provenance.json`` per training session.

A new run writes ``provenance.json`` beside its ``config.yaml``, each resumed session
its own ``provenance.resume<k>.json``: the code's commit (``dirty`` when tracked files
differed; an installed package's version otherwise), the command line's overrides, the
start time, host, threads, library versions and the machine (its CPU and the vector
instructions torch uses on it: docs/evaluation_protocol.md, "The machine is a source of
variation"). :func:`read_provenance` returns a run's records, first session first.
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
import socket
import subprocess
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

__all__ = [
    "PROVENANCE_FILE",
    "code_version",
    "machine_record",
    "provenance_files",
    "read_provenance",
    "session_provenance",
    "write_provenance",
]

PROVENANCE_FILE = "provenance.json"
LIBRARIES = ("torch", "torchrl", "tensordict", "numpy", "gymnasium", "mujoco", "hydra-core")
GIT_TIMEOUT_S = 10.0
_PACKAGE_DIR = Path(__file__).resolve().parents[1]


def _git(args: Sequence[str], cwd: Path) -> str | None:
    try:
        done = subprocess.run(
            ["git", *args],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):  # no git, or it hung
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def code_version(package_dir: Path = _PACKAGE_DIR) -> dict[str, Any]:
    """``{"commit", "dirty", "version"}`` of the code in ``package_dir``.

    ``commit`` is ``None`` when ``package_dir`` is not a tracked part of a git work
    tree (an installed wheel, also one in a virtualenv inside another project's
    repository) or git is missing; ``dirty`` is whether tracked files differ from that
    commit (untracked files are not counted), ``None`` when unknown.
    """
    tracked = _git(["ls-files", "--error-unmatch", "__init__.py"], package_dir)
    commit = None if tracked is None else _git(["rev-parse", "HEAD"], package_dir)
    dirty = None
    if commit is not None:
        status = _git(["status", "--porcelain", "--untracked-files=no"], package_dir)
        dirty = None if status is None else bool(status)
    try:
        version = metadata.version("wcsac_rl")
    except metadata.PackageNotFoundError:
        version = None
    return {"commit": commit, "dirty": dirty, "version": version}


def _library_versions() -> dict[str, str | None]:
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def _cpu_model() -> str | None:
    """The CPU's model name (``/proc/cpuinfo`` on Linux, else ``platform.processor()``),
    ``None`` when neither names it."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or None


def machine_record() -> dict[str, str | None]:
    """``{"processor", "architecture", "cpu_capability"}`` of this machine (see the
    module docstring)."""
    try:
        import torch

        capability = str(torch.backends.cpu.get_cpu_capability())
    except (ImportError, AttributeError, RuntimeError):
        capability = None
    return {
        "processor": _cpu_model(),
        "architecture": platform.machine() or None,
        "cpu_capability": capability,
    }


def session_provenance(
    *, overrides: Sequence[str] | None, threads: int, resumed_from_frames: int | None
) -> dict[str, Any]:
    """The record of the session starting now (see the module docstring)."""
    return {
        "code": code_version(),
        "overrides": None if overrides is None else [str(o) for o in overrides],
        "resumed_from_frames": resumed_from_frames,
        "started": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "host": socket.gethostname(),
        "threads": int(threads),
        "versions": _library_versions(),
        "machine": machine_record(),
    }


def provenance_files(run_dir: Path) -> list[Path]:
    """``provenance.json`` then ``provenance.resume1.json``, ... (those that exist)."""
    run_dir = Path(run_dir)
    files = [run_dir / PROVENANCE_FILE] if (run_dir / PROVENANCE_FILE).is_file() else []
    k = 1
    while (path := run_dir / f"provenance.resume{k}.json").is_file():
        files.append(path)
        k += 1
    return files


def write_provenance(run_dir: Path, record: dict[str, Any], *, resumed: bool) -> Path:
    """Write ``record`` as the run's first session's file or, ``resumed``, as the next
    free ``provenance.resume<k>.json`` (also for a run begun before sessions recorded
    their provenance: its first session's record stays missing, not mislabelled)."""
    from wcsac_rl.training.run_dir import replace_text  # (run_dir imports config only)

    run_dir = Path(run_dir)
    path = run_dir / PROVENANCE_FILE
    if resumed:
        k = 1
        while (path := run_dir / f"provenance.resume{k}.json").exists():
            k += 1
    replace_text(path, json.dumps(record, indent=2) + "\n")
    return path


def read_provenance(run_dir: Path) -> list[dict[str, Any]]:
    """The run's session records, first session first; a file that is not a JSON
    object (a half-written or hand-edited one) is skipped."""
    from wcsac_rl.training.safe_load import load_json  # (torch: only when reading)

    records = []
    for path in provenance_files(run_dir):
        try:
            record = load_json(path)
        except (OSError, ValueError):
            continue
        if isinstance(record, dict):
            records.append(record)
    return records
