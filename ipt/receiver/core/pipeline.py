"""Camera frames in, poses out: pairing → alignment → difference → pose → gates, with the reason when none.

Pure apart from the detector's C library: frames and their capture times go in, results come out, in
frame order. The pipeline keeps the last few frames, what it learnt about the projector's phase and the
camera's recent motion.

Two ways through, chosen by the profile (:meth:`PipelineConfig.profile`):

**paper** (Algorithm 2 as published, ``alignment: sampled_lines``, ``pose.method: apriltag``): each
frame against the previous one (lag 1), the paper's integer shift, the median threshold, AprilTag, IPPE.

**ipt** (the default). Each frame is undistorted once and its signal mask taken (no signal in the drone's
shadow or beyond the projection). A *pair* is two frames of opposite projector phase (a time step close to
an odd number of projector periods); the floor homography between them comes from their content
(:mod:`ipt.receiver.core.imagealign`), their difference is brightness-matched and masked where content changed
(:func:`~ipt.receiver.core.demodulator.pair_difference`). The pose of a frame comes from the whole visible map
(:mod:`ipt.receiver.core.track`), started from the partner frame's pose carried by the homography, or from the
recent motion; AprilTag acquires when there is neither, and checks the track now and then. A pair serves
both its frames: a frame whose earlier partners fail (its pair straddles a change of the video, or its
exposure a flip) waits up to ``lookahead_frames`` for a later partner. Results come out in frame order, so
a pose may leave up to that many frames after its frame.

Gates (both profiles, where configured): a pose far from where the recent motion puts the camera is held
back (``inconsistent``); before that motion is known, only a certain pose goes out (``unconfirmed``); a
jump faster than a drone flies is held back (``motion_jump``) until it repeats.
"""

from __future__ import annotations

import math
import time
from collections import Counter, defaultdict, deque
from dataclasses import replace

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.config.models import PipelineConfig
from ipt.receiver.core import kernels
from ipt.receiver.core.acquire import ACQUIRE_LIT_SHARE, Acquisition
from ipt.receiver.core.bridge import ContentBridge
from ipt.receiver.core.demodulator import (
    PairDifference,
    Undistorter,
    binned,
    ksize_for,
    luminance,
    pair_difference,
    undistorted_lit,
)
from ipt.receiver.core.detection import Detector, DetectorError
from ipt.receiver.core.framecheck import RESTARTS, frame_problem
from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.gates import PoseGates
from ipt.receiver.core.history import GOOD_QUALITY, Candidate, Frame, FrameHistory, Pair, Prepared
from ipt.receiver.core.imagealign import AlignTarget, alignment_features, floor_warp_between, warp_image
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.motion import MotionTrack, floor_warp
from ipt.receiver.core.paperway import PaperWay
from ipt.receiver.core.phaseclock import PhaseClock
from ipt.receiver.core.pose import Pose, pose_of, rt_of
from ipt.receiver.core.reasons import PAIR_FAILURES, SHADOWED_SHARE, FrameReason
from ipt.receiver.core.scales import DetectScale, ScaleChooser
from ipt.receiver.core.secondlook import SecondLook
from ipt.receiver.core.sparse import SparseCamera
from ipt.receiver.core.sparsechain import LiveChain, chain_settings, fitter
from ipt.receiver.core.sparsestage import SparseStage
from ipt.receiver.core.sparsestage import posed as sparse_posed
from ipt.receiver.core.track import (
    MaskRenderer,
    TrackResult,
    TrackSettings,
    carried_pose,
    coarse_shift,
    shifted_pose,
    slope_noise,
    track_pose,
)
from ipt.tagmap import TagMap, pixel_to_arena

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
Guess = tuple[tuple[F64, F64], bool]
"""A first guess of a frame's pose, OpenCV's (rvec, tvec), and whether it is close (:meth:`Pipeline._initial_pose`)."""

#: A gap in capture times longer than this (or time going backwards) starts pairing afresh.
MAX_GAP_US = 100_000
#: A predicted warp that moves the image centre further than this fraction of the width is not trusted.
MAX_PREDICTED_MOVE = 0.25
#: Without a pose for this long the track is lost, and AprilTag looks for tags again.
LOST_AFTER_US = 50_000
#: A coarse search whose normalised correlation peak is weaker than this is not followed.
MIN_COARSE_SCORE = 0.1
#: ... and while the track fails from its guesses, once the newest pose is older than this.
SEARCH_AFTER_US = 20_000


class Pipeline:
    """The receiver's per-frame processing, for either profile (see :meth:`PipelineConfig.profile`)."""

    def __init__(
        self, tag_map: TagMap, camera: CameraInfo, cfg: PipelineConfig, projector_hz: float, detector: Detector
    ) -> None:
        """``detector``: AprilTag as configured (``cfg.detector``), made by the caller
        (:func:`ipt.receiver.detect.detector.pipeline_detector`); it may still be starting (its helper process
        imports while this sets up: a restarted daemon poses sooner), this waits for it last. The pipeline
        owns it from here: :meth:`close` closes it."""
        demod = cfg.demodulation
        self.sensor = camera
        """The camera as it delivers frames; :attr:`camera` is the one the pipeline works with."""
        self.binning = demod.binning(camera)
        """The side of the square of the sensor's pixels that :attr:`camera`'s pixel averages: 1, or more for a
        camera much wider than the ipt profile's settings are made for (``demodulation.work_width_px``)."""
        camera = camera.binned(self.binning)
        self.tag_map, self.camera, self.cfg, self.projector_hz = tag_map, camera, cfg, projector_hz
        self.history = FrameHistory(projector_hz, cfg.demodulation.pairing)
        """The frames kept for pairing, and the rules that pair them."""
        self.pair_span_us = self.history.pair_span_us
        """Frames further apart than this are never paired (:data:`~ipt.receiver.core.history.MAX_PAIR_PERIODS`)."""
        self.detector, self.ipt = detector, demod.alignment == "gradient"
        self.tracking = self.ipt and cfg.pose.method == "track"
        size = (camera.width_px, camera.height_px)
        self.undistort = (
            Undistorter(camera.camera_matrix, camera.dist_coeffs, size) if self.ipt and demod.undistort else None
        )
        self.pinhole = replace(camera, distortion=(0.0, 0.0, 0.0, 0.0, 0.0)) if self.undistort is not None else camera
        self.edges = MapEdges.from_tag_map(tag_map) if self.tracking else None
        if self.ipt:
            kernels.warm_in_background()  # ready before the first pair: a live camera must not wait
        mask = tag_map.render_mask() if self.tracking else None  # (one rendering for the coarse search and the map's)
        self.masks = MaskRenderer(mask, pixel_to_arena(tag_map)) if mask is not None else None
        scale = camera.width_px / 640
        t = cfg.pose.track
        self.track_settings = TrackSettings(
            search_px=t.search_px * scale, min_inliers=t.min_inliers, rolling_shutter=t.rolling_shutter
        )
        base = DetectScale(ksize_for(demod.blur_ksize, camera.width_px), cfg.detector.quad_decimate)
        self.scales = ScaleChooser(tag_map, camera.fx_px, min(size), base)
        """Filter and decimation sizes for AprilTag, from the height the camera was last seen at."""
        self.lookahead = demod.lookahead_frames if self.ipt else 0
        self._pending: deque[Frame] = deque()
        self._pairs: dict[tuple[int, int], Pair | None] = {}
        self.gates = PoseGates(cfg.pose)
        """The gates on the poses, and the motion of the poses they judged (the first guesses' last resort)."""
        coverage = self.undistort.coverage if self.undistort is not None else None
        self.bridge = ContentBridge(self.history, self.gates.motion, self, coverage, self.lookahead, t.rolling_shutter)
        """The bridge over frames whose exposure spans a content change (tracking only; not under a rolling shutter)."""
        self.second_look = SecondLook(self.history, self.gates, self)
        """The second look at frames whose fits the recent motion doubts (tracking only)."""
        self._guide = MotionTrack()
        """The motion of every frame's best candidate as soon as it is found: the first guesses' source."""
        self._view_px = max(1, cv2.countNonZero(coverage) if coverage is not None else size[0] * size[1])
        self.reasons: Counter[str] = Counter()
        self.stage_seconds: dict[str, float] = defaultdict(float)
        """Processor time of the pipeline's thread spent per stage (the AprilTag helper process's own time is not
        in "detect"), for benchmarks and diagnostics."""
        self.acquisition = Acquisition(self, tag_map, self.pinhole, cfg, detector, mask)
        """AprilTag's acquisition and check of the track, and the search of the whole map."""
        self.sparse: SparseStage | None = None
        """The sparse tracker (``cfg.tracker`` "sparse", tracking only): poses a frame first, the dense way second."""
        if self.edges is not None and cfg.tracker == "sparse":
            lens = SparseCamera.of(camera.camera_matrix, camera.dist_coeffs, size)
            fit = fitter(lens, self.edges, *chain_settings(camera.width_px))
            chain = LiveChain(lens, self.edges, fit, projector_hz, wait=self.lookahead > 0)
            self.sparse = SparseStage(
                chain, self.history, self.gates, self._solve, self._dense, self.add_candidate, self.lap, self._tracked
            )
            self.bridge.prepare, self.bridge.too_late = self.sparse.prepare, self.sparse.too_late  # (see the bridge)
        self.dense_prepared = 0
        """Frames given the dense preparation after their arrival (sparse tracker), for tests and benchmarks."""
        self.paper = PaperWay(cfg, camera, tag_map, detector, self.history, self.gates, self.lap)
        """The paper's way through (the paper profile)."""
        self.detector.wait_ready()

    def close(self) -> None:
        """End the detector (and its helper process) now rather than when this object is collected."""
        self.detector.close()

    @property
    def detector_runs(self) -> int:
        """AprilTag runs so far (either profile)."""
        return self.acquisition.runs + self.paper.detector_runs

    @property
    def detector_replacements(self) -> tuple[int, int]:
        """Helper processes of the detector replaced so far: (for their memory, after a failure)."""
        backend = getattr(self.detector, "backend", None)
        return (getattr(backend, "recycles", 0), getattr(backend, "restarts", 0))

    # -- the interface -------------------------------------------------------------------------------

    def prepare(self, frame: U8) -> Prepared:
        """The work on ``frame`` that needs no other frame (its check, lightness, binning, undistortion, signal mask and
        alignment features), for :meth:`process`. It reads no state that processing changes, so it may run
        on another thread, one frame ahead of the pairing (a second core's share of the work)."""
        problem = frame_problem(frame, self.sensor.height_px, self.sensor.width_px)
        if problem is not None:
            return Prepared(problem, None, None, None)
        lum = binned(luminance(frame, self.cfg.demodulation.lightness), self.binning)
        if not self.ipt or self.sparse is not None:  # (the sparse tracker prepares the rest when it is needed)
            return Prepared(None, lum, None, None)
        lum, signal = undistorted_lit(lum, self.undistort)
        return Prepared(None, lum, signal, alignment_features(lum))

    def _tracked(self) -> None:
        self.acquisition.since_verify += 1

    def _lit_share(self, signal: U8) -> float:
        """The share of the view (the undistorted sensor's pixels) that a frame's signal mask ``signal`` lights."""
        return cv2.countNonZero(signal) / self._view_px

    def _dense(self, f: Frame, features: bool = False) -> None:
        """The dense preparation of ``f`` (sparse tracker), once: its undistorted lightness and signal mask (its lit
        share), its alignment features only for a pair (``features``: 0.2 of 1.5 ms, of no use to a frame at rest)."""
        if f.raw is None or (f.signal is not None and (f.features is not None or not features)):
            return
        t0 = time.thread_time()
        if f.signal is None:
            f.lum, f.signal = undistorted_lit(f.raw, self.undistort)
            f.lit_share = self._lit_share(f.signal)
            self.dense_prepared += 1
        if features and f.features is None:
            f.features = alignment_features(f.lum)
        self.lap("prepare", t0)

    def process(
        self, index: int, frame: U8 | Prepared, capture_time_us: int, waited_us: int | None = None
    ) -> list[FrameResult]:
        """Take camera frame ``index`` (H×W×3 RGB, or H×W grey: a mono camera's, or the luma plane of a YUV or JPEG
        frame; or what :meth:`prepare` made of it), and for a live camera's frame how long it ``waited_us`` since its
        grab (the sparse stage's live rule); return the results that became final, in frame order (this frame's,
        earlier ones' that waited for it, or none yet). Never raises for a bad frame: its result says why
        (:mod:`ipt.receiver.core.framecheck`: "bad_frame", "wrong_size", "dark", "saturated"; "time_gap" for the
        first frame after a gap in capture times, which pairing starts afresh from)."""
        t0 = time.thread_time()
        ready = frame if isinstance(frame, Prepared) else self.prepare(frame)
        problem = ready.problem
        if problem is not None:  # not an image of this camera, or one without signal: never a partner
            if problem in RESTARTS:
                self._restart()
            elif self.sparse is not None:
                self.sparse.reset(True)
            bad = Frame(index, capture_time_us, np.zeros((0, 0), np.uint8), final=True)
            bad.result = FrameResult(index, capture_time_us, None, 0, problem)
            self._pending.append(bad)
            return self._emit()
        gap = bool(self.history) and not 0 < capture_time_us - self.history[-1].time_us <= MAX_GAP_US
        if gap:
            self._restart()  # a jump in the video, or time going backwards
        assert ready.lum is not None
        new = Frame(index, capture_time_us, ready.lum, ready.signal, ready.features)
        if ready.signal is not None:
            new.lit_share = self._lit_share(ready.signal)
        if self.sparse is not None:
            new.raw, self.sparse.now_us = ready.lum, None if waited_us is None else capture_time_us + waited_us
        if gap:  # its reason unless a later frame pairs with it
            new.failure = FrameResult(index, capture_time_us, None, 0, FrameReason.TIME_GAP)
        t0 = self.lap("lightness", t0)
        self.history.append(new)
        self._pending.append(new)
        if not self.ipt:
            new.result = self.paper.solve(new)
            new.final = True
        else:
            self._ipt(new)
        return self._emit()

    def flush(self) -> list[FrameResult]:
        """The results still waiting for later frames (at the end of a recording)."""
        self._finish_pending()
        return self._emit()

    def live_hints(self) -> tuple[PhaseClock | None, bool]:
        """For a live daemon's choice of frames (:mod:`ipt.receiver.liverun`): the sparse chain's projector phase
        clock (a snapshot another thread may keep; None: none yet) and whether it judged the content to move."""
        return (None, False) if (s := self.sparse) is None else (s.chain.clock(), s.chain.content_moved())

    def finish_before(self, time_us: int) -> list[FrameResult]:
        """The results, in frame order, of the frames waiting for later partners that no frame captured at ``time_us``
        or later can be (it is more than :data:`~ipt.receiver.core.history.MAX_PAIR_PERIODS` projector periods after
        them). Processing that frame would give the same results, only after it: a live daemon that dropped frames
        calls this before handing over the next frame it took, so their results do not wait for it."""
        for f in self._pending:  # in frame order: the frames before one still waiting are final or finished here
            if not f.final and time_us - f.time_us > self.pair_span_us:
                self._finish(f)
        return self._emit()

    def _finish_pending(self) -> None:
        for f in (f for f in self._pending if not f.final):
            self._finish(f)

    # -- frames and results ---------------------------------------------------------------------------

    def _restart(self) -> None:
        """Start pairing afresh: earlier frames get no more partners, the motion is forgotten."""
        self._finish_pending()
        self.history.clear()
        self._pairs.clear()
        self.gates.motion.clear()
        self._guide.clear()
        self.scales.forget()
        if self.sparse is not None:
            self.sparse.reset(True)

    def _emit(self) -> list[FrameResult]:
        out = []
        while self._pending and self._pending[0].final:
            f = self._pending.popleft()
            result = f.result or FrameResult(
                f.index, f.time_us, None, 0, FrameReason.FIRST_FRAME if not f.tried else FrameReason.NO_TAGS
            )
            if result.pose is None and result.reason in PAIR_FAILURES:
                self._dense(f)  # (its lit share, with the sparse tracker)
            if result.pose is None and result.reason in PAIR_FAILURES and f.lit_share < SHADOWED_SHARE:
                result = replace(result, reason=FrameReason.SHADOWED)
            if self.acquisition.detector_failed:
                result = replace(result, detector_failed=True)
                self.acquisition.detector_failed = False
            self.reasons[result.reason] += 1
            out.append(result)
        live = {f.index for f in self.history}
        self._pairs = {k: v for k, v in self._pairs.items() if k[0] in live and k[1] in live}
        self.bridge.keep_only(live)
        return out

    def lap(self, stage: str, t0: float) -> float:
        """Count this thread's processor time since ``t0`` to ``stage`` (:attr:`stage_seconds`); the time now."""
        t1 = time.thread_time()
        self.stage_seconds[stage] += t1 - t0
        return t1

    # -- the ipt way ----------------------------------------------------------------------------------

    def _ipt(self, new: Frame) -> None:
        """Every pair ``new`` makes with an earlier frame gives each of its two frames a candidate pose; a
        frame takes its best candidate (the one that fits most of the map's edges: a pair whose content
        changed between its frames doubles the edges and fits fewer) once no later frame can pair with it,
        and the gates judge it then, in frame order. Once ``new`` has a good pose its other partners are paired
        only for their own sake, if they have none (fast: 84.2 → 88.3 %: a frame exposed across a flip often has
        its strongest pair with its later neighbour, which had found its own pose with the frame before). A pair
        that poses the partner where ``new`` found none is tried again for ``new`` from that pose (sparse tracker)."""
        if self.sparse is None or self.sparse.step(new):
            good = False
            for partner in self.history.partners(new, earlier=True):
                if not good:
                    self._solve(partner, new, new)
                if not partner.final and not (good and partner.best is not None):
                    had = partner.best
                    self._solve(partner, new, partner)
                    if self.sparse is not None and new.best is None and partner.best is not had:
                        self._solve(partner, new, new)
                good = new.best is not None and new.best.quality >= GOOD_QUALITY
            if self.sparse is not None:
                self.sparse.after_dense(new)
        if self.tracking and (self.sparse is None or self.sparse.bridge_ready()):
            self.bridge.offer(new)
        for f in self._pending:
            if f.final or f.waiting:
                continue
            wait = self.lookahead + (self.bridge.wait(f) if self.tracking else 0)
            if sparse_posed(f) or self._good_now(f) or new.index - f.index >= wait:
                self._finish(f)

    def _good_now(self, f: Frame) -> bool:
        """With the sparse tracker, whether ``f`` (a check, or a frame the chain refused) goes out now: its dense pose
        fits well (:data:`GOOD_QUALITY`) and the gates do not doubt it (later frames mostly pose themselves sparsely
        and never pair with it: waiting held it, and the frames after it, two frames longer for nothing)."""
        best = f.best
        if self.sparse is None or best is None or best.quality < GOOD_QUALITY:
            return False
        return self.gates.doubt(f.time_us, best.pose) is None

    def _finish(self, f: Frame) -> None:
        """Judge ``f``'s candidates (earlier frames are final already), after a second look if the recent motion doubts
        them all: the best fit it does not doubt, or else the best fit, which the gates then hold back. A frame the
        sparse chain still waits for, or whose sparse poses the gates all doubt, takes the dense way first."""
        if self.sparse is not None:
            self.sparse.before_finish(f)
        f.final = True
        if self.tracking:
            self.second_look.look(f)
        if not f.candidates:
            f.result = f.failure
            return
        ranked = sorted(f.candidates, key=lambda c: -c.quality)
        best = next((c for c in ranked if self.gates.doubt(f.time_us, c.pose) is None), ranked[0])
        later = [(g.time_us, g.best.pose) for g in self.history if g.index > f.index and g.best is not None]
        f.result = self.gates.judge(f.index, f.time_us, best.pose, best.tags, best.method, best.partner, later)
        f.rt = best.rt if f.result.pose is not None else None

    def pair(self, a: Frame, b: Frame) -> Pair | None:
        """The alignment and difference of ``a`` (earlier) and ``b`` (later), computed once."""
        key = (a.index, b.index)
        if key in self._pairs:
            return self._pairs[key]
        self._dense(a, True)  # (the sparse tracker's frames are prepared here, when a dense pair first needs them)
        self._dense(b, True)
        t0 = time.thread_time()
        assert a.features is not None
        assert b.features is not None
        assert a.signal is not None
        assert b.signal is not None
        if b.target is None:
            b.target = AlignTarget.of(b.features, b.signal)
        warp = floor_warp_between(b.target, a.features, self.predicted_warp(a, b), a.signal)
        t0 = self.lap("align", t0)
        pair = None
        if warp is not None:
            coverage = self.undistort.coverage if self.undistort is not None else None
            pair = Pair(warp, pair_difference(a.lum, b.lum, warp, a.signal, b.signal, coverage))
        self.lap("difference", t0)
        self._pairs[key] = pair
        return pair

    def predicted_warp(self, a: Frame, b: Frame, poses: tuple[Pose, Pose] | None = None) -> F64 | None:
        """The floor homography from ``a`` to ``b`` from their ``poses``, else those found or predicted, if trusted."""
        if not self.cfg.demodulation.predict_warp:
            return None
        k = self.pinhole.camera_matrix
        if poses is None:
            found = [pose_of(*f.rt) if f.rt is not None else self.gates.motion.pose_at(f.time_us) for f in (a, b)]
            if found[0] is None or found[1] is None:
                return None
            poses = (found[0], found[1])
        warp = floor_warp(k, poses[0], poses[1])
        if warp is None:
            return None
        centre = np.array([self.camera.width_px / 2, self.camera.height_px / 2, 1.0])
        moved = warp @ centre
        off_px = float(np.linalg.norm(moved[:2] / moved[2] - centre[:2])) if moved[2] > 0 else math.inf
        return None if off_px > MAX_PREDICTED_MOVE * self.camera.width_px else warp

    def difference_in(self, pair: Pair, target_is_later: bool) -> PairDifference:
        """The pair's difference in the target frame's geometry, as target minus other."""
        if target_is_later:
            return pair.later
        if pair.earlier is None:
            inverse = np.asarray(np.linalg.inv(pair.warp), np.float64)
            d = pair.later
            diff = -np.asarray(warp_image(d.diff, inverse, border=cv2.BORDER_CONSTANT), np.float32)
            valid = np.asarray(cv2.warpPerspective(d.valid, inverse, d.valid.shape[::-1], flags=cv2.INTER_NEAREST))
            pair.earlier = PairDifference(diff, np.asarray(valid, np.uint8), d.amplitude, d.changed)
        return pair.earlier

    def _solve(self, a: Frame, b: Frame, target: Frame) -> None:
        """A candidate pose of ``target`` (``a`` or ``b``) from the pair (a earlier, b later)."""
        other = b if target is a else a
        target.tried.add(other.index)
        if self._rests(target, other):
            reason = FrameReason.NO_TAGS
            target.failure = FrameResult(target.index, target.time_us, None, 0, reason, partner=other.index)
            return
        pair = self.pair(a, b)
        if pair is None:
            target.failure = FrameResult(
                target.index, target.time_us, None, 0, FrameReason.NO_ALIGNMENT, partner=other.index
            )
            return
        diff = self.difference_in(pair, target is b)
        warp_other_to_target = pair.warp if target is b else np.asarray(np.linalg.inv(pair.warp), np.float64)
        t0 = time.thread_time()
        reason = FrameReason.NO_TAGS
        guess = self._initial_pose(target, other, warp_other_to_target)
        tracked: TrackResult | None = None
        if self.tracking and guess is not None:
            tracked = self.track_guessed(diff, guess, target.signal)
            t0 = self.lap("track", t0)
            if tracked is None:
                reason = FrameReason.LOST
            elif self.cfg.pose.track.verify_every and self.acquisition.since_verify >= self.cfg.pose.track.verify_every:
                if not self.acquisition.verified(tracked, diff, t0):
                    tracked, reason = None, FrameReason.TRACK_DISAGREES
                t0 = time.thread_time()
        candidate: Candidate | None = None
        if tracked is not None:
            self.acquisition.since_verify += 1
            target.phase, other.phase = tracked.sign, -tracked.sign
            candidate = self.candidate(tracked, other.index)
        elif not self.tracking or guess is None or (not guess[1] and self._lost(target)):
            # AprilTag when there is no track to follow: at the start, or once the motion it predicted from
            # is too old (while it lasts, a pair that fails is just a bad pair: another partner may do).
            try:
                candidate = self.acquisition.acquire(target, other, diff)
            except DetectorError:
                target.failure = FrameResult(target.index, target.time_us, None, 0, FrameReason.DETECTOR_FAILED)
                self.acquisition.detector_failed = True
                return
            t0 = self.lap("detect", t0)
        elif reason == FrameReason.LOST and target.best is None and self._lost(target, SEARCH_AFTER_US):
            candidate = self.acquisition.search_map(target, other, diff)  # the track has been failing from its guesses
            t0 = self.lap("detect", t0)
        if candidate is None:
            target.failure = FrameResult(target.index, target.time_us, None, 0, reason, partner=other.index)
            return
        self.lap("pose", t0)
        self.add_candidate(target, candidate)

    def _rests(self, target: Frame, other: Frame) -> bool:
        """Whether ``target``'s pair with ``other`` is left unmade: only AprilTag could use it (no partner's pose, no
        recent motion) and it rests on this mostly unlit view (:meth:`~ipt.receiver.core.acquire.Acquisition.rests`)."""
        self._dense(target)  # (its lit share)
        if target.lit_share >= ACQUIRE_LIT_SHARE or other.rt is not None:
            return False
        no_track = not self.tracking or self._guide.pose_at(target.time_us) is None or self._lost(target)
        return no_track and self.acquisition.rests(target, later=other.index > target.index)

    def add_candidate(self, target: Frame, candidate: Candidate) -> None:
        target.candidates.append(candidate)
        if target.best is None or candidate.quality > target.best.quality:
            target.best = candidate
            target.rt = candidate.rt
            p = candidate.pose
            self.scales.seen_at(float(p.position_m[2]))
            self._guide.add(target.time_us, p.position_m, p.r_arena_cam, float(np.linalg.norm(p.position_std_m)))

    def _lost(self, target: Frame, after_us: int = LOST_AFTER_US) -> bool:
        """No recent pose to track from: the newest is more than ``after_us`` before ``target``, and a frame since
        has failed (frames the sparse chain still waits for have not: else a dense pair beside them searches the
        map, 37 times in vain on moving-content, 27 ms each). A frame the gates held back has no pose to track from
        (fits gone astray kept the track alive: two-projectors uncalibrated, 30 frames, the motion 15 cm off)."""
        posed = [f for f in self.history if f.best is not None and (f.result is None or f.result.pose is not None)]
        newest = max((f.time_us for f in posed), default=None)
        if newest is None:
            return True
        since = [f for f in self.history if newest < f.time_us < target.time_us]
        return target.time_us - newest > after_us and not (since and all(f.waiting for f in since))

    def candidate(self, tracked: TrackResult, partner: int) -> Candidate:
        pose = tracked.estimate()
        rt = (tracked.rvec, tracked.tvec)
        return Candidate(pose, rt, len(tracked.tags), "track", partner, tracked.inlier_fraction)

    def track_from(
        self, diff: PairDifference, init: tuple[F64, F64], lit: U8 | None = None, coarse_px: float = 0.0
    ) -> TrackResult | None:
        """The pose from the map's edges on ``diff`` from ``init``; only where ``lit`` (the target frame's
        signal mask) too, if given: samples in the drone's shadow find no step, and counted as tried they
        would sink the inlier fraction of a right pose once the shadow fills most of the view (a landing
        drone). ``coarse_px``: how far off ``init`` may be (:func:`~ipt.receiver.core.track.track_pose`)."""
        assert self.edges is not None
        if diff.noise is None:
            diff.noise = slope_noise(diff.diff, diff.valid)
        result = track_pose(
            diff.diff,
            self.pinhole.camera_matrix,
            self.edges,
            init[0],
            init[1],
            self.track_settings,
            None,
            diff.valid if lit is None else np.minimum(diff.valid, lit),
            coarse_px=coarse_px,
            noise=diff.noise,
        )
        t = self.cfg.pose.track
        if result is None or result.inlier_fraction < t.min_inlier_fraction:
            return None
        if not result.cells_confirm(t.min_cell_agreement):  # (few clear cells: fewer may disagree)
            return None
        if len(result.tags) < self.cfg.pose.min_tags:
            return None
        return result

    def track_guessed(self, diff: PairDifference, guess: Guess, lit: U8 | None) -> TrackResult | None:
        """The pose tracked from ``guess``: from its start if close, else from a search around it; a close start
        that fails is searched around too (the partner's pose or the pair's homography was off), unless the
        search keeps the start (no clear peak): the same track again would fail again."""
        init, close = guess
        tracked = self.track_from(diff, init if close else self.coarse(diff, init), lit)
        if tracked is None and close and (moved := self.coarse(diff, init)) is not init:
            tracked = self.track_from(diff, moved, lit)
        return tracked

    def _initial_pose(self, target: Frame, other: Frame, warp_other_to_target: F64) -> Guess | None:
        """A first guess of ``target``'s pose and whether it is close (within a few pixels): the partner's
        pose carried by the pair's homography (close), else the recent motion's prediction (not)."""
        if other.rt is not None:
            size = (self.camera.width_px, self.camera.height_px)
            carried = carried_pose(self.pinhole.camera_matrix, size, other.rt, warp_other_to_target)
            if carried is not None:
                return carried, True
        predicted = self._guide.pose_at(target.time_us)
        return None if predicted is None else (rt_of(*predicted), False)

    def coarse(self, diff: PairDifference, init: tuple[F64, F64]) -> tuple[F64, F64]:
        """``init`` moved by the image shift that best lays the map on the difference."""
        assert self.masks is not None
        size = (self.camera.width_px, self.camera.height_px)
        k = self.pinhole.camera_matrix
        dx, dy, score = coarse_shift(diff.diff, self.masks.render(k, init[0], init[1], size), diff.valid)
        if abs(score) < MIN_COARSE_SCORE:
            return init
        moved = shifted_pose(k, init[0], init[1], dx, dy, size)
        return init if moved is None else moved


__all__ = ["FrameResult", "Pipeline", "Prepared"]
