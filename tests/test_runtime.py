"""The plumbing both daemons share (ipt/runtime.py): the duration histogram, the stepped clock, the
statistics interval, the task set and the shutdown budget."""

from __future__ import annotations

import asyncio
import math

import pytest

from ipt.runtime import Histogram, Interval, ShutdownBudget, SteppedClock, TaskSet


def test_histogram_percentiles_in_bins_capped_at_the_largest_seen() -> None:
    h = Histogram(bin_ms=0.1, limit_ms=10_000.0)
    assert h.quantile_ms(0.5) is None
    assert math.isnan(h.percentile(50))
    for ms in (1.0, 2.0, 3.0, 4.0, 100.0):
        h.add(ms)
    assert math.isclose(h.percentile(50), 3.05)  # the middle of the bin of 3.0 ms
    assert h.quantile_ms(0.5) == h.percentile(50)
    assert h.percentile(100) == 100.0  # its bin's middle (100.05) is above what was seen
    assert h.mean_ms == 22.0
    h.add(50_000.0)  # beyond the limit: the last bin, reported as the largest seen
    assert h.percentile(100) == 50_000.0
    h.clear()
    assert h.n == 0
    assert h.quantile_ms(0.99) is None


@pytest.mark.asyncio
async def test_a_stepped_clock_wakes_a_sleep_only_once_stepped_past_its_end() -> None:
    clock = SteppedClock(10.0)
    nap = asyncio.ensure_future(clock.sleep(2.0))
    await clock.wait_for_sleepers(1)
    clock.advance(1.5)
    assert clock.now() == 11.5
    assert not nap.done()
    assert clock.sleepers == 1
    clock.advance(0.5)
    await asyncio.wait_for(nap, 1.0)
    assert clock.sleepers == 0


def test_an_interval_is_due_after_its_length_and_restarts_where_it_ended() -> None:
    interval = Interval(5.0, 100.0)
    assert not interval.due(104.9)
    assert interval.due(105.0)
    assert interval.restart(106.0) == 6.0
    assert not interval.due(110.0)
    assert interval.due(111.0)
    assert interval.restart(106.0) == 1e-9  # never 0: a rate divides by it


@pytest.mark.asyncio
async def test_the_task_set_cancels_what_still_runs_and_the_budget_bounds_the_waits() -> None:
    now = [0.0]
    budget = ShutdownBudget(0.5, now=lambda: now[0])
    tasks = TaskSet()

    async def wait_forever() -> None:
        await asyncio.Event().wait()

    async def nothing() -> None:
        pass

    forever = tasks.spawn(wait_forever(), "forever")
    done = tasks.spawn(nothing(), "done")
    assert await budget.wait({done}) is True
    assert len(tasks) == 1
    now[0] = 0.45
    assert budget.left() == pytest.approx(0.05)
    assert budget.left(cap_s=0.01) == 0.01
    assert await budget.wait({forever}) is False  # 50 ms, and still running
    now[0] = 0.6
    assert budget.left() == 0.0
    await tasks.cancel_all()
    assert forever.cancelled()
    assert len(tasks) == 0
