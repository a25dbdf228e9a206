"""Binning a wide camera's frames (``demodulation.work_width_px``, :meth:`CameraInfo.binned`): which factor a camera
gets, that the binned camera sees a point where the averaged block is, and that the pipeline given a camera twice as
fine, whose frames are the short flight's with each pixel doubled, bins them back and poses every frame exactly as it
poses the short flight itself."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from flightpipeline import flight_frames, flight_pipeline

from ipt.config.camera_info import CameraInfo, CameraInfoError, load_camera_info
from ipt.config.models import PipelineConfig
from ipt.receiver.core.demodulator import binned
from ipt.receiver.core.pipeline import FrameResult, Pipeline

FPS = 120.0


def _camera(width: int, height: int) -> CameraInfo:
    return CameraInfo(width, height, 0.8 * width, 0.8 * width, width / 2 - 0.3, height / 2 + 0.7, (-0.1, 0.02, 0, 0, 0))


@pytest.mark.parametrize(
    ("size", "work", "factor"),
    [
        ((640, 360), 640, 1),
        ((800, 600), 640, 1),  # less than twice as wide: kept
        ((1279, 720), 640, 1),
        ((1280, 720), 640, 2),
        ((1280, 800), 640, 2),
        ((1920, 1080), 640, 3),
        ((2592, 1944), 640, 4),
        ((3280, 2464), 640, 4),  # 5 does not divide 2464
        ((1282, 721), 640, 1),  # 2 does not divide 721
        ((1280, 720), 0, 1),  # 0: never
        ((1280, 720), 320, 4),
    ],
)
def test_the_binning_factor_keeps_the_work_width_and_divides_both_sides(
    size: tuple[int, int], work: int, factor: int
) -> None:
    assert _camera(*size).binning_for(work) == factor


@pytest.mark.parametrize("k", [2, 3])
def test_the_binned_camera_sees_a_point_at_the_centre_of_its_block(k: int) -> None:
    fine = _camera(640 * k, 360 * k)
    coarse = fine.binned(k)
    assert (coarse.width_px, coarse.height_px) == (640, 360)
    rng = np.random.default_rng(4)
    points = np.column_stack([rng.uniform(-0.6, 0.6, (50, 2)), rng.uniform(1.0, 3.0, 50)])
    zero = np.zeros(3)
    seen_fine, _ = cv2.projectPoints(points, zero, zero, fine.camera_matrix, fine.dist_coeffs)
    seen_coarse, _ = cv2.projectPoints(points, zero, zero, coarse.camera_matrix, coarse.dist_coeffs)
    # pixel centres at whole coordinates: the block of fine pixels k·c .. k·c + k − 1 has its centre at k·c + (k − 1)/2
    np.testing.assert_allclose(seen_coarse, (seen_fine - (k - 1) / 2) / k, atol=1e-9)
    assert fine.binned(1) is fine
    with pytest.raises(CameraInfoError, match="cannot bin a 1920x1080 camera by 7"):
        _camera(1920, 1080).binned(7)


def test_binning_averages_each_block() -> None:
    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (36, 64), dtype=np.uint8)
    out = binned(image, 2)
    assert out.shape == (18, 32)
    assert out.dtype == np.uint8
    means = image.reshape(18, 2, 32, 2).astype(np.float64).mean(axis=(1, 3))
    assert np.abs(out - means).max() <= 0.5
    assert binned(image, 1) is image


def _doubled(camera: CameraInfo) -> CameraInfo:
    """The camera with each pixel split into 2 × 2: the one whose frame binned by 2 is ``camera``'s."""
    return replace(
        camera,
        width_px=2 * camera.width_px,
        height_px=2 * camera.height_px,
        fx_px=2 * camera.fx_px,
        fy_px=2 * camera.fy_px,
        cx_px=2 * camera.cx_px + 0.5,
        cy_px=2 * camera.cy_px + 0.5,
    )


def _poses(folder: Path, camera: CameraInfo, frames: list[Any], cfg: PipelineConfig) -> tuple[Pipeline, list[Any]]:
    p = flight_pipeline(folder, cfg, camera)
    try:
        out: list[FrameResult] = []
        for k, f in enumerate(frames):
            out += p.process(k, f, round(k / FPS * 1e6))
        out += p.flush()
    finally:
        p.close()
    rows = [(r.index, r.reason, r.method, None if r.pose is None else r.pose.position_m.tolist()) for r in out]
    return p, rows


def test_a_camera_twice_as_fine_is_binned_back_and_posed_exactly_alike(short_flight: Path) -> None:
    camera = load_camera_info(short_flight / "camera.yaml")
    frames = flight_frames(short_flight)[:40]
    fine_frames = [np.repeat(np.repeat(f, 2, axis=0), 2, axis=1) for f in frames]
    cfg = PipelineConfig()  # the ipt profile: work_width_px 640
    direct, rows = _poses(short_flight, camera, frames, cfg)
    assert direct.binning == 1
    assert direct.camera == camera
    fine, fine_rows = _poses(short_flight, _doubled(camera), fine_frames, cfg)
    assert fine.binning == 2
    assert fine.sensor == _doubled(camera)
    assert fine.camera == camera
    assert sum(r[3] is not None for r in rows) >= 30
    assert fine_rows == rows  # every result, every pose to the bit
    # A frame of the coarse size is not one of this camera's.
    p = flight_pipeline(short_flight, cfg, _doubled(camera))
    try:
        assert [r.reason for r in p.process(0, frames[0], 0)] == ["wrong_size"]
    finally:
        p.close()


def test_work_width_0_and_the_paper_profile_never_bin(short_flight: Path) -> None:
    fine = _doubled(load_camera_info(short_flight / "camera.yaml"))
    ipt = PipelineConfig()
    off = ipt.model_copy(update={"demodulation": ipt.demodulation.model_copy(update={"work_width_px": 0})})
    for cfg in (off, PipelineConfig.profile("paper")):
        p = flight_pipeline(short_flight, cfg, fine)
        try:
            assert p.binning == 1
            assert p.camera == fine
        finally:
            p.close()
