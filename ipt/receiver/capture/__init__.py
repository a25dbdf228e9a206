"""Frame sources of the receiver daemon and the hand-over of their frames to the event loop.

A source (:class:`VideoCapture` for a video file or an image folder, :class:`DeviceCapture` for a V4L2
camera through OpenCV, :class:`PiCamera2Capture` for a Raspberry Pi camera, or one handed in from outside,
such as the simulator's :class:`ipt.sim.capture.SimCapture`) is plain blocking code:
``open()``, then ``read()`` until it returns ``None`` (end of a recording), then ``close()``. A
:class:`CaptureThread` runs it on its own thread, so no blocking read ever happens on the event loop,
and hands each :class:`CapturedFrame` to a bounded :class:`FrameQueue` that the asyncio side reads.

Two queue policies:

- **live** sources (a camera, or a recording or the simulator paced to real time): the newest frames
  win. When the queue is full the *oldest* frame is dropped and counted; the camera never waits. The
  daemon takes what the queue holds (its newest three at most, consecutive) as one run
  (:data:`ipt.receiver.liverun.LIVE_RUN_FRAMES`), or, behind, a + and − frame of it
  (:func:`ipt.receiver.liverun.pick_run`).
- a recording read **as fast as possible** (no pacing): the reader waits for room, nothing is dropped.

A source made with ``grey`` hands over H×W luma frames instead of RGB ones (the daemon asks for them
when the pipeline works on luminance only, :attr:`~ipt.config.models.PipelineConfig.luminance_only`),
taken without a detour through RGB where the source has them: a V4L2 camera's GREY, YUYV or MJPG
buffers (:mod:`ipt.receiver.capture.pixelformats`), a Pi camera's YUV420 Y plane, a video's Y plane, a JPEG
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

from ipt.receiver.capture.listing import list_cameras
from ipt.receiver.capture.picamera import PICAMERA2_MISSING, PiCamera2Capture
from ipt.receiver.capture.queue import FrameQueue
from ipt.receiver.capture.recording import VideoCapture
from ipt.receiver.capture.source import (
    MAX_UNDECODABLE_IN_A_ROW,
    U8,
    CapturedFrame,
    CaptureError,
    CaptureSource,
    Clock,
    LiveCamera,
    Pacer,
    Sleep,
    capture_time_us,
)
from ipt.receiver.capture.thread import BACKOFF_FIRST_S, BACKOFF_MAX_S, CaptureThread
from ipt.receiver.capture.v4l2 import (
    V4L2_EXPOSURE_APERTURE_PRIORITY,
    V4L2_EXPOSURE_MANUAL,
    V4L2_EXPOSURE_UNIT_US,
    DeviceCapture,
    apply_v4l2_settings,
)

__all__ = [
    "BACKOFF_FIRST_S",
    "BACKOFF_MAX_S",
    "MAX_UNDECODABLE_IN_A_ROW",
    "PICAMERA2_MISSING",
    "U8",
    "V4L2_EXPOSURE_APERTURE_PRIORITY",
    "V4L2_EXPOSURE_MANUAL",
    "V4L2_EXPOSURE_UNIT_US",
    "CaptureError",
    "CaptureSource",
    "CaptureThread",
    "CapturedFrame",
    "Clock",
    "DeviceCapture",
    "FrameQueue",
    "LiveCamera",
    "Pacer",
    "PiCamera2Capture",
    "Sleep",
    "VideoCapture",
    "apply_v4l2_settings",
    "capture_time_us",
    "list_cameras",
]
