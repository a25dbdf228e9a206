"""The flight recorder: the frames the pipeline saw, kept losslessly with their numbers and capture times,
so that ``ipt-receiver replay --frames DIR`` gives back the poses the live run sent, bit for bit.

A recording is a folder:

- ``recording.json``: what the poses depend on besides the frames: the arena (as its validated model), the
  pipeline settings, the map hash, the codec; written first, atomically.
- ``camera.yaml``: a byte copy of the camera_info file the run used.
- ``frames.bin``: records one after the other, each a fixed header (:data:`RECORD`: magic, kind, codec,
  channels, frame number, capture time in µs, width, height, payload length, CRC-32 of the payload, and how
  long a live camera's frame waited before the pipeline took it, in µs, or −1) and a payload. A *frame* record
  holds one image as the pipeline got it (H×W luma, or H×W×3), and its wait, which the pipeline's live rules
  read (``Pipeline.process``'s ``waited_us``; version 1, made before there was any, has none: still read); a
  *finish* record says that the live run finished the results waiting before a capture time because frames
  were dropped (``Pipeline.finish_before``); a *lost* record says that frames were handed to the pipeline but
  not kept here (the writer fell behind), so the replay cannot be exact after it and says so.

The reader stops at the first record that is cut short or fails its CRC (a full disk, a power cut): what
came before stays readable.

Writing happens on the recorder's own thread behind a bounded queue (:data:`QUEUE_FRAMES`), so the event
loop never waits for the disk. A frame that finds the queue full is not kept (counted, a *lost* record
follows). The recording is bounded by size and by duration (:data:`DEFAULT_MAX_MB`,
:data:`DEFAULT_MAX_S`): at the bound it says so once and **stops** (the start of the flight is what a
bit-exact replay needs: the pipeline's state is built from the first frame on). A write that fails (a full
disk, a file-size limit) is said in one line; the file is cut back to its last whole record and recording
stops while the daemon goes on localising.

Codec: ``zstd`` (default when the ``zstandard`` module is present, as it is with ``mcap``): each row minus
its left neighbour (mod 256), then Zstandard level 1; ``raw`` otherwise. Figures in ``docs/doctor.md``.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import struct
import threading
import time
import zlib
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ipt.config.receiver import ReceiverConfig
from ipt.errors import IptError
from ipt.receiver.capture.source import U8, CapturedFrame

FRAMES_NAME = "frames.bin"
META_NAME = "recording.json"
CAMERA_NAME = "camera.yaml"
FORMAT = "ipt-frame-log"
VERSION = 2
RECORD = struct.Struct("<4sBBBxqqHHIIq")
"""Record header: magic, kind, codec, channels, pad, frame number, capture time (µs), width, height, payload
bytes, CRC-32 of the payload, the frame's wait (µs; −1: not a live camera's frame)."""
RECORD_V1 = struct.Struct("<4sBBBxqqHHII")
"""Version 1's header (read still): the same without the wait."""
MAGIC = b"IPTF"
KIND_FRAME, KIND_FINISH, KIND_LOST = 1, 2, 3
CODECS = {"raw": 0, "zstd": 1}
DEFAULT_MAX_MB = 4000.0
"""Default size bound of a recording in MB (10^6 bytes): about 4.5 min of 640×360 luma at 120 FPS with
``zstd`` on the simulated flight (14 MB/s), 2.4 min raw (27.6 MB/s)."""
DEFAULT_MAX_S = 600.0
"""Default duration bound in seconds of capture time."""
QUEUE_FRAMES = 240
"""Frames waiting for the disk at most (2 s at 120 FPS, 55 MB of 640×360 luma)."""


STOPS = "recording stops, localisation goes on"


class FrameLogError(IptError):
    """A frame recording cannot be made or read."""


def default_codec() -> str:
    """``zstd`` when the ``zstandard`` module can be imported, else ``raw``."""
    try:
        import zstandard  # noqa: F401
    except ImportError:
        return "raw"
    return "zstd"


def _encoder(codec: str) -> Callable[[U8], bytes]:
    if codec == "raw":
        return lambda image: image.tobytes()
    import zstandard

    compressor = zstandard.ZstdCompressor(level=1)

    def encode(image: U8) -> bytes:
        diff = image.copy()
        diff[:, 1:] -= image[:, :-1]  # uint8 wraps: exact inverse by a cumulative sum mod 256
        return bytes(compressor.compress(diff.tobytes()))

    return encode


def _decode(codec: int, payload: bytes, shape: tuple[int, ...]) -> U8:
    if codec == CODECS["raw"]:
        return np.frombuffer(payload, np.uint8).reshape(shape).copy()
    if codec != CODECS["zstd"]:
        raise FrameLogError(f"unknown codec {codec}")
    import zstandard

    size = int(np.prod(shape))
    diff = np.frombuffer(zstandard.ZstdDecompressor().decompress(payload, max_output_size=size), np.uint8)
    return np.cumsum(diff.reshape(shape), axis=1, dtype=np.uint8)


@dataclass(frozen=True)
class _Item:
    kind: int
    index: int
    capture_time_us: int
    image: U8 | None = None
    waited_us: int | None = None


class FrameLogWriter:
    """Keeps the frames handed to :meth:`add` in ``folder`` (see the module's doc); ``say`` gets its lines."""

    def __init__(
        self,
        folder: Path,
        meta: dict[str, Any],
        camera_file: Path,
        *,
        say: Callable[[str], None],
        max_mb: float = DEFAULT_MAX_MB,
        max_s: float = DEFAULT_MAX_S,
        codec: str | None = None,
        queue_frames: int = QUEUE_FRAMES,
    ) -> None:
        self.folder, self.say = folder, say
        self.max_bytes, self.max_us = int(max_mb * 1e6), int(max_s * 1e6)
        self.codec = codec if codec is not None else default_codec()
        self.queue_frames = queue_frames
        self._made_folder = not folder.exists()
        _prepare(folder, camera_file, {**meta, "format": FORMAT, "version": VERSION, "codec": self.codec})
        path = folder / FRAMES_NAME
        try:
            self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except OSError as exc:
            raise FrameLogError(f"--record-frames {folder}: cannot create {FRAMES_NAME} ({exc.strerror})") from None
        self._encode = _encoder(self.codec)
        self._items: deque[_Item] = deque()
        self._cond = threading.Condition()
        self._closing = False
        self.stopped: str | None = None
        """Why recording stopped early (the bound, a write error), once it did."""
        self.frames = self.lost = 0
        self.bytes = 0
        self._pending_lost = self._queued = 0
        self._ended = False
        self._first_us: int | None = None
        self.encode_s = 0.0
        """Processor time spent encoding and writing, on the recorder's thread."""
        self._thread = threading.Thread(target=self._run, name="ipt-framelog", daemon=True)
        self._thread.start()

    def add(self, frame: CapturedFrame, waited_us: int | None = None) -> None:
        """Keep this frame (it is about to go to the pipeline, with ``waited_us``); never blocks."""
        if self.stopped is not None or self._ended:
            return
        if self._first_us is None:
            self._first_us = frame.capture_time_us
        if frame.capture_time_us - self._first_us >= self.max_us:
            self._ended = True  # what waits for the disk is still written
            self.say(f"frame recording: reached its bound of {self.max_us / 1e6:g} s at frame {frame.index}; {STOPS}")
            return
        with self._cond:
            if self._queued >= self.queue_frames:
                self._pending_lost += 1
                self.lost += 1
                return
            if self._pending_lost:
                self._items.append(_Item(KIND_LOST, frame.index, frame.capture_time_us))  # before this frame
                self._pending_lost = 0
            # A copy (20 µs at 640x360): the frame is kept as the pipeline got it, whatever is done to it later.
            item = _Item(KIND_FRAME, frame.index, frame.capture_time_us, frame.image.copy(), waited_us)
            self._items.append(item)
            self._queued += 1
            self._cond.notify()

    def finish_before(self, capture_time_us: int) -> None:
        """The live run finished the results waiting before this capture time (frames were dropped)."""
        if self.stopped is None:
            with self._cond:
                self._items.append(_Item(KIND_FINISH, -1, capture_time_us))
                self._cond.notify()

    def close(self) -> None:
        """Write what waits, close the file, and say what was kept."""
        with self._cond:
            self._closing = True
            self._cond.notify()
        self._thread.join()
        if self.frames == 0 and self.stopped is None:  # a run that never got going leaves nothing behind
            for name in (FRAMES_NAME, META_NAME, CAMERA_NAME):
                with contextlib.suppress(OSError):
                    (self.folder / name).unlink()
            if self._made_folder:
                with contextlib.suppress(OSError):
                    self.folder.rmdir()
            return  # silently: the line that says why the run ended is the one to read
        lost = f", {self.lost} frames not kept (the disk fell behind)" if self.lost else ""
        self.say(
            f"frame recording: {self.frames} frames, {self.bytes / 1e6:.1f} MB ({self.codec}) -> {self.folder}{lost}"
        )

    def _stop(self, why: str) -> None:
        if self.stopped is None:
            self.stopped = why
            self.say(f"frame recording: {why}; {STOPS}")

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    while not self._items and not self._closing:
                        self._cond.wait()
                    if not self._items:
                        return
                    item = self._items.popleft()
                    self._queued -= item.kind == KIND_FRAME
                if self.stopped is None:
                    self._write(item)
        finally:
            with contextlib.suppress(OSError):
                os.close(self._fd)

    def _write(self, item: _Item) -> None:
        t0 = time.thread_time()
        image = item.image
        if image is None:
            payload, shape = b"", (0, 0, 0)
        else:
            payload = self._encode(np.ascontiguousarray(image))
            shape = (image.shape[0], image.shape[1], image.shape[2] if image.ndim == 3 else 1)
        head = RECORD.pack(
            MAGIC,
            item.kind,
            CODECS[self.codec],
            shape[2],
            item.index,
            item.capture_time_us,
            shape[1],
            shape[0],
            len(payload),
            zlib.crc32(payload),
            -1 if item.waited_us is None else item.waited_us,
        )
        if self.bytes + len(head) + len(payload) > self.max_bytes:
            self._stop(f"reached its bound of {self.max_bytes / 1e6:g} MB at frame {item.index}")
            return
        try:
            _write_all(self._fd, head + payload)
        except OSError as exc:
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, self.bytes)  # back to the last whole record
            where = self.folder / FRAMES_NAME
            self._stop(f"{where}: {exc.strerror or exc} at frame {item.index} ({self.frames} frames kept)")
            return
        self.bytes += len(head) + len(payload)
        self.frames += item.kind == KIND_FRAME
        self.encode_s += time.thread_time() - t0


def start_frame_log(
    cfg: ReceiverConfig, folder: Path, say: Callable[[str], None], *, max_mb: float, max_s: float
) -> FrameLogWriter:
    """A recorder of the frames of the run ``cfg`` describes, with what its replay needs in ``folder``."""
    from ipt.config.models import load_arena_config
    from ipt.maphash import map_hash
    from ipt.tagmap import grid_tag_map

    arena = load_arena_config(cfg.arena)
    meta = {
        "arena": arena.model_dump(mode="json"),
        "pipeline": cfg.pipeline.model_dump(mode="json"),
        "map_hash": map_hash(grid_tag_map(arena)),
        "source": cfg.source,
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    return FrameLogWriter(folder, meta, cfg.camera, say=say, max_mb=max_mb, max_s=max_s)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        if n <= 0:
            raise OSError(errno.EIO, "short write")
        view = view[n:]


def _prepare(folder: Path, camera_file: Path, meta: dict[str, Any]) -> None:
    """Make ``folder`` (empty or new) with the metadata and the camera file; refuse one that holds files."""
    flag = f"--record-frames {folder}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if any(folder.iterdir()):
            raise FrameLogError(f"{flag}: the folder is not empty (a recording is never overwritten)")
        shutil.copyfile(camera_file, folder / CAMERA_NAME)
        tmp = folder / f".{META_NAME}.tmp"
        tmp.write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
        tmp.replace(folder / META_NAME)
    except OSError as exc:
        raise FrameLogError(f"{flag}: {exc.strerror or exc}") from None


@dataclass(frozen=True)
class FrameLogEvent:
    """One record of a recording: a frame (``image`` set), a *finish* or a *lost* mark."""

    kind: int
    index: int
    capture_time_us: int
    image: U8 | None = None
    waited_us: int | None = None
    """How long a live camera's frame waited before the pipeline took it (None: not recorded, or not live)."""


class FrameLog:
    """A recording made by :class:`FrameLogWriter`: its metadata, and its records in order (:meth:`events`).
    After the iteration :attr:`problem` says where and why it ended early, if it did."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        try:
            self.meta: dict[str, Any] = json.loads((folder / META_NAME).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            why = exc.strerror if isinstance(exc, OSError) else f"not JSON ({exc})"
            raise FrameLogError(f"{folder / META_NAME}: {why}; is {folder} a frame recording?") from None
        if self.meta.get("format") != FORMAT or self.meta.get("version") not in (1, VERSION):
            raise FrameLogError(f"{folder / META_NAME}: not a {FORMAT} version 1 or {VERSION}")
        self._record = RECORD if self.meta["version"] == VERSION else RECORD_V1
        self.camera_file = folder / CAMERA_NAME
        self.problem: str | None = None

    def events(self) -> Iterator[FrameLogEvent]:
        """The records in order, up to the first damaged or cut one."""
        path = self.folder / FRAMES_NAME
        try:
            f = path.open("rb")
        except OSError as exc:
            raise FrameLogError(f"{path}: {exc.strerror}") from None
        with f:
            k = 0
            record = self._record
            while head := f.read(record.size):
                if len(head) < record.size:
                    self.problem = f"{path}: record {k} is cut short (header); the frames before it were read"
                    return
                magic, kind, codec, ch, index, t_us, w, h, n, crc, *rest = record.unpack(head)
                waited_us = rest[0] if rest and rest[0] >= 0 else None
                payload = f.read(n)
                if magic != MAGIC or len(payload) < n or zlib.crc32(payload) != crc:
                    self.problem = f"{path}: record {k} is damaged or cut short; the frames before it were read"
                    return
                image = None
                if kind == KIND_FRAME:
                    image = _decode(codec, payload, (h, w) if ch == 1 else (h, w, ch))
                yield FrameLogEvent(kind, index, t_us, image, waited_us)
                k += 1


__all__ = [
    "DEFAULT_MAX_MB",
    "DEFAULT_MAX_S",
    "KIND_FINISH",
    "KIND_FRAME",
    "KIND_LOST",
    "MAGIC",
    "RECORD",
    "RECORD_V1",
    "FrameLog",
    "FrameLogError",
    "FrameLogEvent",
    "FrameLogWriter",
    "default_codec",
    "start_frame_log",
]
