"""Invisibility and camera-side signal of every modulation profile, on two contents, as JSON.

For each content, ``--pairs`` input frames are modulated by each profile at the shipped arena's size and
ΔL, and :mod:`ipt.invisibility` measures the fused image (the linear-light mean of the two phases)
against the input, as CIEDE2000 over tag and non-tag pixels, and the camera-side signal. The contents:

- ``demo``: the built-in generated map app (what ``ipt demo`` and ``ipt-sender`` show);
- ``independent``: a video made here from the photograph and the terrain model that matplotlib ships as
  sample data (a slow pan and zoom over each, one above the other), at 1280x720 and 25 fps, so it is
  also resized and re-timed on the way in. ``--keep DIR`` keeps it, so that
  ``ipt invisibility --video DIR/independent.mkv`` reproduces the figures.
- ``photos``: the photographic video ``benchmarks/sender.py`` runs the sender on (made once from
  :class:`~ipt.sender.photos.PanningPhotoScene` with a seed nothing else uses: photographs, terrain, dead
  leaves, clouds, colour bars and grey ramps panning 3-10 px a frame, 1280x720 at 30 fps, 20 s).

Each profile also gets the saccade figure (the two phases seen ``--saccade-px`` apart, as a moving eye
sees them; :mod:`ipt.invisibility`).

The ``ipt`` profile is measured as the shipped arena configures it (clip allowance 2.2: where the colour
leaves no room for the step, the fused colour may move by up to CIEDE2000 0.49, for signal there) and with
each ``--clip-allowance`` (``ipt@A``; the default ``ipt@0`` is exact everywhere). ``criteria`` checks the
issue's targets for each: fused CIEDE2000 over tag pixels p99 <= 0.5, non-tag pixels identical to the
input, signal >= 95 % of the paper profile's.

    ./dev run python benchmarks/invisibility.py [--pairs 10] [--delta-l 4] [--clip-allowance 0 2] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import matplotlib
import numpy as np
import numpy.typing as npt
from sender import PHOTO_SEED, photo_video  # the sender benchmark's content (this folder is on sys.path)

from ipt.config.models import load_arena_config, shipped_config_path
from ipt.imageio import read_image
from ipt.invisibility import SACCADE_PX, frame_indices, measure_scene
from ipt.sender.content import GeneratedScene, VideoScene
from ipt.videoio import FfvWriter

U8 = npt.NDArray[np.uint8]


def _sample(name: str) -> Path:
    return Path(matplotlib.get_data_path()) / "sample_data" / name


def _terrain_rgb() -> U8:
    """matplotlib's topobathy sample (elevation) through its 'terrain' colour map, as 8-bit RGB."""
    from matplotlib import colormaps

    with np.load(_sample("topobathy.npz")) as data:
        z = np.asarray(data["topo"], dtype=np.float64)
    z = (z - z.min()) / max(1e-9, float(np.ptp(z)))
    rgba = colormaps["terrain"](z)
    return np.asarray(np.rint(rgba[:, :, :3] * 255), dtype=np.uint8)


def make_independent_video(
    path: Path, seconds: float = 4.0, width: int = 1280, height: int = 720, fps: int = 25
) -> Path:
    """A natural-looking content video unlike the map app (see the module doc)."""
    photo = read_image(_sample("grace_hopper.jpg"), "rgb")
    terrain = _terrain_rgb()
    half = height // 2
    with FfvWriter(path, width, height, fps) as writer:
        for k in range(round(seconds * fps)):
            t = k / fps
            frame = np.empty((height, width, 3), np.uint8)
            for img, rows, phase in ((photo, slice(0, half), 0.0), (terrain, slice(half, height), 1.3)):
                h, w = img.shape[:2]
                zoom = 1.0 + 0.15 * (0.5 - 0.5 * math.cos(2 * math.pi * t / 8.0 + phase))
                cw, ch = w / zoom, min(h / zoom, (w / zoom) * half / width)
                cx = w / 2 + (w - cw) / 2 * math.sin(2 * math.pi * t / 11.0 + phase)
                cy = h / 2 + (h - ch) / 2 * math.sin(2 * math.pi * t / 7.0 + phase)
                sx, sy = width / cw, half / ch
                m = np.array([[sx, 0.0, -(cx - cw / 2) * sx], [0.0, sy, -(cy - ch / 2) * sy]])
                frame[rows] = cv2.warpAffine(
                    img, m, (width, half), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
                )
            writer.write(frame)
    return path


def _criteria(profiles: dict[str, Any]) -> dict[str, Any]:
    paper = profiles.get("paper")
    out: dict[str, Any] = {}
    for name, fig in profiles.items():
        if fig["profile"] != "ipt":
            continue
        checks = {
            "tag_p99_le_0.5": fig["fused_ciede2000_tag"]["p99"] <= 0.5,
            "non_tag_identical": fig["non_tag_identical_fraction"] == 1.0,
        }
        if paper is not None:
            checks["signal_ge_95pct_of_paper"] = fig["signal_l8"] >= 0.95 * paper["signal_l8"]
        out[name] = checks
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--pairs", type=int, default=10, help="input frames per content (default 10)")
    p.add_argument("--delta-l", type=float, help="ΔL in 8-bit L units (default: the shipped arena's, 4)")
    p.add_argument("--keep", type=Path, help="keep the independent content video in this folder")
    p.add_argument(
        "--clip-allowance",
        type=float,
        nargs="*",
        default=[0.0],
        metavar="A",
        help="also measure ipt with these clip allowances (default 0: exact everywhere, beside the arena's 2)",
    )
    p.add_argument("--saccade-px", type=int, default=SACCADE_PX, help="saccade figure: phases this far apart")
    p.add_argument("--full", action="store_true", help="keep each pair's own figures in the output")
    args = p.parse_args()
    arena = load_arena_config(shipped_config_path("arena.yaml"))
    w, h = arena.projector.width_px, arena.projector.height_px
    rate = arena.modulation.input_rate_hz
    results: dict[str, Any] = {"benchmark": "invisibility", "arena": "shipped arena.yaml"}
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep if args.keep is not None else Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        video = make_independent_video(folder / "independent.mkv")
        contents: list[tuple[str, Any, list[int], float]] = [
            ("demo", GeneratedScene(w, h), frame_indices(args.pairs, None, round(rate)), rate),
        ]
        independent = VideoScene(video, w, h)
        fps = independent.fps or 25.0
        contents.append(("independent", independent, frame_indices(args.pairs, round(4.0 * fps), 1), fps))
        photos = VideoScene(photo_video(), w, h)
        contents.append(("photos", photos, frame_indices(args.pairs, round(20.0 * 30), 1), photos.fps or 30.0))
        for name, scene, indices, rate_hz in contents:
            t0 = time.perf_counter()
            r = measure_scene(
                arena,
                scene,
                indices,
                rate_hz,
                delta_l=args.delta_l,
                clip_allowances_l8=args.clip_allowance,
                saccade_px=args.saccade_px,
            )
            if not args.full:
                for prof in r["profiles"].values():
                    prof.pop("pairs", None)
            r["criteria"] = _criteria(r["profiles"])
            r["input_frames"] = indices
            r["seconds"] = round(time.perf_counter() - t0, 1)
            if name == "photos":
                r["content"] = f"photographic video (seed {PHOTO_SEED})"
            results[name] = r
        independent.close()
        photos.close()
    json.dump(results, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
