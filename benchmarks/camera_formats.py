"""Camera formats: what handing the pipeline the luma saves per frame, from the camera's buffer to the
pipeline's lightness image (the ``lightness`` stage), for each format the receiver decodes itself.

    python benchmarks/camera_formats.py [--video DIR] [--frames N] [--repeat R]

For each format, two routes on the same buffers: **rgb** (before: OpenCV converts the buffer to BGR, the
capture thread to RGB, the pipeline takes the luma and maps it to L) and **luma** (now: the Y plane or a
grey JPEG decode, then the same map). The buffers are made from rendered frames (DIR holds frames.mkv as
``ipt sim`` writes it; without it 0.25 s of the smooth flight is simulated first). Single-threaded
(OpenCV limited to one thread); pin it to one core for stable figures: ``taskset -c 0 python ...``.
Prints one line per format and the whole as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from ipt.receiver.capture.pixelformats import raw_luma, yuyv_from_rgb
from ipt.receiver.core.demodulator import luminance
from ipt.videoio import open_frames

U8 = npt.NDArray[np.uint8]


def _frames(video: Path | None, n: int, tmp: Path) -> list[U8]:
    if video is None:
        from ipt.config.models import ArenaConfig
        from ipt.sender.content import GeneratedScene
        from ipt.sim.config import SimConfig
        from ipt.sim.run import simulate_to_folder

        simulate_to_folder(ArenaConfig(), SimConfig.smooth(), GeneratedScene(1920, 2160), tmp, 0.25, progress=None)
        video = tmp
    with open_frames(video / "frames.mkv") as src:
        return [f for _, f in zip(range(n), src, strict=False)]


def _time_ms(route: Callable[[object], U8], buffers: list[object], repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for b in buffers:
            route(b)
        best = min(best, (time.perf_counter() - t0) / len(buffers))
    return 1e3 * best


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--video", type=Path, help="folder with frames.mkv (default: simulate 0.25 s)")
    parser.add_argument("--frames", type=int, default=30, help="frames to convert (default 30)")
    parser.add_argument("--repeat", type=int, default=5, help="timing repeats, the best kept (default 5)")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    with tempfile.TemporaryDirectory() as tmp:
        frames = _frames(args.video, args.frames, Path(tmp))
    h, w = frames[0].shape[:2]

    def rgb_route(to_bgr: Callable[[object], U8]) -> Callable[[object], U8]:
        return lambda b: luminance(np.ascontiguousarray(cv2.cvtColor(to_bgr(b), cv2.COLOR_BGR2RGB)))

    quality = [cv2.IMWRITE_JPEG_QUALITY, 90]
    jpegs = [cv2.imencode(".jpg", cv2.cvtColor(f, cv2.COLOR_RGB2BGR), quality)[1] for f in frames]
    yuyvs = [yuyv_from_rgb(f) for f in frames]
    greys = [np.asarray(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY)) for f in frames]
    yuv420 = [np.asarray(cv2.cvtColor(f, cv2.COLOR_RGB2YUV_I420)) for f in frames]  # picamera2's YUV420 layout
    bgr888 = [np.ascontiguousarray(f[:, :, ::-1]) for f in frames]  # picamera2's RGB888 (B, G, R in memory)
    cases: dict[str, tuple[list[object], Callable[[object], U8], Callable[[object], U8]]] = {
        "MJPG": (
            list(jpegs),
            rgb_route(lambda b: cv2.imdecode(b, cv2.IMREAD_COLOR)),  # type: ignore[call-overload]
            lambda b: luminance(raw_luma(b, "MJPG", w, h)),  # type: ignore[arg-type]
        ),
        "YUYV": (
            list(yuyvs),
            rgb_route(lambda b: cv2.cvtColor(b, cv2.COLOR_YUV2BGR_YUYV)),  # type: ignore[call-overload]
            lambda b: luminance(raw_luma(b, "YUYV", w, h)),  # type: ignore[arg-type]
        ),
        "GREY": (
            list(greys),
            rgb_route(lambda b: cv2.cvtColor(b, cv2.COLOR_GRAY2BGR)),  # type: ignore[call-overload]
            lambda b: luminance(raw_luma(b, "GREY", w, h)),  # type: ignore[arg-type]
        ),
        "picamera2": (
            [(a, b) for a, b in zip(bgr888, yuv420, strict=True)],
            lambda ab: luminance(np.ascontiguousarray(ab[0][:, :, 2::-1])),  # type: ignore[index]
            lambda ab: luminance(np.ascontiguousarray(ab[1][:h, :w])),  # type: ignore[index]
        ),
    }
    results = {}
    for name, (buffers, before, after) in cases.items():
        rgb_ms = _time_ms(before, buffers, args.repeat)
        luma_ms = _time_ms(after, buffers, args.repeat)
        saved = rgb_ms - luma_ms
        results[name] = {"rgb_ms": round(rgb_ms, 3), "luma_ms": round(luma_ms, 3), "saved_ms": round(saved, 3)}
        line = f"{name:10s} {w}x{h}: via RGB {rgb_ms:6.3f} ms, luma {luma_ms:6.3f} ms, saved {saved:6.3f} ms/frame"
        print(line, file=sys.stderr)
    summary = {"width_px": w, "height_px": h, "frames": len(frames), "formats": results}
    json.dump(summary, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
