"""A second look at a frame whose fits the recent motion doubts, or whose track was lost on every pair: the
track once more, started from where that motion puts the camera (:meth:`SecondLook.look`). The pipeline
holds one and asks it about each frame before judging it; it pairs and tracks through the pipeline's own
stages (:class:`PairTracker`).

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

from typing import Protocol

import numpy as np
import numpy.typing as npt

from ipt.receiver.core.demodulator import PairDifference
from ipt.receiver.core.gates import PoseGates
from ipt.receiver.core.history import Candidate, Frame, FrameHistory, Pair
from ipt.receiver.core.pose import rt_of
from ipt.receiver.core.reasons import FrameReason
from ipt.receiver.core.track import TrackResult

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

#: A frame whose track was lost is looked at again on at most this many of its pairs (best phase first).
LOST_PAIRS = 2


class PairTracker(Protocol):
    """The pipeline's stages the second look uses."""

    def pair(self, a: Frame, b: Frame) -> Pair | None:
        """The alignment and difference of ``a`` (earlier) and ``b`` (later), computed once."""

    def difference_in(self, pair: Pair, target_is_later: bool) -> PairDifference:
        """The pair's difference in the target frame's geometry."""

    def track_guessed(
        self, diff: PairDifference, guess: tuple[tuple[F64, F64], bool], lit: U8 | None
    ) -> TrackResult | None:
        """The pose tracked on ``diff`` from ``guess`` (OpenCV's rvec, tvec; and whether it is close)."""

    def candidate(self, tracked: TrackResult, partner: int) -> Candidate:
        """A candidate of the track's pose, paired with frame ``partner``."""

    def add_candidate(self, target: Frame, candidate: Candidate) -> None:
        """``candidate`` joins ``target``'s candidates."""


class SecondLook:
    """The second look at the frames of ``history`` that ``gates`` would doubt, through ``stages``."""

    def __init__(self, history: FrameHistory, gates: PoseGates, stages: PairTracker) -> None:
        self.history, self.gates, self.stages = history, gates, stages

    def look(self, f: Frame) -> None:
        """If no candidate of ``f`` fits the recent motion (all doubted, or the track lost on every pair), track
        it again from the motion's prediction on its pairs with the frames still kept; the first fit the gates
        do not doubt joins its candidates."""
        if not f.tried:
            return
        partners = list(self.history)
        if f.candidates:
            if any(self.gates.doubt(f.time_us, c.pose) is None for c in f.candidates):
                return
            by_index = {p.index: p for p in partners}
            ranked = sorted(f.candidates, key=lambda c: -c.quality)
            others = [by_index[i] for i in dict.fromkeys(c.partner for c in ranked) if i in by_index]
        elif f.failure is not None and f.failure.reason == FrameReason.LOST:
            others = [p for p in partners if p.index in f.tried]
            others.sort(key=lambda p: self.history.partner_rank(f, p))
            others = others[:LOST_PAIRS]
        else:
            return
        predicted = self.gates.motion.pose_at(f.time_us)
        if predicted is None:
            return
        init = rt_of(*predicted)
        for other in others:
            a, b = (other, f) if other.index < f.index else (f, other)
            pair = self.stages.pair(a, b)
            if pair is None:
                continue
            tracked = self.stages.track_guessed(self.stages.difference_in(pair, f is b), (init, True), f.signal)
            if tracked is None:
                continue
            candidate = self.stages.candidate(tracked, other.index)
            if self.gates.doubt(f.time_us, candidate.pose) is None:
                self.stages.add_candidate(f, candidate)
                return
