"""Plumbing the long-running programs share: the event loop they run on, their stderr lines, a latency
histogram.

Used by the receiver daemon (:mod:`ipt.receiver.daemon`) and the closed-loop demo (:mod:`ipt.sim.demo`);
the stop signals have their own module (:mod:`ipt.signals`). Standard library and numpy only, so that
the sender, the receiver and the simulator may all import it.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable, Coroutine
from typing import Any, TextIO, TypeVar

import numpy as np
import numpy.typing as npt

T = TypeVar("T")


def loop_factory() -> Callable[[], asyncio.AbstractEventLoop] | None:
    """uvloop's event loop when it is installed, else None (asyncio's own loop, fine too)."""
    try:
        import uvloop
    except ImportError:  # not on every platform: the standard loop is fine
        return None
    return uvloop.new_event_loop


def run_loop(main: Coroutine[Any, Any, T]) -> T:
    """Run ``main`` to its end on a fresh event loop (uvloop when installed) and close the loop."""
    with asyncio.Runner(loop_factory=loop_factory()) as runner:
        return runner.run(main)


def write_line(out: TextIO, line: str) -> None:
    """Write one line and flush it; a stream that is gone (a closed pipe) is ignored: the program goes on."""
    try:
        out.write(line + "\n")
        out.flush()
    except (OSError, ValueError):  # stderr gone (closed pipe): the daemon carries on regardless
        pass


def line_writer(out: TextIO) -> Callable[[str], None]:
    """A function that writes one line to ``out`` as :func:`write_line` does (a log for a ``log=`` hook)."""

    def log(line: str) -> None:
        with contextlib.suppress(OSError, ValueError):
            out.write(line + "\n")
            out.flush()

    return log


class LatencyHistogram:
    """Latencies in 0.1 ms bins up to 10 s (later ones in the last bin): constant memory, exact enough."""

    BIN_MS = 0.1
    BINS = 100_000

    def __init__(self) -> None:
        self.counts: npt.NDArray[np.int64] = np.zeros(self.BINS + 1, np.int64)
        self.n = 0

    def add(self, seconds: float) -> None:
        """Count one latency."""
        i = int(max(seconds, 0.0) * 1e3 / self.BIN_MS)
        self.counts[min(i, self.BINS)] += 1
        self.n += 1

    def quantile_ms(self, q: float) -> float | None:
        """The ``q`` quantile (0..1) in milliseconds (the middle of its bin); None when empty."""
        if self.n == 0:
            return None
        rank = max(1, int(np.ceil(q * self.n)))
        i = int(np.searchsorted(np.cumsum(self.counts), rank))
        return (i + 0.5) * self.BIN_MS

    def clear(self) -> None:
        """Forget every latency."""
        self.counts.fill(0)
        self.n = 0
