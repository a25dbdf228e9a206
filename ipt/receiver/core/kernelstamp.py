"""What the compiled kernels depend on, as text: the stamp of a complete ``ipt-receiver warm``
(:mod:`~ipt.receiver.core.kernelcache`) and the key of the kernels built ahead of time
(:mod:`~ipt.receiver.core.kernelbuild`). The standard library only: a warm that finds its stamp matching returns
without importing numpy or numba."""

from __future__ import annotations

import hashlib
import importlib.metadata
import platform
import sys
from pathlib import Path


def stamp_text() -> str:
    """What the cached kernels depend on: the receiver core's sources (the kernels and whatever defines
    more of them there), numba's, llvmlite's and numpy's versions (a module built ahead of time is compiled
    against numpy's C interface), Python's version and the processor's kind."""
    digest = hashlib.sha256()
    core = Path(__file__).resolve().parent  # ipt.receiver.core (this module's folder), without importing numpy
    for source in sorted(core.glob("*.py")):
        digest.update(source.name.encode() + b"\0" + source.read_bytes())
    versions = [f"{name} {importlib.metadata.version(name)}" for name in ("numba", "llvmlite", "numpy")]
    return "\n".join([f"sources {digest.hexdigest()}", *versions, f"python {sys.version}", platform.machine(), ""])
