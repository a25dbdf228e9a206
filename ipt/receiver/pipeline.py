"""One frame in, at most one pose out: demodulation → detection → pose, with the reason when none.

Pure apart from the detector's C library: frames and their capture times go in, results come out. The
``paper`` profile is the paper's Algorithm 2 as published: each frame is paired with the frame before it
(lag 1), so only pairs that straddle a projector flip carry the tags.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.config.models import PipelineConfig
from ipt.receiver.demodulator import demodulate, lightness
from ipt.receiver.detector import TagDetection, TagDetector
from ipt.receiver.pose import PoseEstimate, solve_pose
from ipt.tagmap import TagMap

U8 = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class FrameResult:
    """What one camera frame gave."""

    index: int
    capture_time_us: int
    pose: PoseEstimate | None
    num_detections: int
    reason: str
    """"pose" when a pose was made; otherwise why not (e.g. "first_frame", "no_tags", "bad_frame")."""


class PaperPipeline:
    """The paper's receiver: lag-1 pairs, both polarities tried, IPPE pose."""

    profile = "paper"

    def __init__(self, tag_map: TagMap, camera: CameraInfo, cfg: PipelineConfig) -> None:
        self.tag_map, self.camera, self.cfg = tag_map, camera, cfg
        self.detector = TagDetector(cfg.detector, known_ids=tag_map.by_id)
        self._prev_l: U8 | None = None
        self.reasons: Counter[str] = Counter()

    def _detect_both_polarities(self, binary: U8) -> tuple[TagDetection, ...]:
        found = self.detector.detect(binary)
        inverted = self.detector.detect(255 - binary)
        return inverted if len(inverted) > len(found) else found

    def process(self, index: int, frame_rgb: U8, capture_time_us: int) -> FrameResult:
        """Process camera frame ``index``; never raises for a bad frame (the reason says what happened)."""
        result = self._process(index, frame_rgb, capture_time_us)
        self.reasons[result.reason] += 1
        return result

    def _process(self, index: int, frame_rgb: U8, capture_time_us: int) -> FrameResult:
        expected = (self.camera.height_px, self.camera.width_px, 3)
        if not isinstance(frame_rgb, np.ndarray) or frame_rgb.shape != expected or frame_rgb.dtype != np.uint8:
            self._prev_l = None
            return FrameResult(index, capture_time_us, None, 0, "bad_frame")
        now_l = lightness(frame_rgb)
        prev_l, self._prev_l = self._prev_l, now_l
        if prev_l is None:
            return FrameResult(index, capture_time_us, None, 0, "first_frame")
        demod = demodulate(prev_l, now_l, self.cfg.demodulation)
        detections = self._detect_both_polarities(demod.binary)
        if not detections:
            return FrameResult(index, capture_time_us, None, 0, "no_tags")
        pose = solve_pose(detections, self.tag_map, self.camera, self.cfg.pose)
        if pose is None:
            return FrameResult(index, capture_time_us, None, len(detections), "pose_rejected")
        return FrameResult(index, capture_time_us, pose, len(detections), "pose")
