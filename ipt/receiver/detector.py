"""AprilTag 3 detection (pupil-apriltags), wrapped behind a small interface of frozen dataclasses.

Corners are returned in OpenCV pixel coordinates (the centre of the top-left pixel is (0, 0)); AprilTag
reports them with the origin at the top-left pixel's corner, so half a pixel is subtracted here, once.
Corner order is AprilTag's (see :mod:`ipt.tagmap`), which the tag map uses for its own corners.

The C detector runs either here (``isolation: inline``) or in a helper process that
:mod:`ipt.receiver.tagworker` manages (``isolation: process``, the default): pupil-apriltags 1.0.4's C
code leaks memory on every call, and only ending the process gives it back. Both give the same
detections; the filtering below (bit errors, ids, image border) is the same for both.

This module imports neither pydantic nor the configuration models at run time, so that the helper
process, which needs only :func:`make_pupil_detector`, starts quickly.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt
import pupil_apriltags

from ipt.errors import IptError

if TYPE_CHECKING:
    from ipt.config.models import DetectorConfig

#: AprilTag's pixel origin is the top-left corner of the top-left pixel; OpenCV's is its centre.
APRILTAG_TO_OPENCV_PX = -0.5

#: One detection as the C library gives it: id, bits corrected, decision margin, 4x2 corners (AprilTag px).
RawDetection = tuple[int, int, float, npt.NDArray[np.float64]]


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


def c_settings(cfg: DetectorConfig) -> dict[str, float]:
    """The settings the C detector is made with (plain values, so they can cross to the helper process)."""
    return {
        "nthreads": cfg.threads,
        "quad_decimate": cfg.quad_decimate,
        "quad_sigma": cfg.quad_sigma,
        "refine_edges": int(cfg.refine_edges),
        "decode_sharpening": cfg.decode_sharpening,
    }


def make_pupil_detector(settings: dict[str, float]) -> Any:
    """A tag36h11 pupil-apriltags detector with ``settings`` (see :func:`c_settings`). Free it with
    :func:`free_pupil_detector`."""
    det = pupil_apriltags.Detector(
        families="tag36h11",
        nthreads=int(settings["nthreads"]),
        quad_decimate=settings["quad_decimate"],
        quad_sigma=settings["quad_sigma"],
        refine_edges=int(settings["refine_edges"]),
        decode_sharpening=settings["decode_sharpening"],
    )
    # pupil-apriltags 1.0.4 stores int(decode_sharpening), so 0.25 would reach the C detector as 0.
    det.tag_detector_ptr.contents.decode_sharpening = settings["decode_sharpening"]
    return det


def pupil_settings(det: Any) -> dict[str, float]:
    """The settings as the C detector holds them (pupil-apriltags may coerce what it is given)."""
    c = det.tag_detector_ptr.contents
    return {
        "nthreads": int(c.nthreads),
        "quad_decimate": float(c.quad_decimate),
        "quad_sigma": float(c.quad_sigma),
        "refine_edges": int(c.refine_edges),
        "decode_sharpening": float(c.decode_sharpening),
    }


def pupil_detect(det: Any, gray: npt.NDArray[np.uint8], decimate: float | None = None) -> list[RawDetection]:
    """Every tag36h11 decode the C detector finds in ``gray``, unfiltered; with ``decimate``, quads are
    looked for at that decimation from now on (the C detector reads it on every call)."""
    if decimate is not None:
        det.tag_detector_ptr.contents.quad_decimate = decimate
    return [
        (int(d.tag_id), int(d.hamming), float(d.decision_margin), np.asarray(d.corners, dtype=np.float64).reshape(4, 2))
        for d in det.detect(gray)
    ]


class Backend(Protocol):
    """Where the C detector runs: :class:`InlineBackend` or :class:`ipt.receiver.tagworker.ProcessBackend`."""

    def detect_raw(self, gray: npt.NDArray[np.uint8], decimate: float | None = None) -> list[RawDetection]: ...

    def settings(self) -> dict[str, float]: ...

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

    def close(self) -> None:
        self._finalizer()


def _isolated(cfg: DetectorConfig, wait: bool) -> Backend:
    """The C detector in a helper process where the system allows it (Linux), else in this one."""
    from ipt.receiver.tagworker import ProcessBackend, process_isolation_available

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
        wait = getattr(self.backend, "wait_ready", None)
        if wait is not None:
            with self._lock:
                wait()

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
        """The settings as the C detector holds them (pupil-apriltags may coerce what it is given)."""
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
