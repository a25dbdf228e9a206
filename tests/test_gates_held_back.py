"""The gates' motion and the poses they hold back (ipt/receiver/core/gates.py): a run of fits gone astray, held back as
inconsistent, must not drag the motion that judges the frames after them."""

from __future__ import annotations

import numpy as np

from ipt.config.models import PoseConfig
from ipt.receiver.core.gates import PoseGates
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.core.reasons import FrameReason

PERIOD_US = 8333  # 120 FPS
STD_M = 0.0015  # per axis: a sparse pose's own uncertainty


def _pose(x_m: float) -> PoseEstimate:
    cov = np.eye(3) * STD_M**2
    return PoseEstimate(np.array([x_m, 0.0, 0.8]), np.eye(3), (1, 2, 3), 0.5, cov, cov * 1e-2)


def test_fits_gone_astray_and_held_back_do_not_drag_the_motion() -> None:
    """Still camera at x = 0 for 100 ms; then, as at a seam of an arena file wrong by centimetres, every other frame's
    fit lands 11 cm off (held back) between right ones. The frames after must still be judged against x = 0: the
    right ones go out and a further fit 11 cm off is held back (it once went out, the motion having followed the
    wrong fits)."""
    gates = PoseGates(PoseConfig())
    k = 0
    for _ in range(12):
        gates.judge(k, k * PERIOD_US, _pose(0.0), 3, "sparse", k - 1)
        k += 1
    reasons = []
    for i in range(16):
        x_m = 0.11 if i % 2 == 0 else 0.0
        reasons.append(gates.judge(k, k * PERIOD_US, _pose(x_m), 3, "track", k - 1).reason)
        k += 1
    assert reasons[1::2] == [FrameReason.POSE] * 8
    assert reasons[0::2] == [FrameReason.INCONSISTENT] * 8
    predicted = gates.motion.pose_at(k * PERIOD_US)
    assert predicted is not None
    assert abs(float(predicted[0][0])) < 0.01
    assert gates.judge(k, k * PERIOD_US, _pose(0.11), 3, "track", k - 1).reason == FrameReason.INCONSISTENT


def test_a_right_track_the_motion_lost_still_takes_over() -> None:
    """The other way round: the camera really is at x = 0.11 from some frame on (the motion had it wrong): once the
    poses before have left the motion's window, the new place goes out again."""
    gates = PoseGates(PoseConfig())
    k = 0
    for _ in range(12):
        gates.judge(k, k * PERIOD_US, _pose(0.0), 3, "sparse", k - 1)
        k += 1
    reasons = []
    for _ in range(60):  # half a second at the new place
        reasons.append(gates.judge(k, k * PERIOD_US, _pose(0.11), 3, "track", k - 1).reason)
        k += 1
    assert reasons[0] == FrameReason.INCONSISTENT
    assert reasons[-10:] == [FrameReason.POSE] * 10
