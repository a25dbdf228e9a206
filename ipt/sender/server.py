"""The sender daemon: a frame clock at the projector rate, a render thread, a sink, and a pose listener.

Frames. Output frame ``j`` is due at ``start + j / f_o`` (``time.monotonic``), with ``f_o`` the
projector rate. It shows input frame ``i = floor(j · f_i / f_o)`` of the scene (``j // N`` when
``f_o = N·f_i``; other ratios repeat or drop input frames, :class:`~ipt.sender.modulator.FrameTiming`).
A content thread makes input frame ``i + 1`` (scene frame, resized to the projector) while the render
thread works on frame ``i``. At the first output frame of input frame ``i`` the render thread draws the
AR overlay on it and makes both phases in one pass (:meth:`Modulator.phases`, the arena's profile);
every output frame is then the phase of ``phase_sign(j)``. The render thread works up to ``lookahead``
frames ahead of the clock, one frame at a time and in order. The clock never skips or repeats a frame:
``j`` counts every frame, so the phases keep alternating whatever happens. A frame whose rendering
finished after its due time is still shown, at once, and counted as a missed deadline; a frame that was
ready but is reached more than half a period late (the sink or the loop itself was behind) is shown at
once and counted as late. In both cases the clock then restarts from that frame (``start`` moves on):
the next frame is due one period later, instead of a burst of frames to catch up that no display could
show anyway. So each counted frame is one stutter of the projection: on a real projector the previous
frame stays up one refresh longer, a repeated phase (``repeated_phases`` in the statistics).

Pacing. A sink that is ``paced`` (the window, the null sink) gets frame j at its due time. A file is
not paced: frames are rendered and written as fast as possible, and there are no deadlines to miss.

Packets. A UDP socket (an asyncio datagram endpoint on the event loop) feeds every datagram, with its
source address, to a :class:`~ipt.protocol.PacketFilter`; accepted poses update the
:class:`~ipt.sender.scene.ArScene`, rejected ones are counted by reason. Nothing in a datagram can stop
the loop: anything unexpected is counted as ``error``. The default filter tracks at most
:data:`~ipt.sender.scene.DEFAULT_MAX_VEHICLES` vehicles and takes at most :data:`DEFAULT_SOURCE_RATE_HZ`
datagrams a second from one source address, so that a flood of made-up vehicle ids neither grows the
overlay's work nor takes the event loop's time from the frames (``docs/reliability.md``).

Stopping. SIGTERM, SIGINT and SIGHUP only set a flag (a second SIGINT also skips the waits); one that
arrived while the sender was starting stops it as soon as its loop runs (:mod:`ipt.signals`). The loop
then stops taking frames, and shutdown runs in order with bounded waits: close the socket, let the
render thread finish its frame and the content thread the input frame it is making, close the sink,
print the final statistics line, which always contains ``missed=<count>``. A file is completed with the
frames shown, unless a number of frames was asked for and the run stopped short of it: then the file is
not kept (a video with fewer frames than asked for would look finished).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import queue
import signal
import socket
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Final, Literal

import numpy as np
import numpy.typing as npt

from ipt import signals
from ipt.config.models import ArenaConfig
from ipt.errors import IptError
from ipt.memory import keep_freed_memory, warm
from ipt.protocol import ACCEPTED, PacketFilter
from ipt.sender.content import GeneratedScene, Scene
from ipt.sender.display import Sink
from ipt.sender.modulator import FrameTiming, Modulator, make_modulator, phase_sign, resize_to
from ipt.sender.pairs import default_cache_dir
from ipt.sender.scene import DEFAULT_MAX_VEHICLES, ArScene
from ipt.tagmap import grid_tag_map

U8 = npt.NDArray[np.uint8]

DEFAULT_LISTEN: Final = ("127.0.0.1", 9870)
"""Where the sender listens for pose packets unless told otherwise."""

RECEIVE_BUFFER_BYTES: Final = 1 << 20
"""Receive buffer asked for on the UDP socket (the kernel may cap it), so bursts are not dropped."""

ERROR: Final = "error"
"""Key in the packet counts for datagrams whose handling raised (a bug; never expected)."""

DEFAULT_SOURCE_RATE_HZ: Final = 1000.0
"""Datagrams a second the sender takes from one source address unless told otherwise: a drone sends one
pose per camera frame (120 a second), so this leaves room for eight drones behind one address, and a
flood from one address costs a token-bucket check per datagram instead of a decode."""


def default_packet_filter(key: bytes | None = None, vehicle_ids: list[int] | None = None) -> PacketFilter:
    """The sender's packet filter: ``key`` and ``vehicle_ids`` as given, a restarted drone re-baselined after
    10 s of silence, at most :data:`DEFAULT_MAX_VEHICLES` vehicles and :data:`DEFAULT_SOURCE_RATE_HZ`
    datagrams a second from one source address."""
    return PacketFilter(
        key=key,
        vehicle_ids=vehicle_ids,
        resync_after_s=10.0,
        max_vehicles=DEFAULT_MAX_VEHICLES,
        source_rate_hz=DEFAULT_SOURCE_RATE_HZ,
    )


class SenderError(IptError):
    """The sender cannot start (a bad address, a port in use) or was given unusable settings."""


def parse_listen(spec: str) -> tuple[str, int]:
    """``"HOST:PORT"`` (IPv6 as ``"[::1]:PORT"``) as ``(host, port)``; port 0 lets the system choose."""
    host, sep, port_text = spec.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not sep or not host or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise SenderError(f"listen address must be HOST:PORT with a port 0..65535, got {spec!r}")
    return host, int(port_text)


class _Histogram:
    """Durations in milliseconds, in 0.05 ms bins up to 2 s: bounded memory however long the run."""

    BIN_MS: Final = 0.05
    BINS: Final = 40_000

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS + 1, dtype=np.int64)
        self.n = 0
        self.max_ms = 0.0
        self.total_ms = 0.0

    def add(self, ms: float) -> None:
        self.counts[min(self.BINS, max(0, int(ms / self.BIN_MS)))] += 1
        self.n += 1
        self.total_ms += ms
        self.max_ms = max(self.max_ms, ms)

    def percentile(self, p: float) -> float:
        """The ``p``-th percentile (bin centre), NaN when empty."""
        if self.n == 0:
            return math.nan
        rank = max(1, math.ceil(p / 100.0 * self.n))
        index = int(np.searchsorted(np.cumsum(self.counts), rank))
        return self.max_ms if index >= self.BINS else min(self.max_ms, (index + 0.5) * self.BIN_MS)

    @property
    def mean_ms(self) -> float:
        """Mean of the durations added (NaN when empty)."""
        return self.total_ms / self.n if self.n else math.nan

    def clear(self) -> None:
        self.counts[:] = 0
        self.n = 0
        self.max_ms = 0.0
        self.total_ms = 0.0


@dataclass
class SenderStats:
    """What the sender did; :meth:`line` is the statistics line it prints."""

    width_px: int
    height_px: int
    rate_hz: float
    paced: bool
    frames: int = 0
    """Output frames handed to the sink."""
    missed: int = 0
    """Frames whose rendering finished after their due time (paced sinks only)."""
    late: int = 0
    """Frames rendered in time but reached more than half a period after their due time, because the sink
    or the loop was behind (paced sinks only)."""
    elapsed_s: float = 0.0
    """From showing the first frame to showing the last."""
    work_ms: _Histogram = field(default_factory=_Histogram)
    """Render-thread time per output frame: at the first output frame of an input frame, waiting for its
    content (made ahead in the content thread), the overlay and both phases; the others reuse them."""
    overlay_ms: _Histogram = field(default_factory=_Histogram)
    """Time of the AR overlay per input frame."""
    work_cpu_ms: _Histogram = field(default_factory=_Histogram)
    """CPU time of the render thread per output frame: the part of ``work_ms`` that is not waiting for a core
    (on a busy machine ``work_ms`` grows, this does not)."""
    content_ms: _Histogram = field(default_factory=_Histogram)
    """Content-thread time per input frame (scene frame, resize to projector size), made ahead in parallel."""
    content_cpu_ms: _Histogram = field(default_factory=_Histogram)
    """CPU time of the content thread per input frame."""
    overlay_errors: int = 0
    content_errors: int = 0
    """Input frames the scene failed to make; the last good one was shown instead (phases alternating)."""
    display_errors: int = 0
    """Output frames the sink failed to show; the loop went on (phases alternating) and tried the next."""
    packets: Counter[str] = field(default_factory=Counter)
    """Datagram outcomes: ``accepted`` and each rejection reason (and ``error``)."""
    vehicles: int = 0
    """Vehicles on the overlay when the statistics were taken."""
    pacing: dict[str, Any] | None = None
    """What the sink saw of its frames reaching the screen, for a sink that times them (the window:
    :meth:`~ipt.sender.display.WindowSink.pacing`): refreshes that repeated a frame, frames never shown."""
    startup_s: float = math.nan
    """From the start of the run to the first frame shown: the colour table, warming memory, the first
    frame's work (the modulator was made before)."""
    stopped_by: int | None = None
    """The signal that stopped the run, if one did."""
    output_kept: bool = True
    """Whether the sink's output (a file) was kept: not when the run stopped short of the frames asked for."""

    @property
    def frames_per_s(self) -> float:
        """Output rate between the first frame shown and the last."""
        return (self.frames - 1) / self.elapsed_s if self.frames > 1 and self.elapsed_s > 0 else math.nan

    @property
    def accepted(self) -> int:
        return self.packets[ACCEPTED]

    @property
    def rejected(self) -> int:
        return sum(v for k, v in self.packets.items() if k != ACCEPTED)

    def line(self, frames: int | None = None, seconds: float | None = None, work: _Histogram | None = None) -> str:
        """One line of statistics; ``frames``/``seconds``/``work`` override the totals (for an interval)."""
        work = self.work_ms if work is None else work
        if frames is None or seconds is None:
            fps = self.frames_per_s
        else:
            fps = frames / seconds if seconds > 0 else math.nan
        reasons = ", ".join(f"{k}={v}" for k, v in sorted(self.packets.items()) if k != ACCEPTED and v)
        text = (
            f"frames={self.frames} fps={fps:.2f} work_p50={work.percentile(50):.2f}ms "
            f"work_p99={work.percentile(99):.2f}ms missed={self.missed} late={self.late} "
            f"vehicles={self.vehicles} packets accepted={self.accepted} rejected={self.rejected}"
        )
        if reasons:
            text += f" ({reasons})"
        if self.overlay_errors:
            text += f" overlay_errors={self.overlay_errors}"
        if self.content_errors:
            text += f" content_errors={self.content_errors}"
        if self.display_errors:
            text += f" display_errors={self.display_errors}"
        if self.pacing is not None:
            p = self.pacing
            text += (
                f" repeated_vsyncs={p['repeated_vsyncs']} dropped_frames={p['dropped_frames']} "
                f"present_p99={p['present_interval_p99_ms']:.2f}ms"
            )
        return text

    def to_dict(self) -> dict[str, Any]:
        """The totals as plain JSON-able values."""
        return {
            "width_px": self.width_px,
            "height_px": self.height_px,
            "rate_hz": self.rate_hz,
            "paced": self.paced,
            "output_frames": self.frames,
            "seconds": round(self.elapsed_s, 3),
            "frames_per_s": round(self.frames_per_s, 3),
            "work_p50_ms": round(self.work_ms.percentile(50), 3),
            "work_p99_ms": round(self.work_ms.percentile(99), 3),
            "work_mean_ms": round(self.work_ms.mean_ms, 3),
            "work_max_ms": round(self.work_ms.max_ms, 3),
            "overlay_p50_ms": round(self.overlay_ms.percentile(50), 3),
            "overlay_p99_ms": round(self.overlay_ms.percentile(99), 3),
            "work_cpu_p50_ms": round(self.work_cpu_ms.percentile(50), 3),
            "work_cpu_p99_ms": round(self.work_cpu_ms.percentile(99), 3),
            "work_cpu_mean_ms": round(self.work_cpu_ms.mean_ms, 3),
            "content_p50_ms": round(self.content_ms.percentile(50), 3),
            "content_p99_ms": round(self.content_ms.percentile(99), 3),
            "content_cpu_p50_ms": round(self.content_cpu_ms.percentile(50), 3),
            "content_cpu_p99_ms": round(self.content_cpu_ms.percentile(99), 3),
            "content_cpu_mean_ms": round(self.content_cpu_ms.mean_ms, 3),
            "startup_s": round(self.startup_s, 3),
            "missed_deadlines": self.missed,
            "late_frames": self.late,
            "repeated_phases": self.missed + self.late,
            "overlay_errors": self.overlay_errors,
            "content_errors": self.content_errors,
            "display_errors": self.display_errors,
            "packets": dict(sorted(self.packets.items())),
            "pacing": self.pacing,
        }


class _Worker:
    """One daemon thread running submitted calls in order; a stuck call never blocks interpreter exit."""

    def __init__(self, name: str) -> None:
        self._jobs: queue.SimpleQueue[tuple[Future[Any], Callable[..., Any], tuple[Any, ...]] | None] = (
            queue.SimpleQueue()
        )
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future[Any]:
        fut: Future[Any] = Future()
        self._jobs.put((fut, fn, args))
        return fut

    def stop(self) -> None:
        """Finish the jobs already queued (cancelled ones are skipped), then end the thread."""
        self._jobs.put(None)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            fut, fn, args = job
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn(*args))
            except BaseException as exc:
                fut.set_exception(exc)


@dataclass
class _Rendered:
    index: int
    frame: U8
    work_s: float
    work_cpu_s: float  # CPU time of the render thread for this frame (less affected by a busy machine)
    overlay_s: float | None
    content_s: float | None  # time the content thread took for this frame's input frame (first frame of it)
    content_cpu_s: float | None
    ready_s: float  # time.monotonic() when the frame was finished


@dataclass
class _Content:
    index: int
    rgb: U8
    seconds: float
    cpu_s: float


@dataclass
class _Early:
    """An input frame whose phases were begun at the output frame before its first one."""

    index: int
    rgb: U8
    out: tuple[U8, U8]
    row: int  # rows [0, row) of both phases are done


EARLY_ROWS: Final = 0.4
"""Share of the rows of an input frame's phases made one output frame early (with the overlay), so that
the two output frames of an input frame carry about the same work."""


MAX_CONTENT_NOTES: Final = 20
"""Notes from the scene (frames of another size) logged in one run at most: a file that changes size at
every frame does not fill the log."""


WARM_FRAMES: Final = 6
"""Frame-sized buffers each worker thread faults in before the clock starts (content frame, resized copy,
overlay and phases in flight; more than any one thread holds at once)."""


class _Renderer:
    """Makes output frame j; runs in the render thread, one frame at a time, in order.

    The content of the next input frame is made ahead in the content thread (``content_worker``); the
    overlay is drawn here, just before modulation, so that it shows the newest poses. Both phases of an
    input frame are made in one pass over its pixels; its output frames all reuse them. With ``early``
    (a paced sink and a modulator that works by rows), the output frame before an input frame's first one
    already draws its overlay and makes the first ``early`` share of the rows of both phases, if its
    content is ready, and the first frame makes the rest: the work is spread over the output frames
    instead of falling on every N-th. With ``buffers`` the phases are written into a ring of that many
    preallocated pairs (for sinks that are done with a frame when ``show`` returns); otherwise every input
    frame gets new arrays.
    """

    def __init__(
        self,
        scene: Scene,
        modulator: Modulator,
        ar: ArScene | None,
        timing: FrameTiming,
        clock: Callable[[], float] = time.monotonic,
        content_worker: _Worker | None = None,
        buffers: int | None = None,
        frames: int | None = None,
        early: float | None = None,
    ) -> None:
        self.scene = scene
        self.frames = frames
        self.modulator = modulator
        self.ar = ar
        self.clock = clock
        self.timing = timing
        self.input_rate_hz = timing.input_rate_hz
        self.content_worker = content_worker
        self._rows: Any = modulator if hasattr(modulator, "phases_rows") else None  # IptModulator.phases_rows
        self.early = early if self._rows is not None else None
        self.overlay_errors = 0
        self.first_overlay_error: str | None = None
        # The scene failing (a video that cannot be decoded or read any more): counted, and the last good
        # input frame is shown instead; `content_failing` says whether the newest attempt failed.
        self.live = False  # set by the sender for sinks that retry (a display): keep going on a source failure
        self._fault_lock = threading.Lock()
        self.content_errors = 0
        self.content_failing = False
        self.last_content_error: str | None = None
        self.notes: list[str] = []  # lines for the user about the scene (a frame of another size), said once
        self._scene_shape: tuple[int, int] | None = None  # (H, W) of the scene's newest frame
        self._phases: tuple[U8, U8] | None = None
        self._input = -1
        self._next: tuple[int, Future[_Content]] | None = None
        self._early: _Early | None = None
        self._ring: list[tuple[U8, U8]] = []
        self._ring_size = buffers
        self._ring_next = 0

    def _make_content(self, i: int) -> _Content:
        t0, cpu0 = time.perf_counter(), time.thread_time()
        h, w = self.modulator.height_px, self.modulator.width_px
        try:
            rgb = self._scene_frame(i, w, h)
            failed = None
        except Exception as exc:  # the video source failing must never stop a live projection
            if not self.live:
                raise  # a file must not fill up with a frozen frame: the run ends, the file is not kept
            failed = f"{type(exc).__name__}: {exc}"
            rgb = self._last_good(w, h)
        with self._fault_lock:
            self.content_failing = failed is not None
            if failed is not None:
                self.content_errors += 1
                self.last_content_error = failed
        return _Content(i, rgb, time.perf_counter() - t0, time.thread_time() - cpu0)

    def content_state(self) -> tuple[bool, int, str | None]:
        """Whether the newest input frame asked for failed, how many have failed, and the last error."""
        with self._fault_lock:
            return self.content_failing, self.content_errors, self.last_content_error

    def take_notes(self) -> list[str]:
        """The notes about the scene since the last call."""
        with self._fault_lock:
            notes, self.notes = self.notes, []
        return notes

    def _scene_frame(self, i: int, w: int, h: int) -> U8:
        rgb = self.scene.frame(i, self.input_rate_hz)
        if not (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3):
            got = f"{getattr(rgb, 'shape', '?')} {getattr(rgb, 'dtype', type(rgb).__name__)}"
            raise TypeError(f"the scene gave {got}, not an H×W×3 uint8 image")
        shape = (int(rgb.shape[0]), int(rgb.shape[1]))
        if shape != self._scene_shape:
            if shape != (h, w):  # resized from now on: say so once
                with self._fault_lock:
                    self.notes.append(f"the scene's frames are {shape[1]}x{shape[0]} from input frame {i} on; "
                                      f"resized to {w}x{h}")  # fmt: skip
            self._scene_shape = shape
        if shape != (h, w):
            rgb = resize_to(rgb, w, h)
        return np.ascontiguousarray(rgb)

    def _last_good(self, w: int, h: int) -> U8:
        """A fresh copy of the last input frame the scene made (black if it never made one)."""
        last: Callable[[], U8 | None] | None = getattr(self.scene, "last_frame", None)
        rgb = last() if last is not None else None
        if rgb is None:
            return np.zeros((h, w, 3), np.uint8)
        return np.ascontiguousarray(rgb if rgb.shape[:2] == (h, w) else resize_to(rgb, w, h))

    def _next_input(self, i: int, j: int) -> int:
        """The input frame after ``i``, shown from output frame ``j`` on."""
        return max(i + 1, self.timing.input_of(j + 1))

    def _content(self, i: int, next_i: int) -> _Content:
        """Input frame ``i`` (made ahead if it was asked for), and ask for ``next_i`` ahead."""
        ahead = self._next
        self._next = None
        if ahead is not None and ahead[0] == i:
            content = ahead[1].result()
        else:
            if ahead is not None:
                ahead[1].cancel()
            content = self._make_content(i)
        ratio = self.timing.ratio
        first_output = -(-next_i * ratio.numerator // ratio.denominator)  # ceil: first j showing next_i
        if self.content_worker is not None and (self.frames is None or first_output < self.frames):
            self._next = (next_i, self.content_worker.submit(self._make_content, next_i))
        return content

    def cancel_ahead(self) -> Future[_Content] | None:
        """Cancel the input frame asked for ahead; returns its future if it is already running."""
        ahead, self._next = self._next, None
        if ahead is None or ahead[1].cancel():
            return None
        return ahead[1]

    def allocate(self) -> None:
        """Allocate the ring of output pairs now, and write each page once.

        Called before the frame clock starts: a fresh array's pages are mapped at their first write, and
        doing that for 2 x 12 MB (at 1920x2160) inside a frame's budget costs tens of milliseconds here.
        """
        while self._ring_size is not None and len(self._ring) < self._ring_size:
            shape = (self.modulator.height_px, self.modulator.width_px, 3)
            pair = (np.empty(shape, np.uint8), np.empty(shape, np.uint8))
            for a in pair:
                a.fill(0)
            self._ring.append(pair)

    def _buffers(self) -> tuple[U8, U8] | None:
        if self._ring_size is None:
            return None
        self.allocate()
        pair = self._ring[self._ring_next % self._ring_size]
        self._ring_next += 1
        return pair

    def _overlay(self, rgb: U8) -> float | None:
        """Draw the AR overlay into ``rgb``; its duration (None without an overlay)."""
        if self.ar is None:
            return None
        t1 = time.perf_counter()
        try:
            self.ar.draw(rgb, self.clock())
        except Exception as exc:  # the overlay must never stop the projection
            self.overlay_errors += 1
            if self.first_overlay_error is None:
                self.first_overlay_error = f"{type(exc).__name__}: {exc}"
        return time.perf_counter() - t1

    def render(self, j: int) -> _Rendered:
        t0, cpu0 = time.perf_counter(), time.thread_time()
        overlay_s = content_s = content_cpu_s = None
        i = self.timing.input_of(j)
        if self._phases is None or i != self._input:
            early, self._early = self._early, None
            if early is not None and early.index == i:
                self._rows.phases_rows(early.rgb, early.out, early.row, self.modulator.height_px)
                self._phases = early.out
            else:
                content = self._content(i, self._next_input(i, j))
                content_s, content_cpu_s = content.seconds, content.cpu_s
                overlay_s = self._overlay(content.rgb)
                self._phases = self.modulator.phases(content.rgb, self._buffers())
            self._input = i
        assert self._phases is not None
        frame = self._phases[0] if phase_sign(j) > 0 else self._phases[1]
        if self.early is not None and (self.frames is None or j + 1 < self.frames):
            ni = self.timing.input_of(j + 1)
            ahead = self._next
            if ni != i and ahead is not None and ahead[0] == ni and ahead[1].done():
                content = self._content(ni, self._next_input(ni, j + 1))
                content_s, content_cpu_s = content.seconds, content.cpu_s
                overlay_s = self._overlay(content.rgb)
                out = self._buffers()
                if out is None:
                    shape = (self.modulator.height_px, self.modulator.width_px, 3)
                    out = (np.empty(shape, np.uint8), np.empty(shape, np.uint8))
                row = round(self.modulator.height_px * self.early)
                self._rows.phases_rows(content.rgb, out, 0, row)
                self._early = _Early(ni, content.rgb, out, row)
        work_s, work_cpu_s = time.perf_counter() - t0, time.thread_time() - cpu0
        return _Rendered(j, frame, work_s, work_cpu_s, overlay_s, content_s, content_cpu_s, time.monotonic())


class _PoseListener(asyncio.DatagramProtocol):
    """Every datagram goes through the filter; accepted poses update the overlay."""

    def __init__(
        self, packet_filter: PacketFilter, ar: ArScene | None, clock: Callable[[], float] | None = None
    ) -> None:
        self.filter = packet_filter
        self.ar = ar
        self.clock = clock
        self.errors = 0
        self.socket_errors = 0

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        now = time.monotonic()
        try:
            packet = self.filter.accept(data, now, addr[0] if addr else None)
            if packet is not None and self.ar is not None:
                self.ar.update(packet, now if self.clock is None else self.clock())
        except Exception:  # a bug somewhere below: count it, keep listening
            self.errors += 1

    def error_received(self, exc: Exception) -> None:
        self.socket_errors += 1


def _wrap(fut: Future[Any]) -> asyncio.Future[Any]:
    """``fut`` as an asyncio future whose exception counts as seen (the run reports it its own way)."""
    wrapped = asyncio.wrap_future(fut)
    wrapped.add_done_callback(lambda f: f.cancelled() or f.exception())
    return wrapped


def _stderr_line(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def _nothing() -> None:
    pass


class Sender:
    """One run of the sender; see the module doc. Use :func:`run_sender`."""

    def __init__(
        self,
        arena: ArenaConfig,
        sink: Sink,
        scene: Scene,
        *,
        frames: int | None,
        paced: bool,
        listen: tuple[str, int] | None,
        packet_filter: PacketFilter,
        ar_scene: ArScene | None,
        stats_every_s: float,
        log: Callable[[str], None],
        lookahead: int,
        install_signal_handlers: bool,
        stop: asyncio.Event | None,
        shutdown_timeout_s: float,
        overlay_clock: Callable[[], float] | None = None,
        on_listening: Callable[[tuple[str, int]], None] | None = None,
        input_rate_hz: float | None = None,
        modulator: Modulator | None = None,
        pair_cache: os.PathLike[str] | None = None,
    ) -> None:
        if frames is not None and frames < 0:
            raise SenderError(f"frames must be >= 0, got {frames}")
        if lookahead < 1:
            raise SenderError(f"lookahead must be >= 1, got {lookahead}")
        self.arena = arena
        self.sink = sink
        self.frames = frames
        self.paced = paced
        self.listen = listen
        self.filter = packet_filter
        self.ar = ar_scene
        self.stats_every_s = stats_every_s
        self.log = log
        self.lookahead = lookahead
        self.install_signal_handlers = install_signal_handlers
        self.stop = stop
        self.shutdown_timeout_s = shutdown_timeout_s
        self.overlay_clock = overlay_clock if overlay_clock is not None else time.monotonic
        self._listener_clock = overlay_clock  # None: the listener's own receive time
        self.on_listening = on_listening
        self.rate_hz = arena.projector.rate_hz
        mod = arena.modulation
        self.timing = FrameTiming(input_rate_hz if input_rate_hz is not None else mod.input_rate_hz, self.rate_hz)
        if modulator is None:
            mask = grid_tag_map(arena).render_mask()
            modulator = make_modulator(mod.profile, mask, mod.delta_l, clip_allowance_l8=mod.clip_allowance_l8)
        elif (modulator.width_px, modulator.height_px) != (arena.projector.width_px, arena.projector.height_px):
            raise SenderError(
                f"the modulator is for {modulator.width_px}x{modulator.height_px}, the projector is "
                f"{arena.projector.width_px}x{arena.projector.height_px}"
            )
        self.modulator = modulator
        self.pair_cache = pair_cache
        # Sinks that are done with a frame when show() returns let the phases be written into a ring of
        # reused arrays: the pair shown, those of the frames up to `lookahead` ahead, and one begun early.
        buffers = lookahead + 3 if getattr(sink, "borrows", False) else None
        self.renderer = _Renderer(
            scene,
            modulator,
            ar_scene,
            self.timing,
            self.overlay_clock,
            None,
            buffers,
            frames,
            EARLY_ROWS if paced else None,  # unpaced sinks have no deadlines: keep the work simple there
        )
        self.renderer.live = bool(getattr(sink, "retries", False))
        self.stats = SenderStats(arena.projector.width_px, arena.projector.height_px, self.rate_hz, paced)
        self.bound: tuple[str, int] | None = None
        self.should_exit = False
        self.force_exit = False
        self._listener: _PoseListener | None = None
        self._transport: asyncio.DatagramTransport | None = None
        self._render: _Worker | None = None
        self._content: _Worker | None = None
        self._display: _Worker | None = None
        self._pending: deque[tuple[int, Future[Any]]] = deque()
        self._next_submit = 0
        self._unroute_signals: Callable[[], None] = _nothing
        self._interval_work = _Histogram()
        self._overlay_error_logged = False
        self._display_failed = 0  # consecutive output frames the sink failed to show
        self._content_failing = False  # the scene was failing at the last check
        self._content_errors_before = 0  # content errors counted before the current failure began
        self._notes_said = 0  # the scene's notes logged so far
        self._started = False
        self._run_start = math.nan

    # -- signals: they only set flags --

    def handle_exit(self, sig: int) -> None:
        if self.should_exit and sig == signal.SIGINT:
            self.force_exit = True
        if self.stats.stopped_by is None:
            self.stats.stopped_by = sig
        self.should_exit = True

    def _install_signal_handlers(self, loop: asyncio.AbstractEventLoop) -> None:
        if self.install_signal_handlers:
            self._unroute_signals = signals.route_to_loop(loop, self.handle_exit)

    def _remove_signal_handlers(self, loop: asyncio.AbstractEventLoop) -> None:
        self._unroute_signals()
        self._unroute_signals = _nothing

    def _stopping(self) -> bool:
        if self.stop is not None and self.stop.is_set():
            self.should_exit = True
        return self.should_exit

    # -- the run --

    async def run(self) -> SenderStats:
        self._run_start = time.monotonic()
        loop = asyncio.get_running_loop()
        self._install_signal_handlers(loop)
        ok = False
        try:
            await self._startup(loop)
            await self._main_loop()
            ok = True
        finally:
            try:
                await self._shutdown(ok)
            finally:
                self._remove_signal_handlers(loop)
        return self.stats

    async def _startup(self, loop: asyncio.AbstractEventLoop) -> None:
        self._render = _Worker("ipt-render")
        self._content = self.renderer.content_worker = _Worker("ipt-content")
        # Deadlines from the first frame: every colour's pair before the clock starts (read from the cache,
        # or computed once), so that no frame has to work out the colours it is the first to show.
        complete: Callable[..., str] | None = getattr(self.modulator, "complete_table", None)
        if self.paced and complete is not None and not getattr(self.modulator, "table_complete", True):

            def log(text: str) -> None:
                self.log(f"ipt-sender: {text}")

            said = await asyncio.wrap_future(self._render.submit(complete, self.pair_cache, log))
            log(said)
        # Before the clock starts, fault in the memory the first frames will use (see ipt.memory): without
        # this the first second at 1920x2160 missed up to 8 deadlines, each frame paying tens of
        # milliseconds for fresh pages.
        shape = (self.modulator.height_px, self.modulator.width_px, 3)
        frame_bytes = int(np.prod(shape))
        keep_freed_memory(frame_bytes, WARM_FRAMES * 3 * frame_bytes)
        for worker in (self._render, self._content):
            await asyncio.wrap_future(worker.submit(warm, shape, WARM_FRAMES))
        self.renderer.allocate()
        if self.sink.threaded:
            self._display = _Worker("ipt-display")
        if self.listen is not None:
            self._listener = _PoseListener(self.filter, self.ar, self._listener_clock)
            self._transport, self.bound = await self._bind(loop, *self.listen)
            self.log(f"ipt-sender: listening for pose packets on udp {self.bound[0]}:{self.bound[1]}")
            if self.on_listening is not None:
                self.on_listening(self.bound)
        self._started = True

    async def _bind(
        self, loop: asyncio.AbstractEventLoop, host: str, port: int
    ) -> tuple[asyncio.DatagramTransport, tuple[str, int]]:
        assert self._listener is not None
        listener = self._listener
        try:
            infos = await loop.getaddrinfo(host, port, type=socket.SOCK_DGRAM, flags=socket.AI_PASSIVE)
            family, _, proto, _, address = infos[0]
            sock = socket.socket(family, socket.SOCK_DGRAM, proto)
        except OSError as exc:
            raise SenderError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        try:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
            sock.bind(address)
            sock.setblocking(False)
            transport, _ = await loop.create_datagram_endpoint(lambda: listener, sock=sock)
        except OSError as exc:
            sock.close()
            raise SenderError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
        name = sock.getsockname()
        return transport, (str(name[0]), int(name[1]))

    def _fill(self) -> None:
        """Keep ``lookahead`` frames queued for (or in) the render thread."""
        assert self._render is not None
        while len(self._pending) < self.lookahead and (self.frames is None or self._next_submit < self.frames):
            j = self._next_submit
            self._pending.append((j, self._render.submit(self.renderer.render, j)))
            self._next_submit += 1

    async def _wait_rendered(self, fut: Future[Any]) -> _Rendered | None:
        """The frame of ``fut``, or None if a stop is asked for while waiting."""
        wrapped = _wrap(fut)
        while not wrapped.done():
            await asyncio.wait([wrapped], timeout=0.05)
            if not wrapped.done() and self._stopping():
                return None
        result: _Rendered = wrapped.result()
        return result

    async def _sleep_until(self, due: float) -> None:
        while not self._stopping():
            delay = due - time.monotonic()
            if delay <= 0:
                return
            await asyncio.sleep(min(delay, 0.05))

    async def _show(self, frame: U8, j: int) -> None:
        """Hand frame ``j`` to the sink. A sink that can come back (``retries``: a window, the null sink)
        may fail: that is said once, counted, and the next frame tries again, so that the clock and the
        phases go on; a file cannot skip a frame, so its failure ends the run."""
        try:
            if self._display is None:
                self.sink.show(frame, j)
            else:
                await asyncio.wrap_future(self._display.submit(self.sink.show, frame, j))
        except Exception as exc:
            if not getattr(self.sink, "retries", False):
                raise
            self.stats.display_errors += 1
            self._display_failed += 1
            if self._display_failed == 1:
                self.log(
                    f"ipt-sender: the {self.sink.name} sink failed at output frame {j} ({type(exc).__name__}: "
                    f"{exc}); the loop goes on, phases alternating, and tries again at every frame"
                )
            return
        if self._display_failed:
            self.log(f"ipt-sender: the {self.sink.name} sink is back at output frame {j} "
                     f"after {self._display_failed} failed frames")  # fmt: skip
            self._display_failed = 0

    def _report_content(self) -> None:
        """Say when the scene starts and stops failing (checked at every frame; the counts are the renderer's)."""
        failing, errors, message = self.renderer.content_state()
        if failing and not self._content_failing:
            self.log(f"ipt-sender: the video source failed ({message}); showing the last good frame, phases "
                     "still alternating, and trying the source again at every input frame")  # fmt: skip
        elif not failing and self._content_failing:
            self.log(f"ipt-sender: the video source is back ({errors - self._content_errors_before} input "
                     "frames were replaced by the last good one)")  # fmt: skip
        if not failing:
            self._content_errors_before = errors
        self._content_failing = failing
        self.stats.content_errors = errors
        for note in self.renderer.take_notes():
            self._notes_said += 1
            if self._notes_said <= MAX_CONTENT_NOTES:
                last = self._notes_said == MAX_CONTENT_NOTES
                self.log(f"ipt-sender: {note}" + (" (no more such notes)" if last else ""))

    async def _main_loop(self) -> None:
        period = 1.0 / self.rate_hz
        start: float | None = None  # due time of frame 0 (moved on after a late frame)
        first = 0.0  # when frame 0 was shown
        stats = self.stats
        report_at = time.monotonic() + self.stats_every_s
        interval_start, interval_frames = time.monotonic(), 0
        j = 0
        self._fill()
        while not self._stopping() and (self.frames is None or j < self.frames):
            rendered = await self._wait_rendered(self._pending[0][1])
            if rendered is None:
                break
            self._pending.popleft()
            self._fill()  # the render thread goes on with the next frames while this one waits
            now = time.monotonic()
            if start is None:
                start = now  # frame 0 is due as soon as it is ready
            due = start + j * period
            if self.paced:
                if rendered.ready_s > due or now > due + 0.5 * period:
                    # Late: show it now and count it. The clock restarts from this frame (the next one is
                    # due a period later) rather than rushing frames out to catch up.
                    if rendered.ready_s > due:
                        stats.missed += 1
                    else:
                        stats.late += 1
                    start += now - due
                else:
                    await self._sleep_until(due)
                    if self.should_exit:
                        break
            shown_at = time.monotonic()
            if j == 0:
                first = shown_at
                stats.startup_s = shown_at - self._run_start
            await self._show(rendered.frame, j)
            self._report_content()
            j += 1
            stats.frames = j
            stats.elapsed_s = shown_at - first
            work_ms = rendered.work_s * 1e3
            stats.work_ms.add(work_ms)
            stats.work_cpu_ms.add(rendered.work_cpu_s * 1e3)
            self._interval_work.add(work_ms)
            interval_frames += 1
            if rendered.overlay_s is not None:
                stats.overlay_ms.add(rendered.overlay_s * 1e3)
            if rendered.content_s is not None:
                stats.content_ms.add(rendered.content_s * 1e3)
            if rendered.content_cpu_s is not None:
                stats.content_cpu_ms.add(rendered.content_cpu_s * 1e3)
            if self.sink.quit_requested:
                self.log("ipt-sender: the window was closed; stopping")
                self.should_exit = True
            now = time.monotonic()
            if now >= report_at:
                self._collect()
                self.log(f"ipt-sender: t={stats.elapsed_s:.1f}s " + stats.line(
                    interval_frames, now - interval_start, self._interval_work
                ))  # fmt: skip
                self._interval_work.clear()
                interval_start, interval_frames = now, 0
                report_at = now + self.stats_every_s

    def _collect(self) -> None:
        """Copy the counters kept elsewhere (filter, listener, renderer, overlay) into the stats."""
        stats = self.stats
        stats.packets = Counter(self.filter.counts)
        if self._listener is not None and self._listener.errors:
            stats.packets[ERROR] = self._listener.errors
        stats.overlay_errors = self.renderer.overlay_errors
        pacing: Callable[[], dict[str, Any]] | None = getattr(self.sink, "pacing", None)
        if pacing is not None:
            stats.pacing = pacing()
        if self.ar is not None:
            stats.vehicles = len(self.ar.vehicle_ids())
        if self.renderer.first_overlay_error is not None and not self._overlay_error_logged:
            self._overlay_error_logged = True
            self.log(f"ipt-sender: overlay failed (frames are shown without it): {self.renderer.first_overlay_error}")

    async def _shutdown(self, ok: bool) -> None:
        """Ordered, each wait bounded: socket, render thread, content thread, sink, final statistics."""
        t_end = time.monotonic() + (0.1 if self.force_exit else self.shutdown_timeout_s)
        running = [fut for _, fut in self._pending if not fut.cancel()]  # cancel the frames not started
        self._pending.clear()
        if self._transport is not None:
            self._transport.close()
        if self._render is not None:
            self._render.stop()
            if running:
                await asyncio.wait([_wrap(f) for f in running], timeout=max(0.0, t_end - time.monotonic()))
        if self._content is not None:
            # The input frame made ahead: not needed any more; if it is being made, let it finish (the
            # caller may close the scene next).
            ahead = self.renderer.cancel_ahead()
            self._content.stop()
            if ahead is not None:
                await asyncio.wait([_wrap(ahead)], timeout=max(0.0, t_end - time.monotonic()))
        short = self.frames is not None and self.stats.frames < self.frames
        if ok and short and not getattr(self.sink, "retries", False):
            ok = False  # a file stopped short of the frames asked for would look finished: not kept
        self.stats.output_kept = ok
        close = self.sink.close if ok else self.sink.abort
        close_timeout = 0.1 if self.force_exit else self.sink.close_timeout_s
        if self._display is None:
            close()
        else:
            done, _ = await asyncio.wait([_wrap(self._display.submit(close))], timeout=close_timeout)
            self._display.stop()
            if not done:
                self.log(f"ipt-sender: the {self.sink.name} sink did not close within {close_timeout:g} s")
            else:
                for d in done:
                    if (exc := d.exception()) is not None and ok:
                        raise exc
        self._collect()
        if self._started or self.stats.stopped_by is not None:
            self.log("ipt-sender: done: " + self.stats.line())


async def run_sender(
    arena: ArenaConfig,
    sink: Sink,
    scene: Scene | None = None,
    *,
    frames: int | None = None,
    paced: bool | None = None,
    listen: tuple[str, int] | None = DEFAULT_LISTEN,
    packet_filter: PacketFilter | None = None,
    ar_scene: ArScene | None = None,
    stats_every_s: float = 5.0,
    log: Callable[[str], None] | None = None,
    lookahead: int = 2,
    install_signal_handlers: bool = True,
    stop: asyncio.Event | None = None,
    shutdown_timeout_s: float = 0.5,
    overlay_clock: Callable[[], float] | None = None,
    on_listening: Callable[[tuple[str, int]], None] | None = None,
    input_rate_hz: float | None = None,
    modulator: Modulator | None = None,
    pair_cache: os.PathLike[str] | Literal["default"] | None = "default",
) -> SenderStats:
    """Run the sender until ``frames`` output frames are shown, a signal, ``stop`` or the sink says stop.

    Args:
        arena: projector size and rate, tag map and modulation.
        sink: where the frames go (:mod:`ipt.sender.display`).
        scene: the content (default: the generated map at projector size).
        frames: how many output frames to show; ``None`` runs until stopped.
        paced: hand frame j to the sink at its due time; default: the sink's own ``paced``.
        listen: ``(host, port)`` of the UDP pose listener, or ``None`` for none.
        packet_filter: the gate for datagrams (default: :func:`default_packet_filter`, any vehicle, no key,
            at most 16 vehicles, re-baselined after 10 s of silence so that a restarted drone is seen again).
        ar_scene: the overlay (default: a new :class:`ArScene`); it is also updated by the caller's
            own code if it likes (it is thread-safe).
        stats_every_s: interval of the statistics lines.
        log: where lines go (default: stderr).
        lookahead: frames the render thread may work ahead of the clock.
        install_signal_handlers: SIGTERM, SIGINT and SIGHUP stop the run (main thread only).
        stop: set it to stop the run from elsewhere.
        shutdown_timeout_s: bound on waiting for the render thread when stopping.
        overlay_clock: the time (seconds) the overlay runs on: given to :meth:`ArScene.update` for each
            accepted pose and to :meth:`ArScene.draw` for each input frame, so it sets fading and trails
            (default ``time.monotonic``; the closed-loop demo passes the simulation's clock).
        on_listening: called with the bound ``(host, port)`` once the pose listener is up (useful with
            port 0).
        input_rate_hz: the content's frame rate (default: the arena's ``modulation.input_rate_hz``); any
            ratio to the projector rate works (:class:`~ipt.sender.modulator.FrameTiming`).
        modulator: the modulator (default: the arena's ``modulation.profile`` for its tag map and ΔL).
        pair_cache: folder of the ``ipt`` profile's colour table cache (default
            :func:`~ipt.sender.pairs.default_cache_dir`; ``None``: none, the table is computed at every
            start). A paced run completes the table before its first frame.
    """
    if not stats_every_s > 0:
        raise SenderError(f"stats_every_s must be > 0, got {stats_every_s}")
    w, h = arena.projector.width_px, arena.projector.height_px
    try:
        sender = Sender(
            arena,
            sink,
            scene if scene is not None else GeneratedScene(w, h),
            frames=frames,
            paced=sink.paced if paced is None else paced,
            listen=listen,
            packet_filter=packet_filter if packet_filter is not None else default_packet_filter(),
            ar_scene=ar_scene if ar_scene is not None else ArScene(arena),
            stats_every_s=stats_every_s,
            log=log if log is not None else _stderr_line,
            lookahead=lookahead,
            install_signal_handlers=install_signal_handlers,
            stop=stop,
            shutdown_timeout_s=shutdown_timeout_s,
            overlay_clock=overlay_clock,
            on_listening=on_listening,
            input_rate_hz=input_rate_hz,
            modulator=modulator,
            pair_cache=default_cache_dir() if pair_cache == "default" else pair_cache,
        )
    except BaseException:
        sink.abort()  # nothing was shown: leave nothing behind (a file sink may have started its file)
        raise
    return await sender.run()
