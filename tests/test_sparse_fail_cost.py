"""Issue 29: with the sparse tracker a frame that fails, or that the bridge poses, must not cost far more than one that
tracks. The mechanism that cuts part of that cost, in isolation: the bridge prepares only the three frames of a
bridge it tries, not every frame kept."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import ipt.receiver.core.bridge as bridge_module
from ipt.config.models import PoseConfig
from ipt.receiver.core.gates import PoseGates
from ipt.receiver.core.history import Candidate, Frame, FrameHistory
from ipt.receiver.core.motion import MotionTrack
from ipt.receiver.core.pose import PoseEstimate, rt_of
from ipt.receiver.core.sparsestage import SparseStage

PERIOD_US = 8333  # 120 FPS


class _Chain:
    def seed(self, k: int, rt: object, sign: int) -> None:
        pass

    def reset(self, frames: bool = True) -> None:
        pass


def _candidate(quality: float, partner: int) -> Candidate:
    pose = PoseEstimate(np.array([0.0, 0.0, 1.0]), np.eye(3), (1, 2), 0.5)
    return Candidate(pose, (np.zeros(3), np.array([0.0, 0.0, 1.0])), 2, "track", partner, quality)


def _stage(qualities: dict[int, float]) -> tuple[SparseStage, list[int], list[int], Frame]:
    """Frames 0..6 at 120 FPS against a 60 Hz projector, none paired yet; frame 3 is the one paired late. A dense
    pair of frame 3 with partner j gives a candidate of quality ``qualities[j]`` (none if absent). The partners
    solved in order, and the frames prepared."""
    history = FrameHistory(60.0, "opposite_phase")
    frames = [Frame(k, k * PERIOD_US, np.zeros((2, 2), np.uint8)) for k in range(7)]
    for f in frames:
        history.append(f)
    solved: list[int] = []
    prepared: list[int] = []

    def solve(a: Frame, b: Frame, target: Frame) -> None:
        other = b if target is a else a
        target.tried.add(other.index)
        solved.append(other.index)
        if other.index in qualities:
            c = _candidate(qualities[other.index], other.index)
            target.candidates.append(c)
            if target.best is None or c.quality > target.best.quality:
                target.best = c

    stage = SparseStage(
        _Chain(),  # type: ignore[arg-type]
        history,
        PoseGates(PoseConfig()),
        solve,
        lambda f: prepared.append(f.index),
        lambda f, c: None,
        lambda stage, t0: t0,
        lambda: None,
    )
    return stage, solved, prepared, frames[3]


def test_the_bridge_being_possible_prepares_no_frame() -> None:
    """(Before: every kept frame was prepared densely as soon as one frame might want the bridge.)"""
    stage, _, prepared, f = _stage({})
    f.tried.add(2)  # its dense pairs failed: the bridge may want it
    assert stage.bridge_ready()
    assert prepared == []


class _BridgeStages:
    """The pipeline's stages the bridge uses, without a pipeline; the warps from poses as identities."""

    def lap(self, stage: str, t0: float) -> float:
        return t0

    def predicted_warp(self, a: Frame, b: Frame, poses: Any = None) -> Any:
        return np.eye(3)

    def track_guessed(self, diff: Any, guess: Any, lit: Any) -> None:
        return None


def test_a_bridge_prepares_its_three_frames_only_when_it_is_tried(monkeypatch: pytest.MonkeyPatch) -> None:
    history = FrameHistory(60.0, "opposite_phase")
    lum = np.zeros((8, 8), np.uint8)
    frames = [Frame(k, k * PERIOD_US, lum) for k in range(6)]
    for f in frames:
        history.append(f)
    bridge = bridge_module.ContentBridge(history, MotionTrack(), _BridgeStages(), None, 2)  # type: ignore[arg-type]
    prepared: list[int] = []

    def prepare(f: Frame) -> None:
        prepared.append(f.index)
        f.signal = lum

    monkeypatch.setattr(bridge_module, "bridge_difference", lambda *a, **k: None)
    bridge.prepare = prepare  # (as the pipeline sets it with the sparse tracker)
    bridge.bridge(frames[1], frames[2], frames[3])  # no neighbour has a pose: not tried
    assert prepared == []
    down = np.diag([1.0, -1.0, -1.0])
    frames[1].rt = rt_of(np.array([0.0, 0.0, 1.0]), down)
    frames[3].rt = rt_of(np.array([0.002, 0.0, 1.0]), down)
    bridge.bridge(frames[1], frames[2], frames[3])
    assert prepared == [1, 2, 3]
