"""The MCAP flight log: what it holds, how ROS 2 tools see it, and what a full disk does to it."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from ipt.geometry import rot_z
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.outputs.mavlink.output import R_FRD_CAM_DOWNWARD, Mounting
from ipt.receiver.outputs.ros.frames import RosMessageMaker, RosNames, StampClock
from ipt.receiver.outputs.ros.record import DIFFERENCE_GAIN, DifferenceSampler, McapRecorder
from ipt.rosmsg import COMPRESSED_IMAGE, DIAGNOSTICS, METADATA_NAME, ODOMETRY, POSE, TF, read_mcap_trajectory, time_ns
from ipt.sim.run import CAMERA_NAME, VIDEO_NAME

RUN_TIMEOUT_S = 120.0
WALL_NS = 1_800_000_000_000_000_000


def _pose(k: int) -> PoseEstimate:
    r = rot_z(0.3) @ np.diag([1.0, -1.0, -1.0]) @ R_FRD_CAM_DOWNWARD
    return PoseEstimate(np.array([0.01 * k, 0.2, 0.8]), r, (1, 2), 0.3, np.eye(3) * 1e-6, np.eye(3) * 1e-6)


def _lines() -> tuple[list[str], object]:
    said: list[str] = []
    return said, said.append


def test_recording_holds_every_topic_at_its_stamp_and_the_capture_clock(tmp_path: Path) -> None:
    path = tmp_path / "flight.mcap"
    said, report = _lines()
    rec = McapRecorder(path, metadata={"vehicle_id": "4"}, report=report)  # type: ignore[arg-type]
    clock = StampClock(lambda: WALL_NS, lambda: 10.0)
    maker = RosMessageMaker(RosNames(), Mounting(), clock)
    rec.start()
    assert (tmp_path / "flight.mcap.partial").exists()
    assert not path.exists()  # nothing that looks complete until it is
    for k in range(20):
        t_us = 500_000 + 8333 * k
        items = maker.frame(k, t_us, 10.0, "pose" if k % 4 else "no_tags", 2, _pose(k) if k % 4 else None)
        if k == 0:
            rec.set_metadata({"capture_time_offset_ns": str(clock.offset_ns)})
        rec.put(items)
    assert rec.close()
    assert path.exists()
    assert not (tmp_path / "flight.mcap.partial").exists()
    assert said == []
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        assert {s.name: s.encoding for s in summary.schemas.values()} == {
            POSE: "ros2msg",
            ODOMETRY: "ros2msg",
            TF: "ros2msg",
            DIAGNOSTICS: "ros2msg",
            COMPRESSED_IMAGE: "ros2msg",
        }
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        counts = {summary.channels[i].topic: n for i, n in summary.statistics.channel_message_counts.items()}
        assert counts == {"/ipt/pose": 15, "/ipt/odom": 15, "/tf": 15, "/ipt/diagnostics": 20}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta[METADATA_NAME]["vehicle_id"] == "4"
        for _, channel, message, decoded in reader.iter_decoded_messages():
            stamp = decoded.header.stamp if hasattr(decoded, "header") else decoded.transforms[0].header.stamp
            assert message.log_time == message.publish_time == time_ns(stamp), channel.topic
    traj = read_mcap_trajectory(path)
    expected = [500_000 + 8333 * k for k in range(20) if k % 4]
    assert [round(t * 1e6) for t in traj.times_s] == expected  # the capture clock, back from the stamps
    np.testing.assert_array_equal(traj.positions_m[:, 0], [0.01 * k for k in range(20) if k % 4])
    raw = read_mcap_trajectory(path, capture_time=False)
    assert clock.offset_ns is not None
    assert abs(raw.times_s[0] * 1e9 - 1000 * expected[0] - clock.offset_ns) < 1000  # float64 seconds since 1970


def test_difference_images_pair_frames_a_projector_period_apart(tmp_path: Path) -> None:
    base = np.full((40, 60, 3), 100, np.uint8)
    brighter = base.copy()
    brighter[10:20, 10:30] = 110  # +10 grey levels in one patch

    def frame(k: int) -> np.ndarray:  # 120 FPS under a 60 Hz flicker: the phase changes every 2 frames
        return brighter if (k // 2) % 2 else base

    sampler = DifferenceSampler(image_hz=10.0, projector_hz=60.0)
    paired = [k for k in range(30) if sampler.offer(round(k * 1e6 / 120), frame(k)) is not None]
    assert paired == [2, 14, 26]  # one every 0.1 s, each with the frame one projector period (2 frames) later
    path = tmp_path / "images.mcap"
    rec = McapRecorder(path, image_hz=10.0, projector_hz=60.0)
    rec.start()
    for k in range(4):
        rec.offer_frame(round(k * 1e6 / 120), WALL_NS + k, frame(k))
    assert rec.close()
    assert rec.stats.images == 1
    with path.open("rb") as f:
        msgs = list(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages())
    assert len(msgs) == 1
    _, channel, message, image_msg = msgs[0]
    assert channel.topic == "/ipt/difference"
    assert message.log_time == WALL_NS + 2
    assert image_msg.format == "jpeg"
    decoded = cv2.imdecode(np.frombuffer(bytes(image_msg.data), np.uint8), cv2.IMREAD_GRAYSCALE)
    assert decoded.shape == (40, 60)
    assert abs(float(decoded[30:, 40:].mean()) - 128) < 2  # no difference: mid-grey
    assert abs(float(decoded[12:18, 12:28].mean()) - (128 + DIFFERENCE_GAIN * 10)) < 3  # frame 2 minus frame 0


def test_a_full_disk_stops_the_recording_with_one_line_and_counts_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "flight.mcap"
    (tmp_path / "flight.mcap.partial").symlink_to("/dev/full")  # every write: ENOSPC, as a full disk
    said, report = _lines()
    rec = McapRecorder(path, report=report, queue_size=100_000)  # type: ignore[arg-type]
    maker = RosMessageMaker(RosNames(), Mounting(), StampClock(lambda: WALL_NS, lambda: 0.0))
    rec.start()
    for k in range(3000):  # more than one 1 MB chunk
        rec.put(maker.frame(k, 8333 * k, 0.0, "pose", 2, _pose(k)))
    assert not rec.close(timeout_s=30.0)
    assert rec.stats.failure is not None
    assert "No space left on device" in rec.stats.failure
    assert rec.stats.lost > 0
    assert rec.stats.written + rec.stats.lost == 4 * 3000
    failures = [line for line in said if "write failed" in line]
    assert len(failures) == 1, said
    assert not path.exists()
    assert f"{rec.stats.lost} lost after it" in rec.summary()


def _run(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "run", *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=RUN_TIMEOUT_S,
    )


@pytest.mark.parametrize("where", ["missing/dir/x.mcap", "a_dir"])
def test_an_unwritable_recording_is_one_line_at_start(tmp_path: Path, where: str) -> None:
    (tmp_path / "a_dir").mkdir()
    proc = _run(tmp_path, "--source", "sim", "--max-frames", "2", "--record", where)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"ipt-receiver: error: {where}: cannot write")


@pytest.mark.slow
def test_daemon_goes_on_localising_when_the_disk_fills(short_flight: Path, tmp_path: Path) -> None:
    (tmp_path / "flight.mcap.partial").symlink_to("/dev/full")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as udp:
        udp.bind(("127.0.0.1", 0))
        udp.settimeout(0.2)
        proc = _run(
            tmp_path,
            "--source", f"video:{short_flight / VIDEO_NAME}", "--camera", str(short_flight / CAMERA_NAME),
            "--fps", "120", "--send", f"127.0.0.1:{udp.getsockname()[1]}", "--record", "flight.mcap",
        )  # fmt: skip
        packets = 0
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            try:
                udp.recv(2048)
            except TimeoutError:
                break
            packets += 1
    assert proc.returncode == 0, proc.stderr
    final = next(line for line in proc.stderr.splitlines() if "final:" in line)
    poses = int(final.split(" poses,")[0].rsplit(" ", 1)[1])
    assert packets == poses > 0  # localisation and the UDP output went on
    failures = [line for line in proc.stderr.splitlines() if "write failed" in line]
    assert len(failures) == 1, proc.stderr
    assert "No space left on device" in failures[0]
    summary = next(line for line in proc.stderr.splitlines() if "stopped by a write error" in line)
    assert summary.startswith("ipt-receiver: record: flight.mcap.partial: stopped by a write error (No space")
    assert os.path.islink(tmp_path / "flight.mcap.partial")
    assert not (tmp_path / "flight.mcap").exists()


def test_a_run_that_cannot_start_leaves_no_recording(tmp_path: Path) -> None:
    # The recording cannot be opened: the daemon stops before its first frame (after the recorder started), exit 2.
    proc = _run(tmp_path, "--source", "video:missing.mkv", "--record", "x.mcap")
    assert proc.returncode == 2, proc.stderr
    assert "missing.mkv" in proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # neither x.mcap nor x.mcap.partial
    rec = McapRecorder(tmp_path / "y.mcap")
    rec.abort()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_recording_cut_short_is_read_up_to_its_last_complete_chunk(tmp_path: Path) -> None:
    path = tmp_path / "flight.mcap"
    rec = McapRecorder(path, queue_size=10_000)  # room for all: this test is about reading, not about a slow disk
    clock = StampClock(lambda: WALL_NS, lambda: 0.0)
    maker = RosMessageMaker(RosNames(), Mounting(), clock)
    rec.start()
    for k in range(1500):
        items = maker.frame(k, 8333 * k, 0.0, "pose", 2, _pose(k))
        if k == 0:
            rec.set_metadata({"capture_time_offset_ns": str(clock.offset_ns)})
        rec.put(items)
    assert rec.close()
    whole = read_mcap_trajectory(path)
    assert len(whole) == 1500
    cut = tmp_path / "cut.mcap.partial"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])  # as a killed run or a full disk leaves it: no summary, half a chunk
    part = read_mcap_trajectory(cut)
    assert 0 < len(part) < len(whole)
    np.testing.assert_array_equal(part.times_s, whole.times_s[: len(part)])  # the same poses, capture clock
    np.testing.assert_array_equal(part.positions_m, whole.positions_m[: len(part)])
