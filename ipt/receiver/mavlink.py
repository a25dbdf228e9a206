"""MAVLink to the flight controller: ODOMETRY (and optionally VISION_POSITION_ESTIMATE), HEARTBEAT, TIMESYNC.

Two layers:

- **The maths, pure** (:mod:`ipt.receiver.mavframes`, re-exported here: :func:`body_pose_ned`,
  :func:`odometry_sample`, :func:`body_velocity_frd`, :class:`OdometryTracker`, :class:`RateLimiter`,
  :class:`FixMonitor`): a camera pose in the arena in, the vehicle body's pose in the autopilot's frames
  out, with its covariance, a quality, a reset counter and the body's velocity fitted over the recent poses
  (:mod:`ipt.receiver.kinematics`). No clock, no socket.
- **The connection, thin** (:class:`MavlinkOutput`, here): pymavlink encodes and decodes; the bytes go
  through an asyncio UDP endpoint (``udpout:HOST:PORT``) or a raw serial port (``serial:DEVICE:BAUD``),
  opened with termios by :mod:`ipt.receiver.mavlinks`, so every read and write is non-blocking on the
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
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TextIO

import numpy as np

from ipt.config.receiver import LinkSpec, parse_link
from ipt.ratelimit import LogThrottle
from ipt.receiver.kinematics import VelocityFit
from ipt.receiver.mavframes import (
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
from ipt.receiver.mavlinks import SerialPort, UdpLink, load_dialect

if TYPE_CHECKING:
    from ipt.config.receiver import MavlinkConfig
    from ipt.receiver.capture import CapturedFrame
    from ipt.receiver.pipeline import FrameResult

HEARTBEAT_PERIOD_S = 1.0
WATCH_PERIOD_S = 0.1
"""How often the loss of fix and the autopilot's silence are checked."""
BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 5.0
STATUSTEXT_PREFIX = "IPT: "
DEFAULT_DIALECT = "common"


@dataclass
class MavlinkStats:
    """Counts of one run of the MAVLink output."""

    odometry: int = 0
    odometry_with_velocity: int = 0
    """ODOMETRY that carried a velocity (the fit had enough recent poses)."""
    held_back: int = 0
    """Poses not sent because they came sooner than 1/max_rate_hz after the last one sent."""
    vision_position: int = 0
    heartbeats: int = 0
    timesync_answered: int = 0
    statustexts: int = 0
    send_errors: int = 0
    resets: int = 0
    autopilot: str | None = None
    """Who answered, e.g. "system 1 component 1 (PX4)"; None if no autopilot HEARTBEAT was heard."""


_AUTOPILOT_NAMES = {3: "ArduPilot", 12: "PX4"}


class MavlinkOutput:
    """The daemon's MAVLink output. :meth:`open` never fails for the link: it is (re)opened in the
    background; :meth:`on_result` takes every frame's result, in capture order, on the event loop."""

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
        self.mav: Any = self.dialect.MAVLink(None, srcSystem=cfg.system_id, srcComponent=cfg.component_id)
        self.mav.robust_parsing = True
        self._parser: Any = self.dialect.MAVLink(None)
        self._parser.robust_parsing = True
        self.tracker = OdometryTracker(
            mounting_from(cfg.r_frd_cam, cfg.camera_position_frd_m),
            cfg.reset_jump_m,
            cfg.zero_quality_std_m,
            cfg.min_attitude_std_rad,
        )
        self.fix = FixMonitor(cfg.fix_timeout_s)
        self.rate = RateLimiter(cfg.max_rate_hz)
        self.velocity = VelocityFit()
        self.stats = MavlinkStats()
        self.report, self.prog = report, prog
        self._clock_s, self._clock_ns = clock_s, clock_ns
        self._time_offset_us: int | None = None
        self._link: UdpLink | SerialPort | None = None
        self._broken = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self._started_sent = False
        self._last_autopilot_s: float | None = None
        self._link_up_s: float | None = None
        self._silence_reported = False
        self._last_link_error: str | None = None
        # A peer that changes its system id at every HEARTBEAT would otherwise print a line for each.
        self._heard_log = LogThrottle(period_s=10.0, burst=3)

    # -- reporting -----------------------------------------------------------------------------------

    def _say(self, text: str) -> None:
        if self.report is None:
            return
        try:
            self.report.write(f"{self.prog}: mavlink: {text}\n")
            self.report.flush()
        except (OSError, ValueError):
            pass

    # -- lifecycle -----------------------------------------------------------------------------------

    async def open(self) -> None:
        """Start the link keeper, the heartbeat and the watchdog (the link itself may come up later)."""
        loop = asyncio.get_running_loop()
        self._tasks = [
            loop.create_task(self._keep_link(), name="ipt-mavlink-link"),
            loop.create_task(self._heartbeats(), name="ipt-mavlink-heartbeat"),
            loop.create_task(self._watch(), name="ipt-mavlink-watch"),
        ]

    async def close(self) -> None:
        """Say goodbye (STATUSTEXT), stop the tasks and close the link."""
        if self._link is not None and self._started_sent:
            self._statustext(self.dialect.MAV_SEVERITY_NOTICE, "localisation stopped")
        for task in self._tasks:
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        self._close_link()

    def _close_link(self) -> None:
        link, self._link = self._link, None
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
            self._link_up_s = self._clock_s()
            self._silence_reported = False
            self._say(f"{self.spec}: link open (system {self.cfg.system_id}, component {self.cfg.component_id})")
            self._last_link_error = None
            self._send_heartbeat()
            if not self._started_sent:
                self._started_sent = True
                self._statustext(self.dialect.MAV_SEVERITY_INFO, "localisation started")
            await self._broken.wait()
            self._close_link()

    def _on_broken(self, why: str) -> None:
        if not self._broken.is_set():
            self._say(f"{why}; reopening")
            self._broken.set()

    def _on_send_error(self, exc: BaseException) -> None:
        self.stats.send_errors += 1

    async def _heartbeats(self) -> None:
        start = self._clock_s()
        k = 1
        while True:
            await asyncio.sleep(max(0.0, start + k * HEARTBEAT_PERIOD_S - self._clock_s()))
            k += 1
            self._send_heartbeat()

    async def _watch(self) -> None:
        while True:
            await asyncio.sleep(WATCH_PERIOD_S)
            now = self._clock_s()
            if self.fix.tick(now) == "lost":
                self._say(f"fix lost: no pose for {self.cfg.fix_timeout_s:g} s")
                self._statustext(self.dialect.MAV_SEVERITY_WARNING, "fix lost")
            self._check_autopilot(now)

    def _check_autopilot(self, now: float) -> None:
        if self._link is None or self._link_up_s is None or self._silence_reported:
            return
        timeout = self.cfg.autopilot_timeout_s
        if self._last_autopilot_s is None and now - self._link_up_s > timeout:
            self._say(
                f"no HEARTBEAT from an autopilot on {self.spec} within {timeout:g} s (wiring, baud rate, the port's "
                "MAVLink setting?); sending poses anyway"
            )
            self._silence_reported = True
        elif self._last_autopilot_s is not None and now - self._last_autopilot_s > timeout:
            self._say(f"the autopilot has been silent for {timeout:g} s; sending poses anyway")
            self._silence_reported = True

    # -- sending -------------------------------------------------------------------------------------

    def _send(self, msg: Any) -> bool:
        link = self._link
        if link is None:
            return False
        data = bytes(msg.pack(self.mav))
        if link.send(data):
            return True
        self.stats.send_errors += 1
        return False

    def _send_heartbeat(self) -> None:
        d = self.dialect
        state = d.MAV_STATE_ACTIVE if self.fix.have_fix else d.MAV_STATE_STANDBY
        msg = self.mav.heartbeat_encode(d.MAV_TYPE_ONBOARD_CONTROLLER, d.MAV_AUTOPILOT_INVALID, 0, 0, state)
        if self._send(msg):
            self.stats.heartbeats += 1

    def _statustext(self, severity: int, text: str) -> None:
        body = (STATUSTEXT_PREFIX + text).encode("utf-8")[:50]
        if self._send(self.mav.statustext_encode(severity, body)):
            self.stats.statustexts += 1

    def time_usec(self, frame: CapturedFrame) -> int:
        """The frame's capture time on the monotonic clock, in µs (see the module doc)."""
        if self._time_offset_us is None:
            self._time_offset_us = round(frame.grabbed_s * 1e6) - frame.capture_time_us
        return frame.capture_time_us + self._time_offset_us

    def on_result(self, frame: CapturedFrame, result: FrameResult) -> OdometrySample | None:
        """Send the pose of one frame (if it has one); returns what was sent."""
        pose = result.pose
        if pose is None:
            return None
        if self.fix.pose(self._clock_s()) == "regained":
            self._say("fix regained")
            self._statustext(self.dialect.MAV_SEVERITY_INFO, "fix regained")
        resets_before = self.tracker.resets
        sample = self.tracker.update(pose, self.time_usec(frame), result.reset)
        self.stats.resets += self.tracker.resets - resets_before
        if not all(math.isfinite(float(v)) for v in (*sample.position_ned_m, *sample.quat_wxyz)):
            return None
        if result.reset:
            self.velocity.clear()  # the motion before a re-initialised track says nothing about after it
        self.velocity.add(
            frame.capture_time_us, pose.position_m, pose.r_arena_cam, pose.position_cov_m2, pose.attitude_cov_rad2
        )
        if not self.rate.admit(frame.capture_time_us):
            self.stats.held_back += 1
            return None
        twist = self.velocity.twist()
        if twist is not None:
            v, cov = body_velocity_frd(twist, pose, self.tracker.mounting)
            if np.all(np.isfinite(v)) and np.all(np.isfinite(cov)):
                sample = OdometrySample(**{**sample.__dict__, "velocity_frd_mps": v, "velocity_cov_frd": cov})
        if self.cfg.odometry and self._send(self._odometry_message(sample)):
            self.stats.odometry += 1
            if np.all(np.isfinite(sample.velocity_frd_mps)):
                self.stats.odometry_with_velocity += 1
        if self.cfg.vision_position_estimate and self._send(self._vision_message(sample)):
            self.stats.vision_position += 1
        return sample

    def _odometry_message(self, s: OdometrySample) -> Any:
        d = self.dialect
        nan = math.nan
        x, y, z = (float(v) for v in s.position_ned_m)
        vx, vy, vz = (float(v) for v in s.velocity_frd_mps)  # NaN until the fit has enough poses
        return self.mav.odometry_encode(
            s.time_usec,
            d.MAV_FRAME_LOCAL_FRD,
            d.MAV_FRAME_BODY_FRD,
            x,
            y,
            z,
            [float(v) for v in s.quat_wxyz],
            vx,  # in the child frame, body FRD, as MAVLink defines it (PX4 and ArduPilot rotate it to NED)
            vy,
            vz,
            nan,  # angular rates are not sent (no autopilot fuses them from external vision)
            nan,
            nan,
            list(s.pose_covariance),
            list(s.velocity_covariance),
            s.reset_counter,
            d.MAV_ESTIMATOR_TYPE_VISION,
            s.quality,
        )

    def _vision_message(self, s: OdometrySample) -> Any:
        x, y, z = (float(v) for v in s.position_ned_m)
        roll, pitch, yaw = s.rpy_rad
        return self.mav.vision_position_estimate_encode(
            s.time_usec, x, y, z, roll, pitch, yaw, list(s.pose_covariance), s.reset_counter
        )

    # -- receiving -----------------------------------------------------------------------------------

    def _on_bytes(self, data: bytes) -> None:
        try:
            messages = self._parser.parse_buffer(data) or []
        except Exception:  # pymavlink raises on some corrupt input even when robust: skip the datagram
            return
        for msg in messages:
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                self._heard_heartbeat(msg)
            elif kind == "TIMESYNC":
                self._answer_timesync(msg)

    def _heard_heartbeat(self, msg: Any) -> None:
        if msg.autopilot == self.dialect.MAV_AUTOPILOT_INVALID:
            return  # another companion component, a camera, a GCS
        self._last_autopilot_s = self._clock_s()
        who = f"system {msg.get_srcSystem()} component {msg.get_srcComponent()}"
        name = _AUTOPILOT_NAMES.get(int(msg.autopilot))
        who = f"{who} ({name})" if name else who
        if self.stats.autopilot != who or self._silence_reported:
            line = self._heard_log.line("autopilot heard", f"autopilot heard: {who}", self._clock_s())
            if line is not None:
                self._say(line)
        self.stats.autopilot = who
        self._silence_reported = False

    def _answer_timesync(self, msg: Any) -> None:
        if msg.tc1 != 0:
            return  # a reply to someone else's request
        target = {}
        names = self.dialect.MAVLink_timesync_message.fieldnames
        if "target_system" in names:
            ts, tc = getattr(msg, "target_system", 0), getattr(msg, "target_component", 0)
            if ts not in (0, self.cfg.system_id) or tc not in (0, self.cfg.component_id):
                return  # meant for another component
            target = {"target_system": msg.get_srcSystem(), "target_component": msg.get_srcComponent()}
        if self._send(self.mav.timesync_encode(self._clock_ns(), msg.ts1, **target)):
            self.stats.timesync_answered += 1

    def summary(self) -> str:
        """One line for the end of the run."""
        s = self.stats
        vpe = f", {s.vision_position} VISION_POSITION_ESTIMATE" if self.cfg.vision_position_estimate else ""
        heard = s.autopilot if s.autopilot is not None else "no autopilot heard"
        limit = "" if self.cfg.max_rate_hz is None else f" ({s.held_back} poses held back by max_rate_hz)"
        return (
            f"{self.spec}: {s.odometry} ODOMETRY{limit}, {s.odometry_with_velocity} with a velocity{vpe}, "
            f"{s.heartbeats} HEARTBEAT, {s.timesync_answered} TIMESYNC "
            f"answered, {s.statustexts} STATUSTEXT, {s.resets} resets, send errors {s.send_errors}; {heard}"
        )

    def say_summary(self) -> None:
        """Print :meth:`summary` on the report stream."""
        self._say(self.summary())


__all__ = [
    "R_FRD_CAM_DOWNWARD",
    "R_NED_ENU",
    "FixMonitor",
    "LinkSpec",
    "MavlinkError",
    "MavlinkOutput",
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
