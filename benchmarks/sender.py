"""Sender throughput with the AR overlay: output frames/s, frame-work p50/p99, missed deadlines, start-up.

Runs the real sender loop (content, modulation, 8 vehicles drawn on the overlay) into the null sink,
paced at the projector rate, for ``--frames`` output frames (or ``--seconds`` of wall time; SIGINT stops
it early), from its very first frame: start-up (the modulator, the ``ipt`` profile's colour table, read
from its cache or computed on a first run) is part of the run and measured. The vehicles are fed straight
to the :class:`~ipt.sender.overlay.ArOverlay` at 30 Hz (no UDP): each circles the arena centre at its own
radius and speed, nose along its path. The shipped arena is used with the projector size replaced by
``--width``/``--height`` (tags scaled to fit; the floor size is unchanged) and its modulation profile by
``--profile``. Prints one JSON object; ``criteria`` checks the targets (>= 60 output frames/s, no missed
deadline, start-up within 5 s).

Content (``--content``): ``photos`` (default) is a video this script makes once (kept in
``benchmarks/.cache/``) from :class:`~ipt.sender.photos.PanningPhotoScene` with a seed nothing else uses:
1280x720 at 30 fps, panning 3-10 px a frame over photographs, fractal terrain, dead leaves, clouds and
colour bars with grey ramps, a cut every 2.5 s, so it is decoded, resized to the projector and re-timed
like a user's video. It is H.264 (libx264, CRF 18, as a user's video usually comes: 3 ms a frame to
decode here). ``photos-ffv1`` is the same frames lossless (FFV1), what this benchmark used before: its
frames are 1 MB each and take 67 ms of processor time each to decode here, more than one core gives at
30 fps, so no player could show it on time on this machine and the sender misses deadlines waiting for
its content thread. ``map`` is the generated map app; anything else is a video file or image folder.

``work_p50_ms``/``work_p99_ms`` are the render thread's time per output frame (at the first output frame
of an input frame: the overlay and both phases; the second reuses them); ``content_*`` is the content
thread's time per input frame (the map app's frame), made ahead in parallel. The ``load_avg`` fields say
how busy the machine was.

    ./dev run python benchmarks/sender.py                                  # 1920x2160, 1200 frames, photos
    ./dev run python benchmarks/sender.py --content map --seconds 60
    ./dev run python benchmarks/sender.py --width 960 --height 1080 --seconds 30 --profile paper
    ./dev run python benchmarks/sender.py --threads 2      # the modulation pass split over two threads
    ./dev run python benchmarks/sender.py --content loop5s --frames 1200   # the loop seam (issue 33 item 5)
    ./dev run python benchmarks/sender.py --content photos24 --frames 600  # large photos (issue 33 item 3)
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import resource
import sys
import time
from pathlib import Path
from typing import Any

import av
import cv2
import numpy as np

from ipt.config.models import MIN_TAG_SIZE_PX, ArenaConfig, load_arena_config, shipped_config_path
from ipt.fileio import atomic_path
from ipt.geometry import R_BODY_CAM_DOWNWARD, quat_wxyz_from_matrix, rot_z
from ipt.imageio import write_image
from ipt.protocol import PosePacket
from ipt.sender.content import GeneratedScene, VideoScene
from ipt.sender.display import NullSink
from ipt.sender.modulator import make_modulator
from ipt.sender.overlay import ArOverlay
from ipt.sender.photos import PanningPhotoScene
from ipt.sender.prefetch import PrefetchedVideo
from ipt.sender.server import run_sender
from ipt.tagmap import grid_tag_map
from ipt.videoio import FfvWriter

POSE_RATE_HZ = 30.0
CACHE = Path(__file__).resolve().parent / ".cache"
PHOTO_SEED = 19
"""The photographic video's seed: not the simulator's (0) nor any the modulator was looked at with."""


def process_age_s() -> float:
    """Seconds since this process started (Linux: /proc), NaN elsewhere."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime_s = float(Path("/proc/uptime").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return math.nan
    return uptime_s - start_ticks / os.sysconf("SC_CLK_TCK")


def photo_video(
    seconds: float = 20.0, width: int = 1280, height: int = 720, fps: int = 30, codec: str = "h264"
) -> Path:
    """The photographic content video (made once, then kept), H.264 or FFV1: see the module doc."""
    suffix = "mp4" if codec == "h264" else "mkv"
    path = CACHE / f"photos-seed{PHOTO_SEED}-{width}x{height}-{fps}fps-{seconds:g}s.{suffix}"
    if path.exists():
        return path
    CACHE.mkdir(parents=True, exist_ok=True)
    scene = PanningPhotoScene(width, height, seed=PHOTO_SEED)
    frames = round(seconds * fps)
    print(f"sender benchmark: making {path.name} (once)", file=sys.stderr)
    if codec != "h264":
        with FfvWriter(path, width, height, fps) as writer:
            for k in range(frames):
                writer.write(scene.frame(k, fps))
        return path
    with atomic_path(path) as tmp, av.open(str(tmp), mode="w", format="mp4") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        stream.options = {"crf": "18", "preset": "veryfast"}
        for k in range(frames):
            for packet in stream.encode(av.VideoFrame.from_ndarray(scene.frame(k, fps), format="rgb24")):
                container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    return path


def large_photos(count: int = 4, width: int = 6000, height: int = 4000) -> Path:
    """A folder of ``count`` 24-megapixel JPEGs (made once, then kept): the photographic scene's frames, enlarged,
    with grain (so that they cost what a camera's JPEG costs to decode)."""
    folder = CACHE / f"photos24-seed{PHOTO_SEED}-{count}x{width}x{height}"
    if folder.is_dir() and len(list(folder.glob("*.jpg"))) == count:
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    print(f"sender benchmark: making {folder.name} (once)", file=sys.stderr)
    scene = PanningPhotoScene(1280, 720, seed=PHOTO_SEED)
    rng = np.random.default_rng(PHOTO_SEED)
    for k in range(count):
        big = cv2.resize(scene.frame(k * 80, 30.0), (width, height), interpolation=cv2.INTER_CUBIC)
        grain = rng.normal(0.0, 6.0, (height, width, 1)).astype(np.float32)
        rgb = np.clip(big.astype(np.float32) + grain, 0, 255).astype(np.uint8)
        write_image(folder / f"photo{k}.jpg", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    return folder


def arena_for(width: int, height: int, profile: str | None = None) -> ArenaConfig:
    """The shipped arena at another projector size, with the tags scaled by the same factor."""
    data: dict[str, Any] = load_arena_config(shipped_config_path("arena.yaml")).model_dump()
    if profile is not None:
        data["modulation"]["profile"] = profile
    scale = min(width / data["projector"]["width_px"], height / data["projector"]["height_px"])
    data["projector"].update(width_px=width, height_px=height)
    tm = data["tag_map"]
    tm["tag_size_px"] = max(MIN_TAG_SIZE_PX, int(tm["tag_size_px"] * scale) // 8 * 8)
    # Tags keep 8 projector px per bit: on a small projector fewer of them fit, and a pad's small tags none.
    quiet_size = tm["tag_size_px"] * 10 // 8
    tm.update(cols=min(tm["cols"], width // quiet_size), rows=min(tm["rows"], height // quiet_size))
    if scale < 1:
        tm["pads"] = []
    return ArenaConfig.model_validate(data)


async def feed_vehicles(ar: ArOverlay, count: int, stop: asyncio.Event) -> int:
    """Update ``count`` vehicles at POSE_RATE_HZ until ``stop``; returns the number of poses fed."""
    fed, seq, t0 = 0, 0, time.monotonic()
    while not stop.is_set():
        t = time.monotonic() - t0
        seq += 1
        for k in range(count):
            radius = 0.25 + 0.1 * k
            omega = (0.4 + 0.1 * k) * (1 if k % 2 else -1)
            angle = omega * t + k * 2 * math.pi / count
            yaw = angle + math.copysign(math.pi / 2, omega)  # along the path
            quat = quat_wxyz_from_matrix(rot_z(yaw) @ R_BODY_CAM_DOWNWARD)
            position = (radius * math.cos(angle), radius * math.sin(angle), 1.2)
            ar.update(PosePacket(k + 1, seq, int(t * 1e6), position, tuple(quat.tolist())), time.monotonic())
            fed += 1
        await asyncio.sleep(1 / POSE_RATE_HZ)
    return fed


async def bench(
    width: int,
    height: int,
    seconds: float | None,
    frames: int | None,
    vehicles: int,
    profile: str | None,
    threads: int,
    content: str,
    lookahead: int = 2,
    player: str = "prefetch",
) -> dict[str, Any]:
    made = {"photos": "h264", "photos-ffv1": "ffv1"}
    t_video = time.monotonic()
    path: Path | str
    if content == "loop5s":
        path = photo_video(seconds=5.0, width=1920, height=2160, fps=30, codec="h264")
    elif content == "photos24":
        path = large_photos()
    else:
        path = photo_video(codec=made[content]) if content in made else content  # made once: not the sender's start
    video_s = time.monotonic() - t_video
    t0 = time.monotonic()
    arena = arena_for(width, height, profile)
    ar = ArOverlay(arena)
    scene: GeneratedScene | VideoScene | PrefetchedVideo
    if content == "map":
        scene = GeneratedScene(width, height)
    elif player == "videoscene":  # as ipt-sender played a video up to 5def445: decoded in the content thread
        scene = VideoScene(path, width, height, cache_bytes=0)
    else:
        scene = PrefetchedVideo(path, width, height)  # as ipt-sender plays a video: decoded ahead
    input_rate_hz = getattr(scene, "fps", None) or arena.modulation.input_rate_hz
    mod = arena.modulation
    modulator = make_modulator(
        mod.profile, grid_tag_map(arena).render_mask(), mod.delta_l, threads, mod.clip_allowance_l8
    )
    modulator_s = time.monotonic() - t0
    stop = asyncio.Event()
    feeder = asyncio.create_task(feed_vehicles(ar, vehicles, stop))
    load_before = os.getloadavg()
    if seconds is not None:
        asyncio.get_running_loop().call_later(seconds, stop.set)
    lines: list[str] = []

    def log(text: str) -> None:
        lines.append(text)
        print(text, file=sys.stderr, flush=True)

    try:
        stats = await run_sender(
            arena,
            NullSink(),
            scene,
            frames=frames,
            listen=None,
            overlay=ar,
            stats_every_s=5.0,
            stop=stop,
            modulator=modulator,
            input_rate_hz=input_rate_hz,
            log=log,
            lookahead=lookahead,
        )
    finally:
        stop.set()
        fed = await feeder
        for thing in (modulator, scene):
            close = getattr(thing, "close", None)
            if close is not None:
                close()
    # The first frame was shown startup_s after run_sender began, which was modulator_s after t0; the time
    # spent making the benchmark's video (on its first run) is not the sender's.
    first_frame_age_s = process_age_s() - (time.monotonic() - t0) - video_s + modulator_s + stats.startup_s
    result = stats.to_dict()
    return {
        "benchmark": "sender",
        "profile": mod.profile,
        "clip_allowance_l8": mod.clip_allowance_l8,
        "delta_l": mod.delta_l,
        "modulator_threads": threads,
        "lookahead": lookahead,
        "content": {
            "map": "generated map app",
            "photos": f"photographic video (seed {PHOTO_SEED}, H.264)",
            "photos-ffv1": f"photographic video (seed {PHOTO_SEED}, FFV1)",
            "loop5s": f"5 s 1920x2160 30 fps H.264 photographic clip (seed {PHOTO_SEED}), looped",
            "photos24": "four 24-megapixel (6000x4000) JPEG photos, a folder",
        }.get(content, content),
        "player": player if content != "map" else None,
        "content_waits": getattr(scene, "waits", None),
        "content_notes": [line for line in lines if "cannot keep up" in line or "skipped" in line],
        "vehicles": vehicles,
        "vehicles_drawn": stats.vehicles,
        "poses_fed": fed,
        "modulator_s": round(modulator_s, 3),
        "colour_table": [line for line in lines if "colour table" in line],
        "first_frame_after_process_start_s": round(first_frame_age_s, 3),
        **result,
        "criteria": {
            "fps_ge_60": result["frames_per_s"] >= 60.0 * (1 - 1e-3),
            "no_missed_deadline": result["missed_deadlines"] == 0,
            "startup_le_5s": first_frame_age_s <= 5.0,
        },
        "max_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "cpu_count": os.cpu_count(),
        "load_avg_1min_before": round(load_before[0], 2),
        "load_avg_1min_after": round(os.getloadavg()[0], 2),
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=2160)
    p.add_argument("--frames", type=int, default=1200, help="output frames to show (default 1200: 20 s)")
    p.add_argument("--seconds", type=float, help="run this long instead of --frames")
    p.add_argument("--vehicles", type=int, default=8)
    p.add_argument("--profile", choices=("ipt", "paper"), help="modulation profile (default: the shipped arena's)")
    p.add_argument("--threads", type=int, default=1, help="threads sharing each ipt modulation pass (default 1)")
    p.add_argument(
        "--content",
        default="photos",
        help="photos (default: the photographic video, H.264, made once), photos-ffv1 (the same frames lossless: "
        "slower to decode than real time here), loop5s (a 5 s 1920x2160 H.264 clip: a seam every 5 s), photos24 "
        "(four 24-megapixel JPEGs), map (the generated map app), or a video file or image folder",
    )
    p.add_argument(
        "--player",
        choices=("prefetch", "videoscene"),
        default="prefetch",
        help="prefetch (default: as ipt-sender plays a video, decoded ahead in a thread of its own) or videoscene "
        "(decoded in the content thread, one input frame ahead, as up to 5def445)",
    )
    p.add_argument(
        "--warmup",
        type=float,
        default=0.0,
        metavar="S",
        help="run S seconds first, in the same process, and report only the run after it (the warm-up is "
        "reported with its own missed count)",
    )
    p.add_argument(
        "--lookahead", type=int, default=2, help="frames the render thread may work ahead of the clock (default 2)"
    )
    args = p.parse_args()

    async def runs() -> dict[str, Any]:
        warm: dict[str, Any] | None = None
        common = (args.vehicles, args.profile, args.threads, args.content, args.lookahead, args.player)
        if args.warmup > 0:
            warm = await bench(args.width, args.height, args.warmup, None, *common)
        frames = None if args.seconds is not None else args.frames
        out = await bench(args.width, args.height, args.seconds, frames, *common)
        if warm is not None:
            out["warmup"] = {k: warm[k] for k in ("seconds", "output_frames", "missed_deadlines", "late_frames")}
        return out

    try:
        import uvloop
    except ImportError:
        result = asyncio.run(runs())
    else:
        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            result = runner.run(runs())
    json.dump(result, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
