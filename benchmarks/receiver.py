"""Receiver benchmark: both pipeline profiles on the same simulated flight, side by side, as JSON.

    python benchmarks/receiver.py [--video DIR] [--seconds S] [--profiles ipt,paper]

DIR holds frames.mkv, camera.yaml and groundtruth.tum (as ``ipt sim`` writes them); without it a flight
of S seconds (default 15, the paper's test unit) is simulated first into a temporary folder. For each
profile: yield, MAE/STD per axis, tilt and yaw error, poses more than 10 cm off, and processing speed
(whole frames and per stage: lightness, demodulate, detect, pose).
Speed counts the pipeline only (frames are decoded beforehand), single-threaded (OpenCV limited to one
thread); pin the process to one core for the paper's comparison: ``taskset -c 0 python benchmarks/...``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from ipt.config.camera_info import load_camera_info
from ipt.config.models import PROFILES, ArenaConfig, PipelineConfig
from ipt.eval import evaluate
from ipt.receiver.core.pipeline import Pipeline
from ipt.receiver.detect.detector import pipeline_detector
from ipt.tagmap import grid_tag_map
from ipt.tum import Trajectory, read_tum
from ipt.videoio import open_frames


def _flight(video: Path | None, seconds: float, tmp: Path) -> Path:
    if video is not None:
        return video
    from ipt.sender.content import GeneratedScene
    from ipt.sim.config import SimConfig
    from ipt.sim.run import simulate_to_folder

    arena = ArenaConfig()
    pr = arena.projector
    simulate_to_folder(arena, SimConfig(), GeneratedScene(pr.width_px, pr.height_px), tmp, seconds)
    return tmp


def run_profile(folder: Path, frames: list[np.ndarray], profile: str, fps: float) -> dict[str, object]:
    arena = ArenaConfig()
    camera = load_camera_info(folder / "camera.yaml")
    cfg, tag_map = PipelineConfig.profile(profile), grid_tag_map(arena)
    pipeline = Pipeline(tag_map, camera, cfg, arena.projector.rate_hz, pipeline_detector(cfg.detector, tag_map.by_id))
    times, positions, quats, per_frame_s = [], [], [], []
    results = []
    for k, frame in enumerate(frames):
        t_us = round(k / fps * 1e6)
        t0 = time.perf_counter()
        results += pipeline.process(k, frame, t_us)
        per_frame_s.append(time.perf_counter() - t0)
    results += pipeline.flush()
    for result in results:
        if result.pose is not None:
            times.append(result.capture_time_us * 1e-6)
            positions.append(result.pose.position_m)
            quats.append(result.pose.quat_wxyz)
    report = evaluate(read_tum(folder / "groundtruth.tum"), Trajectory.from_arrays(times, positions, quats))
    d = report.to_dict()
    keep = [k for k in d if k.startswith(("mae_", "std_")) or k in ("yield", "n_estimates", "n_truth")]
    out: dict[str, object] = {k: d[k] for k in keep}
    out["outliers_over_10cm"] = report.n_outliers
    out["max_position_error_m"] = report.max_pos_err_m
    out["frames_per_second"] = len(frames) / sum(per_frame_s)
    out["frame_ms_median"] = 1e3 * statistics.median(per_frame_s)
    out["frame_ms_p99"] = 1e3 * float(np.percentile(per_frame_s, 99))
    out["stage_ms_per_frame"] = {k: 1e3 * v / len(frames) for k, v in pipeline.stage_seconds.items()}
    out["detector_runs_per_frame"] = pipeline.detector_runs / len(frames)
    out["reasons"] = dict(pipeline.reasons)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--video", type=Path, help="folder with frames.mkv, camera.yaml, groundtruth.tum")
    p.add_argument("--seconds", type=float, default=15.0, help="length of the flight to simulate (no --video)")
    p.add_argument("--profiles", default=",".join(PROFILES), help="comma-separated profiles to compare")
    p.add_argument("--fps", type=float, default=120.0, help="camera frame rate")
    args = p.parse_args()
    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory() as tmp:
        folder = _flight(args.video, args.seconds, Path(tmp))
        with open_frames(folder / "frames.mkv") as src:
            frames = list(src)
        print(f"receiver benchmark: {len(frames)} frames from {folder}", file=sys.stderr)
        results = {name: run_profile(folder, frames, name, args.fps) for name in args.profiles.split(",")}
        info = {"frames": len(frames), "width_px": frames[0].shape[1], "height_px": frames[0].shape[0]}
    print(json.dumps({"flight": info, "profiles": results}, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
