"""The MAVLink session without a link or a clock: made-up times in, messages out
(ipt/receiver/outputs/mavlink/session.py)."""

from __future__ import annotations

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from ipt.config.receiver import MavlinkConfig
from ipt.geometry import rot_z
from ipt.receiver.capture import CapturedFrame
from ipt.receiver.core.frameresult import FrameResult
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.outputs.mavlink.frames import R_FRD_CAM_DOWNWARD
from ipt.receiver.outputs.mavlink.links import load_dialect
from ipt.receiver.outputs.mavlink.session import HEARTBEAT_PERIOD_S, WATCH_PERIOD_S, MavlinkSession, Outgoing


def _pose() -> PoseEstimate:
    """A level drone 0.8 m up, nose 0.4 rad from arena x, camera looking down, millimetre covariances."""
    r_arena_cam = rot_z(0.4) @ np.diag([1.0, -1.0, -1.0]) @ R_FRD_CAM_DOWNWARD
    return PoseEstimate(
        np.array([0.3, -0.2, 0.8]),
        r_arena_cam,
        (1, 2, 3),
        0.4,
        np.diag([1e-6, 4e-6, 9e-6]),
        np.diag([1e-6, 2e-6, 3e-6]),
    )


def _session(**cfg: object) -> tuple[MavlinkSession, list[str]]:
    said: list[str] = []
    config = MavlinkConfig.model_validate({"link": "udpout:127.0.0.1:9", "max_rate_hz": None, **cfg})
    return MavlinkSession(config, load_dialect(config.dialect), "udpout:127.0.0.1:9", said.append), said


def _kinds(messages: list[Outgoing]) -> list[str]:
    parser = mavlink2.MAVLink(None)
    return [parser.decode(bytearray(m.data)).get_type() for m in messages]


def _frame(index: int, t_us: int) -> CapturedFrame:
    return CapturedFrame(index, t_us, np.zeros((2, 2, 3), np.uint8), 100.0 + t_us * 1e-6)


def test_heartbeats_once_a_period_from_the_start_and_once_when_late() -> None:
    s, _ = _session()
    assert s.next_deadline() == float("inf")  # not started: nothing due
    s.start(100.0)
    assert _kinds(s.link_opened(100.0)) == ["HEARTBEAT", "STATUSTEXT"]  # at once, and "started"
    assert s.next_deadline() == 100.0 + WATCH_PERIOD_S
    assert _kinds(s.poll(100.5)) == []
    assert _kinds(s.poll(100.0 + HEARTBEAT_PERIOD_S)) == ["HEARTBEAT"]
    assert _kinds(s.poll(103.7)) == ["HEARTBEAT"], "late by two periods: one HEARTBEAT, not three"
    assert s.next_deadline() <= 104.0
    assert _kinds(s.poll(103.9)) == []


def test_nothing_is_made_while_the_link_is_down_and_goodbye_only_after_hello() -> None:
    s, _ = _session()
    s.start(0.0)
    sample, messages = s.on_result(_frame(0, 0), FrameResult(0, 0, _pose(), 3, "pose"), 0.0)
    assert sample is not None
    assert messages == []  # a pose is only worth its moment: not queued for a link that is down
    assert s.poll(5.0) == []
    assert s.goodbye() == []
    s.link_opened(5.0)
    sample, messages = s.on_result(_frame(1, 8333), FrameResult(1, 8333, _pose(), 3, "pose"), 5.01)
    assert _kinds(messages) == ["STATUSTEXT", "ODOMETRY"]  # the fix, lost at 5.0 s, is regained
    assert messages[1].counts == ("odometry",)  # no velocity from two poses yet
    assert _kinds(s.goodbye()) == ["STATUSTEXT"]
    s.link_closed()
    assert s.poll(9.0) == []


def test_fix_lost_after_the_timeout_regained_with_the_next_pose() -> None:
    s, said = _session(fix_timeout_s=0.2)
    s.start(0.0)
    s.link_opened(0.0)
    s.on_result(_frame(0, 0), FrameResult(0, 0, _pose(), 3, "pose"), 0.0)
    assert s.poll(0.15) == []
    lost = s.poll(0.3)
    assert _kinds(lost) == ["STATUSTEXT"]
    assert any("fix lost" in line for line in said)
    _, messages = s.on_result(_frame(1, 400_000), FrameResult(1, 400_000, _pose(), 3, "pose"), 0.4)
    assert _kinds(messages) == ["STATUSTEXT", "ODOMETRY"]
    assert said[-1] == "fix regained"


def test_the_autopilot_heard_and_its_silence_named() -> None:
    s, said = _session(autopilot_timeout_s=1.0)
    s.start(0.0)
    s.link_opened(0.0)
    s.poll(1.5)
    assert any("no HEARTBEAT from an autopilot" in line for line in said)
    autopilot = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    beat = autopilot.heartbeat_encode(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4, 0, 0, 0)
    assert s.receive(bytes(beat.pack(autopilot)), 2.0, 2_000_000_000) == []
    assert s.stats.autopilot == "system 1 component 1 (PX4)"
    request = autopilot.timesync_encode(0, 42)
    reply = s.receive(bytes(request.pack(autopilot)), 2.1, 2_100_000_000)
    assert _kinds(reply) == ["TIMESYNC"]
    assert reply[0].counts == ("timesync_answered",)
    assert mavlink2.MAVLink(None).decode(bytearray(reply[0].data)).tc1 == 2_100_000_000
    s.poll(3.5)
    assert "the autopilot has been silent for 1 s; sending poses anyway" in said
