"""Waiting in tests for what another thread, process or the kernel does: until a condition holds, never for a
fixed time. The only sleeps of the tests that are not pacing something on purpose live here
(``tests/test_architecture.py`` counts them)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

POLL_S = 0.005
"""How often a condition is looked at."""


def wait_until(condition: Callable[[], object], timeout_s: float = 10.0, what: str = "the condition") -> None:
    """Return as soon as ``condition()`` holds; fail the test if it does not within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s:g} s")
        time.sleep(POLL_S)  # real: the condition is another thread's, process's or the kernel's to make true


async def until(condition: Callable[[], object], timeout_s: float = 10.0, what: str = "the condition") -> None:
    """:func:`wait_until` on an event loop, which goes on running meanwhile."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout_s:g} s")
        await asyncio.sleep(POLL_S)  # real: the condition is another thread's, process's or the kernel's


async def loop_turns(count: int = 3) -> None:
    """Let the event loop run ``count`` times round: what other coroutines can do without waiting is done."""
    for _ in range(count):
        await asyncio.sleep(0)  # not a wait in time: one turn of the loop
