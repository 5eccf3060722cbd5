"""Process-level settings for fast CPU training."""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["retain_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def retain_freed_memory(mmap_threshold: int = 256 << 20, trim_threshold: int = 1 << 30) -> bool:
    """Make glibc's ``malloc`` keep freed memory in the process for reuse.

    The WCSAC update allocates and frees dozens of 0.25–1 MB activation tensors;
    with glibc's default (dynamic) thresholds many of them are ``mmap``-ed and
    returned to the OS on free, so every update pays page faults on fresh pages.
    Serving blocks below ``mmap_threshold`` from the heap and trimming the heap
    only above ``trim_threshold`` of free memory makes the update ~4% faster on
    this CPU (``benchmarks/bench_update.py``); the price is that the process keeps
    up to ``trim_threshold`` of freed memory instead of returning it.

    Returns whether the settings were applied (``False`` without glibc, e.g. on
    macOS or musl, where nothing changes).
    """
    if mmap_threshold <= 0 or trim_threshold <= 0:
        raise ValueError(
            f"thresholds must be positive byte counts, got {mmap_threshold} and {trim_threshold}"
        )
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018  (glibc only)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(
        mallopt(_M_TRIM_THRESHOLD, int(trim_threshold))
    )
