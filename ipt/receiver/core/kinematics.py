"""Velocity and angular velocity of the camera from its recent poses, with their covariances.

Pure: each pose the daemon sends goes in with its capture time and its own covariances; out comes the
twist at the newest pose's time. The outputs that need a velocity (MAVLink ``ODOMETRY``, ROS
``nav_msgs/Odometry``) keep one of these each and feed it every pose, so the fit does not depend on how
the per-frame pipeline tracks motion inside.

The fit is a generalised least-squares line through the poses of the last :data:`WINDOW_US`: position
``p(τ) = a + v τ`` with ``τ`` the time since the newest pose, each pose weighted by the inverse of its
own 3x3 position covariance (floored at :data:`MIN_POSITION_STD_M`), so a view of two far-off tags
counts less than one of six, and the z axis (worse determined from above) less than x and y. The
rotation is fitted the same way, as small rotations about the arena axes relative to the newest
attitude. The covariance of the slope is the fit's own, scaled up by the reduced chi-square when the
poses scatter more than their covariances say (or the motion is not constant over the window).

A line through the last 100 ms estimates the mean velocity over that window: under an acceleration
``a`` it lags the true velocity by about ``a`` × 50 ms (0.05 m/s at 1 m/s²).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

WINDOW_US = 100_000
"""Poses older than this before the newest are left out of the fit."""
MIN_POSES = 3
"""At least this many poses in the window ..."""
MIN_SPAN_US = 15_000
"""... spanning at least this much time, or there is no estimate."""
MIN_POSITION_STD_M = 0.001
"""Floor on each pose's position uncertainty in the fit (and the uncertainty of one without a covariance
is taken as :data:`UNKNOWN_POSITION_STD_M`)."""
UNKNOWN_POSITION_STD_M = 0.005
MIN_ATTITUDE_STD_RAD = 0.001
UNKNOWN_ATTITUDE_STD_RAD = 0.005


def skew(v: F64) -> F64:
    """The cross-product matrix: ``skew(a) @ b == np.cross(a, b)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass(frozen=True)
class Twist:
    """The camera's motion at :attr:`time_us`, in arena axes."""

    time_us: int
    """Capture time of the newest pose in the fit."""
    velocity_mps: F64
    """(3,) velocity of the camera's optical centre, arena ENU, m/s."""
    velocity_cov: F64
    """3x3 covariance of :attr:`velocity_mps`, (m/s)²."""
    angular_velocity_radps: F64
    """(3,) angular velocity about the arena axes, rad/s (``dR/dt = [ω]× R``)."""
    angular_velocity_cov: F64
    """3x3 covariance of :attr:`angular_velocity_radps`, (rad/s)²."""
    poses: int
    """How many poses the fit used."""

    def velocity_of_point(self, offset_m: F64) -> tuple[F64, F64]:
        """Velocity and its covariance of a point rigidly attached to the camera at ``offset_m`` from the
        optical centre (arena axes): ``v + ω × d``. The two fits are taken as independent."""
        d = np.asarray(offset_m, np.float64)
        s = skew(d)  # ω × d = -d × ω = -skew(d) ω
        return self.velocity_mps + np.cross(self.angular_velocity_radps, d), self.velocity_cov + s @ (
            self.angular_velocity_cov @ s.T
        )


def _rotvecs_relative(rotations: F64, reference: F64) -> F64:
    """(N, 3) rotation vectors of ``R_i Rᵀ_ref`` (small rotations about the fixed axes), all at once."""
    rel = rotations @ reference.T  # (N, 3, 3)
    axis = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], axis=1)
    sin2 = np.linalg.norm(axis, axis=1)  # 2 sin(angle)
    cos2 = np.trace(rel, axis1=1, axis2=2) - 1.0  # 2 cos(angle)
    angle = np.arctan2(sin2, cos2)
    # angle / (2 sin angle), with its limit 1/2 at 0 (the poses of 100 ms differ by a few degrees at most)
    scale = np.where(sin2 > 1e-12, angle / np.maximum(sin2, 1e-300), 0.5)
    return np.asarray(axis * scale[:, None], np.float64)


def _weight(cov: F64, floor_std: float, unknown_std: float) -> F64:
    """The inverse of a covariance with ``floor_std``² added on the diagonal (an unknown one: isotropic)."""
    c = np.asarray(cov, np.float64)
    if c.shape != (3, 3) or not np.all(np.isfinite(c)):
        c = np.eye(3) * unknown_std**2
    return np.asarray(np.linalg.inv(c + np.eye(3) * floor_std**2), np.float64)


def _line_fit(taus_s: F64, values: F64, weights: F64) -> tuple[F64, F64] | None:
    """Slope and its 3x3 covariance of ``values[i] ≈ a + b τ_i`` (3-vectors), each row weighted by its 3x3
    inverse covariance ``weights[i]``; None if the normal equations are singular. The normal matrix of
    ``[I, τ I]`` rows is built from the sums of W, τW and τ²W."""
    t = taus_s[:, None, None]
    s0, s1, s2 = weights.sum(axis=0), (t * weights).sum(axis=0), (t * t * weights).sum(axis=0)
    normal = np.block([[s0, s1], [s1, s2]])
    wy = np.einsum("nij,nj->ni", weights, values)
    rhs = np.concatenate([wy.sum(axis=0), (taus_s[:, None] * wy).sum(axis=0)])
    try:
        cov = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        return None
    theta = cov @ rhs
    r = values - theta[:3] - taus_s[:, None] * theta[3:]
    chi2 = float(np.einsum("ni,nij,nj->", r, weights, r))
    dof = 3 * len(taus_s) - 6
    scale = max(1.0, chi2 / dof) if dof > 0 else 1.0
    slope_cov = scale * cov[3:, 3:]
    return np.asarray(theta[3:], np.float64), np.asarray(0.5 * (slope_cov + slope_cov.T), np.float64)


class VelocityFit:
    """The recent poses of one camera and the twist fitted through them (see the module doc)."""

    def __init__(self, window_us: int = WINDOW_US, min_poses: int = MIN_POSES, min_span_us: int = MIN_SPAN_US):
        self.window_us, self.min_poses, self.min_span_us = window_us, min_poses, min_span_us
        self._poses: deque[tuple[int, F64, F64, F64, F64]] = deque()

    def __len__(self) -> int:
        return len(self._poses)

    def clear(self) -> None:
        """Forget every pose (a re-initialised track: the motion before it says nothing about after)."""
        self._poses.clear()

    def add(
        self,
        time_us: int,
        position_m: F64,
        r_arena_cam: F64,
        position_cov_m2: F64 | None = None,
        attitude_cov_rad2: F64 | None = None,
    ) -> None:
        """Record a pose. A time not after the newest, or more than a window after it, starts afresh."""
        if self._poses and not 0 < time_us - self._poses[-1][0] <= self.window_us:
            self._poses.clear()
        nan = np.full((3, 3), np.nan)
        self._poses.append(
            (
                int(time_us),
                np.asarray(position_m, np.float64).reshape(3),
                np.asarray(r_arena_cam, np.float64).reshape(3, 3),
                _weight(
                    nan if position_cov_m2 is None else position_cov_m2, MIN_POSITION_STD_M, UNKNOWN_POSITION_STD_M
                ),
                _weight(
                    nan if attitude_cov_rad2 is None else attitude_cov_rad2,
                    MIN_ATTITUDE_STD_RAD,
                    UNKNOWN_ATTITUDE_STD_RAD,
                ),
            )
        )
        while time_us - self._poses[0][0] > self.window_us:
            self._poses.popleft()

    def twist(self) -> Twist | None:
        """The twist at the newest pose's time, or None with too few poses or too short a span."""
        if len(self._poses) < self.min_poses:
            return None
        t_new, _, r_new, _, _ = self._poses[-1]
        if t_new - self._poses[0][0] < self.min_span_us:
            return None
        taus = np.array([(p[0] - t_new) * 1e-6 for p in self._poses])
        linear = _line_fit(taus, np.stack([p[1] for p in self._poses]), np.stack([p[3] for p in self._poses]))
        rotvecs = _rotvecs_relative(np.stack([p[2] for p in self._poses]), r_new)
        angular = _line_fit(taus, rotvecs, np.stack([p[4] for p in self._poses]))
        if linear is None or angular is None:
            return None
        return Twist(t_new, linear[0], linear[1], angular[0], angular[1], len(self._poses))


__all__ = ["Twist", "VelocityFit", "skew"]
