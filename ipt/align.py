"""Aligning a motion-capture trajectory with IPT's, in time and in space, as the paper did with OptiTrack.

A lab's motion-capture system (OptiTrack, Vicon, ...) records the drone's rigid body in its own world
frame, on its own clock, at its own point on the drone. Before ``ipt eval`` can compare, three unknowns
are estimated from the two trajectories themselves (pure numpy, :func:`align`):

1. **the time offset** (``truth time = estimate time + offset_s``): the speed profiles of both, resampled
   on a common grid and lightly smoothed, are cross-correlated over every lag with enough overlap (speed
   does not depend on either world frame, so this works before any spatial alignment); the best lag is
   then refined to :data:`REFINE_STEP_S` by the position residual of step 2;
2. **the world transform** (SE(3), no scale: both measure metres): a least-squares rotation and
   translation of the mocap positions onto IPT's (Kabsch's SVD solution), once with every pair and again
   without pairs more than three robust standard deviations off;
3. **the body rotation** between the mocap rigid body's axes and the camera's: the rotation mean of
   ``(R_align R_mocap)ᵀ R_ipt`` over all pairs (so attitudes can be compared).

The position of the mocap body's origin on the drone is not estimated: place the rigid body's origin at
the camera (most mocap software lets you move it), or expect a constant offset in the position errors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.geometry import matrix_from_quat_wxyz, quat_wxyz_from_matrix
from ipt.tum import Trajectory

F64 = npt.NDArray[np.float64]

GRID_S = 0.005
"""Sample spacing of the speed profiles."""
SMOOTH_S = 0.05
"""Positions are averaged over this long before differencing (the estimates' noise would dominate the
speed from one frame to the next)."""
MIN_OVERLAP = 0.5
"""A lag is considered only if the profiles overlap for at least this share of the shorter one."""
REFINE_STEP_S = 0.0005
"""Resolution of the refined time offset."""
REFINE_HALF_WIDTH_S = 0.02
"""The refinement searches this far either side of the cross-correlation's best lag."""
MIN_PAIRS = 10


class AlignError(IptError):
    """The two trajectories cannot be aligned (too short, no common motion, no overlap)."""


@dataclass(frozen=True)
class Alignment:
    """How a motion-capture trajectory maps onto IPT's."""

    offset_s: float
    """truth time = estimate time + ``offset_s``."""
    r_arena_mocap: F64
    """3x3 rotation of the mocap world frame into the arena frame."""
    t_arena_mocap_m: F64
    """(3,) the mocap origin in the arena frame."""
    r_mocap_body_cam: F64
    """3x3 rotation from the camera's axes to the mocap rigid body's."""
    rms_m: float
    """Root mean square position difference after alignment, over the pairs used."""
    pairs: int
    """Pairs (estimate, interpolated truth) the spatial fit used."""
    correlation: float
    """Peak normalised cross-correlation of the speed profiles (1: identical shapes)."""

    def apply(self, truth: Trajectory) -> Trajectory:
        """``truth`` in the arena frame, on the estimates' clock, with the camera's attitude."""
        positions = truth.positions_m @ self.r_arena_mocap.T + self.t_arena_mocap_m
        quats = np.array(
            [
                quat_wxyz_from_matrix(self.r_arena_mocap @ matrix_from_quat_wxyz(q) @ self.r_mocap_body_cam)
                for q in truth.quats_wxyz
            ]
        ).reshape(-1, 4)
        return Trajectory(truth.times_s - self.offset_s, positions, quats)


def _uniform(traj: Trajectory, dt_s: float) -> tuple[float, F64]:
    """(start time, positions on a grid of ``dt_s``), linearly interpolated."""
    t = traj.times_s
    grid = np.arange(t[0], t[-1] + 0.5 * dt_s, dt_s)
    return float(t[0]), np.stack([np.interp(grid, t, traj.positions_m[:, k]) for k in range(3)], axis=1)


def speed_profile(traj: Trajectory, dt_s: float = GRID_S, smooth_s: float = SMOOTH_S) -> tuple[float, F64]:
    """(start time, speed in m/s on a grid of ``dt_s``) after a moving average over ``smooth_s``."""
    t0, pos = _uniform(traj, dt_s)
    width = max(1, round(smooth_s / dt_s))
    if len(pos) <= width + 1:
        raise AlignError(f"a trajectory of {traj.times_s[-1] - traj.times_s[0]:.3f} s is too short to align")
    kernel = np.ones(width) / width
    smooth = np.stack([np.convolve(pos[:, k], kernel, mode="valid") for k in range(3)], axis=1)
    speed = np.linalg.norm(np.diff(smooth, axis=0), axis=1) / dt_s
    # the moving average and the difference shift the profile by half a window and half a sample
    return t0 + 0.5 * (width - 1) * dt_s + 0.5 * dt_s, np.asarray(speed, np.float64)


def time_offset_by_speed(
    truth: Trajectory, est: Trajectory, dt_s: float = GRID_S, smooth_s: float = SMOOTH_S
) -> tuple[float, float]:
    """(offset_s, peak correlation): the lag that best matches the two speed profiles (truth time = estimate
    time + offset_s), to one grid step."""
    t_truth, s_truth = speed_profile(truth, dt_s, smooth_s)
    t_est, s_est = speed_profile(est, dt_s, smooth_s)
    a = (s_truth - s_truth.mean()) / max(float(s_truth.std()), 1e-12)
    b = (s_est - s_est.mean()) / max(float(s_est.std()), 1e-12)
    if s_truth.std() < 1e-6 or s_est.std() < 1e-6:
        raise AlignError("one trajectory does not move (constant speed): there is nothing to align in time")
    corr = np.correlate(a, b, mode="full")
    overlap = np.correlate(np.ones_like(a), np.ones_like(b), mode="full")
    need = MIN_OVERLAP * min(len(a), len(b))
    score = np.where(overlap >= need, corr / np.maximum(overlap, 1.0), -np.inf)
    k = int(np.argmax(score))
    if not np.isfinite(score[k]):
        raise AlignError("the trajectories never overlap enough to compare their motion")
    lag = k - (len(b) - 1)  # a[n + lag] matches b[n]
    return t_truth - t_est + lag * dt_s, float(score[k])


def fit_se3(source_m: F64, target_m: F64) -> tuple[F64, F64]:
    """(R, t) minimising ``Σ |target - (R source + t)|²`` (Kabsch; a proper rotation, no scale)."""
    src_c, dst_c = source_m.mean(axis=0), target_m.mean(axis=0)
    h = (source_m - src_c).T @ (target_m - dst_c)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return np.asarray(r, np.float64), np.asarray(dst_c - r @ src_c, np.float64)


def _pairs(truth: Trajectory, est: Trajectory, offset_s: float) -> tuple[F64, F64, F64, F64]:
    """(truth positions, estimate positions, truth quats, estimate quats) at the estimates' times that fall
    inside the truth's span once shifted by ``offset_s``; positions linearly interpolated, the truth's
    attitude taken from its nearest sample."""
    t = est.times_s + offset_s
    inside = (t >= truth.times_s[0]) & (t <= truth.times_s[-1])
    t = t[inside]
    truth_pos = np.stack([np.interp(t, truth.times_s, truth.positions_m[:, k]) for k in range(3)], axis=1)
    nearest = np.clip(np.searchsorted(truth.times_s, t), 0, len(truth) - 1)
    return truth_pos, est.positions_m[inside], truth.quats_wxyz[nearest], est.quats_wxyz[inside]


def _robust_fit(truth_pos: F64, est_pos: F64) -> tuple[F64, F64, float, int]:
    """SE(3) fit, then again without pairs beyond 3 robust standard deviations: (R, t, rms, pairs kept)."""
    r, t = fit_se3(truth_pos, est_pos)
    residual = np.linalg.norm(est_pos - (truth_pos @ r.T + t), axis=1)
    keep = residual <= max(3.0 * 1.4826 * float(np.median(residual)), 1e-6)
    if keep.sum() >= MIN_PAIRS and not keep.all():
        r, t = fit_se3(truth_pos[keep], est_pos[keep])
        residual = np.linalg.norm(est_pos - (truth_pos @ r.T + t), axis=1)
    used = residual[keep]
    return r, t, float(np.sqrt(np.mean(used**2))), int(keep.sum())


def _mean_rotation(rotations: F64) -> F64:
    """The rotation nearest (chordally) to the mean of a stack of rotation matrices."""
    u, _, vt = np.linalg.svd(rotations.mean(axis=0))
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return np.asarray(u @ np.diag([1.0, 1.0, d]) @ vt, np.float64)


def align(truth: Trajectory, est: Trajectory, offset_s: float | None = None) -> Alignment:
    """Estimate the time offset (unless given), the world transform and the body rotation (module doc)."""
    correlation = float("nan")
    if offset_s is None:
        coarse, correlation = time_offset_by_speed(truth, est)
        candidates = coarse + np.arange(-REFINE_HALF_WIDTH_S, REFINE_HALF_WIDTH_S + 1e-12, REFINE_STEP_S)
    else:
        candidates = np.array([offset_s])
    best: tuple[float, float] | None = None
    for c in candidates:
        truth_pos, est_pos, _, _ = _pairs(truth, est, float(c))
        if len(est_pos) < MIN_PAIRS:
            continue
        _, _, rms, _ = _robust_fit(truth_pos, est_pos)
        if best is None or rms < best[1]:
            best = (float(c), rms)
    if best is None:
        raise AlignError(f"fewer than {MIN_PAIRS} estimates fall inside the truth's time span after the offset")
    offset = best[0]
    truth_pos, est_pos, truth_q, est_q = _pairs(truth, est, offset)
    r, t, rms, kept = _robust_fit(truth_pos, est_pos)
    relative = np.stack(
        [(r @ matrix_from_quat_wxyz(qt)).T @ matrix_from_quat_wxyz(qe) for qt, qe in zip(truth_q, est_q, strict=True)]
    )
    return Alignment(offset, r, t, _mean_rotation(relative), rms, kept, correlation)


__all__ = ["AlignError", "Alignment", "align", "fit_se3", "speed_profile", "time_offset_by_speed"]
