"""The C allocator's settings for a process that solves calibrations and ends (the CLI, the benchmarks).

A solve builds and drops arrays of a few to tens of MB many times over. With glibc's defaults each
one is either a fresh ``mmap`` or heap memory handed back to the system as soon as it is freed, so
every new array faults its pages in again: about 14,000 page faults (56 MB) per IMU-aided
calibration of 4,000 sets, a quarter of its time. Keeping freed memory in the process for reuse
removes them; the peak memory is unchanged. The nodes keep glibc's defaults: with the setting a calibration
node's resident memory grew by about 40 MB with each recalibration of a mission soak (its solves run in a
worker thread's arena), even with ``malloc_trim`` after each. Other C libraries: nothing is changed.
"""

from __future__ import annotations

import ctypes
from functools import cache

LARGEST_HEAP_BLOCK: int = 32 * 1024 * 1024
"""Bytes: blocks up to this size come from the reusable heap, larger ones straight from the system
(glibc's largest allowed threshold on 64-bit)."""

KEPT_FREE: int = 512 * 1024 * 1024
"""Bytes of freed memory at the heap's top kept for reuse before any is handed back to the system."""

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


@cache
def _glibc() -> ctypes.CDLL | None:
    """The C library when it is glibc (``mallopt`` exists), else None."""
    try:
        libc = ctypes.CDLL(None)  # the interpreter's own symbols, the C library's among them (no library search)
        return libc if hasattr(libc, "mallopt") else None
    except (OSError, TypeError):
        return None


@cache
def keep_freed_memory() -> bool:
    """Keep freed memory in the process for the next array instead of faulting fresh pages in (once per
    process; later calls do nothing). Returns whether the allocator took the settings."""
    libc = _glibc()
    if libc is None:
        return False
    return bool(libc.mallopt(_M_MMAP_THRESHOLD, LARGEST_HEAP_BLOCK)) and bool(libc.mallopt(_M_TRIM_THRESHOLD,
                                                                                          KEPT_FREE))

