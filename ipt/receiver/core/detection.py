"""What the pipeline needs of a tag detector, without knowing which one or where it runs.

The core is pure: it does not make the detector (a C library, maybe in a helper process), it is handed one
(:class:`Detector`) by whoever builds the pipeline: the daemon, the replay, benchmarks, tests
(:func:`ipt.receiver.detect.detector.pipeline_detector` makes the configured one). The detection's data and
the one exception the pipeline catches live here, so that the detector's side imports them from the core and
not the other way round.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from ipt.errors import IptError


class DetectorError(IptError):
    """The detector was given something it cannot work on, or its helper process failed."""


@dataclass(frozen=True)
class TagDetection:
    """One decoded tag."""

    tag_id: int
    hamming: int
    """Bits corrected while decoding."""
    decision_margin: float
    """AprilTag's decoding confidence (larger is better)."""
    corners_px: npt.NDArray[np.float64]
    """4x2 corners in OpenCV pixel coordinates, in AprilTag's order."""


class Detector(Protocol):
    """A tag detector as the pipeline uses it (:class:`ipt.receiver.detect.detector.TagDetector`)."""

    def detect(self, gray: npt.NDArray[np.uint8], decimate: float | None = None) -> tuple[TagDetection, ...]:
        """The map's tags in an 8-bit image; :class:`DetectorError` when the detector fails."""
        ...

    def wait_ready(self) -> None:
        """Return once a frame can be taken (a helper process may still be starting when handed over)."""
        ...

    def close(self) -> None:
        """Free the detector (end its helper process) now."""
        ...


__all__ = ["Detector", "DetectorError", "TagDetection"]
