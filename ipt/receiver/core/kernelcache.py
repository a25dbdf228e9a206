"""Whether the receiver's kernels (:mod:`ipt.receiver.core.kernels`) run compiled, and from numba's disk cache.

On the drone the kernels must neither fall back to numpy (5× slower: a sandbox that forbids executable
memory, or numba missing) nor compile in flight (seconds on a Pi before the first pose). ``ipt-receiver warm``
compiles them once into numba's cache (``NUMBA_CACHE_DIR``; the systemd unit gives it
``/var/cache/ipt-receiver``), then builds them ahead of time into a module there that later processes load
without numba (:mod:`~ipt.receiver.core.kernelbuild`), and says so; ``replay`` and ``run`` report the same
line at their end: the module they loaded, or the cache hits and misses of that process (after a warm, a new
process loads every kernel (hits) and compiles none (0 misses)).
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ipt.receiver.core.kernelstamp import stamp_text

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
    ahead: str | None = None
    """The module the kernels were loaded from, built ahead of time (:mod:`~ipt.receiver.core.kernelbuild`), or
    None: numba's."""
    not_fitting: int = 0
    """Calls that went to numba although the kernels were built ahead (their arguments were not as built)."""
    build: str | None = None
    """``ipt-receiver warm``'s ahead-of-time build: where it put the module, or why it did not build one."""

    def line(self) -> str:
        """One line for a log or a terminal."""
        if not self.loaded:
            return "kernels: not loaded yet (the process stopped before its first frame pair)"
        if self.ahead is not None:
            calls = f"{self.not_fitting} call{'' if self.not_fitting == 1 else 's'}"
            odd = f", {calls} not as built went to numba" if self.not_fitting else ""
            return f"kernels: built ahead of time, loaded from {self.ahead} (numba not needed){odd}"
        if not self.compiled:
            return f"kernels: NOT compiled, running numpy/Python fallbacks (5x slower): {self.reason}"
        where = f"cache {self.cache_dir}" if self.cache_dir else f"NO disk cache ({self.reason})"
        built = f"; {self.build}" if self.build else ""
        return f"kernels: compiled, {where}, {self.hits} loaded from the cache, {self.misses} compiled{built}"


def status() -> KernelStatus:
    """The kernels' state in this process now (after :func:`ipt.receiver.core.kernels.ensure`)."""
    from ipt.receiver.core import kernels

    if not kernels._ready.is_set():
        return KernelStatus(False, None, 0, 0, None, loaded=False)
    if kernels.AHEAD is not None:
        not_fitting = sum(k.not_fitting for k in kernels.BY_NAME.values())
        return KernelStatus(True, None, 0, 0, None, ahead=kernels.AHEAD, not_fitting=not_fitting)
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


def warm(progress: Callable[[str], None] | None = None) -> KernelStatus:
    """Compile every kernel into numba's disk cache (or load it from there), build them ahead of time into
    ``$NUMBA_CACHE_DIR`` (:mod:`~ipt.receiver.core.kernelbuild`; numba's cache serves where that fails) and say
    how it went; leaves the stamp of :func:`already_warm` when every kernel is compiled and cached.
    ``progress`` is told before each long step."""
    from dataclasses import replace

    from ipt.receiver.core import kernelbuild, kernels

    if progress is not None:
        progress(f"compiling the kernels with numba, or loading them from its cache ({cache_env_hint()})")
    kernels.compile_with_numba()
    kernels.warm()
    kernels.warm_sparse()
    result = status()
    folder = os.environ.get("NUMBA_CACHE_DIR")
    if result.compiled and folder:
        try:
            if kernelbuild.load(Path(folder)) is not None:
                built = f"built ahead of time: {kernelbuild.module_file(Path(folder), kernelbuild.key())}"
            else:
                if progress is not None:
                    progress("building the kernels ahead of time (a C compiler's work: seconds here, a minute on a Pi)")
                dispatchers = {name: kernel.compiled for name, kernel in kernels.BY_NAME.items()}
                built = f"built ahead of time into {kernelbuild.build(Path(folder), dispatchers)}"
        except kernelbuild.KernelBuildError as exc:
            built = str(exc)
        result = replace(result, build=built)
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
