"""Command-line options the console scripts share (``wcsac-evaluate``, ``wcsac-calibration``,
``wcsac-report``): defined once, so their flags and refusals read the same everywhere.
Imports nothing heavy: ``--help`` is answered before torch is imported."""

from __future__ import annotations

import argparse

__all__ = ["SEED_MAX", "add_trust_env_code", "check_seed", "check_threads", "machine_cores"]

SEED_MAX = 2**63 - 1
"""The largest seed: torch seeds are 64-bit, and a run seeds its envs and collector with
``seed`` plus offsets (frames, env indices)."""


def add_trust_env_code(parser: argparse.ArgumentParser) -> None:
    """``--trust-env-code``: import the env code a run of ``env=gymnasium`` names."""
    parser.add_argument(
        "--trust-env-code",
        action="store_true",
        help=(
            "import and call the env code (env.id=module:callable, with env.kwargs) that a "
            "run of env=gymnasium names in its files; without it such a run is refused, "
            "nothing imported (a run directory is untrusted input: docs/guarantees.md)"
        ),
    )


def check_seed(parser: argparse.ArgumentParser, option: str, value: int) -> None:
    """Refuse a seed option outside ``[0, SEED_MAX]`` in one line naming ``option``."""
    if not 0 <= value <= SEED_MAX:
        parser.error(f"{option} must be a whole number in [0, 2**63 - 1], got {value}")


def machine_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS tells it)."""
    import os

    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # (not Linux)
        return max(1, os.cpu_count() or 1)


def check_threads(parser: argparse.ArgumentParser, value: int) -> None:
    """Refuse ``--threads`` below 1 or above the cores this process may run on, in one
    line (torch threads beyond the cores only wait for each other)."""
    cores = machine_cores()
    if not 1 <= value <= cores:
        parser.error(
            f"--threads must be a whole number in [1, {cores}] (this machine's cores), got {value}"
        )
