"""Process memory: keep freed frame buffers in the process instead of handing them back to the kernel.

Both programs make and free large arrays every frame: the sender's are megabytes (12 MB at 1920x2160), the
receiver's 0.2-3 MB (the frame, its lightness, the dense way's images), freed a few frames later. glibc's malloc
serves such blocks with ``mmap`` and returns them with ``munmap`` until a free raises its (dynamic) threshold, and
trims the top of a heap back to the kernel whenever more than twice that threshold is free there. Each time memory
goes back, the next frame's pages are faulted in again, zeroed, at their first write: on a virtual machine tens of
milliseconds for one 1920x2160 pair of phases, more than a 60 Hz frame can spare; in the receiver ~10 000 page
faults a 960-frame replay at 640x360, 0.1-0.5 s of its system time (docs/receiver-cores.md, stop 64).

:func:`keep_freed_memory` fixes both thresholds (``mallopt``), so that blocks up to ``largest_block_bytes``
come from the heap and freed ones stay there for the next frame (the peak memory is the same: the heap keeps only
what the process had in use at once), and :func:`warm` faults in a thread's working set before its deadlines start.
Where the C library is not glibc (no ``mallopt``, or it refuses), or the user's ``MALLOC_MMAP_THRESHOLD_`` /
``MALLOC_TRIM_THRESHOLD_`` environment variables already say otherwise, it does nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys
from typing import Final

_M_TRIM_THRESHOLD: Final = -1
_M_MMAP_THRESHOLD: Final = -3
MMAP_THRESHOLD_MAX: Final = 32 * 1024 * 1024
"""glibc's largest allowed ``M_MMAP_THRESHOLD`` on 64-bit systems (``HEAP_MAX_SIZE / 2``)."""
KEEP_BYTES: Final = 128 * 1024 * 1024
"""The receiver's choice: up to this much free heap kept for the next frames."""
USER_SETTINGS: Final = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
"""The environment variables by which glibc takes these settings from the user (read at the process's start)."""


def keep_freed_memory(largest_block_bytes: int = MMAP_THRESHOLD_MAX, keep_bytes: int = KEEP_BYTES) -> bool:
    """Serve blocks up to ``largest_block_bytes`` from the heap and keep up to ``keep_bytes`` of freed memory, for
    this process and those it forks (the defaults: the receiver's). Returns whether it took effect (glibc only, and
    not where the user set :data:`USER_SETTINGS`; ``largest_block_bytes`` is capped at :data:`MMAP_THRESHOLD_MAX`).
    """
    if not sys.platform.startswith("linux") or any(name in os.environ for name in USER_SETTINGS):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # (the C library this process already runs on)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    threshold = min(max(largest_block_bytes + 4096, 128 * 1024), MMAP_THRESHOLD_MAX)
    keep = min(max(keep_bytes, threshold), 2**31 - 1)
    # Both, in this order: setting the trim threshold alone stops glibc's adapting, and every large block is mapped.
    return bool(mallopt(_M_MMAP_THRESHOLD, threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, keep))


def warm(shape: tuple[int, ...], count: int) -> None:
    """Allocate ``count`` uint8 arrays of ``shape`` at once, write each page, and free them: run in a thread
    before its deadlines start, so that its heap already holds faulted-in memory for that many frames."""
    import numpy as np  # (here: ipt-receiver imports this module before it limits numpy's BLAS threads, which
    # would stop its AprilTag helper's fork: tests/test_startup.py)

    arrays = [np.empty(shape, np.uint8) for _ in range(count)]
    for a in arrays:
        a.fill(0)
    del arrays
