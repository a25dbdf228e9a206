"""What one frame becomes on the ROS 2 side: pose, odometry, transforms and diagnostics, as messages.

Pure: a frame's result (and its pose, capture time, stage times) in, ROS messages out (nested dicts in
the layout of :mod:`ipt.rosmsg`). The DDS output (:mod:`ipt.receiver.outputs.ros.dds`) publishes the first three; the
recorder (:mod:`ipt.receiver.outputs.ros.record`) writes all four. Frames, as REP 103/105 ask:

- ``/ipt/pose`` (``geometry_msgs/msg/PoseWithCovarianceStamped``): the camera's pose in the arena frame
  (``frame_id``, ENU), exactly the pose the pipeline solved: the optical centre and ``R_arena_cam``
  (OpenCV optical axes: x right, y down, z forward). Covariance order (x, y, z, rotation about the arena's
  X, Y, Z axes), from the pose's own position and attitude covariances; the PnP solution gives no
  cross terms between the two, so those are 0. An unknown covariance is all zeros (ROS: "unknown").
- ``/ipt/odom`` (``nav_msgs/msg/Odometry``): the vehicle body (``base_link``, FLU: x forward, y left,
  z up) in the arena frame, through the camera mounting (``r_frd_cam``, ``camera_position_frd_m``); its
  covariance carries the attitude's uncertainty through the lever arm. The twist is in ``base_link`` axes
  (as ``nav_msgs/Odometry`` defines it), from :class:`~ipt.receiver.core.kinematics.VelocityFit`; without an
  estimate yet it is zero with ``covariance[0] = -1`` (the ROS sign for "no estimate").
- ``/tf`` (``tf2_msgs/msg/TFMessage``): arena → camera and arena → base_link, the same poses.
- ``/ipt/diagnostics`` (``diagnostic_msgs/msg/DiagnosticArray``), recorded only: every frame's outcome
  (why there is no pose), tag count and stage times. (The recorder adds ``/ipt/difference`` itself.)

With a ``namespace`` (one per drone) topics become ``/ipt/<namespace>/pose`` ... and the body frames
``<namespace>/base_link`` and ``<namespace>/camera``; ``/tf`` and the arena frame are shared.

Time stamps are the frames' capture times turned into ROS time (:class:`StampClock`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ipt.geometry import quat_wxyz_from_matrix
from ipt.receiver.core.kinematics import Twist, VelocityFit, skew
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.outputs.mavlink.frames import Mounting
from ipt.rosmsg import DIAGNOSTICS, ODOMETRY, POSE, TF, Message, time_msg

F64 = npt.NDArray[np.float64]

#: Body FRD (the MAVLink mounting's frame) → body FLU (ROS ``base_link``).
R_FLU_FRD: F64 = np.diag([1.0, -1.0, -1.0])

DIAG_OK, DIAG_WARN, DIAG_ERROR = 0, 1, 2


class StampClock:
    """Capture times → ROS time stamps (nanoseconds since the epoch).

    The first frame's stamp is the wall-clock time of its grab (``grabbed_s`` on the monotonic clock,
    carried back from now); later frames keep their capture-time spacing. For a camera, whose capture
    times are the monotonic clock, every stamp is then that frame's grab on the wall clock; a recording
    or the simulator plays as if it were being flown now. :attr:`offset_ns` (stamp minus capture time)
    is what a reader subtracts to get the source's own time back. Clocks are injected."""

    def __init__(
        self, wall_ns: Callable[[], int] = time.time_ns, monotonic_s: Callable[[], float] = time.monotonic
    ) -> None:
        self._wall_ns, self._monotonic_s = wall_ns, monotonic_s
        self.offset_ns: int | None = None

    def stamp_ns(self, capture_time_us: int, grabbed_s: float) -> int:
        """The stamp of a frame captured at ``capture_time_us`` and grabbed at ``grabbed_s``."""
        if self.offset_ns is None:
            grab_wall_ns = self._wall_ns() - round((self._monotonic_s() - grabbed_s) * 1e9)
            self.offset_ns = grab_wall_ns - capture_time_us * 1000
        return capture_time_us * 1000 + self.offset_ns


@dataclass(frozen=True)
class RosNames:
    """Topic and frame names of one vehicle."""

    frame_id: str = "arena"
    base_frame_id: str = "base_link"
    camera_frame_id: str = "camera"
    namespace: str | None = None
    tf_topic: str = "/tf"
    """Shared by every vehicle (tf frames are global; the body frames carry the namespace)."""

    def topic(self, leaf: str) -> str:
        """``/ipt/<leaf>``, or ``/ipt/<namespace>/<leaf>``."""
        return f"/ipt/{self.namespace}/{leaf}" if self.namespace else f"/ipt/{leaf}"

    def child(self, frame: str) -> str:
        """A body frame's name: ``frame`` or ``<namespace>/frame``."""
        return f"{self.namespace}/{frame}" if self.namespace else frame

    @property
    def pose_topic(self) -> str:
        return self.topic("pose")

    @property
    def odom_topic(self) -> str:
        return self.topic("odom")

    @property
    def diagnostics_topic(self) -> str:
        return self.topic("diagnostics")



@dataclass(frozen=True)
class Outgoing:
    """One message to publish or record."""

    topic: str
    type_name: str
    """``pkg/msg/Type``."""
    message: Message
    stamp_ns: int
    """The header stamp (also the recording's publish time)."""


def _point(v: F64) -> Message:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _quat(r: F64) -> Message:
    w, x, y, z = (float(c) for c in quat_wxyz_from_matrix(r))
    return {"x": x, "y": y, "z": z, "w": w}


def _cov36(cov: F64) -> list[float]:
    """A 6x6 covariance row-major, or all zeros ("unknown") if any entry is not finite."""
    if not np.all(np.isfinite(cov)):
        return [0.0] * 36
    return [float(c) for c in np.asarray(cov, np.float64).reshape(36)]


def camera_covariance(pose: PoseEstimate) -> F64:
    """6x6 covariance of (x, y, z, rotation about arena X, Y, Z) of the camera."""
    cov = np.zeros((6, 6))
    cov[:3, :3] = pose.position_cov_m2
    cov[3:, 3:] = pose.attitude_cov_rad2
    return cov


def body_pose(pose: PoseEstimate, mounting: Mounting) -> tuple[F64, F64, F64]:
    """``base_link`` in the arena: position (m), ``R_arena_flu`` and the 6x6 covariance of (x, y, z, rotation
    about arena X, Y, Z). The body origin is ``c - R t`` (t the camera's offset on the body), so a small
    rotation θ moves it by ``(R t) × θ``: the attitude's uncertainty adds to the position's."""
    r_arena_frd = pose.r_arena_cam @ mounting.r_frd_cam.T
    lever_arena = r_arena_frd @ mounting.camera_position_frd_m
    position = pose.position_m - lever_arena
    s = skew(lever_arena)
    cov_th = np.asarray(pose.attitude_cov_rad2, np.float64)
    cov = np.zeros((6, 6))
    cov[:3, :3] = pose.position_cov_m2 + s @ cov_th @ s.T
    cov[:3, 3:] = s @ cov_th
    cov[3:, :3] = cov[:3, 3:].T
    cov[3:, 3:] = cov_th
    return position, r_arena_frd @ R_FLU_FRD.T, cov


def body_twist(twist: Twist, pose: PoseEstimate, mounting: Mounting) -> tuple[F64, F64, F64, F64]:
    """The body origin's velocity and the angular velocity, both in ``base_link`` (FLU) axes, with their
    covariances."""
    r_arena_frd = pose.r_arena_cam @ mounting.r_frd_cam.T
    r_arena_flu = r_arena_frd @ R_FLU_FRD.T
    v_arena, cov_v_arena = twist.velocity_of_point(-(r_arena_frd @ mounting.camera_position_frd_m))
    r = r_arena_flu.T
    return (
        r @ v_arena,
        r @ cov_v_arena @ r.T,
        r @ twist.angular_velocity_radps,
        r @ twist.angular_velocity_cov @ r.T,
    )


def _header(stamp_ns: int, frame_id: str) -> Message:
    return {"stamp": time_msg(stamp_ns), "frame_id": frame_id}


def pose_message(pose: PoseEstimate, stamp_ns: int, frame_id: str) -> Message:
    """``geometry_msgs/msg/PoseWithCovarianceStamped`` of the camera."""
    return {
        "header": _header(stamp_ns, frame_id),
        "pose": {
            "pose": {"position": _point(pose.position_m), "orientation": _quat(pose.r_arena_cam)},
            "covariance": _cov36(camera_covariance(pose)),
        },
    }


def odometry_message(
    pose: PoseEstimate, twist: Twist | None, mounting: Mounting, stamp_ns: int, names: RosNames
) -> Message:
    """``nav_msgs/msg/Odometry`` of ``base_link``, the twist in ``base_link`` axes."""
    position, r_arena_flu, cov = body_pose(pose, mounting)
    zero = {"x": 0.0, "y": 0.0, "z": 0.0}
    twist_msg: Message = {"twist": {"linear": zero, "angular": zero}, "covariance": [-1.0] + [0.0] * 35}
    if twist is not None:
        v, cov_v, w, cov_w = body_twist(twist, pose, mounting)
        tcov = np.zeros((6, 6))
        tcov[:3, :3], tcov[3:, 3:] = cov_v, cov_w
        if np.all(np.isfinite(v)) and np.all(np.isfinite(w)):
            twist_msg = {"twist": {"linear": _point(v), "angular": _point(w)}, "covariance": _cov36(tcov)}
    return {
        "header": _header(stamp_ns, names.frame_id),
        "child_frame_id": names.child(names.base_frame_id),
        "pose": {"pose": {"position": _point(position), "orientation": _quat(r_arena_flu)}, "covariance": _cov36(cov)},
        "twist": twist_msg,
    }


def _transform(stamp_ns: int, parent: str, child: str, position: F64, r: F64) -> Message:
    return {
        "header": _header(stamp_ns, parent),
        "child_frame_id": child,
        "transform": {"translation": _point(position), "rotation": _quat(r)},
    }


def tf_message(pose: PoseEstimate, mounting: Mounting, stamp_ns: int, names: RosNames) -> Message:
    """``tf2_msgs/msg/TFMessage``: arena → camera and arena → base_link."""
    position, r_arena_flu, _ = body_pose(pose, mounting)
    return {
        "transforms": [
            _transform(stamp_ns, names.frame_id, names.child(names.camera_frame_id), pose.position_m, pose.r_arena_cam),
            _transform(stamp_ns, names.frame_id, names.child(names.base_frame_id), position, r_arena_flu),
        ]
    }


def diagnostics_message(
    stamp_ns: int,
    names: RosNames,
    hardware_id: str,
    frame_index: int,
    capture_time_us: int,
    reason: str,
    detections: int,
    pose: PoseEstimate | None,
    stage_seconds: Mapping[str, float],
) -> Message:
    """``diagnostic_msgs/msg/DiagnosticArray`` with one status for one frame: OK with a pose, WARN without
    one, ERROR when processing failed. Values (strings, as the message has them): frame index, capture
    time, tags detected, the pose's tag ids and reprojection RMS, and each stage's time in ms."""
    level = DIAG_OK if pose is not None else (DIAG_ERROR if reason in ("error", "detector_failed") else DIAG_WARN)
    values = [
        ("frame", str(frame_index)),
        ("capture_time_us", str(capture_time_us)),
        ("detections", str(detections)),
    ]
    if pose is not None:
        values.append(("tag_ids", " ".join(str(i) for i in pose.tag_ids)))
        values.append(("reprojection_rms_px", f"{pose.reprojection_rms_px:.4f}"))
    values.extend((f"{stage}_ms", f"{1e3 * seconds:.3f}") for stage, seconds in stage_seconds.items())
    return {
        "header": _header(stamp_ns, ""),
        "status": [
            {
                "level": level,
                "name": f"ipt: {names.namespace} pipeline" if names.namespace else "ipt: pipeline",
                "message": reason,
                "hardware_id": hardware_id,
                "values": [{"key": k, "value": v} for k, v in values],
            }
        ],
    }


class RosMessageMaker:
    """Every frame's ROS messages, with the velocity fitted over the poses sent (see the module doc)."""

    def __init__(
        self,
        names: RosNames,
        mounting: Mounting,
        clock: StampClock,
        hardware_id: str = "ipt",
        velocity: VelocityFit | None = None,
    ) -> None:
        self.names, self.mounting, self.clock, self.hardware_id = names, mounting, clock, hardware_id
        self.velocity = velocity if velocity is not None else VelocityFit()

    def frame(
        self,
        frame_index: int,
        capture_time_us: int,
        grabbed_s: float,
        reason: str,
        detections: int,
        pose: PoseEstimate | None,
        reset: bool = False,
        stage_seconds: Mapping[str, float] | None = None,
    ) -> list[Outgoing]:
        """The messages of one frame: pose, odometry and transforms when it has a pose, and its diagnostics."""
        names = self.names
        stamp = self.clock.stamp_ns(capture_time_us, grabbed_s)
        out: list[Outgoing] = []
        if pose is not None and np.all(np.isfinite(pose.position_m)) and np.all(np.isfinite(pose.r_arena_cam)):
            if reset:
                self.velocity.clear()
            self.velocity.add(
                capture_time_us, pose.position_m, pose.r_arena_cam, pose.position_cov_m2, pose.attitude_cov_rad2
            )
            twist = self.velocity.twist()
            out.append(Outgoing(names.pose_topic, POSE, pose_message(pose, stamp, names.frame_id), stamp))
            out.append(
                Outgoing(names.odom_topic, ODOMETRY, odometry_message(pose, twist, self.mounting, stamp, names), stamp)
            )
            out.append(Outgoing(names.tf_topic, TF, tf_message(pose, self.mounting, stamp, names), stamp))
        else:
            pose = None
        diag = diagnostics_message(
            stamp, names, self.hardware_id, frame_index, capture_time_us, reason, detections, pose, stage_seconds or {}
        )
        out.append(Outgoing(names.diagnostics_topic, DIAGNOSTICS, diag, stamp))
        return out


__all__ = [
    "R_FLU_FRD",
    "Outgoing",
    "RosMessageMaker",
    "RosNames",
    "StampClock",
    "body_pose",
    "body_twist",
    "camera_covariance",
    "diagnostics_message",
    "odometry_message",
    "pose_message",
    "tf_message",
]
