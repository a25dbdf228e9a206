"""MAVLink output: the ENU→NED/FRD maths, covariance and quality, and the real thing on loopback.

The listener is pymavlink's own ``udpin`` connection bound on 127.0.0.1 (what mavproxy or a ground station
would use), run on a thread; the daemon runs as a real subprocess. A pseudo-terminal stands in for the
autopilot's serial port.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import itertools
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("MAVLINK20", "1")  # the listener speaks MAVLink 2 (ODOMETRY needs it) from the start

import cv2
import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2
from waiting import until, wait_until

from ipt.config.camera_info import CameraInfo
from ipt.config.models import ArenaConfig, ConfigError, PoseConfig
from ipt.config.receiver import MavlinkConfig, ReceiverConfig, parse_link, with_overrides
from ipt.geometry import matrix_from_quat_wxyz, matrix_from_ypr, rot_z
from ipt.protocol import decode_pose
from ipt.receiver.capture import CapturedFrame
from ipt.receiver.core.pipeline import FrameResult
from ipt.receiver.core.pose import PoseEstimate, solve_pose
from ipt.receiver.detect.detector import TagDetection
from ipt.receiver.outputs.mavlink.output import (
    R_FRD_CAM_DOWNWARD,
    R_NED_ENU,
    FixMonitor,
    MavlinkError,
    MavlinkOutput,
    Mounting,
    OdometryTracker,
    RateLimiter,
    body_pose_ned,
    euler_jacobian,
    euler_rpy_rad,
    load_dialect,
    odometry_sample,
    pose_covariance_ned,
    quality_percent,
    upper_triangle_21,
)
from ipt.receiver.outputs.mavlink.session import MavlinkSession
from ipt.sim.run import CAMERA_NAME, VIDEO_NAME
from ipt.tagmap import grid_tag_map

RUN_TIMEOUT_S = 90.0
FPS = 120


# --- poses ---------------------------------------------------------------------------------------


def _r_arena_cam_level(heading_rad: float) -> np.ndarray:
    """A level drone whose nose points ``heading_rad`` from arena x towards arena y, camera looking down."""
    r_arena_flu = rot_z(heading_rad)
    r_flu_frd = np.diag([1.0, -1.0, -1.0])
    return np.asarray(r_arena_flu @ r_flu_frd @ R_FRD_CAM_DOWNWARD)


def _pose(
    position_m: tuple[float, float, float] = (0.3, -0.2, 0.8),
    r_arena_cam: np.ndarray | None = None,
    cov_p: np.ndarray | None = None,
    cov_a: np.ndarray | None = None,
) -> PoseEstimate:
    r = _r_arena_cam_level(0.4) if r_arena_cam is None else r_arena_cam
    return PoseEstimate(
        np.asarray(position_m, np.float64),
        r,
        (1, 2, 3),
        0.4,
        np.diag([1e-6, 4e-6, 9e-6]) if cov_p is None else cov_p,
        np.diag([1e-6, 2e-6, 3e-6]) if cov_a is None else cov_a,
    )


# --- the maths -----------------------------------------------------------------------------------


def test_default_mounting_gives_ned_position_and_frd_attitude() -> None:
    pose = _pose((0.3, -0.2, 0.8), _r_arena_cam_level(0.0))  # nose along arena x ("east")
    position_ned, r_ned_frd = body_pose_ned(pose, Mounting())
    np.testing.assert_allclose(position_ned, [-0.2, 0.3, -0.8], atol=1e-12)  # x=y_enu, y=x_enu, z=-z_enu
    np.testing.assert_allclose(r_ned_frd[:, 0], [0, 1, 0], atol=1e-12)  # the nose points "east" = NED y
    np.testing.assert_allclose(r_ned_frd[:, 2], [0, 0, 1], atol=1e-12)  # body z is down
    roll, pitch, yaw = euler_rpy_rad(r_ned_frd)
    assert (roll, pitch) == pytest.approx((0.0, 0.0), abs=1e-12)
    assert yaw == pytest.approx(math.pi / 2)  # east is yaw +90 degrees in NED

    north = body_pose_ned(_pose(r_arena_cam=_r_arena_cam_level(math.pi / 2)), Mounting())[1]
    np.testing.assert_allclose(north, np.eye(3), atol=1e-12)  # nose along arena y: the null rotation
    s = odometry_sample(_pose(r_arena_cam=_r_arena_cam_level(math.pi / 2)), 7, Mounting())
    np.testing.assert_allclose(s.quat_wxyz, [1, 0, 0, 0], atol=1e-12)


def test_tilted_pose_round_trips_through_the_quaternion() -> None:
    r_arena_flu = matrix_from_ypr(0.7, 0.1, -0.15)
    r_arena_cam = r_arena_flu @ np.diag([1.0, -1.0, -1.0]) @ R_FRD_CAM_DOWNWARD
    s = odometry_sample(_pose(r_arena_cam=r_arena_cam), 0, Mounting())
    r_ned_frd = R_NED_ENU @ r_arena_flu @ np.diag([1.0, -1.0, -1.0])
    np.testing.assert_allclose(matrix_from_quat_wxyz(s.quat_wxyz), r_ned_frd, atol=1e-12)
    np.testing.assert_allclose(matrix_from_ypr(s.rpy_rad[2], s.rpy_rad[1], s.rpy_rad[0]), r_ned_frd, atol=1e-12)


def test_lever_arm_moves_the_body_origin_and_adds_attitude_uncertainty() -> None:
    heading = 0.3
    camera_ahead = Mounting(R_FRD_CAM_DOWNWARD, np.array([0.10, 0.0, 0.05]))  # 10 cm forward, 5 cm below
    pose = _pose((0.5, 0.5, 0.8), _r_arena_cam_level(heading))
    body_ned, _ = body_pose_ned(pose, camera_ahead)
    nose_enu = np.array([math.cos(heading), math.sin(heading), 0.0])
    expected_enu = np.array([0.5, 0.5, 0.8]) - 0.10 * nose_enu + np.array([0, 0, 0.05])
    np.testing.assert_allclose(body_ned, R_NED_ENU @ expected_enu, atol=1e-12)

    plain = pose_covariance_ned(pose, Mounting())
    offset = pose_covariance_ned(pose, camera_ahead)
    assert np.all(np.diag(offset)[:3] >= np.diag(plain)[:3] - 1e-18)
    assert np.trace(offset[:3, :3]) > np.trace(plain[:3, :3])
    assert np.abs(offset[:3, 3:]).max() > 0  # position-attitude cross terms from the lever arm
    assert np.all(np.linalg.eigvalsh(offset) > -1e-15)


def test_covariance_is_rotated_into_ned_and_laid_out_as_mavlink_wants() -> None:
    cov_p = np.array([[1e-6, 2e-7, 0.0], [2e-7, 4e-6, 1e-7], [0.0, 1e-7, 9e-6]])
    cov = pose_covariance_ned(_pose(cov_p=cov_p), Mounting())
    np.testing.assert_allclose(cov[:3, :3], R_NED_ENU @ cov_p @ R_NED_ENU.T)
    assert cov[0, 0] == pytest.approx(4e-6)
    assert cov[1, 1] == pytest.approx(1e-6)
    urt = upper_triangle_21(cov)
    assert len(urt) == 21
    assert (urt[0], urt[1], urt[6], urt[11], urt[15], urt[18], urt[20]) == pytest.approx(
        (cov[0, 0], cov[0, 1], cov[1, 1], cov[2, 2], cov[3, 3], cov[4, 4], cov[5, 5])
    )
    unknown = upper_triangle_21(np.full((6, 6), np.nan))
    assert math.isnan(unknown[0])


def test_attitude_floor_and_euler_jacobian() -> None:
    zero_att = _pose(cov_a=np.zeros((3, 3)))
    cov = pose_covariance_ned(zero_att, Mounting(), min_attitude_std_rad=0.005)
    assert np.all(np.diag(cov)[3:] > 0.5 * 0.005**2)
    # The analytic Jacobian against finite differences of a small rotation about each local axis.
    r = matrix_from_ypr(0.8, 0.2, -0.3)
    j = euler_jacobian(r)
    eps = 1e-7
    base = np.array(euler_rpy_rad(r))
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        theta = np.linalg.norm(d)
        k = d / theta
        kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        rot = np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx
        numeric = (np.array(euler_rpy_rad(rot @ r)) - base) / eps
        np.testing.assert_allclose(j[:, i], numeric, atol=1e-5)


def test_quality_falls_with_uncertainty() -> None:
    assert quality_percent(0.0, 0.1) == 100
    assert quality_percent(0.003, 0.1) == 97
    assert quality_percent(0.05, 0.1) == 50
    assert quality_percent(1.0, 0.1) == 1
    assert quality_percent(float("nan"), 0.1) == 0


def _camera() -> CameraInfo:
    return CameraInfo(640, 360, 460.0, 460.0, 319.5, 179.5, (0.0, 0.0, 0.0, 0.0, 0.0))


def _detections(r_arena_cam: np.ndarray, position_m: np.ndarray, noise_px: float, seed: int) -> list[TagDetection]:
    """Tags of the shipped arena as the camera sees them (corners projected, with Gaussian noise)."""
    arena = ArenaConfig()
    tm = grid_tag_map(arena)
    cam = _camera()
    r_cam_arena = r_arena_cam.T
    rvec, _ = cv2.Rodrigues(r_cam_arena)
    tvec = -r_cam_arena @ position_m
    rng = np.random.default_rng(seed)
    out = []
    for tag in tm.tags:
        corners = np.asarray(tag.corners_m)
        in_cam = (r_cam_arena @ (corners - position_m).T).T
        if np.any(in_cam[:, 2] <= 0):
            continue
        px, _ = cv2.projectPoints(corners, rvec, tvec, cam.camera_matrix, cam.dist_coeffs)
        px = px.reshape(4, 2) + rng.normal(0.0, noise_px, (4, 2))
        if px.min() < 3 or px[:, 0].max() > cam.width_px - 4 or px[:, 1].max() > cam.height_px - 4:
            continue
        out.append(TagDetection(tag.tag_id, 0, 50.0, px))
    return out


def test_covariance_grows_when_fewer_tags_are_seen() -> None:
    position = np.array([0.05, 0.1, 1.6])
    r = _r_arena_cam_level(1.2)
    dets = _detections(r, position, 0.3, seed=1)
    assert len(dets) >= 6
    cfg = PoseConfig(max_speed_mps=None)
    tm = grid_tag_map(ArenaConfig())
    variances = {}
    for n in (len(dets), 3, 2):
        pose = solve_pose(dets[:n], tm, _camera(), cfg)
        assert pose is not None
        s = odometry_sample(pose, 0, Mounting())
        np.testing.assert_allclose(s.position_ned_m, R_NED_ENU @ position, atol=0.03)
        variances[n] = (np.diag(s.covariance_6x6)[:3].sum(), s.quality)
        # what goes on the wire decodes to the same numbers (float32)
        mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
        out = MavlinkSession.__new__(MavlinkSession)  # only the message builder: no link, no clock
        out.mav, out.dialect = mav, mavlink2
        decoded = mavlink2.MAVLink(None).parse_buffer(bytes(out._odometry_message(s).pack(mav)))
        assert decoded is not None
        np.testing.assert_allclose(decoded[0].pose_covariance, s.pose_covariance, rtol=1e-6)
    many, three, two = variances[len(dets)], variances[3], variances[2]
    assert two[0] > three[0] > many[0]
    assert two[1] <= three[1] <= many[1]


def test_reset_counter_counts_reinitialisations_and_jumps_and_wraps() -> None:
    tracker = OdometryTracker(Mounting(), reset_jump_m=0.5)
    assert tracker.update(_pose((0.0, 0.0, 0.8)), 0).reset_counter == 0
    assert tracker.update(_pose((0.01, 0.0, 0.8)), 1).reset_counter == 0
    assert tracker.update(_pose((0.02, 0.0, 0.8)), 2, reset=True).reset_counter == 1
    assert tracker.update(_pose((0.9, 0.0, 0.8)), 3).reset_counter == 2  # a 0.88 m jump
    assert tracker.update(_pose((0.9, 0.0, 0.8)), 4).reset_counter == 2
    for k in range(254):
        tracker.update(_pose((0.9, 0.0, 0.8)), 5 + k, reset=True)
    assert tracker.reset_counter == 0
    assert tracker.resets == 256


def test_rate_limiter_keeps_at_most_max_rate_per_second_each_the_newest() -> None:
    for fps, expected_per_s in ((120, 40), (200, 50), (50, 50), (30, 30)):
        limiter = RateLimiter(50.0)
        times = [round(k * 1e6 / fps) for k in range(10 * fps)]  # 10 s of frames, every one a pose
        sent = np.array([t for t in times if limiter.admit(t)])
        assert np.diff(sent).min() >= 20_000  # ArduPilot's EKF takes nothing closer than 20 ms
        per_window = [int(np.sum((sent >= t) & (sent < t + 1_000_000))) for t in times]
        assert max(per_window) <= 50, (fps, max(per_window))
        assert len(sent) == 10 * expected_per_s, (fps, len(sent))
        # "the newest": a pose goes out as soon as it may; the one before it was held back for being too soon
        for t in sent[1:]:
            k = times.index(int(t))
            assert times[k - 1] - sent[sent < t].max() < 20_000
        assert limiter.held_back == len(times) - len(sent)
    everything = RateLimiter(None)
    assert all(everything.admit(t) for t in (0, 1, 2, 3))
    again = RateLimiter(50.0)
    assert again.admit(1_000_000)
    assert not again.admit(1_010_000)
    assert again.admit(0)  # time went backwards: a new recording, start afresh


def test_odometry_carries_the_body_velocity_in_frd_with_its_covariance() -> None:
    out = MavlinkOutput(MavlinkConfig(link="udpout:127.0.0.1:9", max_rate_hz=None), report=None)
    heading = 0.7
    v_arena = np.array([0.6, -0.4, 0.05])
    samples = []
    for k in range(14):
        t_us = round(k * 1e6 / 120)
        pose = _pose((0.1 + v_arena[0] * t_us * 1e-6, v_arena[1] * t_us * 1e-6, 0.8 + v_arena[2] * t_us * 1e-6),
                     _r_arena_cam_level(heading))  # fmt: skip
        samples.append(out.on_result(_frame(k, t_us), FrameResult(k, t_us, pose, 3, "pose")))
    assert all(s is not None for s in samples)
    assert not np.isfinite(samples[1].velocity_frd_mps).any()  # two poses: no fit yet
    last = samples[-1]
    r_arena_frd = _r_arena_cam_level(heading) @ R_FRD_CAM_DOWNWARD.T
    np.testing.assert_allclose(last.velocity_frd_mps, r_arena_frd.T @ v_arena, atol=1e-9)
    cov = last.velocity_covariance
    assert min(cov[0], cov[6], cov[11]) > 0  # vx, vy, vz variances where PX4 reads them
    assert all(math.isnan(cov[i]) for i in (15, 18, 20))  # the rates are not sent
    msg = out._odometry_message(last)
    decoded = mavlink2.MAVLink(None).decode(bytearray(msg.pack(mavlink2.MAVLink(None, srcSystem=1, srcComponent=197))))
    np.testing.assert_allclose([decoded.vx, decoded.vy, decoded.vz], last.velocity_frd_mps, atol=1e-6)
    assert math.isnan(decoded.rollspeed)
    assert out.stats.odometry == 0  # the link was never opened: nothing was sent, and nothing counted


def test_fix_monitor_says_lost_once_and_regained() -> None:
    fix = FixMonitor(0.5)
    assert fix.tick(10.0) is None  # never had a fix: nothing to lose
    assert fix.pose(10.0) is None
    assert fix.tick(10.4) is None
    assert fix.tick(10.6) == "lost"
    assert fix.tick(11.0) is None
    assert fix.pose(11.1) == "regained"
    assert fix.have_fix


def test_link_and_dialect_mistakes_are_one_line() -> None:
    assert str(parse_link("udpout:127.0.0.1:14540")) == "udpout:127.0.0.1:14540"
    assert str(parse_link("serial:/dev/ttyAMA0:921600")) == "serial:/dev/ttyAMA0:921600"
    for bad in ("tcp:127.0.0.1:5760", "udpout:nohost", "serial:/dev/ttyAMA0", "serial:/dev/ttyS0:123457"):
        with pytest.raises(ValueError, match=r"udpout|serial|baud") as info:
            parse_link(bad)
        assert "\n" not in str(info.value)
    with pytest.raises(MavlinkError, match="unknown MAVLink dialect"):
        load_dialect("nosuchdialect")
    with pytest.raises(MavlinkError, match="no ODOMETRY"):
        load_dialect("minimal")
    base = ReceiverConfig(arena=Path("a.yaml"), camera=Path("c.yaml"))
    with pytest.raises(ConfigError, match=r"mavlink\.dialect: .*unknown MAVLink dialect 'ardupilot'"):
        with_overrides(base, mavlink={**MavlinkConfig().model_dump(), "dialect": "ardupilot"})
    with pytest.raises(ConfigError, match=r"mavlink\.r_frd_cam: .*rotation"):
        with_overrides(base, mavlink={**MavlinkConfig().model_dump(), "r_frd_cam": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]})


def test_cli_unknown_dialect_and_bad_link_exit_2_with_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "receiver.yaml"
    cfg.write_text("arena: a.yaml\ncamera: c.yaml\nmavlink:\n  link: udpout:127.0.0.1:14540\n  dialect: px4\n")
    for args in (["--config", str(cfg)], ["--mavlink", "tcp:1.2.3.4:5760"]):
        out = subprocess.run(
            [sys.executable, "-m", "ipt.receiver.cli", "run", *args],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
        )
        assert out.returncode == 2, out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1, out.stderr
        assert "dialect" in lines[0] or "udpout:HOST:PORT or serial:DEVICE:BAUD" in lines[0]


# --- a pymavlink listener on 127.0.0.1 -------------------------------------------------------------


@dataclass
class Heard:
    t_s: float
    msg: Any


@dataclass
class Listener:
    """pymavlink ``udpin`` on 127.0.0.1 (an ephemeral port) collecting every message on a thread."""

    conn: Any
    port: int
    heard: list[Heard] = field(default_factory=list)
    stop: threading.Event = field(default_factory=threading.Event)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def run(self) -> None:
        while not self.stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is not None and msg.get_type() != "BAD_DATA":
                with self.lock:
                    self.heard.append(Heard(time.monotonic(), msg))

    def of(self, kind: str) -> list[Heard]:
        with self.lock:
            return [h for h in self.heard if h.msg.get_type() == kind]

    def wait_for(self, kind: str, count: int = 1, timeout_s: float = 30.0) -> list[Heard]:
        try:
            wait_until(lambda: len(self.of(kind)) >= count, timeout_s, f"{count} {kind}")
        except AssertionError:
            raise AssertionError(
                f"fewer than {count} {kind} in {timeout_s} s; heard {len(self.heard)} messages"
            ) from None
        return self.of(kind)


@contextlib.contextmanager
def _listener() -> Iterator[Listener]:
    conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
    listener = Listener(conn, conn.port.getsockname()[1])
    thread = threading.Thread(target=listener.run, daemon=True)
    thread.start()
    try:
        yield listener
    finally:
        listener.stop.set()
        thread.join(2.0)
        conn.close()


def _frame(index: int, t_us: int) -> CapturedFrame:
    return CapturedFrame(index, t_us, np.zeros((2, 2, 3), np.uint8), 100.0 + t_us * 1e-6)


@pytest.mark.asyncio
async def test_output_answers_timesync_says_fix_lost_and_regained() -> None:
    with _listener() as listener:
        cfg = MavlinkConfig(link=f"udpout:127.0.0.1:{listener.port}", fix_timeout_s=0.2, vision_position_estimate=True)
        now_s = [100.0]  # the output's clock, injected: the fix is lost when it moves on, not after a sleep
        out = MavlinkOutput(cfg, report=None, clock_s=lambda: now_s[0])
        await out.open()
        try:
            await asyncio.to_thread(listener.wait_for, "STATUSTEXT", 1, 10.0)  # "started", once the link is up
            out.on_result(_frame(0, 0), FrameResult(0, 0, _pose(), 3, "pose"))
            await asyncio.to_thread(listener.wait_for, "ODOMETRY", 1, 10.0)
            ts1 = 123_456_789
            before_ns = time.monotonic_ns()
            listener.conn.mav.timesync_send(0, ts1)  # a request, as the autopilot sends it
            replies = await asyncio.to_thread(listener.wait_for, "TIMESYNC", 1, 10.0)
            reply = replies[0].msg
            assert reply.ts1 == ts1
            assert before_ns <= reply.tc1 <= time.monotonic_ns()  # the monotonic clock, in ns
            listener.conn.mav.timesync_send(5, ts1)  # a reply to someone else: not answered
            now_s[0] += 0.6  # longer than fix_timeout_s: the watchdog's next look finds the fix lost
            await _until(lambda: not out.fix.have_fix, 10.0)
            out.on_result(_frame(1, 600_000), FrameResult(1, 600_000, _pose(), 3, "pose"))
            texts = await asyncio.to_thread(listener.wait_for, "STATUSTEXT", 3, 10.0)
        finally:
            await out.close()
        await asyncio.to_thread(listener.wait_for, "STATUSTEXT", 4, 10.0)
        said = [h.msg.text for h in listener.of("STATUSTEXT")]
        assert said == [
            "IPT: localisation started",
            "IPT: fix lost",
            "IPT: fix regained",
            "IPT: localisation stopped",
        ]
        assert [h.msg.severity for h in listener.of("STATUSTEXT")] == [6, 4, 6, 5]
        assert len(listener.of("TIMESYNC")) == 1
        assert len(listener.of("VISION_POSITION_ESTIMATE")) == 2
        odo = [h.msg for h in listener.of("ODOMETRY")]
        assert [m.time_usec for m in odo] == [100_000_000, 100_600_000]  # capture times on the grab clock
        assert odo[0].get_srcSystem() == 1
        assert odo[0].get_srcComponent() == 197
        assert texts


@pytest.mark.asyncio
async def test_serial_link_over_a_pseudo_terminal_and_busy_port_is_retried() -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    holder = os.open(path, os.O_RDWR | os.O_NOCTTY)
    fcntl.flock(holder, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another program has the port
    report = _Lines()
    out = MavlinkOutput(MavlinkConfig(link=f"serial:{path}:921600"), report=report)  # type: ignore[arg-type]
    await out.open()
    try:
        await _until(lambda: any("busy" in line for line in report.lines), 5.0)
        assert sum("busy" in line for line in report.lines) == 1  # said once, retried quietly
        os.close(holder)  # the other program lets go
        await _until(lambda: any("link open" in line for line in report.lines), 10.0)
        out.on_result(_frame(0, 0), FrameResult(0, 0, _pose(), 3, "pose"))
        parser = mavlink2.MAVLink(None)
        kinds: list[str] = []
        os.set_blocking(master, False)

        def odometry_read() -> bool:
            with contextlib.suppress(BlockingIOError):
                kinds.extend(m.get_type() for m in parser.parse_buffer(os.read(master, 4096)) or [])
            return "ODOMETRY" in kinds

        with contextlib.suppress(AssertionError):  # the assertions below say what was missing
            await until(odometry_read, 5.0)
        assert "HEARTBEAT" in kinds
        assert "ODOMETRY" in kinds
    finally:
        await out.close()
        os.close(master)
        os.close(slave)
    assert all("\n" not in line.rstrip("\n") for line in report.lines)


class _Lines:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def write(self, text: str) -> int:
        self.lines += [line for line in text.splitlines() if line]
        return len(text)

    def flush(self) -> None:
        pass


async def _until(check: Any, timeout_s: float) -> None:
    await until(check, timeout_s)


# --- the daemon, end to end -----------------------------------------------------------------------


def _daemon(*args: str, cwd: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "ipt.receiver.cli", "run", *args],
        cwd=cwd,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


@contextlib.contextmanager
def _pose_listener() -> Iterator[tuple[int, list[bytes], threading.Event]]:
    import socket

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    packets: list[bytes] = []
    stop = threading.Event()

    def run() -> None:
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                packets.append(sock.recv(2048))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    try:
        yield sock.getsockname()[1], packets, stop
    finally:
        stop.set()
        thread.join(2.0)
        sock.close()


@pytest.mark.slow
def test_replayed_flight_odometry_matches_the_arena_poses(short_flight: Path, tmp_path: Path) -> None:
    with _listener() as mav, _pose_listener() as (pose_port, packets, _):
        proc = _daemon(
            "--source",
            f"video:{short_flight / VIDEO_NAME}",
            "--camera",
            str(short_flight / CAMERA_NAME),
            "--fps",
            str(FPS),
            "--send",
            f"127.0.0.1:{pose_port}",
            "--mavlink",
            f"udpout:127.0.0.1:{mav.port}",
            cwd=tmp_path,
        )
        _, err = proc.communicate(timeout=RUN_TIMEOUT_S)
        assert proc.returncode == 0, err
        sent = int(re.findall(r"(\d+) poses,", err)[-1])
        odometry_sent = int(re.findall(r"(\d+) ODOMETRY", err)[-1])
        wait_until(lambda: len(packets) >= sent, what="the pose datagrams the kernel already holds read")
        mav.wait_for("ODOMETRY", odometry_sent, 10.0)
    poses = [decode_pose(p) for p in packets]
    odometry = [h.msg for h in mav.of("ODOMETRY")]
    assert poses, err
    assert f"{len(odometry)} ODOMETRY ({len(poses) - len(odometry)} poses held back by max_rate_hz)" in err
    # At most 50 per second of capture time (max_rate_hz's default), each one a pose that was sent, and the
    # newest at that moment: every pose between two ODOMETRY came too soon after the first of them.
    offset = odometry[0].time_usec - poses[0].capture_time_us
    by_time = {p.capture_time_us: p for p in poses}
    sent_us = [o.time_usec - offset for o in odometry]
    assert all(t in by_time for t in sent_us)
    assert min(np.diff(sent_us)) >= 20_000
    assert max(sum(1 for u in sent_us if t <= u < t + 1_000_000) for t in sent_us) <= 50
    for before, after in itertools.pairwise(sent_us):
        skipped = [p.capture_time_us for p in poses if before < p.capture_time_us < after]
        assert all(t - before < 20_000 for t in skipped)
    worst_m = 0.0
    position_var_m2: list[float] = []
    with_velocity = 0
    for o, t in zip(odometry, sent_us, strict=True):
        p = by_time[t]
        assert (o.frame_id, o.child_frame_id) == (mavlink2.MAV_FRAME_LOCAL_FRD, mavlink2.MAV_FRAME_BODY_FRD)
        x, y, z = p.position_m
        worst_m = max(worst_m, float(np.abs(np.array([o.x, o.y, o.z]) - np.array([y, x, -z])).max()))
        assert o.estimator_type == mavlink2.MAV_ESTIMATOR_TYPE_VISION
        assert 1 <= o.quality <= 100
        assert all(math.isfinite(v) for v in o.pose_covariance)
        assert o.pose_covariance[0] > 0
        assert o.pose_covariance[15] > 0
        if math.isfinite(o.vx):
            with_velocity += 1
            assert abs(math.hypot(o.vx, o.vy, o.vz)) < 3.0  # the simulated flight stays under 1.5 m/s
            assert o.velocity_covariance[0] > 0
        else:
            assert math.isnan(o.velocity_covariance[0])
        position_var_m2.append(o.pose_covariance[0] + o.pose_covariance[6] + o.pose_covariance[11])
    assert worst_m < 1e-3, worst_m
    assert with_velocity >= 0.9 * len(odometry), (with_velocity, len(odometry))
    print(
        f"ODOMETRY {len(odometry)} for {len(poses)} poses, {with_velocity} with a velocity; "
        f"worst NED difference {worst_m * 1e3:.4f} mm"
    )
    # In square metres, as MAVLink wants: a millimetre-level fit is a variance of order 1e-6 m², never mm².
    spread_m = math.sqrt(float(np.median(position_var_m2)))
    assert 1e-5 < spread_m < 0.02, spread_m
    assert len(mav.of("HEARTBEAT")) >= 1


@pytest.mark.slow
def test_live_daemon_heartbeats_at_1_hz_answers_timesync_and_says_start_and_stop(tmp_path: Path) -> None:
    with _listener() as mav:
        proc = _daemon("--source", "sim", "--realtime", "--mavlink", f"udpout:127.0.0.1:{mav.port}", cwd=tmp_path)
        try:
            mav.wait_for("HEARTBEAT", 1, RUN_TIMEOUT_S)
            mav.conn.mav.timesync_send(0, 42)
            mav.conn.mav.heartbeat_send(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4, 0, 0, 4)
            mav.wait_for("TIMESYNC", 1, 10.0)
            beats = mav.wait_for("HEARTBEAT", 5, 30.0)
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=10.0)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        wait_until(
            lambda: any(h.msg.text == "IPT: localisation stopped" for h in mav.of("STATUSTEXT")),
            10.0,
            "the last STATUSTEXT read",
        )
    assert proc.returncode == 0, err
    intervals = np.diff([b.t_s for b in beats[:5]])
    print(f"HEARTBEAT intervals {np.round(intervals, 3).tolist()} s")
    assert float(np.mean(intervals)) == pytest.approx(1.0, abs=0.05)
    assert float(np.max(np.abs(intervals - 1.0))) < 0.25
    hb = beats[0].msg
    assert (hb.type, hb.autopilot) == (mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID)
    assert hb.get_srcComponent() == 197
    assert mav.of("TIMESYNC")[0].msg.ts1 == 42
    texts = [h.msg.text for h in mav.of("STATUSTEXT")]
    assert texts[0] == "IPT: localisation started"
    assert texts[-1] == "IPT: localisation stopped"
    assert "autopilot heard: system 1 component 1 (PX4)" in err
    assert "1 TIMESYNC answered" in err


@pytest.mark.slow
def test_missing_serial_port_is_one_line_and_localisation_goes_on(short_flight: Path, tmp_path: Path) -> None:
    proc = _daemon(
        "--source",
        f"video:{short_flight / VIDEO_NAME}",
        "--camera",
        str(short_flight / CAMERA_NAME),
        "--fps",
        str(FPS),
        "--max-frames",
        "20",
        "--mavlink",
        "serial:/dev/ipt-no-such-port:921600",
        cwd=tmp_path,
    )
    _, err = proc.communicate(timeout=RUN_TIMEOUT_S)
    assert proc.returncode == 0, err
    problems = [line for line in err.splitlines() if "no such serial port" in line]
    assert len(problems) == 1, err
    assert "retrying" in problems[0]
    assert "localisation goes on" in problems[0]
    assert "Traceback" not in err
    final = next(line for line in err.splitlines() if line.startswith("ipt-receiver: final:"))
    assert "20 frames" in final
    assert " 0 poses" not in final
