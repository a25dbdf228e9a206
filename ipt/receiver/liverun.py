"""Which of the frames a live camera's queue holds the daemon hands the pipeline next (a *run*), and which it drops.

The rule is pure (:func:`pairs_pay`, :func:`pick_run`: frame indices, capture times, a phase clock in, a slice
out); :class:`LivePicker` holds what the daemon keeps for it and waits for frames as it says. The daemon
(:mod:`ipt.receiver.daemon`) applies it and ``benchmarks/live_sim.py`` models it.

- While the worker keeps up, the queue holds the one newest frame, or the few that came during the last one's
  processing, and the run is all of them (:data:`LIVE_RUN_FRAMES` at most: what the queue keeps).
- When it fell further behind (the queue dropped frames since the last run), the chain's last pose is too old
  to carry on from, and the pipeline starts again from the frames it is given. Then, once the projector's phase
  is known (:class:`~ipt.receiver.core.phaseclock.PhaseClock`), the run is the newest **pair of one video
  frame**, its + frame and the − frame right after it (IPT's sender shows each video frame in its + phase,
  then its −: at twice the projector's rate a video frame is [+, +, −, −]): the pair the chain fits best, and
  only two frames' work, so that the next run starts sooner, closer to this one. Without such a pair among
  the frames held, or with the phase not known yet, all of them.
- ... but only where pairs pay (:func:`pairs_pay`): while the floor's content moves (a + frame then waits for
  its video frame's − frame anyway), or on a worker slower than the camera (a Pi 4). A worker that keeps up
  over content that holds still fits a + frame with the − frame before it at once, and there the three
  frames it holds after a stall (the live start) did better than a pair (modelled and measured:
  ``docs/receiver-cores.md``).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Protocol, TypeVar

if TYPE_CHECKING:
    from ipt.receiver.core.phaseclock import PhaseClock

LIVE_RUN_FRAMES = 3
"""The longest run of consecutive frames a live source hands the pipeline at once (the queue keeps that many
newest frames): the frame with its partners one and two frames before it, the best ones (one projector
period apart, and half of one). The newest two alone, whatever their phases, did worse on the fast and
vibrating flights whenever the worker is more than about three times slower than the camera
(``docs/receiver-cores.md``); one video frame's + and − frames are another matter (:func:`pick_run`)."""


def pick_run(
    indices: Sequence[int], times_us: Sequence[int], behind: bool, phase_at: Callable[[int], int | None] | None
) -> tuple[int, int] | None:
    """The run among the frames held (``indices`` and capture ``times_us``, oldest first) as a slice
    ``(start, stop)`` of them; the others are dropped. ``behind``: frames were dropped since the last run;
    ``phase_at``: the projector's phase (+1, −1, or None if not known) at a capture time, if any is known.
    None: wait for the next frame, which (with the newest, or with the one after it) makes the pair: its
    video frame's + and − frames are one to three frames away (taking what is held instead, half of the time
    three frames of two video frames, a slow worker fell further behind at each run: a Pi 4's model,
    ``docs/receiver-cores.md``)."""
    everything = (0, len(indices))
    if not behind or phase_at is None or not indices:
        return everything
    phases = [phase_at(t) for t in times_us]
    for i in range(len(indices) - 1, 0, -1):
        if indices[i] == indices[i - 1] + 1 and phases[i] == -1 and phases[i - 1] == 1:
            return i - 1, i + 1
    return None if phases[-1] in (1, -1) else everything  # (a clock that cannot tell the newest's phase: all)


PAIR_WAIT_FRAMES = 3
"""The most frames the daemon waits for when :func:`pick_run` says the pair is coming (at twice the projector's
rate it is complete within three); the frame periods it waits for each are :data:`PAIR_WAIT_PERIODS`."""
PAIR_WAIT_PERIODS = 2.0
"""How many camera frame periods the daemon waits for the next frame before it takes what it holds (a camera
that stalls, or one that only delivers while the pipeline works)."""


SLOW_WORKER_SHARE = 0.8
"""A worker whose median processing time per frame (:data:`SLOW_WORKER_FRAMES` newest frames) is more than this
share of the camera's frame period cannot follow the camera for long (a Pi 4's core, by the scaling rule)."""
SLOW_WORKER_FRAMES = 32


def pairs_pay(content_moves: bool, frame_seconds: Sequence[float], period_s: float) -> bool:
    """Whether a worker behind its camera should take pairs (:func:`pick_run`): the floor's content was judged to
    move, or the worker's median time per frame over the newest :data:`SLOW_WORKER_FRAMES` (``frame_seconds``, at
    least half of them known) is over :data:`SLOW_WORKER_SHARE` of the camera's ``period_s``. (Not while nothing
    is known: the live start, whose stall three frames held recover from better.)"""
    if content_moves:
        return True
    newest = sorted(frame_seconds[-SLOW_WORKER_FRAMES:])
    if len(newest) < SLOW_WORKER_FRAMES // 2:
        return False
    return newest[len(newest) // 2] > SLOW_WORKER_SHARE * period_s


class LiveFrame(Protocol):
    """What the rule reads of a captured frame."""

    @property
    def index(self) -> int: ...

    @property
    def capture_time_us(self) -> int: ...


F = TypeVar("F", bound=LiveFrame)


class LivePicker:
    """The daemon's side of the rule: what the pipeline told after its last frame (:meth:`note`, on the worker
    thread; plain attribute assignments another thread reads whole) and the frames passed over."""

    def __init__(self) -> None:
        self.clock: PhaseClock | None = None
        self.moves = False
        self.frame_seconds: deque[float] = deque(maxlen=SLOW_WORKER_FRAMES)
        self.passed_over = 0
        """Frames taken from the queue with a run but not processed: drops too."""

    def note(self, hints: tuple[PhaseClock | None, bool], seconds: float) -> None:
        """After a frame (worker thread): the pipeline's phase clock and content judgement, and the frame's
        processing time (wall clock)."""
        self.clock, self.moves = hints
        self.frame_seconds.append(seconds)

    async def pick(self, held: list[F], more: Callable[[float], Awaitable[list[F]]]) -> list[F]:
        """From the frames held after the worker fell behind (frames were dropped), the run to process: where
        pairs pay, :func:`pick_run`'s, waiting with ``more(timeout_s)`` (the next frames, [] if none came in
        time or the source ended) up to :data:`PAIR_WAIT_FRAMES` frames when it says the pair is coming."""
        period_s = frame_period_s(held)
        if not pairs_pay(self.moves, tuple(self.frame_seconds), period_s):
            return held
        clock = self.clock
        phase_at = clock.at if clock is not None else None
        picked = pick_run([f.index for f in held], [f.capture_time_us for f in held], True, phase_at)
        waits = 0
        while picked is None and waits < PAIR_WAIT_FRAMES:
            came = await more(PAIR_WAIT_PERIODS * period_s)
            if not came:
                break
            keep = consecutive_tail([*held, *came])[-LIVE_RUN_FRAMES:]
            self.passed_over += len(held) + len(came) - len(keep)
            held, waits = keep, waits + 1
            picked = pick_run([f.index for f in held], [f.capture_time_us for f in held], True, phase_at)
        start, stop = picked if picked is not None else (0, len(held))
        self.passed_over += len(held) - (stop - start)
        return held[start:stop]


def frame_period_s(frames: Sequence[LiveFrame]) -> float:
    """The camera's frame period from frames' capture times (1/120 s when they do not tell)."""
    span = frames[-1].index - frames[0].index if frames else 0
    if span <= 0:
        return 1.0 / 120.0
    return max((frames[-1].capture_time_us - frames[0].capture_time_us) * 1e-6 / span, 1e-4)


def consecutive_tail(frames: list[F]) -> list[F]:
    """The newest of ``frames`` (in capture order) with no index missing between them."""
    start = len(frames) - 1
    while start > 0 and frames[start - 1].index == frames[start].index - 1:
        start -= 1
    return frames[start:]
