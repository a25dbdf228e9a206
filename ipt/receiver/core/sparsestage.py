"""The sparse tracker in the pipeline (``tracker: sparse``, the default; :class:`SparseStage`, held by
:class:`~ipt.receiver.core.pipeline.Pipeline`).

Each frame goes to the sparse chain first (:class:`~ipt.receiver.core.sparsechain.LiveChain`: raw lightness, no
undistortion, no content homography, no difference image). A pose it finds becomes the frame's candidate with
method ``sparse`` and goes through the same gates; such a frame goes out at once. A frame the chain does not pose
(and does not wait for a later partner to pose) takes the pipeline's dense way, as with ``tracker: dense``; so do
the frames the chain waited for in vain, those whose sparse poses the gates all doubt, and acquisition (no chain
yet). Dense poses the gates do not doubt re-seed the chain. Against drift: every :data:`CHECK_EVERY` sparse poses a
frame is posed the dense way too (which also lets AprilTag's periodic check of the track run); a sparse pose more
than :data:`CHECK_M` off the dense one restarts the chain from the dense pose, and the dense pose is taken. Once
:data:`TRUSTED_AFTER` checks in a row found the chain within :data:`TRUSTED_M` of a dense pose that fits the map well
(:data:`TRUSTED_QUALITY`), the checks come every :data:`TRUSTED_CHECK_EVERY` sparse poses instead. Live
(a live camera's frames come with their wait: :attr:`SparseStage.now_us`), a frame the chain gave up on that is
already :data:`LIVE_LATE_US` old takes no dense way and no bridge: it goes out without a pose (``late``).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.gates import PoseGates
from ipt.receiver.core.history import GOOD_QUALITY, Candidate, Frame, FrameHistory
from ipt.receiver.core.reasons import FrameReason
from ipt.receiver.core.sparsechain import LiveChain

#: Every this many sparse poses one frame is posed the dense way too, as a check.
CHECK_EVERY = 16
#: ... and a sparse pose further than this from the dense one restarts the chain from the dense pose.
CHECK_M = 0.02
#: The checks come every this many sparse poses once :data:`TRUSTED_AFTER` checks in a row found the chain within
#: :data:`TRUSTED_M` of a dense pose fitting at least :data:`TRUSTED_QUALITY` of the map's edges in view. A check is
#: 11-13 ms where a sparse frame is 3-4 (shadow-vibration: 61 checks, a sixth of its time). The dense fit's share
#: is what tells a wrong arena file: at the checks the uncalibrated keystoned flight's dense poses fit 0.45 of the
#: edges (median; 0.23-0.62 where the chain agreed within 3 mm), shadow-vibration's 0.78 (p10 0.63). Every 32 sparse
#: poses after close checks alone (stops 57, 62), that flight's chain went otherwise where its file is 5-6 cm off,
#: and the dense way then posed frames 10-14 cm off (docs/receiver-cores.md, stop 63). Also after joint fits (a new
#: video frame: both poses predicted), since the image's measured shift starts them (stop 69): stop 63 kept those at
#: 16 for the re-seeds a joint fit then needed. 48, not 32 (stop 70): moving-content's dense pair solves 63 -> 26,
#: realcam's 103 -> 48, takeoff's 902 -> 849, the uncalibrated keystoned flight's the same (never trusted).
TRUSTED_CHECK_EVERY = 48
TRUSTED_AFTER = 2
TRUSTED_M = 0.003
TRUSTED_QUALITY = 0.6
#: Live, a frame the chain waited for in vain (or whose sparse poses the gates all doubt) this long after its capture
#: gets no dense way, and no bridge (:meth:`SparseStage.too_late`): it is two or three frames old then, the dense way
#: takes 10-60 ms more (its partners on both sides; shadow-vibration's frame 57, 59 ms; a bridge 77 ms), and every
#: frame behind it waits as long. Live on shadow-vibration, poses over 30 ms of ~940 in a run, the median of 11-21
#: runs alternating: 30.5 without it, 24 with the dense way spared, 19 with the bridge too; after the first second
#: 18 -> 7 (docs/receiver-cores.md, stop 59). 10 ms did no better in five runs (17).
LIVE_LATE_US = 20_000


class SparseStage:
    """The sparse chain between the pipeline's frames and its dense way: ``solve(a, b, target)`` a dense pair
    (a earlier), ``prepare(f)`` a frame's dense preparation (once), ``add_candidate``, ``lap`` (processor time),
    ``verified_count()`` (one more tracked frame towards AprilTag's check)."""

    def __init__(
        self,
        chain: LiveChain,
        history: FrameHistory,
        gates: PoseGates,
        solve: Callable[[Frame, Frame, Frame], None],
        prepare: Callable[[Frame], None],
        add_candidate: Callable[[Frame, Candidate], None],
        lap: Callable[[str, float], float],
        tracked: Callable[[], None],
    ) -> None:
        self.chain, self.history, self.gates = chain, history, gates
        self._solve, self._prepare, self._add, self._lap, self._tracked = solve, prepare, add_candidate, lap, tracked
        self._since_check = 0
        self._trusted = 0
        """Checks in a row that found the chain within :data:`TRUSTED_M` of a dense pose of :data:`TRUSTED_QUALITY`."""
        self._checking: int | None = None
        """The frame a check is due on (posed by the chain, then the dense way)."""
        self.checks_failed = 0
        """Dense checks that found the chain's pose more than :data:`CHECK_M` off."""
        self.now_us: int | None = None
        """A live camera's newest frame's capture time plus how long it waited before the pipeline took it (the
        camera's clock): a frame older than :data:`LIVE_LATE_US` then gets no :meth:`dense_late`. None (a recording,
        whose frames never wait): every frame is posed."""
        self.late = 0
        """Frames given up as ``late``."""

    def step(self, new: Frame) -> bool:
        """Feed ``new`` to the chain; its poses (``new``'s, and earlier frames' that waited for it) join their
        frames' candidates; frames it gives up on are posed densely. Whether ``new`` takes the dense way (the chain
        did not pose it and does not wait; or a check)."""
        assert new.raw is not None
        t0 = time.thread_time()
        step = self.chain.feed(new.index, new.time_us, new.raw, self.history.predicted_phase(new))
        self._lap("sparse", t0)
        frames = {f.index: f for f in self.history}
        for j, result in step.poses.items():
            f = frames.get(j)
            if f is None or f.final:
                continue
            f.waiting, f.phase = False, result.sign
            self._tracked()
            quality = result.inliers / max(result.tried, 1)
            rt = (result.rvec, result.tvec)
            self._add(f, Candidate(result.estimate(), rt, len(result.tags), "sparse", step.partners[j], quality))
        new.waiting = step.waits
        for j in step.given_up:
            if j in frames and frames[j].waiting and not frames[j].final:
                frames[j].waiting = False
                self.dense_late(frames[j])
        if new.index not in step.poses:
            return not step.waits
        self._since_check += 1
        if self._since_check < (TRUSTED_CHECK_EVERY if self._trusted >= TRUSTED_AFTER else CHECK_EVERY):
            return False
        self._since_check, self._checking = 0, new.index
        return True

    def after_dense(self, new: Frame) -> None:
        """After ``new``'s dense pairs: the check of a sparse pose (the chain starts afresh if the two are more than
        :data:`CHECK_M` apart; the dense pose is taken either way; one within :data:`TRUSTED_M` of a dense pose of
        :data:`TRUSTED_QUALITY` counts towards :data:`TRUSTED_AFTER`, any other ends the run); then the dense poses
        the gates do not doubt re-seed the chain, and those of frames that went out already (a dense frame goes out
        once its pose is good)."""
        dense = [c for c in new.candidates if c.method != "sparse"]
        trusted = False
        if dense and len(dense) < len(new.candidates):
            best = max(dense, key=lambda c: c.quality)
            sparse = next(c for c in new.candidates if c.method == "sparse")
            apart_m = float(np.linalg.norm(best.pose.position_m - sparse.pose.position_m))
            if apart_m > CHECK_M:
                self.checks_failed += 1
                self.reset(False)
            trusted = apart_m <= TRUSTED_M and best.quality >= TRUSTED_QUALITY
            new.candidates, new.best, new.rt = dense, best, best.rt
        if new.index == self._checking:  # (a check without a dense pose, or not close: every CHECK_EVERY again)
            self._checking, self._trusted = None, self._trusted + 1 if trusted else 0
        for f in self.history:
            if f.best is None or f.best.method == "sparse" or f.phase is None:
                continue
            if f.final:  # (gone out already: a seed if its pose did)
                if f.result is not None and f.result.pose is not None:
                    self.chain.seed(f.index, f.best.rt, f.phase)
            elif self.gates.doubt(f.time_us, f.best.pose) is None:
                self.chain.seed(f.index, f.best.rt, f.phase)
                f.waiting = False

    def dense_late(self, f: Frame) -> None:
        """``f``'s dense pairs with the partners on both sides it has not been paired with (a frame the chain waited
        for in vain, or whose sparse poses the gates doubt). (All of them: stopping at the first that fitted 0.8 of
        the map's edges took two-projectors uncalibrated from 99.17 to 96.35 %; these poses re-seed the chain.) Live,
        none for a frame :data:`LIVE_LATE_US` old (:attr:`now_us`): its result says ``late``."""
        if self.too_late(f):
            f.failure = FrameResult(f.index, f.time_us, None, 0, FrameReason.LATE)
            self.late += 1
            return
        partners = [*self.history.partners(f, earlier=True), *self.history.partners(f, earlier=False)]
        for other in partners:
            if other.index not in f.tried:
                a, b = (other, f) if other.index < f.index else (f, other)
                self._solve(a, b, f)
        self.after_dense(f)

    def too_late(self, f: Frame) -> bool:
        """Live, whether ``f`` is :data:`LIVE_LATE_US` old: no more dense pairs nor bridges for it."""
        return self.now_us is not None and self.now_us - f.time_us > LIVE_LATE_US

    def reset(self, frames: bool) -> None:
        """The chain starts afresh (``frames``: forgetting the frames it has); the frames it made wait take the
        dense way."""
        self.chain.reset(frames)
        self._trusted = 0
        for f in self.history:
            if f.waiting and not f.final:
                f.waiting = False
                self.dense_late(f)

    def before_finish(self, f: Frame) -> None:
        """Before ``f`` is judged: if the chain still waits for it, or the gates doubt every candidate and its best
        is the chain's, the dense way (the chain restarts in the second case); if it took the dense way and its
        best dense fit is weak (below :data:`~ipt.receiver.core.history.GOOD_QUALITY`), its untried partners too.
        (The dense tracker pairs a frame with its partners on both sides; here the later ones pose themselves
        sparsely and never pair with it, and a frame's earlier partner may show other content: realcam's frames
        that took the dense way had MAE 2.50 / 2.11 mm against the dense tracker's 1.30 / 1.24 on the same
        frames.)"""
        if f.waiting:
            f.waiting = False
            self.dense_late(f)
        elif posed(f) and all(self.gates.doubt(f.time_us, c.pose) is not None for c in f.candidates):
            self.reset(False)
            self.dense_late(f)
            drop_sparse(f)
        elif f.tried and not posed(f) and (f.best is None or f.best.quality < GOOD_QUALITY):
            self.dense_late(f)

    def bridge_ready(self) -> bool:
        """Whether the bridge may look at the frames kept: once a frame may want it (its dense pairs failed). The
        bridge prepares the three frames of a bridge it tries (:meth:`prepare`, its ``prepare``), not every frame
        kept: on fast, the frames the chain refused took 1.9 dense preparations each when every kept frame was
        prepared."""
        return any(not f.final and f.best is None and f.tried for f in self.history)

    def prepare(self, f: Frame) -> None:
        """``f``'s dense preparation (undistortion, signal mask, alignment features), if it has none yet."""
        self._prepare(f)


def drop_sparse(f: Frame) -> None:
    """``f`` without the chain's candidates (the gates doubted them all): the dense ones, if any, are judged alone,
    and a doubted sparse pose does not join the gates' motion (where a dense fit's does: a sparse fit holds to
    the pose the chain predicted, so one the gates doubt is the chain gone astray, and fed to the motion it
    leads the dense way's guesses astray too: two-projectors uncalibrated lost frames 862-901 after one)."""
    f.candidates = [c for c in f.candidates if c.method != "sparse"]
    f.best = max(f.candidates, key=lambda c: c.quality, default=None)
    f.rt = f.best.rt if f.best is not None else None


def posed(f: Frame) -> bool:
    """``f``'s best pose is the sparse chain's: it goes out at once, waiting for no later frame."""
    return f.best is not None and f.best.method == "sparse"
