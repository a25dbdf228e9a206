"""A V4L2 camera (``/dev/videoN``) through OpenCV as a frame source, and the settings asked of its driver."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.receiver import CameraControls
from ipt.receiver.capture.pixelformats import RAW_LUMA_FORMATS, PixelFormatError, raw_luma
from ipt.receiver.capture.source import (
    U8,
    CapturedFrame,
    CaptureError,
    LiveCamera,
)

V4L2_EXPOSURE_MANUAL = 1
"""V4L2's ``exposure_auto`` menu value for manual exposure (OpenCV passes it through)."""
V4L2_EXPOSURE_APERTURE_PRIORITY = 3
"""V4L2's ``exposure_auto`` value for automatic exposure on UVC cameras."""
V4L2_EXPOSURE_UNIT_US = 100.0
"""V4L2's ``exposure_time_absolute`` counts in units of 100 µs."""


class DeviceCapture(LiveCamera):
    """A V4L2 camera (``/dev/videoN``) through OpenCV: RGB frames, or with ``grey`` the luma.

    The capture time is the monotonic clock at the moment ``grab`` returned, in microseconds. A camera
    is always live (newest wins); if it cannot be opened it is retried, like a read failure.

    On open, the pixel format, size and rate are asked for, then automatic exposure and white balance are
    turned off (unless ``controls`` leave them on) and the manual exposure and gain set. What the driver
    did not take is listed in :attr:`notes` (the capture thread prints them): drivers differ in what they
    allow. With ``grey``, a camera delivering GREY, YUYV or MJPG (whichever the driver settled on) hands
    over its raw buffers, whose luma :mod:`ipt.receiver.capture.pixelformats` takes; any other format goes through
    OpenCV's conversion to BGR and then to grey. A frame that does not decode is skipped and counted.
    """

    kind = "device"
    _cap: cv2.VideoCapture | None = None  # while open
    raw_format: str | None = None
    """The pixel format whose raw buffers are decoded here (None: OpenCV converts to BGR)."""

    def open(self) -> None:
        """Open the device and ask for the camera's format, size, rate, exposure and gain."""
        cap = cv2.VideoCapture(self.index, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise CaptureError(f"/dev/video{self.index}: cannot open the camera")
        self.notes = apply_v4l2_settings(cap, self.width, self.height, self.fps, self.controls, self.name)
        self.raw_format = None
        if self.grey:
            fourcc = _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
            if fourcc in RAW_LUMA_FORMATS and cap.set(cv2.CAP_PROP_CONVERT_RGB, 0):
                self.raw_format = fourcc
        self._cap = cap
        self._undecodable = 0

    def read(self) -> CapturedFrame | None:
        """The next frame that decodes; raises :class:`CaptureError` if the camera fails (it is then
        reopened)."""
        cap = self._cap
        if cap is None:
            raise CaptureError(f"/dev/video{self.index}: read before open")
        while True:
            if not cap.grab():
                raise CaptureError(f"/dev/video{self.index}: grabbing a frame failed")
            grabbed = self._clock()
            ok, data = cap.retrieve()
            image = self._decoded(data) if ok and data is not None else None
            if image is not None:
                break
            self._skip("cannot be decoded")  # OpenCV's V4L2 backend fails a damaged MJPG frame in retrieve
        self._undecodable = 0
        k = self._count
        self._count += 1
        return CapturedFrame(k, round(grabbed * 1e6), image, grabbed)

    def _decoded(self, data: npt.NDArray[np.uint8]) -> U8 | None:
        """The frame (RGB, or the luma with ``grey``) from what ``retrieve`` gave; None if it does not decode."""
        if self.raw_format is not None:
            try:
                return raw_luma(data, self.raw_format, self.width, self.height)
            except PixelFormatError as exc:
                raise CaptureError(f"/dev/video{self.index}: {exc}") from None
        if data.ndim != 3 or data.shape[:2] != (self.height, self.width):
            raise CaptureError(
                f"/dev/video{self.index}: frames are {data.shape[1]}x{data.shape[0]}, the camera file says "
                f"{self.width}x{self.height}"
            )
        code = cv2.COLOR_BGR2GRAY if self.grey else cv2.COLOR_BGR2RGB
        return np.ascontiguousarray(cv2.cvtColor(data, code), dtype=np.uint8)

    def close(self) -> None:
        """Release the device."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None


def _fourcc_text(value: float) -> str:
    code = int(value)
    text = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
    return text if text.isprintable() and text.strip() else f"0x{code:08x}"


def apply_v4l2_settings(
    cap: cv2.VideoCapture,
    width: int,
    height: int,
    fps: float | None,
    controls: CameraControls,
    name: str,
) -> list[str]:
    """Ask an open OpenCV V4L2 capture for the settings; one line for each the driver did not take."""
    notes = []

    def ask(prop: int, value: float, what: str, shown: str, tolerance: float = 1e-3) -> None:
        accepted = bool(cap.set(prop, value))
        got = float(cap.get(prop))
        if not accepted or abs(got - value) > tolerance * max(1.0, abs(value)):
            notes.append(f"{name}: the driver did not take {what} {shown} (it reports {got:g})")

    if controls.fourcc is not None:
        wanted = sum(ord(c) << (8 * i) for i, c in enumerate(controls.fourcc))  # cv2.VideoWriter_fourcc
        cap.set(cv2.CAP_PROP_FOURCC, wanted)
        got_fourcc = _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
        if got_fourcc != controls.fourcc:
            notes.append(f"{name}: the driver did not take pixel format {controls.fourcc} (it uses {got_fourcc})")
    ask(cv2.CAP_PROP_FRAME_WIDTH, width, "width", str(width))
    ask(cv2.CAP_PROP_FRAME_HEIGHT, height, "height", str(height))
    if fps is not None:
        ask(cv2.CAP_PROP_FPS, fps, "frame rate", f"{fps:g} FPS", tolerance=0.02)
    cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not a stale one from the driver's queue
    auto = V4L2_EXPOSURE_APERTURE_PRIORITY if controls.auto_exposure else V4L2_EXPOSURE_MANUAL
    ask(cv2.CAP_PROP_AUTO_EXPOSURE, auto, "automatic exposure", "on" if controls.auto_exposure else "off")
    ask(
        cv2.CAP_PROP_AUTO_WB,
        1.0 if controls.auto_white_balance else 0.0,
        "automatic white balance",
        "on" if controls.auto_white_balance else "off",
    )
    if controls.exposure_us is not None:
        units = round(controls.exposure_us / V4L2_EXPOSURE_UNIT_US)
        ask(cv2.CAP_PROP_EXPOSURE, units, "exposure", f"{controls.exposure_us:g} us ({units} x 100 us)", 0.05)
    if controls.gain is not None:
        ask(cv2.CAP_PROP_GAIN, controls.gain, "gain", f"{controls.gain:g}", 0.05)
    return notes


def probe_v4l2(index: int) -> str:
    cap = cv2.VideoCapture(index, cv2.CAP_V4L2)
    try:
        if not cap.isOpened():
            return "cannot open (in use, no permission, or not a capture node)"
        ok = cap.grab()
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        fourcc = _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
        state = "frames" if ok else "opens but gives no frames"
        return f"{state} at {w}x{h}, {fps:g} FPS, {fourcc} (its current mode)"
    finally:
        cap.release()
