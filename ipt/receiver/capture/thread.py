"""The capture thread: runs a source's blocking reads off the event loop and hands the frames to the queue."""

from __future__ import annotations

import asyncio
import concurrent.futures
import sys
import threading
import time
from collections.abc import Callable
from typing import TextIO

from ipt.errors import IptError
from ipt.ratelimit import LogThrottle
from ipt.receiver.capture.queue import FrameQueue
from ipt.receiver.capture.source import (
    CapturedFrame,
    CaptureSource,
)

BACKOFF_FIRST_S = 0.1
BACKOFF_MAX_S = 1.0


class CaptureThread:
    """Runs a source on its own (daemon) thread and hands its frames to a :class:`FrameQueue`.

    Live sources use ``put_newest`` (the oldest frame is dropped when the consumer lags); the others
    wait for room. The queue is finished when the source ends, after ``max_frames`` frames, or on
    :meth:`stop`. :attr:`ready` resolves once the source first opened, or with the error of a first
    open that is not retried.
    """

    def __init__(
        self,
        source: CaptureSource,
        queue: FrameQueue[CapturedFrame],
        loop: asyncio.AbstractEventLoop,
        *,
        stop: threading.Event | None = None,
        max_frames: int | None = None,
        report: TextIO | None = sys.stderr,
    ) -> None:
        self.source, self.queue, self.loop = source, queue, loop
        self.stop_event = stop if stop is not None else threading.Event()
        self.max_frames = max_frames
        self.report = report
        self.frames = 0
        """Frames delivered to the queue (dropped ones included)."""
        self.failures = 0
        """Failed opens and reads."""
        self.skipped = 0
        """Frames of a recording skipped because they could not be decoded or read (the source counts them)."""
        self._throttle = LogThrottle()
        self.ready: concurrent.futures.Future[None] = concurrent.futures.Future()
        self._thread = threading.Thread(target=self._run, name=f"ipt-capture-{source.name}", daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def stop(self) -> None:
        """Ask the thread to stop (it ends after the read in progress)."""
        self.stop_event.set()

    def join(self, timeout: float | None = None) -> bool:
        """Wait for the thread; whether it has ended."""
        if self._thread.ident is not None:
            self._thread.join(timeout)
        return not self._thread.is_alive()

    def _say(self, text: str) -> None:
        if self.report is not None:
            try:
                self.report.write(f"ipt-receiver: capture: {text}\n")
                self.report.flush()
            except (OSError, ValueError):
                pass

    def _run(self) -> None:
        delay = BACKOFF_FIRST_S
        opened = False
        if self.source.retry_open:
            self._resolve_ready()  # a camera that is not there yet is retried: the daemon runs meanwhile
        try:
            while not self.stop_event.is_set():
                if not opened:
                    try:
                        self.source.open()
                    except Exception as exc:
                        self.failures += 1
                        if not self.ready.done() and not self.source.retry_open:
                            self._resolve_ready(exc)
                            return
                        self._say(f"{self.source.name}: {_describe(exc)}; retrying in {delay:.1f} s")
                        self.stop_event.wait(delay)
                        delay = min(2 * delay, BACKOFF_MAX_S)
                        continue
                    opened = True
                    for note in getattr(self.source, "notes", ()):
                        self._say(note)
                    self._resolve_ready()
                try:
                    frame = self.source.read()
                except Exception as exc:
                    self.failures += 1
                    if getattr(self.source, "recording", False):
                        self._say(f"{self.source.name}: {_describe(exc)}; the recording ends here")
                        break
                    self._say(f"{self.source.name}: {_describe(exc)}; reopening in {delay:.1f} s")
                    self._close_source()
                    opened = False
                    self.stop_event.wait(delay)
                    delay = min(2 * delay, BACKOFF_MAX_S)
                    continue
                self._report_skipped()
                if frame is None:
                    end_note: Callable[[], str | None] | None = getattr(self.source, "end_note", None)
                    if end_note is not None and (note := end_note()) is not None:
                        self._say(note)
                    break  # the end of a recording
                delay = BACKOFF_FIRST_S
                if self.stop_event.is_set() or not self._deliver(frame):
                    break
                self.frames += 1
                if self.max_frames is not None and self.frames >= self.max_frames:
                    break
        finally:
            self._close_source()
            self._resolve_ready()
            self._call(self.queue.finish)

    def _report_skipped(self) -> None:
        """Count the frames the source skipped since the last read, and say why (a few lines, then a count)."""
        skipped = int(getattr(self.source, "skipped", 0))
        if skipped > self.skipped:
            self.skipped = skipped
            why = getattr(self.source, "last_skipped", None) or "a frame cannot be read"
            if (line := self._throttle.line("skipped", f"{why}; skipped", time.monotonic())) is not None:
                self._say(line)

    def _resolve_ready(self, exc: BaseException | None = None) -> None:
        if self.ready.done():
            return
        try:
            if exc is None:
                self.ready.set_result(None)
            else:
                self.ready.set_exception(exc)
        except concurrent.futures.InvalidStateError:  # cancelled meanwhile: nobody waits for it
            pass

    def _close_source(self) -> None:
        try:
            self.source.close()
        except Exception as exc:
            self._say(f"{self.source.name}: closing failed: {_describe(exc)}")

    def _call(self, fn: Callable[[], object]) -> bool:
        try:
            self.loop.call_soon_threadsafe(fn)
        except RuntimeError:  # the loop is closed: nobody is listening any more
            return False
        return True

    def _deliver(self, frame: CapturedFrame) -> bool:
        if self.source.live:
            return self._call(lambda: self.queue.put_newest(frame))
        try:
            fut = asyncio.run_coroutine_threadsafe(self.queue.put(frame), self.loop)
        except RuntimeError:
            return False
        while True:
            try:
                return fut.result(timeout=0.1)
            except TimeoutError:
                if self.stop_event.is_set():
                    fut.cancel()
                    return False
            except concurrent.futures.CancelledError:
                return False


def _describe(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, IptError) else f"{type(exc).__name__}: {exc}"
