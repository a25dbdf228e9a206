"""The projector's phase at a capture time, from the phases the sparse chain found for recent frames (issue 29):
:func:`clock_phase`, and :class:`PhaseClock`, its snapshot the chain gives the live daemon
(:mod:`ipt.receiver.liverun`) to choose its next frames by. Pure: times and signs in, a phase out."""

from __future__ import annotations

import math
from dataclasses import dataclass

#: The clock offsets tried, twentieths of a period, each in the middle of its twentieth.
OFFSETS = tuple((i + 0.5) / 20.0 for i in range(20))


def _agreement(t: list[float], signs: list[int]) -> list[int]:
    """Per offset φ of :data:`OFFSETS`: Σ sign · (−1)^⌊t + φ⌋ over the phases (``t`` in periods). A phase's term
    flips at most once over the offsets (they span less than a period, and t + φ grows with φ in floats too), so
    its flip is found by bisection, not by all twenty floors: the same sums (a third of the time)."""
    last = len(OFFSETS) - 1
    change = [0] * (last + 2)  # the sums' differences from one offset to the next
    for ti, sign in zip(t, signs, strict=True):
        low = math.floor(ti + OFFSETS[0])
        first = sign if low % 2 == 0 else -sign
        change[0] += first
        if math.floor(ti + OFFSETS[last]) == low:
            continue
        lo, hi = 0, last  # the floor is low at lo and above it at hi
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if math.floor(ti + OFFSETS[mid]) == low else (lo, mid)
        change[hi] -= 2 * first
    agree, total = [], 0
    for step in change[:-1]:
        total += step
        agree.append(total)
    return agree


def clock_phase(times_us: list[int], signs: list[int], at_us: int, projector_hz: float) -> int | None:
    """The projector phase at ``at_us`` from the phases ``signs`` of frames captured at ``times_us``: the phase
    is ±(−1)^⌊t·f + φ⌋ (f the projector's rate), φ the unknown offset of its clock against the camera's; the
    offsets (twentieths of a period, each in the middle of its twentieth) and signs that agree with the most of
    the given phases (all but at most one) must all predict the same phase, else None. (At 120 FPS against
    60 Hz a frame is half a period from its neighbours, so a single known phase does not tell whether its
    neighbour flipped; two known phases that every offset finds one right and one wrong tell nothing either.)"""
    if len(signs) < 2:
        return None
    # In plain Python (it runs once a frame on at most eight phases: numpy's calls cost 0.1 ms of a frame's 4-5), with
    # numpy's steps: the same floats, so the same answer to the bit (tests/test_sparse.py compares the two).
    ref = times_us[-1]
    t = [(float(time_us) - ref) * 1e-6 * projector_hz for time_us in times_us]
    # Not 0 nor 1/2: a camera at twice the projector's rate captures every frame half a period after the last,
    # so those offsets put every frame on a flip, where a microsecond of the clocks' rounding decides its side.
    agree = _agreement(t, signs)
    best = max(abs(a) for a in agree)
    if best < len(signs) - 2 or best == 0:  # (0: agreement's sign, the phase predicted, would be 0)
        return None
    at = (at_us - ref) * 1e-6 * projector_hz
    predicted = {
        (1 if a > 0 else -1) * (1 if math.floor(at + offset) % 2 == 0 else -1)
        for a, offset in zip(agree, OFFSETS, strict=True)
        if abs(a) == best
    }
    return predicted.pop() if len(predicted) == 1 else None


@dataclass(frozen=True)
class PhaseClock:
    """The projector's phase at any capture time (:func:`clock_phase`) from the phases found for some recent
    frames: a snapshot, which another thread may keep and ask (the live daemon choosing its next frames)."""

    times_us: tuple[int, ...]
    signs: tuple[int, ...]
    projector_hz: float

    def at(self, time_us: int) -> int | None:
        """+1 or −1: the phase at ``time_us``; None when the phases found do not tell."""
        return clock_phase(list(self.times_us), list(self.signs), time_us, self.projector_hz)
