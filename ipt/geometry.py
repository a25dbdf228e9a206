"""Rotations, quaternions and poses, with the frames in the names.

Conventions (see README "Frames"):
- arena: ENU metres, origin at the tag-map centre, z up;
- camera: OpenCV optical (x right, y down, z forward);
- body: FLU (x forward, y left, z up);
- ``r_a_b`` rotates vectors from frame b into frame a; quaternions are ``quat_wxyz`` (Hamilton, w first).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

#: The default camera mounting: looking straight down, the top of the image towards the body's nose.
#: Columns are the camera axes in body FLU: x_cam = right = -y_body, y_cam = backwards = -x_body,
#: z_cam = down = -z_body.
R_BODY_CAM_DOWNWARD: F64 = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def rot_x(angle_rad: float) -> F64:
    """Rotation about x by ``angle_rad`` (right hand)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> F64:
    """Rotation about y by ``angle_rad`` (right hand)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> F64:
    """Rotation about z by ``angle_rad`` (right hand)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def matrix_from_ypr(yaw_rad: float, pitch_rad: float, roll_rad: float) -> F64:
    """``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``: the intrinsic Z-Y'-X'' (yaw, pitch, roll) convention."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def ypr_from_matrix(r: F64) -> tuple[float, float, float]:
    """Inverse of :func:`matrix_from_ypr`: (yaw, pitch, roll) in radians, pitch in [-pi/2, pi/2]."""
    pitch = float(np.arcsin(np.clip(-r[2, 0], -1.0, 1.0)))
    yaw = float(np.arctan2(r[1, 0], r[0, 0]))
    roll = float(np.arctan2(r[2, 1], r[2, 2]))
    return yaw, pitch, roll


def quat_wxyz_from_matrix(r: F64) -> F64:
    """Unit quaternion (w, x, y, z) with w >= 0 for the rotation matrix ``r``."""
    m = np.asarray(r, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = np.array([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = np.array([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = np.array([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    q /= np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return q


def matrix_from_quat_wxyz(q: F64) -> F64:
    """Rotation matrix of the quaternion (w, x, y, z); the quaternion need not be normalised."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def slerp_quat_wxyz(q0: F64, q1: F64, fraction: float) -> F64:
    """Spherical linear interpolation from ``q0`` (fraction 0) to ``q1`` (fraction 1)."""
    a = np.asarray(q0, dtype=np.float64) / np.linalg.norm(q0)
    b = np.asarray(q1, dtype=np.float64) / np.linalg.norm(q1)
    dot = float(np.dot(a, b))
    if dot < 0.0:
        b, dot = -b, -dot
    if dot > 0.9995:
        q = a + fraction * (b - a)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    q_out: F64 = (np.sin((1 - fraction) * theta) * a + np.sin(fraction * theta) * b) / np.sin(theta)
    return q_out


def rotation_angle_rad(r: F64) -> float:
    """Angle of the rotation ``r`` in radians, in [0, pi]."""
    return float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))


def wrap_angle_rad(a: F64 | float) -> F64:
    """Wrap angles to (-pi, pi]."""
    wrapped: F64 = np.asarray(-((-np.asarray(a, dtype=np.float64) + np.pi) % (2 * np.pi) - np.pi), dtype=np.float64)
    return wrapped
