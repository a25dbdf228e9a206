"""Plumbing the long-running programs share: the event loop they run on, their stderr lines, the
duration histogram.

Used by the sender (:mod:`ipt.sender.server`, :mod:`ipt.sender.cli`), the receiver daemon
(:mod:`ipt.receiver.daemon`) and the closed-loop demo (:mod:`ipt.sim.demo`);
the stop signals have their own module (:mod:`ipt.signals`). Standard library and numpy only, so that
the sender, the receiver and the simulator may all import it.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Callable, Coroutine
from typing import Any, TextIO, TypeVar

import numpy as np
import numpy.typing as npt

from ipt import signals

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
    with signals.kept_while_a_loop_runs(), asyncio.Runner(loop_factory=loop_factory()) as runner:
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


class Histogram:
    """Durations in milliseconds, in ``bin_ms`` bins up to ``limit_ms`` (later ones in the last bin, their
    percentiles capped at the largest seen): bounded memory however long the run, exact enough. The one
    histogram of the daemons: the sender's frame work, the receiver's pose latency."""

    def __init__(self, bin_ms: float = 0.05, limit_ms: float = 2000.0) -> None:
        self.bin_ms = bin_ms
        self.bins = round(limit_ms / bin_ms)
        self.counts: npt.NDArray[np.int64] = np.zeros(self.bins + 1, np.int64)
        self.n = 0
        self.max_ms = 0.0
        self.total_ms = 0.0

    def add(self, ms: float) -> None:
        """Count one duration (milliseconds)."""
        self.counts[min(self.bins, max(0, int(ms / self.bin_ms)))] += 1
        self.n += 1
        self.total_ms += ms
        self.max_ms = max(self.max_ms, ms)

    def percentile(self, p: float) -> float:
        """The ``p``-th percentile (0..100, the middle of its bin), NaN when empty."""
        if self.n == 0:
            return math.nan
        rank = max(1, math.ceil(p / 100.0 * self.n))
        index = int(np.searchsorted(np.cumsum(self.counts), rank))
        return self.max_ms if index >= self.bins else min(self.max_ms, (index + 0.5) * self.bin_ms)

    def quantile_ms(self, q: float) -> float | None:
        """The ``q`` quantile (0..1) in milliseconds; None when empty."""
        return None if self.n == 0 else self.percentile(100.0 * q)

    @property
    def mean_ms(self) -> float:
        """Mean of the durations added (NaN when empty)."""
        return self.total_ms / self.n if self.n else math.nan

    def clear(self) -> None:
        """Forget every duration."""
        self.counts.fill(0)
        self.n = 0
        self.max_ms = 0.0
        self.total_ms = 0.0
