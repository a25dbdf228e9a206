"""Accuracy of estimated poses against ground truth, as in the paper's Table I and Fig. 6.

Both inputs are :class:`~ipt.tum.Trajectory` objects (TUM files) holding the *camera* pose in the
arena: the position of the camera's optical centre (ENU metres) and ``R_arena_cam``, which rotates
OpenCV optical camera vectors (x right, y down, z forward) into the arena frame.

Attitude is compared for the *body* (FLU: x forward, y left, z up). ``r_body_cam`` (by default
:data:`~ipt.geometry.R_BODY_CAM_DOWNWARD`) has the camera axes expressed in the body frame as its
columns, so it rotates camera vectors into the body frame (``v_body = r_body_cam @ v_cam``); hence::

    R_arena_body = R_arena_cam @ R_cam_body = R_arena_cam @ r_body_cam.T

and yaw, pitch and roll are the intrinsic Z-Y'-X'' angles of ``R_arena_body``
(:func:`~ipt.geometry.ypr_from_matrix`).

Statistics follow the paper: for each axis, the error is ``estimate - truth`` (signed); "MAE" is the
mean of its absolute value and "STD" the (population) standard deviation of the signed error. Angle
errors are wrapped to (-180, 180] degrees before either is taken.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ipt.cliutil import Parser, one_line, same_file
from ipt.errors import IptError
from ipt.fileio import atomic_path, output_group, write_text_atomic
from ipt.geometry import (
    R_BODY_CAM_DOWNWARD,
    matrix_from_quat_wxyz,
    rotation_angle_rad,
    slerp_quat_wxyz,
    wrap_angle_rad,
    ypr_from_matrix,
)
from ipt.tum import Trajectory, read_tum

F64 = npt.NDArray[np.float64]

DEFAULT_MAX_DT_S = 1e-3
"""How far (seconds) an estimate may lie outside the truth's time span and still be compared (against
the first or last truth pose). Covers the rounding of time stamps in files, nothing more."""

DEFAULT_OUTLIER_M = 0.10
"""3D position errors above this (metres) count as outliers."""

PAPER_IPT_TABLE_I: dict[str, tuple[float, float]] = {
    "x": (0.0690, 0.0886),
    "y": (0.0535, 0.0674),
    "z": (0.0230, 0.0263),
    "yaw": (0.352, 0.460),
    "pitch": (2.659, 3.657),
    "roll": (3.342, 4.305),
}
"""The paper's Table I, row IPT: (MAE, STD) in metres for x, y, z and in degrees for yaw, pitch, roll."""

PAPER_IPT_YIELD: tuple[int, int] = (625, 1800)
"""The paper's IPT run: poses estimated, camera frames."""


class EvalError(IptError):
    """The truth and the estimates cannot be compared (e.g. they do not overlap in time)."""


MAX_POSITION_M = 1e6
"""The largest position coordinate ``ipt eval`` compares, metres: past it the differences and their squares
overflow (1e308 gave inf in the table and Infinity, not valid JSON, in the report)."""
UNIT_QUAT_TOLERANCE = 1e-6
"""How far from 1 the norm of a read quaternion may be."""


def check_trajectory(traj: Trajectory, source: str | Path) -> None:
    """Refuse, naming ``source``, poses that cannot be compared: positions beyond :data:`MAX_POSITION_M`,
    quaternions that are not rotations (an MCAP recording's are not normalised for us)."""
    big = np.abs(traj.positions_m).max(axis=1)
    if (bad := np.flatnonzero(~(big <= MAX_POSITION_M))).size:
        i = int(bad[0])
        raise EvalError(
            f"{source}: pose {i + 1} (t = {traj.times_s[i]:.6f} s) is {big[i]:g} m from the origin; "
            f"positions beyond {MAX_POSITION_M:g} m cannot be compared"
        )
    with np.errstate(all="ignore"):
        norms = np.sqrt(np.sum(traj.quats_wxyz**2, axis=1))
    if (bad := np.flatnonzero(~(np.abs(norms - 1.0) <= UNIT_QUAT_TOLERANCE))).size:
        i = int(bad[0])
        raise EvalError(f"{source}: pose {i + 1} (t = {traj.times_s[i]:.6f} s) has a quaternion that is not a rotation")


@dataclass(frozen=True)
class Association:
    """Estimates paired with the truth interpolated at their time stamps.

    Attributes:
        times_s: (M,) the time stamps of the estimates kept.
        est_indices: (M,) their indices in the estimated trajectory.
        truth_positions_m: (M, 3) truth positions, linearly interpolated.
        truth_quats_wxyz: (M, 4) truth orientations, spherically interpolated (slerp).
        est_positions_m: (M, 3) the estimated positions.
        est_quats_wxyz: (M, 4) the estimated orientations.
        n_dropped: how many estimates lay outside the truth's time span and were left out.
    """

    times_s: F64
    est_indices: npt.NDArray[np.intp]
    truth_positions_m: F64
    truth_quats_wxyz: F64
    est_positions_m: F64
    est_quats_wxyz: F64
    n_dropped: int

    def __len__(self) -> int:
        return int(self.times_s.shape[0])


def associate(truth: Trajectory, est: Trajectory, max_dt_s: float = DEFAULT_MAX_DT_S) -> Association:
    """Pair every estimate with the truth at the estimate's time.

    The truth is interpolated between the two truth samples around the estimate's time: linearly for
    the position, by slerp for the orientation. Estimates earlier than the first truth sample or later
    than the last by more than ``max_dt_s`` seconds are dropped (and counted in ``n_dropped``); those
    within the tolerance are compared with the first or last truth pose.
    """
    if max_dt_s < 0 or not math.isfinite(max_dt_s):
        raise ValueError(f"associate: max_dt_s must be finite and >= 0, got {max_dt_s}")
    if len(truth) == 0:
        raise EvalError("the truth trajectory is empty")
    tt = truth.times_s
    te = est.times_s
    keep = (te >= tt[0] - max_dt_s) & (te <= tt[-1] + max_dt_s)
    idx_kept = np.flatnonzero(keep)
    t_kept = te[idx_kept]
    tc = np.clip(t_kept, tt[0], tt[-1])
    if len(tt) == 1:
        lo = np.zeros(len(tc), dtype=np.intp)
        hi = lo
        frac = np.zeros(len(tc))
    else:
        lo = np.clip(np.searchsorted(tt, tc, side="right") - 1, 0, len(tt) - 2).astype(np.intp)
        hi = lo + 1
        frac = np.clip((tc - tt[lo]) / (tt[hi] - tt[lo]), 0.0, 1.0)
    p0, p1 = truth.positions_m[lo], truth.positions_m[hi]
    truth_pos = p0 + frac[:, None] * (p1 - p0)
    truth_q = np.empty((len(tc), 4))
    for k in range(len(tc)):
        truth_q[k] = slerp_quat_wxyz(truth.quats_wxyz[lo[k]], truth.quats_wxyz[hi[k]], float(frac[k]))
    return Association(
        times_s=t_kept.copy(),
        est_indices=idx_kept.astype(np.intp),
        truth_positions_m=truth_pos,
        truth_quats_wxyz=truth_q,
        est_positions_m=est.positions_m[idx_kept].copy(),
        est_quats_wxyz=est.quats_wxyz[idx_kept].copy(),
        n_dropped=int(len(te) - len(idx_kept)),
    )


def body_matrices(quats_wxyz: F64, r_body_cam: F64 = R_BODY_CAM_DOWNWARD) -> npt.NDArray[np.float64]:
    """(N, 3, 3) ``R_arena_body = R_arena_cam @ r_body_cam.T`` for (N, 4) camera quaternions."""
    r_cam_body = np.asarray(r_body_cam, dtype=np.float64).T
    out = np.empty((len(quats_wxyz), 3, 3))
    for k, q in enumerate(quats_wxyz):
        out[k] = matrix_from_quat_wxyz(q) @ r_cam_body
    return out


def body_ypr_rad(quats_wxyz: F64, r_body_cam: F64 = R_BODY_CAM_DOWNWARD) -> F64:
    """(N, 3) body yaw, pitch, roll (radians, Z-Y'-X'') for (N, 4) camera quaternions."""
    mats = body_matrices(quats_wxyz, r_body_cam)
    return np.array([ypr_from_matrix(m) for m in mats], dtype=np.float64).reshape(-1, 3)


def _angle_between_rad(a: F64, b: F64) -> F64:
    """Row-wise angle between unit vectors (atan2 form: accurate for small angles too)."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.asarray(np.arctan2(cross, dot), dtype=np.float64)


_AXES_POS = ("x", "y", "z")
_AXES_ATT = ("yaw", "pitch", "roll")


@dataclass(frozen=True)
class ErrorReport:
    """Accuracy of one run. Errors are ``estimate - truth``; see the module docstring for the frames.

    Scalar attributes carry their unit in the name (``_m`` metres, ``_deg`` degrees). The per-estimate
    arrays at the end (aligned with ``times_s``) are kept for plotting and left out of ``to_dict()``
    unless asked for.
    """

    n_estimates: int
    """Estimates compared (those inside the truth's time span)."""
    n_truth: int
    """Truth samples, one per camera frame."""
    n_dropped: int
    """Estimates outside the truth's time span, not compared."""
    yield_fraction: float
    """``n_estimates / n_truth``: the share of camera frames that gave a pose."""
    mae_x_m: float
    std_x_m: float
    mae_y_m: float
    std_y_m: float
    mae_z_m: float
    std_z_m: float
    mae_yaw_deg: float
    std_yaw_deg: float
    mae_pitch_deg: float
    std_pitch_deg: float
    mae_roll_deg: float
    std_roll_deg: float
    mae_tilt_deg: float
    """Mean angle between the true and the estimated body z axes (tilt error, always >= 0)."""
    std_tilt_deg: float
    mae_rotation_deg: float
    """Mean angle of the rotation between the true and the estimated body attitudes."""
    rmse_pos_m: float
    """Root mean square of the 3D position error (the usual absolute trajectory error)."""
    max_pos_err_m: float
    """Largest 3D position error."""
    n_outliers: int
    """Estimates whose 3D position error exceeds ``outlier_threshold_m``."""
    outlier_threshold_m: float
    times_s: F64 = field(repr=False, compare=False)
    """(M,) the estimates' time stamps."""
    pos_err_m: F64 = field(repr=False, compare=False)
    """(M, 3) signed position error x, y, z."""
    ypr_err_deg: F64 = field(repr=False, compare=False)
    """(M, 3) wrapped yaw, pitch, roll error."""
    tilt_err_deg: F64 = field(repr=False, compare=False)
    """(M,) tilt error."""
    pos_err_3d_m: F64 = field(repr=False, compare=False)
    """(M,) 3D position error."""
    r_body_cam: F64 = field(repr=False, compare=False, default_factory=lambda: R_BODY_CAM_DOWNWARD.copy())
    """The camera mounting used to turn camera attitudes into body attitudes."""

    def to_dict(self, include_series: bool = False) -> dict[str, Any]:
        """JSON-serialisable summary; with ``include_series`` also the per-estimate errors."""
        d: dict[str, Any] = {
            "n_estimates": self.n_estimates,
            "n_truth": self.n_truth,
            "n_dropped": self.n_dropped,
            "yield": self.yield_fraction,
        }
        for name in (*_AXES_POS, *_AXES_ATT, "tilt"):
            unit = "m" if name in _AXES_POS else "deg"
            d[f"mae_{name}_{unit}"] = float(getattr(self, f"mae_{name}_{unit}"))
            d[f"std_{name}_{unit}"] = float(getattr(self, f"std_{name}_{unit}"))
        d["mae_rotation_deg"] = self.mae_rotation_deg
        d["rmse_pos_m"] = self.rmse_pos_m
        d["max_pos_err_m"] = self.max_pos_err_m
        d["n_outliers"] = self.n_outliers
        d["outlier_threshold_m"] = self.outlier_threshold_m
        if include_series:
            d["series"] = {
                "times_s": self.times_s.tolist(),
                "pos_err_m": self.pos_err_m.tolist(),
                "ypr_err_deg": self.ypr_err_deg.tolist(),
                "tilt_err_deg": self.tilt_err_deg.tolist(),
            }
        return d


def evaluate(
    truth: Trajectory,
    est: Trajectory,
    r_body_cam: F64 = R_BODY_CAM_DOWNWARD,
    *,
    max_dt_s: float = DEFAULT_MAX_DT_S,
    outlier_m: float = DEFAULT_OUTLIER_M,
) -> ErrorReport:
    """Compare ``est`` with ``truth`` (both camera poses in the arena) and summarise the errors.

    Raises :class:`EvalError` if no estimate lies within the truth's time span.
    """
    a = associate(truth, est, max_dt_s=max_dt_s)
    if len(a) == 0:
        if len(est) == 0:
            raise EvalError("no estimated poses to evaluate")
        raise EvalError(
            f"no overlap in time: the truth spans {truth.times_s[0]:.6f}..{truth.times_s[-1]:.6f} s, "
            f"the estimates {est.times_s[0]:.6f}..{est.times_s[-1]:.6f} s"
        )
    r_body_cam = np.asarray(r_body_cam, dtype=np.float64)
    pos_err = a.est_positions_m - a.truth_positions_m
    pos_err_3d = np.linalg.norm(pos_err, axis=1)

    rb_truth = body_matrices(a.truth_quats_wxyz, r_body_cam)
    rb_est = body_matrices(a.est_quats_wxyz, r_body_cam)
    ypr_truth = np.array([ypr_from_matrix(m) for m in rb_truth]).reshape(-1, 3)
    ypr_est = np.array([ypr_from_matrix(m) for m in rb_est]).reshape(-1, 3)
    ypr_err_deg = np.degrees(wrap_angle_rad(ypr_est - ypr_truth))
    tilt_deg = np.degrees(_angle_between_rad(rb_truth[:, :, 2], rb_est[:, :, 2]))
    rot_deg = np.degrees([rotation_angle_rad(t.T @ e) for t, e in zip(rb_truth, rb_est, strict=True)])

    def mae(v: F64) -> float:
        return float(np.mean(np.abs(v)))

    def std(v: F64) -> float:
        return float(np.std(v))

    return ErrorReport(
        n_estimates=len(a),
        n_truth=len(truth),
        n_dropped=a.n_dropped,
        yield_fraction=len(a) / len(truth),
        mae_x_m=mae(pos_err[:, 0]),
        std_x_m=std(pos_err[:, 0]),
        mae_y_m=mae(pos_err[:, 1]),
        std_y_m=std(pos_err[:, 1]),
        mae_z_m=mae(pos_err[:, 2]),
        std_z_m=std(pos_err[:, 2]),
        mae_yaw_deg=mae(ypr_err_deg[:, 0]),
        std_yaw_deg=std(ypr_err_deg[:, 0]),
        mae_pitch_deg=mae(ypr_err_deg[:, 1]),
        std_pitch_deg=std(ypr_err_deg[:, 1]),
        mae_roll_deg=mae(ypr_err_deg[:, 2]),
        std_roll_deg=std(ypr_err_deg[:, 2]),
        mae_tilt_deg=mae(tilt_deg),
        std_tilt_deg=std(tilt_deg),
        mae_rotation_deg=mae(rot_deg),
        rmse_pos_m=float(np.sqrt(np.mean(pos_err_3d**2))),
        max_pos_err_m=float(np.max(pos_err_3d)),
        n_outliers=int(np.count_nonzero(pos_err_3d > outlier_m)),
        outlier_threshold_m=float(outlier_m),
        times_s=a.times_s,
        pos_err_m=pos_err,
        ypr_err_deg=ypr_err_deg,
        tilt_err_deg=tilt_deg,
        pos_err_3d_m=pos_err_3d,
        r_body_cam=r_body_cam.copy(),
    )


def format_table(report: ErrorReport, *, paper: bool = True, label: str = "this run") -> str:
    """The paper's Table I layout ("mae / std" per column), optionally with the paper's IPT row."""
    width_label = max(len(label), len("paper IPT")) + 2
    col = 20

    def cell(mae_std: tuple[float, float], decimals: int) -> str:
        return f"{mae_std[0]:.{decimals}f} / {mae_std[1]:.{decimals}f}".ljust(col)

    def block(axes: tuple[str, str, str], unit: str, decimals: int) -> list[str]:
        head = " " * width_label + "".join(f"{a.capitalize()} Error [{unit}]".ljust(col) for a in axes)
        sub = " " * width_label + "".join("mae / std".ljust(col) for _ in axes)
        ours = label.ljust(width_label) + "".join(
            cell((getattr(report, f"mae_{a}_{unit}"), getattr(report, f"std_{a}_{unit}")), decimals)
            for a in axes
        )
        rows = [head.rstrip(), sub.rstrip(), ours.rstrip()]
        if paper:
            rows.append(
                (
                    "paper IPT".ljust(width_label)
                    + "".join(cell(PAPER_IPT_TABLE_I[a], decimals) for a in axes)
                ).rstrip()
            )
        return rows

    lines = [*block(_AXES_POS, "m", 4), "", *block(_AXES_ATT, "deg", 3), ""]
    n, m = report.n_estimates, report.n_truth
    yield_text = f"yield {n}/{m} = {100.0 * report.yield_fraction:.1f} %"
    if paper:
        pn, pm = PAPER_IPT_YIELD
        yield_text += f" (paper IPT {pn}/{pm} = {100.0 * pn / pm:.1f} %)"
    lines.append(yield_text)
    outlier_pct = 100.0 * report.n_outliers / n
    lines.append(
        f"count {n}, max error {report.max_pos_err_m:.4f} m, rmse {report.rmse_pos_m:.4f} m, "
        f"outliers > {100.0 * report.outlier_threshold_m:.0f} cm: {report.n_outliers} ({outlier_pct:.1f} %)"
    )
    lines.append(f"tilt error {report.mae_tilt_deg:.3f} / {report.std_tilt_deg:.3f} deg (mean / std)")
    if report.n_dropped:
        lines.append(f"note: {report.n_dropped} estimates outside the truth's time span were not compared")
    return "\n".join(lines) + "\n"


def plot_report(truth: Trajectory, est: Trajectory, report: ErrorReport, path: str | Path) -> None:
    """Save a figure like the paper's Fig. 6 as PNG (atomically) at ``path``.

    Left column: x, y, z position; right column: body yaw, pitch, roll — truth as a line, estimates as
    dots, against time since the first truth sample. Bottom: horizontal (xy) position error against
    time, with the outlier threshold.
    """
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    t0 = float(truth.times_s[0])
    tt = truth.times_s - t0
    te = est.times_s - t0
    ypr_truth = np.degrees(body_ypr_rad(truth.quats_wxyz, report.r_body_cam))
    ypr_est = np.degrees(body_ypr_rad(est.quats_wxyz, report.r_body_cam))
    # Draw angles continuously: unwrap the truth, and put each estimate within 180 deg of the truth.
    ypr_truth = np.degrees(np.unwrap(np.radians(ypr_truth), axis=0))
    if len(est):
        ref = np.stack([np.interp(te, tt, ypr_truth[:, k]) for k in range(3)], axis=1)
        ypr_est = ref + np.degrees(wrap_angle_rad(np.radians(ypr_est - ref)))

    fig = Figure(figsize=(12.0, 10.0), layout="constrained")
    gs = fig.add_gridspec(4, 2)
    pos_names = ("x [m]", "y [m]", "z [m]")
    att_names = ("yaw [deg]", "pitch [deg]", "roll [deg]")
    for k in range(3):
        ax = fig.add_subplot(gs[k, 0])
        ax.plot(tt, truth.positions_m[:, k], "-", color="tab:blue", linewidth=1.0, label="truth")
        ax.plot(te, est.positions_m[:, k], ".", color="tab:red", markersize=3, label="estimate")
        ax.set_ylabel(pos_names[k])
        ax.grid(True, alpha=0.3)
        if k == 0:
            ax.set_title("position")
            ax.legend(loc="upper right", fontsize="small")
        ax = fig.add_subplot(gs[k, 1])
        ax.plot(tt, ypr_truth[:, k], "-", color="tab:blue", linewidth=1.0, label="truth")
        ax.plot(te, ypr_est[:, k], ".", color="tab:red", markersize=3, label="estimate")
        ax.set_ylabel(att_names[k])
        ax.grid(True, alpha=0.3)
        if k == 0:
            ax.set_title("attitude (body)")
    ax = fig.add_subplot(gs[3, :])
    horiz = np.hypot(report.pos_err_m[:, 0], report.pos_err_m[:, 1])
    ax.plot(report.times_s - t0, horiz, ".", color="tab:red", markersize=3, label="horizontal error")
    ax.axhline(
        report.outlier_threshold_m,
        color="grey",
        linestyle="--",
        linewidth=1.0,
        label=f"{100.0 * report.outlier_threshold_m:.0f} cm (outlier threshold for the 3D error)",
    )
    ax.set_xlabel("time [s]")
    ax.set_ylabel("xy error [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper right", fontsize="small")
    fig.suptitle(
        f"IPT against ground truth: {report.n_estimates} poses / {report.n_truth} frames, "
        f"MAE x {report.mae_x_m:.3f} m, y {report.mae_y_m:.3f} m, z {report.mae_z_m:.3f} m"
    )
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)


_EPILOG = """\
input: TUM trajectory files, one pose per line 't x y z qx qy qz qw' (seconds, metres, unit
quaternion with the scalar last); the pose is the camera's (optical centre and R_arena_cam, OpenCV
camera axes) in the arena frame (ENU). --truth holds one sample per camera frame; --poses holds the
estimates, compared with the truth interpolated at their time stamps. Either may instead be an MCAP
recording (ipt-receiver run --record): its --topic (default /ipt/pose) is read, on the frames' own
capture clock.

motion capture (--align): the truth is a mocap system's TUM file, in its own frame and on its own
clock. The time offset is found by cross-correlating the two speed profiles (then refined to 0.5 ms
by the position fit), the mocap frame is fitted onto the arena by a rotation and translation, and the
rotation between the mocap rigid body and the camera is taken as the mean over all pairs; the
alignment is printed, then the table for the aligned truth. Put the rigid body's origin at the
camera, or its offset shows as a constant position error. Yield counts the truth's samples.

output columns, as in the paper's Table I:
  X/Y/Z Error [m]             position error estimate - truth along the arena axes
  Yaw/Pitch/Roll Error [deg]  body attitude error (Z-Y-X angles of R_arena_body, wrapped)
  mae / std                   mean absolute error / standard deviation of the signed error
  paper IPT                   the paper's own figures, for comparison
  yield                       poses estimated / camera frames (truth samples)
  max error, outliers         largest 3D position error; count of 3D errors above 10 cm

exit status: 0 on success, 2 on bad input (one line on stderr)."""


def _parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="ipt eval",
        description="Accuracy of estimated drone poses against ground truth, as in Table I of the paper.",
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--truth", required=True, metavar="FILE", help="ground-truth TUM file (one pose per frame), or a mocap TUM file"
    )
    p.add_argument("--poses", required=True, metavar="FILE", help="estimated poses: TUM file or MCAP recording")
    p.add_argument(
        "--topic", default="/ipt/pose", help="the pose topic of an MCAP recording (default %(default)s)"
    )
    p.add_argument(
        "--align",
        action="store_true",
        help="the truth is motion capture: find the time offset, the mocap-to-arena transform and the body "
        "rotation first (see below)",
    )
    p.add_argument(
        "--time-offset",
        type=float,
        metavar="S",
        help="with --align: truth time = estimate time + S, instead of finding it by cross-correlation",
    )
    p.add_argument("--plot", metavar="FIG.png", help="also save a figure like the paper's Fig. 6 (PNG)")
    p.add_argument("--json", metavar="OUT.json", help="also write the summary as JSON")
    p.add_argument(
        "--max-dt",
        type=float,
        default=DEFAULT_MAX_DT_S,
        metavar="S",
        help="tolerance in seconds for estimates just outside the truth's time span (default %(default)s)",
    )
    p.add_argument("--no-paper", action="store_true", help="leave out the paper's row in the table")
    return p


def eval_main(argv: list[str] | None = None) -> int:
    """``ipt eval``: print the accuracy table; 0 on success, 2 on bad input."""
    args = _parser().parse_args(argv)
    try:
        if not (math.isfinite(args.max_dt) and args.max_dt >= 0):
            raise EvalError(f"--max-dt must be a finite number >= 0, got {args.max_dt}")
        if args.time_offset is not None and not (args.align and math.isfinite(args.time_offset)):
            raise EvalError("--time-offset needs --align and a finite number of seconds")
        _check_outputs(args.json, args.plot)
        truth = read_trajectory(args.truth, args.topic)
        check_trajectory(truth, args.truth)
        est = read_trajectory(args.poses, args.topic)
        check_trajectory(est, args.poses)
        if args.align:
            from ipt.align import align

            alignment = align(truth, est, args.time_offset)
            truth = alignment.apply(truth)
            sys.stdout.write(format_alignment(alignment))
        report = evaluate(truth, est, max_dt_s=args.max_dt)
        summary = _json_text(report, args.poses)
        sys.stdout.write(format_table(report, paper=not args.no_paper))
        with output_group():  # both files or neither, also when a signal or a failed write stops the run
            if args.json:
                _write_output(args.json, lambda p: write_text_atomic(p, summary))
            if args.plot:
                _write_output(args.plot, lambda p: plot_report(truth, est, report, p))
        for written in (args.json, args.plot):
            if written:
                print(f"wrote {written}")
    except IptError as exc:
        print(f"ipt eval: error: {one_line(str(exc))}", file=sys.stderr)
        return 2
    return 0


def read_trajectory(path: str | Path, topic: str = "/ipt/pose") -> Trajectory:
    """A TUM file, or the poses on ``topic`` of an MCAP recording (told apart by the file's first bytes)."""
    from ipt.rosmsg import is_mcap, read_mcap_trajectory

    if is_mcap(path):
        return read_mcap_trajectory(path, topic)
    return read_tum(path)


def format_alignment(a: Any) -> str:
    """The alignment ``--align`` found (an :class:`ipt.align.Alignment`), as a few lines."""
    ypr = np.degrees(ypr_from_matrix(a.r_arena_mocap))
    body = np.degrees(ypr_from_matrix(a.r_mocap_body_cam))
    x, y, z = a.t_arena_mocap_m
    corr = "" if not math.isfinite(a.correlation) else f" (speed correlation {a.correlation:.3f})"
    return (
        f"alignment: truth time = estimate time + {a.offset_s:.4f} s{corr}\n"
        f"alignment: mocap -> arena: yaw {ypr[0]:.2f}, pitch {ypr[1]:.2f}, roll {ypr[2]:.2f} deg, "
        f"translation {x:.4f} {y:.4f} {z:.4f} m; position rms {1e3 * a.rms_m:.2f} mm over {a.pairs} pairs\n"
        f"alignment: camera -> mocap body: yaw {body[0]:.2f}, pitch {body[1]:.2f}, roll {body[2]:.2f} deg\n\n"
    )


def _check_outputs(json_path: str | None, plot_path: str | None) -> None:
    """--json and --plot must be two files: the figure would replace the summary."""
    if json_path and plot_path and same_file(json_path, plot_path):
        raise EvalError(f"--json and --plot name the same file ({plot_path}): one would replace the other")


def _json_text(report: ErrorReport, poses: str) -> str:
    """The report as JSON; every figure must be a number JSON can hold (no NaN, no Infinity)."""
    try:
        return json.dumps(report.to_dict(), indent=1, allow_nan=False) + "\n"
    except ValueError:
        raise EvalError(f"{poses}: the errors are not finite numbers; nothing was written") from None


def _write_output(path: str, write: Callable[[str], None]) -> None:
    try:
        write(path)
    except OSError as exc:
        raise EvalError(f"{path}: cannot write ({exc.strerror or exc})") from None
