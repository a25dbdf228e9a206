"""The C detector's decode table corrects as many bits as the detector keeps (``max_hamming``, 1 by default), not the
binding's two: the same decodes of at most one bit, a tag two bits off found by neither, and at a fraction of the cost
at every start (ipt/receiver/detect/apriltag_c.py)."""

from __future__ import annotations

import resource
import time
from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from ipt.config.models import DetectorConfig
from ipt.receiver.detect.apriltag_c import BINDING_BITS, free_pupil_detector, make_pupil_detector, pupil_detect
from ipt.receiver.detect.detector import TagDetector, c_settings
from ipt.tagmap import TAG36H11_CELLS, tag36h11_bitmap

CELL_PX = 12
DATA = range(2, TAG36H11_CELLS - 2)
"""The data cells' rows and columns in a tag's cell image (quiet zone and black border around them)."""


def _scene(flips: dict[int, list[tuple[int, int]]]) -> npt.NDArray[np.uint8]:
    """Tags 0-5 in a row on grey, each with its listed data cells flipped (one flipped cell: one bit off its code)."""
    side = TAG36H11_CELLS * CELL_PX
    out = np.full((side + 40, 6 * (side + 20) + 20), 128, np.uint8)
    for k in range(6):
        cells = tag36h11_bitmap(k).copy()
        for r, c in flips.get(k, []):
            cells[r, c] ^= 1
        tag = cv2.resize(cells * 255, (side, side), interpolation=cv2.INTER_NEAREST)
        x = 20 + k * (side + 20)
        out[20 : 20 + side, x : x + side] = tag
    return out


@pytest.fixture(scope="module")
def detectors() -> Iterator[tuple[Any, Any]]:
    settings = c_settings(DetectorConfig())
    ours, binding_s = make_pupil_detector(settings), make_pupil_detector(dict(settings, max_hamming=BINDING_BITS))
    try:
        yield ours, binding_s
    finally:
        free_pupil_detector(ours)
        free_pupil_detector(binding_s)


def _found(det: Any, image: npt.NDArray[np.uint8]) -> list[tuple[int, int, float, list[float]]]:
    return sorted((i, h, m, c.ravel().tolist()) for i, h, m, c in pupil_detect(det, image, 1.0))


def test_the_detector_keeps_one_corrected_bit_by_default() -> None:
    assert c_settings(DetectorConfig())["max_hamming"] == DetectorConfig().max_hamming == 1


def test_decodes_of_at_most_one_bit_are_the_binding_s_and_two_bits_off_are_not_decoded(
    detectors: tuple[Any, Any],
) -> None:
    ours, binding_s = detectors
    rows = list(DATA)
    image = _scene({1: [(rows[0], rows[1])], 2: [(rows[2], rows[3])], 4: [(rows[1], rows[1]), (rows[4], rows[2])]})
    mine, theirs = _found(ours, image), _found(binding_s, image)
    assert [(i, h) for i, h, _, _ in theirs] == [(0, 0), (1, 1), (2, 1), (3, 0), (4, 2), (5, 0)]
    assert mine == [d for d in theirs if d[1] <= 1]  # the same ids, bits, margins and corners to the last bit


def test_the_detector_s_tags_are_the_same_through_its_filter(detectors: tuple[Any, Any]) -> None:
    """What the pipeline gets (:class:`TagDetector`, which drops decodes of more than ``max_hamming`` bits) is the same
    with either table."""
    rows = list(DATA)
    image = _scene({3: [(rows[5], rows[0])], 5: [(rows[0], rows[0]), (rows[5], rows[5])]})
    kept = TagDetector(DetectorConfig(isolation="inline", quad_decimate=1.0))
    wide = TagDetector(DetectorConfig(isolation="inline", quad_decimate=1.0))
    free_pupil_detector(wide.backend.det)  # type: ignore[attr-defined]
    wide.backend.det = make_pupil_detector(  # type: ignore[attr-defined]
        dict(c_settings(DetectorConfig(quad_decimate=1.0)), max_hamming=BINDING_BITS)
    )
    try:
        a, b = kept.detect(image), wide.detect(image)
    finally:
        kept.close()
        wide.close()
    assert [t.tag_id for t in a] == [0, 1, 2, 3, 4]
    assert [(t.tag_id, t.hamming, t.decision_margin, t.corners_px.tobytes()) for t in a] == [
        (t.tag_id, t.hamming, t.decision_margin, t.corners_px.tobytes()) for t in b
    ]


def test_the_one_bit_table_costs_a_fraction_of_the_two_bit_one() -> None:
    """Processor time and page faults of making each (the two-bit table: ~23 ms and ~9 000 faults here)."""
    settings = c_settings(DetectorConfig())
    costs = {}
    for bits in (1, BINDING_BITS):
        t0, f0 = time.process_time(), resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        det = make_pupil_detector(dict(settings, max_hamming=bits))
        costs[bits] = (time.process_time() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)
        free_pupil_detector(det)
    assert costs[1][1] * 5 < costs[BINDING_BITS][1]
