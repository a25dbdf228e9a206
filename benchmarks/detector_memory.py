"""Detector memory: AprilTag's leak in process (``isolation: inline``) against the recycled helper
process (``isolation: process``, the default), on the images the receiver really gives the detector.

    python benchmarks/detector_memory.py [--video DIR] [--calls N] [--seconds S] [--recycle-mb MB]

First the images: a simulated flight (DIR from ``ipt sim``, or S seconds simulated into a temporary
folder) goes through the receiver's pipeline once, and every binary image it hands the detector is kept.
Then, for each isolation, a fresh Python process calls the detector N times over those images, in a
loop, as fast as it can (faster than a 120 FPS camera would), and every 1,000 calls samples the
resident memory of itself and its descendants (``RssAnon`` summed, as benchmarks/soak.py does). The
first 1,000 calls are the warm-up; growth is measured from there.

Prints one JSON object: per isolation, calls, calls/s, the median time per call, RssAnon at the start,
the end and the maximum, growth (end - start, last-tenth median - first-tenth median, and the
least-squares slope per 100,000 calls), the calling process's own growth, bytes per call, and the
helpers replaced. With ``isolation: process`` the memory is a saw-tooth of height ``--recycle-mb``:
the slope, over many teeth, is the measure; ``--recycle-mb 1`` gives more teeth in a short run.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ipt.config.models import DetectorConfig

WARM_CALLS = 1000
SAMPLE_EVERY = 1000


def collect_images(folder: Path, out: Path) -> int:
    """Run the pipeline over the flight in ``folder``; save every detector input to ``out`` (npz)."""
    from ipt.config.camera_info import load_camera_info
    from ipt.config.models import ArenaConfig, PipelineConfig
    from ipt.receiver.core.pipeline import Pipeline
    from ipt.receiver.detect.detector import pipeline_detector
    from ipt.tagmap import grid_tag_map
    from ipt.videoio import open_frames

    arena = ArenaConfig()
    camera = load_camera_info(folder / "camera.yaml")
    # AprilTag on every frame (the default profile runs it only to acquire and to check its track): the
    # images are the detector's load in the worst case.
    cfg = PipelineConfig.model_validate({"pose": {"method": "apriltag"}})
    tag_map = grid_tag_map(arena)
    pipeline = Pipeline(tag_map, camera, cfg, arena.projector.rate_hz, pipeline_detector(cfg.detector, tag_map.by_id))
    seen: list[np.ndarray] = []
    detect = pipeline.detector.detect

    def keep(gray: np.ndarray, decimate: float | None = None) -> Any:
        seen.append(gray.copy())
        return detect(gray, decimate)

    pipeline.detector.detect = keep  # type: ignore[method-assign]
    with open_frames(folder / "frames.mkv") as frames:
        for k, frame in enumerate(frames):
            pipeline.process(k, frame, round(k / 120 * 1e6))
    pipeline.close()
    np.savez_compressed(out, *seen)
    return len(seen)


def child(images_path: Path, isolation: str, calls: int, recycle_mb: float) -> dict[str, Any]:
    """The measurement, in a fresh process."""
    from soak import sample  # benchmarks/ is on sys.path when a script here runs

    from ipt.receiver.detect.detector import TagDetector

    with np.load(images_path) as data:
        images = [data[k] for k in data.files]
    det = TagDetector(DetectorConfig(isolation=isolation, recycle_mb=recycle_mb))
    me = os.getpid()
    points: list[tuple[int, float, float]] = []  # calls, tree RssAnon MB, this process's RssAnon MB
    # Allocated and written up front: a growing list, or the lazily mapped pages of np.zeros, would
    # show here as growth.
    per_call = np.full(calls, np.nan)
    t_start = time.perf_counter()
    for k in range(calls):
        t0 = time.perf_counter()
        det.detect(images[k % len(images)])
        per_call[k] = time.perf_counter() - t0
        if (k + 1) % SAMPLE_EVERY == 0 and k + 1 >= WARM_CALLS:
            s = sample(me)
            assert s is not None
            points.append((k + 1, s["rss_anon_kb"] / 1024, s["main_rss_anon_kb"] / 1024))
    wall = time.perf_counter() - t_start
    backend = det.backend
    recycles, restarts = getattr(backend, "recycles", 0), getattr(backend, "restarts", 0)
    det.close()
    mb = [m for _, m, _ in points]
    tenth = max(1, len(mb) // 10)
    measured_calls = points[-1][0] - points[0][0]
    growth = mb[-1] - mb[0]
    slope_per_call = float(np.polyfit([c for c, _, _ in points], mb, 1)[0]) if len(points) > 2 else 0.0
    return {
        "isolation": isolation,
        "images": len(images),
        "calls": calls,
        "calls_per_s": round(calls / wall, 1),
        "call_ms_median": round(1000 * float(np.median(per_call)), 3),
        "rss_anon_mb": {
            "start": round(mb[0], 1),
            "end": round(mb[-1], 1),
            "max": round(max(mb), 1),
            "growth": round(growth, 2),
            "growth_tenth_median": round(statistics.median(mb[-tenth:]) - statistics.median(mb[:tenth]), 2),
            "slope_per_100k_calls": round(slope_per_call * 100_000, 2),
            "main_process_growth": round(points[-1][2] - points[0][2], 2),
        },
        "bytes_per_call": round(growth * 1024 * 1024 / measured_calls, 1) if measured_calls else None,
        "helpers_replaced_for_memory": recycles,
        "helpers_restarted": restarts,
        "samples": [(c, round(m, 2), round(main, 2)) for c, m, main in points],
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--video", type=Path, help="a flight folder from `ipt sim` (default: simulate one)")
    p.add_argument("--seconds", type=float, default=2.0, help="length of the simulated flight (default 2)")
    p.add_argument("--calls", type=int, default=60_000, help="detector calls per isolation (default 60,000)")
    p.add_argument("--recycle-mb", type=float, default=DetectorConfig().recycle_mb, help="detector.recycle_mb")
    p.add_argument("--isolations", default="inline,process", help="comma-separated (default inline,process)")
    p.add_argument("--child", nargs=2, metavar=("IMAGES", "ISOLATION"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.calls < 2 * WARM_CALLS:
        p.error(f"--calls must be at least {2 * WARM_CALLS}")
    if args.child:
        print(json.dumps(child(Path(args.child[0]), args.child[1], args.calls, args.recycle_mb)))
        return 0
    with tempfile.TemporaryDirectory(prefix="ipt-detmem-") as tmp:
        folder = args.video
        if folder is None:
            from ipt.config.models import ArenaConfig
            from ipt.sender.content import GeneratedScene
            from ipt.sim.config import SimConfig
            from ipt.sim.run import simulate_to_folder

            arena = ArenaConfig()
            folder = Path(tmp) / "flight"
            print(f"simulating a {args.seconds:g} s flight ...", file=sys.stderr)
            simulate_to_folder(
                arena, SimConfig(), GeneratedScene(arena.projector.width_px, arena.projector.height_px), folder,
                args.seconds, progress=None,
            )  # fmt: skip
        images = Path(tmp) / "images.npz"
        n = collect_images(folder, images)
        print(f"{n} detector images from {folder}", file=sys.stderr)
        results = []
        for isolation in args.isolations.split(","):
            print(f"{isolation}: {args.calls} calls ...", file=sys.stderr)
            cmd = [sys.executable, __file__, "--calls", str(args.calls), "--recycle-mb", str(args.recycle_mb),
                   "--child", str(images), isolation]  # fmt: skip
            out = subprocess.run(cmd, check=True, capture_output=True, text=True)
            results.append(json.loads(out.stdout))
    print(json.dumps({"recycle_mb": args.recycle_mb, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
