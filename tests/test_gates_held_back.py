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


def _still_for_100_ms() -> tuple[PoseGates, int]:
    """Gates that let 12 poses at x = 0 out (the motion confirmed); the next frame's number."""
    gates = PoseGates(PoseConfig())
    for k in range(12):
        assert gates.judge(k, k * PERIOD_US, _pose(0.0), 3, "sparse", k - 1).reason == FrameReason.POSE
    return gates, 12


def test_fits_gone_astray_and_held_back_do_not_drag_the_motion() -> None:
    """Still camera at x = 0 for 100 ms; then, as at a seam of an arena file wrong by centimetres, every other frame's
    fit lands 11 cm off (held back) between right ones. The frames after must still be judged against x = 0: the
    right ones go out and a further fit 11 cm off is held back (it once went out, the motion having followed the
    wrong fits)."""
    gates, k = _still_for_100_ms()
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
    gates, k = _still_for_100_ms()
    reasons = []
    for _ in range(60):  # half a second at the new place
        reasons.append(gates.judge(k, k * PERIOD_US, _pose(0.11), 3, "track", k - 1).reason)
        k += 1
    assert reasons[0] == FrameReason.INCONSISTENT
    assert reasons[-10:] == [FrameReason.POSE] * 10


def _followed(before: int, places_m: list[float]) -> float:
    """Where the motion puts the camera after ``before`` poses at x = 0 went out and then poses at ``places_m``."""
    gates = PoseGates(PoseConfig())
    for k in range(before):
        gates.judge(k, k * PERIOD_US, _pose(0.0), 3, "sparse", k - 1)
    for k, x_m in enumerate(places_m, before):
        gates.judge(k, k * PERIOD_US, _pose(x_m), 3, "track", k - 1)
    predicted = gates.motion.pose_at((before + len(places_m)) * PERIOD_US)
    assert predicted is not None
    return float(predicted[0][0])


def test_at_a_flights_start_a_held_back_pose_weighs_in_full() -> None:
    """Before 8 poses went out the motion is not confirmed: poses it holds back join it at their own weight (a
    flight's first poses may be the wrong ones) and a new place takes over within frames."""
    assert _followed(5, [0.11] * 4) > 0.1


def test_once_confirmed_a_lone_held_back_pose_weighs_little() -> None:
    """After 12 poses went out, one fit 11 cm off between right ones barely moves the motion (less than 1 cm)."""
    assert abs(_followed(12, [0.0, 0.11, 0.0])) < 0.01


def test_held_back_poses_that_agree_in_a_row_weigh_in_full() -> None:
    """A right track the motion lost (low-fast-big-shadow: three fits 14-23 mm off went out, and the right poses
    after them, 29-34 mm from the prediction and within a millimetre or two of each other, were held back for nine
    frames): from the second such pose in a row they join the motion in full and it follows them; poses held back
    that disagree with each other (fits gone astray, 11 cm off and 6 cm off in turn) still weigh little."""
    assert _followed(12, [0.11] * 4) > 0.05
    assert abs(_followed(12, [0.11, 0.05, 0.11, 0.05])) < 0.02


def test_before_the_motion_is_confirmed_a_jump_from_the_pose_just_out_is_held_back() -> None:
    """After a gap of dropped frames (few poses out lately) a right pose goes out, and one camera frame later a fit
    60 mm from it (a dense track locked off on the periodic map: 53-73 mm off behind live, stop 47) is held back by the
    speed gate until another agrees; 15 mm from it (a hard flight's spread) goes out. Once the motion is confirmed
    the gate allows its 5 cm again (the consistency gate, off here, judges such poses then)."""
    gates = PoseGates(PoseConfig())
    assert gates.judge(0, 0, _pose(0.0), 3, "track", 2).reason == FrameReason.POSE
    assert gates.judge(1, PERIOD_US, _pose(0.06), 3, "track", 2).reason == FrameReason.MOTION_JUMP
    assert gates.judge(2, 2 * PERIOD_US, _pose(0.015), 3, "track", 0).reason == FrameReason.POSE
    confirmed = PoseGates(PoseConfig(max_prediction_error_m=None))
    for k in range(12):
        assert confirmed.judge(k, k * PERIOD_US, _pose(0.0), 3, "sparse", k - 1).reason == FrameReason.POSE
    assert confirmed.judge(12, 12 * PERIOD_US, _pose(0.06), 3, "track", 11).reason == FrameReason.POSE


def test_before_the_motion_is_confirmed_a_pose_its_next_two_frames_outvote_is_held_back() -> None:
    """Behind live the first frame of a run can be the wrong one (stop 47: frame 617 79 mm off, 618 and 619 right),
    judged before its right neighbours: before the motion is confirmed, a pose further than the speed gate's allowance
    from both later frames' poses, which agree with each other, is held back; one later pose alone does not outvote it,
    nor do two that disagree."""
    right = [(PERIOD_US, _pose(0.0)), (2 * PERIOD_US, _pose(0.004))]
    assert PoseGates(PoseConfig()).judge(0, 0, _pose(0.08), 3, "track", 2, right).reason == FrameReason.MOTION_JUMP
    assert PoseGates(PoseConfig()).judge(0, 0, _pose(0.002), 3, "track", 2, right).reason == FrameReason.POSE
    assert PoseGates(PoseConfig()).judge(0, 0, _pose(0.08), 3, "track", 2, right[:1]).reason == FrameReason.POSE
    split = [(PERIOD_US, _pose(0.0)), (2 * PERIOD_US, _pose(0.16))]
    assert PoseGates(PoseConfig()).judge(0, 0, _pose(0.08), 3, "track", 2, split).reason == FrameReason.POSE


def test_a_pose_asked_about_again_is_judged_against_the_motion_as_it_is_now() -> None:
    """The gates remember their answer for a pose while the motion is unchanged (a frame's pose is asked about two or
    three times); a pose added to the motion, or the motion cleared, and the same pose is judged afresh."""
    gates, k = _still_for_100_ms()
    t_us, astray = k * PERIOD_US, _pose(0.05)
    assert gates.doubt(t_us, astray) == FrameReason.INCONSISTENT
    assert gates.doubt(t_us, astray) == FrameReason.INCONSISTENT
    assert gates.doubt(t_us, _pose(0.0)) is None
    gates.motion.clear()  # (a restart: nothing to judge against)
    assert gates.doubt(t_us, astray) is None
    gates, k = _still_for_100_ms()
    assert gates.doubt(t_us, astray) == FrameReason.INCONSISTENT
    for i in range(30):  # the camera moved to x = 0.05 and stayed: once the motion follows, the pose agrees
        gates.motion.add(t_us - (30 - i) * 1000, np.array([0.05, 0.0, 0.8]), np.eye(3), 0.001)
    assert gates.doubt(t_us, astray) is None
