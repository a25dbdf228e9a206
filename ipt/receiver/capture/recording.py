"""A recording as a frame source: a video file or a folder of images, read once to its end."""

from __future__ import annotations

import time
from pathlib import Path

from ipt.config.models import MAX_RATE_HZ, MIN_CAMERA_RATE_HZ
from ipt.receiver.capture.source import (
    CapturedFrame,
    CaptureError,
    Clock,
    Pacer,
    Sleep,
    capture_time_us,
)
from ipt.videoio import FrameSource, open_frames


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
        # A frame larger than the camera's (an image bomb in a folder) is skipped undecoded.
        cap, limit = (
            (None, None)
            if self.size is None
            else (self.size[0] * self.size[1], "the camera's {}x{}".format(*self.size))
        )
        source = open_frames(self.path, skip_bad=True, grey=self.grey, max_pixels=cap, limit=limit, paced=self.live)
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
