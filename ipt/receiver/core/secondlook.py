"""A second look at a frame whose fits the recent motion doubts, or whose track was lost on every pair: the
track once more, started from where that motion puts the camera (:meth:`SecondLook._second_look`). A
mix-in of :class:`ipt.receiver.core.pipeline.Pipeline`, whose state and stages it uses.

Why. A frame's track starts from its partner's pose carried by the pair's homography. On a vibrating drone
over moving video that homography is now and then a few pixels off, the fit settles in a wrong basin (the
poses the consistency gate turned away on shadow-vibration were 36 mm off, median) or finds no basin at
all (``lost``), while the motion of the frames around it knows within millimetres where the camera is.
Started from there, the same fit on the same pair usually lands on the right pose. The result is still the
image's: the fit is free, and the gates judge it like any other candidate (only a fit they do not doubt
joins the frame's candidates).

Measured (``benchmarks/suite.py``, 8 s flights, the same renderings, aa6affa → 60ad9b6): shadow-vibration
90.9 → 97.5 % (inconsistent 50 → 8, lost 36 → 14; MAE 1.8 / 1.6 / 0.6 → 2.0 / 1.8 / 0.6 mm, worst 18 mm),
moving-content 93.9 → 94.7 %, rolling (told) 88.6 → 94.5 %, independent 83.1 → 89.0 %, fast 76.7 → 78.3 %,
take-off 70.0 → 72.2 %; no pose over 10 cm on any flight whose arena file is right.
"""

from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from ipt.receiver.core.pose import rt_of
from ipt.receiver.core.reasons import FrameReason

if TYPE_CHECKING:
    from ipt.receiver.core.demodulator import PairDifference
    from ipt.receiver.core.frameresult import _Candidate, _Frame, _Pair
    from ipt.receiver.core.motion import MotionTrack
    from ipt.receiver.core.pose import PoseEstimate
    from ipt.receiver.core.track import TrackResult

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

#: A frame whose track was lost is looked at again on at most this many of its pairs (best phase first).
LOST_PAIRS = 2


class SecondLook:
    """The second look, as a method of :class:`~ipt.receiver.core.pipeline.Pipeline` (which has what is declared
    here)."""

    tracking: bool
    _history: deque[_Frame]
    _track: MotionTrack

    if TYPE_CHECKING:  # the pipeline's own stages and gates

        def _doubtful(self, t_us: int, pose: PoseEstimate) -> str | None: ...
        def _pair(self, a: _Frame, b: _Frame) -> _Pair | None: ...
        def _difference_in(self, pair: _Pair, target_is_later: bool) -> PairDifference: ...
        def _partner_rank(self, frame: _Frame, other: _Frame) -> tuple[int, int]: ...
        def _track_guessed(
            self, diff: PairDifference, guess: tuple[tuple[F64, F64], bool], lit: U8 | None
        ) -> TrackResult | None: ...
        def _candidate(self, tracked: TrackResult, partner: int) -> _Candidate: ...
        def _add_candidate(self, target: _Frame, candidate: _Candidate) -> None: ...

    def _second_look(self, f: _Frame) -> None:
        """If no candidate of ``f`` fits the recent motion (all doubted, or the track lost on every pair), track
        it again from the motion's prediction on its pairs with the frames still kept; the first fit the gates
        do not doubt joins its candidates."""
        if not self.tracking or not f.tried:
            return
        partners = list(self._history)
        if f.candidates:
            if any(self._doubtful(f.time_us, c.pose) is None for c in f.candidates):
                return
            by_index = {p.index: p for p in partners}
            ranked = sorted(f.candidates, key=lambda c: -c.quality)
            others = [by_index[i] for i in dict.fromkeys(c.partner for c in ranked) if i in by_index]
        elif f.failure is not None and f.failure.reason == FrameReason.LOST:
            others = [p for p in partners if p.index in f.tried]
            others.sort(key=lambda p: self._partner_rank(f, p))
            others = others[:LOST_PAIRS]
        else:
            return
        predicted = self._track.pose_at(f.time_us)
        if predicted is None:
            return
        init = rt_of(*predicted)
        for other in others:
            a, b = (other, f) if other.index < f.index else (f, other)
            pair = self._pair(a, b)
            if pair is None:
                continue
            tracked = self._track_guessed(self._difference_in(pair, f is b), (init, True), f.signal)
            if tracked is None:
                continue
            candidate = self._candidate(tracked, other.index)
            if self._doubtful(f.time_us, candidate.pose) is None:
                self._add_candidate(f, candidate)
                return
