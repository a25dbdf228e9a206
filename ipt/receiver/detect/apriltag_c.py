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


#: Bits of error the binding's decode table corrects (its constructor's, for every family).
BINDING_BITS = 2


def make_pupil_detector(settings: dict[str, float], binding: Any = None) -> Any:
    """A tag36h11 dt-apriltags detector with ``settings`` (see :func:`ipt.receiver.detect.detector.c_settings`).
    Free it with :func:`free_pupil_detector`. ``binding``: another module of pupil-apriltags' interface to make
    it with (``pupil_apriltags`` itself, for ``benchmarks/apriltag_binding.py``'s comparison).

    Its decode table corrects ``settings["max_hamming"]`` bits (default :data:`BINDING_BITS`): the detector keeps
    no decode with more, and tag36h11's table with two corrected bits costs 23 ms and ~35 MB at every start where
    one bit's costs 0.6 ms and ~1 MB. Its codewords are 11 bits apart, so a code within one bit of a codeword is
    more than two bits from every other: both tables give the same decodes of at most one bit. The binding builds
    the table in its constructor, for two bits, so the detector is made with the tiny tag16h5 family and that is
    swapped for tag36h11 (:func:`_use_tag36h11`)."""
    if binding is None:
        import dt_apriltags

        binding = dt_apriltags
    bits = int(settings.get("max_hamming", BINDING_BITS))
    det = binding.Detector(
        families="tag36h11" if bits >= BINDING_BITS else "tag16h5",
        nthreads=int(settings["nthreads"]),
        quad_decimate=settings["quad_decimate"],
        quad_sigma=settings["quad_sigma"],
        refine_edges=int(settings["refine_edges"]),
        decode_sharpening=settings["decode_sharpening"],
    )
    if bits < BINDING_BITS:
        _use_tag36h11(det, bits)
    # dt-apriltags 3.1.7 (as pupil-apriltags 1.0.4) stores int(decode_sharpening): 0.25 would reach C as 0.
    det.tag_detector_ptr.contents.decode_sharpening = settings["decode_sharpening"]
    return det


def _use_tag36h11(det: Any, bits: int) -> None:
    """Replace ``det``'s tag16h5 family by tag36h11 with a decode table of ``bits`` corrected bits (the library's
    own calls; the binding's ``tag_families`` kept in step, which :func:`free_pupil_detector` frees)."""
    libc, ptr = det.libc, det.tag_detector_ptr
    small = det.tag_families.pop("tag16h5")
    for name in ("apriltag_detector_remove_family", "tag16h5_destroy", "apriltag_detector_add_family_bits"):
        getattr(libc, name).restype = None
    libc.apriltag_detector_remove_family(ptr, small)  # (frees its decode table)
    libc.tag16h5_destroy(small)
    libc.tag36h11_create.restype = type(small)
    family = libc.tag36h11_create()
    libc.apriltag_detector_add_family_bits(ptr, family, bits)
    det.tag_families["tag36h11"] = family
    det.params["families"] = ["tag36h11"]


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
