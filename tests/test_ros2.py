"""ROS 2 over DDS: a plain DDS reader with the ROS 2 types receives what the daemon publishes.

Every test here that starts DDS goes through :func:`dds_domain`: ``CYCLONEDDS_URI`` is the loopback-only,
multicast-off configuration of :mod:`ipt.receiver.outputs.ros.ddsconfig` (no packet leaves 127.0.0.1) and the domain
is one of this test run's own. Waits are bounded; the daemon runs as a real subprocess.
"""

from __future__ import annotations

import contextlib
import os
import re
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from waiting import wait_until

from ipt.config.receiver import Ros2Config
from ipt.geometry import rot_z
from ipt.protocol import decode_pose
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.outputs.mavlink.output import R_FRD_CAM_DOWNWARD, Mounting
from ipt.receiver.outputs.ros.dds import (
    Odometry,
    PoseWithCovarianceStamped,
    Ros2Error,
    Ros2Output,
    TFMessage,
    domain_from,
    qos_profile,
)
from ipt.receiver.outputs.ros.ddsconfig import LOOPBACK_XML, loopback_environ
from ipt.receiver.outputs.ros.frames import RosMessageMaker, RosNames, StampClock
from ipt.rosmsg import ODOMETRY, POSE, TF, read_mcap_trajectory, time_ns
from ipt.sim.run import CAMERA_NAME, VIDEO_NAME

MATCH_TIMEOUT_S = 10.0
RUN_TIMEOUT_S = 120.0


@pytest.fixture
def dds_domain(monkeypatch: pytest.MonkeyPatch) -> int:
    """Loopback-only DDS for this test (the one place the tests set CYCLONEDDS_URI) and a domain of its own.

    Domains 1-100 only: CycloneDDS's unicast ports for domain d are 7400 + 250·d + 10 + 2·i (participant index
    i up to MAX_PARTICIPANTS), and with multicast off it sends discovery to each of them on 127.0.0.1. For a
    domain over 101 those ports lie in Linux's ephemeral range (32768-60999), where a test's own UDP socket
    (port 0) may sit, and it received RTPS discovery instead of pose packets (seen once in a full run)."""
    domain = 1 + os.getpid() % 100
    for key, value in loopback_environ({}, domain).items():
        monkeypatch.setenv(key, value)
    return domain


def _reader_qos(reliable: bool, depth: int = 1000) -> Qos:
    return Qos(
        Policy.Reliability.Reliable(0) if reliable else Policy.Reliability.BestEffort,
        Policy.History.KeepLast(depth),
    )


@contextlib.contextmanager
def _readers(domain: int, topics: dict[str, tuple[type[Any], bool]]) -> Iterator[dict[str, DataReader[Any]]]:
    """A participant with one reader per DDS topic (type, reliable?), deleted on the way out."""
    participant = DomainParticipant(domain)
    try:
        yield {
            name: DataReader(participant, Topic(participant, name, struct), qos=_reader_qos(reliable))
            for name, (struct, reliable) in topics.items()
        }
    finally:
        participant.__del__()  # the binding keeps entities in a class-wide table: delete explicitly


def _samples(reader: DataReader[Any], struct: type[Any]) -> list[Any]:
    """What the reader holds, less the "invalid samples" that only announce a writer went away."""
    return [s for s in reader.take(200) if isinstance(s, struct)]


def _wait(check: Any, timeout_s: float = MATCH_TIMEOUT_S) -> None:
    wait_until(check, timeout_s)


def _pose(k: int) -> PoseEstimate:
    r = rot_z(0.3) @ np.diag([1.0, -1.0, -1.0]) @ R_FRD_CAM_DOWNWARD
    return PoseEstimate(np.array([0.1 + 0.01 * k, 0.2, 0.8]), r, (1, 2, 3), 0.3, np.eye(3) * 1e-6, np.eye(3) * 1e-6)


def test_loopback_configuration_is_what_the_tests_promise() -> None:
    assert '<NetworkInterface address="127.0.0.1"/>' in LOOPBACK_XML
    assert "<AllowMulticast>false</AllowMulticast>" in LOOPBACK_XML
    assert '<Peer address="127.0.0.1"/>' in LOOPBACK_XML
    env = loopback_environ({"PATH": "/bin"}, 7)
    assert env == {"PATH": "/bin", "CYCLONEDDS_URI": LOOPBACK_XML, "ROS_DOMAIN_ID": "7"}


def test_domain_and_qos_names() -> None:
    assert domain_from(Ros2Config(domain_id=5), {"ROS_DOMAIN_ID": "9"}) == 5
    assert domain_from(Ros2Config(), {"ROS_DOMAIN_ID": "9"}) == 9
    assert domain_from(Ros2Config(), {}) == 0
    with pytest.raises(Ros2Error, match="ROS_DOMAIN_ID"):
        domain_from(Ros2Config(), {"ROS_DOMAIN_ID": "lots"})
    sensor = qos_profile("sensor_data")
    assert Policy.Reliability.BestEffort in sensor
    assert Policy.History.KeepLast(5) in sensor
    assert Policy.History.KeepLast(100) in qos_profile("tf")
    with pytest.raises(Ros2Error, match="unknown QoS"):
        qos_profile("fast")


def test_published_messages_arrive_with_ros2_types_and_qos(dds_domain: int) -> None:
    names = RosNames(namespace="drone2")
    topics = [(names.pose_topic, POSE), (names.odom_topic, ODOMETRY), (names.tf_topic, TF)]
    out = Ros2Output(Ros2Config(), topics)
    try:
        wanted = {
            "rt/ipt/drone2/pose": (PoseWithCovarianceStamped, False),
            "rt/ipt/drone2/odom": (Odometry, False),
            "rt/tf": (TFMessage, True),  # tf2 listeners are reliable: /tf must be offered reliably
        }
        with _readers(dds_domain, wanted) as readers:
            _wait(lambda: all(out.matched(t) == 1 for t, _ in topics))
            maker = RosMessageMaker(names, Mounting(), StampClock(lambda: 1_000_000_000_000, lambda: 0.0))
            for k in range(10):
                out.publish(maker.frame(k, 10_000 * k, 0.0, "pose", 3, _pose(k)))
            got: dict[str, list[Any]] = {name: [] for name in wanted}

            def all_in() -> bool:
                for name, reader in readers.items():
                    got[name].extend(_samples(reader, wanted[name][0]))
                return all(len(v) == 10 for v in got.values())

            _wait(all_in)
        poses = got["rt/ipt/drone2/pose"]
        assert [round(p.pose.pose.position.x, 9) for p in poses] == [round(0.1 + 0.01 * k, 9) for k in range(10)]
        assert [time_ns(p.header.stamp) - 1_000_000_000_000 for p in poses] == [10_000_000 * k for k in range(10)]
        assert {p.header.frame_id for p in poses} == {"arena"}
        assert poses[0].pose.covariance[0] == pytest.approx(1e-6)
        odom = got["rt/ipt/drone2/odom"][-1]
        assert odom.child_frame_id == "drone2/base_link"
        assert odom.twist.covariance[0] > 0  # a velocity after a few poses
        assert np.hypot(odom.twist.twist.linear.x, odom.twist.twist.linear.y) == pytest.approx(1.0, abs=1e-6)
        tf = got["rt/tf"][0]
        assert [t.child_frame_id for t in tf.transforms] == ["drone2/camera", "drone2/base_link"]
        assert out.published == 30
        assert out.errors == 0
    finally:
        out.close()


def test_a_reliable_reader_gets_nothing_from_sensor_data_and_everything_from_reliable(dds_domain: int) -> None:
    """The QoS trap ROS users keep hitting, made visible: it is why the default needs a best-effort reader."""
    for qos, expected in (("sensor_data", 0), ("reliable", 1)):
        out = Ros2Output(Ros2Config(qos=qos), [("/ipt/pose", POSE)])
        try:
            with _readers(dds_domain, {"rt/ipt/pose": (PoseWithCovarianceStamped, True)}) as readers:
                assert readers  # held: the binding deletes an entity nothing refers to
                if expected:
                    _wait(lambda out=out: out.matched("/ipt/pose") == 1)  # type: ignore[misc]
                else:  # the reader has seen the writer and refused it: they can never match
                    reader = readers["rt/ipt/pose"]
                    _wait(lambda r=reader: r.get_requested_incompatible_qos_status().total_count >= 1)
                assert out.matched("/ipt/pose") == expected
        finally:
            out.close()


def test_a_domain_that_cannot_start_is_one_line(tmp_path: Path) -> None:
    # An interface this machine does not have: CycloneDDS refuses to start the domain (nothing is sent).
    bad = LOOPBACK_XML.replace('address="127.0.0.1"/></Interfaces>', 'address="192.0.2.77"/></Interfaces>')
    env = loopback_environ(None, 3)
    env["CYCLONEDDS_URI"] = bad
    proc = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "run", "--source", "sim", "--max-frames", "2", "--ros2"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("ipt-receiver: error: DDS domain 3 cannot start: 192.0.2.77"), lines
    assert lines[0].endswith("(check CYCLONEDDS_URI)")


def test_unknown_qos_name_is_one_line(tmp_path: Path) -> None:
    cfg = tmp_path / "receiver.yaml"
    cfg.write_text("arena: a.yaml\ncamera: c.yaml\nros2:\n  enabled: true\n  qos: fastest\n", encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "run", "--config", str(cfg)],
        cwd=tmp_path,
        env=loopback_environ(None, 3),
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "ros2.qos" in lines[0]
    assert "sensor_data" in lines[0]


def test_without_cyclonedds_ros2_is_one_line_and_says_how_to_install(tmp_path: Path) -> None:
    code = (
        "import sys; sys.modules['cyclonedds'] = None; from ipt.receiver.cli import main; "
        "sys.exit(main(['run', '--source', 'sim', '--max-frames', '2', '--ros2']))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=loopback_environ(None, 3), capture_output=True, text=True,
        timeout=RUN_TIMEOUT_S,
    )  # fmt: skip
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "pip install 'ipt[ros2]'" in lines[0]


# --- the daemon, end to end -------------------------------------------------------------------------


def _udp_sockets(pid: int) -> list[tuple[str, int, str, int]]:
    """(local address, port, remote address, port) of every IPv4 UDP socket of process ``pid``."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        with contextlib.suppress(OSError):
            if m := re.fullmatch(r"socket:\[(\d+)\]", os.readlink(fd)):
                inodes.add(m.group(1))
    found = []
    for line in Path(f"/proc/{pid}/net/udp").read_text().splitlines()[1:]:
        f = line.split()
        if f[9] in inodes:
            (la, lp), (ra, rp) = (x.split(":") for x in (f[1], f[2]))
            local = socket.inet_ntoa(bytes.fromhex(la)[::-1])
            remote = socket.inet_ntoa(bytes.fromhex(ra)[::-1])
            found.append((local, int(lp, 16), remote, int(rp, 16)))
    return found


@pytest.mark.slow
def test_daemon_publishes_every_pose_over_loopback_dds(short_flight: Path, tmp_path: Path, dds_domain: int) -> None:
    wanted = {
        "rt/ipt/pose": (PoseWithCovarianceStamped, False),
        "rt/ipt/odom": (Odometry, False),
        "rt/tf": (TFMessage, True),
    }
    record = tmp_path / "flight.mcap"
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp,
        _readers(dds_domain, wanted) as readers,
    ):
        udp.bind(("127.0.0.1", 0))
        udp.settimeout(0.05)
        packets: list[bytes] = []
        got: dict[str, list[Any]] = {name: [] for name in wanted}
        stop = threading.Event()

        def collect() -> None:
            while not stop.is_set():
                with contextlib.suppress(TimeoutError):
                    packets.append(udp.recv(2048))
                for name, reader in readers.items():
                    got[name].extend(_samples(reader, wanted[name][0]))

        thread = threading.Thread(target=collect, daemon=True)
        thread.start()
        port = udp.getsockname()[1]
        cmd = [sys.executable, "-m", "ipt.receiver.cli", "run", "--source", f"video:{short_flight / VIDEO_NAME}",
               "--camera", str(short_flight / CAMERA_NAME), "--fps", "120", "--send", f"127.0.0.1:{port}",
               "--ros2", "--record", str(record)]  # fmt: skip
        proc = subprocess.Popen(cmd, cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
        sockets: list[tuple[str, int, str, int]] = []

        def publishing() -> bool:  # the daemon's sockets, seen while it runs
            nonlocal sockets
            with contextlib.suppress(OSError):
                sockets = _udp_sockets(proc.pid) or sockets
            return proc.poll() is not None or any(got.values())

        with contextlib.suppress(AssertionError):  # the sockets are checked below
            wait_until(publishing, RUN_TIMEOUT_S)
        _, err = proc.communicate(timeout=RUN_TIMEOUT_S)
        if proc.returncode == 0:  # what the kernel and DDS still hold: every recorded pose, sent and on /tf
            n = len(read_mcap_trajectory(record))
            with contextlib.suppress(AssertionError):  # the counts are checked below
                wait_until(lambda: len(packets) >= n and len(got["rt/tf"]) >= n, 10.0)
        stop.set()
        thread.join(2.0)
    assert proc.returncode == 0, err
    sent = [decode_pose(p) for p in packets]
    recorded = read_mcap_trajectory(record)
    assert len(recorded) == len(sent) > 0, err
    received = got["rt/ipt/pose"]
    assert len(received) >= 0.95 * len(sent), (len(received), len(sent), err)
    by_time = {round(t * 1e6): p for t, p in zip(recorded.times_s, recorded.positions_m, strict=True)}
    assert len(by_time) == len(recorded)
    stamps = [time_ns(m.header.stamp) for m in received]
    offset_ns = stamps[0] - min(by_time) * 1000 if received else 0
    for m, stamp in zip(received, stamps, strict=True):  # each received pose is a recorded one, unchanged
        p = by_time[round((stamp - offset_ns) / 1000)]
        assert (m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z) == tuple(p)
    assert len(got["rt/ipt/odom"]) >= 0.95 * len(sent)
    assert len(got["rt/tf"]) == len(sent)  # reliable over loopback: all of them
    print(f"DDS: {len(received)} of {len(sent)} poses on rt/ipt/pose, {len(got['rt/tf'])} on rt/tf")
    # The only sending socket DDS has is bound to 127.0.0.1; the others are its unbound-address receivers on
    # the domain's own ports (7400 + 250 d + 10 + 2 i, + 1), connected to no one.
    base = 7400 + 250 * dds_domain + 10
    assert sockets, "the daemon's sockets were not seen"
    for local, port, remote, rport in sockets:
        if local != "127.0.0.1":
            assert local == "0.0.0.0", sockets
            assert (remote, rport) == ("0.0.0.0", 0), sockets
            assert port == 7400 + 250 * dds_domain or 0 <= port - base < 2 * 32, sockets
