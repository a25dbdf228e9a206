"""Which frames a live daemon that fell behind hands the pipeline (:func:`ipt.receiver.liverun.pick_run`): all it
holds while it keeps up or the projector's phase is unknown; once behind, the newest + and − frames of one video
frame, or a wait for them when they are one to three frames away. The phases come from a real
:class:`~ipt.receiver.core.phaseclock.PhaseClock` on a 120 FPS camera under a 60 Hz projector."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from ipt.receiver.core.phaseclock import PhaseClock
from ipt.receiver.liverun import (
    LIVE_RUN_FRAMES,
    PAIR_WAIT_PERIODS,
    SLOW_WORKER_FRAMES,
    LivePicker,
    pairs_pay,
    pick_run,
)

FPS, PROJECTOR_HZ = 120.0, 60.0
PHASES = (1, 1, -1, -1)
"""Frames 0-3 of a video frame as a 120 FPS camera sees IPT's sender: its + phase twice, then its − twice."""


def _time_us(k: int) -> int:
    # A quarter of a camera period past the projector's flips: each frame well inside its phase.
    return round((k + 0.25) * 1e6 / FPS)


@pytest.fixture
def clock() -> PhaseClock:
    """The phase clock a chain that posed frames 0-7 would give."""
    known = range(8)
    return PhaseClock(tuple(_time_us(k) for k in known), tuple(PHASES[k % 4] for k in known), PROJECTOR_HZ)


def _pick(indices: list[int], clock: PhaseClock | None, behind: bool = True) -> tuple[int, int] | None:
    return pick_run(indices, [_time_us(k) for k in indices], behind, clock.at if clock is not None else None)


def test_the_clock_gives_the_phases_of_later_frames(clock: PhaseClock) -> None:
    assert [clock.at(_time_us(k)) for k in range(40, 48)] == [PHASES[k % 4] for k in range(40, 48)]


def test_a_worker_that_keeps_up_or_knows_no_phase_takes_everything_it_holds(clock: PhaseClock) -> None:
    assert _pick([41, 42, 43], clock, behind=False) == (0, 3)
    assert _pick([41, 42, 43], None) == (0, 3)
    assert _pick([], clock) == (0, 0)


@pytest.mark.parametrize(
    ("held", "pair"),
    [
        ([40, 41, 42], (41, 42)),  # + + −: the second + with the first −
        ([41, 42, 43], (41, 42)),  # + − −
        ([45, 46], (45, 46)),  # + −
        ([44, 45, 46, 47, 48, 49, 50], (49, 50)),  # the newest pair
    ],
)
def test_behind_the_run_is_the_newest_plus_and_minus_frame_of_one_video_frame(
    clock: PhaseClock, held: list[int], pair: tuple[int, int]
) -> None:
    picked = _pick(held, clock)
    assert picked is not None
    start, stop = picked
    assert (held[start], held[stop - 1]) == pair
    assert stop - start == 2
    assert [clock.at(_time_us(k)) for k in pair] == [1, -1]


@pytest.mark.parametrize("held", [[42, 43, 44], [43, 44, 45], [42, 43], [44]])
def test_without_that_pair_it_waits_for_the_next_frames(clock: PhaseClock, held: list[int]) -> None:
    # − − +, − + +, − −, +: the pair is one to three frames away.
    assert _pick(held, clock) is None
    # Those frames come, the newest LIVE_RUN_FRAMES are held, and the pair is among them within three.
    for more in range(1, 4):
        newest = held[-1] + more
        window = list(range(max(held[0], newest - LIVE_RUN_FRAMES + 1), newest + 1))
        if _pick(window, clock) is not None:
            break
    else:
        pytest.fail(f"no pair within three frames after {held}")


def test_a_missing_frame_breaks_a_pair(clock: PhaseClock) -> None:
    # 41 (+) and 42 (−) would pair, but 41 is not held: 40 (+) and 42 are two frames apart.
    assert _pick([40, 42, 43], clock) is None


@pytest.mark.parametrize("told", [None, 0])
def test_a_phase_the_clock_cannot_tell_takes_everything(told: int | None) -> None:
    # (a caller's own prediction may be 0: unknown, as None is)
    assert pick_run([42, 43], [_time_us(42), _time_us(43)], True, lambda t: told) == (0, 2)


def test_pairs_pay_where_the_content_moves_or_the_worker_is_slower_than_its_camera() -> None:
    period_s = 1 / FPS
    quick, slow = [0.004] * SLOW_WORKER_FRAMES, [0.012] * SLOW_WORKER_FRAMES
    assert pairs_pay(True, quick, period_s)  # moving content: a + frame waits for its − frame anyway
    assert not pairs_pay(False, quick, period_s)  # still content, a worker that keeps up: the frames held
    assert pairs_pay(False, slow, period_s)  # a Pi 4's 12 ms a frame against the camera's 8.3
    assert not pairs_pay(False, slow[: SLOW_WORKER_FRAMES // 2 - 1], period_s)  # too few frames timed yet
    # The median of the newest frames: an acquisition's few slow frames do not make a worker slow.
    assert not pairs_pay(False, [0.004] * 20 + [0.040] * 12, period_s)
    assert pairs_pay(False, [0.004] * 40 + [0.012] * SLOW_WORKER_FRAMES, period_s)


@dataclass(frozen=True)
class _Frame:
    index: int
    capture_time_us: int


def _frames(*indices: int) -> list[_Frame]:
    return [_Frame(k, _time_us(k)) for k in indices]


def _picker(clock: PhaseClock, moves: bool = True) -> LivePicker:
    picker = LivePicker()
    picker.note((clock, moves), 0.004)
    return picker


@pytest.mark.asyncio
async def test_the_picker_waits_for_the_pair_and_counts_the_frames_it_passes_over(clock: PhaseClock) -> None:
    coming = [_frames(45), _frames(46)]  # − − + held: 45 (+) then 46 (−) come, one at a time
    asked: list[float] = []

    async def more(timeout_s: float) -> list[_Frame]:
        asked.append(timeout_s)
        return coming.pop(0) if coming else []

    picker = _picker(clock)
    run = await picker.pick(_frames(42, 43, 44), more)
    assert [f.index for f in run] == [45, 46]
    assert len(asked) == 2
    assert asked[0] == pytest.approx(PAIR_WAIT_PERIODS / FPS, rel=1e-3)  # the camera's period from the frames held
    assert picker.passed_over == 3  # 42, 43, 44: taken from the queue, not processed


@pytest.mark.asyncio
async def test_the_picker_takes_what_it_holds_when_no_frame_comes_or_pairs_do_not_pay(clock: PhaseClock) -> None:
    async def nothing(timeout_s: float) -> list[_Frame]:
        return []

    picker = _picker(clock)
    assert [f.index for f in await picker.pick(_frames(42, 43, 44), nothing)] == [42, 43, 44]
    still = _picker(clock, moves=False)  # still content, a worker that keeps up: no pair, no wait
    assert [f.index for f in await still.pick(_frames(40, 41, 42), nothing)] == [40, 41, 42]
    assert picker.passed_over == still.passed_over == 0


@pytest.mark.asyncio
async def test_frames_that_come_after_a_gap_start_the_held_run_afresh(clock: PhaseClock) -> None:
    async def after_gap(timeout_s: float) -> list[_Frame]:
        return _frames(49, 50)  # 45-48 dropped meanwhile: 49 (+) and 50 (−) alone are consecutive

    picker = _picker(clock)
    run = await picker.pick(_frames(42, 43, 44), after_gap)
    assert [f.index for f in run] == [49, 50]
    assert picker.passed_over == 3
