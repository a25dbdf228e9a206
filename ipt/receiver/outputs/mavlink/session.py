"""The MAVLink session, sans-IO: what to send to the flight controller and when, with no socket and no clock.

Times come in as arguments; messages go out as :class:`Outgoing` (bytes and the counters of
:class:`MavlinkStats` a successful send adds to). :class:`ipt.receiver.outputs.mavlink.output.MavlinkOutput` is the thin
shell around it: it opens the link, sends what the session returns, counts what was sent and sleeps until
:meth:`MavlinkSession.next_deadline`. Its tests drive it with made-up times.

- :meth:`MavlinkSession.poll` (at :meth:`~MavlinkSession.next_deadline`): HEARTBEAT once a second, the loss
  of fix (no pose for ``fix_timeout_s``) and the autopilot's silence checked every 0.1 s;
- :meth:`~MavlinkSession.on_result`: ODOMETRY (and VISION_POSITION_ESTIMATE) of each pose, "fix regained";
- :meth:`~MavlinkSession.receive`: the autopilot's HEARTBEAT heard, TIMESYNC requests answered;
- :meth:`~MavlinkSession.link_opened` / :meth:`~MavlinkSession.link_closed` / :meth:`~MavlinkSession.goodbye`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ipt.ratelimit import LogThrottle
from ipt.receiver.core.kinematics import VelocityFit
from ipt.receiver.outputs.mavlink.frames import (
    FixMonitor,
    OdometrySample,
    OdometryTracker,
    RateLimiter,
    body_velocity_frd,
    mounting_from,
)

if TYPE_CHECKING:
    from ipt.config.receiver import MavlinkConfig
    from ipt.receiver.capture import CapturedFrame
    from ipt.receiver.core.frameresult import FrameResult

HEARTBEAT_PERIOD_S = 1.0
WATCH_PERIOD_S = 0.1
"""How often the loss of fix and the autopilot's silence are checked."""
STATUSTEXT_PREFIX = "IPT: "

_AUTOPILOT_NAMES = {3: "ArduPilot", 12: "PX4"}


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


@dataclass(frozen=True)
class Outgoing:
    """One message for the link: its bytes, and the :class:`MavlinkStats` counters it adds 1 to once sent."""

    data: bytes
    counts: tuple[str, ...]


class MavlinkSession:
    """What the MAVLink output says and when; see the module doc. ``say`` takes a line for the report."""

    def __init__(self, cfg: MavlinkConfig, dialect: Any, link_name: str, say: Callable[[str], None]) -> None:
        self.cfg, self.dialect, self.link_name, self._say = cfg, dialect, link_name, say
        self.mav: Any = dialect.MAVLink(None, srcSystem=cfg.system_id, srcComponent=cfg.component_id)
        self.mav.robust_parsing = True
        self._parser: Any = dialect.MAVLink(None)
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
        self.link_up = False
        """Whether the link is open: messages are made only while it is."""
        self._outbox: list[Outgoing] = []
        self._time_offset_us: int | None = None
        self._started_sent = False
        self._last_autopilot_s: float | None = None
        self._link_up_s: float | None = None
        self._silence_reported = False
        self._next_heartbeat_s = math.inf
        self._next_watch_s = math.inf
        # A peer that changes its system id at every HEARTBEAT would otherwise print a line for each.
        self._heard_log = LogThrottle(period_s=10.0, burst=3)

    # -- time ----------------------------------------------------------------------------------------

    def start(self, now_s: float) -> None:
        """The output started at ``now_s``: the first HEARTBEAT is due a period later, the first check at once
        a watch period later (the link's own first HEARTBEAT goes when it opens)."""
        self._next_heartbeat_s = now_s + HEARTBEAT_PERIOD_S
        self._next_watch_s = now_s + WATCH_PERIOD_S

    def next_deadline(self) -> float:
        """When :meth:`poll` has something to do next (the clock of the times passed in); inf before
        :meth:`start`."""
        return min(self._next_heartbeat_s, self._next_watch_s)

    def poll(self, now_s: float) -> list[Outgoing]:
        """Do what is due at ``now_s``; the messages to send now. A HEARTBEAT late by more than a period is
        sent once, not once per period missed."""
        if now_s >= self._next_heartbeat_s:
            self._send_heartbeat()
            periods = math.floor((now_s - self._next_heartbeat_s) / HEARTBEAT_PERIOD_S) + 1
            self._next_heartbeat_s += periods * HEARTBEAT_PERIOD_S
        if now_s >= self._next_watch_s:
            self._next_watch_s = now_s + WATCH_PERIOD_S
            if self.fix.tick(now_s) == "lost":
                self._say(f"fix lost: no pose for {self.cfg.fix_timeout_s:g} s")
                self._statustext(self.dialect.MAV_SEVERITY_WARNING, "fix lost")
            self._check_autopilot(now_s)
        return self._drain()

    # -- the link ------------------------------------------------------------------------------------

    def link_opened(self, now_s: float) -> list[Outgoing]:
        """The link is (again) open: a HEARTBEAT at once, and "localisation started" the first time."""
        self.link_up = True
        self._link_up_s = now_s
        self._silence_reported = False
        self._send_heartbeat()
        if not self._started_sent:
            self._started_sent = True
            self._statustext(self.dialect.MAV_SEVERITY_INFO, "localisation started")
        return self._drain()

    def link_closed(self) -> None:
        """The link broke or was closed: nothing is made for it until it opens again."""
        self.link_up = False
        self._outbox = []

    def goodbye(self) -> list[Outgoing]:
        """At the end: "localisation stopped", if "started" was said on an open link."""
        if self.link_up and self._started_sent:
            self._statustext(self.dialect.MAV_SEVERITY_NOTICE, "localisation stopped")
        return self._drain()

    def _check_autopilot(self, now: float) -> None:
        if not self.link_up or self._link_up_s is None or self._silence_reported:
            return
        timeout = self.cfg.autopilot_timeout_s
        if self._last_autopilot_s is None and now - self._link_up_s > timeout:
            self._say(
                f"no HEARTBEAT from an autopilot on {self.link_name} within {timeout:g} s (wiring, baud rate, the "
                "port's MAVLink setting?); sending poses anyway"
            )
            self._silence_reported = True
        elif self._last_autopilot_s is not None and now - self._last_autopilot_s > timeout:
            self._say(f"the autopilot has been silent for {timeout:g} s; sending poses anyway")
            self._silence_reported = True

    # -- sending -------------------------------------------------------------------------------------

    def _send(self, msg: Any, *counts: str) -> None:
        """Queue ``msg`` for the link (nothing while the link is down: a pose is only worth its moment)."""
        if self.link_up:
            self._outbox.append(Outgoing(bytes(msg.pack(self.mav)), counts))

    def _drain(self) -> list[Outgoing]:
        out, self._outbox = self._outbox, []
        return out

    def _send_heartbeat(self) -> None:
        d = self.dialect
        state = d.MAV_STATE_ACTIVE if self.fix.have_fix else d.MAV_STATE_STANDBY
        msg = self.mav.heartbeat_encode(d.MAV_TYPE_ONBOARD_CONTROLLER, d.MAV_AUTOPILOT_INVALID, 0, 0, state)
        self._send(msg, "heartbeats")

    def _statustext(self, severity: int, text: str) -> None:
        body = (STATUSTEXT_PREFIX + text).encode("utf-8")[:50]
        self._send(self.mav.statustext_encode(severity, body), "statustexts")

    def time_usec(self, frame: CapturedFrame) -> int:
        """The frame's capture time on the monotonic clock, in µs (see the module doc)."""
        if self._time_offset_us is None:
            self._time_offset_us = round(frame.grabbed_s * 1e6) - frame.capture_time_us
        return frame.capture_time_us + self._time_offset_us

    def on_result(
        self, frame: CapturedFrame, result: FrameResult, now_s: float
    ) -> tuple[OdometrySample | None, list[Outgoing]]:
        """The pose of one frame (if it has one) as it is sent, and the messages to send now."""
        return self._on_result(frame, result, now_s), self._drain()

    def _on_result(self, frame: CapturedFrame, result: FrameResult, now_s: float) -> OdometrySample | None:
        pose = result.pose
        if pose is None:
            return None
        if self.fix.pose(now_s) == "regained":
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
        if self.cfg.odometry:
            with_velocity = ("odometry_with_velocity",) if np.all(np.isfinite(sample.velocity_frd_mps)) else ()
            self._send(self._odometry_message(sample), "odometry", *with_velocity)
        if self.cfg.vision_position_estimate:
            self._send(self._vision_message(sample), "vision_position")
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

    def receive(self, data: bytes, now_s: float, now_ns: int) -> list[Outgoing]:
        """Bytes from the link (``now_ns``: the monotonic clock in ns, which TIMESYNC answers with); the
        messages to send in reply."""
        try:
            messages = self._parser.parse_buffer(data) or []
        except Exception:  # pymavlink raises on some corrupt input even when robust: skip the datagram
            return []
        for msg in messages:
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                self._heard_heartbeat(msg, now_s)
            elif kind == "TIMESYNC":
                self._answer_timesync(msg, now_ns)
        return self._drain()

    def _heard_heartbeat(self, msg: Any, now_s: float) -> None:
        if msg.autopilot == self.dialect.MAV_AUTOPILOT_INVALID:
            return  # another companion component, a camera, a GCS
        self._last_autopilot_s = now_s
        who = f"system {msg.get_srcSystem()} component {msg.get_srcComponent()}"
        name = _AUTOPILOT_NAMES.get(int(msg.autopilot))
        who = f"{who} ({name})" if name else who
        if self.stats.autopilot != who or self._silence_reported:
            line = self._heard_log.line("autopilot heard", f"autopilot heard: {who}", now_s)
            if line is not None:
                self._say(line)
        self.stats.autopilot = who
        self._silence_reported = False

    def _answer_timesync(self, msg: Any, now_ns: int) -> None:
        if msg.tc1 != 0:
            return  # a reply to someone else's request
        target = {}
        names = self.dialect.MAVLink_timesync_message.fieldnames
        if "target_system" in names:
            ts, tc = getattr(msg, "target_system", 0), getattr(msg, "target_component", 0)
            if ts not in (0, self.cfg.system_id) or tc not in (0, self.cfg.component_id):
                return  # meant for another component
            target = {"target_system": msg.get_srcSystem(), "target_component": msg.get_srcComponent()}
        self._send(self.mav.timesync_encode(now_ns, msg.ts1, **target), "timesync_answered")

    def summary(self) -> str:
        """One line for the end of the run."""
        s = self.stats
        vpe = f", {s.vision_position} VISION_POSITION_ESTIMATE" if self.cfg.vision_position_estimate else ""
        heard = s.autopilot if s.autopilot is not None else "no autopilot heard"
        limit = "" if self.cfg.max_rate_hz is None else f" ({s.held_back} poses held back by max_rate_hz)"
        return (
            f"{self.link_name}: {s.odometry} ODOMETRY{limit}, {s.odometry_with_velocity} with a velocity{vpe}, "
            f"{s.heartbeats} HEARTBEAT, {s.timesync_answered} TIMESYNC "
            f"answered, {s.statustexts} STATUSTEXT, {s.resets} resets, send errors {s.send_errors}; {heard}"
        )
