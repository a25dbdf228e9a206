"""A Raspberry Pi camera through picamera2 as a frame source (picamera2 is imported only when it is opened)."""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np

from ipt.receiver.capture.source import (
    CapturedFrame,
    CaptureError,
    LiveCamera,
)

PICAMERA2_MISSING = (
    "picamera2 is not installed: on Raspberry Pi OS run 'sudo apt install python3-picamera2' and make the "
    "virtual environment with --system-site-packages"
)


class PiCamera2Capture(LiveCamera):
    """A Raspberry Pi camera through picamera2 (imported only when this source is opened).

    Frames are asked for as RGB888 (which libcamera stores B, G, R) at the camera file's size, or with
    ``grey`` as YUV420 in full-range sYCC (the JPEG colour space) whose Y plane is the luma: the ISP makes
    it, nothing is converted on the CPU. Automatic exposure and white balance are turned off unless
    ``controls`` leave them on. The capture time is the
    frame's ``SensorTimestamp`` (the start of its exposure, on the monotonic clock) when the driver gives
    one on that clock, else the moment the frame was handed over.
    """

    kind = "picamera2"
    _cam: Any = None  # the Picamera2 object while open

    def camera_controls(self) -> dict[str, Any]:
        """The libcamera controls this source asks for."""
        c = self.controls
        out: dict[str, Any] = {"AeEnable": c.auto_exposure, "AwbEnable": c.auto_white_balance}
        if self.fps is not None:
            frame_us = round(1e6 / self.fps)
            out["FrameDurationLimits"] = (frame_us, frame_us)
        if c.exposure_us is not None:
            out["ExposureTime"] = round(c.exposure_us)
        if c.gain is not None:
            out["AnalogueGain"] = float(c.gain)
        return out

    def open(self) -> None:
        """Import picamera2, configure the camera and start it."""
        try:
            from picamera2 import Picamera2
        except ImportError:
            raise CaptureError(PICAMERA2_MISSING) from None
        try:
            cam = Picamera2(self.index)
        except Exception as exc:  # no such camera, or it is in use: picamera2 raises various types
            raise CaptureError(f"{self.name}: cannot open the camera ({type(exc).__name__}: {exc})") from None
        try:
            extra: dict[str, Any] = {}
            if self.grey:
                try:  # libcamera's Python module comes with picamera2
                    from libcamera import ColorSpace

                    extra["colour_space"] = ColorSpace.Sycc()
                except ImportError:
                    pass
            config = cam.create_video_configuration(
                main={"size": (self.width, self.height), "format": "YUV420" if self.grey else "RGB888"},
                controls=self.camera_controls(),
                buffer_count=4,
                **extra,
            )
            cam.configure(config)
            cam.start()
        except Exception as exc:
            with contextlib.suppress(Exception):
                cam.close()
            raise CaptureError(f"{self.name}: cannot configure the camera ({type(exc).__name__}: {exc})") from None
        self._cam = cam

    def read(self) -> CapturedFrame | None:
        """The next frame, RGB (or the luma); raises :class:`CaptureError` if the camera fails."""
        cam = self._cam
        if cam is None:
            raise CaptureError(f"{self.name}: read before open")
        request = cam.capture_request()
        try:
            array = np.asarray(request.make_array("main"), dtype=np.uint8)
            metadata = request.get_metadata()
        finally:
            request.release()
        handed_s = self._clock()
        if self.grey:
            # YUV420 comes as one array of 1.5 times the height (Y, then U and V), rows padded to the stride.
            if array.ndim != 2 or array.shape[0] != self.height * 3 // 2 or array.shape[1] < self.width:
                raise CaptureError(
                    f"{self.name}: YUV420 frames are {array.shape}, the camera file says {self.width}x{self.height}"
                )
            image = np.ascontiguousarray(array[: self.height, : self.width])
        else:
            if array.ndim != 3 or array.shape[:2] != (self.height, self.width):
                raise CaptureError(
                    f"{self.name}: frames are {array.shape[1]}x{array.shape[0]}, "
                    f"the camera file says {self.width}x{self.height}"
                )
            image = np.ascontiguousarray(array[:, :, 2::-1], dtype=np.uint8)
        sensor_ns = metadata.get("SensorTimestamp") if isinstance(metadata, dict) else None
        captured_s = handed_s
        if isinstance(sensor_ns, int) and abs(sensor_ns * 1e-9 - handed_s) < 1.0:
            captured_s = sensor_ns * 1e-9
        k = self._count
        self._count += 1
        return CapturedFrame(k, round(captured_s * 1e6), image, captured_s)

    def close(self) -> None:
        """Stop and release the camera."""
        cam, self._cam = self._cam, None
        if cam is not None:
            with contextlib.suppress(Exception):
                cam.stop()
            cam.close()


def picamera2_cameras() -> str:
    try:
        from picamera2 import Picamera2
    except ImportError:
        return "picamera2: not installed (needed only for Raspberry Pi cameras)"
    try:
        infos = Picamera2.global_camera_info()
    except Exception as exc:
        return f"picamera2: cannot list the cameras ({type(exc).__name__}: {exc})"
    if not infos:
        return "picamera2: no cameras"
    names = ", ".join(f"picamera2:{i} {info.get('Model', '?')}" for i, info in enumerate(infos))
    return f"picamera2: {names}"
