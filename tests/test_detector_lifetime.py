"""The pupil-apriltags detector must be freed in the order its C library needs (see detector.py)."""

from __future__ import annotations

from ipt.config.models import DetectorConfig
from ipt.receiver.detect.detector import TagDetector


def test_close_frees_detector_before_family_and_disarms_library_del() -> None:
    det = TagDetector(DetectorConfig(isolation="inline"))
    inner = det.backend.det  # type: ignore[attr-defined]
    assert inner.tag_detector_ptr is not None
    det.close()
    # pupil-apriltags' own __del__ checks this pointer: None means it will not free anything again.
    assert inner.tag_detector_ptr is None
    assert inner.tag_families == {}
    det.close()  # idempotent
