"""What the receiver's start-up loads: a replay of image frames imports none of the modules that only a video
file, a camera, the event loop or an optional output needs (issue 29, target 4: the first pose within 0.8 s
of the start). Real subprocesses; ``python -X importtime`` lists every module a process imported."""

from __future__ import annotations

import gc
import json
import os
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from ipt.config.camera_info import CameraInfo, save_camera_info

CAMERA = CameraInfo(width_px=64, height_px=48, fx_px=60.0, fy_px=60.0, cx_px=31.5, cy_px=23.5, name="startup_test")

NOT_FOR_IMAGES = (
    "av",  # PyAV: video files only
    "asyncio",  # the daemon's event loop
    "uvloop",
    "matplotlib",  # (not scipy: numba's loading of the kernels looks at scipy's BLAS itself)
    "cyclonedds",  # ROS 2 output
    "mcap",  # the MCAP flight log
    "pymavlink",  # MAVLink output
    "ipt.receiver.capture",  # cameras, recordings, the flight recorder
    "ipt.receiver.outputs",  # UDP, MAVLink, ROS 2
    "ipt.receiver.daemon",
    "ipt.sim",
    "ipt.sender",
)
"""Packages (with everything below them) that a replay of a folder of images must not import."""


def _imported(stderr: str) -> set[str]:
    """The modules ``-X importtime`` says the process imported."""
    return {line.rsplit("|", 1)[1].strip() for line in stderr.splitlines() if line.startswith("import time:")}


def _heavy(modules: set[str]) -> list[str]:
    return sorted(m for m in modules for p in NOT_FOR_IMAGES if m == p or m.startswith(p + "."))


def test_replay_of_images_imports_no_video_camera_loop_or_output_modules(tmp_path: Path) -> None:
    camera = tmp_path / "camera.yaml"
    save_camera_info(CAMERA, camera)
    frames = tmp_path / "bmp"
    frames.mkdir()
    for i in range(3):
        cv2.imwrite(str(frames / f"{i:06d}.bmp"), np.full((48, 64, 3), 90 + 20 * i, np.uint8))
    out = tmp_path / "poses.tum"
    command = [sys.executable, "-X", "importtime", "-m", "ipt.receiver.cli", "replay", "--camera", str(camera)]
    command += ["--video", str(frames), "--fps", "120", "--output", str(out)]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "0 poses from 3 frames" in proc.stdout, proc.stdout
    modules = _imported(proc.stderr)
    assert "ipt.receiver.replay" in modules, "importtime listed no modules"
    assert _heavy(modules) == [], "a replay of image frames imported what only videos, cameras or outputs need"


def _frames(tmp_path: Path, count: int) -> tuple[Path, Path]:
    camera = tmp_path / "camera.yaml"
    save_camera_info(CAMERA, camera)
    frames = tmp_path / "bmp"
    frames.mkdir()
    for i in range(count):
        cv2.imwrite(str(frames / f"{i:06d}.bmp"), np.full((48, 64, 3), 90 + 20 * i, np.uint8))
    return camera, frames


def test_the_daemon_starts_one_interpreter_its_apriltag_helper_is_forked(tmp_path: Path) -> None:
    # A new interpreter for the AprilTag helper (python -m ipt.receiver.detect.tagworker) imports numpy and the
    # rest again: a tenth of a second of processor time before a restarted daemon's first pose. Forked from the
    # daemon at its start, it imports nothing of that. PYTHONPROFILEIMPORTTIME makes every interpreter, a
    # helper's too, list its imports on the stderr they share.
    camera, frames = _frames(tmp_path, 3)
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.bind(("127.0.0.1", 0))
    try:
        command = [sys.executable, "-m", "ipt.receiver.cli", "run", "--camera", str(camera)]
        command += ["--source", f"images:{frames}", "--fps", "120", "--max-frames", "3"]
        command += ["--send", f"127.0.0.1:{sink.getsockname()[1]}"]
        env = dict(os.environ, PYTHONPROFILEIMPORTTIME="1")
        env.pop("OPENBLAS_NUM_THREADS", None)  # the receiver sets it itself (a BLAS thread would forbid the fork)
        proc = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path, env=env)
    finally:
        sink.close()
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "final: 3 frames" in proc.stderr, proc.stderr[-3000:]
    assert "0 for memory and 0 after failures" in proc.stderr, "the helper started and answered"
    lines = [line for line in proc.stderr.splitlines() if line.startswith("import time:")]
    numpy_imports = [line for line in lines if line.rsplit("|", 1)[1].strip() == "numpy"]
    assert len(numpy_imports) == 1, "numpy imported by more than one interpreter: the helper was not forked"
    assert any(line.rsplit("|", 1)[1].strip() == "dt_apriltags" for line in lines), "the C detector was loaded"


def test_a_replay_forks_its_apriltag_helper_too(tmp_path: Path) -> None:
    # A replay is timed as a whole process (issue 29, target 1): a new interpreter for its helper cost 0.15 s of
    # processor time of a two-frame replay's 0.6 s.
    camera, frames = _frames(tmp_path, 3)
    command = [sys.executable, "-m", "ipt.receiver.cli", "replay", "--camera", str(camera), "--video", str(frames)]
    command += ["--fps", "120", "--output", str(tmp_path / "poses.tum")]
    env = dict(os.environ, PYTHONPROFILEIMPORTTIME="1")
    env.pop("OPENBLAS_NUM_THREADS", None)  # the receiver sets it itself (a BLAS thread would forbid the fork)
    proc = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "0 poses from 3 frames" in proc.stdout, proc.stdout
    lines = [line for line in proc.stderr.splitlines() if line.startswith("import time:")]
    numpy_imports = [line for line in lines if line.rsplit("|", 1)[1].strip() == "numpy"]
    assert len(numpy_imports) == 1, "numpy imported by more than one interpreter: the helper was not forked"


_REPLAY_HOLDS_THE_COLLECTOR = """
import gc, sys
from ipt.receiver import replay as module

seen = []
replay = module.replay
def spied(*args, **kwargs):
    hook = kwargs["on_result"]
    def on_result(frame, result, sent):
        seen.append((result.index, gc.isenabled()))
        hook(frame, result, sent)
    kwargs["on_result"] = on_result
    return replay(*args, **kwargs)
module.replay = spied
from ipt.receiver.cli import main
code = main(sys.argv[1:])
print(code, seen, gc.isenabled(), gc.get_freeze_count() > 0)
"""


def test_a_replay_holds_the_collector_off_until_its_first_pose_as_the_daemon_does(tmp_path: Path) -> None:
    # A replay is timed as a whole process (issue 29, target 1): the collector's passes over what the start-up made
    # cost moving-content's replay 0.058 s, 0.002 s held off until the first pose and then frozen. Frames without a
    # pose keep it held (up to START_UP_RESULTS); the replay's end lets go whatever came.
    camera, frames = _frames(tmp_path, 3)
    command = [sys.executable, "-c", _REPLAY_HOLDS_THE_COLLECTOR, "replay", "--camera", str(camera)]
    command += ["--video", str(frames), "--fps", "120", "--output", str(tmp_path / "poses.tum")]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.splitlines()[-1] == "0 [(0, False), (1, False), (2, False)] True True", proc.stdout


FORKED_HELPER = """
import json, os, sys
from ipt.receiver.detect import tagworker
from ipt.receiver.detect.tagworker import ProcessBackend

forked = tagworker.prestart()
pid = tagworker._prestarted.helper.proc.pid if forked else None
view = json.loads(sys.stdin.readline())
import numpy as np
from ipt.receiver.detect.apriltag_c import make_pupil_detector, pupil_detect
image = np.asarray(view["image"], np.uint8)
backend = ProcessBackend(view["settings"])
found = backend.detect_raw(image)
inline = pupil_detect(make_pupil_detector(view["settings"]), image, view["settings"]["quad_decimate"])
same = [(a[0], a[1], a[2], a[3].tolist()) for a in found] == [(b[0], b[1], b[2], b[3].tolist()) for b in inline]
out = {"forked": forked, "adopted": backend.helper_pids == [pid], "ids": sorted(d[0] for d in found), "same": same}
out["comm"] = open(f"/proc/{pid}/comm").read().strip()
backend.close()
out["reaped"] = not os.path.exists(f"/proc/{pid}")
tagworker.prestart()  # a second one, not adopted: dropped (the configuration runs AprilTag inline)
second = tagworker._prestarted.helper.proc.pid
tagworker.drop_prestarted()
out["dropped"] = not os.path.exists(f"/proc/{second}")
print(json.dumps(out), flush=True)
"""


def test_a_forked_helper_is_adopted_detects_as_inline_and_is_reaped(tmp_path: Path) -> None:
    from ipt.config.models import DetectorConfig, load_arena_config, shipped_config_path
    from ipt.receiver.detect.detector import c_settings
    from ipt.tagmap import grid_tag_map

    floor = grid_tag_map(load_arena_config(shipped_config_path("arena.yaml"))).render_image()
    src = np.array([[100, 150], [800, 170], [790, 550], [90, 540]], np.float32)
    dst = np.array([[0, 0], [640, 0], [640, 360], [0, 360]], np.float32)
    view = cv2.warpPerspective(floor, cv2.getPerspectiveTransform(src, dst), (640, 360), flags=cv2.INTER_AREA)
    request = json.dumps({"image": view.tolist(), "settings": c_settings(DetectorConfig())}) + "\n"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")  # one thread: the fork is allowed
    done = subprocess.run(
        [sys.executable, "-c", FORKED_HELPER], input=request, capture_output=True, text=True, timeout=120,
        check=False, cwd=tmp_path, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout.splitlines()[-1])
    assert out["forked"], out
    assert out["adopted"], out
    assert out["comm"] == "ipt-tagworker", "its name in top (its command line is the daemon's)"
    assert out["ids"], out
    assert out["same"], "the forked helper's detections differ from the C detector's in this process"
    assert out["reaped"], out
    assert out["dropped"], out


class _FakeTimer:
    """A stand-in for threading.Timer: the test calls its function when it chooses (no sleeping)."""

    def __init__(self, seconds: float, fn: Callable[[], None]) -> None:
        self.seconds, self.fn = seconds, fn
        self.daemon = False
        self.started = self.cancelled = False

    def start(self) -> None:
        self.started = True

    def cancel(self) -> None:
        self.cancelled = True


def test_the_collector_is_held_off_until_the_first_pose_then_the_start_up_is_frozen() -> None:
    # The start-up's long-lived objects (numba, pydantic, OpenCV, the pipeline) cost the cyclic collector
    # 0.05-0.1 s of passes before the first pose; held off, then frozen, they are never scanned again.
    from ipt.receiver.cli import START_UP_RESULTS, START_UP_SECONDS, GcHeldForStartUp
    from ipt.receiver.core.frameresult import FrameResult

    assert gc.isenabled()
    frozen_before = gc.get_freeze_count()
    try:
        hold = GcHeldForStartUp()
        assert not gc.isenabled()
        hold.on_result(None, None, 0)  # a frame whose processing raised
        hold.on_result(None, FrameResult(0, 0, None, 0, "first_frame"), 0)
        assert not gc.isenabled(), "no pose yet: still held"
        pose = object()
        hold.on_result(None, FrameResult(1, 8333, pose, 4, "pose"), 1)  # type: ignore[arg-type]
        assert gc.isenabled()
        assert gc.get_freeze_count() > frozen_before, "what the start-up made is frozen"
        hold.on_result(None, FrameResult(2, 16667, pose, 4, "pose"), 1)  # type: ignore[arg-type]
        assert gc.isenabled()
        # Without a pose, the hold ends after START_UP_RESULTS results all the same.
        late = GcHeldForStartUp()
        for k in range(START_UP_RESULTS - 1):
            late.on_result(None, FrameResult(k, 0, None, 0, "no_tags"), 0)
        assert not gc.isenabled()
        late.on_result(None, FrameResult(START_UP_RESULTS, 0, None, 0, "no_tags"), 0)
        assert gc.isenabled()
        # Without any result (a camera that delivers nothing yet), it ends after START_UP_SECONDS.
        timers: list[_FakeTimer] = []
        idle = GcHeldForStartUp()
        idle.release_after(START_UP_SECONDS, lambda seconds, fn: timers.append(_FakeTimer(seconds, fn)) or timers[-1])
        assert timers[0].seconds == START_UP_SECONDS
        assert timers[0].started
        assert not gc.isenabled()
        timers[0].fn()  # the time is up
        assert gc.isenabled()
        # A pose first: the timer is cancelled.
        posed = GcHeldForStartUp()
        posed.release_after(START_UP_SECONDS, lambda seconds, fn: timers.append(_FakeTimer(seconds, fn)) or timers[-1])
        posed.on_result(None, FrameResult(3, 0, pose, 4, "pose"), 1)  # type: ignore[arg-type]
        assert gc.isenabled()
        assert timers[1].cancelled
    finally:
        gc.unfreeze()
        gc.enable()


_THREADS_AFTER_MAIN = """
import contextlib, io, os, sys
from ipt.receiver.cli import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):
    main(["--version"])
import cv2
print(os.environ["OPENCV_FOR_THREADS_NUM"], cv2.getNumThreads())
"""


@pytest.mark.parametrize(("users", "expected"), [(None, "1 1"), ("3", "3 3")])
def test_the_receiver_runs_opencv_on_one_thread_unless_told(users: str | None, expected: str) -> None:
    # OpenCV's pool splits a 640-pixel frame's remaps and warps over the cores and its idle workers spin
    # (sched_yield): 10-22 % of a two-core replay's processor time for no wall time (docs/receiver-cores.md, stop
    # 67). The entry point sets one thread before OpenCV loads; a user's own OPENCV_FOR_THREADS_NUM is kept.
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FOR_THREADS_NUM"}
    if users is not None:
        env["OPENCV_FOR_THREADS_NUM"] = users
    proc = subprocess.run(
        [sys.executable, "-c", _THREADS_AFTER_MAIN], capture_output=True, text=True, timeout=120, check=False, env=env
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == expected
