"""What the pipeline gives for each camera frame (:class:`FrameResult`), and the records it keeps of the
frames, pairs and candidate poses it works on (private to :mod:`ipt.receiver.core.pipeline` and
:mod:`ipt.receiver.core.gates`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from ipt.receiver.core.demodulator import PairDifference
from ipt.receiver.core.imagealign import AlignTarget
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


@dataclass
class _Frame:
    index: int
    time_us: int
    lum: U8
    """Lightness (undistorted in the ipt profile)."""
    signal: U8 | None = None
    features: F32 | None = None
    target: AlignTarget | None = None
    rt: tuple[F64, F64] | None = None
    """OpenCV's (rvec, tvec) of the pose found for this frame."""
    phase: int | None = None
    """+1 if this frame showed the +ΔL phase, -1 the other, None if not known."""
    result: FrameResult | None = None
    final: bool = False
    tried: set[int] = field(default_factory=set)
    candidates: list[_Candidate] = field(default_factory=list)
    """The poses found for this frame with each partner (ipt profile), not yet gated."""
    best: _Candidate | None = None
    """The candidate that fits the map best so far."""
    failure: FrameResult | None = None
    """Why the last attempt gave no pose."""


@dataclass(frozen=True)
class _Candidate:
    """A pose found for a frame with one partner, and how well the map fitted it."""

    pose: PoseEstimate
    rt: tuple[F64, F64]
    tags: int
    method: str
    partner: int
    quality: float
    """The share of the visible map's edges on their steps (0 for a pose from tag corners alone)."""


@dataclass
class _Pair:
    warp: F64
    """Carries the earlier frame onto the later one (undistorted pixels)."""
    later: PairDifference
    earlier: PairDifference | None = None
