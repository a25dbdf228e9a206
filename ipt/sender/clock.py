"""The sender's frame clock: when output frame ``j`` is due, and whether it was shown on time.

Pure: times go in (seconds on one monotonic clock), a verdict comes out; nothing here reads a clock or
sleeps, so the rules can be tested with made-up times. Output frame ``j`` is due at
``start + j / f_o``; frame 0 is due as soon as it is ready (``start`` is the time it was judged). A frame
whose rendering finished after its due time is :attr:`Verdict.MISSED`; one that was ready but is reached
more than half a period after its due time (the sink or the loop was behind) is :attr:`Verdict.LATE`.
Either way it is shown at once and the clock restarts from it (``start`` moves on), so the next frame is
due one period later instead of a burst of frames to catch up that no display could show anyway.
"""

from __future__ import annotations

import enum


class Verdict(enum.Enum):
    """What :meth:`FrameClock.judge` says of a frame."""

    ON_TIME = "on_time"
    """Ready before its due time and reached in time: wait until it is due, then show it."""
    MISSED = "missed"
    """Its rendering finished after its due time (a missed deadline): show it now."""
    LATE = "late"
    """Ready in time, but reached more than half a period after its due time: show it now."""


class FrameClock:
    """Due times of the output frames at ``rate_hz``, restarted after every frame that was not on time."""

    def __init__(self, rate_hz: float) -> None:
        self.period_s = 1.0 / rate_hz
        self.start_s: float | None = None
        """Due time of frame 0 (moved on after a frame that was not on time); None until frame 0 is judged."""

    def due_s(self, j: int) -> float:
        """When output frame ``j`` is due (after frame 0 was judged)."""
        assert self.start_s is not None, "frame 0 has not been judged yet"
        return self.start_s + j * self.period_s

    def judge(self, j: int, ready_s: float, now_s: float) -> Verdict:
        """Output frame ``j``, finished at ``ready_s``, reached at ``now_s``: on time, missed or late.

        Frame 0 starts the clock: it is due at ``now_s`` when it is first judged. After a frame that was not
        on time the clock restarts from it: frame ``j + 1`` is due one period after ``now_s``.
        """
        if self.start_s is None:
            self.start_s = now_s
        due = self.start_s + j * self.period_s
        if ready_s > due:
            verdict = Verdict.MISSED
        elif now_s > due + 0.5 * self.period_s:
            verdict = Verdict.LATE
        else:
            return Verdict.ON_TIME
        self.start_s += now_s - due
        return verdict
