"""The flight log: every frame's ROS 2 messages into an MCAP file that Foxglove and ``ros2 bag`` open.

Topics (schemas ``ros2msg``, messages ``cdr``, written with mcap-ros2-support; no ROS needed):
``/ipt/pose``, ``/ipt/odom``, ``/tf`` and ``/ipt/diagnostics`` as :mod:`ipt.receiver.outputs.ros.frames` makes
them, and, if asked, ``/ipt/difference`` (``foxglove_msgs/msg/CompressedImage``, JPEG): the raw
difference between a frame and the one a projector period before it (no alignment, gain
:data:`DIFFERENCE_GAIN` around mid-grey), a few times a second. Messages are logged at their header
stamp, so a player replays the flight at the pace it was captured. A metadata record ``ipt`` holds the
offset from those stamps back to the source's own capture times (``ipt eval`` uses it).

The event loop only queues messages (:meth:`McapRecorder.put`, never blocking); a writer thread encodes
and writes them. If the disk does not keep up, the queue's overflow is dropped and counted; if a write
fails (a full disk, a removed USB stick) the failure is reported once, the recording stops there and
later messages are counted as lost, while localisation and the other outputs go on. The file is written
as ``NAME.partial`` beside the target and renamed when it is complete, so an interrupted run leaves no
file that looks complete; what a partial file holds up to its last complete chunk stays readable
(``ipt eval`` reads it as a stream when the summary at the end is missing).
"""

from __future__ import annotations

import contextlib
import errno
import os
import queue
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import cv2
import numpy as np
import numpy.typing as npt

from ipt.fileio import WriteError, output_target
from ipt.receiver.outputs.ros.frames import Outgoing
from ipt.rosmsg import COMPRESSED_IMAGE, DIAGNOSTICS, METADATA_NAME, ODOMETRY, POSE, TF, message_definition, time_msg

U8 = npt.NDArray[np.uint8]

CHUNK_BYTES = 256 * 1024
"""MCAP chunk size: messages reach the disk a chunk at a time, so a failure loses at most one chunk."""
QUEUE_SIZE = 2048
"""Messages waiting for the writer thread; beyond that they are dropped (and counted)."""
CLOSE_TIMEOUT_S = 1.0
"""How long closing waits for the writer thread to write what is queued and finish the file."""
DIFFERENCE_GAIN = 4.0
"""Grey levels of the difference image per grey level of difference (128 is no difference)."""
JPEG_QUALITY = 90
PARTIAL_SUFFIX = ".partial"
RECORDED_TYPES = (POSE, ODOMETRY, TF, DIAGNOSTICS, COMPRESSED_IMAGE)


class DifferenceSampler:
    """Which frames make the difference images: a frame at least ``1 / image_hz`` of capture time after the
    last image's, paired with the next frame that lies one projector period (±half a period) after it.
    Pure apart from the grey conversion of the two frames it keeps."""

    def __init__(self, image_hz: float, projector_hz: float) -> None:
        self.interval_us = 1e6 / image_hz if image_hz > 0 else None
        self.period_us = 1e6 / projector_hz
        self._last_us: int | None = None
        self._pending: tuple[int, U8] | None = None

    def offer(self, capture_time_us: int, image: U8) -> tuple[int, U8, U8] | None:
        """(capture time, earlier grey, this grey) when this frame completes a pair, else None."""
        if self.interval_us is None:
            return None
        if self._pending is not None:
            t0, grey0 = self._pending
            periods = (capture_time_us - t0) / self.period_us
            if 0.5 <= periods < 1.5:
                self._pending = None
                return capture_time_us, grey0, _grey(image)
            if periods >= 1.5 or periods < 0:  # the partner was lost: start again
                self._pending = None
        if self._pending is None and (self._last_us is None or capture_time_us - self._last_us >= self.interval_us):
            self._last_us = capture_time_us
            self._pending = (capture_time_us, _grey(image))
        return None


def _grey(image: U8) -> U8:
    """An RGB frame's luma; a grey frame (a mono camera's, or the luma a source handed over) as it is."""
    if image.ndim == 2:
        return image
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY), np.uint8)


def difference_jpeg(before: U8, after: U8, gain: float = DIFFERENCE_GAIN) -> bytes:
    """The JPEG of ``128 + gain · (after - before)``, clipped to 0..255."""
    diff = after.astype(np.float32) - before.astype(np.float32)
    image = np.clip(128.0 + gain * diff, 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return bytes(np.asarray(buf, np.uint8).tobytes())


@dataclass
class RecorderStats:
    """Counts of one recording."""

    written: int = 0
    """Messages written."""
    images: int = 0
    dropped: int = 0
    """Messages dropped because the writer thread was behind (the queue was full)."""
    lost: int = 0
    """Messages not written because an earlier write had failed."""
    invalid: int = 0
    """Messages that could not be encoded (a bug: reported once)."""
    failure: str | None = None
    """The write error that stopped the recording, if one did."""


def _open_partial(path: Path) -> tuple[Path, BinaryIO]:
    """Create ``path.partial`` (or raise :class:`WriteError` naming ``path``). A link is followed (the partial
    file goes beside its target); a character device is opened itself, written through, never replaced; a
    pipe, a socket or a folder is refused (:func:`ipt.fileio.output_target`)."""
    if path.is_dir():
        raise WriteError(errno.EISDIR, "is a directory", str(path))
    target, through = output_target(path)
    partial = target if through else target.with_name(target.name + PARTIAL_SUFFIX)
    try:
        return partial, partial.open("wb")
    except OSError as exc:
        raise WriteError(exc.errno, exc.strerror or str(exc), str(path)) from None
    except ValueError:  # a NUL character in the name
        raise WriteError(errno.EINVAL, "the name contains a NUL character", str(path)) from None


class McapRecorder:
    """An MCAP recording fed from the event loop (see the module doc). :meth:`start`, :meth:`put` ...,
    :meth:`close`; the file is opened (and its header written) in the constructor, so an unwritable path
    fails at start-up."""

    def __init__(
        self,
        path: Path,
        *,
        metadata: Mapping[str, str] | None = None,
        image_hz: float = 0.0,
        projector_hz: float = 60.0,
        camera_frame_id: str = "camera",
        image_topic: str = "/ipt/difference",
        report: Callable[[str], None] | None = None,
        queue_size: int = QUEUE_SIZE,
    ) -> None:
        from mcap_ros2.writer import Writer

        self.path = Path(path)
        self.report = report
        self.stats = RecorderStats()
        self.images = DifferenceSampler(image_hz, projector_hz)
        self.camera_frame_id, self.image_topic = camera_frame_id, image_topic
        self._metadata = dict(metadata or {})
        self._metadata_written = False
        self._target, self._through = output_target(self.path)  # the link's target; a device: no rename or unlink
        self.partial, self._file = _open_partial(self.path)
        try:
            self._writer = Writer(self._file, chunk_size=CHUNK_BYTES)
            self._schemas = {
                name: self._writer.register_msgdef(name, message_definition(name)) for name in RECORDED_TYPES
            }
        except OSError as exc:
            self._file.close()
            raise WriteError(exc.errno, exc.strerror or str(exc), str(self.path)) from None
        self._queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(maxsize=queue_size)
        self._thread = threading.Thread(target=self._run, name="ipt-record", daemon=True)
        self._closed = False
        self._aborting = False
        self.completed = False
        """The file was finished and renamed onto :attr:`path`."""

    # -- the event loop's side ---------------------------------------------------------------------------

    def start(self) -> None:
        """Start the writer thread."""
        self._thread.start()

    def _enqueue(self, item: tuple[Any, ...], count: int = 1) -> None:
        if self._closed:
            return
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.stats.dropped += count

    def set_metadata(self, values: Mapping[str, str]) -> None:
        """Add to the ``ipt`` metadata record (written once, before the first message, or at the end)."""
        self._enqueue(("metadata", dict(values)), 0)

    def put(self, items: Sequence[Outgoing]) -> None:
        """Queue a frame's messages (never blocks; overflow is dropped and counted)."""
        for item in items:
            self._enqueue(("message", item), 1)

    def offer_frame(self, capture_time_us: int, stamp_ns: int, image: U8) -> None:
        """Let the difference-image sampler see a frame; queue an image when one is due."""
        pair = self.images.offer(capture_time_us, image)
        if pair is not None:
            self._enqueue(("image", stamp_ns, pair[1], pair[2]), 1)

    def close(self, timeout_s: float = CLOSE_TIMEOUT_S) -> bool:
        """Write what is queued, finish the file and rename it onto :attr:`path` (unless a write failed);
        True when that happened within ``timeout_s``."""
        if self._closed:
            return self.completed
        self._closed = True
        if not self._thread.is_alive() and not self._thread.ident:
            self._thread.start()  # never started: still finish the file
        with contextlib.suppress(queue.Full):  # a writer that long behind is reported just below
            self._queue.put(None, timeout=timeout_s)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            self._say(f"{self.partial}: not finished within {timeout_s:g} s; it holds what was written so far")
        return self.completed

    def abort(self) -> None:
        """Give the recording up (the daemon could not start): close and remove the partial file, so nothing
        is left that looks like a recording."""
        self._aborting = True
        if self._thread.is_alive():
            self.close()  # the writer thread sees _aborting when it finishes
            return
        self._closed = True
        self._discard()

    def _discard(self) -> None:
        with contextlib.suppress(OSError):
            self._file.close()
        if not self._through:
            with contextlib.suppress(OSError):
                self.partial.unlink()

    # -- the writer thread -------------------------------------------------------------------------------

    def _say(self, text: str) -> None:
        if self.report is not None:
            self.report(f"record: {text}")

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                break
            kind = item[0]
            if self.stats.failure is not None:
                self.stats.lost += kind != "metadata"
                continue
            try:
                if kind == "metadata":
                    self._metadata.update(item[1])
                elif kind == "message":
                    self._write_metadata_once()
                    self._write(item[1])
                else:
                    self._write_metadata_once()
                    self._write_image(item[1], item[2], item[3])
            except OSError as exc:
                self._fail(exc)
            except Exception as exc:  # an encoding bug on one message: report once, go on
                self.stats.invalid += 1
                if self.stats.invalid == 1:
                    self._say(f"a message could not be encoded ({type(exc).__name__}: {exc}); counting, going on")
        self._finish()

    def _write_metadata_once(self) -> None:
        if not self._metadata_written:
            self._metadata_written = True
            self._writer.add_metadata(METADATA_NAME, self._metadata)

    def _write(self, item: Outgoing) -> None:
        schema = self._schemas[item.type_name]
        self._writer.write_message(item.topic, schema, item.message, log_time=item.stamp_ns, publish_time=item.stamp_ns)
        self.stats.written += 1

    def _write_image(self, stamp_ns: int, before: U8, after: U8) -> None:
        message = {
            "timestamp": time_msg(stamp_ns),
            "frame_id": self.camera_frame_id,
            "data": difference_jpeg(before, after),
            "format": "jpeg",
        }
        schema = self._schemas[COMPRESSED_IMAGE]
        self._writer.write_message(self.image_topic, schema, message, log_time=stamp_ns, publish_time=stamp_ns)
        self.stats.written += 1
        self.stats.images += 1

    def _fail(self, exc: OSError) -> None:
        self.stats.failure = f"{exc.strerror or exc}"
        self.stats.lost += 1
        self._say(
            f"{self.partial}: write failed ({self.stats.failure}); the recording stops here, localisation and the "
            "other outputs go on"
        )

    def _finish(self) -> None:
        if self._aborting:
            self._discard()
            return
        try:
            if self.stats.failure is None:
                self._write_metadata_once()
                self._writer.finish()
                self._file.flush()
                if not self._through:
                    os.fsync(self._file.fileno())
        except OSError as exc:
            self._fail(exc)
        finally:
            try:
                self._file.close()
            except OSError as exc:
                if self.stats.failure is None:
                    self._fail(exc)
        if self.stats.failure is not None:
            self._say(f"{self.partial} is incomplete: it holds the chunks written before the failure")
            return
        try:
            if not self._through:
                os.replace(self.partial, self._target)
        except OSError as exc:
            self._fail(exc)
            return
        self.completed = True

    def summary(self) -> str:
        """One line for the end of the run."""
        s = self.stats
        if s.failure is None:
            where = self.path if self.completed else self.partial
            return (
                f"record: {where}: {s.written} messages ({s.images} images), dropped {s.dropped} (writer behind)"
                + ("" if self.completed else "; not finished")
            )
        return (
            f"record: {self.partial}: stopped by a write error ({s.failure}) after {s.written} messages (the last "
            f"unfinished chunk of those, up to {CHUNK_BYTES // 1024} KiB, is not in the file); {s.lost} lost after it, "
            f"dropped {s.dropped} (writer behind)"
        )


__all__ = ["DifferenceSampler", "McapRecorder", "RecorderStats", "difference_jpeg"]
