"""The motion track and the floor homography that the pipeline uses to predict how a frame pair is warped."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from ipt.geometry import R_BODY_CAM_DOWNWARD, rot_x, rot_z, rotation_angle_rad
from ipt.receiver.core.motion import MotionTrack, floor_homography, floor_warp

F64 = npt.NDArray[np.float64]
K = np.array([[460.0, 0.0, 319.5], [0.0, 460.0, 179.5], [0.0, 0.0, 1.0]])
VELOCITY_MPS = np.array([0.6, -0.3, 0.05])
YAW_RATE_RADPS = np.deg2rad(20.0)


def _true_pose(t_us: int) -> tuple[F64, F64]:
    t = t_us * 1e-6
    return np.array([0.1, 0.2, 0.8]) + VELOCITY_MPS * t, rot_z(0.3 + YAW_RATE_RADPS * t) @ R_BODY_CAM_DOWNWARD


def _track(times_us: list[int]) -> MotionTrack:
    track = MotionTrack()
    for t in times_us:
        track.add(t, *_true_pose(t))
    return track


def test_constant_motion_is_extrapolated_exactly() -> None:
    times = [round(k * 1e6 / 120) for k in range(12)]
    predicted = _track(times).pose_at(times[-1] + 16_667)
    assert predicted is not None
    position, rotation = predicted
    true_position, true_rotation = _true_pose(times[-1] + 16_667)
    assert np.linalg.norm(position - true_position) < 1e-9
    assert rotation_angle_rad(rotation.T @ true_rotation) < 1e-6


def test_one_bad_pose_does_not_drag_the_prediction() -> None:
    track = MotionTrack()
    for k in range(14):
        t = round(k * 1e6 / 120)
        position, rotation = _true_pose(t)
        if k == 10:
            position = position + np.array([0.04, 0.0, 0.0])
            rotation = rot_x(np.deg2rad(3.0)) @ rotation
        track.add(t, position, rotation)
    t_next = round(14 * 1e6 / 120)
    predicted = track.pose_at(t_next)
    assert predicted is not None
    true_position, true_rotation = _true_pose(t_next)
    assert np.linalg.norm(predicted[0] - true_position) < 1e-6
    assert rotation_angle_rad(predicted[1].T @ true_rotation) < 1e-6


@pytest.mark.parametrize(
    ("times_us", "at_us"),
    [
        ([], 0),  # nothing yet
        ([0, 8_333, 16_667], 25_000),  # too few poses
        ([0, 5_000, 10_000, 15_000, 20_000], 25_000),  # enough poses, too short a span to fit a rate
        ([round(k * 1e6 / 120) for k in range(12)], 91_667 + 100_001),  # too far past the newest pose
    ],
)
def test_no_prediction_without_enough_recent_poses(times_us: list[int], at_us: int) -> None:
    assert _track(times_us).pose_at(at_us) is None


def test_time_going_backwards_starts_afresh() -> None:
    track = _track([round(k * 1e6 / 120) for k in range(40, 52)])
    track.add(0, *_true_pose(0))  # far before the fit's window: a jump back in the recording
    assert len(track) == 1


def test_floor_warp_carries_floor_points_between_views() -> None:
    before, after = _true_pose(0), _true_pose(16_667)
    floor_m = np.array([[0.0, 0.0, 0.0], [0.3, 0.1, 0.0], [-0.2, 0.35, 0.0], [0.25, -0.3, 0.0]])

    def project(pose: tuple[F64, F64]) -> F64:
        r_cam_arena = pose[1].T
        rvec, _ = cv2.Rodrigues(r_cam_arena)
        uv, _ = cv2.projectPoints(floor_m, rvec, -r_cam_arena @ pose[0], K, np.zeros(5))
        return np.asarray(uv, np.float64).reshape(-1, 2)

    uv_before, uv_after = project(before), project(after)
    h = floor_homography(K, *before)
    np.testing.assert_allclose(cv2.perspectiveTransform(floor_m[None, :, :2], h)[0], uv_before, atol=1e-9)
    warp = floor_warp(K, before, after)
    assert warp is not None
    np.testing.assert_allclose(cv2.perspectiveTransform(uv_before[None], warp)[0], uv_after, atol=1e-6)


def test_floor_warp_refuses_a_camera_in_the_floor() -> None:
    level = (np.array([0.0, 0.0, 0.0]), rot_x(np.pi / 2))  # on the floor, looking along it
    assert floor_warp(K, level, _true_pose(0)) is None


def test_uncertain_poses_count_less_than_certain_ones() -> None:
    # Every other pose is a two-tag view 35 mm off with a large uncertainty: too many to be left out as
    # outliers by a plain fit, but weighted by their uncertainty they barely move the prediction.
    track = MotionTrack()
    for k in range(16):
        t = round(k * 1e6 / 120)
        position, rotation = _true_pose(t)
        if k % 2:
            track.add(t, position + np.array([0.035, -0.01, 0.0]), rotation, position_std_m=0.03)
        else:
            track.add(t, position, rotation, position_std_m=0.003)
    t_next = round(16 * 1e6 / 120)
    predicted = track.pose_at(t_next)
    assert predicted is not None
    assert np.linalg.norm(predicted[0] - _true_pose(t_next)[0]) < 0.002


def test_a_pose_solved_late_takes_its_place_in_time() -> None:
    # Poses come out of order when a frame waited for a later partner: 0, 2, 1, 3, 5, 4 (8.3 ms apart).
    track = MotionTrack()
    for k in (0, 2, 1, 3, 5, 4, 6):
        track.add(round(k * 8333), np.array([0.01 * k, 0.0, 0.8]), np.eye(3))
    assert len(track) == 7
    predicted = track.pose_at(8 * 8333)
    assert predicted is not None
    assert predicted[0][0] == pytest.approx(0.08, abs=1e-4)  # the line through them, not a reset


def test_a_better_pose_for_a_time_replaces_the_first() -> None:
    track = MotionTrack()
    for k in range(6):
        track.add(round(k * 8333), np.array([0.01 * k, 0.0, 0.8]), np.eye(3))
    track.add(5 * 8333, np.array([0.05, 0.0, 0.8]), np.eye(3), 0.001)
    assert len(track) == 6


def test_the_attitude_follows_a_vibration_better_than_a_long_line() -> None:
    # Roll oscillating ±1.5° at 6 Hz: the fit over the last 40 ms predicts two frames ahead within a
    # fraction of a degree, where a straight line through 150 ms would be off by more than a degree.
    track = MotionTrack()
    amplitude, w = np.deg2rad(1.5), 2 * np.pi * 6
    times = np.arange(0, 0.2, 1 / 120)
    for t in times:
        track.add(round(t * 1e6), np.array([0.0, 0.0, 0.8]), rot_x(amplitude * np.sin(w * t)))
    ahead = times[-1] + 2 / 120
    predicted = track.pose_at(round(ahead * 1e6))
    assert predicted is not None
    error = np.rad2deg(rotation_angle_rad(predicted[1].T @ rot_x(amplitude * np.sin(w * ahead))))
    assert error < 0.7


def _noisy_track(count: int, rng: np.random.Generator) -> tuple[MotionTrack, list[tuple[int, F64, F64]]]:
    track, poses = MotionTrack(), []
    for k in range(count):
        t = round(k * 1e6 / 120)
        position, rotation = _true_pose(t)
        position = position + rng.normal(0.0, 0.002, 3)
        rotation = rot_x(float(rng.normal(0.0, 0.01))) @ rotation
        poses.append((t, position, rotation))
        track.add(t, position, rotation)
    return track, poses


def test_the_position_alone_is_the_poses_and_the_attitude_follows_each_added_pose() -> None:
    """The gates ask only for the position (``position_at``), the dense way for the whole pose (``pose_at``, whose
    attitude is fitted when first asked for): the same position to the bit either way, in either order, and a pose
    added after a prediction refits the attitude too (a stale attitude fit would survive in ``pose_at``)."""
    rng = np.random.default_rng(5)
    asked, poses = _noisy_track(20, rng)
    at = poses[-1][0] + 16_667
    position = asked.position_at(at)
    first = asked.pose_at(at)
    assert position is not None
    assert first is not None
    assert np.array_equal(position, first[0])
    fresh, _ = _noisy_track(20, np.random.default_rng(5))
    again = fresh.pose_at(at)
    assert again is not None
    assert np.array_equal(again[0], first[0])
    assert np.array_equal(again[1], first[1])
    t = at
    turned = rot_z(0.2) @ poses[-1][2]  # a pose turned well away from the fitted attitude
    asked.add(t, poses[-1][1], turned)
    fresh = MotionTrack()
    for p in [*poses, (t, poses[-1][1], turned)]:
        fresh.add(*p)
    later, expected = asked.pose_at(t + 8_333), fresh.pose_at(t + 8_333)
    assert later is not None
    assert expected is not None
    assert np.array_equal(later[1], expected[1])
    assert not np.array_equal(later[1], first[1])
