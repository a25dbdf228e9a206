"""Frames in and out: lossless FFV1 video files, any video PyAV can read, and folders of images.

Every frame that crosses this module is a C-contiguous ``numpy.uint8`` array of shape (H, W, 3) in RGB
order (not OpenCV's BGR), or, for a reader opened with ``grey`` (or a grey writer), of shape (H, W): the
frame's luma (BT.601, full range), which is all the receiver's pipeline needs of a frame. A grey reader
takes it without a detour through RGB where the file stores it: the Y plane of a YUV video (limited-range
Y stretched to full range), a grey video's pixels, a JPEG decoded to grey by libjpeg.

Writing: :class:`FfvWriter` stores FFV1 in Matroska with pixel format ``bgr0``. FFV1 is lossless, and
``bgr0`` is the only 8-bit-per-channel RGB layout the FFV1 encoder accepts (the planar ``gbrp`` is
offered only at 9 bits and up): going from RGB24 to ``bgr0`` and back only reorders bytes and adds an
unused padding byte, so frames come back bit-identical. The YUV formats would round the colour
conversion and so are not lossless for RGB input.

Reading: :func:`open_frames` returns a streaming :class:`FrameSource`; a video is decoded one packet
at a time, a folder of images is read one file at a time (through :mod:`ipt.imageio`, never handing
OpenCV a path). A recording may be read with ``skip_bad``: a frame that cannot be decoded is then
skipped and counted rather than ending the stream, and a file shorter than its header says is reported.

A disk that cannot take the video (full, read-only) is a :class:`~ipt.fileio.WriteError` naming it.
"""

from __future__ import annotations

import abc
import contextlib
import math
import re
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path
from types import TracebackType
from typing import Any, Literal, Self

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.fileio import FileBuffer, WriteError, atomic_path, disk_write_error
from ipt.imageio import IMAGE_SUFFIXES, MAX_IMAGE_BYTES, MAX_IMAGE_PIXELS, image_from_bytes, too_many_pixels

# PyAV (``av``) is imported where a video is opened, not here: a folder of images needs none of it, and it
# costs a replay or a daemon's start a twentieth of a second.

__all__ = ["FFV1_PIX_FMT", "IMAGE_SUFFIXES", "FfvWriter", "FrameSource", "VideoError", "open_frames"]

FFV1_PIX_FMT = "bgr0"
"""The pixel format :class:`FfvWriter` stores; see the module docstring for why."""

_RATE_TAG = "IPT_FRAME_RATE"
"""Track tag holding the exact frame rate as ``num/den``.

Matroska keeps timestamps in milliseconds and the frame duration in whole nanoseconds, so a rate such
as 60000/1001 would otherwise read back as 19001/317.
"""

_MAX_RATE_DENOMINATOR = 1001


class VideoError(IptError):
    """A video file or image folder cannot be read or written."""


def _rate_fraction(fps: float | Fraction) -> Fraction:
    """``fps`` as an exact rational: 120 → 120/1, 59.94 → 2997/50, 29.97002997 → 30000/1001."""
    if isinstance(fps, bool) or not isinstance(fps, int | float | Fraction):
        raise VideoError(f"frame rate must be a number, not {fps!r}")
    if isinstance(fps, float) and not math.isfinite(fps):
        raise VideoError(f"frame rate must be finite, not {fps}")
    rate = fps if isinstance(fps, Fraction) else Fraction(fps).limit_denominator(_MAX_RATE_DENOMINATOR)
    if rate <= 0:
        raise VideoError(f"frame rate must be positive, not {fps}")
    return rate


def _check_frame(frame: Any, width: int, height: int, what: str, grey: bool = False) -> npt.NDArray[np.uint8]:
    """``frame`` as a C-contiguous RGB (or, with ``grey``, single-channel) array of the given size, or a
    :class:`VideoError`."""
    if not isinstance(frame, np.ndarray):
        raise VideoError(f"{what}: a frame must be a numpy array, not {type(frame).__name__}")
    if frame.dtype != np.uint8:
        raise VideoError(f"{what}: frames must have dtype uint8, not {frame.dtype}")
    expected = (height, width) if grey else (height, width, 3)
    if frame.shape != expected:
        layout = "height, width" if grey else "height, width, RGB"
        raise VideoError(f"{what}: frame has shape {frame.shape}, expected {expected} ({layout})")
    return np.ascontiguousarray(frame)


class FfvWriter:
    """Write RGB frames (or grey ones, with ``grey``: pixel format ``gray``, as a mono camera gives them) to
    a lossless FFV1/Matroska file that appears at ``path`` only when complete.

    Frames go to a temporary ``….partial.mkv`` file beside ``path``; :meth:`close` (or leaving the
    ``with`` block normally) renames it onto ``path``. If the ``with`` block raises, or :meth:`abort`
    is called, the temporary file is removed and ``path`` is left as it was.
    """

    def __init__(self, path: str | Path, width: int, height: int, fps: float | Fraction, grey: bool = False) -> None:
        self.path = Path(path)
        self.grey = grey
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise VideoError(f"{self.path}: {name} must be a positive integer, not {value!r}")
        self.width = width
        self.height = height
        self.rate = _rate_fraction(fps)
        self.frames_written = 0
        self._closed = False
        self._container: Any = None
        self._stream: Any = None
        self._stack = contextlib.ExitStack()
        try:
            tmp = self._stack.enter_context(atomic_path(self.path))
        except OSError as e:
            raise VideoError(f"{self.path}: cannot create a file here: {e.strerror or e}") from e
        import av

        try:
            self._container = av.open(str(tmp), mode="w", format="matroska")
            self._stream = self._container.add_stream("ffv1", rate=self.rate)
            self._stream.width = width
            self._stream.height = height
            self._stream.pix_fmt = "gray" if grey else FFV1_PIX_FMT
            # level 3 with per-slice CRCs: the current FFV1 version, and damage is detected on reading.
            self._stream.options = {"level": "3", "slicecrc": "1", "g": "1"}
            self._stream.metadata[_RATE_TAG] = f"{self.rate.numerator}/{self.rate.denominator}"
        except (av.FFmpegError, OSError) as e:
            self._fail()
            raise VideoError(f"{self.path}: cannot start an FFV1 video: {e}") from e

    def write(self, frame_rgb: npt.NDArray[np.uint8]) -> None:
        """Append one H×W×3 uint8 RGB frame (H×W for a grey writer)."""
        if self._closed:
            raise VideoError(f"{self.path}: write after the writer was closed")
        frame = _check_frame(frame_rgb, self.width, self.height, str(self.path), self.grey)
        import av

        video_frame = av.VideoFrame.from_ndarray(frame, format="gray" if self.grey else "rgb24")
        video_frame.pts = self.frames_written
        video_frame.time_base = 1 / self.rate
        try:
            for packet in self._stream.encode(video_frame):
                self._container.mux(packet)
        except (av.FFmpegError, OSError) as e:
            self._fail()
            if (disk := disk_write_error(self.path, e)) is not None:
                raise disk from None
            raise VideoError(f"{self.path}: writing frame {self.frames_written} failed: {e}") from e
        self.frames_written += 1

    def close(self) -> None:
        """Finish the file and move it to ``path``. Calling it again does nothing."""
        if self._closed:
            return
        import av

        try:
            if self.frames_written == 0:
                self._container.start_encoding()  # so that even an empty video has a valid header
            for packet in self._stream.encode(None):
                self._container.mux(packet)
            self._container.close()
        except (av.FFmpegError, OSError) as e:
            self._fail()
            if (disk := disk_write_error(self.path, e)) is not None:
                raise disk from None
            raise VideoError(f"{self.path}: finishing the video failed: {e}") from e
        self._closed = True
        try:
            self._stack.close()  # renames the temporary file onto self.path (or hands it to an output group)
        except WriteError:
            raise
        except OSError as e:
            raise VideoError(f"{self.path}: cannot move the finished video into place: {e}") from e

    def abort(self) -> None:
        """Drop everything written so far: remove the temporary file, leave ``path`` untouched."""
        if not self._closed:
            self._fail()

    def _fail(self) -> None:
        import av

        self._closed = True
        if self._container is not None:
            with contextlib.suppress(av.FFmpegError, OSError):
                self._container.close()
        # Tell atomic_path the body failed, so that it removes the temporary file instead of renaming.
        self._stack.__exit__(VideoError, VideoError("aborted"), None)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class FrameSource(abc.ABC):
    """A stream of RGB (or luma) frames from a video file or an image folder; use it as an iterator.

    Attributes: ``path``; ``width`` and ``height`` in pixels (every frame has this size);
    ``frame_count`` (None when a video container does not say); ``fps`` (None when unknown, always
    for an image folder). Close it, or use it as a context manager, to release the file.

    A recording read with ``skip_bad`` (:func:`open_frames`) keeps going past a frame that cannot be
    decoded, or an image that cannot be read or differs in size from the first: such a frame is skipped
    and counted in ``skipped`` (``last_skipped`` says why). ``index`` is the number of the frame last
    returned, counting the skipped ones, so that frame k keeps its time k/fps. Without ``skip_bad`` such a
    frame raises :class:`VideoError`. After the last frame, :meth:`shortfall` says whether the file held
    fewer frames than its header announced (a truncated file).
    """

    path: Path
    width: int
    height: int
    frame_count: int | None
    fps: float | None
    skip_bad: bool = False
    skipped: int = 0
    last_skipped: str | None = None
    index: int = -1

    def __iter__(self) -> Self:
        return self

    @abc.abstractmethod
    def __next__(self) -> npt.NDArray[np.uint8]: ...

    @abc.abstractmethod
    def close(self) -> None:
        """Release the file; iteration then ends."""

    def shortfall(self) -> str | None:
        """Once the frames ran out: a sentence if the file announced more than it held, else ``None``."""
        return None

    def _skip(self, why: str) -> None:
        """Count a frame that cannot be used, or raise if bad frames are not skipped."""
        if not self.skip_bad:
            raise VideoError(why)
        self.skipped += 1
        self.last_skipped = why

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def _stream_fps(stream: Any) -> float | None:
    tagged = (stream.metadata or {}).get(_RATE_TAG)
    if tagged:
        try:
            rate = Fraction(tagged)
        except (ValueError, ZeroDivisionError):
            rate = Fraction(0)
        if rate > 0:
            return float(rate)
    for rate in (stream.average_rate, stream.guessed_rate):
        if rate is not None and rate > 0:
            return float(rate)
    return None


#: Limited-range ("MPEG", studio swing) luma 16..235 to full range 0..255, clipped: what OpenCV's and
#: FFmpeg's conversions of such YUV to RGB do to the luma, so a Y plane gives the RGB frame's luma.
LIMITED_TO_FULL_LUMA = np.clip(np.round((np.arange(256) - 16) * 255 / 219), 0, 255).astype(np.uint8)


def expand_limited_luma(y: npt.NDArray[np.uint8]) -> npt.NDArray[np.uint8]:
    """A limited-range Y plane as full-range luma (:data:`LIMITED_TO_FULL_LUMA`)."""
    return np.asarray(cv2.LUT(np.ascontiguousarray(y), LIMITED_TO_FULL_LUMA), dtype=np.uint8)


#: 8-bit pixel formats whose first plane is the luma, one byte a pixel (FFmpeg's names); "yuvj" ones and
#: "gray" are full range, the others full range only if the frame says so.
_LUMA_PLANE_FORMATS = frozenset(
    {"gray", "nv12", "nv21", "yuv410p", "yuv411p", "yuv420p", "yuv422p", "yuv440p", "yuv444p"}
    | {"yuvj411p", "yuvj420p", "yuvj422p", "yuvj440p", "yuvj444p"}
)
_FULL_RANGE = 2  # AVCOL_RANGE_JPEG


def _luma(frame: Any) -> npt.NDArray[np.uint8]:
    """A decoded PyAV video frame's luma (H×W, full range), taken from its luma plane where it has one; a
    frame stored otherwise (RGB, packed YUV) is converted to RGB and its luma taken by OpenCV (FFmpeg's own
    conversion to "gray" cost four times as much on FFV1 ``bgr0``), FFV1's ``bgr0`` without the conversion
    (the same luma, a quarter of the time: 0.2 instead of 0.7 ms a 640x360 frame)."""
    name = frame.format.name
    if name in _LUMA_PLANE_FORMATS:
        plane = frame.planes[0]
        rows = np.frombuffer(plane, np.uint8).reshape(-1, plane.line_size)
        y = rows[: frame.height, : frame.width]
        if name != "gray" and not name.startswith("yuvj") and frame.color_range != _FULL_RANGE:
            return expand_limited_luma(y)
        return np.ascontiguousarray(y, dtype=np.uint8)
    if name == FFV1_PIX_FMT:  # FfvWriter's bgr0, read in place: OpenCV's luma of B, G, R and a byte it ignores
        plane = frame.planes[0]
        rows = np.frombuffer(plane, np.uint8).reshape(-1, plane.line_size)
        bgrx = rows[: frame.height, : frame.width * 4].reshape(frame.height, frame.width, 4)
        return np.asarray(cv2.cvtColor(bgrx, cv2.COLOR_BGRA2GRAY), dtype=np.uint8)
    rgb = np.ascontiguousarray(frame.to_ndarray(format="rgb24"), dtype=np.uint8)
    return np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), dtype=np.uint8)


class _VideoSource(FrameSource):
    """Frames decoded one packet at a time from a file PyAV can open (a damaged packet costs one frame)."""

    def __init__(self, path: Path, skip_bad: bool = False, grey: bool = False, paced: bool = False) -> None:
        self.path = path
        self.skip_bad = skip_bad
        self.grey = grey
        import av

        try:
            self._container: Any = av.open(str(path), mode="r")
        except av.EOFError as e:
            # A well-formed header followed by nothing: what a video with zero frames looks like.
            raise VideoError(f"{path}: contains no frames") from e
        except (av.FFmpegError, OSError, UnicodeDecodeError) as e:
            raise VideoError(f"{path}: not a video file PyAV can read") from e
        try:
            if not self._container.streams.video:
                raise VideoError(f"{path}: has no video stream")
            stream = self._container.streams.video[0]
            # Frame threads (AUTO) decode several frames at once: the most frames a processor-second when they
            # are read as fast as they come, but their start and look-ahead cost ~0.1 s of processor time
            # before the first frame is out. Frames read at a camera's rate need no more than slice threads.
            stream.thread_type = "SLICE" if paced else "AUTO"
            self.fps = _stream_fps(stream)
            self.frame_count = int(stream.frames) if stream.frames and stream.frames > 0 else None
            self._announced = self.frame_count
            duration = self._container.duration  # microseconds (AV_TIME_BASE), from the container's header
            if self._announced is None and duration and self.fps:
                self._announced = round(duration / 1e6 * self.fps)
            self._items: Iterator[npt.NDArray[np.uint8] | Exception] = self._decoded(stream)
            self._damaged: str | None = None  # why the container could not be read on, if it could not
            self._position = 0  # frames taken from the file so far, bad ones included
            # Decode the first frame now, so that an empty or broken file fails here with one clear
            # line, and so that width and height are those of the frames actually decoded.
            first = self._first()
            self.height, self.width = first.shape[:2]
            self._pending: npt.NDArray[np.uint8] | None = first
        except BaseException:
            self._container.close()
            raise

    def _decoded(self, stream: Any) -> Iterator[npt.NDArray[np.uint8] | Exception]:
        """Each frame of the file in order: its pixels, or the error that lost it."""
        import av

        decode_errors = (av.FFmpegError, OSError, ValueError)
        packets = self._container.demux(stream)
        while True:
            try:
                packet = next(packets)
            except StopIteration:
                return
            except decode_errors as e:  # the container itself is damaged: nothing after this can be found
                self._damaged = str(e)
                return
            try:
                frames = packet.decode()
            except decode_errors as e:
                yield e
                continue
            for frame in frames:
                try:
                    if self.grey:
                        yield _luma(frame)
                    else:
                        yield np.ascontiguousarray(frame.to_ndarray(format="rgb24"), dtype=np.uint8)
                except decode_errors as e:
                    yield e

    def _take(self) -> npt.NDArray[np.uint8] | Exception | None:
        item = next(self._items, None)
        if item is not None:
            self._position += 1
        return item

    def _first(self) -> npt.NDArray[np.uint8]:
        while True:
            item = self._take()
            if item is None:
                if self._position == 0:
                    raise VideoError(f"{self.path}: contains no frames")
                raise VideoError(f"{self.path}: none of its {self._position} frames can be decoded")
            if not isinstance(item, Exception):
                return item
            self._skip(f"{self.path}: decoding frame {self._position - 1} failed: {item}")

    def __next__(self) -> npt.NDArray[np.uint8]:
        if self._pending is not None:
            rgb, self._pending = self._pending, None
            self.index = self._position - 1
            return rgb
        while True:
            if self._container is None:
                raise StopIteration
            item = self._take()
            if item is None:
                self.close()
                raise StopIteration
            k = self._position - 1
            if isinstance(item, Exception):
                self._skip(f"{self.path}: decoding frame {k} failed: {item}")
                continue
            if item.shape[:2] != (self.height, self.width):
                h, w = item.shape[:2]
                self._skip(f"{self.path}: frame {k} is {w}x{h}, the first frame is {self.width}x{self.height}")
                continue
            self.index = k
            return item

    def shortfall(self) -> str | None:
        if self._damaged is not None:
            return f"{self.path}: the file is damaged after frame {self._position} ({self._damaged}); it ends there"
        if self._announced is not None and self._position + 1 < self._announced:
            return (
                f"{self.path}: ends after {self._position} frames, but its header announces {self._announced}: "
                "the file is truncated"
            )
        return None

    def close(self) -> None:
        self._pending = None
        if self._container is not None:
            self._container.close()
            self._container = None


def _natural_key(name: str) -> tuple[tuple[int | str, ...], str]:
    """Sort key that orders embedded numbers by value: frame2 < frame10."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p.casefold() for i, p in enumerate(parts)), name


class _ImageFolderSource(FrameSource):
    """The images in a folder in natural name order, each read when it is needed.

    An image whose header gives more pixels than ``max_pixels`` (the first image) or than the first image
    (the others; with ``skip_bad`` only, without it, more than ``max_pixels``) is skipped and counted, with
    or without ``skip_bad``, before it is decoded: an image bomb costs neither memory nor time.
    """

    def __init__(
        self,
        path: Path,
        skip_bad: bool = False,
        grey: bool = False,
        max_pixels: int | None = None,
        limit: str | None = None,
    ) -> None:
        self.path = path
        self.skip_bad = skip_bad
        self._mode: Literal["rgb", "grey"] = "grey" if grey else "rgb"
        self._max_pixels = MAX_IMAGE_PIXELS if max_pixels is None else max_pixels
        self._limit = limit
        self._buffer = FileBuffer()  # each image read into the same memory (see FileBuffer)
        self.oversized = 0
        """Images skipped undecoded because their header gives too many pixels (counted in ``skipped`` too)."""
        try:
            entries = list(path.iterdir())
        except OSError as e:
            raise VideoError(f"{path}: cannot list the folder: {e.strerror or e}") from e
        self._files = sorted(
            (f for f in entries if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith(".") and f.is_file()),
            key=lambda f: _natural_key(f.name),
        )
        if not self._files:
            suffixes = "/".join(sorted(s.lstrip(".").upper() for s in IMAGE_SUFFIXES))
            raise VideoError(f"{path}: folder holds no images ({suffixes})")
        self.frame_count = len(self._files)
        self.fps = None
        self._next = 0
        self._first_name = ""
        self.height = self.width = 0
        first: npt.NDArray[np.uint8] | None = None
        while first is None:
            if self._next >= len(self._files):
                raise VideoError(f"{path}: none of its {len(self._files)} images can be read")
            first = self._read(self._files[self._next])
            self._next += 1
        self._first_name = self._files[self._next - 1].name
        self.height, self.width = first.shape[:2]
        self._pending: npt.NDArray[np.uint8] | None = first
        self._closed = False

    def _read(self, file: Path) -> npt.NDArray[np.uint8] | None:
        """The image in ``file``, or None if it was skipped (see the class doc)."""
        try:
            data = self._buffer.read(file, VideoError, "an image file", max_bytes=MAX_IMAGE_BYTES)
        except VideoError as e:
            self._skip(str(e))
            return None
        first = self.width * self.height
        if first and self.skip_bad and first < self._max_pixels:
            why = too_many_pixels(data, first, f"the first image {self._first_name}'s {self.width}x{self.height}")
        else:
            why = too_many_pixels(data, self._max_pixels, self._limit)
        if why is not None:  # skipped even without skip_bad: decoding it is the harm
            self.skipped += 1
            self.oversized += 1
            self.last_skipped = f"{file}: {why}"
            return None
        try:
            return image_from_bytes(data, file, self._mode, VideoError)
        except VideoError as e:
            self._skip(str(e))
            return None

    def __next__(self) -> npt.NDArray[np.uint8]:
        if self._closed:
            raise StopIteration
        if self._pending is not None:
            rgb, self._pending = self._pending, None
            self.index = self._next - 1
            return rgb
        while self._next < len(self._files):
            file = self._files[self._next]
            self._next += 1
            image = self._read(file)
            if image is None:
                continue
            if image.shape[:2] != (self.height, self.width):
                h, w = image.shape[:2]
                self._skip(
                    f"{file}: image is {w}x{h}, but the first image {self._first_name} is {self.width}x{self.height}"
                )
                continue
            self.index = self._next - 1
            return image
        raise StopIteration

    def close(self) -> None:
        self._closed = True
        self._pending = None


def open_frames(
    path: str | Path,
    *,
    skip_bad: bool = False,
    grey: bool = False,
    max_pixels: int | None = None,
    limit: str | None = None,
    paced: bool = False,
) -> FrameSource:
    """Open a video file (anything PyAV reads) or a folder of PNG/JPG/BMP/TIFF images as RGB frames (with
    ``grey``: as H×W luma frames, see the module docstring).

    Raises :class:`VideoError` with one line naming the file if it is missing, unreadable, has no
    video stream or no frames, or (for a folder) if an image differs in size from the first. With
    ``skip_bad`` a frame that cannot be decoded or read, or has another size, is skipped and counted
    instead (see :class:`FrameSource`); only a file with no usable frame at all is an error. An image in a
    folder whose header gives more than ``max_pixels`` pixels (default
    :data:`~ipt.imageio.MAX_IMAGE_PIXELS`; ``limit`` names the cap in the sentence) is skipped and counted
    undecoded in any case. ``paced``: the frames will be read at a camera's rate, not as fast as they can be
    decoded (the daemon's ``--realtime``): a video is decoded without frame threads, whose start costs more
    processor time before the first frame than they save at that rate.
    """
    p = Path(path)
    if p.is_dir():
        return _ImageFolderSource(p, skip_bad, grey, max_pixels, limit)
    if not p.exists():
        raise VideoError(f"{p}: no such file or folder")
    return _VideoSource(p, skip_bad, grey, paced)
