"""Does another AprilTag binding give exactly pupil-apriltags' detections on the receiver's real images?

    python benchmarks/apriltag_binding.py collect FLIGHT_DIR... --out IMAGES.npz [--frames N]
    python benchmarks/apriltag_binding.py compare IMAGES.npz [--binding pyapriltags]
    python benchmarks/apriltag_binding.py leak IMAGES.npz [--bindings pupil_apriltags,dt_apriltags] [--calls N]

``collect`` runs the receiver's pipeline over each flight (a folder with frames.mkv, camera.yaml and
arena.yaml, as the suite renders them) with AprilTag on every frame (``pose.method: apriltag``, as
benchmarks/detector_memory.py does: the detector's load in the worst case) and keeps every image the
pipeline hands the detector, with the ``decimate`` it asks for. ``compare`` makes the C detector of each
binding with the receiver's default settings (:func:`ipt.receiver.detect.detector.c_settings`), runs both
on every image with the same decimation and prints one JSON object: images, detections of each, ids that
differ, the largest corner difference in pixels over the detections both make, and the largest difference
of the decision margins. pyapriltags' and dt-apriltags' ``Detector`` share pupil-apriltags' ctypes layout.
``leak`` calls each binding's detector N times over the images in a fresh process and reports how much its
anonymous resident memory (``RssAnon``) grew after the first 1,000 calls, in bytes per call.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np


def collect(folders: list[Path], out: Path, frames: int) -> dict[str, int]:
    """Every detector input of the pipeline over ``folders`` (at most ``frames`` each), into ``out``."""
    from ipt.config.camera_info import load_camera_info
    from ipt.config.models import PipelineConfig, load_arena_config
    from ipt.receiver.core.pipeline import Pipeline
    from ipt.tagmap import grid_tag_map
    from ipt.videoio import open_frames

    images: list[np.ndarray] = []
    decimates: list[float] = []
    counts = {}
    for folder in folders:
        arena = load_arena_config(folder / "arena.yaml")
        camera = load_camera_info(folder / "camera.yaml")
        cfg = PipelineConfig.model_validate({"pose": {"method": "apriltag"}})
        pipeline = Pipeline(grid_tag_map(arena), camera, cfg, arena.projector.rate_hz)
        detect = pipeline.detector.detect
        before = len(images)

        def keep(gray: np.ndarray, decimate: float | None = None, detect: Any = detect) -> Any:
            images.append(gray.copy())
            decimates.append(np.nan if decimate is None else float(decimate))
            return detect(gray, decimate)

        pipeline.detector.detect = keep  # type: ignore[method-assign]
        with open_frames(folder / "frames.mkv") as video:
            for k, frame in enumerate(video):
                if k >= frames:
                    break
                pipeline.process(k, frame, round(k / 120 * 1e6))
        pipeline.close()
        counts[folder.name] = len(images) - before
    np.savez_compressed(out, *images, decimates=np.array(decimates))
    return counts


def _detector(module_name: str, settings: dict[str, float]) -> Any:
    from ipt.receiver.detect.apriltag_c import make_pupil_detector

    return make_pupil_detector(settings, importlib.import_module(module_name))


def _raw(det: Any, gray: np.ndarray, decimate: float) -> dict[tuple[int, int], tuple[int, float, np.ndarray]]:
    det.tag_detector_ptr.contents.quad_decimate = decimate
    found: dict[tuple[int, int], tuple[int, float, np.ndarray]] = {}
    for d in det.detect(gray):
        key = (int(d.tag_id), sum(1 for k in found if k[0] == int(d.tag_id)))
        found[key] = (int(d.hamming), float(d.decision_margin), np.asarray(d.corners, np.float64).reshape(4, 2))
    return found


def compare(images_path: Path, binding: str) -> dict[str, Any]:
    """Both bindings over every collected image; what differs."""
    from ipt.config.models import DetectorConfig
    from ipt.receiver.detect.detector import c_settings

    settings = c_settings(DetectorConfig())
    ref, other = _detector("pupil_apriltags", settings), _detector(binding, settings)
    with np.load(images_path) as data:
        decimates = data["decimates"]
        images = [data[f"arr_{k}"] for k in range(len(decimates))]
    n_ref = n_other = id_mismatch = hamming_mismatch = 0
    corner_max = margin_max = 0.0
    for gray, dec in zip(images, decimates, strict=True):
        decimate = settings["quad_decimate"] if np.isnan(dec) else float(dec)
        a, b = _raw(ref, gray, decimate), _raw(other, gray, decimate)
        n_ref += len(a)
        n_other += len(b)
        id_mismatch += len(set(a) ^ set(b))
        for key in set(a) & set(b):
            hamming_mismatch += a[key][0] != b[key][0]
            margin_max = max(margin_max, abs(a[key][1] - b[key][1]))
            corner_max = max(corner_max, float(np.abs(a[key][2] - b[key][2]).max()))
    version = importlib.metadata.version(binding)
    return {
        "binding": f"{binding} {version}",
        "reference": f"pupil-apriltags {importlib.metadata.version('pupil-apriltags')}",
        "settings": settings,
        "images": len(images),
        "detections_reference": n_ref,
        "detections_binding": n_other,
        "detections_only_in_one": id_mismatch,
        "hamming_differs": hamming_mismatch,
        "corner_max_abs_diff_px": corner_max,
        "decision_margin_max_abs_diff": margin_max,
    }


def _rss_anon_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssAnon:"):
            return int(line.split()[1])
    raise RuntimeError("no RssAnon in /proc/self/status")


def leak_child(images_path: Path, binding: str, calls: int) -> dict[str, Any]:
    """RssAnon growth of ``calls`` detections with ``binding`` (in this process, run fresh per binding)."""
    from ipt.config.models import DetectorConfig
    from ipt.receiver.detect.detector import c_settings

    settings = c_settings(DetectorConfig())
    det = _detector(binding, settings)
    with np.load(images_path) as data:
        decimates = data["decimates"]
        images = [data[f"arr_{k}"] for k in range(len(decimates))]
    warm = 1000
    start_kb = 0
    for k in range(calls):
        if k == warm:
            start_kb = _rss_anon_kb()
        dec = decimates[k % len(images)]
        _raw(det, images[k % len(images)], settings["quad_decimate"] if np.isnan(dec) else float(dec))
    growth_kb = _rss_anon_kb() - start_kb
    return {"binding": f"{binding} {importlib.metadata.version(binding)}", "calls": calls - warm,
            "rss_anon_growth_kb": growth_kb, "bytes_per_call": round(growth_kb * 1024 / (calls - warm), 1)}  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    c = sub.add_parser("collect")
    c.add_argument("folders", nargs="+", type=Path)
    c.add_argument("--out", type=Path, required=True)
    c.add_argument("--frames", type=int, default=960)
    m = sub.add_parser("compare")
    m.add_argument("images", type=Path)
    m.add_argument("--binding", default="pyapriltags")
    lk = sub.add_parser("leak")
    lk.add_argument("images", type=Path)
    lk.add_argument("--bindings", default="pupil_apriltags,dt_apriltags")
    lk.add_argument("--calls", type=int, default=20_000)
    lk.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.command == "leak":
        if args.child:
            print(json.dumps(leak_child(args.images, args.child, args.calls)))
            return 0
        results = []
        for binding in args.bindings.split(","):
            cmd = [sys.executable, __file__, "leak", str(args.images), "--calls", str(args.calls), "--child", binding]
            results.append(json.loads(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout))
        print(json.dumps(results, indent=1))
    elif args.command == "collect":
        print(json.dumps({"images_per_flight": collect(args.folders, args.out, args.frames)}))
    else:
        print(json.dumps(compare(args.images, args.binding), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
