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


def test_live_no_bridge_and_no_wait_for_one_for_a_frame_too_late(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 29, target 3 (stop 59): a live camera's frame past the sparse stage's LIVE_LATE_US gets no more work. A
    shadow-vibration run spent 77 ms bridging a frame already 44 ms old while the frames behind it waited; and a frame
    that may still be bridged waits a frame longer, holding the results behind it. A frame not too late is bridged
    and waited for as before."""
    history = FrameHistory(60.0, "opposite_phase")
    frames = [Frame(k, k * PERIOD_US, np.zeros((8, 8), np.uint8)) for k in range(6)]
    for f in frames:
        history.append(f)
    target = frames[2]
    target.tried = {1, 3}  # paired with an earlier and a later frame, no pose
    for too_late, tried in ((False, [(1, 2, 3)]), (True, [])):
        bridge = bridge_module.ContentBridge(history, MotionTrack(), _BridgeStages(), None, 2)  # type: ignore[arg-type]
        bridge.too_late = lambda frame, late=too_late: late and frame is target
        bridges: list[tuple[int, int, int]] = []
        monkeypatch.setattr(bridge, "bridge", lambda a, b, c, out=bridges: out.append((a.index, b.index, c.index)))
        bridge.offer(frames[3])
        assert bridges == tried
        assert bridge.wait(target) == (0 if too_late else 1)
