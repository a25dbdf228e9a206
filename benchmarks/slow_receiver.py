"""A receiver slower than its camera: which frames the live daemon hands the pipeline, and the poses, as JSON.

    python benchmarks/slow_receiver.py --video DIR [--slowdown 2.4 3.3 7 9] [--frames N]

DIR holds frames.mkv, camera.yaml, arena.yaml and groundtruth.tum (``ipt sim --out DIR`` writes them; the
suite's renderings are such folders). A live daemon whose pipeline takes ``k`` camera frame times per
frame (``--slowdown``) sees only some of the camera's frames. This replays which ones, without a clock:
after each run the pipeline is free ``k`` frame times per frame later, and takes

- ``newest``: the newest frame alone (the daemon before runs; a partner is then ``k`` frames away), or
- ``runs``: what the live queue holds, up to :data:`ipt.receiver.liverun.LIVE_RUN_FRAMES` consecutive frames
  ending with the newest (the daemon until stop 51, and still until the projector's phase is known; once it
  is, the daemon takes a + and − frame of one video frame when it fell behind by more than that,
  :func:`ipt.receiver.liverun.pick_run`, which needs the pipeline's phase as it runs: ``benchmarks/live_sim.py``
  models it),

and feeds exactly those frames, with their capture times, to a real pipeline (profile ``ipt``). Printed per
policy and slowdown: frames fed, poses, yield of the frames fed, poses per second of flight, and the poses'
position error against the truth (median, largest, and how many are more than 10 cm off).
Deterministic (no timing): the same figures on any machine.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ipt.config.camera_info import load_camera_info
from ipt.config.models import PipelineConfig, load_arena_config
from ipt.receiver.core.pipeline import Pipeline
from ipt.receiver.detect.detector import pipeline_detector
from ipt.receiver.liverun import LIVE_RUN_FRAMES
from ipt.tagmap import grid_tag_map
from ipt.tum import read_tum
from ipt.videoio import open_frames

POLICIES = ("newest", "runs")


def taken(frames: int, slowdown: float, policy: str) -> list[int]:
    """The frames a daemon whose pipeline takes ``slowdown`` frame times per frame processes, in order."""
    out: list[int] = []
    t, last = 0.0, -1
    while (newest := math.floor(t + 1e-9)) < frames:
        if newest <= last:  # nothing new yet: the next frame comes
            t = last + 1
            continue
        first = max(last + 1, newest - LIVE_RUN_FRAMES + 1) if policy == "runs" else newest
        run = list(range(first, newest + 1))
        out += run
        last = newest
        t += slowdown * len(run)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--video", type=Path, required=True, help="a flight folder (frames.mkv, camera.yaml, ...)")
    p.add_argument(
        "--slowdown", type=float, nargs="+", default=[2.4, 3.3, 7.0, 9.0], help="camera frames per frame processed"
    )
    p.add_argument("--frames", type=int, default=480, help="camera frames of the flight to use (default 480: 4 s)")
    args = p.parse_args()
    folder: Path = args.video
    missing = [n for n in ("frames.mkv", "camera.yaml", "arena.yaml", "groundtruth.tum") if not (folder / n).exists()]
    if missing:
        print(f"slow_receiver: {folder} lacks {', '.join(missing)}", file=sys.stderr)
        return 2
    cv2.setNumThreads(1)
    arena = load_arena_config(folder / "arena.yaml")
    camera = load_camera_info(folder / "camera.yaml")
    truth = read_tum(folder / "groundtruth.tum")
    times_s = truth.times_s
    with open_frames(folder / "frames.mkv") as src:
        images = [f for _, f in zip(range(args.frames), src, strict=False)]
    flight_s = len(images) / camera_fps(times_s)
    rows: list[dict[str, Any]] = []
    for slowdown in args.slowdown:
        for policy in POLICIES:
            feed = taken(len(images), slowdown, policy)
            cfg, tag_map = PipelineConfig.profile("ipt"), grid_tag_map(arena)
            detector = pipeline_detector(cfg.detector, tag_map.by_id)
            pipeline = Pipeline(tag_map, camera, cfg, arena.projector.rate_hz, detector)
            try:
                results = [r for k in feed for r in pipeline.process(k, images[k], round(times_s[k] * 1e6))]
                results += pipeline.flush()
            finally:
                pipeline.close()
            errors_mm = [
                1e3 * float(np.linalg.norm(r.pose.position_m - truth.positions_m[r.index]))
                for r in results
                if r.pose is not None
            ]
            poses = len(errors_mm)
            rows.append(
                {
                    "slowdown": slowdown,
                    "policy": policy,
                    "frames_fed": len(feed),
                    "poses": poses,
                    "yield_of_fed": round(poses / len(feed), 3) if feed else None,
                    "poses_per_s": round(poses / flight_s, 1),
                    "error_mm": {
                        "median": round(float(np.median(errors_mm)), 1) if errors_mm else None,
                        "max": round(max(errors_mm), 1) if errors_mm else None,
                        "over_100mm": sum(e > 100 for e in errors_mm),
                    },
                }
            )
            print(f"slow_receiver: {rows[-1]}", file=sys.stderr, flush=True)
    json.dump(
        {"benchmark": "slow_receiver", "flight": str(folder), "frames": len(images), "rows": rows}, sys.stdout, indent=1
    )
    print()
    return 0


def camera_fps(times_s: Any) -> float:
    """The camera's frame rate from the truth's capture times."""
    return float((len(times_s) - 1) / (times_s[-1] - times_s[0]))


if __name__ == "__main__":
    sys.exit(main())
