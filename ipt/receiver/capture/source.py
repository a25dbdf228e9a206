"""What every frame source of the receiver is: a :class:`CaptureSource` handing over :class:`CapturedFrame`
objects, paced by a :class:`Pacer` when it plays a recording in real time; and what the live cameras share
(:class:`LiveCamera`)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import numpy.typing as npt

from ipt.config.receiver import CameraControls
from ipt.errors import IptError

U8 = npt.NDArray[np.uint8]
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


MAX_UNDECODABLE_IN_A_ROW = 30
"""A camera whose frames fail to decode this many times in a row is reopened (a single damaged frame,
e.g. an MJPG frame cut short on a busy USB bus, is skipped and counted)."""


class LiveCamera:
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
