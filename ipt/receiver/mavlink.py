"""MAVLink to the flight controller: ODOMETRY (and optionally VISION_POSITION_ESTIMATE), HEARTBEAT, TIMESYNC.

Two layers:

- **The maths, pure** (:func:`body_pose_ned`, :func:`odometry_sample`, :func:`body_velocity_frd`,
  :class:`OdometryTracker`, :class:`RateLimiter`, :class:`FixMonitor`): a camera pose in the arena in, the
  vehicle body's pose in the autopilot's frames out, with its covariance, a quality, a reset counter and
  the body's velocity fitted over the recent poses (:mod:`ipt.receiver.kinematics`). No clock, no socket.
- **The connection, thin** (:class:`MavlinkOutput`): pymavlink encodes and decodes; the bytes go through
  an asyncio UDP endpoint (``udpout:HOST:PORT``) or a raw serial port (``serial:DEVICE:BAUD``) opened here
  with termios, so every read and write is non-blocking on the daemon's event loop. A link that cannot be
  opened (port missing or busy, name not resolving) is reported in one line and retried with backoff;
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
import contextlib
import errno
import fcntl
import importlib
import math
import os
import re
import termios
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any, Literal, TextIO

import numpy as np
import numpy.typing as npt

from ipt.config.receiver import LinkSpec, parse_link
from ipt.errors import IptError
from ipt.geometry import R_BODY_CAM_DOWNWARD, quat_wxyz_from_matrix, ypr_from_matrix
from ipt.ratelimit import LogThrottle
from ipt.receiver.kinematics import Twist, VelocityFit
from ipt.receiver.pose import PoseEstimate

if TYPE_CHECKING:
    from ipt.config.receiver import MavlinkConfig
    from ipt.receiver.capture import CapturedFrame
    from ipt.receiver.pipeline import FrameResult

F64 = npt.NDArray[np.float64]

#: Arena ENU → local NED (the arena's y is "north"): a proper rotation (determinant +1).
R_NED_ENU: F64 = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: Body FLU (``ipt.geometry``'s body) → body FRD.
R_FRD_FLU: F64 = np.diag([1.0, -1.0, -1.0])
#: The default mounting in FRD: looking straight down, the top of the image towards the nose. Columns are
#: the camera axes in body FRD: x_cam = right = +y, y_cam = backwards = -x, z_cam = down = +z.
R_FRD_CAM_DOWNWARD: F64 = R_FRD_FLU @ R_BODY_CAM_DOWNWARD

HEARTBEAT_PERIOD_S = 1.0
WATCH_PERIOD_S = 0.1
"""How often the loss of fix and the autopilot's silence are checked."""
BACKOFF_FIRST_S = 0.5
BACKOFF_MAX_S = 5.0
MAX_SERIAL_BUFFER_BYTES = 16 * 1024
"""Bytes queued for a serial port that does not keep up; further messages are dropped (and counted)."""
STATUSTEXT_PREFIX = "IPT: "
DEFAULT_DIALECT = "common"


class MavlinkError(IptError):
    """A MAVLink setting is wrong (unknown dialect, bad link) or a link cannot be opened."""


# --- the maths (pure) ------------------------------------------------------------------------------


@dataclass(frozen=True)
class Mounting:
    """Where the camera sits on the vehicle body (FRD)."""

    r_frd_cam: F64 = field(default_factory=lambda: R_FRD_CAM_DOWNWARD.copy())
    """3x3 rotation camera (OpenCV optical) → body FRD: the camera axes as columns in body axes."""
    camera_position_frd_m: F64 = field(default_factory=lambda: np.zeros(3))
    """The camera's optical centre from the body origin, body FRD metres."""

    def __post_init__(self) -> None:
        r = np.asarray(self.r_frd_cam, np.float64)
        if r.shape != (3, 3) or not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise MavlinkError("the camera rotation must be a 3x3 rotation matrix (orthonormal, determinant +1)")
        object.__setattr__(self, "r_frd_cam", r)
        object.__setattr__(self, "camera_position_frd_m", np.asarray(self.camera_position_frd_m, np.float64))


def skew(v: F64) -> F64:
    """The cross-product matrix: ``skew(a) @ b == np.cross(a, b)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def body_pose_ned(pose: PoseEstimate, mounting: Mounting) -> tuple[F64, F64]:
    """The body origin's position in local NED metres and the rotation body FRD → local NED."""
    r_arena_frd = pose.r_arena_cam @ mounting.r_frd_cam.T
    body_enu = pose.position_m - r_arena_frd @ mounting.camera_position_frd_m
    return R_NED_ENU @ body_enu, R_NED_ENU @ r_arena_frd


def euler_rpy_rad(r_ned_frd: F64) -> tuple[float, float, float]:
    """(roll, pitch, yaw) of the body: ``r = Rz(yaw) Ry(pitch) Rx(roll)``, MAVLink's convention."""
    yaw, pitch, roll = ypr_from_matrix(r_ned_frd)
    return roll, pitch, yaw


def euler_jacobian(r_ned_frd: F64) -> F64:
    """d(roll, pitch, yaw) / dθ for a small rotation θ about the local axes applied as ``exp(θ×) r``.

    An angular velocity in the local frame is ``E · (roll', pitch', yaw')`` with E's columns the roll axis
    (body x), the pitch axis (yaw-rotated y) and the yaw axis (local z); the Jacobian is ``E⁻¹``. Singular
    at ±90° of pitch, which a drone flying over a floor does not reach.
    """
    _, pitch, yaw = euler_rpy_rad(r_ned_frd)
    cp, sp, cy, sy = math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    e = np.array([[cp * cy, -sy, 0.0], [cp * sy, cy, 0.0], [-sp, 0.0, 1.0]])
    return np.asarray(np.linalg.inv(e), np.float64)


def pose_covariance_ned(pose: PoseEstimate, mounting: Mounting, min_attitude_std_rad: float = 0.0) -> F64:
    """6x6 covariance of (x, y, z, roll, pitch, yaw) of the body in local NED, from the pose's own.

    The body origin is ``c - R t`` (c the camera, t its offset on the body), so a small rotation θ moves it
    by ``(R t) × θ``: the attitude's uncertainty adds to the position's through the lever arm. The pose
    gives no position–attitude cross terms of the camera; those of the lever arm are kept. Each attitude
    variance is at least ``min_attitude_std_rad`` squared (raising diagonal entries keeps the matrix a
    covariance): no autopilot should be told the attitude is exact.
    """
    r_arena_frd = pose.r_arena_cam @ mounting.r_frd_cam.T
    lever = skew(r_arena_frd @ mounting.camera_position_frd_m)  # d(body)/dθ, arena axes
    cov_c = np.asarray(pose.position_cov_m2, np.float64)
    cov_th = np.array(pose.attitude_cov_rad2, np.float64)
    floor = min_attitude_std_rad**2
    for i in range(3):
        if np.isfinite(cov_th[i, i]) and cov_th[i, i] < floor:
            cov_th[i, i] = floor
    cov_p_enu = cov_c + lever @ cov_th @ lever.T
    cross_enu = lever @ cov_th
    m = R_NED_ENU
    _, r_ned_frd = body_pose_ned(pose, mounting)
    j = euler_jacobian(r_ned_frd) @ m  # d(rpy) / dθ_enu
    cov = np.zeros((6, 6))
    cov[:3, :3] = m @ cov_p_enu @ m.T
    cov[3:, 3:] = j @ cov_th @ j.T
    cov[:3, 3:] = m @ cross_enu @ j.T
    cov[3:, :3] = cov[:3, 3:].T
    return cov


def upper_triangle_21(cov: F64) -> tuple[float, ...]:
    """MAVLink's covariance layout: the upper-right triangle of a 6x6 matrix, row by row (21 values).

    A matrix with any non-finite entry is "unknown": NaN first, as the MAVLink spec asks."""
    if not np.all(np.isfinite(cov)):
        return (math.nan,) + (0.0,) * 20
    return tuple(float(cov[i, j]) for i in range(6) for j in range(i, 6))


def quality_percent(position_std_m: float, zero_quality_std_m: float) -> int:
    """MAVLink's quality: 100 for a perfect position, falling linearly to 1 at ``zero_quality_std_m`` of
    3-D standard deviation and staying there; 0 ("unknown") when the uncertainty is unknown."""
    if not math.isfinite(position_std_m):
        return 0
    return int(np.clip(round(100.0 * (1.0 - position_std_m / zero_quality_std_m)), 1, 100))


@dataclass(frozen=True)
class OdometrySample:
    """What one pose becomes on the wire (both ODOMETRY and VISION_POSITION_ESTIMATE carry it)."""

    time_usec: int
    position_ned_m: F64
    """The body origin in local NED (the arena's axes turned to north-east-down) metres."""
    quat_wxyz: F64
    """Rotation body FRD → local NED."""
    rpy_rad: tuple[float, float, float]
    """The same rotation as roll, pitch, yaw (Z-Y-X)."""
    covariance_6x6: F64
    """Covariance of (x, y, z, roll, pitch, yaw)."""
    quality: int
    reset_counter: int
    num_tags: int
    velocity_frd_mps: F64 = field(default_factory=lambda: np.full(3, np.nan))
    """The body origin's velocity in body FRD axes (ODOMETRY's child frame); NaN when unknown."""
    velocity_cov_frd: F64 = field(default_factory=lambda: np.full((3, 3), np.nan))
    """3x3 covariance of :attr:`velocity_frd_mps`."""

    @property
    def pose_covariance(self) -> tuple[float, ...]:
        """The 21 values of the covariance's upper-right triangle."""
        return upper_triangle_21(self.covariance_6x6)

    @property
    def velocity_covariance(self) -> tuple[float, ...]:
        """ODOMETRY's ``velocity_covariance``: (vx, vy, vz, rollspeed, pitchspeed, yawspeed), upper triangle.
        The rates are not sent, so their variances are NaN; the whole is "unknown" (NaN first) without a
        velocity."""
        if not (np.all(np.isfinite(self.velocity_frd_mps)) and np.all(np.isfinite(self.velocity_cov_frd))):
            return (math.nan,) + (0.0,) * 20
        cov = np.zeros((6, 6))
        cov[:3, :3] = self.velocity_cov_frd
        for i in range(3, 6):
            cov[i, i] = math.nan
        return tuple(float(cov[i, j]) for i in range(6) for j in range(i, 6))


def odometry_sample(
    pose: PoseEstimate,
    time_usec: int,
    mounting: Mounting,
    reset_counter: int = 0,
    zero_quality_std_m: float = 0.1,
    min_attitude_std_rad: float = 0.0,
) -> OdometrySample:
    """The MAVLink view of one camera pose."""
    position_ned_m, r_ned_frd = body_pose_ned(pose, mounting)
    cov = pose_covariance_ned(pose, mounting, min_attitude_std_rad)
    std_m = float(np.sqrt(np.trace(cov[:3, :3]))) if np.all(np.isfinite(cov[:3, :3])) else math.nan
    return OdometrySample(
        time_usec=time_usec,
        position_ned_m=position_ned_m,
        quat_wxyz=quat_wxyz_from_matrix(r_ned_frd),
        rpy_rad=euler_rpy_rad(r_ned_frd),
        covariance_6x6=cov,
        quality=quality_percent(std_m, zero_quality_std_m),
        reset_counter=reset_counter % 256,
        num_tags=len(pose.tag_ids),
    )


def body_velocity_frd(twist: Twist, pose: PoseEstimate, mounting: Mounting) -> tuple[F64, F64]:
    """The body origin's velocity in body FRD axes and its covariance, from the camera's twist: the origin
    sits at ``-R t`` from the camera (t its offset on the body), so it moves at ``v + ω × (-R t)``."""
    r_arena_frd = pose.r_arena_cam @ mounting.r_frd_cam.T
    v_arena, cov_arena = twist.velocity_of_point(-(r_arena_frd @ mounting.camera_position_frd_m))
    r = r_arena_frd.T
    return r @ v_arena, r @ cov_arena @ r.T


class RateLimiter:
    """At most ``max_rate_hz`` messages per second of capture time: a sample goes out when it is at least
    ``1 / max_rate_hz`` after the last one that went out (so any second holds at most ``max_rate_hz``), and
    the one that goes out is always the newest. ``None``: everything goes out. Time going backwards (a
    new recording) starts afresh."""

    def __init__(self, max_rate_hz: float | None) -> None:
        self.min_interval_us = None if max_rate_hz is None else 1e6 / max_rate_hz
        self._last_us: int | None = None
        self.held_back = 0
        """Samples not sent because they came too soon."""

    def admit(self, time_us: int) -> bool:
        """Whether a sample captured at ``time_us`` goes out now (and if so, it is counted as sent)."""
        last = self._last_us
        if self.min_interval_us is not None and last is not None and 0 <= time_us - last < self.min_interval_us:
            self.held_back += 1
            return False
        self._last_us = time_us
        return True


class OdometryTracker:
    """Turns successive poses into samples, counting resets: the pipeline re-initialised its track
    (``reset``), or the body moved more than ``reset_jump_m`` since the previous sample. The counter is
    a uint8 on the wire and wraps."""

    def __init__(
        self,
        mounting: Mounting,
        reset_jump_m: float = 0.5,
        zero_quality_std_m: float = 0.1,
        min_attitude_std_rad: float = 0.0,
    ) -> None:
        self.mounting = mounting
        self.reset_jump_m = reset_jump_m
        self.zero_quality_std_m = zero_quality_std_m
        self.min_attitude_std_rad = min_attitude_std_rad
        self.reset_counter = 0
        self.resets = 0
        self._last: F64 | None = None

    def update(self, pose: PoseEstimate, time_usec: int, reset: bool = False) -> OdometrySample:
        """The sample for ``pose``; increments the reset counter first when the solution jumped."""
        sample = odometry_sample(
            pose, time_usec, self.mounting, self.reset_counter, self.zero_quality_std_m, self.min_attitude_std_rad
        )
        jumped = (
            self._last is not None and float(np.linalg.norm(sample.position_ned_m - self._last)) > self.reset_jump_m
        )
        if reset or jumped:
            self.reset_counter = (self.reset_counter + 1) % 256
            self.resets += 1
            sample = OdometrySample(**{**sample.__dict__, "reset_counter": self.reset_counter})
        self._last = sample.position_ned_m
        return sample


FixEvent = Literal["lost", "regained"]


class FixMonitor:
    """Says when the fix is lost (no pose for ``timeout_s`` after one) and when it comes back. Pure: the
    caller passes the time in."""

    def __init__(self, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self.have_fix = False
        self.ever = False
        self._last_pose_s: float | None = None

    def pose(self, now_s: float) -> FixEvent | None:
        """A pose arrived at ``now_s``."""
        self._last_pose_s = now_s
        event: FixEvent | None = "regained" if self.ever and not self.have_fix else None
        self.have_fix = self.ever = True
        return event

    def tick(self, now_s: float) -> FixEvent | None:
        """Time passed; "lost" once when the last pose is older than the timeout."""
        if self.have_fix and self._last_pose_s is not None and now_s - self._last_pose_s > self.timeout_s:
            self.have_fix = False
            return "lost"
        return None


# --- the link ------------------------------------------------------------------------------------


def load_dialect(name: str) -> ModuleType:
    """pymavlink's MAVLink 2 module for dialect ``name``; :class:`MavlinkError` if unknown or unsuitable."""
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name):
        raise MavlinkError(f"unknown MAVLink dialect {name!r}")
    try:
        module = importlib.import_module(f"pymavlink.dialects.v20.{name}")
    except ImportError:
        raise MavlinkError(f"unknown MAVLink dialect {name!r} (e.g. common, ardupilotmega, development)") from None
    if not hasattr(module, "MAVLink_odometry_message"):
        raise MavlinkError(f"MAVLink dialect {name!r} has no ODOMETRY message; use common or ardupilotmega")
    return module


class _SerialPort:
    """A raw serial port on the event loop: non-blocking reads and writes, exclusive use."""

    def __init__(self, spec: LinkSpec, on_bytes: Callable[[bytes], None], on_broken: Callable[[str], None]) -> None:
        self.spec, self.on_bytes, self.on_broken = spec, on_bytes, on_broken
        self.fd: int | None = None
        self._out = bytearray()
        self._loop: asyncio.AbstractEventLoop | None = None

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        dev = self.spec.device
        try:
            fd = os.open(dev, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except FileNotFoundError:
            raise MavlinkError(f"{dev}: no such serial port") from None
        except PermissionError:
            raise MavlinkError(f"{dev}: permission denied (is this user in the dialout group?)") from None
        except OSError as exc:
            if exc.errno == errno.EBUSY:
                raise MavlinkError(f"{dev}: busy (another program has it open)") from None
            raise MavlinkError(f"{dev}: cannot open ({exc.strerror or exc})") from None
        try:
            if not os.isatty(fd):
                raise MavlinkError(f"{dev}: not a serial port")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise MavlinkError(
                    f"{dev}: busy (another program holds it: a serial console, ModemManager, mavproxy?)"
                ) from None
            speed = getattr(termios, f"B{self.spec.baud}")
            attrs = termios.tcgetattr(fd)
            # Raw 8N1, no flow control, no echo, no line editing (what tty.setraw does, plus the speed).
            attrs[0] = 0  # iflag
            attrs[1] = 0  # oflag
            attrs[2] = (attrs[2] & ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | termios.CRTSCTS)) | (
                termios.CS8 | termios.CREAD | termios.CLOCAL
            )
            attrs[3] = 0  # lflag
            attrs[4] = attrs[5] = speed
            attrs[6][termios.VMIN] = 0
            attrs[6][termios.VTIME] = 0
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
            with contextlib.suppress(OSError):
                fcntl.ioctl(fd, termios.TIOCEXCL)  # nobody else may open it while we have it
        except MavlinkError:
            os.close(fd)
            raise
        except (OSError, termios.error) as exc:
            os.close(fd)
            raise MavlinkError(f"{dev}: cannot set it up as a serial port ({exc})") from None
        self.fd, self._loop = fd, loop
        loop.add_reader(fd, self._readable)

    def _readable(self) -> None:
        if self.fd is None:
            return
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            self.on_broken(f"{self.spec.device}: read failed ({exc.strerror or exc})")
            return
        if data:
            self.on_bytes(data)

    def _writable(self) -> None:
        if self.fd is None or self._loop is None:
            return
        try:
            n = os.write(self.fd, self._out)
        except BlockingIOError:
            return
        except OSError as exc:
            self.on_broken(f"{self.spec.device}: write failed ({exc.strerror or exc})")
            return
        del self._out[:n]
        if not self._out:
            self._loop.remove_writer(self.fd)

    def send(self, data: bytes) -> bool:
        """Queue ``data``; False (dropped) if the port is closed or far behind."""
        if self.fd is None or self._loop is None:
            return False
        if self._out:
            if len(self._out) + len(data) > MAX_SERIAL_BUFFER_BYTES:
                return False
            self._out += data
            return True
        try:
            n = os.write(self.fd, data)
        except BlockingIOError:
            n = 0
        except OSError as exc:
            self.on_broken(f"{self.spec.device}: write failed ({exc.strerror or exc})")
            return False
        if n < len(data):
            self._out += data[n:]
            self._loop.add_writer(self.fd, self._writable)
        return True

    def close(self) -> None:
        fd, self.fd = self.fd, None
        if fd is None:
            return
        if self._loop is not None:
            with contextlib.suppress(Exception):
                self._loop.remove_reader(fd)
            with contextlib.suppress(Exception):
                self._loop.remove_writer(fd)
        self._out.clear()
        with contextlib.suppress(OSError):
            os.close(fd)


class _UdpProtocol(asyncio.DatagramProtocol):
    def __init__(self, link: _UdpLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self.link.on_bytes(data)

    def error_received(self, exc: Exception) -> None:
        self.link.on_error(exc)


class _UdpLink:
    """A connected UDP endpoint: datagrams to HOST:PORT, replies from it."""

    def __init__(self, spec: LinkSpec, on_bytes: Callable[[bytes], None], on_error: Callable[[BaseException], None]):
        self.spec, self.on_bytes, self.on_error = spec, on_bytes, on_error
        self.transport: asyncio.DatagramTransport | None = None

    async def open(self, loop: asyncio.AbstractEventLoop) -> None:
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: _UdpProtocol(self), remote_addr=(self.spec.host, self.spec.port)
            )
        except OSError as exc:
            raise MavlinkError(f"{self.spec}: {exc.strerror or exc}") from None
        self.transport = transport

    def send(self, data: bytes) -> bool:
        t = self.transport
        if t is None or t.is_closing():
            return False
        try:
            t.sendto(data)
        except OSError as exc:
            self.on_error(exc)
            return False
        return True

    def close(self) -> None:
        t, self.transport = self.transport, None
        if t is not None:
            t.close()


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
        self._link: _UdpLink | _SerialPort | None = None
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
            link: _UdpLink | _SerialPort
            try:
                if self.spec.kind == "udpout":
                    link = _UdpLink(self.spec, self._on_bytes, self._on_send_error)
                    await link.open(loop)
                else:
                    link = _SerialPort(self.spec, self._on_bytes, self._on_broken)
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


def mounting_from(r_frd_cam: Sequence[Sequence[float]] | None, camera_position_frd_m: Sequence[float]) -> Mounting:
    """A :class:`Mounting` from config values (``None``: the downward default)."""
    r = R_FRD_CAM_DOWNWARD if r_frd_cam is None else np.asarray(r_frd_cam, np.float64)
    return Mounting(r, np.asarray(camera_position_frd_m, np.float64))


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
    "load_dialect",
    "odometry_sample",
    "parse_link",
    "pose_covariance_ned",
    "upper_triangle_21",
]
