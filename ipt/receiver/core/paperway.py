"""The paper's way through (the ``paper`` profile, Algorithm 2 as published): each frame against the previous
one (lag 1), the paper's integer shift and median threshold, AprilTag, IPPE. A mix-in of
:class:`ipt.receiver.core.pipeline.Pipeline`, whose state and stages it uses."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.config.models import PipelineConfig
from ipt.receiver.core.demodulator import demodulate
from ipt.receiver.core.detection import Detector, DetectorError, TagDetection
from ipt.receiver.core.frameresult import FrameResult, _Frame
from ipt.receiver.core.pose import PoseEstimate, solve_pose
from ipt.receiver.core.reasons import FrameReason
from ipt.tagmap import TagMap

U8 = npt.NDArray[np.uint8]


class PaperWay:
    """The paper's profile, as methods of :class:`~ipt.receiver.core.pipeline.Pipeline`."""

    cfg: PipelineConfig
    camera: CameraInfo
    tag_map: TagMap
    detector: Detector
    detector_runs: int

    if TYPE_CHECKING:  # the pipeline's own pairing and gates

        def _partners(self, frame: _Frame, earlier: bool) -> list[_Frame]: ...
        def _lap(self, stage: str, t0: float) -> float: ...
        def _predicted_phase(self, frame: _Frame) -> int | None: ...
        def _gated(self, frame: _Frame, pose: PoseEstimate, tags: int, method: str, partner: int) -> FrameResult: ...

    def _paper(self, new: _Frame) -> FrameResult:
        result = new.failure or FrameResult(new.index, new.time_us, None, 0, FrameReason.FIRST_FRAME)
        t0 = time.thread_time()
        for prev in self._partners(new, earlier=True):
            new.tried.add(prev.index)
            demod = demodulate(prev.lum, new.lum, self.cfg.demodulation)
            t0 = self._lap("demodulate", t0)
            try:
                dets, sign = self._detect(demod.binary, self._predicted_phase(new) or 1)
            except DetectorError:
                self._lap("detect", t0)
                return FrameResult(new.index, new.time_us, None, 0, FrameReason.DETECTOR_FAILED, detector_failed=True)
            t0 = self._lap("detect", t0)
            if not dets:
                result = FrameResult(new.index, new.time_us, None, 0, FrameReason.NO_TAGS, partner=prev.index)
                continue
            new.phase, prev.phase = sign, -sign
            pose = solve_pose(dets, self.tag_map, self.camera, self.cfg.pose)
            self._lap("pose", t0)
            if pose is None:
                return FrameResult(
                    new.index, new.time_us, None, len(dets), FrameReason.POSE_REJECTED, partner=prev.index
                )
            return self._gated(new, pose, len(dets), "apriltag", prev.index)
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
