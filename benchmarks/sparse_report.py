"""The sparse tracker benchmark's report of a chain (:mod:`sparse_track`): yield, errors against the ground
truth and the dense pipeline's, latency, and the joint fits' predictions' errors."""

from __future__ import annotations

from collections import Counter
from typing import Any

import cv2
import numpy as np

from ipt.eval import evaluate
from ipt.geometry import matrix_from_quat_wxyz
from ipt.receiver.core.pipeline import FrameResult
from ipt.receiver.core.pose import pose_of
from ipt.receiver.core.sparse import SparseCamera
from ipt.tum import Trajectory


def errors(truth: Trajectory, times_s: list[float], poses: list[Any]) -> dict[str, Any]:
    if not poses:
        return {"poses": 0}
    r = evaluate(truth, Trajectory.from_arrays(times_s, [p.position_m for p in poses], [p.quat_wxyz for p in poses]))
    return {
        "poses": len(poses),
        "mae_mm": [round(1e3 * v, 2) for v in (r.mae_x_m, r.mae_y_m, r.mae_z_m)],
        "max_error_mm": round(1e3 * r.max_pos_err_m, 1),
        "poses_over_10cm": r.n_outliers,
    }


def chain_report(
    chain: Any,
    sparse_s: float,
    worked: int,
    dense: dict[int, FrameResult],
    phase: dict[int, int],
    truth: Trajectory,
    times_us: list[int],
    camera: SparseCamera,
) -> dict[str, Any]:
    """A chain's yield, re-seeds, processor time, errors (its own and the dense pipeline's on the same frames)
    and latency (from the frame's capture to the arrival of the frame whose fit gave its pose)."""
    own = sorted(chain.fitted)
    same = [k for k in own if dense.get(k) is not None and dense[k].pose is not None]
    waited_ms = [(times_us[chain.emitted[k]] - times_us[k]) * 1e-3 for k in own]
    return {
        "sparse_yield_pct": round(100.0 * len(own) / len(times_us), 1),
        "reseeds": chain.reseeds,
        "refused": dict(sorted(chain.refused.items())),
        "sparse_ms_per_frame": round(1e3 * sparse_s / max(worked, 1), 3),
        "sparse_ms_per_pose": round(1e3 * sparse_s / max(len(own), 1), 3),
        "iterations_mean": round(float(np.mean([chain.fitted[k].iterations for k in own])), 2) if own else None,
        "joint_guess_error": _guess_errors(chain, truth, camera),
        "frames_waited": dict(sorted(Counter(chain.emitted[k] - k for k in own).items())),
        "wait_ms_p50_p99": [round(float(np.percentile(waited_ms, q)), 1) for q in (50, 99)] if own else None,
        "sparse": errors(truth, [times_us[k] * 1e-6 for k in own], [chain.fitted[k].estimate() for k in own]),
        "dense_same_frames": errors(truth, [times_us[k] * 1e-6 for k in same], [dense[k].pose for k in same]),
        # By the frame's phase: with a 60 Hz projector showing each 30 Hz video frame as one phase then the
        # other, the first phase's past partners all show the video frame before (moved, cut).
        "sparse_by_phase": {
            f"{p:+d}": errors(
                truth,
                [times_us[k] * 1e-6 for k in own if phase.get(k) == p],
                [chain.fitted[k].estimate() for k in own if phase.get(k) == p],
            )
            for p in (1, -1)
        },
        "sparse_same_frames": errors(
            truth, [times_us[k] * 1e-6 for k in same], [chain.fitted[k].estimate() for k in same]
        ),
    }


def _guess_errors(chain: Any, truth: Trajectory, camera: SparseCamera) -> dict[str, Any] | None:
    """The joint fits' predictions' errors against the ground truth: of the camera's position (mm) and in the
    image (px: the largest move of the floor under a 5x4 grid over the image, pinhole), p50 and p90 of all,
    and the medians of the frames whose joint fit passed its checks and of those whose fit did not."""
    if not chain.guesses:
        return None
    w, h = camera.size
    grid = np.stack(np.meshgrid(np.linspace(0.1, 0.9, 5) * w, np.linspace(0.1, 0.9, 4) * h), -1).reshape(-1, 2)
    rays = (np.linalg.inv(camera.camera_matrix) @ np.column_stack([grid, np.ones(len(grid))]).T).T
    mm, px = {}, {}
    for k, rt in chain.guesses.items():
        r_true = matrix_from_quat_wxyz(truth.quats_wxyz[k])
        position = truth.positions_m[k]
        mm[k] = 1e3 * float(np.linalg.norm(pose_of(*rt)[0] - position))
        world = rays @ r_true.T
        floor = position + (-position[2] / world[:, 2])[:, None] * world
        seen, _ = cv2.projectPoints(floor, rt[0], rt[1], camera.camera_matrix, None)
        px[k] = float(np.linalg.norm(seen.reshape(-1, 2) - grid, axis=1).max())

    def summary(err: dict[int, float]) -> list[float]:
        ok = [e for k, e in err.items() if chain.joint_ok.get(k)]
        bad = [e for k, e in err.items() if chain.joint_ok.get(k) is False]
        out = [round(float(np.percentile(list(err.values()), q)), 2) for q in (50, 90)]
        return out + [round(float(np.median(v)), 2) if v else -1.0 for v in (ok, bad)]

    return {"mm_p50_p90_ok_refused": summary(mm), "px_p50_p90_ok_refused": summary(px)}
