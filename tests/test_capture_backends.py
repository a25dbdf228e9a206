"""Capture backends: image folders, the V4L2 settings, picamera2, and ``--list-cameras``.

No camera is attached here, so the V4L2 settings are checked against a stand-in of OpenCV's capture object
that behaves like a driver refusing some controls, and picamera2 against a stand-in module with
picamera2's calls (the real one needs libcamera on a Raspberry Pi). Folders of images, the daemon's
source selection and ``--list-cameras`` run for real.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import types
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from ipt.config.models import ConfigError
from ipt.config.receiver import CameraControls, ReceiverConfig, parse_source, with_overrides
from ipt.receiver.capture import (
    PICAMERA2_MISSING,
    CaptureError,
    PiCamera2Capture,
    VideoCapture,
    apply_v4l2_settings,
    capture_time_us,
    list_cameras,
)
from ipt.sim.run import VIDEO_NAME
from ipt.videoio import open_frames


def test_source_forms() -> None:
    assert str(parse_source("images:frames")) == "images:frames"
    assert parse_source("picamera2") == parse_source("picamera2:0")
    assert parse_source("picamera2:1").device == 1
    assert parse_source("device:2").kind == "device"
    for bad in ("images:", "picamera2:x", "usb:0", "camera"):
        with pytest.raises(ValueError, match=r"sim, video:PATH, images:DIR, device:N or picamera2|needs"):
            parse_source(bad)


def test_image_folder_source_gives_the_video_frames_with_frame_times(short_flight: Path, tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    with open_frames(short_flight / VIDEO_NAME) as video:
        originals = [frame for _, frame in zip(range(6), video, strict=False)]
    for k, rgb in enumerate(originals):
        cv2.imwrite(str(folder / f"frame{k}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    src = VideoCapture(folder, 120.0, realtime=False, size=(640, 360), images_only=True)
    assert src.name == f"images:{folder}"
    src.open()
    try:
        frames = [src.read() for _ in range(7)]
    finally:
        src.close()
    assert frames[-1] is None
    for k, (f, rgb) in enumerate(zip(frames[:-1], originals, strict=True)):
        assert f is not None
        assert f.index == k
        assert f.capture_time_us == capture_time_us(k, 120.0)
        np.testing.assert_array_equal(f.image, rgb)
    not_a_folder = VideoCapture(short_flight / VIDEO_NAME, 120.0, realtime=False, images_only=True)
    with pytest.raises(CaptureError, match="not a folder"):
        not_a_folder.open()


class _Driver:
    """Stands in for ``cv2.VideoCapture`` on a V4L2 camera that refuses manual white balance and rounds
    the frame rate, as real UVC drivers do."""

    def __init__(self) -> None:
        self.props: dict[int, float] = {cv2.CAP_PROP_FOURCC: float(sum(ord(c) << 8 * i for i, c in enumerate("YUYV")))}
        self.calls: list[tuple[int, float]] = []

    def set(self, prop: int, value: float) -> bool:
        self.calls.append((prop, value))
        if prop == cv2.CAP_PROP_AUTO_WB:
            return False
        self.props[prop] = 100.0 if prop == cv2.CAP_PROP_FPS else value
        return True

    def get(self, prop: int) -> float:
        return self.props.get(prop, -1.0)


def test_v4l2_settings_turn_automatics_off_and_say_what_the_driver_refused() -> None:
    driver = _Driver()
    controls = CameraControls(exposure_us=2000, gain=12, fourcc="MJPG")
    notes = apply_v4l2_settings(driver, 640, 360, 120.0, controls, "device:0")  # type: ignore[arg-type]
    asked = dict(driver.calls)
    assert asked[cv2.CAP_PROP_AUTO_EXPOSURE] == 1  # V4L2 manual exposure
    assert asked[cv2.CAP_PROP_EXPOSURE] == 20  # 2000 us in units of 100 us
    assert asked[cv2.CAP_PROP_GAIN] == 12
    assert asked[cv2.CAP_PROP_AUTO_WB] == 0
    assert [p for p, _ in driver.calls].index(cv2.CAP_PROP_FOURCC) < [p for p, _ in driver.calls].index(
        cv2.CAP_PROP_FRAME_WIDTH
    )  # the pixel format first: it decides which sizes and rates exist
    assert notes == [
        "device:0: the driver did not take frame rate 120 FPS (it reports 100)",
        "device:0: the driver did not take automatic white balance off (it reports -1)",
    ]
    assert all("\n" not in n for n in notes)


class _Request:
    def __init__(self, bgr: np.ndarray, sensor_ns: int) -> None:
        self.bgr, self.sensor_ns, self.released = bgr, sensor_ns, False

    def make_array(self, name: str) -> np.ndarray:
        assert name == "main"
        return self.bgr

    def get_metadata(self) -> dict[str, Any]:
        return {"SensorTimestamp": self.sensor_ns}

    def release(self) -> None:
        self.released = True


def _fake_picamera2(monkeypatch: pytest.MonkeyPatch, log: dict[str, Any], sensor_ns: int) -> None:
    class Picamera2:
        def __init__(self, index: int) -> None:
            log["index"] = index

        def create_video_configuration(self, **kw: Any) -> dict[str, Any]:
            log["config"] = kw
            return kw

        def configure(self, config: dict[str, Any]) -> None:
            log["configured"] = True

        def start(self) -> None:
            log["started"] = True

        def capture_request(self) -> _Request:
            bgr = np.zeros((360, 640, 3), np.uint8)
            bgr[..., 0] = 10  # blue
            bgr[..., 2] = 200  # red
            req = _Request(bgr, sensor_ns)
            log.setdefault("requests", []).append(req)
            return req

        def stop(self) -> None:
            log["stopped"] = True

        def close(self) -> None:
            log["closed"] = True

    module = types.ModuleType("picamera2")
    module.Picamera2 = Picamera2  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "picamera2", module)


def test_picamera2_source_configures_manual_exposure_and_gives_rgb_with_sensor_time(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    log: dict[str, Any] = {}
    now_s = 5000.0
    _fake_picamera2(monkeypatch, log, sensor_ns=int((now_s - 0.004) * 1e9))
    controls = CameraControls(exposure_us=1500, gain=2.0)
    src = PiCamera2Capture(1, 640, 360, 120.0, controls=controls, clock=lambda: now_s)
    src.open()
    frame = src.read()
    src.close()
    assert log["index"] == 1
    assert log["started"]
    assert log["stopped"]
    assert log["closed"]
    cfg = log["config"]
    assert cfg["main"] == {"size": (640, 360), "format": "RGB888"}
    assert cfg["controls"] == {
        "AeEnable": False,
        "AwbEnable": False,
        "FrameDurationLimits": (8333, 8333),
        "ExposureTime": 1500,
        "AnalogueGain": 2.0,
    }
    assert frame is not None
    assert frame.image[0, 0].tolist() == [200, 0, 10]  # libcamera's RGB888 is B, G, R in memory
    assert frame.capture_time_us == round((now_s - 0.004) * 1e6)  # the sensor's timestamp
    assert all(r.released for r in log["requests"])


def test_picamera2_missing_is_one_line_and_not_imported_unless_used() -> None:
    code = (
        "import sys, ipt.receiver.daemon, ipt.receiver.capture as c\n"
        "print('picamera2' in sys.modules)\n"
        "src = c.PiCamera2Capture(0, 640, 360, 120.0)\n"
        "try:\n    src.open()\nexcept c.CaptureError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    lines = out.stdout.strip().splitlines()
    assert lines[0] == "False"
    if importlib.util.find_spec("picamera2") is None:  # on a Pi with picamera2 the line says what else failed
        assert lines[1] == PICAMERA2_MISSING


def test_list_cameras_says_what_it_found(tmp_path: Path) -> None:
    dev = tmp_path / "dev"
    sysfs = tmp_path / "sys"
    dev.mkdir()
    assert list_cameras(dev, sysfs, probe=False)[0] == f"V4L2: no cameras ({dev}/video* absent)"
    for n in (0, 1, 10):
        (dev / f"video{n}").touch()
    (dev / "video-notacamera").touch()
    (sysfs / "video0").mkdir(parents=True)
    (sysfs / "video0" / "name").write_text("Arducam OV9281 USB Camera\n")
    lines = list_cameras(dev, sysfs, probe=False)
    assert lines[0] == f"device:0  {dev}/video0  Arducam OV9281 USB Camera: not opened"
    assert lines[1].startswith("device:1  ")
    assert lines[2].startswith("device:10  ")
    assert lines[3].startswith("V4L2: 3 node(s)")
    assert lines[-1].startswith("picamera2: ")

    out = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "--list-cameras"], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert "V4L2: " in out.stdout
    assert "picamera2: " in out.stdout


def test_camera_controls_are_validated_in_the_config() -> None:
    base = ReceiverConfig(arena=Path("a.yaml"), camera=Path("c.yaml"))
    for bad in ({"fourcc": "MJPEG"}, {"exposure_us": 0}, {"colour": True}):
        with pytest.raises(ConfigError, match="camera_controls"):
            with_overrides(base, camera_controls=bad)
    ok = with_overrides(base, camera_controls={"exposure_us": 1000, "fourcc": "MJPG"}, source="picamera2")
    assert ok.camera_controls.exposure_us == 1000
    assert ok.source_spec.kind == "picamera2"
