"""What the receiver's start-up loads: a replay of image frames imports none of the modules that only a video
file, a camera, the event loop or an optional output needs (issue 29, target 4: the first pose within 0.8 s
of the start). Real subprocesses; ``python -X importtime`` lists every module a process imported."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

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
