"""Pose from tag corners: OpenCV solvePnP (IPPE) over all corners, then the paper's inversion (4).

IPPE's solution is refined by Levenberg-Marquardt on the reprojection error unless ``refine_lm`` is off
(the paper uses IPPE alone); a tag that fits far worse than the rest is dropped first.

Pure. The result is the camera in the arena: the optical centre in arena metres and the rotation that
takes camera (OpenCV optical) vectors into the arena frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

# np.median imports numpy.ma at its first call (for its NaN check): 16-23 ms here, on a daemon's first pose; imported
# with this module, it is paid while the pipeline is made.
import numpy.ma
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.config.models import REFERENCE_WIDTH_PX, PoseConfig
from ipt.geometry import quat_wxyz_from_matrix
from ipt.receiver.core.detection import TagDetection
from ipt.tagmap import TagMap

F64 = npt.NDArray[np.float64]
Pose = tuple[F64, F64]
"""A camera pose: (position_m, r_arena_cam)."""

#: Floor on the corner noise used for the covariance (a perfect fit does not make a perfect pose).
MIN_CORNER_SIGMA_PX = 0.3


def pose_of(rvec: F64, tvec: F64) -> Pose:
    """(position_m, r_arena_cam) of the camera whose OpenCV (rvec, tvec), arena → camera, a PnP fit gives."""
    r_cam_arena, _ = cv2.Rodrigues(rvec)
    r_arena_cam = np.asarray(r_cam_arena, np.float64).T
    return -r_arena_cam @ tvec.reshape(3), r_arena_cam


def rt_of(position_m: F64, r_arena_cam: F64) -> tuple[F64, F64]:
    """OpenCV's (rvec, tvec), arena → camera, of the camera at ``position_m`` turned by ``r_arena_cam``: the
    inverse of what a PnP solution gives the pose from."""
    rvec, _ = cv2.Rodrigues(r_arena_cam.T)
    return np.asarray(rvec, np.float64).reshape(3), -r_arena_cam.T @ position_m


def _covariances(obj: F64, rvec: F64, tvec: F64, camera: CameraInfo, sigma_px: float) -> tuple[F64, F64]:
    """Position and attitude covariances: sigma² (JᵀJ)⁻¹ of the PnP fit, carried to the camera pose."""
    _, jac = cv2.projectPoints(obj, rvec, tvec, camera.camera_matrix, camera.dist_coeffs)
    j = np.asarray(jac, np.float64)[:, :6]
    try:
        cov_rt = np.asarray(sigma_px**2 * np.linalg.inv(j.T @ j), np.float64)
    except np.linalg.LinAlgError:
        nan = np.full((3, 3), np.nan)
        return nan, nan
    return pose_covariances(rvec, tvec, cov_rt)


def pose_covariances(rvec: F64, tvec: F64, cov_rt: F64) -> tuple[F64, F64]:
    """The covariance of (rvec, tvec) (6x6, OpenCV's arena → camera) carried to the camera's position in
    the arena and to a small rotation about the arena axes (each 3x3)."""
    position0, r0 = pose_of(rvec, tvec)
    jp = np.zeros((3, 6))
    ja = np.zeros((3, 6))
    eps = 1e-6
    for i in range(6):
        d = np.zeros(6)
        d[i] = eps
        position1, r1 = pose_of(rvec.reshape(3) + d[:3], tvec.reshape(3) + d[3:])
        jp[:, i] = (position1 - position0) / eps
        # The small rotation about arena axes: r1 r0ᵀ ≈ I + [δ]×. (cv2.Rodrigues returns 0 for angles this
        # small, which once made every attitude covariance zero.)
        m = r1 @ r0.T
        ja[:, i] = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) / (2.0 * eps)
    return jp @ cov_rt @ jp.T, ja @ cov_rt @ ja.T


@dataclass(frozen=True)
class PoseEstimate:
    """The camera's pose in the arena from one frame."""

    position_m: F64
    """Optical centre in arena ENU metres."""
    r_arena_cam: F64
    """3x3 rotation camera→arena."""
    tag_ids: tuple[int, ...]
    reprojection_rms_px: float
    position_cov_m2: F64 = field(default_factory=lambda: np.full((3, 3), np.nan))
    """3x3 covariance of ``position_m`` from the PnP geometry (corner noise = the fit's RMS, at least
    :data:`MIN_CORNER_SIGMA_PX`)."""
    attitude_cov_rad2: F64 = field(default_factory=lambda: np.full((3, 3), np.nan))
    """3x3 covariance of a small rotation about the arena axes applied to ``r_arena_cam``."""

    @property
    def position_std_m(self) -> F64:
        """Per-axis standard deviation of the position."""
        return np.sqrt(np.clip(np.diag(self.position_cov_m2), 0.0, None))

    @property
    def attitude_std_rad(self) -> F64:
        """Per-axis (arena x, y, z) standard deviation of the attitude."""
        return np.sqrt(np.clip(np.diag(self.attitude_cov_rad2), 0.0, None))

    @property
    def quat_wxyz(self) -> F64:
        """``r_arena_cam`` as a unit quaternion (w, x, y, z)."""
        return quat_wxyz_from_matrix(self.r_arena_cam)


def estimate_from(rvec: F64, tvec: F64, cov_rt: F64, tag_ids: tuple[int, ...], rms_px: float) -> PoseEstimate:
    """A :class:`PoseEstimate` from OpenCV's (rvec, tvec) and their covariance."""
    rvec, tvec = np.asarray(rvec, np.float64), np.asarray(tvec, np.float64)
    position_m, r_arena_cam = pose_of(rvec, tvec)
    cov_p, cov_a = pose_covariances(rvec, tvec, cov_rt)
    return PoseEstimate(position_m, r_arena_cam, tag_ids, rms_px, cov_p, cov_a)


def estimate_from_step(rvec: F64, tvec: F64, cov_step: F64, tag_ids: tuple[int, ...], rms_px: float) -> PoseEstimate:
    """A :class:`PoseEstimate` from OpenCV's (rvec, tvec) and the covariance (6x6) of a fit's last step (δ, Δt): a
    small rotation δ applied on the arena → camera side (R ← exp([δ]×)·R) and the change of ``tvec`` (the edge
    fits' parametrisation, :mod:`~ipt.receiver.core.track` and :mod:`~ipt.receiver.core.sparse`)."""
    r, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    rt = np.asarray(r, np.float64).T
    # p = −Rᵀt: dp/dδ = −Rᵀ[t]×, dp/dΔt = −Rᵀ; the arena-axis rotation of Rᵀ is −Rᵀδ.
    j_p = np.hstack([-rt @ _skew(tvec), -rt])
    j_a = np.hstack([-rt, np.zeros((3, 3))])
    return PoseEstimate(-rt @ tvec, rt, tag_ids, rms_px, j_p @ cov_step @ j_p.T, j_a @ cov_step @ j_a.T)


def _skew(v: F64) -> F64:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def correspondences(detections: Sequence[TagDetection], tag_map: TagMap) -> tuple[F64, F64, tuple[int, ...]]:
    """Arena points (N×3) and image points (N×2) of every corner of every detected tag in the map."""
    obj, img, ids = [], [], []
    for d in detections:
        corners_m = tag_map.corners_m(d.tag_id)
        if corners_m is None:
            continue
        obj.append(corners_m)
        img.append(d.corners_px)
        ids.append(d.tag_id)
    if not obj:
        return np.zeros((0, 3)), np.zeros((0, 2)), ()
    return np.concatenate(obj), np.concatenate(img), tuple(ids)


def _fit(obj: F64, img: F64, camera: CameraInfo, refine_lm: bool) -> tuple[F64, F64, F64] | None:
    """IPPE over all points (then LM if asked); returns (rvec, tvec, per-point reprojection error px)."""
    k, dist = camera.camera_matrix, camera.dist_coeffs
    ok, rvec, tvec = cv2.solvePnP(obj, img, k, dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    if refine_lm:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, k, dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, k, dist)
    err = np.linalg.norm(proj.reshape(-1, 2) - img, axis=1)
    return np.asarray(rvec, np.float64), np.asarray(tvec, np.float64), np.asarray(err, np.float64)


def solve_pose(
    detections: Sequence[TagDetection], tag_map: TagMap, camera: CameraInfo, cfg: PoseConfig
) -> PoseEstimate | None:
    """The camera pose from the detected tags, or None if too few tags or the fit is poor.

    A tag that fits far worse than the others (a misread corner) is dropped and the pose solved again,
    one tag at a time.
    """
    obj, img, ids = correspondences(detections, tag_map)
    scale = camera.width_px / REFERENCE_WIDTH_PX
    max_rms = cfg.max_reprojection_rms_px if cfg.max_reprojection_rms_px is not None else 2.5 * scale
    outlier_px = cfg.outlier_tag_px if cfg.outlier_tag_px is not None else 2.0 * scale
    while len(ids) >= cfg.min_tags:
        fit = _fit(obj, img, camera, cfg.refine_lm)
        if fit is None:
            return None
        rvec, tvec, err = fit
        per_tag = np.sqrt(np.mean(err.reshape(-1, 4) ** 2, axis=1))
        worst = int(np.argmax(per_tag))
        if len(ids) > 1 and per_tag[worst] > max(outlier_px, 3.0 * float(np.median(per_tag))):
            keep = np.repeat(np.arange(len(ids)) != worst, 4)
            obj, img = obj[keep], img[keep]
            ids = ids[:worst] + ids[worst + 1 :]
            continue
        rms = float(np.sqrt(np.mean(err**2)))
        if not np.isfinite(rms) or rms > max_rms:
            return None
        position_m, r_arena_cam = pose_of(rvec, tvec)
        cov_p, cov_a = _covariances(obj, rvec, tvec, camera, max(rms, MIN_CORNER_SIGMA_PX))
        return PoseEstimate(position_m, r_arena_cam, ids, rms, cov_p, cov_a)
    return None
