"""A video file or image folder played in a loop, decoded and resized ahead in a thread of its own.

:class:`~ipt.sender.content.VideoScene` decodes a frame when the content thread asks for it, one input
frame ahead of the render: a 24-megapixel photo (hundreds of milliseconds to decode and resize) or the
re-opening of the file at each loop (the seam) then makes the frame late, and the render misses its
deadline. :class:`PrefetchedVideo` shows the same frames (the same file frame for each input frame, the
same resize) but decodes and resizes them in a thread of its own, up to ``ahead_bytes`` of frames ahead
of need: at the end of the file it opens the next loop at once, so the first frames of the next loop are
ready before they are due. A loop whose resized frames fit in ``cache_bytes`` is decoded once: the later
loops are served from memory. :meth:`PrefetchedVideo.prime` fills the buffer before the frame clock
starts.

When the content thread must still wait for a frame (decoding is slower than the frames are due), it
says so once (:meth:`PrefetchedVideo.take_notes`), with the time decoding takes a frame; an image skipped
as too large (:mod:`ipt.imageio`) is said once too.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Final, Self

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.sender.content import ContentError, file_frame_index
from ipt.videoio import FrameSource, VideoError, open_frames

U8 = npt.NDArray[np.uint8]
Opener = Callable[[Path], FrameSource]

AHEAD_BYTES: Final = 192 * 2**20
"""Resized frames decoded ahead of need, at most (16 frames at 1920x2160; at least 2 frames)..."""
AHEAD_FRAMES: Final = 32
"""... and at most this many (about a second of content: enough to hide the re-opening at a loop)."""
CACHE_BYTES: Final = 256 * 2**20
"""A loop whose resized frames fit in this many bytes is decoded once and then played from memory."""
PRIME_TIMEOUT_S: Final = 20.0
""":meth:`PrefetchedVideo.prime` waits at most this long for the buffer to fill."""
SLOW_WAIT_S: Final = 0.005
"""A wait for a frame this long or longer, once the buffer was primed, is said (once): the content is late."""
_COST_FRAMES: Final = 30
"""Decoding time is averaged over this many frames for the note that the content cannot keep up."""


class PrefetchError(IptError):
    """The prefetching source was used wrongly (a bad frame index or rate)."""


def _resize(image: U8, width_px: int, height_px: int) -> U8:
    """As :class:`~ipt.sender.content.VideoScene` resizes (``cv2.INTER_AREA``): the same pixels."""
    if image.shape[:2] == (height_px, width_px):
        return np.ascontiguousarray(image)
    return np.ascontiguousarray(cv2.resize(image, (width_px, height_px), interpolation=cv2.INTER_AREA))


def _open(path: Path) -> FrameSource:
    return open_frames(path)


Key = tuple[int, int]
"""(loop, file frame): the position of a frame in the looped stream."""


class PrefetchedVideo:
    """A video file or image folder resized to the screen and played in a loop, decoded ahead; see the
    module doc. ``opener`` opens the file (tests give a slow one); ``fps`` as for ``VideoScene``;
    ``cache_bytes`` defaults to :data:`CACHE_BYTES`."""

    def __init__(
        self,
        path: str | Path,
        width_px: int,
        height_px: int,
        fps: float | None = None,
        *,
        ahead_bytes: int = AHEAD_BYTES,
        cache_bytes: int | None = None,
        opener: Opener = _open,
    ) -> None:
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise PrefetchError(f"fps must be a positive number, not {fps!r}")
        self.path = Path(path)
        self.width_px, self.height_px = width_px, height_px
        self._opener = opener
        frame_bytes = width_px * height_px * 3
        self._capacity = max(2, min(AHEAD_FRAMES, ahead_bytes // frame_bytes))
        self._cache_limit = max(0, CACHE_BYTES if cache_bytes is None else cache_bytes) // frame_bytes
        first = opener(self.path)  # fails here, with one line, if the file cannot be read at all
        self.fps = fps if fps is not None else first.fps
        self._cond = threading.Condition()
        self._buffer: deque[tuple[Key, U8]] = deque()
        self._cache: list[U8] | None = None  # the whole loop, once it fitted
        self._length: int | None = None  # file frames in a loop, known after the first
        self._rate_hz: float | None = None  # input rate, known from the first frame asked
        self._error: Exception | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last: tuple[Key, U8] | None = None
        self._notes: list[str] = []
        self._said_slow = False
        self._primed = False
        self._skip_notes = 0
        self._costs: deque[float] = deque(maxlen=_COST_FRAMES)
        self.waits = 0
        """Frames the content thread had to wait for (not ready when asked)."""
        self.reopens = 0
        """Times the file was opened again (a new loop, or a seek back)."""
        self._start((0, 0), first)

    # -- the producer --

    def _start(self, at: Key, source: FrameSource | None = None) -> None:
        """(Re)start the decoding thread at ``at``, dropping what was buffered."""
        self._halt()
        self._stop = threading.Event()
        with self._cond:
            self._buffer.clear()
            self._error = None
        self._thread = threading.Thread(
            target=self._produce, args=(at, source, self._stop), name="ipt-prefetch", daemon=True
        )
        self._thread.start()

    def _halt(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            with self._cond:
                self._cond.notify_all()
            thread.join(timeout=5.0)

    def _produce(self, at: Key, source: FrameSource | None, stop: threading.Event) -> None:
        loop, skip_to = at
        try:
            while not stop.is_set():
                if source is None:
                    source = self._opener(self.path)
                    self.reopens += 1
                if not self._play_loop(source, loop, skip_to, stop):
                    return
                source, loop, skip_to = None, loop + 1, 0
        except Exception as exc:  # the file vanished or broke: the consumer raises it (and retries)
            with self._cond:
                self._error = exc
                self._cond.notify_all()
        finally:
            if source is not None:
                source.close()

    def _play_loop(self, source: FrameSource, loop: int, skip_to: int, stop: threading.Event) -> bool:
        """Decode one loop into the buffer; False when nothing more is to be decoded (cached, or stopped)."""
        caching: list[U8] | None = [] if loop == 0 and self._cache_limit > 0 else None
        frames = iter(source)
        k = 0
        try:
            while True:
                t0 = time.perf_counter()
                raw = next(frames, None)
                if raw is None:
                    break
                if stop.is_set():
                    return False
                keep = caching is not None or (k >= skip_to and self._wanted(loop, k))
                image = _resize(raw, self.width_px, self.height_px) if keep else None
                self._costs.append(time.perf_counter() - t0)  # decoding and resizing, not waiting for room
                if caching is not None and image is not None:
                    if len(caching) < self._cache_limit:
                        caching.append(image)
                    else:
                        caching = None
                if image is not None and k >= skip_to and not self._put((loop, k), image, stop):
                    return False
                k += 1
            self._note_skipped(source)
        finally:
            source.close()
        with self._cond:
            if self._length is None:
                if k == 0:
                    raise VideoError(f"{self.path}: contains no frames")
                self._length = k
            if caching is not None and len(caching) == self._length:
                self._cache = caching
                self._cond.notify_all()
                return False
            self._cond.notify_all()
        return True

    def _put(self, key: Key, image: U8, stop: threading.Event) -> bool:
        with self._cond:
            while len(self._buffer) >= self._capacity and not stop.is_set():
                self._cond.wait()
            if stop.is_set():
                return False
            self._buffer.append((key, image))
            self._cond.notify_all()
        return True

    def _wanted(self, loop: int, k: int) -> bool:
        """Whether some input frame shows file frame ``k`` of loop ``loop`` (True while that is unknown)."""
        rate, fps, length = self._rate_hz, self.fps, self._length
        if rate is None or fps is None or (loop > 0 and length is None):
            return True
        j = loop * (length or 0) + k
        i = math.ceil((j - 1e-6) * rate / fps)
        return any(math.floor(n * fps / rate + 1e-6) == j for n in (i - 1, i, i + 1) if n >= 0)

    def _note_skipped(self, source: FrameSource) -> None:
        oversized = getattr(source, "oversized", 0)
        if oversized and self._skip_notes == 0:
            self._skip_notes = oversized
            with self._cond:
                self._notes.append(f"{source.last_skipped}: {oversized} such image(s) skipped at every loop")

    # -- the consumer (the content thread) --

    def file_index(self, index: int, rate_hz: float) -> int:
        """The file frame (before looping) shown as input frame ``index`` at ``rate_hz``: VideoScene's rule."""
        try:
            return file_frame_index(index, self.fps, rate_hz)
        except ContentError as exc:
            raise PrefetchError(str(exc)) from None

    def frame(self, index: int, rate_hz: float) -> U8:
        """File frame for input frame ``index`` at ``rate_hz``: a new array the caller may modify."""
        j = self.file_index(index, rate_hz)
        self._rate_hz = float(rate_hz)
        with self._cond:
            if self._cache is not None:
                image = self._cache[j % len(self._cache)]
                self._last = ((0, j % len(self._cache)), image)
                return image.copy()
        return self._take(j).copy()

    def _key(self, j: int) -> Key:
        return (0, j) if self._length is None else divmod(j, self._length)

    def _take(self, j: int) -> U8:
        waited_from: float | None = None
        while True:
            restart: Key | None = None
            with self._cond:
                if self._cache is not None:
                    image = self._cache[j % len(self._cache)]
                    break
                want = self._key(j)
                if self._last is not None and self._last[0] == want:
                    image = self._last[1]
                    break
                while self._buffer and self._buffer[0][0] < want:
                    self._buffer.popleft()
                    self._cond.notify_all()
                if self._buffer and self._buffer[0][0] == want:
                    image = self._buffer.popleft()[1]
                    self._cond.notify_all()
                    break
                if self._error is not None or self._thread is None or self._buffer:
                    # Failed (raise, and retry at the next frame), or the wanted frame is behind: start again there.
                    error, self._error = self._error, None
                    restart = want
                    if error is not None:
                        self._thread = None
                        raise error
                else:
                    waited_from = time.perf_counter() if waited_from is None else waited_from
                    self._cond.wait(timeout=1.0)
            if restart is not None:
                self._start(restart)
        self._last = (want, image)
        if waited_from is not None:
            self._slow(time.perf_counter() - waited_from)
        return image

    def _slow(self, waited_s: float) -> None:
        """Count a wait; say once that the content cannot keep up."""
        self.waits += 1
        if self._said_slow or not self._primed or waited_s < SLOW_WAIT_S or self._rate_hz is None:
            return  # unprimed: no frame clock (a file sink takes frames as fast as they come)
        self._said_slow = True
        cost = sum(self._costs) / len(self._costs) if self._costs else math.nan
        per_frame = 1e3 / (self.fps if self.fps is not None else self._rate_hz)
        with self._cond:
            self._notes.append(
                f"{self.path}: the content cannot keep up: a frame came {waited_s * 1e3:.0f} ms late; decoding and "
                f"resizing takes {cost * 1e3:.0f} ms a frame (a file frame is due every {per_frame:.0f} ms); "
                "frames will be late (said once)"
            )

    def take_notes(self) -> list[str]:
        """Sentences for the user since the last call (the content cannot keep up, images skipped)."""
        with self._cond:
            notes, self._notes = self._notes, []
        return notes

    def prime(self, stop: threading.Event | None = None, timeout_s: float = PRIME_TIMEOUT_S) -> None:
        """Wait until the buffer is full, the loop is cached or decoding failed (at most ``timeout_s``, or
        until ``stop`` is set): called before the frame clock starts."""
        deadline = time.monotonic() + timeout_s
        self._primed = True
        with self._cond:
            while (
                len(self._buffer) < self._capacity
                and self._cache is None
                and self._error is None
                and not (stop is not None and stop.is_set())
                and time.monotonic() < deadline
            ):
                self._cond.wait(timeout=0.05)

    def last_frame(self) -> U8 | None:
        """A copy of the last frame :meth:`frame` returned, or None before the first."""
        return None if self._last is None else self._last[1].copy()

    def close(self) -> None:
        """Stop decoding and release the file."""
        self._halt()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
