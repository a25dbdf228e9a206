"""The sender daemon: a frame clock at the projector rate, a render thread, a sink, and a pose listener.

This module is the asyncio shell; the parts it drives live in their own modules: the frame clock's rules
(:mod:`ipt.sender.clock`, pure), the renderer and its worker threads (:mod:`ipt.sender.render`), the
statistics (:mod:`ipt.sender.stats`) and the options of a run (:mod:`ipt.sender.options`).

Frames. Output frame ``j`` is due at ``start + j / f_o`` (``time.monotonic``), with ``f_o`` the
projector rate. It shows input frame ``i = floor(j · f_i / f_o)`` of the content (``j // N`` when
``f_o = N·f_i``; other ratios repeat or drop input frames, :class:`~ipt.sender.modulator.FrameTiming`).
A content thread makes input frame ``i + 1`` (the content source's frame, resized to the projector)
while the render thread works on frame ``i``. At the first output frame of input frame ``i`` the render thread draws the
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
:class:`~ipt.sender.overlay.ArOverlay`, rejected ones are counted by reason. Nothing in a datagram can stop
the loop: anything unexpected is counted as ``error``. The default filter tracks at most
:data:`~ipt.sender.overlay.DEFAULT_MAX_VEHICLES` vehicles and takes at most :data:`DEFAULT_SOURCE_RATE_HZ`
datagrams a second from one source address, so that a flood of made-up vehicle ids neither grows the
overlay's work nor takes the event loop's time from the frames (``docs/reliability.md``). A restarted
receiver is a newer stream and is taken at its first packet; when two sources (address and stream) claim
one vehicle within a second, one line on stderr names the vehicle and both, once per pair, and the newer
stream is drawn (``docs/protocol.md``).

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
import dataclasses
import math
import signal
import socket
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Final, TypeVar

import numpy as np
import numpy.typing as npt

from ipt import signals
from ipt.config.models import ArenaConfig
from ipt.errors import IptError
from ipt.memory import keep_freed_memory, warm
from ipt.protocol import PacketFilter
from ipt.runtime import Histogram, Interval, ShutdownBudget
from ipt.sender.clock import FrameClock, Verdict
from ipt.sender.content import ContentSource, GeneratedScene
from ipt.sender.display import Sink
from ipt.sender.modulator import FrameTiming, Modulator, make_modulator
from ipt.sender.options import DEFAULT_LISTEN, SenderOptions
from ipt.sender.overlay import DEFAULT_MAX_VEHICLES, ArOverlay
from ipt.sender.pairtable import default_cache_dir, stoppable
from ipt.sender.render import EARLY_ROWS, Rendered, Renderer, Worker
from ipt.sender.stats import SenderStats
from ipt.tagmap import grid_tag_map

__all__ = [
    "DEFAULT_LISTEN",
    "DEFAULT_SOURCE_RATE_HZ",
    "Sender",
    "SenderError",
    "SenderOptions",
    "SenderStats",
    "default_packet_filter",
    "parse_listen",
    "run_sender",
]

U8 = npt.NDArray[np.uint8]

RECEIVE_BUFFER_BYTES: Final = 1 << 20
"""Receive buffer asked for on the UDP socket (the kernel may cap it), so bursts are not dropped."""

ERROR: Final = "error"
"""Key in the packet counts for datagrams whose handling raised (a bug; never expected)."""

DEFAULT_SOURCE_RATE_HZ: Final = 1000.0
"""Datagrams a second the sender takes from one source address unless told otherwise: a drone sends one
pose per camera frame (120 a second), so this leaves room for eight drones behind one address, and a
flood from one address costs a token-bucket check per datagram instead of a decode."""


def default_packet_filter(key: bytes | None = None, vehicle_ids: list[int] | None = None) -> PacketFilter:
    """The sender's packet filter: ``key`` and ``vehicle_ids`` as given, at most :data:`DEFAULT_MAX_VEHICLES`
    vehicles and :data:`DEFAULT_SOURCE_RATE_HZ` datagrams a second from one source address. A restarted
    drone sending version 2 is taken at its first packet (a newer stream); one sending version 1, and a
    drone whose clock went back, after 10 s of silence."""
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


MAX_CONTENT_NOTES: Final = 20
"""Notes from the scene (frames of another size) logged in one run at most: a file that changes size at
every frame does not fill the log."""


TABLE_STOP_POLL_S: Final = 0.05
"""While the colour table is built (or the content primed), how often the event loop looks whether a stop
signal came (seconds)."""

T = TypeVar("T")

WARM_FRAMES: Final = 6
"""Frame-sized buffers each worker thread faults in before the clock starts (content frame, resized copy,
overlay and phases in flight; more than any one thread holds at once)."""


def _stderr_line(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


class _PoseListener(asyncio.DatagramProtocol):
    """Every datagram goes through the filter; accepted poses update the overlay."""

    def __init__(
        self,
        packet_filter: PacketFilter,
        overlay: ArOverlay | None,
        clock: Callable[[], float] | None = None,
        log: Callable[[str], None] = _stderr_line,
    ) -> None:
        self.filter = packet_filter
        self.overlay = overlay
        self.clock = clock
        self.log = log
        self.errors = 0
        self.socket_errors = 0

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        now = time.monotonic()
        try:
            peer = _peer_name(addr)
            packet = self.filter.accept(data, now, addr[0] if addr else None, peer)
            for conflict in self.filter.take_conflicts():  # two sources of one vehicle: said once per pair
                self.log(f"ipt-sender: {conflict}")
            if packet is not None and self.overlay is not None:
                self.overlay.update(packet, now if self.clock is None else self.clock())
        except Exception:  # a bug somewhere below: count it, keep listening
            self.errors += 1

    def error_received(self, exc: Exception) -> None:
        self.socket_errors += 1


def _peer_name(addr: tuple[str | Any, int] | None) -> str | None:
    """``"HOST:PORT"`` (``"[HOST]:PORT"`` for IPv6) of a datagram's source, naming it in conflict lines."""
    if not addr:
        return None
    host = str(addr[0])
    return f"[{host}]:{addr[1]}" if ":" in host else f"{host}:{addr[1]}"


def _wrap(fut: Future[Any]) -> asyncio.Future[Any]:
    """``fut`` as an asyncio future whose exception counts as seen (the run reports it its own way)."""
    wrapped = asyncio.wrap_future(fut)
    wrapped.add_done_callback(lambda f: f.cancelled() or f.exception())
    return wrapped


def _nothing() -> None:
    pass


class Sender:
    """One run of the sender; see the module doc. Use :func:`run_sender`."""

    def __init__(self, arena: ArenaConfig, sink: Sink, content: ContentSource | None, options: SenderOptions) -> None:
        o = options
        if o.frames is not None and o.frames < 0:
            raise SenderError(f"frames must be >= 0, got {o.frames}")
        if o.lookahead < 1:
            raise SenderError(f"lookahead must be >= 1, got {o.lookahead}")
        self.arena = arena
        self.sink = sink
        self.options = o
        self.frames = o.frames
        self.paced = sink.paced if o.paced is None else o.paced
        self.filter = o.packet_filter if o.packet_filter is not None else default_packet_filter()
        self.overlay = o.overlay if o.overlay is not None else ArOverlay(arena)
        self.log = o.log if o.log is not None else _stderr_line
        self.overlay_clock = o.overlay_clock if o.overlay_clock is not None else time.monotonic
        self.rate_hz = arena.projector.rate_hz
        self.timing = FrameTiming(o.input_rate_hz if o.input_rate_hz is not None else arena.modulation.input_rate_hz,
                                  self.rate_hz)  # fmt: skip
        self.modulator = _modulator_for(arena, o.modulator)
        self.pair_cache = default_cache_dir() if o.pair_cache == "default" else o.pair_cache
        pr = arena.projector
        # Sinks that are done with a frame when show() returns let the phases be written into a ring of
        # reused arrays: the pair shown, those of the frames up to `lookahead` ahead, and one begun early.
        self.renderer = Renderer(
            content if content is not None else GeneratedScene(pr.width_px, pr.height_px),
            self.modulator,
            self.overlay,
            self.timing,
            self.overlay_clock,
            None,
            o.lookahead + 3 if getattr(sink, "borrows", False) else None,
            o.frames,
            EARLY_ROWS if self.paced else None,  # unpaced sinks have no deadlines: keep the work simple there
        )
        self.renderer.live = bool(getattr(sink, "retries", False))
        self.stats = SenderStats(pr.width_px, pr.height_px, self.rate_hz, self.paced)
        self.bound: tuple[str, int] | None = None
        self.should_exit = False
        self.force_exit = False
        self._listener: _PoseListener | None = None
        self._transport: asyncio.DatagramTransport | None = None
        self._render: Worker | None = None
        self._content: Worker | None = None
        self._display: Worker | None = None
        self._pending: deque[tuple[int, Future[Any]]] = deque()
        self._next_submit = 0
        self._unroute_signals: Callable[[], None] = _nothing
        self._interval_work = Histogram()
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
        if self.options.install_signal_handlers:
            self._unroute_signals = signals.route_to_loop(loop, self.handle_exit)

    def _remove_signal_handlers(self, loop: asyncio.AbstractEventLoop) -> None:
        self._unroute_signals()
        self._unroute_signals = _nothing

    def _stopping(self) -> bool:
        if self.options.stop is not None and self.options.stop.is_set():
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
        self._render = Worker("ipt-render")
        self._content = self.renderer.content_worker = Worker("ipt-content")
        # Deadlines from the first frame: every colour's pair before the clock starts (read from the cache,
        # or computed once), so that no frame has to work out the colours it is the first to show.
        complete: Callable[..., str] | None = getattr(self.modulator, "complete_table", None)
        if self.paced and complete is not None and not getattr(self.modulator, "table_complete", True):

            def log(text: str) -> None:
                self.log(f"ipt-sender: {text}")

            def build(stop: threading.Event) -> str:
                with stoppable(stop):
                    return complete(self.pair_cache, log)

            log(await self._stoppable(self._render, build))
        # Before the clock starts, fault in the memory the first frames will use (see ipt.memory): without
        # this the first second at 1920x2160 missed up to 8 deadlines, each frame paying tens of
        # milliseconds for fresh pages.
        shape = (self.modulator.height_px, self.modulator.width_px, 3)
        frame_bytes = int(np.prod(shape))
        keep_freed_memory(frame_bytes, WARM_FRAMES * 3 * frame_bytes)
        for worker in (self._render, self._content):
            await asyncio.wrap_future(worker.submit(warm, shape, WARM_FRAMES))
        self.renderer.allocate()
        if self.paced:  # content decoded ahead (a video, photos): its buffer full before the first deadline
            await self._stoppable(self._content, self.renderer.prime_content)
        if self.sink.threaded:
            self._display = Worker("ipt-display")
        if self.options.listen is not None:
            self._listener = _PoseListener(self.filter, self.overlay, self.options.overlay_clock, self.log)
            self._transport, self.bound = await self._bind(loop, *self.options.listen)
            self.log(f"ipt-sender: listening for pose packets on udp {self.bound[0]}:{self.bound[1]}")
            if self.options.on_listening is not None:
                self.options.on_listening(self.bound)
        self._started = True

    async def _stoppable(self, worker: Worker, fn: Callable[[threading.Event], T]) -> T:
        """``fn(stop)`` run in ``worker``; a stop signal meanwhile sets ``stop`` within tens of milliseconds
        (the colour table's build, the content's priming), rather than being seen after ``fn`` returns."""
        stop = threading.Event()
        future = asyncio.wrap_future(worker.submit(fn, stop))
        while not future.done():
            await asyncio.wait({future}, timeout=TABLE_STOP_POLL_S)
            if self._stopping():
                stop.set()
        result: T = future.result()
        return result

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
        while len(self._pending) < self.options.lookahead and (self.frames is None or self._next_submit < self.frames):
            j = self._next_submit
            self._pending.append((j, self._render.submit(self.renderer.render, j)))
            self._next_submit += 1

    async def _wait_rendered(self, fut: Future[Any]) -> Rendered | None:
        """The frame of ``fut``, or None if a stop is asked for while waiting."""
        wrapped = _wrap(fut)
        while not wrapped.done():
            await asyncio.wait([wrapped], timeout=0.05)
            if not wrapped.done() and self._stopping():
                return None
        result: Rendered = wrapped.result()
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
        clock = FrameClock(self.rate_hz)
        first = 0.0  # when frame 0 was shown
        stats = self.stats
        interval, interval_frames = Interval(self.options.stats_every_s, time.monotonic()), 0
        j = 0
        self._fill()
        while not self._stopping() and (self.frames is None or j < self.frames):
            rendered = await self._wait_rendered(self._pending[0][1])
            if rendered is None:
                break
            self._pending.popleft()
            self._fill()  # the render thread goes on with the next frames while this one waits
            if self.paced:
                # Missed or late: show it now and count it; the clock restarts from this frame (the next one
                # is due a period later) rather than rushing frames out to catch up.
                verdict = clock.judge(j, rendered.ready_s, time.monotonic())
                if verdict is Verdict.MISSED:
                    stats.missed += 1
                elif verdict is Verdict.LATE:
                    stats.late += 1
                else:
                    await self._sleep_until(clock.due_s(j))
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
            if interval.due(now):
                self._collect()
                span = interval.restart(now)
                line = stats.line(interval_frames, span, self._interval_work)
                self.log(f"ipt-sender: t={stats.elapsed_s:.1f}s {line}")
                self._interval_work.clear()
                interval_frames = 0

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
        if self.overlay is not None:
            stats.vehicles = len(self.overlay.vehicle_ids())
        if self.renderer.first_overlay_error is not None and not self._overlay_error_logged:
            self._overlay_error_logged = True
            self.log(f"ipt-sender: overlay failed (frames are shown without it): {self.renderer.first_overlay_error}")

    async def _shutdown(self, ok: bool) -> None:
        """Ordered, each wait bounded: socket, render thread, content thread, sink, final statistics."""
        budget = ShutdownBudget(0.1 if self.force_exit else self.options.shutdown_timeout_s)
        running = [fut for _, fut in self._pending if not fut.cancel()]  # cancel the frames not started
        self._pending.clear()
        if self._transport is not None:
            self._transport.close()
        if self._render is not None:
            self._render.stop()
            if running:
                await budget.wait([_wrap(f) for f in running])
        if self._content is not None:
            # The input frame made ahead: not needed any more; if it is being made, let it finish (the
            # caller may close the scene next).
            ahead = self.renderer.cancel_ahead()
            self._content.stop()
            if ahead is not None:
                await budget.wait([_wrap(ahead)])
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
    content: ContentSource | None = None,
    options: SenderOptions | None = None,
    **changes: Any,
) -> SenderStats:
    """Run the sender until ``options.frames`` output frames are shown, a signal, ``options.stop`` or the sink
    says stop.

    Args:
        arena: projector size and rate, tag map and modulation.
        sink: where the frames go (:mod:`ipt.sender.display`).
        content: the content source (default: the generated map at projector size).
        options: how the run is set up (:class:`~ipt.sender.options.SenderOptions`; default: its defaults).
        changes: fields of ``options`` to set, by name (``frames=600, listen=None``).
    """
    options = dataclasses.replace(options if options is not None else SenderOptions(), **changes)
    if not options.stats_every_s > 0:
        raise SenderError(f"stats_every_s must be > 0, got {options.stats_every_s}")
    try:
        sender = Sender(arena, sink, content, options)
    except BaseException:
        sink.abort()  # nothing was shown: leave nothing behind (a file sink may have started its file)
        raise
    return await sender.run()


def _modulator_for(arena: ArenaConfig, modulator: Modulator | None) -> Modulator:
    """``modulator``, checked against the projector's size; by default the arena's profile for its tag map."""
    mod, pr = arena.modulation, arena.projector
    if modulator is None:
        mask = grid_tag_map(arena).render_mask()
        return make_modulator(mod.profile, mask, mod.delta_l, clip_allowance_l8=mod.clip_allowance_l8)
    if (modulator.width_px, modulator.height_px) != (pr.width_px, pr.height_px):
        raise SenderError(
            f"the modulator is for {modulator.width_px}x{modulator.height_px}, the projector is "
            f"{pr.width_px}x{pr.height_px}"
        )
    return modulator
