"""Why a camera frame gave no pose: the values of :attr:`ipt.receiver.core.pipeline.FrameResult.reason`.

A :class:`~enum.StrEnum`, so a member is equal to its text (``FrameReason.NO_TAGS == "no_tags"``) and
prints as it: the statistics lines, the suite's JSON and the diagnostics carry the same words as before.
"""

from __future__ import annotations

from enum import StrEnum


class FrameReason(StrEnum):
    """The reason of one frame's result (``pose`` when it has one)."""

    POSE = "pose"
    """A pose was made."""
    FIRST_FRAME = "first_frame"
    """No frame before it to pair with."""
    TIME_GAP = "time_gap"
    """Too long since the previous frame: the pairing and the track start again."""
    BAD_FRAME = "bad_frame"
    """Not an H×W or H×W×3 uint8 image."""
    WRONG_SIZE = "wrong_size"
    """An image of another size than the camera's."""
    DARK = "dark"
    """Too little light to see the hidden tags."""
    SHADOWED = "shadowed"
    """No pose, and most of the view had no projector light (the drone's own shadow at take-off or landing,
    or the floor beyond the projection): decided from the frame's signal mask, not from a height
    (:data:`SHADOWED_SHARE`)."""
    SATURATED = "saturated"
    """Too much of the frame saturated."""
    NO_ALIGNMENT = "no_alignment"
    """The frame could not be aligned with its partner."""
    NO_TAGS = "no_tags"
    """No tag found."""
    LOST = "lost"
    """The track lost the map and no tag was found."""
    TRACK_DISAGREES = "track_disagrees"
    """The track's pose disagreed with the tags'."""
    DETECTOR_FAILED = "detector_failed"
    """The tag detector's helper process failed on this frame."""
    POSE_REJECTED = "pose_rejected"
    """A pose was found but not trusted (its fit)."""
    INCONSISTENT = "inconsistent"
    """A pose that disagrees with the poses before it."""
    UNCONFIRMED = "unconfirmed"
    """A pose after a disagreement, not yet confirmed by the next ones."""
    MOTION_JUMP = "motion_jump"
    """A pose farther from the last one than the drone can move in the time."""
    BAD_POSE = "bad_pose"
    """A pose that cannot be sent (e.g. a non-finite position): counted by the daemon."""
    LATE = "late"
    """Live: the sparse chain gave up on it (or the gates doubted its sparse poses), and it was too old by then for the
    dense way or the bridge (:data:`~ipt.receiver.core.sparsestage.LIVE_LATE_US`)."""
    ERROR = "error"
    """Processing the frame raised: counted by the daemon, reported on stderr."""


#: A frame without a pose whose signal mask lights less than this share of the view is ``shadowed``. On the
#: suite's two take-offs (the camera's own shadow grows as it nears the floor) the frames below it were all
#: below 0.34 m (open floor, 310 frames) and 0.27 m (landing pad, 152), none of them posed; every posed
#: frame lit at least 27 % of its view.
SHADOWED_SHARE = 0.25
#: The reasons of a frame whose pairs gave no pose: ``shadowed`` instead when most of its view was unlit.
PAIR_FAILURES = frozenset(
    {
        FrameReason.NO_TAGS,
        FrameReason.NO_ALIGNMENT,
        FrameReason.LOST,
        FrameReason.TRACK_DISAGREES,
        FrameReason.POSE_REJECTED,
    }
)
