"""MAVLink to the flight controller: ODOMETRY (and optionally VISION_POSITION_ESTIMATE), HEARTBEAT, TIMESYNC.

Two layers:

- **The maths, pure** (:mod:`ipt.receiver.outputs.mavlink.frames`, re-exported here: :func:`body_pose_ned`,
  :func:`odometry_sample`, :func:`body_velocity_frd`, :class:`OdometryTracker`, :class:`RateLimiter`,
  :class:`FixMonitor`): a camera pose in the arena in, the vehicle body's pose in the autopilot's frames
  out, with its covariance, a quality, a reset counter and the body's velocity fitted over the recent poses
  (:mod:`ipt.receiver.core.kinematics`). No clock, no socket.
- **The session, sans-IO** (:mod:`ipt.receiver.outputs.mavlink.session`): what to send and when, from times passed in
  (``poll(now)``, ``next_deadline()``, ``on_result``, ``receive``); messages out as bytes.
- **The connection, thin** (:class:`MavlinkOutput`, here): it runs the session on the event loop and
  counts what was sent; pymavlink encodes and decodes; the bytes go
  through an asyncio UDP endpoint (``udpout:HOST:PORT``) or a raw serial port (``serial:DEVICE:BAUD``),
  opened with termios by :mod:`ipt.receiver.outputs.mavlink.links`, so every read and write is non-blocking on the
  daemon's event loop. A link that cannot be opened (port missing or busy, name not resolving) is
  reported in one line and retried with backoff;
  the daemon keeps localising meanwhile.

Frames (README "Frames and units"): the arena is ENU; MAVLink wants a local NED-like frame and an FRD body.
The arena's y (its "north") becomes x, its x becomes y, and up becomes down::

    x_ned = y_enu,  y_ned = x_enu,  z_ned = -z_enu

This frame's heading is the arena's, not magnetic north, which is what ``MAV_FRAME_LOCAL_FRD`` says.
The body is FRD (x forward, y right, z down); the camera's mounting on it is ``r_frd_cam`` (camera
optical axes in body axes) and ``camera_position_frd_m`` (the optical centre from the body origin).

Time: ``time_usec`` is the frame's capture time on this computer's monotonic clock (for a recording or the
simulator, its frame times shifted so that the first frame is at its read instant), the same clock
TIMESYNC answers with, so the autopilot can map one to its own.

Rate: at most ``max_rate_hz`` ODOMETRY per second of capture time (:class:`RateLimiter`), each the newest
pose; the velocity fit still sees every pose.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TextIO

from ipt.config.receiver import LinkSpec, parse_link
from ipt.receiver.outputs.mavlink.frames import (
    R_FRD_CAM_DOWNWARD,
    R_NED_ENU,
    FixMonitor,
    MavlinkError,
    Mounting,
    OdometrySample,
    OdometryTracker,
    RateLimiter,
    body_pose_ned,
    body_velocity_frd,
    euler_jacobian,
    euler_rpy_rad,
    mounting_from,
    odometry_sample,
    pose_covariance_ned,
    quality_percent,
    upper_triangle_21,
)
from ipt.receiver.outputs.mavlink.links import SerialPort, UdpLink, load_dialect
from ipt.receiver.outputs.mavlink.session import (
    HEARTBEAT_PERIOD_S,
    STATUSTEXT_PREFIX,
    WATCH_PERIOD_S,
    MavlinkSession,
    MavlinkStats,
    Outgoing,
)

if TYPE_CHECKING:
    from ipt.config.receiver import MavlinkConfig
    from ipt.receiver.capture import CapturedFrame
    from ipt.receiver.core.pipeline import FrameResult

BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 5.0
DEFAULT_DIALECT = "common"


class MavlinkOutput:
    """The daemon's MAVLink output: the link and the event loop around a :class:`MavlinkSession`.
    :meth:`open` never fails for the link: it is (re)opened in the background; :meth:`on_result` takes
    every frame's result, in capture order, on the event loop."""

    def __init__(
        self,
        cfg: MavlinkConfig,
        *,
        report: TextIO | None,
        prog: str = "ipt-receiver",
        clock_s: Callable[[], float] = time.monotonic,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        if cfg.link is None:
            raise MavlinkError("the MAVLink output needs a link (udpout:HOST:PORT or serial:DEVICE:BAUD)")
        self.cfg = cfg
        try:
            self.spec = parse_link(cfg.link)
        except ValueError as exc:
            raise MavlinkError(str(exc)) from None
        self.dialect = load_dialect(cfg.dialect)
        self.report, self.prog = report, prog
        self.session = MavlinkSession(cfg, self.dialect, str(self.spec), self._say)
        self._clock_s, self._clock_ns = clock_s, clock_ns
        self._link: UdpLink | SerialPort | None = None
        self._broken = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self._last_link_error: str | None = None

    # What the session holds, where the daemon and the tests look for it.
    @property
    def stats(self) -> MavlinkStats:
        return self.session.stats

    @property
    def fix(self) -> FixMonitor:
        return self.session.fix

    @property
    def mav(self) -> Any:
        return self.session.mav

    def _odometry_message(self, s: OdometrySample) -> Any:
        return self.session._odometry_message(s)

    # -- reporting -----------------------------------------------------------------------------------

    def _say(self, text: str) -> None:
        if self.report is None:
            return
        try:
            self.report.write(f"{self.prog}: mavlink: {text}\n")
            self.report.flush()
        except (OSError, ValueError):
            pass

    def summary(self) -> str:
        """One line for the end of the run."""
        return self.session.summary()

    def say_summary(self) -> None:
        """Print :meth:`summary` on the report stream."""
        self._say(self.summary())

    # -- lifecycle -----------------------------------------------------------------------------------

    async def open(self) -> None:
        """Start the link keeper and the session's timer (the link itself may come up later)."""
        loop = asyncio.get_running_loop()
        self.session.start(self._clock_s())
        self._tasks = [
            loop.create_task(self._keep_link(), name="ipt-mavlink-link"),
            loop.create_task(self._timer(), name="ipt-mavlink-timer"),
        ]

    async def close(self) -> None:
        """Say goodbye (STATUSTEXT), stop the tasks and close the link."""
        self._deliver(self.session.goodbye())
        for task in self._tasks:
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        self._close_link()

    def _close_link(self) -> None:
        link, self._link = self._link, None
        self.session.link_closed()
        if link is not None:
            link.close()

    async def _keep_link(self) -> None:
        loop = asyncio.get_running_loop()
        delay = BACKOFF_FIRST_S
        while True:
            self._broken.clear()
            link: UdpLink | SerialPort
            try:
                if self.spec.kind == "udpout":
                    link = UdpLink(self.spec, self._on_bytes, self._on_send_error)
                    await link.open(loop)
                else:
                    link = SerialPort(self.spec, self._on_bytes, self._on_broken)
                    link.open(loop)
            except MavlinkError as exc:
                text = str(exc)
                if text != self._last_link_error:  # one line per distinct problem, not one per retry
                    self._say(f"{text}; retrying every {BACKOFF_MAX_S:.0f} s at most, localisation goes on")
                    self._last_link_error = text
                await asyncio.sleep(delay)
                delay = min(2 * delay, BACKOFF_MAX_S)
                continue
            delay = BACKOFF_FIRST_S
            self._link = link
            self._say(f"{self.spec}: link open (system {self.cfg.system_id}, component {self.cfg.component_id})")
            self._last_link_error = None
            self._deliver(self.session.link_opened(self._clock_s()))
            await self._broken.wait()
            self._close_link()

    async def _timer(self) -> None:
        """Poll the session at its deadlines (and whenever the injected clock may have moved: at most
        :data:`~ipt.receiver.outputs.mavlink.session.WATCH_PERIOD_S` of real time apart)."""
        while True:
            wait = min(max(0.0, self.session.next_deadline() - self._clock_s()), WATCH_PERIOD_S)
            await asyncio.sleep(wait)
            self._deliver(self.session.poll(self._clock_s()))

    def _on_broken(self, why: str) -> None:
        if not self._broken.is_set():
            self._say(f"{why}; reopening")
            self._broken.set()

    def _on_send_error(self, exc: BaseException) -> None:
        self.stats.send_errors += 1

    def _on_bytes(self, data: bytes) -> None:
        self._deliver(self.session.receive(data, self._clock_s(), self._clock_ns()))

    def _deliver(self, messages: list[Outgoing]) -> None:
        """Send what the session made; count what went (and the send errors)."""
        stats = self.session.stats
        for m in messages:
            link = self._link
            if link is None:
                return
            if link.send(m.data):
                for name in m.counts:
                    setattr(stats, name, getattr(stats, name) + 1)
            else:
                stats.send_errors += 1

    # -- poses ---------------------------------------------------------------------------------------

    def time_usec(self, frame: CapturedFrame) -> int:
        """The frame's capture time on the monotonic clock, in µs (see the module doc)."""
        return self.session.time_usec(frame)

    def on_result(self, frame: CapturedFrame, result: FrameResult) -> OdometrySample | None:
        """Send the pose of one frame (if it has one); returns what was sent."""
        sample, messages = self.session.on_result(frame, result, self._clock_s())
        self._deliver(messages)
        return sample


__all__ = [
    "HEARTBEAT_PERIOD_S",
    "R_FRD_CAM_DOWNWARD",
    "R_NED_ENU",
    "STATUSTEXT_PREFIX",
    "WATCH_PERIOD_S",
    "FixMonitor",
    "LinkSpec",
    "MavlinkError",
    "MavlinkOutput",
    "MavlinkSession",
    "MavlinkStats",
    "Mounting",
    "OdometrySample",
    "OdometryTracker",
    "RateLimiter",
    "body_pose_ned",
    "body_velocity_frd",
    "euler_jacobian",
    "euler_rpy_rad",
    "load_dialect",
    "mounting_from",
    "odometry_sample",
    "parse_link",
    "pose_covariance_ned",
    "quality_percent",
    "upper_triangle_21",
]
