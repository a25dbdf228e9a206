"""Process memory: keep freed frame buffers in the process instead of handing them back to the kernel.

Every frame array the sender makes is megabytes (12 MB at 1920x2160). glibc's malloc serves such blocks
with ``mmap`` and returns them with ``munmap`` until a free raises its (dynamic) threshold, and trims the
top of a heap back to the kernel when more than a threshold is free there. Each time memory goes back,
the next frame's pages are faulted in again at their first write; on a virtual machine the first touch
of a page costs most (tens of milliseconds for one 1920x2160 pair of phases), which is more than a 60 Hz
frame can spare.

:func:`keep_freed_memory` fixes both thresholds (``mallopt``), so that blocks up to ``largest_block_bytes``
come from the heap and freed ones stay there for the next frame, and :func:`warm` faults in a thread's
working set before its deadlines start. On a C library other than glibc it does nothing. (The receiver
does not use it: its frames are small, and a trial in its daemon changed nothing measurable.)
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from typing import Final

import numpy as np

_M_TRIM_THRESHOLD: Final = -1
_M_MMAP_THRESHOLD: Final = -3
MMAP_THRESHOLD_MAX: Final = 32 * 1024 * 1024
"""glibc's largest allowed ``M_MMAP_THRESHOLD`` on 64-bit systems (``HEAP_MAX_SIZE / 2``)."""


def keep_freed_memory(largest_block_bytes: int, keep_bytes: int) -> bool:
    """Serve blocks up to ``largest_block_bytes`` from the heap and keep up to ``keep_bytes`` of freed memory.

    Returns whether it took effect (glibc only; ``largest_block_bytes`` is capped at
    :data:`MMAP_THRESHOLD_MAX`).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    threshold = min(max(largest_block_bytes + 4096, 128 * 1024), MMAP_THRESHOLD_MAX)
    keep = min(max(keep_bytes, threshold), 2**31 - 1)
    return bool(mallopt(_M_MMAP_THRESHOLD, threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, keep))


def warm(shape: tuple[int, ...], count: int) -> None:
    """Allocate ``count`` uint8 arrays of ``shape`` at once, write each page, and free them: run in a thread
    before its deadlines start, so that its heap already holds faulted-in memory for that many frames."""
    arrays = [np.empty(shape, np.uint8) for _ in range(count)]
    for a in arrays:
        a.fill(0)
    del arrays
