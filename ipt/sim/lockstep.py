"""The lock-step machinery of the closed-loop demo (:mod:`ipt.sim.demo`): the simulated clock, the
projector that makes the sender's frames on demand, the camera that renders what it shows, and the
hand-over between them and the receiver (see the demo's module doc for the order of things).
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Hashable
from typing import Final

import numpy as np
import numpy.typing as npt

from ipt.config.models import ArenaConfig
from ipt.errors import IptError
from ipt.protocol import PacketFilter, PosePacket
from ipt.receiver.capture import CapturedFrame, CaptureError, capture_time_us
from ipt.sender.content import ContentSource
from ipt.sim.arena import SimulatedArena
from ipt.sim.config import SimConfig
from ipt.sim.flight import FlightState
from ipt.tagmap import TagMap

U8 = npt.NDArray[np.uint8]

KEEP_FRAMES: Final = 8
"""Output frames the in-memory projector keeps (an exposure needs the newest one or two)."""
FRAME_TIMEOUT_S: Final = 120.0
"""Longest wait for the sender to make one projector frame (it takes well under a second)."""
RESULT_TIMEOUT_S: Final = 120.0
"""Longest wait for the receiver to finish one camera frame."""
PACKET_TIMEOUT_S: Final = 2.0
"""Longest wait for the sender to take in a pose packet sent over loopback; later it counts as lost."""


class DemoError(IptError):
    """The closed loop cannot run as asked, or one of its parts failed."""


class _Stopped(Exception):
    """The run is being stopped: the camera gives up the frame it was making."""


# --- the simulated clock -----------------------------------------------------------------------------


class SimClock:
    """Simulated seconds: set by the camera before each frame, read by the sender's overlay."""

    def __init__(self) -> None:
        self._t = 0.0

    def now(self) -> float:
        return self._t

    def set(self, t_s: float) -> None:
        self._t = t_s


# --- the projector: the sender's sink, and the gate on its content -----------------------------------


class LockstepProjector:
    """The sender's output frames, made when the simulated camera first needs them.

    As a sink (:class:`ipt.sender.display.Sink`) it keeps the newest ``keep`` output frames by index;
    not paced (the camera sets the pace), not threaded (``show`` only stores the frame). :meth:`gated`
    wraps the sender's content so that its render thread takes input frame ``i`` only once
    :meth:`frame` asked for an output frame of it. :meth:`stop` opens the gate for good and makes every
    wait in :meth:`frame` give up.
    """

    name = "memory"
    paced = False
    threaded = False
    close_timeout_s = 0.1

    def __init__(self, per_input: int, keep: int = KEEP_FRAMES, frame_timeout_s: float = FRAME_TIMEOUT_S) -> None:
        if per_input < 1 or keep < 2:
            raise ValueError(f"need per_input >= 1 and keep >= 2, got {per_input}, {keep}")
        self.per_input = per_input
        self.keep = keep
        self.frame_timeout_s = frame_timeout_s
        self.frames_shown = 0
        self.asked = -1
        """Newest output frame the camera asked for."""
        self._frames: OrderedDict[int, U8] = OrderedDict()
        self._newest = -1
        self._allowed_input = -1
        self._held_for: int | None = None
        self._stopped = False
        self._cond = threading.Condition()

    # -- the sender's side --

    def show(self, frame_rgb: U8, index: int) -> None:
        with self._cond:
            self._frames[index] = frame_rgb
            self._newest = max(self._newest, index)
            while len(self._frames) > self.keep:
                self._frames.popitem(last=False)
            self.frames_shown += 1
            self._cond.notify_all()

    def close(self) -> None:
        self.stop()

    def abort(self) -> None:
        self.stop()

    @property
    def quit_requested(self) -> bool:
        return False

    def gated(self, scene: ContentSource) -> ContentSource:
        """``scene`` as the sender must see it: input frame ``i`` only once the camera needs it."""
        return _GatedScene(scene, self)

    def wait_input(self, input_index: int) -> None:
        """Block (the sender's render thread) until input frame ``input_index`` may be made."""
        with self._cond:
            while not self._stopped and self._allowed_input < input_index:
                self._held_for = input_index
                self._cond.wait()
            self._held_for = None

    @property
    def held_for(self) -> int | None:
        """The input frame the sender waits at the gate for (``None``: it is not waiting there)."""
        with self._cond:
            return self._held_for

    # -- the camera's side --

    def frame(self, index: int) -> U8:
        """Output frame ``index`` as the sender showed it; asks the sender for it and waits if need be."""
        deadline = time.monotonic() + self.frame_timeout_s
        with self._cond:
            self.asked = max(self.asked, index)
            if index // self.per_input > self._allowed_input:
                self._allowed_input = index // self.per_input
                self._cond.notify_all()
            while True:
                found = self._frames.get(index)
                if found is not None:
                    return found
                if self._stopped:
                    raise _Stopped
                if index <= self._newest:
                    raise DemoError(f"projector frame {index} is gone: only the newest {self.keep} are kept")
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DemoError(
                        f"the sender did not make projector frame {index} within {self.frame_timeout_s:g} s"
                    )
                self._cond.wait(left)

    def shown(self, index: int) -> U8 | None:
        """Output frame ``index`` if it is (still) kept; never waits."""
        with self._cond:
            return self._frames.get(index)

    @property
    def newest(self) -> int:
        """Index of the newest frame shown (-1 before the first)."""
        with self._cond:
            return self._newest

    def stop(self) -> None:
        """Open the gate for good (the sender is stopping) and end every wait for a frame."""
        with self._cond:
            self._stopped = True
            self._cond.notify_all()


class _GatedScene:
    """The sender's content, handed out only as fast as the simulated camera asks for it."""

    def __init__(self, scene: ContentSource, projector: LockstepProjector) -> None:
        self._scene, self._projector = scene, projector

    def frame(self, index: int, rate_hz: float) -> U8:
        self._projector.wait_input(index)
        return self._scene.frame(index, rate_hz)


# --- the drone's camera --------------------------------------------------------------------------------


class _NoContent:
    def frame(self, index: int, rate_hz: float) -> U8:
        raise DemoError("the closed loop's floor shows the sender's output, not content of its own")


class ClosedLoopArena(SimulatedArena):
    """The simulated arena whose floor shows the sender's actual output frames."""

    def __init__(
        self, arena: ArenaConfig, sim: SimConfig, projector: LockstepProjector, tag_map: TagMap | None = None
    ) -> None:
        super().__init__(arena, sim, _NoContent(), tag_map)
        self.projector = projector

    def projector_crop(self, index: int, region: tuple[int, int, int, int]) -> U8:
        """Region (x0, y0, x1, y1) of the sender's output frame ``index``, exactly as it was shown."""
        x0, y0, x1, y1 = region
        return np.ascontiguousarray(self.projector.frame(index)[y0:y1, x0:x1])


class Lockstep:
    """Holds the camera back until the receiver has finished the previous frame and the sender has
    taken in its packet. Thread-safe: the event loop reports, the capture thread waits."""

    def __init__(self, result_timeout_s: float = RESULT_TIMEOUT_S, packet_timeout_s: float = PACKET_TIMEOUT_S) -> None:
        self.result_timeout_s = result_timeout_s
        self.packet_timeout_s = packet_timeout_s
        self.finished = -1
        """Newest camera frame the receiver has finished."""
        self.sent = 0
        """Datagrams the receiver sent."""
        self.seen = 0
        """Datagrams the sender's listener took in (accepted or not)."""
        self.lost = 0
        """Datagrams not taken in within ``packet_timeout_s``."""
        self._stopped = False
        self._cond = threading.Condition()

    def frame_done(self, index: int, sent: int) -> None:
        with self._cond:
            self.finished = max(self.finished, index)
            self.sent += sent
            self._cond.notify_all()

    def packet_seen(self) -> None:
        with self._cond:
            self.seen += 1
            self._cond.notify_all()

    def stop(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()

    def wait(self, index: int) -> None:
        """Until frame ``index`` is finished and its packets are in; raises :class:`_Stopped` on stop."""
        with self._cond:
            deadline = time.monotonic() + self.result_timeout_s
            while self.finished < index:
                if self._stopped:
                    raise _Stopped
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DemoError(f"the receiver did not finish camera frame {index} in {self.result_timeout_s:g} s")
                self._cond.wait(left)
            deadline = time.monotonic() + self.packet_timeout_s
            while self.seen + self.lost < self.sent:
                if self._stopped:
                    raise _Stopped
                left = deadline - time.monotonic()
                if left <= 0:
                    self.lost = self.sent - self.seen
                    break
                self._cond.wait(left)


class _CountingFilter(PacketFilter):
    """The sender's usual packet filter, telling the lockstep about every datagram it judged."""

    def __init__(self, lockstep: Lockstep) -> None:
        super().__init__(resync_after_s=10.0)
        self._lockstep = lockstep

    def accept(
        self, data: bytes, now: float | None = None, source: Hashable | None = None, peer: Hashable | None = None
    ) -> PosePacket | None:
        try:
            return super().accept(data, now, source, peer)
        finally:
            self._lockstep.packet_seen()


class ClosedLoopCapture:
    """The receiver daemon's capture source: camera frames of the closed loop, ``frames`` of them.

    Frame ``k`` is rendered once frame ``k - 1`` went all the way round (see the module doc); its
    capture time is ``k / fps``. The ground truth of each frame rendered is kept in :attr:`truth` until
    the demo takes it. A failure ends the stream and is kept in :attr:`failure`.
    """

    live = False
    retry_open = False

    def __init__(
        self,
        arena: ArenaConfig,
        sim: SimConfig,
        projector: LockstepProjector,
        lockstep: Lockstep,
        clock: SimClock,
        frames: int,
        tag_map: TagMap | None = None,
    ) -> None:
        self.name = "sim (closed loop)"
        self.arena, self.sim, self.projector, self.lockstep, self.clock = arena, sim, projector, lockstep, clock
        self.frames = frames
        self.fps = sim.camera.fps
        self.tag_map = tag_map
        self.truth: dict[int, FlightState] = {}
        self.failure: str | None = None
        self.started_s: float | None = None
        """``time.monotonic()`` when the first frame was started (the set-up is done)."""
        self.world: ClosedLoopArena | None = None
        self._next = 0

    def open(self) -> None:
        if self.world is None:
            self.world = ClosedLoopArena(self.arena, self.sim, self.projector, self.tag_map)

    def read(self) -> CapturedFrame | None:
        world = self.world
        if world is None:
            raise CaptureError("sim (closed loop): read before open")
        k = self._next
        if k >= self.frames or self.failure is not None:
            return None
        if self.started_s is None:
            self.started_s = time.monotonic()
        try:
            if k > 0:
                self.lockstep.wait(k - 1)
            self.clock.set(k / self.fps)
            frame = world.render(k)
        except _Stopped:
            return None
        except DemoError as exc:
            self.failure = str(exc)
            return None
        self.truth[k] = frame.truth
        self._next = k + 1
        return CapturedFrame(k, capture_time_us(k, self.fps), frame.image_rgb, time.monotonic())

    def close(self) -> None:
        """Nothing to release."""


# --- what the run gave ---------------------------------------------------------------------------------
