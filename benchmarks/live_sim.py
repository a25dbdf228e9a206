"""A live camera through the pipeline on a slower computer: the daemon's frame-taking rule on processing times measured
here and multiplied by ``--slow``, as JSON (poses a second, capture -> result latency, every pose against the truth).

    python benchmarks/live_sim.py --video DIR [--slow 3.5] [--rounds 3]

DIR holds camera.yaml, groundtruth.tum, the frames (``bmp/`` as ``ipt sim --frames-dir`` writes them, else
frames.mkv) and arena.yaml (else the shipped arena), as ``ipt sim`` writes them. The model, round by round:

- the camera delivers frame k at k / fps; the worker, when free, takes the newest frames it has not taken, at most
  :data:`ipt.receiver.liverun.LIVE_RUN_FRAMES` (the daemon's live queue keeps that many and drops the older ones),
  and of those, when frames were dropped and pairs pay (:func:`ipt.receiver.liverun.pairs_pay`: the content
  moves, or the stretched processing times are slower than the camera), the ones
  :func:`ipt.receiver.liverun.pick_run` picks with the pipeline's phase clock (a + and − frame of one video
  frame), waiting for them: the daemon's own :class:`ipt.receiver.liverun.LivePicker`, told after each frame
  and asked after a stall; after frames were dropped it first calls :meth:`Pipeline.finish_before`, as the
  daemon does;
- each frame of the run is processed in order, with its wait when the run was handed over (the pipeline's live
  rule, :data:`ipt.receiver.core.sparsestage.LIVE_LATE_US`, reads it; ``--every-late``: none, a recording's way),
  and takes the wall-clock time it took here (the AprilTag helper process's time included when pinned to one
  core: ``taskset -c 0``) times ``--slow``;
- a result's latency is the (virtual) time it came out minus its frame's capture time.

What the pipeline does depends only on the frames it is given, so a slower computer is modelled by the clock alone:
``--slow 3.5`` a Raspberry Pi 4 core, ``--slow 1.5`` a Pi 5 core (docs/receiver-cores.md's scaling). Not modelled:
the daemon's event loop and thread hand-offs and the UDP send (a few tenths of a millisecond a frame here), the
capture thread, a busy machine's other work. ``--slow 1`` on an idle core gives figures close to
``benchmarks/daemon.py --modes camera``'s (which runs the real daemon, with its noise) and is deterministic in its
policy, so two rounds differ only by the measured times. ``benchmarks/slow_receiver.py`` replays the same rule with a
fixed cost per frame (k camera frame times each, no clock: the same figures on any machine); here each frame costs
what it cost, so an acquisition's or a restart's extra cost, the catching up after it, and the latency are in.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ipt.config.models import shipped_config_path
from ipt.config.receiver import ReceiverConfig
from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.pipeline import Pipeline
from ipt.receiver.detect.detector import pipeline_detector
from ipt.receiver.liverun import LIVE_RUN_FRAMES, LivePicker
from ipt.receiver.options import load_setup
from ipt.tum import Trajectory, read_tum
from ipt.videoio import open_frames


def _frames(folder: Path) -> list[Any]:
    bmp = folder / "bmp"
    if bmp.is_dir():
        with open_frames(bmp, skip_bad=True, grey=True) as src:
            return list(src)
    with open_frames(folder / "frames.mkv") as src:
        return list(src)


def _pipeline(folder: Path) -> Pipeline:
    arena = folder / "arena.yaml"
    cfg = ReceiverConfig(
        arena=arena if arena.is_file() else shipped_config_path("arena.yaml"),
        camera=folder / "camera.yaml",
        send=["127.0.0.1:9"],  # (nothing is sent: the config wants a target)
    )
    setup = load_setup(cfg)
    detector = pipeline_detector(cfg.pipeline.detector, setup.tag_map.by_id)
    pipeline = Pipeline(setup.tag_map, setup.camera, cfg.pipeline, setup.arena.projector.rate_hz, detector)
    pipeline.acquisition.live = True  # as the daemon sets it for a live camera
    return pipeline


class _Held(NamedTuple):
    """A frame in the modelled live queue (what :class:`~ipt.receiver.liverun.LivePicker` reads of one)."""

    index: int
    capture_time_us: int


def live_round(
    pipeline: Pipeline, frames: list[Any], fps: float, slow: float, every_late: bool = False
) -> dict[int, tuple[float, FrameResult]]:
    """Each frame's result with the virtual time it came out (s), under the daemon's live rule; each frame handed over
    with its wait (virtual time minus capture), as the daemon's are, unless ``every_late``."""
    out: dict[int, tuple[float, FrameResult]] = {}
    now_s, last, n = 0.0, -1, len(frames)
    picker = LivePicker()  # the daemon's own: told after each frame, asked after a stall

    def held(k: int) -> _Held:
        return _Held(k, round(k * 1e6 / fps))

    def took(t0: float, results: list[FrameResult]) -> None:
        nonlocal now_s
        now_s += (time.perf_counter() - t0) * slow
        for r in results:
            out[r.index] = (now_s, r)

    async def more(_timeout_s: float) -> list[_Held]:
        """The next frame, when the camera delivers it (the model's camera never stalls), or [] at the end."""
        nonlocal now_s, newest
        if newest + 1 >= n:
            return []
        newest += 1
        now_s = max(now_s, newest / fps)
        return [held(newest)]

    while last < n - 1:
        newest = min(int(np.floor(now_s * fps + 1e-9)), n - 1)
        if newest <= last:  # the worker waits for the next frame
            now_s = (last + 1) / fps
            continue
        run = list(range(max(last + 1, newest - LIVE_RUN_FRAMES + 1), newest + 1))
        if last >= 0 and run[0] > last + 1:  # behind: the daemon's pick among the frames held, waiting as it does
            run = [f.index for f in asyncio.run(picker.pick([held(k) for k in run], more))]
        if run[0] > last + 1 and last >= 0:  # frames were dropped: what waited for them comes out first
            t0 = time.perf_counter()
            took(t0, pipeline.finish_before(round(run[0] * 1e6 / fps)))
        for k in run:
            t0 = time.perf_counter()
            waited_us = None if every_late else max(round((now_s - k / fps) * 1e6), 0)  # (the daemon's, at hand-over)
            took(t0, pipeline.process(k, frames[k], round(k * 1e6 / fps), waited_us))
            picker.note(pipeline.live_hints(), (time.perf_counter() - t0) * slow)
        last = run[-1]
    t0 = time.perf_counter()
    took(t0, pipeline.flush())
    return out


def _figures(out: dict[int, tuple[float, FrameResult]], n: int, fps: float, truth: Trajectory) -> dict[str, Any]:
    posed, latency_ms, error_mm = [], [], []
    for k in sorted(out):
        at_s, r = out[k]
        if r.pose is None:
            continue
        posed.append(k)
        latency_ms.append(1e3 * (at_s - k / fps))
        i = int(np.argmin(np.abs(truth.times_s - r.capture_time_us * 1e-6)))
        error_mm.append(1e3 * float(np.linalg.norm(truth.positions_m[i] - r.pose.position_m)))
    fig: dict[str, Any] = {"frames": n, "frames_processed": len(out), "poses": len(posed)}
    fig["poses_per_s"] = round(len(posed) * fps / n, 1)
    fig["first_pose_frame"] = posed[0] if posed else None
    if latency_ms:
        lat, err = np.array(latency_ms), np.array(error_mm)
        fig["latency_ms"] = {
            "p50": round(float(np.percentile(lat, 50)), 1),
            "p99": round(float(np.percentile(lat, 99)), 1),
            "max": round(float(lat.max()), 1),
            "over_30ms": int((lat > 30).sum()),
        }
        fig["error_mm"] = {
            "median": round(float(np.median(err)), 1),
            "p99": round(float(np.percentile(err, 99)), 1),
            "max": round(float(err.max()), 1),
            "over_50mm": int((err > 50).sum()),
            "over_100mm": int((err > 100).sum()),
        }
    return fig


def one_round(folder: Path, fps: float, slow: float, every_late: bool = False) -> dict[str, Any]:
    """One round in this process: a fresh pipeline (its kernels loaded from numba's cache as a daemon's are);
    ``every_late``: frames the chain gave up on take the dense way at any age (as before stop 59)."""
    frames = _frames(folder)
    pipeline = _pipeline(folder)
    try:
        out = live_round(pipeline, frames, fps, slow, every_late)
    finally:
        pipeline.close()
    return _figures(out, len(frames), fps, read_tum(folder / "groundtruth.tum"))


def _medians(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    if not all("latency_ms" in r for r in rounds):
        return {}
    picks = {
        "poses_per_s": ("poses_per_s", None),
        "latency_p50_ms": ("latency_ms", "p50"),
        "latency_p99_ms": ("latency_ms", "p99"),
        "latency_over_30ms": ("latency_ms", "over_30ms"),
        "error_max_mm": ("error_mm", "max"),
        "error_over_50mm": ("error_mm", "over_50mm"),
    }
    out = {}
    for name, (key, sub) in picks.items():
        values = [float(r[key] if sub is None else r[key][sub]) for r in rounds]
        out[name] = round(statistics.median(values), 1)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--video", type=Path, required=True, metavar="DIR", help="a rendered flight (ipt sim)")
    parser.add_argument("--slow", type=float, default=1.0, help="processing times multiplied by this (default 1)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, each in a fresh process (default 3)")
    parser.add_argument("--fps", type=float, default=120.0, help="the camera's frame rate (default 120)")
    parser.add_argument(
        "--every-late",
        action="store_true",
        help="frames the sparse chain gave up on take the dense way however old (a recording's rule; the daemon's live "
        "rule gives them up past ipt.receiver.core.sparsestage.LIVE_LATE_US): to compare the two",
    )
    parser.add_argument("--one-round", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.slow <= 0 or args.rounds < 1 or args.fps <= 0:
        parser.error("--slow and --fps must be positive, --rounds at least 1")
    if not (args.video / "camera.yaml").is_file() or not (args.video / "groundtruth.tum").is_file():
        parser.error(f"{args.video}: no camera.yaml and groundtruth.tum (a folder ipt sim wrote)")
    if args.one_round:
        print(json.dumps(one_round(args.video, args.fps, args.slow, args.every_late)))
        return 0
    rounds = []
    cmd = [sys.executable, __file__, "--video", str(args.video), "--fps", str(args.fps), "--slow", str(args.slow)]
    cmd += ["--every-late"] if args.every_late else []
    for k in range(args.rounds):
        proc = subprocess.run([*cmd, "--one-round"], capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            raise SystemExit(f"live_sim: round {k + 1} failed:\n{proc.stderr[-2000:]}")
        rounds.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        print(f"live_sim: round {k + 1}/{args.rounds}: {rounds[-1]['poses_per_s']} poses/s", file=sys.stderr)
    report = {"flight": args.video.name, "slow": args.slow, "fps": args.fps, "every_late": args.every_late}
    report["rounds"] = rounds
    report.update(medians=_medians(rounds), loadavg=list(os.getloadavg()))
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
