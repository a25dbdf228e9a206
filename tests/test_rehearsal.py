"""The live daemon's rehearsal (ipt/receiver/rehearsal.py): frames made up from the shipped map and camera pose with the
real pipeline and AprilTag, the shared detector stays open, and a failure is one line, never an exception."""

from __future__ import annotations

import dataclasses
import io
import types

import numpy as np
import pytest

from ipt.config.camera_info import load_camera_info
from ipt.config.models import PipelineConfig, load_arena_config, shipped_config_path
from ipt.receiver.core.pipeline import Pipeline
from ipt.receiver.detect.detector import pipeline_detector
from ipt.receiver.rehearsal import REHEARSAL_FPS, REHEARSAL_FRAMES, rehearsal_frames, rehearse, warm_up
from ipt.tagmap import grid_tag_map

ARENA = load_arena_config(shipped_config_path("arena.yaml"))
CAMERA = load_camera_info(shipped_config_path("camera.yaml"))
PINHOLE = dataclasses.replace(CAMERA, distortion=(0.0,) * len(CAMERA.distortion))  # the rehearsal's frames have none
INLINE = PipelineConfig().detector.model_copy(update={"isolation": "inline"})
CFG = PipelineConfig().model_copy(update={"detector": INLINE})


def test_rehearsal_frames_show_the_map_in_its_phases_and_pose_where_the_camera_was() -> None:
    tag_map = grid_tag_map(ARENA)
    hz = ARENA.projector.rate_hz
    frames, centre = rehearsal_frames(tag_map, PINHOLE, hz)
    assert len(frames) == REHEARSAL_FRAMES
    assert frames[0].shape == (CAMERA.height_px, CAMERA.width_px, 3)
    assert frames[0].dtype == np.uint8
    assert np.array_equal(frames[0], frames[1]), "at twice the projector's rate: [+, +, -, -]"
    step = frames[0].astype(int) - frames[2].astype(int)
    assert (step > 0).mean() > 0.2, "white cells"
    assert (step < 0).mean() > 0.2, "and black ones"
    pipeline = Pipeline(tag_map, PINHOLE, CFG, hz, pipeline_detector(CFG.detector, tag_map.by_id))
    try:
        results = [r for k, f in enumerate(frames) for r in pipeline.process(k, f, round(k * 1e6 / REHEARSAL_FPS))]
        results += pipeline.flush()
    finally:
        pipeline.close()
    posed = [r for r in results if r.pose is not None]
    assert len(posed) == REHEARSAL_FRAMES, [r.reason for r in results]
    for r in posed:
        assert r.pose is not None
        assert np.linalg.norm(r.pose.position_m - centre) < 0.01


def test_rehearse_shares_the_detector_and_leaves_it_open() -> None:
    tag_map = grid_tag_map(ARENA)
    detector = pipeline_detector(CFG.detector, tag_map.by_id)
    try:
        posed, seconds = rehearse(tag_map, CAMERA, CFG, ARENA.projector.rate_hz, detector)
        assert posed == REHEARSAL_FRAMES
        assert 0.0 < seconds < 30.0
        image = np.full((CAMERA.height_px, CAMERA.width_px), 127, np.uint8)
        assert detector.detect(image) == ()  # still usable: the throwaway pipeline did not close it
    finally:
        detector.close()


@pytest.mark.parametrize("broken", ["tag_map", "sensor"])
def test_a_failed_rehearsal_is_one_line_and_the_run_goes_on(broken: str) -> None:
    tag_map = grid_tag_map(ARENA)
    parts = {"tag_map": tag_map, "sensor": CAMERA, "cfg": CFG, "projector_hz": 60.0, "detector": None, broken: None}
    out = io.StringIO()
    warm_up(types.SimpleNamespace(**parts), out)  # type: ignore[arg-type]
    said = out.getvalue()
    assert said.startswith("ipt-receiver: rehearsal failed (the first frames will be slower): ")
    assert said.count("\n") == 1
