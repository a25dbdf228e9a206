"""AprilTag 3 detection (dt-apriltags), wrapped behind a small interface of frozen dataclasses.

Corners are returned in OpenCV pixel coordinates (the centre of the top-left pixel is (0, 0)); AprilTag
reports them with the origin at the top-left pixel's corner, so half a pixel is subtracted here, once.
Corner order is AprilTag's (see :mod:`ipt.tagmap`), which the tag map uses for its own corners.

The C detector runs either here (``isolation: inline``) or in a helper process that
:mod:`ipt.receiver.detect.tagworker` manages (``isolation: process``, the default): AprilTag's C code (as
dt-apriltags 3.1.7 and pupil-apriltags 1.0.4 ship it) leaks memory on every call, and only ending the
process gives it back. :class:`DetectorError` and :data:`RawDetection` come from
:mod:`ipt.receiver.detect.apriltag_c` and are re-exported here. Both give the same detections; the
filtering below (bit errors, ids, image border) is the same for both.

The C library itself is called in :mod:`ipt.receiver.detect.apriltag_c`, which both this module and the helper
process import (the helper does not import this module).
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Iterable
from typing import TYPE_CHECKING, Protocol

import numpy as np
import numpy.typing as npt

from ipt.receiver.core.detection import TagDetection
from ipt.receiver.detect.apriltag_c import (
    DetectorError,
    RawDetection,
    free_pupil_detector,
    make_pupil_detector,
    pupil_detect,
    pupil_settings,
)

if TYPE_CHECKING:
    from ipt.config.models import DetectorConfig

#: AprilTag's pixel origin is the top-left corner of the top-left pixel; OpenCV's is its centre.
APRILTAG_TO_OPENCV_PX = -0.5


def c_settings(cfg: DetectorConfig) -> dict[str, float]:
    """The settings the C detector is made with (plain values, so they can cross to the helper process)."""
    return {
        "nthreads": cfg.threads,
        "quad_decimate": cfg.quad_decimate,
        "quad_sigma": cfg.quad_sigma,
        "refine_edges": int(cfg.refine_edges),
        "decode_sharpening": cfg.decode_sharpening,
        "max_hamming": cfg.max_hamming,  # (the bits its decode table corrects: no more are kept)
    }


class Backend(Protocol):
    """Where the C detector runs: :class:`InlineBackend` or :class:`ipt.receiver.detect.tagworker.ProcessBackend`."""

    def detect_raw(self, gray: npt.NDArray[np.uint8], decimate: float | None = None) -> list[RawDetection]: ...

    def settings(self) -> dict[str, float]: ...

    def wait_ready(self) -> None: ...

    def close(self) -> None: ...


class InlineBackend:
    """The C detector in this process, called on the caller's thread."""

    def __init__(self, settings: dict[str, float]) -> None:
        self.det = make_pupil_detector(settings)
        self.made_decimate = settings["quad_decimate"]
        self._finalizer = weakref.finalize(self, free_pupil_detector, self.det)

    def detect_raw(self, gray: npt.NDArray[np.uint8], decimate: float | None = None) -> list[RawDetection]:
        return pupil_detect(self.det, gray, decimate or self.made_decimate)

    def settings(self) -> dict[str, float]:
        return pupil_settings(self.det)

    def wait_ready(self) -> None:
        """Ready since it was made (nothing starts in the background)."""

    def close(self) -> None:
        self._finalizer()


def _isolated(cfg: DetectorConfig, wait: bool) -> Backend:
    """The C detector in a helper process where the system allows it (Linux), else in this one."""
    from ipt.receiver.detect.tagworker import ProcessBackend, process_isolation_available

    if not process_isolation_available():
        return InlineBackend(c_settings(cfg))
    return ProcessBackend(c_settings(cfg), recycle_mb=cfg.recycle_mb, wait=wait)


class TagDetector:
    """A configured tag36h11 detector that keeps only ids of the map and trustworthy decodes."""

    def __init__(self, cfg: DetectorConfig, known_ids: Iterable[int] | None = None, *, wait: bool = True) -> None:
        """``wait=False``: a helper process may still be starting on return (see :meth:`wait_ready`)."""
        self.cfg = cfg
        self.known_ids = None if known_ids is None else frozenset(known_ids)
        inline = cfg.isolation == "inline"
        self.backend: Backend = InlineBackend(c_settings(cfg)) if inline else _isolated(cfg, wait)
        self._lock = threading.Lock()

    def wait_ready(self) -> None:
        """Return once the detector can take a frame; :class:`DetectorError` if its helper did not start."""
        with self._lock:
            self.backend.wait_ready()

    @property
    def isolated(self) -> bool:
        """Whether the C code runs in a helper process."""
        return not isinstance(self.backend, InlineBackend)

    def close(self) -> None:
        """Free the C detector (or end its process) now; also done when this object is garbage-collected.
        Waits for a detection in progress on another thread."""
        with self._lock:
            self.backend.close()

    def effective_settings(self) -> dict[str, float]:
        """The settings as the C detector holds them (the binding may coerce what it is given)."""
        with self._lock:
            return self.backend.settings()

    def detect(self, gray: npt.NDArray[np.uint8], decimate: float | None = None) -> tuple[TagDetection, ...]:
        """Decode the tags in an 8-bit single-channel image; ``decimate`` overrides the configured
        ``quad_decimate`` for this call (small tags in the image need less)."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise DetectorError(f"expected an H×W uint8 image, got {gray.shape} {gray.dtype}")
        out = []
        h, w = gray.shape
        m = self.cfg.border_margin_px
        with self._lock:
            raw = self.backend.detect_raw(np.ascontiguousarray(gray), decimate)
        for tag_id, hamming, margin, corners_at in raw:
            if hamming > self.cfg.max_hamming:
                continue
            if self.known_ids is not None and tag_id not in self.known_ids:
                continue
            corners = corners_at + APRILTAG_TO_OPENCV_PX
            if (corners < m - 0.5).any() or (corners[:, 0] > w - 0.5 - m).any() or (corners[:, 1] > h - 0.5 - m).any():
                continue
            out.append(TagDetection(tag_id, hamming, margin, corners))
        return tuple(out)


def pipeline_detector(cfg: DetectorConfig, known_ids: Iterable[int]) -> TagDetector:
    """The detector a pipeline is handed (:class:`ipt.receiver.core.pipeline.Pipeline`), its helper process
    still starting: it imports (0.2-0.4 s) while the pipeline sets up, and the pipeline waits for it last."""
    return TagDetector(cfg, known_ids=known_ids, wait=False)


__all__ = [
    "APRILTAG_TO_OPENCV_PX",
    "Backend",
    "DetectorError",
    "InlineBackend",
    "RawDetection",
    "TagDetection",
    "TagDetector",
    "c_settings",
    "free_pupil_detector",
    "pipeline_detector",
]
