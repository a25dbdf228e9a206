"""Frame sources of the receiver daemon and the hand-over of their frames to the event loop.

A source (:class:`VideoCapture` for a video file or an image folder, :class:`DeviceCapture` for a V4L2
camera through OpenCV, :class:`PiCamera2Capture` for a Raspberry Pi camera, or one handed in from outside,
such as the simulator's :class:`ipt.sim.capture.SimCapture`) is plain blocking code:
``open()``, then ``read()`` until it returns ``None`` (end of a recording), then ``close()``. A
:class:`CaptureThread` runs it on its own thread, so no blocking read ever happens on the event loop,
and hands each :class:`CapturedFrame` to a bounded :class:`FrameQueue` that the asyncio side reads.

Two queue policies:

- **live** sources (a camera, or a recording or the simulator paced to real time): the newest frame
  wins. When the queue is full the *oldest* frame is dropped and counted; the camera never waits.
- a recording read **as fast as possible** (no pacing): the reader waits for room, nothing is dropped.

A source made with ``grey`` hands over H×W luma frames instead of RGB ones (the daemon asks for them
when the pipeline works on luminance only, :attr:`~ipt.config.models.PipelineConfig.luminance_only`),
taken without a detour through RGB where the source has them: a V4L2 camera's GREY, YUYV or MJPG
buffers (:mod:`ipt.receiver.pixelformats`), a Pi camera's YUV420 Y plane, a video's Y plane, a JPEG
decoded to grey.

A camera that fails (``read()`` raises, e.g. unplugged) is reported on stderr, closed and opened again
with exponential backoff; the daemon keeps running. A camera frame that cannot be decoded (a damaged
MJPG frame) is skipped and counted like a recording's; only many in a row count as a failure. A
recording is a recording: it is read once, to its end, which ends the run. A frame of it that cannot be
decoded (or an image that cannot be read or has another size) is skipped and counted, with a few lines
on stderr (rate-limited) and the count in the final statistics; a file that ends before the frames its
header announces is reported as truncated; any other read error ends the recording there, with one line.
"""

from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import contextlib
import re
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, Protocol, TextIO, TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.models import MAX_RATE_HZ, MIN_CAMERA_RATE_HZ
from ipt.config.receiver import CameraControls
from ipt.errors import IptError
from ipt.ratelimit import LogThrottle
from ipt.receiver.pixelformats import RAW_LUMA_FORMATS, PixelFormatError, raw_luma
from ipt.videoio import FrameSource, open_frames

U8 = npt.NDArray[np.uint8]
T = TypeVar("T")

Clock = Callable[[], float]
"""Seconds on a monotonic clock."""
Sleep = Callable[[float], object]
"""Blocks for the given seconds (may return early, e.g. ``threading.Event.wait`` on shutdown)."""


class CaptureError(IptError):
    """A frame source cannot be opened or read."""


@dataclass(frozen=True)
class CapturedFrame:
    """One camera frame as it left the source."""

    index: int
    """Frame number of the source (0, 1, ...); a gap means frames were lost before capture."""
    capture_time_us: int
    """Capture time in microseconds: ``round(k / fps · 1e6)`` for a recording or the simulator, the
    monotonic clock at grab time for a camera. This is what the pose packet carries."""
    image: U8
    """H×W×3 uint8 RGB, or H×W uint8 luma from a source asked for ``grey`` frames (or a mono camera)."""
    grabbed_s: float = field(default_factory=time.monotonic)
    """``time.monotonic()`` when the frame was grabbed (camera) or read (recording, simulator): the start
    of the capture→send latency."""


# --- the queue between the capture thread and the event loop ---------------------------------------


class FrameQueue(Generic[T]):
    """A bounded FIFO for one producer and one consumer on the event loop's thread.

    ``put_newest`` never waits: when full it drops the oldest item and counts it in :attr:`dropped`
    (the live policy). ``put`` waits for room (the recording policy). ``finish`` says no more items
    will come: ``get`` then returns what is left and ``None`` after it. Not thread-safe: a thread hands
    items over with ``loop.call_soon_threadsafe`` / ``asyncio.run_coroutine_threadsafe``.
    """

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"maxsize must be at least 1, got {maxsize}")
        self.maxsize = maxsize
        self.dropped = 0
        self._items: collections.deque[T] = collections.deque()
        self._finished = False
        self._not_empty = asyncio.Event()
        self._not_full = asyncio.Event()
        self._not_full.set()

    def __len__(self) -> int:
        return len(self._items)

    @property
    def finished(self) -> bool:
        """Whether :meth:`finish` was called."""
        return self._finished

    def put_newest(self, item: T) -> T | None:
        """Add ``item``; if the queue was full, drop and return the oldest item (counted). After
        :meth:`finish`, ``item`` itself is discarded (not counted) and returned."""
        if self._finished:
            return item
        dropped: T | None = None
        if len(self._items) >= self.maxsize:
            dropped = self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self._not_empty.set()
        self._update_full()
        return dropped

    async def put(self, item: T) -> bool:
        """Add ``item`` once there is room; ``False`` (and ``item`` discarded) if the queue was finished."""
        while len(self._items) >= self.maxsize and not self._finished:
            await self._not_full.wait()
        if self._finished:
            return False
        self._items.append(item)
        self._not_empty.set()
        self._update_full()
        return True

    async def get(self) -> T | None:
        """The oldest item, waiting for one; ``None`` once the queue is finished and empty."""
        while not self._items:
            if self._finished:
                return None
            self._not_empty.clear()
            await self._not_empty.wait()
        item = self._items.popleft()
        self._update_full()
        if not self._items and not self._finished:
            self._not_empty.clear()
        return item

    def finish(self, discard: bool = False) -> int:
        """No more items will be put; wakes every waiter. With ``discard``, drops what is queued (not
        counted in :attr:`dropped`) and returns how many."""
        self._finished = True
        count = 0
        if discard:
            count = len(self._items)
            self._items.clear()
        self._not_empty.set()
        self._not_full.set()
        return count

    def _update_full(self) -> None:
        if len(self._items) >= self.maxsize:
            self._not_full.clear()
        else:
            self._not_full.set()


# --- sources ---------------------------------------------------------------------------------------


class CaptureSource(Protocol):
    """What :class:`CaptureThread` drives. ``read`` returns ``None`` at the end of the stream."""

    name: str
    live: bool
    """Frames come at their own pace and the newest wins (else the reader waits for the consumer)."""
    retry_open: bool
    """A failure of the first ``open`` is retried (a camera not plugged in yet) instead of fatal."""

    def open(self) -> None: ...

    def read(self) -> CapturedFrame | None: ...

    def close(self) -> None: ...


class Pacer:
    """Sleeps until frame ``k`` is due: ``k / fps`` seconds after the first frame was paced."""

    def __init__(self, fps: float, clock: Clock = time.monotonic, sleep: Sleep = time.sleep) -> None:
        self.fps, self.clock, self.sleep = fps, clock, sleep
        self._origin: tuple[float, int] | None = None

    def wait(self, k: int) -> None:
        """Block until frame ``k`` is due (returns at once if it is late)."""
        now = self.clock()
        if self._origin is None:
            self._origin = (now, k)
            return
        start, k0 = self._origin
        delay = start + (k - k0) / self.fps - now
        if delay > 0:
            self.sleep(delay)


def capture_time_us(k: int, fps: float) -> int:
    """Capture time of frame ``k`` of a recording or the simulator, in microseconds."""
    return round(k / fps * 1e6)


class VideoCapture:
    """Frames of a recording (a video file or an image folder), frame ``k`` captured at ``k / fps``.

    With ``realtime`` the frames are paced to the frame rate and treated as live (newest wins);
    without, they come as fast as the consumer takes them. A frame that cannot be decoded (an image that
    cannot be read, or has another size) is skipped and counted in :attr:`skipped`; the frames after it
    keep their numbers and times. :meth:`end_note` says, at the end, whether the file was truncated.
    """

    retry_open = False
    recording = True
    """Read once to its end (see :class:`CaptureThread`): not retried like a camera."""

    def __init__(
        self,
        path: str | Path,
        fps: float | None,
        realtime: bool,
        *,
        size: tuple[int, int] | None = None,
        clock: Clock = time.monotonic,
        sleep: Sleep = time.sleep,
        images_only: bool = False,
        grey: bool = False,
    ) -> None:
        self.path = Path(path)
        self.grey = grey
        """Hand over H×W luma frames (see :func:`ipt.videoio.open_frames`)."""
        self.images_only = images_only
        """Only a folder of images will do (the ``images:DIR`` source)."""
        self.name = f"{'images' if images_only else 'video'}:{self.path}"
        self.live = realtime
        self.size = size
        """(width, height) the frames must have, or None to accept any."""
        self._fps = fps
        self._clock, self._sleep = clock, sleep
        self._pacer: Pacer | None = None
        self._source: FrameSource | None = None
        self._next = 0
        self._skipped = 0  # of sources closed already
        self._last_skipped: str | None = None
        self._ended: str | None = None

    @property
    def fps(self) -> float | None:
        """The frame rate in use (known once opened, unless given)."""
        return self._fps

    def open(self) -> None:
        """Open the recording (bad frames are skipped and counted, see the class doc)."""
        if self.images_only and not self.path.is_dir():
            raise CaptureError(f"{self.path}: not a folder (images:DIR reads the images in a folder)")
        source = open_frames(self.path, skip_bad=True, grey=self.grey)
        try:
            if self.size is not None and (source.width, source.height) != self.size:
                w, h = self.size
                raise CaptureError(f"{self.path}: frames are {source.width}x{source.height} but the camera is {w}x{h}")
            fps = self._fps if self._fps is not None else source.fps
            if fps is None or not fps > 0:
                raise CaptureError(f"{self.path}: the frame rate is unknown; give it with --fps")
            if not MIN_CAMERA_RATE_HZ <= fps <= MAX_RATE_HZ:
                raise CaptureError(
                    f"{self.path}: its frame rate {fps:.3g} fps is not a camera's ({MIN_CAMERA_RATE_HZ:g} to "
                    f"{MAX_RATE_HZ:g}); give the rate with --fps"
                )
        except BaseException:
            source.close()
            raise
        self._fps = fps
        self._source = source
        self._ended = None
        if self.live and self._pacer is None:
            self._pacer = Pacer(fps, self._clock, self._sleep)

    @property
    def skipped(self) -> int:
        """Frames skipped so far because they could not be decoded or read, or had another size."""
        return self._skipped + (self._source.skipped if self._source is not None else 0)

    @property
    def last_skipped(self) -> str | None:
        """Why the last skipped frame was skipped."""
        return self._source.last_skipped if self._source is not None else self._last_skipped

    def end_note(self) -> str | None:
        """After the last frame: a sentence if the recording ended early (truncated, damaged), else None."""
        return self._ended

    def read(self) -> CapturedFrame | None:
        """The next frame, paced if real time; ``None`` at the end of the recording."""
        if self._source is None or self._fps is None:
            raise CaptureError(f"{self.path}: read before open")
        try:
            image = next(self._source)
        except StopIteration:
            self._ended = self._source.shortfall()
            return None
        k = self._source.index
        self._next = k + 1
        if self._pacer is not None:
            self._pacer.wait(k)
        return CapturedFrame(k, capture_time_us(k, self._fps), image, self._clock())

    def close(self) -> None:
        """Release the file."""
        if self._source is not None:
            self._skipped += self._source.skipped
            self._last_skipped = self._source.last_skipped
            self._source.close()
            self._source = None


V4L2_EXPOSURE_MANUAL = 1
"""V4L2's ``exposure_auto`` menu value for manual exposure (OpenCV passes it through)."""
V4L2_EXPOSURE_APERTURE_PRIORITY = 3
"""V4L2's ``exposure_auto`` value for automatic exposure on UVC cameras."""
V4L2_EXPOSURE_UNIT_US = 100.0
"""V4L2's ``exposure_time_absolute`` counts in units of 100 µs."""


MAX_UNDECODABLE_IN_A_ROW = 30
"""A camera whose frames fail to decode this many times in a row is reopened (a single damaged frame,
e.g. an MJPG frame cut short on a busy USB bus, is skipped and counted)."""


class _LiveCamera:
    """What the live cameras share: camera ``index`` at ``width``×``height`` and ``fps``, the exposure
    ``controls`` asked for, the clock that stamps frames, and the notes of the last open."""

    live = True
    retry_open = True
    kind = "camera"

    def __init__(
        self,
        index: int,
        width: int,
        height: int,
        fps: float | None,
        *,
        controls: CameraControls | None = None,
        clock: Clock = time.monotonic,
        grey: bool = False,
    ) -> None:
        self.index, self.width, self.height, self.fps = index, width, height, fps
        self.controls = controls if controls is not None else CameraControls()
        self.grey = grey
        """Hand over H×W luma frames instead of RGB ones."""
        self.name = f"{self.kind}:{index}"
        self.notes: list[str] = []
        """What the driver did not do as asked, from the last open (one line each)."""
        self.skipped = 0
        """Frames that could not be decoded (skipped; the next frame is read instead)."""
        self.last_skipped: str | None = None
        """Why the last skipped frame was skipped."""
        self._clock = clock
        self._count = 0

    def _skip(self, why: str) -> None:
        """Count a frame that cannot be decoded; raise once :data:`MAX_UNDECODABLE_IN_A_ROW` came in a row."""
        self.skipped += 1
        self._undecodable += 1
        self.last_skipped = f"{self.name}: frame {self._count}: {why}"
        self._count += 1  # the frame had its number: the next one keeps its own, the gap shows
        if self._undecodable >= MAX_UNDECODABLE_IN_A_ROW:
            self._undecodable = 0
            raise CaptureError(f"{self.name}: {MAX_UNDECODABLE_IN_A_ROW} frames in a row cannot be decoded ({why})")

    _undecodable = 0


class DeviceCapture(_LiveCamera):
    """A V4L2 camera (``/dev/videoN``) through OpenCV: RGB frames, or with ``grey`` the luma.

    The capture time is the monotonic clock at the moment ``grab`` returned, in microseconds. A camera
    is always live (newest wins); if it cannot be opened it is retried, like a read failure.

    On open, the pixel format, size and rate are asked for, then automatic exposure and white balance are
    turned off (unless ``controls`` leave them on) and the manual exposure and gain set. What the driver
    did not take is listed in :attr:`notes` (the capture thread prints them): drivers differ in what they
    allow. With ``grey``, a camera delivering GREY, YUYV or MJPG (whichever the driver settled on) hands
    over its raw buffers, whose luma :mod:`ipt.receiver.pixelformats` takes; any other format goes through
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


PICAMERA2_MISSING = (
    "picamera2 is not installed: on Raspberry Pi OS run 'sudo apt install python3-picamera2' and make the "
    "virtual environment with --system-site-packages"
)


class PiCamera2Capture(_LiveCamera):
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


def list_cameras(
    dev_dir: Path = Path("/dev"), sysfs_dir: Path = Path("/sys/class/video4linux"), *, probe: bool = True
) -> list[str]:
    """Lines saying which cameras are there: each V4L2 node (``/dev/videoN``, its name, and what OpenCV
    opens it at) and the picamera2 cameras. Never raises; what cannot be looked at is said."""
    lines = []
    nodes = sorted(
        (p for p in dev_dir.glob("video*") if re.fullmatch(r"video[0-9]+", p.name)), key=lambda p: int(p.name[5:])
    )
    for node in nodes:
        n = int(node.name[5:])
        try:
            label = (sysfs_dir / node.name / "name").read_text(encoding="utf-8", errors="replace").strip()
        except OSError:
            label = "?"
        what = _probe_v4l2(n) if probe else "not opened"
        lines.append(f"device:{n}  {node}  {label or '?'}: {what}")
    if not nodes:
        lines.append(f"V4L2: no cameras ({dev_dir}/video* absent)")
    else:
        usable = sum("frames" in line for line in lines)
        lines.append(f"V4L2: {len(nodes)} node(s), {usable} giving frames (a USB camera also has metadata nodes)")
    lines.append(_picamera2_cameras())
    return lines


def _probe_v4l2(index: int) -> str:
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


def _picamera2_cameras() -> str:
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


# --- the capture thread ----------------------------------------------------------------------------

BACKOFF_FIRST_S = 0.1
BACKOFF_MAX_S = 1.0


class CaptureThread:
    """Runs a source on its own (daemon) thread and hands its frames to a :class:`FrameQueue`.

    Live sources use ``put_newest`` (the oldest frame is dropped when the consumer lags); the others
    wait for room. The queue is finished when the source ends, after ``max_frames`` frames, or on
    :meth:`stop`. :attr:`ready` resolves once the source first opened, or with the error of a first
    open that is not retried.
    """

    def __init__(
        self,
        source: CaptureSource,
        queue: FrameQueue[CapturedFrame],
        loop: asyncio.AbstractEventLoop,
        *,
        stop: threading.Event | None = None,
        max_frames: int | None = None,
        report: TextIO | None = sys.stderr,
    ) -> None:
        self.source, self.queue, self.loop = source, queue, loop
        self.stop_event = stop if stop is not None else threading.Event()
        self.max_frames = max_frames
        self.report = report
        self.frames = 0
        """Frames delivered to the queue (dropped ones included)."""
        self.failures = 0
        """Failed opens and reads."""
        self.skipped = 0
        """Frames of a recording skipped because they could not be decoded or read (the source counts them)."""
        self._throttle = LogThrottle()
        self.ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._thread = threading.Thread(target=self._run, name=f"ipt-capture-{source.name}", daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def stop(self) -> None:
        """Ask the thread to stop (it ends after the read in progress)."""
        self.stop_event.set()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the thread; whether it has ended."""
        if self._thread.ident is not None:
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _say(self, text: str) -> None:
        if self.report is not None:
            try:
                self.report.write(f"ipt-receiver: capture: {text}\n")
                self.report.flush()
            except (OSError, ValueError):
                pass

    def _run(self) -> None:
        delay = BACKOFF_FIRST_S
        opened = False
        if self.source.retry_open:
            self._resolve_ready()  # a camera that is not there yet is retried: the daemon runs meanwhile
        try:
            while not self.stop_event.is_set():
                if not opened:
                    try:
                        self.source.open()
                    except Exception as exc:
                        self.failures += 1
                        if not self.ready.done() and not self.source.retry_open:
                            self._resolve_ready(exc)
                            return
                        self._say(f"{self.source.name}: {_describe(exc)}; retrying in {delay:.1f} s")
                        self.stop_event.wait(delay)
                        delay = min(2 * delay, BACKOFF_MAX_S)
                        continue
                    opened = True
                    for note in getattr(self.source, "notes", ()):
                        self._say(note)
                    self._resolve_ready()
                try:
                    frame = self.source.read()
                except Exception as exc:
                    self.failures += 1
                    if getattr(self.source, "recording", False):
                        self._say(f"{self.source.name}: {_describe(exc)}; the recording ends here")
                        break
                    self._say(f"{self.source.name}: {_describe(exc)}; reopening in {delay:.1f} s")
                    self._close_source()
                    opened = False
                    self.stop_event.wait(delay)
                    delay = min(2 * delay, BACKOFF_MAX_S)
                    continue
                self._report_skipped()
                if frame is None:
                    end_note: Callable[[], str | None] | None = getattr(self.source, "end_note", None)
                    if end_note is not None and (note := end_note()) is not None:
                        self._say(note)
                    break  # the end of a recording
                delay = BACKOFF_FIRST_S
                if self.stop_event.is_set() or not self._deliver(frame):
                    break
                self.frames += 1
                if self.max_frames is not None and self.frames >= self.max_frames:
                    break
        finally:
            self._close_source()
            self._resolve_ready()
            self._call(self.queue.finish)

    def _report_skipped(self) -> None:
        """Count the frames the source skipped since the last read, and say why (a few lines, then a count)."""
        skipped = int(getattr(self.source, "skipped", 0))
        if skipped > self.skipped:
            self.skipped = skipped
            why = getattr(self.source, "last_skipped", None) or "a frame cannot be read"
            if (line := self._throttle.line("skipped", f"{why}; skipped", time.monotonic())) is not None:
                self._say(line)

    def _resolve_ready(self, exc: BaseException | None = None) -> None:
        if self.ready.done():
            return
        try:
            if exc is None:
                self.ready.set_result(None)
            else:
                self.ready.set_exception(exc)
        except concurrent.futures.InvalidStateError:  # cancelled meanwhile: nobody waits for it
            pass

    def _close_source(self) -> None:
        try:
            self.source.close()
        except Exception as exc:
            self._say(f"{self.source.name}: closing failed: {_describe(exc)}")

    def _call(self, fn: Callable[[], object]) -> bool:
        try:
            self.loop.call_soon_threadsafe(fn)
        except RuntimeError:  # the loop is closed: nobody is listening any more
            return False
        return True

    def _deliver(self, frame: CapturedFrame) -> bool:
        if self.source.live:
            return self._call(lambda: self.queue.put_newest(frame))
        try:
            fut = asyncio.run_coroutine_threadsafe(self.queue.put(frame), self.loop)
        except RuntimeError:
            return False
        while True:
            try:
                return fut.result(timeout=0.1)
            except TimeoutError:
                if self.stop_event.is_set():
                    fut.cancel()
                    return False
            except concurrent.futures.CancelledError:
                return False


def _describe(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, IptError) else f"{type(exc).__name__}: {exc}"
