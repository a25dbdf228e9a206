"""Whether the receiver's kernels (:mod:`ipt.receiver.core.kernels`) run compiled, and from numba's disk cache.

On the drone the kernels must neither fall back to numpy (5× slower: a sandbox that forbids executable
memory, or numba missing) nor compile in flight (seconds on a Pi before the first pose). ``ipt-receiver warm``
compiles them once into numba's cache (``NUMBA_CACHE_DIR``; the systemd unit gives it
``/var/cache/ipt-receiver``) and says so; ``replay`` and ``run`` report the same line at their end, with the
cache hits and misses of that process: after a warm, a new process loads every kernel (hits) and compiles
none (0 misses).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

from ipt.receiver.core import kernels


@dataclass(frozen=True)
class KernelStatus:
    """The kernels of this process: compiled or not, cached or not, and numba's cache counts."""

    compiled: bool
    cache_dir: str | None
    """The folder numba's cache files of the kernels are in (None: no cache, or not compiled)."""
    hits: int
    """Kernel versions loaded from the disk cache in this process."""
    misses: int
    """Kernel versions compiled in this process (none after ``ipt-receiver warm``)."""
    reason: str | None
    """Why the kernels are not compiled or not cached, or None when they are both."""

    def line(self) -> str:
        """One line for a log or a terminal."""
        if not self.compiled:
            return f"kernels: NOT compiled, running numpy/Python fallbacks (5x slower): {self.reason}"
        where = f"cache {self.cache_dir}" if self.cache_dir else f"NO disk cache ({self.reason})"
        return f"kernels: compiled, {where}, {self.hits} loaded from the cache, {self.misses} compiled"


def status() -> KernelStatus:
    """The kernels' state in this process now (after :func:`ipt.receiver.core.kernels.ensure`)."""
    if not kernels.COMPILED:
        return KernelStatus(False, None, 0, 0, kernels.NOT_COMPILED_BECAUSE or "numba is unavailable")
    hits = misses = 0
    cache_dir: str | None = None
    for dispatcher in kernels._dispatchers:
        stats = dispatcher.stats
        hits += sum(stats.cache_hits.values())
        misses += sum(stats.cache_misses.values())
        if stats.cache_path and cache_dir is None:
            cache_dir = str(stats.cache_path)
    if kernels.NOT_CACHED_BECAUSE is not None:
        cache_dir = None
    return KernelStatus(True, cache_dir, hits, misses, kernels.NOT_CACHED_BECAUSE)


def warm() -> KernelStatus:
    """Compile every kernel into numba's disk cache (or load it from there) and say how it went."""
    kernels.ensure()
    kernels.warm()
    return status()


def cache_env_hint() -> str:
    """Where numba's cache is configured to go, for messages: ``$NUMBA_CACHE_DIR`` or its default."""
    configured = os.environ.get("NUMBA_CACHE_DIR")
    return f"NUMBA_CACHE_DIR={configured}" if configured else "NUMBA_CACHE_DIR unset (numba's default places)"
