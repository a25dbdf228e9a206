"""The receiver daemon: camera frames in, UDP pose packets out, continuously.

Three stages, each on its own thread, joined by bounded queues::

    capture thread ──FrameQueue(queue_size)──▶ event loop ──▶ pipeline thread ──▶ event loop ──▶ UDP
    (blocking reads;       (live: newest wins,      (submits      (one worker:         (packets,
     paced if real time)    oldest dropped)          in order)     Pipeline)            stats)

- The **capture thread** (:class:`~ipt.receiver.capture.CaptureThread`) does every blocking read and
  hands frames over; a live source never waits, a recording waits for room.
- The **event loop** takes frames in capture order and submits them to a single-worker executor that
  runs :meth:`Pipeline.process`. From a recording it keeps :data:`MAX_IN_FLIGHT` frames there: while
  frame ``k`` is processed, frame ``k + 1`` is already waiting, so the worker never idles for a round
  trip through the loop, and capture (decode or render) overlaps with processing on another core. From
  a live source it takes the newest frames as a *run* of consecutive ones (at most
  :data:`LIVE_RUN_FRAMES`, what the queue holds when the worker comes free) and submits the next run once
  the worker is done with it: a pose needs two frames of opposite phase close in time, so a pipeline slower
  than the camera must still see frames close together. Taking the newest frame alone, a worker k times
  slower than the camera saw every k-th frame: beyond about 5 (a Pi 4, by the estimate in
  ``docs/receiver-cores.md``) no frame had a partner near enough, and not one pose came out; at 3-4 the
  partners 3-4 frames apart failed on a vibrating camera. When the worker keeps up, a run is one frame,
  the newest. When it fell behind by more than the queue holds, the projector's phase is known, and the
  floor's content moves or the worker is slower than the camera (:func:`~ipt.receiver.liverun.pairs_pay`),
  the run is the newest + and − frames of one video frame (:func:`~ipt.receiver.liverun.pick_run`; the
  daemon waits up to three frames for them), the other frames held are dropped. Each frame of a live source goes
  with its wait since its grab (the pipeline's live rule reads it:
  :data:`~ipt.receiver.core.sparsestage.LIVE_LATE_US`; the frame recording keeps it). Figures:
  ``docs/receiver-cores.md``. Before a live camera starts, the worker rehearses (:mod:`ipt.receiver.rehearsal`).
- **In order**: the pipeline is stateful (each frame is demodulated against the one before), so it
  must see frames in capture order. It does: one coroutine submits them in the order the FIFO queue
  yields them, and one worker thread takes them from the executor's FIFO queue one after the other.
  Results are awaited in submission order too, so packets leave in capture order.
- Latency is the daemon's clock right after the packet was sent minus the frame's grab (or read)
  instant, so it includes the time a frame waited in the queues. The clock is passed in
  (:attr:`ReceiverOptions.clock <ipt.receiver.options.ReceiverOptions.clock>`, ``time.monotonic`` by
  default), as the rest of a run's setup: :func:`run_daemon` takes the files already loaded
  (:class:`~ipt.receiver.options.ReceiverSetup`) and a :class:`~ipt.receiver.options.ReceiverOptions`, as the
  sender takes its :class:`~ipt.sender.options.SenderOptions`; the task set, the ordered shutdown's budget and
  the statistics interval are the sender's too (:mod:`ipt.runtime`).
- The other outputs take each result on the event loop after the UDP packet: MAVLink
  (:mod:`ipt.receiver.outputs.mavlink.output`) there, ROS 2 over DDS and the MCAP recording through
  :class:`~ipt.receiver.outputs.ros.output.RosOutputs`, which only queues the result for its own thread. Each
  is set up before the first frame (a mistake there is an :class:`~ipt.errors.IptError`), and a failure
  later is counted in its own summary line while the others go on.

Shutdown (SIGTERM, SIGINT or SIGHUP, the end of a recording, or ``--max-frames``): the signal handlers
only set the stop event, and they are in place from the first line of :func:`run_daemon` (a signal that
came earlier, while the event loop started, is delivered then; see :mod:`ipt.signals`); then, within
:data:`SHUTDOWN_BUDGET_S`, capture stops, queued frames are dropped, frames already submitted get up to
:data:`DRAIN_TIMEOUT_S` to finish and be sent, the sockets are closed, the read in progress on the
capture thread is waited for, and a final statistics line is printed. A read that does not end in time
(a hung camera driver) is left to its daemon thread and reported in :attr:`DaemonStats.capture_running`,
on which the command line leaves with ``os._exit``.
"""

from __future__ import annotations

import asyncio
import dataclasses
import sys
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TextIO

from ipt import signals
from ipt.config.camera_info import CameraInfo
from ipt.config.models import ArenaConfig
from ipt.config.receiver import ReceiverConfig
from ipt.protocol import ProtocolError
from ipt.receiver.capture import (
    CapturedFrame,
    CaptureError,
    CaptureSource,
    CaptureThread,
    DeviceCapture,
    FrameQueue,
    PiCamera2Capture,
    VideoCapture,
)
from ipt.receiver.core.pipeline import FrameResult, Pipeline
from ipt.receiver.core.reasons import FrameReason
from ipt.receiver.detect.detector import pipeline_detector
from ipt.receiver.liverun import LIVE_RUN_FRAMES, LivePicker
from ipt.receiver.options import ProcessedHook, ReceiverOptions, ReceiverSetup, ResultHook, load_setup
from ipt.receiver.outputs.udp import PacketMaker, UdpPoseSender, new_stream_id
from ipt.receiver.rehearsal import warm_up
from ipt.runtime import Clock, Histogram, Interval, ShutdownBudget, TaskSet, run_loop, write_line

if TYPE_CHECKING:
    from ipt.receiver.capture.framelog import FrameLogWriter
    from ipt.receiver.outputs.mavlink.output import MavlinkOutput
    from ipt.receiver.outputs.ros.output import RosOutputs

MAX_IN_FLIGHT = 2
"""Frames submitted to the pipeline worker at once from a recording (one processing, one waiting); a live
source submits one run at a time (:data:`LIVE_RUN_FRAMES`)."""
SHUTDOWN_BUDGET_S = 0.5
"""How long shutdown may take in all, from the stop to the return (the process must be gone within 1 s)."""
DRAIN_TIMEOUT_S = 0.4
"""How long frames already submitted may take to finish at shutdown (within the budget)."""
MAX_ERROR_REPORTS = 5
"""Pipeline errors reported in full on stderr; later ones are only counted."""

PROG = "ipt-receiver"


def _ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f} ms"


@dataclass(frozen=True)
class DaemonStats:
    """Totals of one run of the daemon."""

    frames_captured: int
    """Frames the source delivered (including dropped ones)."""
    frames_processed: int
    poses: int
    packets_sent: int
    """Datagrams handed to the kernel (one per pose per target)."""
    send_errors: int
    drops: int
    """Frames dropped because processing was behind a live source."""
    capture_failures: int
    seconds: float
    latency_p50_ms: float | None
    latency_p99_ms: float | None
    reasons: dict[str, int]
    detector_recycles: int = 0
    """Detector helper processes replaced because their memory grew (see :mod:`ipt.receiver.detect.tagworker`)."""
    detector_restarts: int = 0
    """Detector helper processes replaced because they crashed, hung or did not start."""
    frames_skipped: int = 0
    """Frames of a recording that could not be decoded or read, or had another size: skipped, not captured."""
    capture_running: bool = False
    """The capture thread was still inside a read (stuck in a driver, say) when the daemon returned. It
    is a daemon thread; a process about to exit should then leave with ``os._exit`` rather than run
    native destructors under a thread that is still inside them."""

    @property
    def yield_fraction(self) -> float:
        """Poses per processed frame."""
        return self.poses / self.frames_processed if self.frames_processed else 0.0

    def line(self) -> str:
        """The final statistics line."""
        s = max(self.seconds, 1e-9)
        why = ", ".join(f"{k}={v}" for k, v in sorted(self.reasons.items()))
        return (
            f"{PROG}: final: {self.frames_processed} frames ({self.frames_captured} captured), {self.poses} poses, "
            f"{self.packets_sent} packets in {self.seconds:.2f} s: {self.frames_processed / s:.1f} frames/s, "
            f"{self.poses / s:.1f} poses/s, yield {100 * self.yield_fraction:.1f} %, "
            f"latency p50 {_ms(self.latency_p50_ms)} p99 {_ms(self.latency_p99_ms)}, drops {self.drops}, "
            f"send errors {self.send_errors}, capture failures {self.capture_failures}, "
            + (f"unreadable frames skipped {self.frames_skipped}, " if self.frames_skipped else "")
            + "detector helpers "
            f"replaced {self.detector_recycles} for memory and {self.detector_restarts} after failures ({why})"
        )


class _Meter:
    """Counts kept on the event loop's thread: per interval and for the whole run."""

    def __init__(self, interval: Interval) -> None:
        self.frames = self.poses = 0
        self.reasons: Counter[str] = Counter()
        self.latency = Histogram(bin_ms=0.1, limit_ms=10_000.0)
        self.interval = interval
        self.i_frames = self.i_poses = 0
        self.i_latency = Histogram(bin_ms=0.1, limit_ms=10_000.0)

    def frame(self, reason: str) -> None:
        self.frames += 1
        self.i_frames += 1
        self.reasons[str(reason)] += 1  # plain text keys, whether the reason came as text or a FrameReason

    def pose(self, latency_s: float) -> None:
        self.poses += 1
        self.i_poses += 1
        self.latency.add(latency_s * 1e3)
        self.i_latency.add(latency_s * 1e3)

    def interval_line(self, now_s: float, drops: int, send_errors: int) -> str:
        span = self.interval.restart(now_s)
        yield_ = 100 * self.i_poses / self.i_frames if self.i_frames else 0.0
        line = (
            f"{PROG}: {self.i_frames / span:.1f} frames/s, {self.i_poses / span:.1f} poses/s, yield {yield_:.1f} %, "
            f"latency p50 {_ms(self.i_latency.quantile_ms(0.5))} p99 {_ms(self.i_latency.quantile_ms(0.99))}, "
            f"drops {drops}, send errors {send_errors} (totals)"
        )
        self.i_frames = self.i_poses = 0
        self.i_latency.clear()
        return line


def make_source(cfg: ReceiverConfig, arena: ArenaConfig, camera: CameraInfo, stop: threading.Event) -> CaptureSource:
    """The frame source ``cfg.source`` describes; its pacing sleeps end early when ``stop`` is set.

    The simulated camera (``sim``) is not made here (the receiver does not import the simulator): the
    command line makes it (:func:`ipt.sim.capture.sim_source`) and hands it to :func:`run_daemon`."""
    spec = cfg.source_spec
    grey = cfg.pipeline.luminance_only  # frames as luma, without a detour through RGB
    if spec.kind in ("video", "images") and spec.path is not None:
        size = (camera.width_px, camera.height_px)
        images = spec.kind == "images"
        return VideoCapture(spec.path, cfg.fps, cfg.realtime, size=size, sleep=stop.wait, images_only=images, grey=grey)
    w, h = camera.width_px, camera.height_px
    if spec.kind == "device" and spec.device is not None:
        return DeviceCapture(spec.device, w, h, cfg.fps, controls=cfg.camera_controls, grey=grey)
    if spec.kind == "picamera2" and spec.device is not None:
        return PiCamera2Capture(spec.device, w, h, cfg.fps, controls=cfg.camera_controls, grey=grey)
    raise CaptureError(f"source {cfg.source}: the simulated camera is handed to the daemon by the command line")


async def run_daemon(setup: ReceiverSetup, options: ReceiverOptions | None = None, **changes: Any) -> DaemonStats:
    """Run the receiver until ``options.stop`` is set (or SIGTERM/SIGINT), the recording ends or
    ``options.max_frames`` frames were captured; ``changes`` are fields of ``options`` to set, by name
    (``max_frames=90, install_signal_handlers=False``). Statistics go to ``options.stats_out`` (default:
    stderr). A problem with the outputs raises :class:`~ipt.errors.IptError` before any frame is read (the
    files were read by :func:`~ipt.receiver.options.load_setup`)."""
    options = dataclasses.replace(options if options is not None else ReceiverOptions(), **changes)
    loop = asyncio.get_running_loop()
    stop_event = options.stop if options.stop is not None else asyncio.Event()
    routed = options.install_signal_handlers
    unroute = signals.route_to_loop(loop, lambda _sig: stop_event.set()) if routed else None
    try:
        return await _DaemonRun(setup, options, stop_event).run()
    finally:
        if unroute is not None:
            unroute()


Batch = tuple[list[FrameResult], dict[str, float]]
"""What the pipeline worker gives back for one frame: the results that became final with it, and the
processor time each stage took for it."""


class _DaemonRun:
    """One run of the receiver daemon (what :func:`run_daemon` does), in the sender's shape: :meth:`start`
    opens the outputs and the camera, :meth:`submit` and :meth:`deliver` move the frames through the
    pipeline worker to the outputs, :meth:`report` prints the interval statistics, :meth:`shutdown` stops
    it all in order; :meth:`run` is the whole life, :meth:`stats` its totals."""

    def __init__(self, setup: ReceiverSetup, options: ReceiverOptions, stop: asyncio.Event) -> None:
        """Make the pipeline, the source and the outputs (:class:`~ipt.errors.IptError` on a configuration
        problem, before any frame is read)."""
        self.cfg = cfg = setup.cfg
        self.stop, self.on_result, self.on_processed = stop, options.on_result, options.on_processed
        self.clock: Clock = options.clock
        self.out = out = options.stats_out if options.stats_out is not None else sys.stderr
        self.loop = loop = asyncio.get_running_loop()
        self.camera, self.key, self.map_hash = setup.camera, setup.key, setup.map_hash
        projector_hz = setup.arena.projector.rate_hz
        detector = pipeline_detector(cfg.pipeline.detector, setup.tag_map.by_id)
        self.pipeline = Pipeline(setup.tag_map, setup.camera, cfg.pipeline, projector_hz, detector)
        capture_stop = options.capture_stop if options.capture_stop is not None else threading.Event()
        source = options.source
        if source is None:
            source = make_source(cfg, setup.arena, setup.camera, capture_stop)
        self.source = source
        self.pipeline.acquisition.live = source.live  # (a live camera's fallback pairs are not searched)

        self.frames: FrameQueue[CapturedFrame] = FrameQueue(LIVE_RUN_FRAMES if source.live else cfg.queue_size)
        max_frames = options.max_frames
        self.capture = CaptureThread(source, self.frames, loop, stop=capture_stop, max_frames=max_frames, report=out)
        self.worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="ipt-pipeline")
        self.sender = UdpPoseSender(cfg.send_targets)
        self.maker = PacketMaker(cfg.vehicle_id, self.key, stream_id=new_stream_id())  # each run a newer stream
        self.mavlink = _mavlink_output(cfg, out)
        self.ros = _ros_outputs(cfg, projector_hz, out)
        self.meter = _Meter(Interval(cfg.stats_interval_s, self.clock.now()))
        self.errors_reported = 0

        # A live source: one run at a time, so that the worker always takes the newest frames (a frame waiting
        # in the executor would be stale by a whole processing time when its turn comes). A recording keeps
        # the worker busy instead: the next frame waits while this one is processed.
        self.slots = asyncio.Semaphore(1 if source.live else MAX_IN_FLIGHT)
        # Each submitted frame with its future, and whether its result frees a slot (a run's last frame).
        self.results: asyncio.Queue[tuple[CapturedFrame | None, asyncio.Future[Batch], bool] | None] = asyncio.Queue()
        self.stage_totals: dict[str, float] | None = getattr(self.pipeline, "stage_seconds", None)
        self.last_taken = -1
        """Index of the last frame taken from a live source (a jump after it: frames were dropped)."""
        self.live = LivePicker()
        """Which frames of a live source's queue to process after falling behind (:mod:`ipt.receiver.liverun`)."""
        self.waiting: dict[int, CapturedFrame] = {}
        """Frames processed whose result has not come out yet (the pipeline's look-ahead), by index."""
        self.tasks = TaskSet()
        self.deliver_task: asyncio.Task[None] | None = None
        self.running = False
        """The source opened and frames began to flow (else the ROS recording is aborted, not closed)."""
        self.start_s = self.clock.now()
        self.frame_log: FrameLogWriter | None = options.frame_log

    async def run(self) -> DaemonStats:
        """Start, run until stopped or the source ends, shut down, and print and return the totals."""
        stop_wait = self.tasks.spawn(_wait_event(self.stop), "ipt-stop")
        self.start_s = self.clock.now()
        try:
            if await self.start(stop_wait):
                self.tasks.spawn(self.submit(), "ipt-submit")
                self.deliver_task = self.tasks.spawn(self.deliver(), "ipt-deliver")
                self.tasks.spawn(self.report(), "ipt-stats")
                await asyncio.wait({self.deliver_task, stop_wait}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            await self.shutdown()
        task = self.deliver_task
        if task is not None and not task.cancelled() and task.exception() is not None:
            raise RuntimeError("the delivery stage failed") from task.exception()
        stats = self.stats()
        self.say_summaries(stats)
        return stats

    async def start(self, stop_wait: asyncio.Task[None]) -> bool:
        """Open the outputs, start the capture thread and wait for the source's first open (or the stop):
        whether frames are coming. Raises the error of a first open that is not retried."""
        if self.ros is not None:
            self.ros.start()
        await self.sender.open()
        if self.mavlink is not None:
            await self.mavlink.open()  # the link itself is (re)opened in the background
        if self.source.live and not self.stop.is_set():  # the first frames then find the code warm
            await self.loop.run_in_executor(self.worker, warm_up, self.pipeline, self.out)
        if not self.stop.is_set():  # a signal while starting: do not begin to capture at all
            self.capture.start()
        ready = asyncio.wrap_future(self.capture.ready)
        await asyncio.wait({ready, stop_wait}, return_when=asyncio.FIRST_COMPLETED)
        if not ready.done():
            ready.cancel()
            return False
        ready.result()  # raises the error of a first open that is not retried (bad video file, ...)
        self.running = True
        self.start_s = self.meter.interval.start_s = self.clock.now()
        auth = ", authenticated" if self.key is not None else ""
        source, camera, cfg = self.source, self.camera, self.cfg
        write_line(
            self.out,
            f"{PROG}: running: {source.name}{' (live)' if source.live else ''}, camera "
            f"{camera.width_px}x{camera.height_px}, vehicle {cfg.vehicle_id} -> {', '.join(cfg.send)}{auth}, "
            f"map hash sha256:{self.map_hash}",
        )
        return True

    def finish_before(self, capture_time_us: int) -> Batch:
        """On the worker thread: the results no frame captured from ``capture_time_us`` on can change
        (:meth:`Pipeline.finish_before`)."""
        return self.pipeline.finish_before(capture_time_us), {}

    def process(self, frame: CapturedFrame | None, waited_us: int | None = None) -> Batch:
        """On the worker thread: the results that became final with this frame (``None``: at the end, all
        that wait) and the processor time each stage took for it (from the pipeline's running totals, read
        on the same thread, so no other frame is counted in). ``waited_us``: a live camera's frame's wait."""
        stage_totals = self.stage_totals
        before = dict(stage_totals) if self.ros is not None and stage_totals is not None else None
        if frame is None:
            batch = self.pipeline.flush()
        else:
            t0 = time.perf_counter()
            batch = self.pipeline.process(frame.index, frame.image, frame.capture_time_us, waited_us)
            if self.source.live:  # (only a live source's runs are picked)
                self.live.note(self.pipeline.live_hints(), time.perf_counter() - t0)
        if before is None or stage_totals is None:
            return batch, {}
        stages = {k: v - before.get(k, 0.0) for k, v in stage_totals.items() if v != before.get(k, 0.0)}
        return batch, stages

    async def submit(self) -> None:
        """Frames from the capture queue to the pipeline worker, in capture order."""
        loop, worker, results = self.loop, self.worker, self.results
        try:
            while True:
                await self.slots.acquire()  # before taking a frame, so that a live source's newest ones are taken
                frame = await self.frames.get()
                if frame is None:  # the end of a recording: what still waits for later frames comes out
                    results.put_nowait((None, loop.run_in_executor(worker, self.process, None), True))
                    return
                run = [frame, *self.frames.take_all()] if self.source.live else [frame]
                if self.source.live and frame.index > self.last_taken + 1 and self.last_taken >= 0:
                    run = await self.live.pick(run, self.more_frames)
                    frame = run[0]
                if self.source.live and frame.index > self.last_taken + 1:
                    # Frames were dropped: the results that waited for them come out now, not after this run.
                    t_us = frame.capture_time_us
                    if self.frame_log is not None:
                        self.frame_log.finish_before(t_us)
                    results.put_nowait((None, loop.run_in_executor(worker, self.finish_before, t_us), False))
                self.last_taken = run[-1].index
                for k, item in enumerate(run):
                    waited_us = self.waited_us(item)
                    if self.frame_log is not None:
                        self.frame_log.add(item, waited_us)
                    done = loop.run_in_executor(worker, self.process, item, waited_us)
                    results.put_nowait((item, done, k == len(run) - 1))
        finally:
            results.put_nowait(None)

    def waited_us(self, frame: CapturedFrame) -> int | None:
        """A live camera's frame's wait between its grab and its hand-over to the pipeline (µs; the pipeline's live
        rules read it, the frame recording keeps it); None for a recording's."""
        return max(round((self.clock.now() - frame.grabbed_s) * 1e6), 0) if self.source.live else None

    async def more_frames(self, timeout_s: float) -> list[CapturedFrame]:
        """The next frame of a live source and those queued after it, or [] if none came within ``timeout_s`` or
        the source ended (the next get says so again)."""
        try:
            frame = await asyncio.wait_for(self.frames.get(), timeout_s)
        except TimeoutError:
            return []
        return [] if frame is None else [frame, *self.frames.take_all()]

    async def deliver(self) -> None:
        """Results in frame order to the UDP targets."""
        while True:
            item = await self.results.get()
            if item is None:
                return
            frame, fut, frees_slot = item
            if frame is not None:
                self.waiting[frame.index] = frame
            batch: list[FrameResult] = []
            stages: dict[str, float] = {}
            try:
                batch, stages = await fut
            except Exception as exc:  # a bug or a library failure on one frame: report, count, go on
                self.processing_failed(frame, stages, exc)
            finally:
                if frees_slot:
                    self.slots.release()
            sent_total = 0
            for result in batch:
                owner = self.waiting.pop(result.index, None)
                if owner is None:  # not a frame this daemon submitted (cannot happen): nothing to send it for
                    continue
                sent_total += self.deliver_result(owner, result, stages if owner is frame else {})
            if frame is not None and self.on_processed is not None:
                self.on_processed(frame, sent_total)

    def processing_failed(self, frame: CapturedFrame | None, stages: dict[str, float], exc: Exception) -> None:
        """Count and report a frame whose processing raised (``None``: finishing the frames that waited, at the
        end or after dropped frames)."""
        if frame is not None:
            self.waiting.pop(frame.index, None)
            self.meter.frame(FrameReason.ERROR)
            if self.ros is not None:
                self.ros.on_result(frame, None, stages)
            if self.on_result is not None:
                self.on_result(frame, None, 0)
        if self.errors_reported < MAX_ERROR_REPORTS:
            self.errors_reported += 1
            where = f"frame {frame.index}" if frame is not None else "finishing the frames that waited"
            write_line(self.out, f"{PROG}: {where}: processing failed: {type(exc).__name__}: {exc}")

    def deliver_result(self, frame: CapturedFrame, result: FrameResult, stages: dict[str, float]) -> int:
        """One frame's result to every output; the number of datagrams sent."""
        # One failure, one line: the pipeline flags the first result that comes out after it (the frame that
        # failed may come out later, or keep a pose from another pair).
        if result.detector_failed and self.errors_reported < MAX_ERROR_REPORTS:
            self.errors_reported += 1
            write_line(
                self.out, f"{PROG}: frame {frame.index}: the tag detector's helper process failed; starting another"
            )
        sent = self.deliver_one(frame, result)
        if self.mavlink is not None:
            self.mavlink.on_result(frame, result)
        if self.ros is not None:
            self.ros.on_result(frame, result, stages)
        if self.on_result is not None:
            self.on_result(frame, result, sent)
        return sent

    def deliver_one(self, frame: CapturedFrame, result: FrameResult) -> int:
        """Count one frame's result and send its pose; the number of datagrams sent."""
        if result.pose is None:
            self.meter.frame(result.reason)
            return 0
        try:
            data = self.maker.encode(result.pose, frame.capture_time_us)
        except ProtocolError:  # e.g. a non-finite position: not sendable
            self.meter.frame(FrameReason.BAD_POSE)
            return 0
        self.meter.frame(result.reason)
        sent = self.sender.send(data)
        self.meter.pose(self.clock.now() - frame.grabbed_s)
        return sent

    async def report(self) -> None:
        """The interval statistics line, every ``stats_interval_s``."""
        while True:
            await self.clock.sleep(self.cfg.stats_interval_s)
            write_line(self.out, self.meter.interval_line(self.clock.now(), self.drops, self.sender.errors))

    async def shutdown(self) -> None:
        """Stop everything in order within :data:`SHUTDOWN_BUDGET_S` (see the module's doc)."""
        budget = ShutdownBudget(SHUTDOWN_BUDGET_S)
        # Ordered: stop capture, drop queued frames, let submitted ones finish (bounded), close sockets.
        self.capture.stop()
        self.frames.finish(discard=True)
        if self.deliver_task is not None and not self.deliver_task.done():
            await budget.wait({self.deliver_task}, cap_s=DRAIN_TIMEOUT_S)
        await self.tasks.cancel_all()
        await self.sender.close()
        if self.mavlink is not None:
            await self.mavlink.close()
        if self.ros is not None:
            # A run that never got going (a camera or a send target that cannot be opened) leaves no
            # recording that looks complete.
            await asyncio.to_thread(self.ros.close if self.running else self.ros.abort)
        self.worker.shutdown(wait=False, cancel_futures=True)
        # The detector's helper process ends when its pipe closes: close it once the pipeline thread is done
        # with its frame (not at garbage collection, which may be much later for a daemon run in-process).
        threading.Thread(target=self._close_pipeline, name="ipt-close-pipeline", daemon=True).start()
        # The read in progress (a render, a decode, a camera grab) ends by itself; wait for it within the
        # budget. If it does not end, the thread is a daemon thread and `capture_running` tells the caller.
        self.capture.join(budget.left())

    @property
    def drops(self) -> int:
        """Frames not processed because processing was behind a live source: dropped by the queue, or passed over."""
        return self.frames.dropped + self.live.passed_over

    def _close_pipeline(self) -> None:
        self.worker.shutdown(wait=True)
        self.pipeline.close()

    def stats(self) -> DaemonStats:
        """The totals of the run (after :meth:`shutdown`)."""
        capture, meter, sender = self.capture, self.meter, self.sender
        return DaemonStats(
            frames_captured=capture.frames,
            frames_processed=meter.frames,
            poses=meter.poses,
            packets_sent=sender.sent,
            send_errors=sender.errors,
            drops=self.drops,
            capture_failures=capture.failures,
            seconds=self.clock.now() - self.start_s,
            latency_p50_ms=meter.latency.quantile_ms(0.5),
            latency_p99_ms=meter.latency.quantile_ms(0.99),
            reasons=dict(meter.reasons),
            detector_recycles=self.pipeline.detector_replacements[0],
            detector_restarts=self.pipeline.detector_replacements[1],
            frames_skipped=capture.skipped,
            capture_running=not capture.join(0),
        )

    def say_summaries(self, stats: DaemonStats) -> None:
        """The final statistics line, the last send error, and each output's summary."""
        write_line(self.out, stats.line())
        if self.sender.last_error is not None:
            write_line(self.out, f"{PROG}: last send error: {self.sender.last_error}")
        if self.mavlink is not None:
            self.mavlink.say_summary()
        if self.ros is not None:
            for line in self.ros.summaries():
                write_line(self.out, f"{PROG}: {line}")


def _mavlink_output(cfg: ReceiverConfig, out: TextIO) -> MavlinkOutput | None:
    """The MAVLink output ``cfg.mavlink`` asks for (pymavlink is imported only then)."""
    if cfg.mavlink.link is None:
        return None
    from ipt.receiver.outputs.mavlink.output import MavlinkOutput

    return MavlinkOutput(cfg.mavlink, report=out, prog=PROG)


def _ros_outputs(cfg: ReceiverConfig, projector_hz: float, out: TextIO) -> RosOutputs | None:
    """The ROS 2 topics and the MCAP log ``cfg.ros2`` and ``cfg.record`` ask for, if any (their module, with the
    ROS message layouts, is imported only then: a daemon without them starts sooner)."""
    if not cfg.ros2.enabled and cfg.record.path is None:
        return None
    from ipt.receiver.outputs.ros.output import RosOutputs

    return RosOutputs.create(cfg, projector_hz, lambda line: write_line(out, f"{PROG}: {line}"))


async def _wait_event(event: asyncio.Event) -> None:
    await event.wait()


def run(setup: ReceiverSetup, options: ReceiverOptions | None = None, **changes: Any) -> DaemonStats:
    """Run the daemon on a fresh event loop (uvloop when installed) until it stops (as :func:`run_daemon`)."""
    return run_loop(run_daemon(setup, options, **changes))


__all__ = [
    "DaemonStats",
    "ProcessedHook",
    "ReceiverOptions",
    "ReceiverSetup",
    "ResultHook",
    "load_setup",
    "make_source",
    "run",
    "run_daemon",
]
