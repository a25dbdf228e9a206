"""The receiver daemon end to end: real subprocesses, real loopback UDP, a simulated flight as the camera."""

from __future__ import annotations

import asyncio
import contextlib
import io
import re
import signal
import socket
import sys
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from waiting import loop_turns, until

from ipt.config.models import ConfigError, PipelineConfig, load_arena_config, shipped_config_path
from ipt.config.receiver import ReceiverConfig, load_receiver_config, read_auth_key, with_overrides
from ipt.protocol import QualityFlags, decode_pose
from ipt.receiver.capture import (
    CapturedFrame,
    CaptureError,
    CaptureThread,
    FrameQueue,
    Pacer,
    VideoCapture,
)
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.daemon import ReceiverOptions, load_setup, run_daemon
from ipt.receiver.outputs.udp import PacketMaker, UdpPoseSender
from ipt.receiver.replay import replay
from ipt.runtime import SteppedClock
from ipt.sender.content import GeneratedScene
from ipt.sim.config import SimConfig
from ipt.sim.run import CAMERA_NAME, TRUTH_NAME, VIDEO_NAME, simulate_to_folder
from ipt.tagmap import grid_tag_map
from ipt.tum import read_tum

FPS = 120
RUN_TIMEOUT_S = 60.0
"""Upper bound on any daemon run in these tests (they take a few seconds)."""


@pytest.fixture(scope="session")
def sim_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.5 s (60 frames at 120 FPS) of the smooth simulated flight (these tests check the daemon's mechanics)."""
    out = tmp_path_factory.mktemp("flight")
    arena = load_arena_config(shipped_config_path("arena.yaml"))
    scene = GeneratedScene(arena.projector.width_px, arena.projector.height_px, seed=0)
    simulate_to_folder(arena, SimConfig.smooth(), scene, out, 0.5, progress=None)
    return out


# --- helpers ---------------------------------------------------------------------------------------


class _Collector(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.packets: list[bytes] = []
        self.arrived = asyncio.Event()

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self.packets.append(data)
        self.arrived.set()


@contextlib.asynccontextmanager
async def _udp_listener() -> AsyncIterator[tuple[int, _Collector]]:
    """A UDP socket bound on loopback (an ephemeral port) collecting every datagram."""
    loop = asyncio.get_running_loop()
    transport, protocol = await loop.create_datagram_endpoint(_Collector, local_addr=("127.0.0.1", 0))
    try:
        yield transport.get_extra_info("sockname")[1], protocol
    finally:
        transport.close()


def _dead_port() -> int:
    """A loopback UDP port nobody listens on (bound once to pick it, then released)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


def _daemon_args(*args: str) -> list[str]:
    return [sys.executable, "-m", "ipt.receiver.cli", "run", *args]


async def _run_daemon(*args: str, cwd: Path) -> tuple[int, str]:
    """Run ``ipt-receiver run ARGS`` to completion; (exit code, stderr)."""
    proc = await asyncio.create_subprocess_exec(
        *_daemon_args(*args),
        cwd=cwd,
        stdin=asyncio.subprocess.DEVNULL,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        _, err = await asyncio.wait_for(proc.communicate(), RUN_TIMEOUT_S)
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert proc.returncode is not None
    return proc.returncode, err.decode()


def _final_line(stderr: str) -> str:
    finals = [line for line in stderr.splitlines() if line.startswith("ipt-receiver: final:")]
    assert len(finals) == 1, stderr
    return finals[0]


def _number(line: str, pattern: str) -> int:
    """The integer captured by ``pattern`` (e.g. ``r"(\\d+) poses"``) in a stats line."""
    m = re.search(pattern, line)
    assert m is not None, f"no {pattern!r} in {line!r}"
    return int(m.group(1))


# --- (a) a recording through the daemon matches the replay and the ground truth ---------------------


@pytest.mark.slow
@pytest.mark.asyncio
async def test_video_poses_arrive_in_order_and_match_truth(sim_video: Path, tmp_path: Path) -> None:
    async with _udp_listener() as (port, listener):
        code, stderr = await _run_daemon(
            "--source",
            f"video:{sim_video / VIDEO_NAME}",
            "--camera",
            str(sim_video / CAMERA_NAME),
            "--fps",
            str(FPS),
            "--send",
            f"127.0.0.1:{port}",
            "--vehicle-id",
            "7",
            cwd=tmp_path,
        )
        assert code == 0, stderr
        final = _final_line(stderr)
        sent = _number(final, r"(\d+) poses,")
        await until(lambda: len(listener.packets) >= sent, what="the datagrams the kernel already holds read")
    assert "send errors 0," in final

    packets = [decode_pose(p) for p in listener.packets]
    assert packets, stderr
    assert _number(final, r"(\d+) poses,") == len(packets)
    assert [p.seq for p in packets] == list(range(len(packets)))
    assert {p.vehicle_id for p in packets} == {7}

    truth = read_tum(sim_video / TRUTH_NAME)
    frames, errors_m = [], []
    for p in packets:
        k = round(p.capture_time_us * FPS / 1e6)
        assert p.capture_time_us == round(k / FPS * 1e6)
        assert 0 <= k < len(truth)
        assert truth.times_s[k] == pytest.approx(p.capture_time_us * 1e-6, abs=1e-6)  # TUM keeps µs
        errors_m.append(float(np.linalg.norm(np.asarray(p.position_m) - truth.positions_m[k])))
        frames.append(k)
    assert frames == sorted(set(frames)), "packets must leave in capture order, once per frame"
    # Every pose the daemon sends is within 30 mm of the truth at its capture time (the doubtful ones
    # are rejected, not sent), and the typical one within 10 mm.
    assert max(errors_m) < 0.030, f"worst packet {1e3 * max(errors_m):.1f} mm off"
    assert float(np.median(errors_m)) < 0.010

    # The daemon is the replay, live: the same poses from the same frames (±2 % in number).
    arena = load_arena_config(shipped_config_path("arena.yaml"))
    summary = replay(
        arena,
        grid_tag_map(arena),
        sim_video / CAMERA_NAME,
        sim_video / VIDEO_NAME,
        tmp_path / "replay.tum",
        FPS,
        PipelineConfig(),
        progress=None,
    )
    assert abs(len(packets) - summary.poses) <= max(1, 0.02 * summary.poses)
    replayed = read_tum(tmp_path / "replay.tum")
    by_frame = {round(t * FPS): pos for t, pos in zip(replayed.times_s, replayed.positions_m, strict=True)}
    common = [(k, p) for k, p in zip(frames, packets, strict=True) if k in by_frame]
    assert len(common) >= 0.98 * len(packets)
    for k, p in common:
        np.testing.assert_allclose(p.position_m, by_frame[k], atol=2e-6, err_msg=f"frame {k}")


# --- (b) SIGTERM: prompt, clean exit with a final stats line --------------------------------------------


@pytest.mark.slow
@pytest.mark.asyncio
async def test_sigterm_exits_zero_within_a_second_with_final_stats(tmp_path: Path) -> None:
    async with _udp_listener() as (port, listener):
        proc = await asyncio.create_subprocess_exec(
            *_daemon_args("--source", "sim", "--realtime", "--send", f"127.0.0.1:{port}"),
            cwd=tmp_path,
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE,
        )
        assert proc.stderr is not None
        try:
            first = await asyncio.wait_for(proc.stderr.readline(), RUN_TIMEOUT_S)
            assert b"running" in first, first
            await asyncio.wait_for(listener.arrived.wait(), RUN_TIMEOUT_S)  # poses are flowing
            sent = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            code = await asyncio.wait_for(proc.wait(), 5.0)
            took = time.monotonic() - sent
            rest = (await proc.stderr.read()).decode()
        finally:
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
    assert code == 0, rest
    assert took < 1.0, f"took {took:.2f} s to exit"
    final = _final_line(rest)
    assert _number(final, r"(\d+) poses,") >= 1
    assert "latency p50" in final


# --- (c) an unreachable target is counted, not fatal ---------------------------------------------------


@pytest.mark.slow
@pytest.mark.asyncio
async def test_send_errors_are_counted_not_fatal(sim_video: Path, tmp_path: Path) -> None:
    dead = _dead_port()
    async with _udp_listener() as (port, listener):
        code, stderr = await _run_daemon(
            "--source",
            f"video:{sim_video / VIDEO_NAME}",
            "--camera",
            str(sim_video / CAMERA_NAME),
            "--fps",
            str(FPS),
            "--max-frames",
            "12",
            "--send",
            f"127.0.0.1:{dead}",
            "--send",
            f"127.0.0.1:{port}",
            cwd=tmp_path,
        )
        assert code == 0, stderr
        final = _final_line(stderr)
        sent = _number(final, r"(\d+) poses,")
        await until(lambda: len(listener.packets) >= sent, what="the datagrams the kernel already holds read")
    assert final.startswith("ipt-receiver: final: 12 frames (12 captured)"), final
    assert _number(final, r"send errors (\d+)") >= 1, final  # ECONNREFUSED from the dead port
    poses = _number(final, r"(\d+) poses,")
    assert poses >= 5
    assert len(listener.packets) == poses  # the live target got every pose
    assert "Connection refused" in stderr


def test_bad_config_is_one_line_exit_2(tmp_path: Path) -> None:
    import subprocess

    bad = tmp_path / "receiver.yaml"
    bad.write_text("arena: arena.yaml\ncamera: camera.yaml\nsend: [nowhere]\n", encoding="utf-8")
    done = subprocess.run(
        _daemon_args("--config", str(bad)), capture_output=True, text=True, timeout=RUN_TIMEOUT_S, check=False
    )
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1, done.stderr
    assert "HOST:PORT" in done.stderr


# --- (d) queue policy and capture thread, in process --------------------------------------------------


@pytest.mark.asyncio
async def test_newest_wins_queue_drops_the_oldest_and_counts() -> None:
    q: FrameQueue[int] = FrameQueue(2)
    assert q.put_newest(1) is None
    assert q.put_newest(2) is None
    assert q.put_newest(3) == 1  # full: the oldest goes
    assert q.put_newest(4) == 2
    assert q.dropped == 2
    assert [await q.get(), await q.get()] == [3, 4]
    q.put_newest(5)
    q.finish()
    assert await q.get() == 5  # what was queued before the end still comes out
    assert await q.get() is None
    assert q.put_newest(6) == 6  # after the end: discarded, not counted as a drop
    assert q.dropped == 2


@pytest.mark.asyncio
async def test_waiting_queue_blocks_the_reader_and_drops_nothing() -> None:
    q: FrameQueue[int] = FrameQueue(1)
    assert await q.put(1)
    blocked = asyncio.ensure_future(q.put(2))
    await loop_turns()
    assert not blocked.done()
    assert await q.get() == 1
    assert await asyncio.wait_for(blocked, 1.0)
    assert await q.get() == 2
    assert q.dropped == 0
    assert await q.put(3)
    late = asyncio.ensure_future(q.put(4))
    await loop_turns()
    q.finish()  # the end wakes a waiting reader thread, whose frame is then not taken
    assert await asyncio.wait_for(late, 1.0) is False
    assert await q.get() == 3
    assert await q.get() is None


def test_pacer_sleeps_until_each_frame_is_due() -> None:
    now = [100.0]
    slept: list[float] = []

    def sleep(s: float) -> None:
        slept.append(s)
        now[0] += s

    pacer = Pacer(10.0, clock=lambda: now[0], sleep=sleep)
    pacer.wait(5)  # the first frame sets the origin
    now[0] += 0.03
    pacer.wait(6)  # due 0.1 s after frame 5
    now[0] += 0.5
    pacer.wait(7)  # late: no sleep
    assert slept == pytest.approx([0.07])


def test_realtime_video_is_paced_by_the_injected_clock(sim_video: Path) -> None:
    now = [0.0]

    def sleep(s: float) -> None:
        now[0] += s

    cap = VideoCapture(sim_video / VIDEO_NAME, 40.0, True, clock=lambda: now[0], sleep=sleep)
    cap.open()
    try:
        frames = [cap.read() for _ in range(3)]
    finally:
        cap.close()
    assert cap.live
    assert [f.index for f in frames if f is not None] == [0, 1, 2]
    assert [f.capture_time_us for f in frames if f is not None] == [0, 25_000, 50_000]
    assert [f.grabbed_s for f in frames if f is not None] == pytest.approx([0.0, 0.025, 0.05])


class _FlakySource:
    """A live source that fails once, after two frames."""

    name = "flaky"
    live = True
    retry_open = True

    def __init__(self) -> None:
        self.reads = 0
        self.opens = 0

    def open(self) -> None:
        self.opens += 1

    def read(self) -> CapturedFrame | None:
        self.reads += 1
        if self.reads == 3:
            raise CaptureError("camera unplugged")
        image: npt.NDArray[np.uint8] = np.zeros((2, 2, 3), np.uint8)
        return CapturedFrame(self.reads, self.reads, image)

    def close(self) -> None:
        pass


@pytest.mark.asyncio
async def test_failing_source_is_reported_and_reopened() -> None:
    q: FrameQueue[CapturedFrame] = FrameQueue(2)
    report = io.StringIO()
    source = _FlakySource()
    thread = CaptureThread(source, q, asyncio.get_running_loop(), max_frames=6, report=report)
    thread.start()
    got = []
    while (frame := await asyncio.wait_for(q.get(), 5.0)) is not None:
        got.append(frame.index)
    assert thread.join(1.0)
    assert thread.failures == 1
    assert source.opens == 2
    assert thread.frames == 6
    assert len(got) + q.dropped == 6
    assert got == sorted(got)
    assert "camera unplugged" in report.getvalue()
    assert "reopening" in report.getvalue()


# --- outputs and settings, in process ------------------------------------------------------------------


def _pose() -> PoseEstimate:
    return PoseEstimate(np.array([0.1, -0.2, 0.8]), np.diag([1.0, -1.0, -1.0]), (3, 4, 12), 0.42)


def test_packets_count_up_wrap_and_carry_the_pose() -> None:
    key = b"k" * 16
    maker = PacketMaker(5, key, first_seq=2**32 - 1)
    first = decode_pose(maker.encode(_pose(), 1234), key)
    second = decode_pose(maker.encode(_pose(), 5678), key)
    assert (first.seq, second.seq) == (2**32 - 1, 0)
    assert first.flags & QualityFlags.AUTHENTICATED
    assert first.vehicle_id == 5
    assert first.capture_time_us == 1234
    assert first.num_tags == 3
    assert first.position_m == pytest.approx((0.1, -0.2, 0.8))
    assert first.reprojection_rms_px == pytest.approx(0.42)


@pytest.mark.asyncio
async def test_sender_counts_refused_datagrams_and_keeps_sending() -> None:
    async with _udp_listener() as (port, listener):
        sender = UdpPoseSender([("127.0.0.1", _dead_port()), ("127.0.0.1", port)])
        async with sender:
            for k in range(1, 6):
                sender.send(b"x" * 112)

                def received(count: int = k) -> bool:
                    return len(listener.packets) >= count

                # The live target has it, and the dead port's ICMP error is back before the next send.
                await until(received, what=f"datagram {k} received")
        await until(lambda: len(listener.packets) == 5, what="every datagram received")
    assert sender.errors >= 1
    assert len(listener.packets) == 5


def test_receiver_config_resolves_paths_against_its_folder(tmp_path: Path) -> None:
    (tmp_path / "key").write_bytes(b"0123456789abcdef\n")
    (tmp_path / "key").chmod(0o600)  # a key file others can read is refused
    path = tmp_path / "receiver.yaml"
    path.write_text(
        "arena: a.yaml\ncamera: /abs/camera.yaml\nsource: video:rec/f.mkv\nauth_key_file: key\n"
        "send: ['127.0.0.1:1', '[::1]:2']\n",
        encoding="utf-8",
    )
    cfg = load_receiver_config(path)
    assert cfg.arena == tmp_path / "a.yaml"
    assert cfg.camera == Path("/abs/camera.yaml")
    assert cfg.source == f"video:{tmp_path / 'rec/f.mkv'}"
    assert cfg.send_targets == [("127.0.0.1", 1), ("::1", 2)]
    assert cfg.auth_key_file is not None
    assert read_auth_key(cfg.auth_key_file) == b"0123456789abcdef"
    (tmp_path / "key").write_bytes(b"short")
    with pytest.raises(ConfigError, match="at least 16"):
        read_auth_key(cfg.auth_key_file)
    with pytest.raises(ConfigError, match="source"):
        with_overrides(cfg, source="camera")


# --- the daemon's clock is passed in: statistics on stepped time, no sleeping ------------------------


class _Lines(io.StringIO):
    """A report that tells the test each line as it is written (on the event loop's thread)."""

    def __init__(self) -> None:
        super().__init__()
        self.lines: asyncio.Queue[str] = asyncio.Queue()

    def write(self, text: str) -> int:
        for line in text.splitlines():
            self.lines.put_nowait(line)
        return super().write(text)


class _QuietCamera:
    """A live camera that opens and then shows nothing until the capture thread is stopped."""

    name = "quiet"
    live = True
    retry_open = False

    def __init__(self, stop: threading.Event) -> None:
        self.stop = stop

    def open(self) -> None:
        pass

    def read(self) -> CapturedFrame | None:
        self.stop.wait(10.0)  # ends at once when the daemon stops capture
        return None

    def close(self) -> None:
        pass


@pytest.mark.asyncio
async def test_interval_lines_and_totals_follow_the_injected_clock() -> None:
    """With a stepped clock the interval line comes when the clock says, and the totals count its seconds."""
    cfg = ReceiverConfig(
        arena=shipped_config_path("arena.yaml"),
        camera=shipped_config_path("camera.yaml"),
        send=["127.0.0.1:9"],
        stats_interval_s=5.0,
    )
    clock, report, stop, capture_stop = SteppedClock(100.0), _Lines(), asyncio.Event(), threading.Event()
    options = ReceiverOptions(
        stop=stop,
        install_signal_handlers=False,
        source=_QuietCamera(capture_stop),
        capture_stop=capture_stop,
        stats_out=report,
        clock=clock,
    )
    run = asyncio.ensure_future(run_daemon(load_setup(cfg), options))
    running = await asyncio.wait_for(report.lines.get(), 60.0)
    assert "running: quiet (live)" in running
    await asyncio.wait_for(clock.wait_for_sleepers(1), 10.0)  # the statistics task waits for the clock
    clock.advance(4.5)  # not yet an interval: its wait is still on
    assert clock.sleepers == 1
    clock.advance(0.5)
    line = await asyncio.wait_for(report.lines.get(), 10.0)
    assert line.startswith("ipt-receiver: 0.0 frames/s, 0.0 poses/s, yield 0.0 %"), line
    assert report.lines.empty()
    clock.advance(2.5)
    stop.set()
    stats = await asyncio.wait_for(run, 10.0)
    assert stats.seconds == 7.5  # exactly: the clock's, not the wall's
    assert " in 7.50 s: " in stats.line()
    assert not stats.capture_running
