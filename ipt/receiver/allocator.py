"""The C allocator told to keep the memory a frame frees for the next frame (glibc's ``mallopt``).

Each frame brings arrays of 0.2-3 MB (the frame, its lightness, the dense way's images) that are freed a few frames
later. glibc serves blocks that large from the heap once one has been freed (its mapping threshold adapts), but
gives the heap's free top back to the kernel whenever more than twice that block is free there, and the next
frame's arrays fault the same pages in again, zeroed: ~10 000 page faults a 960-frame replay at 640x360, ~12 000 at
1280x720, 0.1-0.5 s of the process's system time (docs/receiver-cores.md, stop 64). :func:`keep_freed_memory`
fixes both thresholds instead: blocks up to :data:`MMAP_THRESHOLD_BYTES` from the heap, and up to
:data:`TRIM_THRESHOLD_BYTES` of free heap kept. The peak memory is the same (the heap only keeps what the process
had in use at once); nothing else changes. Where the C library is not glibc (its ``mallopt`` absent or refusing), or
the ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_`` environment variables already say otherwise, nothing
is done.
"""

from __future__ import annotations

import ctypes
import os
import sys

#: ``mallopt``'s parameter numbers (glibc's ``malloc.h``).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
#: Blocks up to this size come from the heap (glibc's own adaptive threshold stops at this size too).
MMAP_THRESHOLD_BYTES = 32 * 2**20
#: Free memory at the heap's top up to this size is kept for the next frames.
TRIM_THRESHOLD_BYTES = 128 * 2**20
#: Environment variables by which glibc takes these settings from the user (read at the process's start).
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")


def keep_freed_memory() -> bool:
    """Set the two thresholds for this process (and the processes it forks): whether they were set."""
    if not sys.platform.startswith("linux") or any(name in os.environ for name in USER_SETTINGS):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # (the C library this process already runs on)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # Both, in this order: setting either one alone stops glibc's adapting, and then every large block is mapped.
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
