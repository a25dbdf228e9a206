"""AprilTag's C detector (dt-apriltags), called directly: made, asked, freed.

dt-apriltags is a fork of pupil-apriltags' ctypes bindings around the same AprilTag 3 C library, with
wheels for aarch64 Linux (a Raspberry Pi) where pupil-apriltags has only a source archive; on the suite's
images it gives pupil-apriltags 1.0.4's detections bit for bit (benchmarks/apriltag_binding.py,
docs/raspberry-pi.md). Its ``Detector`` has pupil's attributes (``tag_detector_ptr``, ``libc``,
``tag_families``) and its faults (the free order, ``int(decode_sharpening)``), handled here; the names
below keep "pupil" for that layout.

What both sides of the detector's process boundary need: :mod:`ipt.receiver.detect.detector` runs it inline,
the helper process of :mod:`ipt.receiver.detect.tagworker` runs it there; neither imports the other for it.
Detections come out as the C library gives them (:data:`RawDetection`, AprilTag's pixel origin,
unfiltered); :class:`~ipt.receiver.detect.detector.TagDetector` filters them and moves the corners to OpenCV's.

This module imports neither pydantic nor the configuration models, so that the helper process starts
quickly; dt-apriltags itself loads when a detector is made (the daemon's own process, which leaves the C code
to the helper, never loads it).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from ipt.receiver.core.detection import DetectorError as DetectorError  # re-exported: both sides raise it

#: One detection as the C library gives it: id, bits corrected, decision margin, 4x2 corners (AprilTag px).
RawDetection = tuple[int, int, float, npt.NDArray[np.float64]]


def free_pupil_detector(det: Any) -> None:
    """Free a dt-apriltags (pupil-apriltags layout) detector in the order the C library needs.

    dt-apriltags 3.1.7's ``Detector.__del__``, like pupil-apriltags 1.0.4's, frees the tag family first and
    then calls
    ``apriltag_detector_destroy``, which writes into that freed family (``quick_decode_uninit``): an
    8-byte use-after-free that valgrind shows and that later aborts the process in an unrelated
    ``malloc``. We destroy the detector first, then the family, and disarm the library's ``__del__``.
    """
    ptr = det.tag_detector_ptr
    if ptr is None:
        return
    det.tag_detector_ptr = None  # makes the binding's own __del__ a no-op
    libc = det.libc
    libc.apriltag_detector_destroy.restype = None
    libc.apriltag_detector_destroy(ptr)
    libc.tag36h11_destroy.restype = None
    for family in det.tag_families.values():
        libc.tag36h11_destroy(family)
    det.tag_families = {}


def make_pupil_detector(settings: dict[str, float], binding: Any = None) -> Any:
    """A tag36h11 dt-apriltags detector with ``settings`` (see :func:`ipt.receiver.detect.detector.c_settings`).
    Free it with :func:`free_pupil_detector`. ``binding``: another module of pupil-apriltags' interface to make
    it with (``pupil_apriltags`` itself, for ``benchmarks/apriltag_binding.py``'s comparison)."""
    if binding is None:
        import dt_apriltags

        binding = dt_apriltags
    det = binding.Detector(
        families="tag36h11",
        nthreads=int(settings["nthreads"]),
        quad_decimate=settings["quad_decimate"],
        quad_sigma=settings["quad_sigma"],
        refine_edges=int(settings["refine_edges"]),
        decode_sharpening=settings["decode_sharpening"],
    )
    # dt-apriltags 3.1.7 (as pupil-apriltags 1.0.4) stores int(decode_sharpening): 0.25 would reach C as 0.
    det.tag_detector_ptr.contents.decode_sharpening = settings["decode_sharpening"]
    return det


def pupil_settings(det: Any) -> dict[str, float]:
    """The settings as the C detector holds them (the binding may coerce what it is given)."""
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
