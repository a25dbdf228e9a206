"""The scenario suite: every flight of benchmarks/flights/ through both receiver profiles, as JSON.

    python benchmarks/suite.py [--seconds S] [--only NAME,NAME] [--profiles ipt,paper] [--markdown FILE]

Each flight file is an ``ipt sim --sim-config`` file. It is rendered once (``ipt sim``'s renderer, into
``--cache``, default ``benchmarks/.cache/``) and kept under a hash of its settings, the arena, the length
and the simulator's source code, so a changed flight or renderer renders again and an unchanged one does
not. Each rendering is then replayed through each receiver profile, pinned to one core (the detector's
helper process too) with OpenCV on one thread, and scored against its ground truth:

- ``yield_pct``: poses per camera frame; ``yield_by_height_pct``: the same per band of true height;
  ``vertical_bands``: for flights that climb and descend, yield and MAE per band of true height on the way
  up and on the way down apart (``climb_0.5-0.8m``, ``descent_0.8-0.4m``);
- ``mae_mm``: X, Y, Z mean absolute error; ``tilt_mae_deg`` and ``yaw_mae_deg``; ``poses_over_10cm`` and
  the worst position error;
- ``rolling_shutter``: true when the receiver was told the camera has one (a flight whose camera reads
  its rows out over time: ``pose.track.rolling_shutter``, as a lab sets it for such a camera);
- ``frames_per_s``: frames over the pipeline thread's processor time on one core (decoding and the AprilTag
  helper's own time not counted: ``whole_process`` counts everything), and the
  per-stage times; ``reasons``: why frames gave no pose; ``ms_per_frame_by_outcome``: that time per frame
  for the frames posed, bridged, lost and dark;
- ``whole_process`` (unless ``--no-whole-process``): ``ipt-receiver replay`` of the rendering's frames as BMP
  images (written once into ``bmp/`` beside the rendering), a process pinned to core 0, its user + sys time by
  ``/usr/bin/time`` (the AprilTag helper process included) as ``frames_per_cpu_s``, the load average when it
  started, and the yield and errors of that run's own poses (issue 29's target 1), with the SHA-256 of its poses
  file (``poses_sha256``: two runs that wrote the same poses to the byte), told of a rolling shutter as the
  in-process run is (``replay --rolling-shutter``; ``rolling_shutter`` then true there too). It runs as the systemd unit
  runs the receiver: ``NUMBA_CACHE_DIR`` a folder of ``--cache`` filled by ``ipt-receiver warm`` first, so
  with the kernels built ahead of time where a C compiler is (``kernels`` says how they were loaded). The
  frames are read once before it (into the page cache: reading 2.6 GB of 1280×720 frames from the disk cost
  independent's replay 3.9 s of system time in one run, which no camera costs).

A flight with a keystoned projector (``keystone:``) is scored three ways: ``NAME (uncalibrated)`` with the
arena file's uniform layout, ``NAME (calibrated)`` with the arena ``ipt calibrate arena --points`` makes
from the rendering's ``survey.csv`` (its output is kept in the JSON), and ``NAME (flat)``: the same flight
rendered without the keystone. A flight of several projectors (``arena: {projectors: ...}``) also gets
``seam_mae_mm`` and ``seam_max_error_mm``: the error of the poses whose camera is within 0.25 m of a seam.

JSON goes to stdout (one object: every flight, every profile); a Markdown table of the same figures goes to
stderr at the end and, with ``--markdown``, to a file (the README's "How well it works" table).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import load_camera_info
from ipt.config.models import (
    PROFILES,
    ArenaConfig,
    PipelineConfig,
    load_arena_config,
    load_yaml_model,
    shipped_config_path,
)
from ipt.eval import evaluate
from ipt.receiver.core.pipeline import FrameResult, Pipeline
from ipt.receiver.detect.detector import pipeline_detector
from ipt.sim.arena import scene_for, true_arena
from ipt.sim.config import SimConfig, apply_arena_changes, describe_flight
from ipt.sim.run import simulate_to_folder
from ipt.tagmap import grid_tag_map, pixel_to_arena_m
from ipt.tum import Trajectory, read_tum
from ipt.videoio import open_frames

ROOT = Path(__file__).resolve().parents[1]
FLIGHTS = ROOT / "benchmarks" / "flights"
DEFAULT_CACHE = ROOT / "benchmarks" / ".cache"
#: The order of the table: the issue's flights first, then the others in name order.
ORDER = ("moving-content", "shadow-vibration", "realcam", "rolling", "fast", "takeoff", "smooth")
#: Bands of true camera height (m) for the per-height yield.
HEIGHT_BANDS_M = ((0.0, 0.4), (0.4, 0.7), (0.7, 1.2), (1.2, 1.7), (1.7, 2.2), (2.2, 10.0))
#: Sources whose change invalidates a cached rendering: what renders a flight (not the demo, its lock-step
#: loop or the simulated live camera, which make nothing the suite keeps).
RENDER_SOURCES = ("ipt/sim/__init__.py", "ipt/sim/arena.py", "ipt/sim/config.py", "ipt/sim/flight.py",
                  "ipt/sim/render.py", "ipt/sim/run.py", "ipt/sim/shadow.py", "ipt/sim/darkscene.py",
                  "ipt/sender/photos.py",
                  "ipt/sender/content.py", "ipt/sender/basemap.py", "ipt/sender/modulator.py",
                  "ipt/sender/pairs.py", "ipt/sender/framekernel.py", "ipt/sender/cielab.py",
                  "ipt/sender/colour.py", "ipt/tagmap.py", "ipt/videoio.py", "ipt/calib/floor.py")  # fmt: skip


def scenario_files(only: list[str] | None, folder: Path = FLIGHTS) -> list[Path]:
    files = {p.stem: p for p in sorted(folder.glob("*.yaml"))}
    if not files:
        raise SystemExit(f"suite: no flight files (*.yaml) in {folder}")
    if only:
        unknown = [n for n in only if n not in files]
        if unknown:
            raise SystemExit(f"suite: no flight {', '.join(unknown)} in {folder} (have {', '.join(files)})")
        return [files[n] for n in only]
    ordered = [n for n in ORDER if n in files] + [n for n in files if n not in ORDER]
    return [files[n] for n in ordered]


def _source_digest() -> str:
    h = hashlib.sha256()
    for rel in RENDER_SOURCES:
        path = ROOT / rel
        for f in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            h.update(f.relative_to(ROOT).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()


def flight_key(sim: SimConfig, arena: ArenaConfig, seconds: float, source_digest: str) -> str:
    text = json.dumps([sim.model_dump(mode="json"), arena.model_dump(mode="json"), seconds, source_digest])
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def render(name: str, sim: SimConfig, arena: ArenaConfig, seconds: float, cache: Path, digest: str) -> Path:
    """The flight's folder (frames.mkv, camera.yaml, groundtruth.tum), rendered now unless cached."""
    folder = cache / f"{name}-{flight_key(sim, arena, seconds, digest)}"
    if (folder / "groundtruth.tum").is_file() and (folder / "frames.mkv").is_file():
        return folder
    for old in cache.glob(f"{name}-*"):  # an older rendering of this flight: settings or code changed
        if old.name.rsplit("-", 1)[0] == name:  # not another flight whose name starts with this one's
            shutil.rmtree(old, ignore_errors=True)
    start = time.monotonic()
    print(f"suite: rendering {name} ({seconds:g} s): {describe_flight(sim)}", file=sys.stderr, flush=True)
    simulate_to_folder(arena, sim, scene_for(sim, arena), folder, seconds)
    print(f"suite: rendered {name} in {time.monotonic() - start:.0f} s", file=sys.stderr, flush=True)
    return folder


@contextlib.contextmanager
def one_core() -> Iterator[None]:
    """Pin this process (and what it starts meanwhile) to one core, OpenCV to one thread."""
    saved = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    if saved is not None:
        os.sched_setaffinity(0, {min(saved)})
    try:
        yield
    finally:
        cv2.setNumThreads(threads)
        if saved is not None:
            os.sched_setaffinity(0, saved)


SEAM_BAND_M = 0.25
"""Poses whose camera is within this of a seam between projectors (on the floor) count as across it: at
0.8 m the 640x360 camera sees about 0.55 x 0.3 m on either side of its centre."""


def seam_points_m(truth: ArenaConfig) -> npt.NDArray[np.float64] | None:
    """Points every few millimetres along the seams between projector tiles, on the floor where they truly
    land (the inner tile edges), or None for one projector."""
    if not truth.projectors or len(truth.projectors) < 2:
        return None
    pr, out = truth.projector, []
    for n, t in enumerate(truth.projectors):
        x0, y0, x1, y1 = t.x_px, t.y_px, t.x_px + t.width_px, t.y_px + t.height_px
        for a, b in (((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))):
            if (a[0] == b[0] and a[0] in (0, pr.width_px)) or (a[1] == b[1] and a[1] in (0, pr.height_px)):
                continue  # an edge of the canvas, not a seam
            for f in np.linspace(0, 1, 400):
                u, v = a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])
                out.append(pixel_to_arena_m(truth, u, v, n)[:2])
    return np.array(out) if out else None


def receiver_config(profile: str, rolling_shutter: bool, tracker: str | None = None) -> PipelineConfig:
    """The receiver's pipeline for ``profile``, told that the camera has a rolling shutter if it has one
    (``pose.track.rolling_shutter``, as a lab sets it for its camera; the ``paper`` profile has no such
    setting), with the ``ipt`` profile's ``tracker`` (dense or sparse; None: the profile's own)."""
    cfg = PipelineConfig.profile(profile)
    if profile == "ipt" and tracker is not None:
        cfg = cfg.model_copy(update={"tracker": tracker})
    return cfg.with_rolling_shutter() if rolling_shutter and profile == "ipt" else cfg


def score(
    folder: Path,
    arena: ArenaConfig,
    profile: str,
    seam_m: npt.NDArray[np.float64] | None = None,
    rolling_shutter: bool = False,
    tracker: str | None = None,
) -> dict[str, Any]:
    camera = load_camera_info(folder / "camera.yaml")
    truth = read_tum(folder / "groundtruth.tum")
    rate = 1.0 / float(np.median(np.diff(truth.times_s)))
    times, positions, quats, busy_s = [], [], [], 0.0
    with one_core():
        cfg = receiver_config(profile, rolling_shutter, tracker)
        tag_map = grid_tag_map(arena)
        detector = pipeline_detector(cfg.detector, tag_map.by_id)
        pipeline = Pipeline(tag_map, camera, cfg, arena.projector.rate_hz, detector)
        try:
            with open_frames(folder / "frames.mkv") as src:
                results, frame_s = [], []
                for k, frame in enumerate(src):
                    t_us = round(float(truth.times_s[k]) * 1e6) if k < len(truth) else round(k / rate * 1e6)
                    t0 = time.thread_time()
                    results += pipeline.process(k, frame, t_us)
                    frame_s.append(time.thread_time() - t0)
                    busy_s += frame_s[-1]
                results += pipeline.flush()
            for result in results:
                if result.pose is not None:
                    times.append(result.capture_time_us * 1e-6)
                    positions.append(result.pose.position_m)
                    quats.append(result.pose.quat_wxyz)
            frames = k + 1
        finally:
            pipeline.close()
    out: dict[str, Any] = {"frames": frames, "poses": len(times), "yield_pct": 100.0 * len(times) / frames}
    if cfg.pose.track.rolling_shutter:
        out["rolling_shutter"] = True
    if len(times):
        r = evaluate(truth, Trajectory.from_arrays(times, positions, quats))
        out.update(
            mae_mm=[round(1e3 * v, 2) for v in (r.mae_x_m, r.mae_y_m, r.mae_z_m)],
            tilt_mae_deg=round(r.mae_tilt_deg, 3),
            yaw_mae_deg=round(r.mae_yaw_deg, 3),
            poses_over_10cm=r.n_outliers,
            max_error_mm=round(1e3 * r.max_pos_err_m, 1),
        )
    else:
        out.update(mae_mm=None, tilt_mae_deg=None, yaw_mae_deg=None, poses_over_10cm=0, max_error_mm=None)
    if seam_m is not None and len(times):
        # The poses across a seam: the camera within SEAM_BAND_M of it (truth), their error alone.
        t_idx = np.searchsorted(np.round(truth.times_s, 6), np.round(np.array(times), 6))
        true_xy = truth.positions_m[t_idx, :2]
        near = np.min(np.linalg.norm(true_xy[:, None, :] - seam_m[None, :, :], axis=2), axis=1) <= SEAM_BAND_M
        err = np.abs(np.array(positions)[near] - truth.positions_m[t_idx][near])
        out["seam_poses"] = int(near.sum())
        out["seam_mae_mm"] = [round(1e3 * float(v), 2) for v in err.mean(axis=0)] if near.any() else None
        out["seam_max_error_mm"] = round(1e3 * float(np.linalg.norm(err, axis=1).max()), 1) if near.any() else None
    heights = truth.positions_m[:frames, 2]
    posed = np.isin(np.round(truth.times_s[:frames], 6), np.round(np.array(times), 6))
    bands = {}
    for lo, hi in HEIGHT_BANDS_M:
        inside = (heights >= lo) & (heights < hi)
        if inside.sum() >= 10:
            bands[f"{lo:g}-{hi:g}"] = round(100.0 * float(posed[inside].mean()), 1)
    out["yield_by_height_pct"] = bands
    phases = vertical_bands(truth, frames, times, positions)
    if phases:
        out["vertical_bands"] = phases
    out["frames_per_s"] = round(frames / busy_s, 1) if busy_s > 0 else None
    out["stage_ms_per_frame"] = {k: round(1e3 * v / frames, 3) for k, v in pipeline.stage_seconds.items()}
    out["reasons"] = dict(sorted(pipeline.reasons.items()))
    out["ms_per_frame_by_outcome"] = by_outcome(results, frame_s)
    return out


#: Bands of true height (m) scored apart on the way up and on the way down (issue 30: the climb from a
#: take-off spot and the descent through the same heights); overlapping on purpose.
VERTICAL_BANDS_M = ((0.25, 0.4), (0.4, 0.5), (0.5, 0.8), (0.4, 0.8), (0.8, 1.2), (1.2, 2.2))
#: Vertical speed (m/s, true) above which a frame counts as climbing or descending.
VERTICAL_SPEED_MPS = 0.05


def vertical_bands(
    truth: Trajectory, frames: int, times: list[float], positions: list[Any]
) -> dict[str, dict[str, Any]]:
    """Yield and X / Y / Z MAE per band of true height, climbing and descending apart
    (``climb_0.5-0.8m``, ``descent_0.8-0.4m``): for flights that go up and down (at least 10 frames in a
    band and direction)."""
    t_s, z = truth.times_s[:frames], truth.positions_m[:frames, 2]
    vz = np.gradient(z, t_s) if frames > 2 else np.zeros(frames)
    key = np.round(t_s, 6)
    posed_at = {round(float(t), 6): np.asarray(p, dtype=np.float64) for t, p in zip(times, positions, strict=True)}
    out: dict[str, dict[str, Any]] = {}
    for lo, hi in VERTICAL_BANDS_M:
        for name, moving in (("climb", vz > VERTICAL_SPEED_MPS), ("descent", vz < -VERTICAL_SPEED_MPS)):
            inside = np.flatnonzero(moving & (z >= lo) & (z < hi))
            if len(inside) < 10:
                continue
            errors = [
                np.abs(posed_at[k] - truth.positions_m[i])
                for i, k in zip(inside, key[inside], strict=True)
                if k in posed_at
            ]
            band = f"{name}_{lo:g}-{hi:g}m" if name == "climb" else f"{name}_{hi:g}-{lo:g}m"
            out[band] = {
                "frames": len(inside),
                "yield_pct": round(100.0 * len(errors) / len(inside), 1),
                "mae_mm": [round(1e3 * float(v), 2) for v in np.mean(errors, axis=0)] if errors else None,
            }
    return out


#: Reasons of frames the pipeline turned away before any pairing (:mod:`ipt.receiver.core.framecheck`).
DARK_REASONS = ("dark", "saturated", "bad_frame", "wrong_size")


def outcome(result: FrameResult) -> str:
    """posed (a pose from a pair: the track or AprilTag), bridged (from the bridge), dark (turned away: no
    signal, or not an image of the camera), lost (no pose otherwise)."""
    if result.pose is not None:
        return "bridged" if result.method == "bridge" else "posed"
    return "dark" if result.reason in DARK_REASONS else "lost"


def by_outcome(results: list[FrameResult], frame_s: list[float]) -> dict[str, dict[str, float]]:
    """Pipeline time per frame by its outcome: a call of ``process`` for frame k is charged to frame k (its
    pairs with earlier frames, and the bridges and finishing of earlier frames it triggers)."""
    spent: dict[str, list[float]] = {}
    for r in results:
        if r.index < len(frame_s):
            spent.setdefault(outcome(r), []).append(frame_s[r.index])
    return {
        name: {
            "frames": len(v),
            "ms_mean": round(1e3 * float(np.mean(v)), 2),
            "ms_p90": round(1e3 * float(np.percentile(v, 90)), 2),
        }
        for name, v in sorted(spent.items())
    }


def frames_folder(folder: Path) -> Path:
    """The rendering's frames as a folder of BMP images (``bmp/`` beside ``frames.mkv``), written once: what the
    whole-process replay reads, so that decoding costs it next to nothing."""
    out, done = folder / "bmp", folder / "bmp" / ".complete"
    if done.is_file():
        return out
    out.mkdir(exist_ok=True)
    with open_frames(folder / "frames.mkv") as src:
        for k, frame in enumerate(src):
            image = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_RGB2BGR)
            if not cv2.imwrite(str(out / f"{k:06d}.bmp"), image):
                raise SystemExit(f"suite: cannot write {out / f'{k:06d}.bmp'}")
    done.write_text("", encoding="utf-8")
    return out


_WARMED: set[Path] = set()


def receiver_command(receiver: Path | None) -> list[str]:
    """How to start ``ipt-receiver``: this environment's entry point, or the module for another checkout's."""
    entry = Path(sys.executable).with_name("ipt-receiver")
    return [str(entry)] if receiver is None and entry.is_file() else [sys.executable, "-m", "ipt.receiver.cli"]


def kernel_env(cache: Path, receiver: Path | None, command: list[str]) -> dict[str, str]:
    """The environment of a whole-process replay: as the systemd unit runs the receiver, ``NUMBA_CACHE_DIR``
    (a folder of ``cache`` per receiver checkout) filled by ``ipt-receiver warm`` first (numba's cache, and the
    kernels built ahead of time where a C compiler is), once per run of the suite."""
    tag = hashlib.sha256(str(receiver.resolve()).encode()).hexdigest()[:12] if receiver is not None else "this"
    kernels = (cache / "kernels" / tag).resolve()
    env = dict(os.environ, NUMBA_CACHE_DIR=str(kernels))
    if receiver is not None:
        env["PYTHONPATH"] = str(receiver)
    if kernels not in _WARMED:
        kernels.mkdir(parents=True, exist_ok=True)
        # (without PYTHONDONTWRITEBYTECODE: warm also compiles ipt's bytecode, as pip install does on a drone)
        warm_env = {k: v for k, v in env.items() if k != "PYTHONDONTWRITEBYTECODE"}
        done = subprocess.run([*command, "warm"], capture_output=True, text=True, timeout=1800, check=False,
                              env=warm_env, cwd=kernels)  # fmt: skip
        print(f"suite: {done.stdout.strip() or done.stderr.strip()[-500:]}", file=sys.stderr, flush=True)
        _WARMED.add(kernels)
    return env


def whole_process(
    folder: Path,
    arena_path: Path,
    profile: str,
    receiver: Path | None,
    cache: Path,
    tracker: str | None = None,
    rolling_shutter: bool = False,
) -> dict[str, Any]:
    """``ipt-receiver replay`` of the rendering's BMP frames as a process of its own pinned to core 0, its
    processor time (user + sys, the AprilTag helper process included) by ``/usr/bin/time``, and the yield and
    errors of the poses that run wrote. ``receiver``: another checkout's ``ipt`` to run instead (a baseline).
    ``rolling_shutter``: the replay is told of the camera's (``--rolling-shutter``, with the ipt profile, as the
    in-process run is; a baseline's replay is not: before stop 72 it had no such option). Its frame k is at k/fps,
    with the rate given as a user would (``--fps 120``, 119.88: the truth's times, whole microseconds, put it at
    120.0048), so its poses may differ a little from the in-process run's, which takes the truth's times. (Measured
    at stop 52: the same yields and errors to the digit on every flight of the suite and the held-out set but the
    two with a rolling shutter, whose replay was not told of it then.)"""
    told = rolling_shutter and profile == "ipt" and receiver is None
    truth = read_tum(folder / "groundtruth.tum")
    rate = 1.0 / float(np.median(np.diff(truth.times_s)))
    frames_dir = frames_folder(folder)
    command = receiver_command(receiver)
    env = kernel_env(cache, receiver, command)
    images = sorted(frames_dir.glob("*.bmp"))
    for image in images:  # into the page cache first: a camera's frames come from no disk
        image.read_bytes()
    with tempfile.TemporaryDirectory(prefix="ipt-suite-") as tmp:
        poses, timing = Path(tmp) / "poses.tum", Path(tmp) / "time.txt"
        cmd = ["taskset", "-c", "0", "/usr/bin/time", "-f", "%U %S", "-o", str(timing), *command, "replay",
               "--config", str(arena_path.resolve()), "--camera", str((folder / "camera.yaml").resolve()),
               "--video", str(frames_dir.resolve()), "--fps", f"{rate:.2f}", "--output", str(poses),
               "--profile", profile, *(["--tracker", tracker] if profile == "ipt" and tracker else []),
               *(["--rolling-shutter"] if told else [])]  # fmt: skip
        load = os.getloadavg()[0]
        # In a folder of its own: ``python -m`` puts the working directory first on the path, which in a checkout
        # would import that checkout's ipt instead of ``receiver``'s.
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=3600, check=False, env=env, cwd=tmp)
        if done.returncode != 0:
            raise SystemExit(f"suite: {' '.join(cmd)} failed: {done.stderr.strip()[-2000:]}")
        user_s, sys_s = (float(v) for v in timing.read_text(encoding="utf-8").split()[-2:])
        got, digest = read_tum(poses), hashlib.sha256(poses.read_bytes()).hexdigest()
    kernels_line = next((line for line in done.stdout.splitlines() if "kernels:" in line), "")
    frames = len(images)
    out: dict[str, Any] = {
        **({"rolling_shutter": True} if told else {}),
        "frames_per_cpu_s": round(frames / (user_s + sys_s), 1),
        "user_s": user_s,
        "sys_s": sys_s,
        "load_average": round(load, 2),
        "yield_pct": round(100.0 * len(got) / frames, 2),
        "kernels": kernels_line.split("kernels: ", 1)[-1],
        "poses_sha256": digest,
    }
    if len(got):
        r = evaluate(truth, got)
        out.update(
            mae_mm=[round(1e3 * v, 2) for v in (r.mae_x_m, r.mae_y_m, r.mae_z_m)],
            poses_over_10cm=r.n_outliers,
            max_error_mm=round(1e3 * r.max_pos_err_m, 1),
        )
    return out


def calibrate(folder: Path) -> tuple[ArenaConfig, list[str]]:
    """The flight's arena calibrated from its survey (``survey.csv``) by ``ipt calibrate arena --points`` run
    as a user would (a subprocess), and what it printed."""
    out = folder / "calibrated.yaml"
    cmd = [sys.executable, "-m", "ipt.cli", "calibrate", "arena", "--config", str(folder / "arena.yaml"),
           "--points", str(folder / "survey.csv"), "--output", str(out)]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    if done.returncode != 0:
        raise SystemExit(f"suite: {' '.join(cmd)} failed: {done.stderr.strip()}")
    return load_arena_config(out), done.stdout.splitlines()


def _cell_mm(v: list[float] | None) -> str:
    return "—" if v is None else " / ".join(f"{x:.1f}" for x in v)


def _seam(r: dict[str, Any]) -> str:
    if "seam_mae_mm" not in r:
        return ""
    mae, worst = _cell_mm(r["seam_mae_mm"]), r["seam_max_error_mm"]
    return f"; across the seam ({r['seam_poses']} poses): MAE {mae} mm, worst {worst} mm"


def _whole(r: dict[str, Any]) -> str:
    w = r.get("whole_process")
    if w is None:
        return ""
    return (
        f"; whole process {w['frames_per_cpu_s']} frames/processor-s (load {w['load_average']}), "
        f"yield {w['yield_pct']:.1f} %, MAE {_cell_mm(w.get('mae_mm'))} mm"
    )


def markdown(results: dict[str, Any]) -> str:
    lines = [
        "| flight | profile | yield | X / Y / Z MAE (mm) | tilt / yaw MAE | poses > 10 cm (worst) "
        "| frames/s (1 core) | whole process frames/processor-s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, flight in results["flights"].items():
        for profile, r in flight["profiles"].items():
            angles = "—" if r["tilt_mae_deg"] is None else f"{r['tilt_mae_deg']:.2f}° / {r['yaw_mae_deg']:.2f}°"
            worst = "—" if r["max_error_mm"] is None else f"{r['max_error_mm']:.0f} mm"
            lines.append(
                f"| {name} | `{profile}` | {r['yield_pct']:.1f} % | {_cell_mm(r['mae_mm'])} | {angles} | "
                f"{r['poses_over_10cm']} ({worst}) | {r['frames_per_s']:.0f} | "
                f"{r['whole_process']['frames_per_cpu_s'] if 'whole_process' in r else '—'} |"
            )
    banded = [
        f"- {name} / `{profile}` by true height: "
        + ", ".join(f"{k} m {v:.1f} %" for k, v in r["yield_by_height_pct"].items())
        for name, flight in results["flights"].items()
        for profile, r in flight["profiles"].items()
        if len(r["yield_by_height_pct"]) > 1
    ]
    return "\n".join(lines) + "\n" + ("\n" + "\n".join(banded) + "\n" if banded else "")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seconds", type=float, default=8.0, help="length of each flight (default 8)")
    p.add_argument(
        "--flights",
        type=Path,
        default=FLIGHTS,
        help="folder of flight files (default benchmarks/flights; benchmarks/heldout: flights the receiver was "
        "never tuned on)",
    )
    p.add_argument("--only", help="comma-separated flight names (default: every file in the --flights folder)")
    p.add_argument("--profiles", default=",".join(PROFILES), help="comma-separated receiver profiles")
    p.add_argument(
        "--arena", type=Path, help="arena YAML the flights' changes apply to (default: the shipped one, with its pad)"
    )
    p.add_argument("--cache", type=Path, default=DEFAULT_CACHE, help="where renderings are kept")
    p.add_argument("--markdown", type=Path, help="also write the Markdown table here")
    p.add_argument(
        "--no-whole-process",
        action="store_true",
        help="skip the whole-process replay (ipt-receiver replay of BMP frames on core 0, timed by /usr/bin/time)",
    )
    p.add_argument(
        "--receiver",
        type=Path,
        help="run the whole-process replay with the ipt package of this checkout (PYTHONPATH), e.g. a baseline",
    )
    p.add_argument(
        "--tracker",
        choices=("dense", "sparse"),
        help="the ipt profile's tracker (default: the profile's own, sparse)",
    )
    args = p.parse_args()
    if not 0 < args.seconds <= 600:
        print(f"suite: --seconds must be in (0, 600], got {args.seconds:g}", file=sys.stderr)
        return 2
    profiles = [s for s in args.profiles.split(",") if s]
    if not profiles or any(s not in PROFILES for s in profiles):
        print(f"suite: --profiles must name some of {', '.join(PROFILES)}", file=sys.stderr)
        return 2
    base = load_arena_config(args.arena or shipped_config_path("arena.yaml"))
    args.cache.mkdir(parents=True, exist_ok=True)
    digest = _source_digest()
    results: dict[str, Any] = {"seconds": args.seconds, "tracker": args.tracker or "profile", "flights": {}}
    for path in scenario_files(args.only.split(",") if args.only else None, args.flights):
        sim = load_yaml_model(path, SimConfig)
        arena = apply_arena_changes(base, sim.arena)
        folder = render(path.stem, sim, arena, args.seconds, args.cache, digest)
        flight: dict[str, Any] = {"description": sim.description or describe_flight(sim), "profiles": {}}
        seam = seam_points_m(true_arena(arena, sim))
        for profile in profiles:
            start = time.monotonic()
            flight["profiles"][profile] = score(folder, arena, profile, seam, sim.camera.readout_ms > 0, args.tracker)
            r = flight["profiles"][profile]
            if not args.no_whole_process:
                r["whole_process"] = whole_process(
                    folder, folder / "arena.yaml", profile, args.receiver, args.cache, args.tracker,
                    sim.camera.readout_ms > 0,
                )  # fmt: skip
            print(
                f"suite: {path.stem} / {profile}: yield {r['yield_pct']:.1f} %, MAE {_cell_mm(r['mae_mm'])} mm, "
                f"{r['frames_per_s']} frames/s{_whole(r)} ({time.monotonic() - start:.0f} s){_seam(r)}",
                file=sys.stderr,
                flush=True,
            )
            for band, v in r.get("vertical_bands", {}).items():
                mae = _cell_mm(v["mae_mm"])
                print(f"suite: {path.stem} / {profile}: {band}: yield {v['yield_pct']:.1f} % of {v['frames']}, "
                      f"MAE {mae} mm", file=sys.stderr, flush=True)  # fmt: skip
            if len(r["yield_by_height_pct"]) > 1:  # a flight through several heights (take-off): each band
                bands = ", ".join(f"{k} m {v:.1f} %" for k, v in r["yield_by_height_pct"].items())
                print(f"suite: {path.stem} / {profile}: yield by true height: {bands}", file=sys.stderr, flush=True)
        results["flights"][path.stem] = flight
        if sim.keystone is not None:
            # The same rendering scored with the arena calibrated from its survey (the row above is the
            # uncalibrated receiver), and the same flight without the keystone, for the yield to match.
            calibrated, said = calibrate(folder)
            flight["description"] += " — uncalibrated: the receiver uses the arena file's uniform layout"
            results["flights"][f"{path.stem} (uncalibrated)"] = results["flights"].pop(path.stem)
            flat_sim = sim.model_copy(update={"keystone": None})
            flat = render(f"{path.stem}.flat", flat_sim, arena, args.seconds, args.cache, digest)
            for name, where, scored_arena, desc in (
                (f"{path.stem} (calibrated)", folder, calibrated, "calibrated by ipt calibrate arena --points"),
                (f"{path.stem} (flat)", flat, arena, "the same flight without the keystone"),
            ):
                entry: dict[str, Any] = {"description": f"{sim.description} — {desc}", "profiles": {}}
                if where is folder:
                    entry["calibration"] = said
                for profile in profiles:
                    entry["profiles"][profile] = r = score(
                        where, scored_arena, profile, seam, sim.camera.readout_ms > 0, args.tracker
                    )
                    if not args.no_whole_process:
                        arena_yaml = folder / "calibrated.yaml" if where is folder else where / "arena.yaml"
                        r["whole_process"] = whole_process(
                            where, arena_yaml, profile, args.receiver, args.cache, args.tracker,
                            sim.camera.readout_ms > 0,
                        )  # fmt: skip
                    print(
                        f"suite: {name} / {profile}: yield {r['yield_pct']:.1f} %, MAE {_cell_mm(r['mae_mm'])} mm"
                        f"{_seam(r)}",
                        file=sys.stderr,
                        flush=True,
                    )
                results["flights"][name] = entry
    print(json.dumps(results, indent=1))
    table = markdown(results)
    print("\n" + table, file=sys.stderr)
    if args.markdown is not None:
        args.markdown.write_text(table, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
