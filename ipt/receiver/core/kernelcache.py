"""Whether the receiver's kernels (:mod:`ipt.receiver.core.kernels`) run compiled, and from numba's disk cache.

On the drone the kernels must neither fall back to numpy (5× slower: a sandbox that forbids executable
memory, or numba missing) nor compile in flight (seconds on a Pi before the first pose). ``ipt-receiver warm``
compiles them once into numba's cache (``NUMBA_CACHE_DIR``; the systemd unit gives it
``/var/cache/ipt-receiver``) and says so; ``replay`` and ``run`` report the same line at their end, with the
cache hits and misses of that process: after a warm, a new process loads every kernel (hits) and compiles
none (0 misses).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import os
import platform
import sys
from dataclasses import dataclass
from pathlib import Path

STAMP_NAME = "ipt-receiver-warm.stamp"
"""The file ``ipt-receiver warm`` leaves in ``$NUMBA_CACHE_DIR`` once every kernel is cached: what it was
cached for (:func:`stamp_text`). While it matches, a later ``warm`` (the unit's ExecStartPre, at every start
and restart) returns at once instead of importing numba and loading every kernel (half a second here, more
on a Pi, added to the time poses take to resume after a crash)."""


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
    loaded: bool = True
    """False: this process has not loaded its kernels yet (it stopped before its first frame pair)."""

    def line(self) -> str:
        """One line for a log or a terminal."""
        if not self.loaded:
            return "kernels: not loaded yet (the process stopped before its first frame pair)"
        if not self.compiled:
            return f"kernels: NOT compiled, running numpy/Python fallbacks (5x slower): {self.reason}"
        where = f"cache {self.cache_dir}" if self.cache_dir else f"NO disk cache ({self.reason})"
        return f"kernels: compiled, {where}, {self.hits} loaded from the cache, {self.misses} compiled"


def status() -> KernelStatus:
    """The kernels' state in this process now (after :func:`ipt.receiver.core.kernels.ensure`)."""
    from ipt.receiver.core import kernels

    if not kernels._ready.is_set():
        return KernelStatus(False, None, 0, 0, None, loaded=False)
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


def stamp_text() -> str:
    """What the cached kernels depend on: the receiver core's sources (the kernels and whatever defines
    more of them there), numba's and llvmlite's versions, Python's version and the processor's kind."""
    digest = hashlib.sha256()
    core = Path(__file__).resolve().parent  # ipt.receiver.core (this module's folder), without importing numpy
    for source in sorted(core.glob("*.py")):
        digest.update(source.name.encode() + b"\0" + source.read_bytes())
    versions = [f"{name} {importlib.metadata.version(name)}" for name in ("numba", "llvmlite")]
    return "\n".join([f"sources {digest.hexdigest()}", *versions, f"python {sys.version}", platform.machine(), ""])


def _stamp_path() -> Path | None:
    folder = os.environ.get("NUMBA_CACHE_DIR")
    return Path(folder) / STAMP_NAME if folder else None


def already_warm() -> bool:
    """Whether ``$NUMBA_CACHE_DIR`` holds the stamp of a complete warm for exactly this installation."""
    stamp = _stamp_path()
    try:
        return stamp is not None and stamp.read_text(encoding="utf-8") == stamp_text()
    except (OSError, UnicodeDecodeError, importlib.metadata.PackageNotFoundError):
        return False


def warm() -> KernelStatus:
    """Compile every kernel into numba's disk cache (or load it from there) and say how it went; leaves the
    stamp of :func:`already_warm` when every kernel is compiled and cached."""
    from ipt.receiver.core import kernels

    kernels.ensure()
    kernels.warm()
    kernels.warm_sparse()
    result = status()
    stamp = _stamp_path()
    if result.compiled and result.cache_dir and stamp is not None:
        with contextlib.suppress(OSError):  # only the next start's shortcut is lost
            stamp.write_text(stamp_text(), encoding="utf-8")
    return result


def compile_bytecode() -> bool:
    """Compile ipt's own modules to bytecode (``__pycache__`` beside each source, as ``pip install`` does for a
    regular installation), so that no start of the daemon compiles them (a tenth of a second here, more on a
    Pi). Not when Python is told not to write bytecode (``PYTHONDONTWRITEBYTECODE``, ``-B``); a folder that
    cannot be written (a read-only installation, compiled by pip already) is left as it is. Whether every
    module now has its bytecode."""
    if sys.dont_write_bytecode:
        return False
    import compileall

    package = Path(__file__).resolve().parents[2]  # ipt/ (this module is ipt/receiver/core/kernelcache.py)
    with open(os.devnull, "w", encoding="utf-8") as quiet, contextlib.redirect_stdout(quiet):
        return bool(compileall.compile_dir(package, quiet=2))


def cache_env_hint() -> str:
    """Where numba's cache is configured to go, for messages: ``$NUMBA_CACHE_DIR`` or its default."""
    configured = os.environ.get("NUMBA_CACHE_DIR")
    return f"NUMBA_CACHE_DIR={configured}" if configured else "NUMBA_CACHE_DIR unset (numba's default places)"
