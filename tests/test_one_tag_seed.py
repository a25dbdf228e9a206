"""Acquisition from one whole tag: AprilTag finds a single tag (a landing pad's, seen from just above it, the rest of
the view in the drone's shadow or cut by the frame's edge), too few for a pose (``pose.min_tags``), but each of its two
poses (IPPE's: the tilt of one small tag is ambiguous) may start the map's track, which is taken only if it fits
``MIN_SEARCH_FIT`` of the map's visible edges. A pair rendered 0.3 m above the shipped arena's pad, AprilTag's tags on
it cut down to the one nearest the view's centre: the pose is found, within a centimetre of the truth; the same tag
given another's id (its poses a metre or more away) places nothing."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from flightpipeline import flight_pipeline
from floorview import render_view

from ipt.config.models import PipelineConfig, load_arena_config
from ipt.geometry import R_BODY_CAM_DOWNWARD, rot_x, rot_y, rot_z
from ipt.receiver.core.acquire import Acquisition
from ipt.receiver.core.demodulator import PairDifference, binarise_difference, lightness, pair_difference
from ipt.receiver.core.detection import TagDetection
from ipt.receiver.core.history import Frame
from ipt.receiver.core.pipeline import Pipeline
from ipt.sender.modulator import PaperModulator

F64 = npt.NDArray[np.float64]


class _OneTag:
    """A detector that finds only the given tag, on every call (counted)."""

    def __init__(self, tag: TagDetection) -> None:
        self.tag, self.calls = tag, 0

    def detect(self, image: Any, decimate: float | None = None) -> tuple[TagDetection, ...]:
        self.calls += 1
        return (self.tag,)


#: Just above the shipped arena's landing pad (its small tags), yawed and tilted a little: a drone taking off.
ABOVE_PAD_M = np.array([0.02, -0.015, 0.3])
R_ARENA_CAM = rot_z(np.deg2rad(23.0)) @ rot_x(np.deg2rad(1.2)) @ rot_y(np.deg2rad(-0.8)) @ R_BODY_CAM_DOWNWARD


def _frame(index: int, size: tuple[int, int]) -> Frame:
    w, h = size
    f = Frame(index, index * 8_333, np.zeros((h, w), np.uint8), signal=np.full((h, w), 255, np.uint8))
    f.lit_share = 1.0
    return f


@pytest.fixture(scope="module")
def pair(short_flight: Path) -> Iterator[tuple[Pipeline, Frame, Frame, PairDifference, TagDetection, F64]]:
    """A pipeline for the short flight's arena and camera; a pair of opposite phases over flat content as that camera
    (undistorted) sees it 0.3 m above the pad; the whole tag AprilTag finds nearest the view's centre; the camera's
    true position."""
    p = flight_pipeline(short_flight, PipelineConfig())
    try:
        arena = load_arena_config(short_flight / "arena.yaml")
        (pad,) = arena.tag_map.pads
        position = ABOVE_PAD_M + np.array([pad.centre_m[0], pad.centre_m[1], 0.0])
        w, h = p.camera.width_px, p.camera.height_px
        content = np.full((arena.projector.height_px, arena.projector.width_px, 3), 128, np.uint8)
        plus, minus = PaperModulator(p.tag_map.render_mask(), arena.modulation.delta_l).modulate(content, 0, 2)
        k = p.pinhole.camera_matrix
        later, earlier = (lightness(render_view(img, arena, k, position, R_ARENA_CAM, (w, h))) for img in (plus, minus))
        lit = np.full((h, w), 255, np.uint8)
        diff = pair_difference(earlier, later, np.eye(3), lit, lit)
        scale = p.scales.at(float(position[2]))
        found: tuple[TagDetection, ...] = ()
        for sign in (1, -1):
            found = tuple(p.detector.detect(binarise_difference(diff, sign, scale.ksize), scale.decimate))
            if found:
                break
        assert found, "AprilTag sees the pad's tags from 0.3 m"
        centre = np.array([w / 2, h / 2])
        one = min(found, key=lambda d: float(np.linalg.norm(d.corners_px.mean(axis=0) - centre)))
        yield p, _frame(2, (w, h)), _frame(0, (w, h)), diff, one, position
    finally:
        p.close()


def _acquire(acq: Acquisition, tag: TagDetection, target: Frame, other: Frame, diff: PairDifference) -> Any:
    real = acq.detector
    acq.detector = _OneTag(tag)  # type: ignore[assignment]
    acq.searched_at = target.index  # (not the whole-map search's turn: only the single tag can place the map)
    try:
        return acq.acquire(target, other, diff), acq.detector.calls  # type: ignore[attr-defined]
    finally:
        acq.detector = real


def test_one_tag_starts_the_track_and_the_pose_is_right(
    pair: tuple[Pipeline, Frame, Frame, PairDifference, TagDetection, F64],
) -> None:
    p, target, other, diff, one, position = pair
    assert p.cfg.pose.min_tags == 2
    got, calls = _acquire(p.acquisition, one, target, other, diff)
    assert calls == 1  # the first scale's single tag is enough
    assert got is not None
    assert got.method == "track"
    assert got.quality >= 0.6
    assert float(np.linalg.norm(got.pose.position_m - position)) < 0.01
    assert {target.phase, other.phase} == {1, -1}


def test_one_tag_under_another_id_places_nothing(
    pair: tuple[Pipeline, Frame, Frame, PairDifference, TagDetection, F64],
) -> None:
    p, target, other, diff, one, _ = pair
    ids = sorted(p.tag_map.by_id)
    far = ids[(ids.index(one.tag_id) + len(ids) // 2) % len(ids)]
    wrong = TagDetection(far, one.hamming, one.decision_margin, one.corners_px)
    got, calls = _acquire(p.acquisition, wrong, target, other, diff)
    assert got is None
    assert calls > 1  # every scale and polarity was tried, none placed the map
