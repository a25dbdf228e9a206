"""The flight recorder (``ipt-receiver run --record-frames``) and its replay: the live run's poses, bit for bit,
a bounded and fault-tolerant recording, and records that stay readable up to a fault."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import resource
import socket
import subprocess
import sys
import threading
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ipt.config.models import shipped_config_path
from ipt.config.receiver import load_receiver_config, with_overrides
from ipt.protocol import decode_pose
from ipt.receiver.capture import CapturedFrame, VideoCapture
from ipt.receiver.capture.framelog import (
    FRAMES_NAME,
    KIND_FINISH,
    KIND_FRAME,
    MAGIC,
    RECORD_V1,
    FrameLog,
    FrameLogError,
    FrameLogWriter,
    start_frame_log,
)
from ipt.receiver.core.pipeline import FrameResult
from ipt.receiver.daemon import load_setup, run_daemon
from ipt.receiver.replay import exact_tum_line, replay_frame_log
from ipt.sim.run import CAMERA_NAME, VIDEO_NAME
from ipt.videoio import open_frames

FRAMES = 24
"""Frames of the short flight each daemon run takes (enough for poses, short on 2 busy cores)."""
TIMEOUT_S = 120.0
LIVE_AHEAD = 12
"""How far (frames) the live camera of the replay test runs ahead of the daemon's newest result: more than the daemon
holds (a run of three in the worker, three in the queue, a few waiting for later partners), so it drops frames."""


def _receive_all(sock: socket.socket) -> list[bytes]:
    """Every datagram the kernel holds for ``sock`` (non-blocking)."""
    sock.setblocking(False)
    out: list[bytes] = []
    with contextlib.suppress(BlockingIOError):
        while True:
            out.append(sock.recv(65536))
    return out


def _daemon(flight: Path, *extra: str, cwd: Path, port: int, limit_bytes: int | None = None) -> tuple[int, str]:
    """``ipt-receiver run`` over the first :data:`FRAMES` frames of the flight, packets to 127.0.0.1:port."""

    def limit() -> None:  # a small "disk": a file-size limit in the child only (Python ignores SIGXFSZ)
        if limit_bytes is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    args = ["--source", f"video:{flight / VIDEO_NAME}", "--camera", str(flight / CAMERA_NAME), "--fps", "120"]
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "ipt.receiver.cli",
            "run",
            *args,
            "--send",
            f"127.0.0.1:{port}",
            "--max-frames",
            str(FRAMES),
            *extra,
        ],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        preexec_fn=limit if limit_bytes is not None else None,
        check=False,
    )
    return proc.returncode, proc.stderr


def _exact_lines(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines(keepends=True) if not line.startswith("#")]


@pytest.mark.slow
def test_replay_of_recorded_frames_gives_the_packets_the_live_run_sent(short_flight: Path, tmp_path: Path) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        code, err = _daemon(short_flight, "--record-frames", "rec", cwd=tmp_path, port=sock.getsockname()[1])
        packets = [decode_pose(p) for p in _receive_all(sock)]
    assert code == 0, err
    assert ", map hash sha256:" in err
    assert f"frame recording: {FRAMES} frames" in err
    assert len(packets) >= FRAMES // 2, err

    replayed = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "replay", "--frames", "rec", "--output", "poses.tum"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )
    assert replayed.returncode == 0, replayed.stderr
    sent = [exact_tum_line(p.capture_time_us, p.position_m, p.quat_wxyz) for p in packets]
    assert _exact_lines(tmp_path / "poses.tum") == sent  # every float64 equal (repr), same order, same count


class _JitteredCamera:
    """The flight's frames with a camera's irregular capture times and a frame lost before capture (a gap in the
    numbers): the replay must use what was recorded, not ``k / fps``. With ``ahead``, a live camera faster than any
    pipeline by construction: its frames are decoded before the run, and it hands each over at once unless it is
    more than ``ahead`` frames past the newest result (:meth:`came_out`); so the daemon must drop frames however
    busy the machine is (paced by its decoding, the pipeline kept up with it now and then)."""

    retry_open, name = False, "jittered"

    def __init__(self, video: VideoCapture, live: bool = False, frames: int = FRAMES, ahead: int | None = None) -> None:
        self.video, self.live, self.limit, self.ahead = video, live, frames, ahead
        self._decoded: list[CapturedFrame] = []
        self._newest = -1
        self._progress = threading.Condition()

    def open(self) -> None:
        self.video.open()
        while self.ahead is not None and len(self._decoded) < self.limit and (frame := self.video.read()) is not None:
            self._decoded.append(frame)

    def close(self) -> None:
        self.video.close()

    def came_out(self, index: int) -> None:
        """The result of frame ``index`` came out of the daemon (its event loop's thread)."""
        with self._progress:
            self._newest = max(self._newest, index)
            self._progress.notify_all()

    def read(self) -> CapturedFrame | None:
        if self.ahead is None:
            frame = self.video.read()
        else:
            frame = self._decoded.pop(0) if self._decoded else None
        if frame is None or frame.index >= self.limit:
            return None
        k = frame.index + (frame.index >= 9)  # frame 9 was "lost": numbers 0..8, 10, 11, ...
        if self.ahead is not None:
            with self._progress:  # (bounded: a daemon that stopped taking frames does not hang the test)
                self._progress.wait_for(lambda: k - self._newest <= self.ahead, timeout=TIMEOUT_S / 4)
        t_us = 5_000_000 + round(k * 1e6 / 120) + (137 if k % 3 == 1 else -61 if k % 3 == 2 else 0)
        return replace(frame, index=k, capture_time_us=t_us)


@pytest.mark.slow
@pytest.mark.parametrize("live_source", [False, True], ids=["recording", "live-with-drops"])
def test_replay_uses_recorded_numbers_and_times_not_k_over_fps(
    short_flight: Path, tmp_path: Path, live_source: bool
) -> None:
    """Also from a live source read faster than the pipeline keeps up (newest wins, frames dropped): the frames
    the pipeline took and the points where the daemon finished early are replayed to the same poses."""
    cfg = load_receiver_config(shipped_config_path("receiver.yaml"))
    cfg = with_overrides(cfg, camera=short_flight / CAMERA_NAME, send=["127.0.0.1:9"])
    said: list[str] = []
    log = start_frame_log(cfg, tmp_path / "rec", said.append, max_mb=1000, max_s=60)
    video = VideoCapture(short_flight / VIDEO_NAME, 120.0, False, grey=cfg.pipeline.luminance_only)
    ahead = LIVE_AHEAD if live_source else None
    source = _JitteredCamera(video, live=live_source, frames=60 if live_source else FRAMES, ahead=ahead)
    live: list[str] = []
    drops = 0

    def on_result(frame: CapturedFrame, result: FrameResult | None, sent: int) -> None:
        source.came_out(frame.index)
        if result is not None and result.pose is not None and sent:
            live.append(exact_tum_line(frame.capture_time_us, result.pose.position_m, result.pose.quat_wxyz))

    async def main() -> None:
        with open(os.devnull, "w") as quiet:
            stats = await run_daemon(
                load_setup(cfg),
                install_signal_handlers=False,
                source=source,
                on_result=on_result,
                stats_out=quiet,
                frame_log=log,
            )
        nonlocal drops
        drops = stats.drops

    asyncio.run(main())
    log.close()
    assert live, said
    summary = replay_frame_log(tmp_path / "rec", tmp_path / "poses.tum", progress=None)
    lines = _exact_lines(tmp_path / "poses.tum")
    kinds = [e.kind for e in FrameLog(tmp_path / "rec").events()]
    if live_source:
        assert drops > 0, "the pipeline kept up with an unpaced source: nothing was dropped"
        assert KIND_FINISH in kinds
        assert summary.frames == kinds.count(KIND_FRAME) == 60 - drops
    else:
        assert summary.frames == FRAMES
    assert lines == live
    assert all(line.startswith("5.") for line in lines)  # the camera's times (from 5 s), not k / fps from zero


def _frame(k: int, value: int = 0) -> CapturedFrame:
    image = (np.arange(360 * 640, dtype=np.uint32).reshape(360, 640) * 7 + k + value).astype(np.uint8)
    return CapturedFrame(k, 1000 + 8333 * k, image)


def _writer(folder: Path, said: list[str], **kw: float) -> FrameLogWriter:
    camera = shipped_config_path("camera.yaml")
    return FrameLogWriter(folder, {"note": "test"}, camera, say=said.append, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize("codec", ["raw", "zstd"])
def test_frames_come_back_losslessly_with_their_marks(tmp_path: Path, codec: str) -> None:
    said: list[str] = []
    w = FrameLogWriter(tmp_path / "rec", {}, shipped_config_path("camera.yaml"), say=said.append, codec=codec)
    frames = [_frame(k) for k in range(5)]
    rgb = CapturedFrame(7, 99_000, np.dstack([frames[0].image, frames[1].image, frames[2].image]))
    for f in frames[:3]:
        w.add(f)
    w.finish_before(77_777)
    for f in [*frames[3:], rgb]:
        w.add(f)
    w.close()
    log = FrameLog(tmp_path / "rec")
    events = list(log.events())
    assert log.problem is None
    assert [e.kind for e in events] == [KIND_FRAME] * 3 + [KIND_FINISH] + [KIND_FRAME] * 3
    assert events[3].capture_time_us == 77_777
    got = [e for e in events if e.kind == KIND_FRAME]
    for e, f in zip(got, [*frames, rgb], strict=True):
        assert (e.index, e.capture_time_us) == (f.index, f.capture_time_us)
        assert e.image is not None
        assert e.image.dtype == np.uint8
        np.testing.assert_array_equal(e.image, f.image)


def test_a_live_frames_wait_comes_back_with_it_and_a_version_1_recording_still_reads(tmp_path: Path) -> None:
    """Issue 29 (stop 59): the pipeline's live rule reads each frame's wait before the hand-over, so a replay needs it
    to give the poses the live run sent; a recording's frame has none. A version 1 recording (no wait in its
    records) still reads, its frames without one: the pipeline then treats them as it did when they were made."""
    said: list[str] = []
    w = FrameLogWriter(tmp_path / "rec", {}, shipped_config_path("camera.yaml"), say=said.append, codec="raw")
    for k, waited_us in enumerate((None, 0, 12_345, 2**40)):
        w.add(_frame(k), waited_us)
    w.close()
    assert [e.waited_us for e in FrameLog(tmp_path / "rec").events()] == [None, 0, 12_345, 2**40]
    old = tmp_path / "v1"
    old.mkdir()
    meta = json.loads((tmp_path / "rec" / "recording.json").read_text())
    (old / "recording.json").write_text(json.dumps({**meta, "version": 1}))
    image = _frame(3).image
    head = RECORD_V1.pack(MAGIC, KIND_FRAME, 0, 1, 3, 1234, 640, 360, image.size, zlib.crc32(image.tobytes()))
    (old / "frames.bin").write_bytes(head + image.tobytes())
    (events,) = list(FrameLog(old).events())
    assert (events.index, events.capture_time_us, events.waited_us) == (3, 1234, None)
    np.testing.assert_array_equal(events.image, image)


def test_size_bound_is_said_once_and_stops_recording(tmp_path: Path) -> None:
    said: list[str] = []
    w = _writer(tmp_path / "rec", said, max_mb=0.5, codec="raw")  # type: ignore[arg-type]
    for k in range(6):  # 230 kB each: two fit in 0.5 MB
        w.add(_frame(k))
    w.close()
    assert [s for s in said if "bound of" in s] == [
        "frame recording: reached its bound of 0.5 MB at frame 2; recording stops, localisation goes on"
    ]
    assert [e.index for e in FrameLog(tmp_path / "rec").events()] == [0, 1]


def test_duration_bound_stops_recording(tmp_path: Path) -> None:
    said: list[str] = []
    w = _writer(tmp_path / "rec", said, max_s=0.02)  # frames 8.333 ms apart: 0, 1, 2 are within 20 ms
    for k in range(5):
        w.add(_frame(k))
    w.close()
    assert sum("bound of 0.02 s at frame 3" in s for s in said) == 1
    assert [e.index for e in FrameLog(tmp_path / "rec").events()] == [0, 1, 2]


def test_a_cut_file_reads_up_to_the_cut(tmp_path: Path) -> None:
    said: list[str] = []
    w = _writer(tmp_path / "rec", said)
    for k in range(4):
        w.add(_frame(k))
    w.close()
    path = tmp_path / "rec" / FRAMES_NAME
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])  # a power cut in the last record
    log = FrameLog(tmp_path / "rec")
    assert [e.index for e in log.events()] == [0, 1, 2]
    assert log.problem is not None
    assert "record 3" in log.problem


def test_a_folder_with_files_is_refused_not_overwritten(tmp_path: Path) -> None:
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "keep.txt").write_text("mine")
    with pytest.raises(FrameLogError, match="not empty"):
        _writer(tmp_path / "rec", [])
    assert (tmp_path / "rec" / "keep.txt").read_text() == "mine"


def test_cli_refuses_a_used_folder_in_one_line(tmp_path: Path) -> None:
    (tmp_path / "rec").mkdir()
    (tmp_path / "rec" / "x").write_text("x")
    proc = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "run", "--record-frames", "rec", "--max-frames", "1"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().endswith(
        "--record-frames rec: the folder is not empty (a recording is never overwritten)"
    )
    assert "Traceback" not in proc.stderr


@pytest.mark.slow
def test_full_disk_while_recording_one_line_localisation_goes_on(short_flight: Path, tmp_path: Path) -> None:
    """A file-size limit of 1 MB in the daemon's process stands for a full disk (no system change)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        code, err = _daemon(
            short_flight, "--record-frames", "rec", cwd=tmp_path, port=sock.getsockname()[1], limit_bytes=1_000_000
        )
        packets = _receive_all(sock)
    assert code == 0, err
    faults = [line for line in err.splitlines() if "File too large" in line]
    assert len(faults) == 1, err
    assert "recording stops, localisation goes on" in faults[0]
    assert "Traceback" not in err
    final = next(line for line in err.splitlines() if line.startswith("ipt-receiver: final:"))
    assert f"{FRAMES} frames ({FRAMES} captured)" in final
    assert packets
    assert f"{len(packets)} poses" in final
    log = FrameLog(tmp_path / "rec")
    kept = [e for e in log.events() if e.kind == KIND_FRAME]
    assert log.problem is None  # cut back to the last whole record
    assert 2 <= len(kept) < FRAMES
    assert os.path.getsize(tmp_path / "rec" / FRAMES_NAME) <= 1_000_000
    with open_frames(short_flight / VIDEO_NAME, grey=True) as video:
        for e, original in zip(kept, video, strict=False):
            assert e.image is not None
            np.testing.assert_array_equal(e.image, original)


def test_a_run_that_never_got_going_leaves_no_recording(tmp_path: Path) -> None:
    """A send target that cannot be opened stops the daemon before its first frame: the folder is not left
    behind half made (a second run with the same DIR would be refused)."""
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "ipt.receiver.cli",
            "run",
            "--record-frames",
            "rec",
            "--send",
            "255.255.255.255:9",
            "--max-frames",
            "1",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        check=False,
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "rec").exists(), proc.stderr
    assert len(proc.stderr.splitlines()) == 1, proc.stderr  # the error, and nothing about the recording
