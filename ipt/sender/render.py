"""The sender's workers: the threads that make output frames, and the renderer that runs in them.

:class:`Renderer` makes output frame ``j`` in the render thread: input frame ``i`` of the content (made
ahead in the content thread), the AR overlay drawn on it, both phases made in one pass and every output
frame of ``i`` showing the phase of ``phase_sign(j)``. :class:`Worker` is one such thread. Nothing here
knows about deadlines, sockets or signals: the frame clock and the event loop are
:mod:`ipt.sender.server`'s.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from ipt.sender.content import ContentSource
from ipt.sender.modulator import FrameTiming, Modulator, phase_sign, resize_to
from ipt.sender.overlay import ArOverlay

U8 = npt.NDArray[np.uint8]


class Worker:
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
class Rendered:
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


class Renderer:
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
        source: ContentSource,
        modulator: Modulator,
        overlay: ArOverlay | None,
        timing: FrameTiming,
        clock: Callable[[], float] = time.monotonic,
        content_worker: Worker | None = None,
        buffers: int | None = None,
        frames: int | None = None,
        early: float | None = None,
    ) -> None:
        self.source = source
        self.frames = frames
        self.modulator = modulator
        self.overlay = overlay
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
        self._source_shape: tuple[int, int] | None = None  # (H, W) of the scene's newest frame
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
            rgb = self._source_frame(i, w, h)
            failed = None
        except Exception as exc:  # the video source failing must never stop a live projection
            if not self.live:
                raise  # a file must not fill up with a frozen frame: the run ends, the file is not kept
            failed = f"{type(exc).__name__}: {exc}"
            rgb = self._last_good(w, h)
        source_notes: Callable[[], list[str]] | None = getattr(self.source, "take_notes", None)
        with self._fault_lock:
            if source_notes is not None:  # a prefetching source: it cannot keep up, images skipped
                self.notes.extend(source_notes())
            self.content_failing = failed is not None
            if failed is not None:
                self.content_errors += 1
                self.last_content_error = failed
        return _Content(i, rgb, time.perf_counter() - t0, time.thread_time() - cpu0)

    def prime_content(self, stop: threading.Event) -> None:
        """Let a source that decodes ahead (:class:`~ipt.sender.prefetch.PrefetchedVideo`) fill its buffer before
        the frame clock starts (``stop`` set: stop waiting)."""
        prime: Callable[..., None] | None = getattr(self.source, "prime", None)
        if prime is not None:
            prime(stop)

    def content_state(self) -> tuple[bool, int, str | None]:
        """Whether the newest input frame asked for failed, how many have failed, and the last error."""
        with self._fault_lock:
            return self.content_failing, self.content_errors, self.last_content_error

    def take_notes(self) -> list[str]:
        """The notes about the scene since the last call."""
        with self._fault_lock:
            notes, self.notes = self.notes, []
        return notes

    def _source_frame(self, i: int, w: int, h: int) -> U8:
        rgb = self.source.frame(i, self.input_rate_hz)
        if not (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3):
            got = f"{getattr(rgb, 'shape', '?')} {getattr(rgb, 'dtype', type(rgb).__name__)}"
            raise TypeError(f"the scene gave {got}, not an H×W×3 uint8 image")
        shape = (int(rgb.shape[0]), int(rgb.shape[1]))
        if shape != self._source_shape:
            if shape != (h, w):  # resized from now on: say so once
                with self._fault_lock:
                    self.notes.append(f"the scene's frames are {shape[1]}x{shape[0]} from input frame {i} on; "
                                      f"resized to {w}x{h}")  # fmt: skip
            self._source_shape = shape
        if shape != (h, w):
            rgb = resize_to(rgb, w, h)
        return np.ascontiguousarray(rgb)

    def _last_good(self, w: int, h: int) -> U8:
        """A fresh copy of the last input frame the scene made (black if it never made one)."""
        last: Callable[[], U8 | None] | None = getattr(self.source, "last_frame", None)
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

    def _draw_overlay(self, rgb: U8) -> float | None:
        """Draw the AR overlay into ``rgb``; its duration (None without an overlay)."""
        if self.overlay is None:
            return None
        t1 = time.perf_counter()
        try:
            self.overlay.draw(rgb, self.clock())
        except Exception as exc:  # the overlay must never stop the projection
            self.overlay_errors += 1
            if self.first_overlay_error is None:
                self.first_overlay_error = f"{type(exc).__name__}: {exc}"
        return time.perf_counter() - t1

    def render(self, j: int) -> Rendered:
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
                overlay_s = self._draw_overlay(content.rgb)
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
                overlay_s = self._draw_overlay(content.rgb)
                out = self._buffers()
                if out is None:
                    shape = (self.modulator.height_px, self.modulator.width_px, 3)
                    out = (np.empty(shape, np.uint8), np.empty(shape, np.uint8))
                row = round(self.modulator.height_px * self.early)
                self._rows.phases_rows(content.rgb, out, 0, row)
                self._early = _Early(ni, content.rgb, out, row)
        work_s, work_cpu_s = time.perf_counter() - t0, time.thread_time() - cpu0
        return Rendered(j, frame, work_s, work_cpu_s, overlay_s, content_s, content_cpu_s, time.monotonic())

