"""The paper's way through (the ``paper`` profile, Algorithm 2 as published): each frame against the previous
one (lag 1), the paper's integer shift and median threshold, AprilTag, IPPE (:class:`PaperWay`, which the
pipeline holds in that profile and hands each new frame)."""

from __future__ import annotations

import time
from collections.abc import Callable

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.config.models import PipelineConfig
from ipt.receiver.core.demodulator import demodulate
from ipt.receiver.core.detection import Detector, DetectorError, TagDetection
from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.gates import PoseGates
from ipt.receiver.core.history import Frame, FrameHistory
from ipt.receiver.core.pose import solve_pose
from ipt.receiver.core.reasons import FrameReason
from ipt.tagmap import TagMap

U8 = npt.NDArray[np.uint8]


class PaperWay:
    """The paper's profile: each new frame of ``history`` with the one before it, its pose judged by ``gates``;
    ``lap(stage, t0)`` counts the processor time since ``t0`` to a stage and returns the time now."""

    def __init__(
        self,
        cfg: PipelineConfig,
        camera: CameraInfo,
        tag_map: TagMap,
        detector: Detector,
        history: FrameHistory,
        gates: PoseGates,
        lap: Callable[[str, float], float],
    ) -> None:
        self.cfg, self.camera, self.tag_map, self.detector = cfg, camera, tag_map, detector
        self.history, self.gates, self.lap = history, gates, lap
        self.detector_runs = 0
        """AprilTag runs so far."""

    def solve(self, new: Frame) -> FrameResult:
        """``new``'s result: a pose with the frame before it, or why none."""
        result = new.failure or FrameResult(new.index, new.time_us, None, 0, FrameReason.FIRST_FRAME)
        t0 = time.thread_time()
        for prev in self.history.partners(new, earlier=True):
            new.tried.add(prev.index)
            demod = demodulate(prev.lum, new.lum, self.cfg.demodulation)
            t0 = self.lap("demodulate", t0)
            try:
                dets, sign = self._detect(demod.binary, self.history.predicted_phase(new) or 1)
            except DetectorError:
                self.lap("detect", t0)
                return FrameResult(new.index, new.time_us, None, 0, FrameReason.DETECTOR_FAILED, detector_failed=True)
            t0 = self.lap("detect", t0)
            if not dets:
                result = FrameResult(new.index, new.time_us, None, 0, FrameReason.NO_TAGS, partner=prev.index)
                continue
            new.phase, prev.phase = sign, -sign
            pose = solve_pose(dets, self.tag_map, self.camera, self.cfg.pose)
            self.lap("pose", t0)
            if pose is None:
                return FrameResult(
                    new.index, new.time_us, None, len(dets), FrameReason.POSE_REJECTED, partner=prev.index
                )
            return self.gates.judge(new.index, new.time_us, pose, len(dets), "apriltag", prev.index)
        return result

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
