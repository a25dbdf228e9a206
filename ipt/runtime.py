"""Plumbing the long-running programs share: the event loop they run on, their clock, the tasks they start
and their ordered shutdown, their statistics intervals and stderr lines, the duration histogram.

Used by the sender (:mod:`ipt.sender.server`, :mod:`ipt.sender.cli`), the receiver daemon
(:mod:`ipt.receiver.daemon`) and the closed-loop demo (:mod:`ipt.sim.demo`);
the stop signals have their own module (:mod:`ipt.signals`). Standard library and numpy only, so that
the sender, the receiver and the simulator may all import it.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Awaitable, Callable, Coroutine, Iterable
from typing import Any, Protocol, TextIO, TypeVar

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


class Clock(Protocol):
    """The time a daemon runs on, in seconds, and a wait on it (:data:`MONOTONIC`, or :class:`SteppedClock`)."""

    def now(self) -> float:
        """The time now (seconds)."""
        ...

    async def sleep(self, seconds: float) -> None:
        """Return once ``seconds`` went by on this clock."""
        ...


class MonotonicClock:
    """``time.monotonic`` and ``asyncio.sleep``: the real clock."""

    def now(self) -> float:
        return time.monotonic()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(seconds)


MONOTONIC: Clock = MonotonicClock()
"""The real clock, every daemon's default."""


class SteppedClock:
    """A clock that moves only when :meth:`advance` moves it (tests step time instead of sleeping). Its
    :meth:`sleep` returns once the clock was advanced past its end; use it on one event loop's thread."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._now = start_s
        self._waiters: list[tuple[float, asyncio.Future[None]]] = []
        self._added: asyncio.Future[None] | None = None

    def now(self) -> float:
        return self._now

    async def sleep(self, seconds: float) -> None:
        if seconds <= 0:
            await asyncio.sleep(0)  # a turn of the loop, as asyncio.sleep(0) gives
            return
        waiter = (self._now + seconds, asyncio.get_running_loop().create_future())
        self._waiters.append(waiter)
        if self._added is not None and not self._added.done():
            self._added.set_result(None)
        try:
            await waiter[1]
        finally:
            if waiter in self._waiters:
                self._waiters.remove(waiter)

    @property
    def sleepers(self) -> int:
        """How many sleeps wait for the clock to move."""
        return len(self._waiters)

    async def wait_for_sleepers(self, count: int = 1) -> None:
        """Return once ``count`` sleeps wait for the clock to move (so that a step of time reaches them)."""
        while len(self._waiters) < count:
            self._added = asyncio.get_running_loop().create_future()
            await self._added

    def advance(self, seconds: float) -> None:
        """Move the time on by ``seconds``; the sleeps that end by then return (at the loop's next turn)."""
        self._now += seconds
        for due, fut in list(self._waiters):
            if due <= self._now and not fut.done():
                fut.set_result(None)


class Interval:
    """One statistics interval of a daemon: when it began, and whether its line is due (every ``every_s``)."""

    def __init__(self, every_s: float, start_s: float) -> None:
        self.every_s = every_s
        self.start_s = start_s

    def due(self, now_s: float) -> bool:
        """Whether the interval's line is due at ``now_s``."""
        return now_s >= self.start_s + self.every_s

    def restart(self, now_s: float) -> float:
        """End the interval at ``now_s`` and begin the next: its length in seconds (never 0, to divide by)."""
        span = max(now_s - self.start_s, 1e-9)
        self.start_s = now_s
        return span


class TaskSet:
    """The tasks a daemon started; :meth:`cancel_all` cancels those still running at shutdown and waits for them."""

    def __init__(self) -> None:
        self._tasks: set[asyncio.Task[None]] = set()

    def spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        """Start ``coro`` as a task named ``name``, kept until it ends."""
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def __len__(self) -> int:
        return len(self._tasks)

    async def cancel_all(self) -> None:
        """Cancel every task still running and wait until they are done (their errors are theirs to report)."""
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)


class ShutdownBudget:
    """An ordered shutdown's time: each step waits at most what is left of ``seconds`` (real time, whatever
    clock the run's statistics use, since it bounds real waits)."""

    def __init__(self, seconds: float, now: Callable[[], float] = time.monotonic) -> None:
        self._now = now
        self.deadline_s = now() + seconds

    def left(self, cap_s: float | None = None) -> float:
        """Seconds left (at most ``cap_s``), never below 0."""
        left = max(0.0, self.deadline_s - self._now())
        return left if cap_s is None else min(cap_s, left)

    async def wait(self, aws: Iterable[Awaitable[Any]], cap_s: float | None = None) -> bool:
        """Wait for ``aws`` within what is left (at most ``cap_s``): whether all of them are done."""
        futures = {asyncio.ensure_future(a) for a in aws}
        if not futures:
            return True
        _, pending = await asyncio.wait(futures, timeout=self.left(cap_s))
        return not pending


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
