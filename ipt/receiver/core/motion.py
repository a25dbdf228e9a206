"""The camera's recent motion, for predicting how the floor moves between two frames of a pair.

Pure: every pose the pipeline solved (gated or not) and its capture time go in; out come the pose at
another time (constant velocity and rotation rate, fitted robustly over the last poses so that one bad
pose does not swing the prediction) and the homography the floor plane induces between two such poses.
"""

from __future__ import annotations

import bisect
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.receiver.core.track import fast_median

F64 = npt.NDArray[np.float64]

#: Poses older than this (before the newest) are not used for the fit.
WINDOW_US = 150_000
#: At least this many poses, spanning at least :data:`MIN_SPAN_US`, are needed for a prediction.
MIN_POSES, MIN_SPAN_US = 5, 30_000
#: Floor on a pose's position uncertainty in the weighted fit (and the weight of a pose without one).
MIN_STD_M = 0.002
#: A pose closer than this to the fit through the others is never left out of it.
MIN_OUTLIER_M = 0.005
#: The attitude's rate is fitted over the poses of this last span only (see :meth:`MotionTrack._fit_recent`).
ROTATION_WINDOW_US = 40_000
#: No prediction further than this past the newest pose.
MAX_HORIZON_US = 100_000


def _rotvec(r: F64) -> F64:
    vec, _ = cv2.Rodrigues(r)
    return np.asarray(vec, np.float64).reshape(3)


def _matrix(rotvec: F64) -> F64:
    mat, _ = cv2.Rodrigues(rotvec.reshape(3, 1))
    return np.asarray(mat, np.float64)


class MotionTrack:
    """The last solved poses of one camera and a robust constant-rate fit through them, each pose weighted
    by its own uncertainty (a view of two tags counts far less than one of six)."""

    def __init__(self, maxlen: int = 32) -> None:
        self._poses: deque[tuple[int, F64, F64, float]] = deque(maxlen=maxlen)
        self._fit: _PositionFit | None = None
        self._fitted = False
        self._rotation: F64 | None = None  # the rotation's coefficients, fitted when first asked for
        self.changes = 0
        """Poses added and clearings so far: a prediction asked again before it changes is the same."""

    def __len__(self) -> int:
        return len(self._poses)

    def clear(self) -> None:
        """Forget everything (after a jump in the video or a re-initialised track)."""
        self._poses.clear()
        self._fitted = False
        self.changes += 1

    def add(self, time_us: int, position_m: F64, r_arena_cam: F64, position_std_m: float | None = None) -> None:
        """Record a solved pose and how uncertain its position is (the norm of its per-axis standard
        deviation; unknown: :data:`MIN_STD_M`). A pose a little older than the newest (one solved late,
        from a later frame) takes its place in time, and one at the time of a pose held replaces it; one
        older than the fit's window starts the track afresh."""
        std_m = MIN_STD_M if position_std_m is None or not np.isfinite(position_std_m) else position_std_m
        pose = (time_us, np.asarray(position_m, np.float64), np.asarray(r_arena_cam, np.float64), max(std_m, MIN_STD_M))
        self._fitted = False
        self.changes += 1
        if not self._poses or time_us > self._poses[-1][0]:
            self._poses.append(pose)
            return
        times = [p[0] for p in self._poses]
        if time_us in times:  # a better pose for a time already held takes its place
            self._poses[times.index(time_us)] = pose
            return
        if time_us < times[-1] - WINDOW_US:
            self._poses.clear()
            self._poses.append(pose)
            return
        if len(self._poses) == self._poses.maxlen:
            self._poses.popleft()  # the oldest goes first: a full deque takes no insertion
            times.pop(0)
        self._poses.insert(bisect.bisect(times, time_us), pose)

    def pose_at(self, time_us: int) -> tuple[F64, F64] | None:
        """(position_m, r_arena_cam) at ``time_us``, or None if the recent poses are too few or too old.

        The fit is robust: poses far from the line through the others (beyond three robust standard
        deviations, and at least :data:`MIN_OUTLIER_M`) are left out of it, so a doubtful pose that was
        recorded cannot drag the prediction along. It is computed once per added pose, the attitude's part
        only once a pose is asked for (:meth:`position_at` needs only the position's).
        """
        position = self.position_at(time_us)
        if position is None:
            return None
        assert self._fit is not None
        if self._rotation is None:
            self._rotation = self._fit.rotation()
        dt = (time_us - self._fit.t_ref) * 1e-6
        return position, _matrix(self._rotation[0] + self._rotation[1] * dt) @ self._fit.r_ref

    def position_at(self, time_us: int) -> F64 | None:
        """:meth:`pose_at`'s position alone (the same to the bit), without fitting the attitude's rate: the
        gates ask only where the camera should be."""
        if not self._fitted:
            self._fit = _PositionFit.of(self._poses)
            self._rotation = None
            self._fitted = True
        if self._fit is None:
            return None
        if time_us - self._fit.t_ref > MAX_HORIZON_US:
            return None
        dt = (time_us - self._fit.t_ref) * 1e-6
        coef_p = self._fit.coef_p
        return np.asarray(coef_p[0] + coef_p[1] * dt, np.float64)


@dataclass(frozen=True)
class _PositionFit:
    """The robust straight-line fit of the recent positions (:meth:`MotionTrack.pose_at`), and what the
    attitude's fit over the same poses needs from it."""

    t_ref: int
    r_ref: F64
    coef_p: F64
    rotations: tuple[F64, ...]
    """The attitudes (r_arena_cam) of the poses the fit is over, oldest first."""
    dt_s: F64
    root_w: F64
    design: F64
    inliers: npt.NDArray[np.bool_]

    @staticmethod
    def of(poses: deque[tuple[int, F64, F64, float]]) -> _PositionFit | None:
        if not poses:
            return None
        t_ref, _, r_ref, _ = poses[-1]
        recent = [p for p in poses if t_ref - p[0] <= WINDOW_US]
        if len(recent) < MIN_POSES or t_ref - recent[0][0] < MIN_SPAN_US:
            return None
        dt_s = np.array([(p[0] - t_ref) * 1e-6 for p in recent])
        std_m = np.array([p[3] for p in recent])
        root_w = (1.0 / std_m)[:, None]  # weighted least squares: rows scaled by 1/σ
        design = np.ones((len(recent), 2))  # (built in place: np.stack's calls cost a quarter of this fit)
        design[:, 1] = dt_s
        positions = np.array([p[1] for p in recent])
        inliers = np.ones(len(recent), bool)
        for _ in range(3):
            coef_p, *_ = np.linalg.lstsq((design * root_w)[inliers], (positions * root_w)[inliers], rcond=None)
            residual = np.linalg.norm(positions - design @ coef_p, axis=1)
            z = residual / std_m
            scale = max(1.4826 * fast_median(z[inliers]), 1.0)
            keep = (residual <= MIN_OUTLIER_M) | (z <= 3.0 * scale)
            if keep.sum() < MIN_POSES or np.array_equal(keep, inliers):
                break
            inliers = keep
        rotations = tuple(p[2] for p in recent)
        return _PositionFit(t_ref, r_ref, np.asarray(coef_p, np.float64), rotations, dt_s, root_w, design, inliers)

    def rotation(self) -> F64:
        """The attitude's constant-rate fit (rotation vectors about the arena's axes, relative to the newest
        pose's) over the same recent poses, their inliers of the last :data:`ROTATION_WINDOW_US` where there
        are enough of them."""
        # The attitude is fitted over a shorter span: a vibrating airframe turns back and forth at 5-7 Hz,
        # which a straight line through 150 ms misses by 1.6° (median) two frames ahead, and one through
        # the last 40 ms by 0.65° (on the simulated default flight).
        dt_s, inliers = self.dt_s, self.inliers
        short = inliers & (dt_s >= -ROTATION_WINDOW_US * 1e-6)
        rot_rows = short if short.sum() >= 3 and np.ptp(dt_s[short]) >= MIN_SPAN_US * 1e-6 / 2 else inliers
        # small rotations about arena axes, of the rows fitted only
        fitted = [r for r, used in zip(self.rotations, rot_rows, strict=True) if used]
        rotvecs = np.stack([_rotvec(r @ self.r_ref.T) for r in fitted])
        coef_r, *_ = np.linalg.lstsq((self.design * self.root_w)[rot_rows], rotvecs * self.root_w[rot_rows], rcond=None)
        return np.asarray(coef_r, np.float64)


def floor_homography(camera_matrix: F64, position_m: F64, r_arena_cam: F64) -> F64:
    """The 3x3 map from floor points (x, y) in arena metres (z = 0) to undistorted pixels of the camera."""
    r_cam_arena = r_arena_cam.T
    t_cam = -r_cam_arena @ position_m
    return np.asarray(camera_matrix @ np.column_stack([r_cam_arena[:, 0], r_cam_arena[:, 1], t_cam]), np.float64)


def floor_warp(camera_matrix: F64, before: tuple[F64, F64], after: tuple[F64, F64]) -> F64 | None:
    """The homography that carries the floor's image at pose ``before`` onto its image at pose ``after``.

    None if either pose does not look at the floor from above it (a degenerate map).
    """
    h_before = floor_homography(camera_matrix, *before)
    h_after = floor_homography(camera_matrix, *after)
    if abs(np.linalg.det(h_before)) < 1e-12:
        return None
    warp = h_after @ np.linalg.inv(h_before)
    if not np.all(np.isfinite(warp)) or abs(warp[2, 2]) < 1e-12:
        return None
    return np.asarray(warp / warp[2, 2], np.float64)
