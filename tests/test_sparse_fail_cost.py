"""Issue 29: with the sparse tracker a frame that fails, or that the bridge poses, must not cost far more than one that
tracks. The mechanism that cuts part of that cost, in isolation: the bridge prepares only the three frames of a
bridge it tries, not every frame kept (and the sparse stage none: tests/test_sparse_stage.py)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

import ipt.receiver.core.bridge as bridge_module
from ipt.receiver.core.history import Frame, FrameHistory
from ipt.receiver.core.motion import MotionTrack
from ipt.receiver.core.pose import rt_of

PERIOD_US = 8333  # 120 FPS


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
