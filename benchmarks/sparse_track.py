"""The sparse tracker prototype (issue 29, :mod:`ipt.receiver.core.sparse`) on rendered flights, against the dense
pipeline on the same frames.

    python benchmarks/sparse_track.py DIR [DIR ...] [--frames N]

``DIR`` is a rendering (``bmp/`` frames, ``camera.yaml``, ``arena.yaml``, ``groundtruth.tum``; read only). The
dense :class:`~ipt.receiver.core.pipeline.Pipeline` runs first, in process, for its poses and each frame's
projector phase. Then the sparse tracker runs as a chain: it starts from the dense pose of the first posed
frame; each later frame k is fitted from one of its past partners k−1…k−3 of the other phase that has a pose
of the chain (its own output), starting from the chain's last two poses carried on at constant velocity.
When no partner gives a fit that its checks accept, the chain takes the dense pose of k (a re-seed, counted);
frames without one stay unposed. Prints JSON per flight: the sparse fit's yield, its re-seeds, its processor
time per frame (``time.thread_time`` of everything the fit does: selection, sampling through the lens, the
fit; frames preloaded as lightness, not timed, the lightness's own cost given apart), the errors against the
ground truth of the sparse poses and of the dense poses of the same frames, and the dense pipeline's own
processor time per frame and per stage in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.base import ConfigError
from ipt.config.camera_info import load_camera_info
from ipt.config.models import load_arena_config
from ipt.eval import evaluate
from ipt.receiver.core.demodulator import luminance
from ipt.receiver.core.pipeline import FrameResult, Pipeline
from ipt.receiver.core.pose import pose_of, rt_of
from ipt.receiver.core.sparse import SparseCamera, SparseResult, SparseSettings, extrapolate, fit_sparse
from ipt.receiver.core.track import MapEdges
from ipt.receiver.detect.detector import pipeline_detector
from ipt.tagmap import grid_tag_map
from ipt.tum import Trajectory, read_tum

sys.path.insert(0, str(Path(__file__).resolve().parent))
from suite import one_core, receiver_config

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

#: Past partners tried for a frame, nearest first.
PAST = (1, 2, 3)
#: A fit this far (metres) from the chain's prediction is refused (the dense pipeline's gates do as much).
MAX_JUMP_M = 0.03


def _moved_m(result: SparseResult, guess: tuple[F64, F64]) -> float:
    """How far the fitted camera is from the predicted one, metres."""
    fitted, _ = pose_of(result.rvec, result.tvec)
    predicted, _ = pose_of(*guess)
    return float(np.linalg.norm(fitted - predicted))


@dataclass
class Chain:
    """The sparse chain's poses so far."""

    rt: dict[int, tuple[F64, F64]] = field(default_factory=dict)
    sign: dict[int, int] = field(default_factory=dict)
    step: dict[int, float] = field(default_factory=dict)
    fitted: dict[int, SparseResult] = field(default_factory=dict)
    reseeds: int = 0
    refused: Counter[str] = field(default_factory=Counter)


def load_frames(folder: Path, frames: int | None, method: str) -> tuple[list[npt.NDArray[Any]], list[U8], float]:
    """The rendering's frames as the camera delivers them, their lightness (raw: not undistorted) and its
    processor time per frame."""
    names = sorted((folder / "bmp").glob("*.bmp"))[:frames]
    if not names:
        raise SystemExit(f"sparse_track: {folder / 'bmp'}: no BMP frames")
    raw, lum, spent = [], [], 0.0
    for name in names:
        image = cv2.imread(str(name), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise SystemExit(f"sparse_track: {name}: not a readable image")
        frame = image if image.ndim == 2 else np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_BGR2RGB))
        raw.append(frame)
        t0 = time.thread_time()
        lum.append(luminance(frame, method))
        spent += time.thread_time() - t0
    return raw, lum, spent / len(names)


def run_dense(
    pipeline: Pipeline, raw: list[npt.NDArray[Any]], times_us: list[int]
) -> tuple[dict[int, FrameResult], dict[int, int], float]:
    """The dense pipeline's results by frame, each frame's projector phase as it learnt it, and its processor
    time per frame."""
    results: list[FrameResult] = []
    phase: dict[int, int] = {}
    spent = 0.0
    for k, frame in enumerate(raw):
        t0 = time.thread_time()
        results += pipeline.process(k, frame, times_us[k])
        spent += time.thread_time() - t0
        for f in pipeline.history:
            if f.phase is not None:
                phase[f.index] = f.phase
    results += pipeline.flush()
    return {r.index: r for r in results}, phase, spent / len(raw)


def predict(chain: Chain, k: int, times_us: list[int]) -> tuple[F64, F64] | None:
    """The chain's last two poses before ``k`` (within five frames) carried on to ``k``, or its last one."""
    recent = [j for j in range(k - 1, max(k - 6, -1), -1) if j in chain.rt]
    if not recent:
        return None
    if len(recent) == 1:
        return chain.rt[recent[0]]
    b, a = recent[0], recent[1]
    return extrapolate(chain.rt[a], times_us[a], chain.rt[b], times_us[b], times_us[k])


def sparse_frame(
    chain: Chain, k: int, lum: list[U8], phase: dict[int, int], times_us: list[int], fit: Any, best: bool = False
) -> SparseResult | None:
    """Frame ``k``'s sparse fit from its first past partner of the other phase that gives one (``best``: from
    each such partner, the fit with the smallest residual)."""
    guess = predict(chain, k, times_us)
    if guess is None or k not in phase:
        return None
    found: list[SparseResult] = []
    for back in PAST:
        j = k - back
        if j not in chain.rt or phase.get(j) != -phase[k]:
            continue
        hint = -chain.sign[j] * chain.step[j] if j in chain.step else 0.0
        result, why = fit(lum[k], lum[j], chain.rt[j], guess, hint)
        if result is not None and _moved_m(result, guess) > MAX_JUMP_M:
            chain.refused["far_from_prediction"] += 1
            continue
        if result is not None and result.sign == phase[k]:
            if not best:
                return result
            found.append(result)
            continue
        chain.refused[why or "wrong_phase"] += 1
    return min(found, key=lambda r: r.rms_px) if found else None


def run_sparse(
    lum: list[U8],
    dense: dict[int, FrameResult],
    phase: dict[int, int],
    times_us: list[int],
    camera: SparseCamera,
    edges: MapEdges,
    settings: SparseSettings,
    best: bool = False,
) -> tuple[Chain, float, int]:
    """The chain over the frames; its processor time (sparse work only) and the frames it worked on."""

    def fit(image: U8, other: U8, other_rt: tuple[F64, F64], guess: tuple[F64, F64], hint: float) -> Any:
        return fit_sparse(image, other, camera, edges, other_rt, guess, settings, hint)

    chain = Chain()
    spent, worked = 0.0, 0
    first = next((k for k in range(len(lum)) if k in dense and dense[k].pose is not None), None)
    if first is not None:  # the kernels compiled (or loaded from numba's cache) before the clock starts
        pose = dense[first].pose
        assert pose is not None
        rt = rt_of(pose.position_m, pose.r_arena_cam)
        fit(lum[first], lum[first], rt, rt, 0.0)
    for k in range(len(lum)):
        result = None
        if chain.rt:
            worked += 1
            t0 = time.thread_time()
            result = sparse_frame(chain, k, lum, phase, times_us, fit, best)
            spent += time.thread_time() - t0
        if result is not None:
            chain.rt[k], chain.sign[k], chain.step[k] = (result.rvec, result.tvec), result.sign, result.amplitude
            chain.fitted[k] = result
        elif k in dense and dense[k].pose is not None and k in phase:
            pose = dense[k].pose
            assert pose is not None
            chain.rt[k], chain.sign[k] = rt_of(pose.position_m, pose.r_arena_cam), phase[k]
            chain.step.pop(k, None)
            chain.reseeds += 1 if chain.fitted or len(chain.rt) > 1 else 0
    return chain, spent, worked


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


def flight(folder: Path, frames: int | None, settings: SparseSettings) -> dict[str, Any]:
    try:
        arena = load_arena_config(folder / "arena.yaml")
    except (ConfigError, OSError) as exc:
        raise SystemExit(f"sparse_track: {folder / 'arena.yaml'}: {exc}") from None
    camera = load_camera_info(folder / "camera.yaml")
    truth = read_tum(folder / "groundtruth.tum")
    cfg = receiver_config("ipt", False)
    raw, lum, lightness_s = load_frames(folder, frames, cfg.demodulation.lightness)
    times_us = [round(float(truth.times_s[k]) * 1e6) for k in range(len(raw))]
    tag_map = grid_tag_map(arena)
    with one_core():
        pipeline = Pipeline(
            tag_map, camera, cfg, arena.projector.rate_hz, pipeline_detector(cfg.detector, tag_map.by_id)
        )
        try:
            dense, phase, dense_s = run_dense(pipeline, raw, times_us)
        finally:
            pipeline.close()
        scale = camera.width_px / 640
        settings = SparseSettings(
            **{**settings.__dict__, "blur_px": settings.blur_px * scale, "border_px": settings.border_px * scale}
        )
        sparse_camera = SparseCamera.of(camera.camera_matrix, camera.dist_coeffs, (camera.width_px, camera.height_px))
        chain, sparse_s, worked = run_sparse(
            lum, dense, phase, times_us, sparse_camera, MapEdges.from_tag_map(tag_map), settings
        )
    own = sorted(chain.fitted)
    same = [k for k in own if dense.get(k) is not None and dense[k].pose is not None]
    n = len(raw)
    return {
        "frames": n,
        "sparse_yield_pct": round(100.0 * len(own) / n, 1),
        "dense_yield_pct": round(100.0 * sum(1 for r in dense.values() if r.pose is not None) / n, 1),
        "reseeds": chain.reseeds,
        "refused": dict(sorted(chain.refused.items())),
        "sparse_ms_per_frame": round(1e3 * sparse_s / max(worked, 1), 3),
        "sparse_ms_per_fit": round(1e3 * sparse_s / max(len(own), 1), 3),
        "iterations_mean": round(float(np.mean([chain.fitted[k].iterations for k in own])), 2) if own else None,
        "lightness_ms_per_frame": round(1e3 * lightness_s, 3),
        "dense_ms_per_frame": round(1e3 * dense_s, 3),
        "dense_stage_ms_per_frame": {s: round(1e3 * v / n, 3) for s, v in pipeline.stage_seconds.items()},
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


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "dirs", nargs="+", type=Path, help="renderings (bmp/, camera.yaml, arena.yaml, groundtruth.tum)"
    )
    parser.add_argument("--frames", type=int, default=None, help="only the first N frames")
    parser.add_argument("--blur-px", type=float, default=SparseSettings.blur_px, help="step blur σ at 640 px wide")
    args = parser.parse_args()
    if args.frames is not None and args.frames < 10:
        print(f"sparse_track: --frames {args.frames}: need at least 10", file=sys.stderr)
        return 2
    for d in args.dirs:
        for need in ("bmp", "camera.yaml", "arena.yaml", "groundtruth.tum"):
            if not (d / need).exists():
                print(f"sparse_track: {d}: no {need}", file=sys.stderr)
                return 2
    settings = SparseSettings(blur_px=args.blur_px)
    out = {"load": os.getloadavg()[0], "flights": {d.name: flight(d, args.frames, settings) for d in args.dirs}}
    out["load_after"] = os.getloadavg()[0]
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
