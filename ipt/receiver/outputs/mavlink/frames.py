"""MAVLink's frames and the pose maths, pure: a camera pose in the arena in, the vehicle body's pose in the
autopilot's frames out, with its covariance, a quality, a reset counter and the body's velocity.

No clock, no socket, no pymavlink: :mod:`ipt.receiver.outputs.mavlink.output` sends what this module
computes, and :mod:`ipt.receiver.outputs.ros.frames` uses the same mounting. The frames are described in
:mod:`ipt.receiver.outputs.mavlink.output`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.geometry import R_BODY_CAM_DOWNWARD, quat_wxyz_from_matrix, ypr_from_matrix
from ipt.receiver.core.kinematics import Twist
from ipt.receiver.core.pose import PoseEstimate

if TYPE_CHECKING:
    pass

F64 = npt.NDArray[np.float64]

#: Arena ENU → local NED (the arena's y is "north"): a proper rotation (determinant +1).
R_NED_ENU: F64 = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: Body FLU (``ipt.geometry``'s body) → body FRD.
R_FRD_FLU: F64 = np.diag([1.0, -1.0, -1.0])
#: The default mounting in FRD: looking straight down, the top of the image towards the nose. Columns are
#: the camera axes in body FRD: x_cam = right = +y, y_cam = backwards = -x, z_cam = down = +z.
R_FRD_CAM_DOWNWARD: F64 = R_FRD_FLU @ R_BODY_CAM_DOWNWARD


class MavlinkError(IptError):
    """A MAVLink setting is wrong (unknown dialect, bad link) or a link cannot be opened."""


@dataclass(frozen=True)
class Mounting:
    """Where the camera sits on the vehicle body (FRD)."""

    r_frd_cam: F64 = field(default_factory=lambda: R_FRD_CAM_DOWNWARD.copy())
    """3x3 rotation camera (OpenCV optical) → body FRD: the camera axes as columns in body axes."""
    camera_position_frd_m: F64 = field(default_factory=lambda: np.zeros(3))
    """The camera's optical centre from the body origin, body FRD metres."""

    def __post_init__(self) -> None:
        r = np.asarray(self.r_frd_cam, np.float64)
        if r.shape != (3, 3) or not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise MavlinkError("the camera rotation must be a 3x3 rotation matrix (orthonormal, determinant +1)")
        object.__setattr__(self, "r_frd_cam", r)
        object.__setattr__(self, "camera_position_frd_m", np.asarray(self.camera_position_frd_m, np.float64))


def skew(v: F64) -> F64:
    """The cross-product matrix: ``skew(a) @ b == np.cross(a, b)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def body_pose_ned(pose: PoseEstimate, mounting: Mounting) -> tuple[F64, F64]:
    """The body origin's position in local NED metres and the rotation body FRD → local NED."""
    r_arena_frd = pose.r_arena_cam @ mounting.r_frd_cam.T
    body_enu = pose.position_m - r_arena_frd @ mounting.camera_position_frd_m
    return R_NED_ENU @ body_enu, R_NED_ENU @ r_arena_frd


def euler_rpy_rad(r_ned_frd: F64) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of the body: ``r = Rz(yaw) Ry(pitch) Rx(roll)``, MAVLink's convention."""
    yaw, pitch, roll = ypr_from_matrix(r_ned_frd)
    return roll, pitch, yaw


def euler_jacobian(r_ned_frd: F64) -> F64:
    """d(roll, pitch, yaw) / dθ for a small rotation θ about the local axes applied as ``exp(θ×) r``.

    An angular velocity in the local frame is ``E · (roll', pitch', yaw')`` with E's columns the roll axis
    (body x), the pitch axis (yaw-rotated y) and the yaw axis (local z); the Jacobian is ``E⁻¹``. Singular
    at ±90° of pitch, which a drone flying over a floor does not reach.
    """
    _, pitch, yaw = euler_rpy_rad(r_ned_frd)
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    e = np.array([[cp * cy, -sy, 0.0], [cp * sy, cy, 0.0], [-sp, 0.0, 1.0]])
    return np.asarray(np.linalg.inv(e), np.float64)


def pose_covariance_ned(pose: PoseEstimate, mounting: Mounting, min_attitude_std_rad: float = 0.0) -> F64:
    """6x6 covariance of (x, y, z, roll, pitch, yaw) of the body in local NED, from the pose's own.

    The body origin is ``c - R t`` (c the camera, t its offset on the body), so a small rotation θ moves it
    by ``(R t) × θ``: the attitude's uncertainty adds to the position's through the lever arm. The pose
    gives no position–attitude cross terms of the camera; those of the lever arm are kept. Each attitude
    variance is at least ``min_attitude_std_rad`` squared (raising diagonal entries keeps the matrix a
    covariance): no autopilot should be told the attitude is exact.
    """
    r_arena_frd = pose.r_arena_cam @ mounting.r_frd_cam.T
    lever = skew(r_arena_frd @ mounting.camera_position_frd_m)  # d(body)/dθ, arena axes
    cov_c = np.asarray(pose.position_cov_m2, np.float64)
    cov_th = np.array(pose.attitude_cov_rad2, np.float64)
    floor = min_attitude_std_rad**2
    for i in range(3):
        if np.isfinite(cov_th[i, i]) and cov_th[i, i] < floor:
            cov_th[i, i] = floor
    cov_p_enu = cov_c + lever @ cov_th @ lever.T
    cross_enu = lever @ cov_th
    m = R_NED_ENU
    _, r_ned_frd = body_pose_ned(pose, mounting)
    j = euler_jacobian(r_ned_frd) @ m  # d(rpy) / dθ_enu
    cov = np.zeros((6, 6))
    cov[:3, :3] = m @ cov_p_enu @ m.T
    cov[3:, 3:] = j @ cov_th @ j.T
    cov[:3, 3:] = m @ cross_enu @ j.T
    cov[3:, :3] = cov[:3, 3:].T
    return cov


def upper_triangle_21(cov: F64) -> tuple[float, ...]:
    """MAVLink's covariance layout: the upper-right triangle of a 6x6 matrix, row by row (21 values).

    A matrix with any non-finite entry is "unknown": NaN first, as the MAVLink spec asks."""
    if not np.all(np.isfinite(cov)):
        return (math.nan,) + (0.0,) * 20
    return tuple(float(cov[i, j]) for i in range(6) for j in range(i, 6))


def quality_percent(position_std_m: float, zero_quality_std_m: float) -> int:
    """MAVLink's quality: 100 for a perfect position, falling linearly to 1 at ``zero_quality_std_m`` of
    3-D standard deviation and staying there; 0 ("unknown") when the uncertainty is unknown."""
    if not math.isfinite(position_std_m):
        return 0
    return int(np.clip(round(100.0 * (1.0 - position_std_m / zero_quality_std_m)), 1, 100))


@dataclass(frozen=True)
class OdometrySample:
    """What one pose becomes on the wire (both ODOMETRY and VISION_POSITION_ESTIMATE carry it)."""

    time_usec: int
    position_ned_m: F64
    """The body origin in local NED (the arena's axes turned to north-east-down) metres."""
    quat_wxyz: F64
    """Rotation body FRD → local NED."""
    rpy_rad: tuple[float, float, float]
    """The same rotation as roll, pitch, yaw (Z-Y-X)."""
    covariance_6x6: F64
    """Covariance of (x, y, z, roll, pitch, yaw)."""
    quality: int
    reset_counter: int
    num_tags: int
    velocity_frd_mps: F64 = field(default_factory=lambda: np.full(3, np.nan))
    """The body origin's velocity in body FRD axes (ODOMETRY's child frame); NaN when unknown."""
    velocity_cov_frd: F64 = field(default_factory=lambda: np.full((3, 3), np.nan))
    """3x3 covariance of :attr:`velocity_frd_mps`."""

    @property
    def pose_covariance(self) -> tuple[float, ...]:
        """The 21 values of the covariance's upper-right triangle."""
        return upper_triangle_21(self.covariance_6x6)

    @property
    def velocity_covariance(self) -> tuple[float, ...]:
        """ODOMETRY's ``velocity_covariance``: (vx, vy, vz, rollspeed, pitchspeed, yawspeed), upper triangle.
        The rates are not sent, so their variances are NaN; the whole is "unknown" (NaN first) without a
        velocity."""
        if not (np.all(np.isfinite(self.velocity_frd_mps)) and np.all(np.isfinite(self.velocity_cov_frd))):
            return (math.nan,) + (0.0,) * 20
        cov = np.zeros((6, 6))
        cov[:3, :3] = self.velocity_cov_frd
        for i in range(3, 6):
            cov[i, i] = math.nan
        return tuple(float(cov[i, j]) for i in range(6) for j in range(i, 6))


def odometry_sample(
    pose: PoseEstimate,
    time_usec: int,
    mounting: Mounting,
    reset_counter: int = 0,
    zero_quality_std_m: float = 0.1,
    min_attitude_std_rad: float = 0.0,
) -> OdometrySample:
    """The MAVLink view of one camera pose."""
    position_ned_m, r_ned_frd = body_pose_ned(pose, mounting)
    cov = pose_covariance_ned(pose, mounting, min_attitude_std_rad)
    std_m = float(np.sqrt(np.trace(cov[:3, :3]))) if np.all(np.isfinite(cov[:3, :3])) else math.nan
    return OdometrySample(
        time_usec=time_usec,
        position_ned_m=position_ned_m,
        quat_wxyz=quat_wxyz_from_matrix(r_ned_frd),
        rpy_rad=euler_rpy_rad(r_ned_frd),
        covariance_6x6=cov,
        quality=quality_percent(std_m, zero_quality_std_m),
        reset_counter=reset_counter % 256,
        num_tags=len(pose.tag_ids),
    )


def body_velocity_frd(twist: Twist, pose: PoseEstimate, mounting: Mounting) -> tuple[F64, F64]:
    """The body origin's velocity in body FRD axes and its covariance, from the camera's twist: the origin
    sits at ``-R t`` from the camera (t its offset on the body), so it moves at ``v + ω × (-R t)``."""
    r_arena_frd = pose.r_arena_cam @ mounting.r_frd_cam.T
    v_arena, cov_arena = twist.velocity_of_point(-(r_arena_frd @ mounting.camera_position_frd_m))
    r = r_arena_frd.T
    return r @ v_arena, r @ cov_arena @ r.T


class RateLimiter:
    """At most ``max_rate_hz`` messages per second of capture time: a sample goes out when it is at least
    ``1 / max_rate_hz`` after the last one that went out (so any second holds at most ``max_rate_hz``), and
    the one that goes out is always the newest. ``None``: everything goes out. Time going backwards (a
    new recording) starts afresh."""

    def __init__(self, max_rate_hz: float | None) -> None:
        self.min_interval_us = None if max_rate_hz is None else 1e6 / max_rate_hz
        self._last_us: int | None = None
        self.held_back = 0
        """Samples not sent because they came too soon."""

    def admit(self, time_us: int) -> bool:
        """Whether a sample captured at ``time_us`` goes out now (and if so, it is counted as sent)."""
        last = self._last_us
        if self.min_interval_us is not None and last is not None and 0 <= time_us - last < self.min_interval_us:
            self.held_back += 1
            return False
        self._last_us = time_us
        return True


class OdometryTracker:
    """Turns successive poses into samples, counting resets: the pipeline re-initialised its track
    (``reset``), or the body moved more than ``reset_jump_m`` since the previous sample. The counter is
    a uint8 on the wire and wraps."""

    def __init__(
        self,
        mounting: Mounting,
        reset_jump_m: float = 0.5,
        zero_quality_std_m: float = 0.1,
        min_attitude_std_rad: float = 0.0,
    ) -> None:
        self.mounting = mounting
        self.reset_jump_m = reset_jump_m
        self.zero_quality_std_m = zero_quality_std_m
        self.min_attitude_std_rad = min_attitude_std_rad
        self.reset_counter = 0
        self.resets = 0
        self._last: F64 | None = None

    def update(self, pose: PoseEstimate, time_usec: int, reset: bool = False) -> OdometrySample:
        """The sample for ``pose``; increments the reset counter first when the solution jumped."""
        sample = odometry_sample(
            pose, time_usec, self.mounting, self.reset_counter, self.zero_quality_std_m, self.min_attitude_std_rad
        )
        jumped = (
            self._last is not None and float(np.linalg.norm(sample.position_ned_m - self._last)) > self.reset_jump_m
        )
        if reset or jumped:
            self.reset_counter = (self.reset_counter + 1) % 256
            self.resets += 1
            sample = OdometrySample(**{**sample.__dict__, "reset_counter": self.reset_counter})
        self._last = sample.position_ned_m
        return sample


FixEvent = Literal["lost", "regained"]


class FixMonitor:
    """Says when the fix is lost (no pose for ``timeout_s`` after one) and when it comes back. Pure: the
    caller passes the time in."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.have_fix = False
        self.ever = False
        self._last_pose_s: float | None = None

    def pose(self, now_s: float) -> FixEvent | None:
        """A pose arrived at ``now_s``."""
        self._last_pose_s = now_s
        event: FixEvent | None = "regained" if self.ever and not self.have_fix else None
        self.have_fix = self.ever = True
        return event

    def tick(self, now_s: float) -> FixEvent | None:
        """Time passed; "lost" once when the last pose is older than the timeout."""
        if self.have_fix and self._last_pose_s is not None and now_s - self._last_pose_s > self.timeout_s:
            self.have_fix = False
            return "lost"
        return None


def mounting_from(r_frd_cam: Sequence[Sequence[float]] | None, camera_position_frd_m: Sequence[float]) -> Mounting:
    """A :class:`Mounting` from config values (``None``: the downward default)."""
    r = R_FRD_CAM_DOWNWARD if r_frd_cam is None else np.asarray(r_frd_cam, np.float64)
    return Mounting(r, np.asarray(camera_position_frd_m, np.float64))
