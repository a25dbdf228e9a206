"""What the pipeline gives for each camera frame (:class:`FrameResult`; the records it keeps of the frames,
pairs and candidate poses it works on are :mod:`ipt.receiver.core.history`'s)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ipt.receiver.core.pose import PoseEstimate

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class FrameResult:
    """What one camera frame gave."""

    index: int
    capture_time_us: int
    pose: PoseEstimate | None
    num_detections: int
    """Tags the pose rests on (AprilTag detections, or tags whose edges the track used)."""
    reason: str
    """"pose" when a pose was made; otherwise why not (e.g. "first_frame", "no_tags", "dark", "bad_frame")."""
    reset: bool = False
    """The pose re-initialises the track (it disagreed with the previous ones, which were dropped)."""
    method: str = ""
    """How the pose was found: "track" (the map's edges), "bridge" (the map's edges on the bridge's
    difference of three frames, :mod:`ipt.receiver.core.bridge`), "apriltag" (tag corners), or "" for none."""
    partner: int | None = None
    """The frame it was paired with."""
    detector_failed: bool = False
    """The tag detector's helper process failed since the result before this one came out (while this frame
    or a later one was processed): set on exactly one result per failure, which the daemon reports. The
    frame may still have a pose: the track does not need AprilTag."""
