"""``ipt-receiver`` run as a subprocess with a kernel cache folder of its own (as the systemd unit runs it), for
the tests of ``ipt-receiver warm`` and of the kernels built ahead of time: the environment, the command, and
whether the process imported numba (``-X importtime`` lists every module it imported)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def kernel_env(cache: Path, **extra: str) -> dict[str, str]:
    """This process's environment without any ``NUMBA_*`` setting, with ``NUMBA_CACHE_DIR=cache`` and ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(NUMBA_CACHE_DIR=str(cache), **extra)
    return env


def receiver_cli(env: dict[str, str], *args: str, timeout_s: float = 900) -> subprocess.CompletedProcess[str]:
    """``ipt-receiver ARGS`` in a subprocess under ``env``, its imports listed on stderr."""
    command = [sys.executable, "-X", "importtime", "-m", "ipt.receiver.cli", *args]
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=timeout_s, check=False)


def numba_imported(result: subprocess.CompletedProcess[str]) -> bool:
    """Whether the process of ``result`` (run by :func:`receiver_cli`) imported numba or llvmlite."""
    return any(line.rstrip().endswith(("| numba", "| llvmlite")) for line in result.stderr.splitlines())
