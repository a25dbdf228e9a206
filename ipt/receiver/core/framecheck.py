"""Whether a camera frame can be used at all, before any work is spent on it: its type and size, and its
exposure (a black frame, an all-shadow one or a saturated one carries no signal).

Pure: an array in, the reason it cannot be used (the :class:`~ipt.receiver.core.pipeline.FrameResult` reason
counted for it) or ``None`` out. The exposure checks look at every eighth pixel of every eighth row, a
few microseconds at 640×360, and are absolute: a frame that is merely dim (a dark scene in the projected
video, ambient light in the drone's shadow) passes, and then gives no pose for the usual reasons.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ipt.receiver.core.reasons import FrameReason

#: A frame whose brightest pixels (99th percentile of the sample) stay below this 8-bit level is dark:
#: black, the lens covered, or all in shadow with no ambient light. The ipt profile's signal mask takes
#: nothing below this level for lit floor either (:func:`ipt.receiver.core.demodulator.signal_mask`).
DARK_LEVEL = 12
#: A pixel value at or above this is clipped (or nearly so): a ±ΔL modulation cannot show there.
SATURATED_LEVEL = 250
#: A frame with more than this fraction of its sample clipped is saturated.
SATURATED_FRACTION = 0.95
#: Sampling step (rows and columns) of the exposure checks.
STEP = 8

#: Reasons after which pairing starts afresh (the camera's mode changed, or the frame is not an image):
#: the frames before it are not paired with the frames after it.
RESTARTS = frozenset({"bad_frame", "wrong_size"})


def shape_problem(frame: Any, height: int, width: int) -> str | None:
    """``"bad_frame"`` unless ``frame`` is an H×W (grey) or H×W×3 (RGB) uint8 array, ``"wrong_size"`` if it
    is one of another size than ``height``×``width``, else ``None``."""
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8:
        return FrameReason.BAD_FRAME
    if frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
        return FrameReason.BAD_FRAME
    if frame.shape[:2] != (height, width):
        return FrameReason.WRONG_SIZE
    return None


def exposure_problem(frame: np.ndarray[Any, np.dtype[np.uint8]]) -> str | None:
    """``"dark"`` or ``"saturated"`` (see :data:`DARK_LEVEL`, :data:`SATURATED_FRACTION`) for a frame that
    :func:`shape_problem` accepted, else ``None``."""
    sample = frame[::STEP, ::STEP]
    if sample.size == 0:
        return FrameReason.DARK
    if _percentile_99_below(sample, DARK_LEVEL):
        return FrameReason.DARK
    if np.count_nonzero(sample >= SATURATED_LEVEL) > SATURATED_FRACTION * sample.size:
        return FrameReason.SATURATED
    return None


def _percentile_99_below(sample: np.ndarray[Any, np.dtype[np.uint8]], level: int) -> bool:
    """``np.percentile(sample, 99) < level``, decided by counting where the count settles it (the 99th
    percentile lies between the sorted sample's values at ranks floor((n − 1)·0.99) and the next): a
    tenth of the cost of the percentile, which is taken only when the level falls between those two."""
    lo = int((sample.size - 1) * 0.99)
    below = int(np.count_nonzero(sample < level))
    if below >= lo + 3:  # both values below the level (with a rank to spare either way)
        return True
    if below <= lo - 1:  # both at or above it
        return False
    return bool(np.percentile(sample, 99) < level)


def frame_problem(frame: Any, height: int, width: int) -> str | None:
    """Why ``frame`` cannot be used (:func:`shape_problem`, then :func:`exposure_problem`), or ``None``."""
    return shape_problem(frame, height, width) or exposure_problem(frame)
