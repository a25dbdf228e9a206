"""The sender's frame clock (:mod:`ipt.sender.clock`) with made-up times: no sleeps, no threads."""

from __future__ import annotations

import pytest

from ipt.sender.clock import FrameClock, Verdict

RATE_HZ = 50.0  # a period of 20 ms, exact enough in binary for the sums below
PERIOD = 1.0 / RATE_HZ


def test_frame_zero_starts_the_clock_and_later_frames_are_due_a_period_apart() -> None:
    clock = FrameClock(RATE_HZ)
    assert clock.start_s is None
    assert clock.judge(0, ready_s=9.0, now_s=10.0) is Verdict.ON_TIME  # frame 0 is due when it is first reached
    assert clock.start_s == 10.0
    assert clock.due_s(0) == 10.0
    assert clock.due_s(3) == pytest.approx(10.0 + 3 * PERIOD)
    # Ready before its due time and reached before it: wait for it.
    assert clock.judge(1, ready_s=10.005, now_s=10.01) is Verdict.ON_TIME
    # Reached after its due time but within half a period: still on time, and the clock does not move.
    assert clock.judge(2, ready_s=10.03, now_s=10.04 + 0.4 * PERIOD) is Verdict.ON_TIME
    assert clock.start_s == 10.0


def test_a_frame_finished_after_its_due_time_is_missed_and_restarts_the_clock() -> None:
    clock = FrameClock(RATE_HZ)
    clock.judge(0, ready_s=0.0, now_s=0.0)
    due_1 = clock.due_s(1)
    assert clock.judge(1, ready_s=due_1 + 0.001, now_s=due_1 + 0.002) is Verdict.MISSED
    # The next frame is due one period after the missed one was reached, not at its old time.
    assert clock.due_s(2) == pytest.approx(due_1 + 0.002 + PERIOD)
    # A frame ready on time on the new clock is on time again (no burst to catch up).
    assert clock.judge(2, ready_s=due_1 + 0.01, now_s=due_1 + 0.01) is Verdict.ON_TIME


def test_a_frame_ready_in_time_but_reached_over_half_a_period_late_is_late() -> None:
    clock = FrameClock(RATE_HZ)
    clock.judge(0, ready_s=0.0, now_s=0.0)
    due_1 = clock.due_s(1)
    reached = due_1 + 0.6 * PERIOD
    assert clock.judge(1, ready_s=due_1 - 0.005, now_s=reached) is Verdict.LATE
    assert clock.due_s(1) == pytest.approx(reached)  # restarted from the late frame
    assert clock.due_s(2) == pytest.approx(reached + PERIOD)


def test_missed_wins_over_late_when_both_hold() -> None:
    clock = FrameClock(RATE_HZ)
    clock.judge(0, ready_s=0.0, now_s=0.0)
    due_5 = clock.due_s(5)
    assert clock.judge(5, ready_s=due_5 + 0.05, now_s=due_5 + 0.06) is Verdict.MISSED


def test_a_steady_stream_on_time_never_moves_the_clock() -> None:
    clock = FrameClock(RATE_HZ)
    clock.judge(0, ready_s=100.0, now_s=100.0)
    for j in range(1, 1000):
        due = 100.0 + j * PERIOD
        assert clock.judge(j, ready_s=due - 0.004, now_s=due - 0.001) is Verdict.ON_TIME
    assert clock.start_s == 100.0
