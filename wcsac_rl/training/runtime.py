"""Process-level settings for fast CPU training."""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["retain_freed_memory"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def retain_freed_memory(mmap_threshold: int = 256 << 20, trim_threshold: int = 1 << 30) -> bool:
    """Make glibc's ``malloc`` keep freed memory in the process for reuse: blocks below
    ``mmap_threshold`` come from the heap, which is trimmed only above ``trim_threshold``
    of free memory, so the update's ~1 MB activations stop paying page faults on fresh
    ``mmap``s (docs/performance.md; the price: up to ``trim_threshold`` of freed memory
    kept). Returns whether the settings were applied (``False`` without glibc, e.g. on
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
