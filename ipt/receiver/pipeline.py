"""One frame in, at most one pose out: pairing → demodulation → detection → pose, with the reason when none.

Pure apart from the detector's C library: frames and their capture times go in, results come out; the
pipeline keeps only the last few lightness images and what it learnt about the projector's phase.

Pairing (``demodulation.pairing``):
- ``previous``: the paper's lag 1. With a 120 FPS camera and 60 Hz phases only every other pair
  straddles a flip, so at most half the frames can carry the tags.
- ``opposite_phase``: among the last few frames, the one whose time step is closest to an odd number of
  projector periods (one period at 120 FPS: lag 2; lag 3 at 180 FPS), then the next best on a miss.
  Timing comes from the frames' capture times, so dropped frames and drifting clocks are handled.

Polarity (``demodulation.polarity``): the difference shows the tags with dark borders when the current
frame is the ``+ΔL`` phase. ``both`` tries the image and its inverse (the paper's phase is unknown);
``tracked`` predicts each frame's phase from what earlier detections revealed and tries the other only on
a miss.
"""

from __future__ import annotations

import time
from collections import Counter, defaultdict, deque
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.config.models import PipelineConfig
from ipt.receiver.demodulator import alignment_features, demodulate, lightness
from ipt.receiver.detector import DetectorError, TagDetection, TagDetector
from ipt.receiver.motion import MotionTrack, floor_warp
from ipt.receiver.pose import PoseEstimate, solve_pose
from ipt.tagmap import TagMap

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

#: Frames kept for pairing (lags up to this many frames back).
HISTORY = 4
#: A pairing whose time step is this far (in projector periods) from an odd number is not tried. Half a
#: period is still tried as a fallback: when an exposure straddles a flip, its lag-2 partner straddles the
#: same way and the signal cancels, while the neighbour on the other side of the flip keeps half of it.
MAX_PHASE_ERROR = 0.55
#: The motion gate compares with the last accepted pose only if it is this recent.
GATE_WINDOW_US = 250_000
#: After this many gated poses in a row the track is re-initialised (the earlier pose was the wrong one).
GATE_RESET_AFTER = 4
#: A gap in capture times longer than this (or time going backwards) starts pairing afresh.
MAX_GAP_US = 100_000


@dataclass(frozen=True)
class FrameResult:
    """What one camera frame gave."""

    index: int
    capture_time_us: int
    pose: PoseEstimate | None
    num_detections: int
    reason: str
    """"pose" when a pose was made; otherwise why not (e.g. "first_frame", "no_tags", "bad_frame")."""
    reset: bool = False
    """The pose re-initialises the track (it disagreed with the previous ones, which were dropped)."""


@dataclass
class _Past:
    index: int
    time_us: int
    lightness: U8
    features: F32 | None
    """The frame's alignment features ('gradient' alignment), computed once."""


#: A predicted warp that moves the image centre further than this fraction of the width is not trusted.
MAX_PREDICTED_MOVE = 0.25


class Pipeline:
    """The receiver's per-frame processing, for either profile (see :meth:`PipelineConfig.profile`)."""

    def __init__(self, tag_map: TagMap, camera: CameraInfo, cfg: PipelineConfig, projector_hz: float = 60.0) -> None:
        self.tag_map, self.camera, self.cfg = tag_map, camera, cfg
        self.projector_hz = projector_hz
        self.detector = TagDetector(cfg.detector, known_ids=tag_map.by_id)
        self._history: deque[_Past] = deque(maxlen=HISTORY)
        self._phase: dict[int, int] = {}  # frame index -> +1 (the +ΔL phase) or -1, learnt from detections
        self._last_pose: tuple[int, PoseEstimate] | None = None
        self._track = MotionTrack()
        self._gated_in_a_row = 0
        self.reasons: Counter[str] = Counter()
        self.stage_seconds: dict[str, float] = defaultdict(float)
        """Processor time spent per stage (lightness, demodulate, detect, pose), for benchmarks."""
        self.detector_runs = 0

    def close(self) -> None:
        """End the detector (and its helper process) now rather than when this object is collected."""
        self.detector.close()

    @property
    def detector_replacements(self) -> tuple[int, int]:
        """Helper processes of the detector replaced so far: (for their memory, after a failure)."""
        backend = self.detector.backend
        return (getattr(backend, "recycles", 0), getattr(backend, "restarts", 0))

    def process(self, index: int, frame_rgb: U8, capture_time_us: int) -> FrameResult:
        """Process camera frame ``index``; never raises for a bad frame (the reason says what happened)."""
        result = self._process(index, frame_rgb, capture_time_us)
        self.reasons[result.reason] += 1
        return result

    # -- pairing -------------------------------------------------------------------------------------

    def _phase_error(self, dt_us: int) -> float:
        periods = dt_us * 1e-6 * self.projector_hz
        return float(abs(periods - (2 * np.floor(periods / 2) + 1)))

    def _candidates(self, now_us: int) -> list[_Past]:
        past = list(self._history)
        if self.cfg.demodulation.pairing == "previous":
            return past[-1:]
        scored = [(self._phase_error(now_us - p.time_us), -p.index, p) for p in past]
        good = [(e, i, p) for e, i, p in scored if e < MAX_PHASE_ERROR]
        good.sort(key=lambda t: (t[0], t[1]))
        return [p for _, _, p in good[:2]]

    def _predicted_sign(self, now_us: int, prev: _Past) -> int:
        """+1 if the current frame is probably the +ΔL phase (tags with dark borders), else -1."""
        if prev.index in self._phase:
            return -self._phase[prev.index]
        for p in reversed(self._history):
            if p.index in self._phase:
                flips = round((now_us - p.time_us) * 1e-6 * self.projector_hz)
                return self._phase[p.index] * (-1 if flips % 2 else 1)
        return 1

    # -- detection -----------------------------------------------------------------------------------

    def _detect(self, binary: U8, first_sign: int) -> tuple[tuple[TagDetection, ...], int]:
        """Detections and the sign they were found with (+1: dark borders as is)."""

        def image(sign: int) -> U8:
            return binary if sign == 1 else np.asarray(cv2.bitwise_not(binary), dtype=np.uint8)

        if self.cfg.demodulation.polarity == "both":
            self.detector_runs += 2
            found = {s: self.detector.detect(image(s)) for s in (1, -1)}
            best = max((1, -1), key=lambda s: len(found[s]))
            return found[best], best
        for sign in (first_sign, -first_sign):
            self.detector_runs += 1
            dets = self.detector.detect(image(sign))
            if len(dets) >= self.cfg.pose.min_tags:
                return dets, sign
        return (), first_sign

    # -- the frame -----------------------------------------------------------------------------------

    def _lap(self, stage: str, t0: float) -> float:
        """Add the time since ``t0`` to ``stage`` in :attr:`stage_seconds`; returns the time now."""
        t1 = time.perf_counter()
        self.stage_seconds[stage] += t1 - t0
        return t1

    def _predicted_warp(self, prev_us: int, now_us: int) -> F64 | None:
        """The floor homography from the earlier frame to this one, from the recent poses (or None)."""
        demod = self.cfg.demodulation
        if demod.alignment != "gradient" or not demod.predict_warp:
            return None
        before, after = self._track.pose_at(prev_us), self._track.pose_at(now_us)
        if before is None or after is None:
            return None
        warp = floor_warp(self.camera.camera_matrix, before, after)
        if warp is None:
            return None
        centre = np.array([self.camera.width_px / 2, self.camera.height_px / 2, 1.0])
        moved = warp @ centre
        if moved[2] <= 0:
            return None
        if np.linalg.norm(moved[:2] / moved[2] - centre[:2]) > MAX_PREDICTED_MOVE * self.camera.width_px:
            return None
        return warp

    def _process(self, index: int, frame_rgb: U8, capture_time_us: int) -> FrameResult:
        expected = (self.camera.height_px, self.camera.width_px, 3)
        if not isinstance(frame_rgb, np.ndarray) or frame_rgb.shape != expected or frame_rgb.dtype != np.uint8:
            self._history.clear()
            return FrameResult(index, capture_time_us, None, 0, "bad_frame")
        demod_cfg = self.cfg.demodulation
        t0 = time.perf_counter()
        now_l = lightness(frame_rgb, demod_cfg.lightness)
        now_f = alignment_features(now_l) if demod_cfg.alignment == "gradient" else None
        t0 = self._lap("lightness", t0)
        if self._history and not 0 < capture_time_us - self._history[-1].time_us <= MAX_GAP_US:
            self._history.clear()  # a jump in the video, or time going backwards
            self._track.clear()
        candidates = self._candidates(capture_time_us)
        result = FrameResult(index, capture_time_us, None, 0, "first_frame" if not self._history else "no_pair")
        for prev in candidates:
            features = (prev.features, now_f) if prev.features is not None and now_f is not None else None
            predicted = self._predicted_warp(prev.time_us, capture_time_us)
            demod = demodulate(prev.lightness, now_l, demod_cfg, predicted=predicted, features=features)
            t0 = self._lap("demodulate", t0)
            try:
                dets, sign = self._detect(demod.binary, self._predicted_sign(capture_time_us, prev))
            except DetectorError:  # the detector's helper process died or hung; a new one takes the next frame
                self._lap("detect", t0)
                result = FrameResult(index, capture_time_us, None, 0, "detector_failed")
                break
            t0 = self._lap("detect", t0)
            if not dets:
                result = FrameResult(index, capture_time_us, None, 0, "no_tags")
                continue
            self._phase[index], self._phase[prev.index] = sign, -sign
            result = self._pose(index, capture_time_us, dets)
            self._lap("pose", t0)
            break
        self._history.append(_Past(index, capture_time_us, now_l, now_f))
        for old in [i for i in self._phase if i < index - 4 * HISTORY]:
            del self._phase[old]
        return result

    def _doubtful(self, t_us: int, pose: PoseEstimate) -> str | None:
        """Why ``pose`` disagrees with the recent motion (the reason counted), or None if it does not."""
        cfg = self.cfg.pose
        if cfg.max_prediction_error_m is not None:
            predicted = self._track.pose_at(t_us)
            if predicted is None:
                # Nothing to check it against yet (the start, or after a gap): only a pose whose own
                # uncertainty is within the same bound goes out; the rest only feed the track.
                if float(np.linalg.norm(pose.position_std_m)) > cfg.max_prediction_error_m:
                    return "unconfirmed"
            elif float(np.linalg.norm(pose.position_m - predicted[0])) > cfg.max_prediction_error_m:
                return "inconsistent"
        if cfg.max_speed_mps is not None and self._last_pose is not None:
            last_us, last = self._last_pose
            dt_us = t_us - last_us
            if 0 < dt_us <= GATE_WINDOW_US:
                allowed_m = 0.05 + cfg.max_speed_mps * dt_us * 1e-6
                if float(np.linalg.norm(pose.position_m - last.position_m)) > allowed_m:
                    return "motion_jump"
        return None

    def _pose(self, index: int, t_us: int, dets: tuple[TagDetection, ...]) -> FrameResult:
        pose = solve_pose(dets, self.tag_map, self.camera, self.cfg.pose)
        if pose is None:
            return FrameResult(index, t_us, None, len(dets), "pose_rejected")
        doubt = self._doubtful(t_us, pose)
        # Every solved pose goes into the track, gated or not: its fit is robust, and a gate that fed only
        # on what it let through could lock onto a wrong track and reject every good pose after it.
        self._track.add(t_us, pose.position_m, pose.r_arena_cam, float(np.linalg.norm(pose.position_std_m)))
        reset = False
        if doubt in ("inconsistent", "unconfirmed"):
            return FrameResult(index, t_us, None, len(dets), doubt)
        if doubt == "motion_jump":
            self._gated_in_a_row += 1
            if self._gated_in_a_row < GATE_RESET_AFTER:
                return FrameResult(index, t_us, None, len(dets), doubt)
            reset = True
        self._gated_in_a_row = 0
        self._last_pose = (t_us, pose)
        return FrameResult(index, t_us, pose, len(dets), "pose", reset)
