"""Where the sender's output frames go: a window on a projector, a video file, or nowhere.

Every sink has ``show(frame_rgb, index)`` (one H×W×3 uint8 RGB output frame; ``index`` is the output
frame number j) and ``close()``, and says whether the sender should pace it at the output rate
(``paced``) and whether ``show`` may block long enough to be run off the event loop (``threaded``).
A sink that says ``retries = True`` may fail to show a frame and work again later (a display that
comes back): the sender counts the failure and goes on with the next frame. A sink without it (a file,
which cannot skip a frame) ends the run when it fails.

A sink may also say ``borrows = True``: it is done with a frame when ``show`` returns (it copied,
encoded or discarded it), so the sender may write later frames into the same array. Without it, every
input frame gets new arrays (a sink that keeps frames, such as the closed-loop demo's, needs that).

- :class:`NullSink` discards the frames (benchmarks, dry runs); paced.
- :class:`FileSink` writes exactly the frames given to a lossless FFV1 file (:class:`ipt.videoio.FfvWriter`);
  not paced: the sender renders as fast as it can.
- :class:`WindowSink` shows them full screen on one display with pygame-ce, vsync on; paced. pygame-ce
  is an optional dependency (``pip install 'ipt[display]'``), imported only when a window sink is made.
  All its SDL calls happen on the thread that calls ``show`` and ``close`` (the sender uses one thread).
  It times every flip (:class:`PresentClock`): a frame that stayed up for more than one refresh of the
  display put the same phase on the screen twice in a row, and two flips within one refresh mean a
  frame was never seen, which also leaves two frames of the same phase next to each other; both are
  counted (:meth:`WindowSink.pacing`) and the sender prints them in its statistics line.
"""

from __future__ import annotations

import math
import os
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final, Protocol

import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.videoio import FfvWriter

U8 = npt.NDArray[np.uint8]

SINK_NAMES: Final = ("window", "file", "null")


class DisplayError(IptError):
    """A sink cannot be opened or cannot take a frame."""


class Sink(Protocol):
    """Destination of output frames."""

    name: str
    paced: bool
    """The sender should hand over frame j at its due time start + j / f_o (else: as fast as possible)."""
    threaded: bool
    """``show`` and ``close`` may block: call them from a worker thread, not the event loop."""
    close_timeout_s: float
    """How long the sender waits for ``close`` when stopping (a file must be completed)."""

    def show(self, frame_rgb: U8, index: int) -> None:
        """Output frame ``index``."""
        ...

    def close(self) -> None:
        """Finish: everything shown so far is kept (a file is completed). Calling it again does nothing."""
        ...

    def abort(self) -> None:
        """Give up after an error: release everything, keep nothing half-done."""
        ...

    @property
    def quit_requested(self) -> bool:
        """The user asked to stop through the sink itself (e.g. closed the window)."""
        ...


class NullSink:
    """Discards every frame; counts them."""

    name = "null"
    retries = True
    paced = True
    threaded = False
    borrows = True
    close_timeout_s = 0.1

    def __init__(self) -> None:
        self.frames_shown = 0
        self.last_index: int | None = None

    def show(self, frame_rgb: U8, index: int) -> None:
        self.frames_shown += 1
        self.last_index = index

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass

    @property
    def quit_requested(self) -> bool:
        return False


class FileSink:
    """Writes exactly the frames given, in order, to a lossless FFV1/Matroska file at ``fps``.

    With ``width`` and ``height`` the file is started at once (so that a bad path fails before any
    rendering); otherwise at the first frame. The file appears at ``path`` only on :meth:`close`.
    """

    name = "file"
    retries = False
    paced = False
    threaded = True
    borrows = True
    close_timeout_s = 30.0

    def __init__(self, path: str | Path, fps: float, width: int | None = None, height: int | None = None) -> None:
        self.path = Path(path)
        self.fps = fps
        self._writer: FfvWriter | None = None
        if width is not None and height is not None:
            self._writer = FfvWriter(self.path, width, height, fps)

    @property
    def frames_written(self) -> int:
        return 0 if self._writer is None else self._writer.frames_written

    def show(self, frame_rgb: U8, index: int) -> None:
        if self._writer is None:
            h, w = frame_rgb.shape[:2]
            self._writer = FfvWriter(self.path, w, h, self.fps)
        self._writer.write(frame_rgb)

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()

    def abort(self) -> None:
        if self._writer is not None:
            self._writer.abort()

    @property
    def quit_requested(self) -> bool:
        return False


_NEEDS_PYGAME: Final = "the window sink needs pygame-ce: pip install 'ipt[display]'"


class PresentClock:
    """When each frame reached the screen, and what that says about the phases on it.

    ``add(t)`` takes the time a flip returned (with vsync: the refresh that shows the frame). The interval
    since the previous flip, in refreshes of ``period_s`` rounded, is 1 when all is well; ``n`` >= 2 means
    the previous frame stayed up ``n - 1`` refreshes too long (a repeated phase on the screen: a camera
    pairing frames one refresh apart sees no flicker there); 0 means the two flips fell in one refresh,
    so the earlier frame was never shown and the frames before and after it, of the same phase, are
    next to each other on the screen.
    """

    BIN_MS: Final = 0.1
    BINS: Final = 2000

    def __init__(self, period_s: float) -> None:
        if not (math.isfinite(period_s) and period_s > 0):
            raise DisplayError(f"the refresh period must be a positive number of seconds, got {period_s!r}")
        self.period_s = period_s
        self.presents = 0
        """Flips timed."""
        self.repeated = 0
        """Refreshes that showed the previous frame again (a phase shown twice in a row)."""
        self.dropped = 0
        """Frames flipped within the refresh of the next one: never on the screen."""
        self.max_interval_ms = 0.0
        self._last: float | None = None
        self._counts = [0] * (self.BINS + 1)
        self._intervals = 0

    def add(self, t_s: float) -> None:
        """A frame reached the screen at ``t_s`` (seconds, monotonic)."""
        self.presents += 1
        last, self._last = self._last, t_s
        if last is None:
            return
        interval = t_s - last
        refreshes = round(interval / self.period_s)
        if refreshes >= 2:
            self.repeated += refreshes - 1
        elif refreshes <= 0:
            self.dropped += 1
        ms = interval * 1e3
        self._counts[min(self.BINS, max(0, int(ms / self.BIN_MS)))] += 1
        self._intervals += 1
        self.max_interval_ms = max(self.max_interval_ms, ms)

    def interval_percentile_ms(self, p: float) -> float:
        """The ``p``-th percentile of the intervals between flips (bin centre, ms), NaN before two flips."""
        if self._intervals == 0:
            return math.nan
        rank, seen = max(1, math.ceil(p / 100.0 * self._intervals)), 0
        for k, n in enumerate(self._counts):
            seen += n
            if seen >= rank:
                return self.max_interval_ms if k >= self.BINS else min(self.max_interval_ms, (k + 0.5) * self.BIN_MS)
        return self.max_interval_ms

    def summary(self) -> dict[str, Any]:
        """The counts and the intervals' p50/p99/max, as plain values."""
        return {
            "refresh_hz": round(1.0 / self.period_s, 3),
            "presents": self.presents,
            "repeated_vsyncs": self.repeated,
            "dropped_frames": self.dropped,
            "present_interval_p50_ms": round(self.interval_percentile_ms(50), 2),
            "present_interval_p99_ms": round(self.interval_percentile_ms(99), 2),
            "present_interval_max_ms": round(self.max_interval_ms, 2),
        }


class WindowSink:
    """Full-screen (or windowed) output on display ``display_index`` with pygame-ce, vsync on.

    The window opens at the first frame, at that frame's size; in full screen SDL scales it to the
    display (1:1 when the display runs at the projector's resolution). Closing the window or pressing
    Esc or Q sets :attr:`quit_requested`. ``rate_hz`` is the rate the sender paces frames at: the refresh
    period the flips are timed against (:class:`PresentClock`) is the display's own where SDL reports it,
    with a warning when the two differ. ``clock`` times the flips (``time.monotonic``).
    """

    name = "window"
    retries = True  # a lost window is opened again at the next frame
    paced = True
    threaded = True
    borrows = True
    close_timeout_s = 0.5

    def __init__(
        self,
        display_index: int = 0,
        fullscreen: bool = True,
        title: str = "ipt-sender",
        rate_hz: float = 60.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if display_index < 0:
            raise DisplayError(f"display index must be >= 0, got {display_index}")
        os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
        try:
            import pygame
        except ImportError:
            raise DisplayError(_NEEDS_PYGAME) from None
        self._pg: Any = pygame
        self.display_index = display_index
        self.fullscreen = fullscreen
        self.title = title
        self.vsync = False
        self._screen: Any = None
        self._size: tuple[int, int] | None = None
        self._quit = False
        self._closed = False
        self.rate_hz = rate_hz
        self.clock = clock
        self.presents = PresentClock(1.0 / rate_hz)

    def pacing(self) -> dict[str, Any]:
        """What the flips showed (see :class:`PresentClock`)."""
        return self.presents.summary()

    def _refresh_hz(self) -> float | None:
        """The display's refresh rate as SDL reports it (None if it does not)."""
        try:
            hz = float(self._pg.display.get_current_refresh_rate())
        except (AttributeError, self._pg.error):
            return None
        return hz if math.isfinite(hz) and hz > 0 else None

    def _open(self, width: int, height: int) -> None:
        pg = self._pg
        try:
            pg.display.init()
            count = pg.display.get_num_displays()
            if self.display_index >= count:
                raise DisplayError(f"display {self.display_index} does not exist ({count} found)")
            pg.display.set_caption(self.title)
            flags = pg.SCALED | (pg.FULLSCREEN if self.fullscreen else 0)
            # SDL warns through Python warnings (e.g. "no fast renderer available" without a GPU): report them.
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                try:
                    self._screen = pg.display.set_mode((width, height), flags, display=self.display_index, vsync=1)
                    self.vsync = True
                except pg.error as exc:
                    print(f"ipt-sender: vsync is not available ({exc}); showing frames without it", file=sys.stderr)
                    self._screen = pg.display.set_mode((width, height), flags, display=self.display_index)
            for w in caught:
                print(f"ipt-sender: window: {w.message}", file=sys.stderr)
            if self.fullscreen:
                pg.mouse.set_visible(False)
        except pg.error as exc:
            raise DisplayError(f"cannot open a window on display {self.display_index}: {exc}") from None
        self._size = (width, height)
        hz = self._refresh_hz()
        # SDL reports whole hertz (59 or 60 for a 59.94 Hz display): within 2 % the frames' own rate is the
        # better figure; beyond, the display does not run at the projector rate and the flips say so.
        if hz is not None and abs(hz - self.rate_hz) > 0.02 * self.rate_hz and self.presents.presents == 0:
            self.presents = PresentClock(1.0 / hz)
            print(
                f"ipt-sender: warning: display {self.display_index} refreshes at {hz:g} Hz, frames come at "
                f"{self.rate_hz:g} Hz (the arena's projector.rate_hz): frames will be repeated or never shown, "
                "each counted in the statistics",
                file=sys.stderr,
            )

    def show(self, frame_rgb: U8, index: int) -> None:
        if self._closed:
            raise DisplayError("show() after the window was closed")
        h, w = frame_rgb.shape[:2]
        if self._size is None:
            self._open(w, h)
        elif self._size != (w, h):
            raise DisplayError(f"frame is {w}x{h}, the window is {self._size[0]}x{self._size[1]}")
        pg = self._pg
        for event in pg.event.get():
            if event.type == pg.QUIT or (event.type == pg.KEYDOWN and event.key in (pg.K_ESCAPE, pg.K_q)):
                self._quit = True
        frame = np.ascontiguousarray(frame_rgb)
        try:
            self._screen.blit(pg.image.frombuffer(frame, (w, h), "RGB"), (0, 0))
            pg.display.flip()  # with vsync: waits for the next refresh
            self.presents.add(self.clock())
        except pg.error as exc:  # the display went away: open the window again at the next frame
            self._size = self._screen = None
            pg.display.quit()
            raise DisplayError(f"the window on display {self.display_index} was lost: {exc}") from None

    def pixel(self, x: int, y: int) -> tuple[int, int, int]:
        """The RGB colour of the window's pixel (x, y), as last shown (for tests)."""
        if self._screen is None:
            raise DisplayError("nothing shown yet")
        c = self._screen.get_at((x, y))
        return int(c.r), int(c.g), int(c.b)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._size is not None:
            self._pg.display.quit()

    def abort(self) -> None:
        self.close()

    @property
    def quit_requested(self) -> bool:
        return self._quit


def make_sink(
    name: str,
    *,
    output: str | Path | None = None,
    fps: float = 60.0,
    width: int | None = None,
    height: int | None = None,
    display_index: int = 0,
    fullscreen: bool = True,
) -> NullSink | FileSink | WindowSink:
    """The sink called ``name`` (one of :data:`SINK_NAMES`)."""
    if name == "null":
        return NullSink()
    if name == "file":
        if output is None:
            raise DisplayError("the file sink needs an output path")
        return FileSink(output, fps, width, height)
    if name == "window":
        return WindowSink(display_index, fullscreen, rate_hz=fps)
    raise DisplayError(f"unknown sink {name!r}; choose one of {', '.join(SINK_NAMES)}")
