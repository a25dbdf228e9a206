"""AprilTag 3 detection (pupil-apriltags), wrapped behind a small interface of frozen dataclasses.

Corners are returned in OpenCV pixel coordinates (the centre of the top-left pixel is (0, 0)); AprilTag
reports them with the origin at the top-left pixel's corner, so half a pixel is subtracted here, once.
Corner order is AprilTag's (see :mod:`ipt.tagmap`), which the tag map uses for its own corners.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
import pupil_apriltags

from ipt.config.models import DetectorConfig
from ipt.errors import IptError

#: AprilTag's pixel origin is the top-left corner of the top-left pixel; OpenCV's is its centre.
APRILTAG_TO_OPENCV_PX = -0.5


class DetectorError(IptError):
    """The detector was given something it cannot work on."""


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


def free_pupil_detector(det: Any) -> None:
    """Free a pupil-apriltags detector in the order the C library needs.

    pupil-apriltags 1.0.4's ``Detector.__del__`` frees the tag family first and then calls
    ``apriltag_detector_destroy``, which writes into that freed family (``quick_decode_uninit``): an
    8-byte use-after-free that valgrind shows and that later aborts the process in an unrelated
    ``malloc``. We destroy the detector first, then the family, and disarm the library's ``__del__``.
    """
    ptr = det.tag_detector_ptr
    if ptr is None:
        return
    det.tag_detector_ptr = None  # makes pupil-apriltags' own __del__ a no-op
    libc = det.libc
    libc.apriltag_detector_destroy.restype = None
    libc.apriltag_detector_destroy(ptr)
    libc.tag36h11_destroy.restype = None
    for family in det.tag_families.values():
        libc.tag36h11_destroy(family)
    det.tag_families = {}


class TagDetector:
    """A configured tag36h11 detector that keeps only ids of the map and trustworthy decodes."""

    def __init__(self, cfg: DetectorConfig, known_ids: Iterable[int] | None = None) -> None:
        self.cfg = cfg
        self.known_ids = None if known_ids is None else frozenset(known_ids)
        self._det = pupil_apriltags.Detector(
            families="tag36h11",
            nthreads=cfg.threads,
            quad_decimate=cfg.quad_decimate,
            quad_sigma=cfg.quad_sigma,
            refine_edges=int(cfg.refine_edges),
            decode_sharpening=cfg.decode_sharpening,
        )
        self._finalizer = weakref.finalize(self, free_pupil_detector, self._det)
        # pupil-apriltags 1.0.4 stores int(decode_sharpening), so 0.25 would reach the C detector as 0.
        self._det.tag_detector_ptr.contents.decode_sharpening = cfg.decode_sharpening

    def close(self) -> None:
        """Free the C detector now (also done when this object is garbage-collected)."""
        self._finalizer()

    def effective_settings(self) -> dict[str, float]:
        """The settings as the C detector holds them (pupil-apriltags may coerce what it is given)."""
        c = self._det.tag_detector_ptr.contents
        return {
            "nthreads": int(c.nthreads),
            "quad_decimate": float(c.quad_decimate),
            "quad_sigma": float(c.quad_sigma),
            "refine_edges": int(c.refine_edges),
            "decode_sharpening": float(c.decode_sharpening),
        }

    def detect(self, gray: npt.NDArray[np.uint8]) -> tuple[TagDetection, ...]:
        """Decode the tags in an 8-bit single-channel image."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise DetectorError(f"expected an H×W uint8 image, got {gray.shape} {gray.dtype}")
        out = []
        h, w = gray.shape
        m = self.cfg.border_margin_px
        for d in self._det.detect(np.ascontiguousarray(gray)):
            tag_id, hamming = int(d.tag_id), int(d.hamming)
            if hamming > self.cfg.max_hamming:
                continue
            if self.known_ids is not None and tag_id not in self.known_ids:
                continue
            corners = np.asarray(d.corners, dtype=np.float64).reshape(4, 2) + APRILTAG_TO_OPENCV_PX
            if (corners < m - 0.5).any() or (corners[:, 0] > w - 0.5 - m).any() or (corners[:, 1] > h - 0.5 - m).any():
                continue
            out.append(TagDetection(tag_id, hamming, float(d.decision_margin), corners))
        return tuple(out)
