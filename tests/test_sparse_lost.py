"""When the pipeline takes the track for lost (``Pipeline._lost``: AprilTag again, or the search of the whole map) while
the sparse chain waits for frames: those frames have not failed, so a dense pair beside them does not search the map
(on moving-content the search ran 37 times there, each in vain, 27 ms each); a frame that did fail since the newest
pose still counts, as it does with the dense tracker. A frame whose pose the gates held back is no pose to track
from."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from flightpipeline import flight_pipeline

from ipt.config.models import PipelineConfig
from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.history import Candidate, Frame
from ipt.receiver.core.pipeline import LOST_AFTER_US, SEARCH_AFTER_US, Pipeline
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.core.reasons import FrameReason

STEP_US = 8_333  # 120 FPS


@pytest.fixture(scope="module")
def sparse_pipeline(short_flight: Path) -> Iterator[Pipeline]:
    p = flight_pipeline(short_flight, PipelineConfig(tracker="sparse"))
    yield p
    p.close()


def _history(p: Pipeline, states: str) -> Frame:
    """Frames one camera period apart, one per letter: P posed, W waited for by the chain, F failed (tried, no
    pose), H held back (a candidate, but its result went out without it); then the target frame (tried, no pose
    yet), which is returned."""
    p.history.clear()
    pose = PoseEstimate(np.array([0.0, 0.0, 1.0]), np.eye(3), (0, 1), 0.5)
    rt = (np.zeros(3), np.array([0.0, 0.0, 1.0]))
    lum = np.zeros((4, 4), np.uint8)
    for k, state in enumerate(states):
        f = Frame(k, k * STEP_US, lum)
        if state in "PH":
            f.best = Candidate(pose, rt, 2, "sparse", k - 1, 0.8)
        if state == "H":
            f.result = FrameResult(k, f.time_us, None, 0, FrameReason.INCONSISTENT)
        f.waiting = state == "W"
        if state == "F":
            f.tried.add(k - 1)
        p.history.append(f)
    target = Frame(len(states), len(states) * STEP_US, lum)
    target.tried.add(len(states) - 1)
    p.history.append(target)
    return target


def test_frames_the_chain_waits_for_do_not_make_the_track_lost(sparse_pipeline: Pipeline) -> None:
    target = _history(sparse_pipeline, "PWW")  # the newest pose 25 ms before the target
    assert target.time_us - 0 > SEARCH_AFTER_US
    assert not sparse_pipeline._lost(target, SEARCH_AFTER_US)


def test_a_frame_that_failed_since_the_newest_pose_still_makes_it_lost(sparse_pipeline: Pipeline) -> None:
    assert sparse_pipeline._lost(_history(sparse_pipeline, "PFW"), SEARCH_AFTER_US)
    assert sparse_pipeline._lost(_history(sparse_pipeline, "PFF"), SEARCH_AFTER_US)
    assert sparse_pipeline._lost(_history(sparse_pipeline, "WWW"), SEARCH_AFTER_US)  # no pose at all
    assert not sparse_pipeline._lost(_history(sparse_pipeline, "PF"), SEARCH_AFTER_US)  # 17 ms: not yet


def test_poses_the_gates_held_back_do_not_keep_the_track(sparse_pipeline: Pipeline) -> None:
    """Fits gone astray now and then while the rest fail (an arena file wrong under a projector's seam): the
    newest pose to track from is the last one that went out, and once it is old AprilTag looks again."""
    states = "PFFHFFH"  # the last pose 58 ms before the target, a held-back one 8 ms before it
    assert len(states) * STEP_US > LOST_AFTER_US > 2 * STEP_US
    assert sparse_pipeline._lost(_history(sparse_pipeline, states))
    assert not sparse_pipeline._lost(_history(sparse_pipeline, "PFFFFFP"))  # a pose that went out: tracked
