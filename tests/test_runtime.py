"""``retain_freed_memory``: large blocks come from the heap, not from fresh mmaps."""

from __future__ import annotations

import ctypes
import ctypes.util

import pytest
import torch

from wcsac_rl.training.runtime import retain_freed_memory


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd",
            "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost",
        )
    ]  # fmt: skip


def _mallinfo2():
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    try:
        fn = libc.mallinfo2
    except AttributeError:
        pytest.skip("no glibc mallinfo2 (glibc < 2.33 or not glibc)")
    fn.restype = _MallInfo2
    return fn()


def test_large_tensors_are_served_from_the_heap_after_the_call():
    assert retain_freed_memory() is True  # this machine runs glibc
    mmapped_before = _mallinfo2().hblkhd
    # 64 MB: above glibc's largest dynamic mmap threshold (32 MB), so by default it
    # would be mmap-ed (and unmapped on free); with the setting it comes from the heap
    block = torch.empty(16 << 20, dtype=torch.float32)
    assert _mallinfo2().hblkhd == mmapped_before
    del block


def test_bad_thresholds_are_refused():
    with pytest.raises(ValueError, match="positive byte counts"):
        retain_freed_memory(mmap_threshold=0)
