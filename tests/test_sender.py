"""The sender: the frame clock and its file output, the UDP listener under a flood, the AR overlay, the sinks."""

from __future__ import annotations

import contextlib
import math
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from waiting import until, wait_until

from ipt.config.models import ArenaConfig, load_arena_config
from ipt.geometry import R_BODY_CAM_DOWNWARD, quat_wxyz_from_matrix, rot_z
from ipt.protocol import PosePacket, QualityFlags, encode_pose
from ipt.sender.colour import CODE_TO_LINEAR, LUMINANCE_WEIGHTS, code_to_linear, lstar
from ipt.sender.content import ContentError, GeneratedScene
from ipt.sender.display import DisplayError, FileSink, NullSink, PresentClock, WindowSink, make_sink
from ipt.sender.modulator import IptModulator
from ipt.sender.overlay import PALETTE, ArOverlay, heading_rad
from ipt.sender.server import SenderError, parse_listen, run_sender
from ipt.tagmap import grid_tag_map
from ipt.videoio import FfvWriter, open_frames

U8 = npt.NDArray[np.uint8]

TINY_ARENA = """\
projector: {width_px: 320, height_px: 288, rate_hz: 60}
screen: {width_m: 1.0, height_m: 0.9}
tag_map: {rows: 2, cols: 2, tag_size_px: 64}
modulation: {delta_l: 8, input_rate_hz: 30}
"""
W, H = 320, 288
DELTA_L = 8
GREY = (128, 128, 128)

Quat = tuple[float, float, float, float]


def _quat(r: npt.NDArray[np.float64]) -> Quat:
    w, x, y, z = (float(v) for v in quat_wxyz_from_matrix(r))
    return w, x, y, z


# Downward camera, body aligned with the arena: image-up is the nose, arena +x.
Q_DOWN_EAST = _quat(R_BODY_CAM_DOWNWARD)
Q_DOWN_NORTH = _quat(rot_z(math.pi / 2) @ R_BODY_CAM_DOWNWARD)
# Camera looking along arena +x with image-up straight up: no heading on the floor.
Q_LEVEL = _quat(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]))


@pytest.fixture
def arena_yaml(tmp_path: Path) -> Path:
    path = tmp_path / "arena.yaml"
    path.write_text(TINY_ARENA, encoding="utf-8")
    return path


@pytest.fixture
def arena(arena_yaml: Path) -> ArenaConfig:
    return load_arena_config(arena_yaml)


def _pose(vehicle: int, seq: int, xyz: tuple[float, float, float], quat: Quat = Q_DOWN_EAST) -> PosePacket:
    return PosePacket(vehicle_id=vehicle, seq=seq, capture_time_us=seq * 10_000, position_m=xyz, quat_wxyz=quat)


def _l8(rgb: U8) -> npt.NDArray[np.float64]:
    """8-bit CIELAB L (0..255) of an 8-bit sRGB image, as OpenCV converts it."""
    return np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2Lab)[:, :, 0], dtype=np.float64)


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "ipt.sender.cli", *args]


# --- (a) the frame clock, through the command line, into a file -------------------------------------


def test_file_sink_writes_the_modulated_frames(tmp_path: Path, arena_yaml: Path) -> None:
    colours = [(120, 130, 140), (80, 95, 90), (170, 160, 150)]  # flat frames, well apart in lightness
    small = tmp_path / "small.mkv"
    with FfvWriter(small, 160, 144, 30) as writer:  # another size than the projector: resized
        for c in colours:
            writer.write(np.full((144, 160, 3), c, np.uint8))
    out = tmp_path / "out.mkv"
    run = subprocess.run(
        _cli(
            "--config", str(arena_yaml), "--video", str(small), "--sink", "file", "--output", str(out), "--frames", "6"
        ),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    err_lines = run.stderr.strip().splitlines()
    assert sum("resized to 320x288" in line for line in err_lines) == 1
    assert re.search(r"\bmissed=0\b", err_lines[-1]), err_lines[-1]
    assert "wrote 6 frames" in run.stdout

    with open_frames(out) as source:
        frames = list(source)
    assert len(frames) == 6
    mask = grid_tag_map(load_arena_config(arena_yaml)).render_mask()
    white, black, off = mask > 0, mask < 0, mask == 0
    assert white.any()
    assert black.any()
    assert off.any()
    for i, colour in enumerate(colours):
        first, second = frames[2 * i], frames[2 * i + 1]
        c_in = code_to_linear(np.array(colour, np.uint8))
        # Both come from input frame i: their linear-light mean (what the eye sees) is the input's on the
        # tags, to within 8-bit quantisation...
        fused = (code_to_linear(first) + code_to_linear(second)) / 2
        step = float(np.max(np.diff(CODE_TO_LINEAR)[max(0, min(colour) - 8) : max(colour) + 8]))
        assert np.abs(fused[~off] - c_in).max() <= step / 2
        # ...every other input frame is much further away...
        for other in colours:
            if other != colour:
                other_in = code_to_linear(np.array(other, np.uint8))
                assert np.abs(fused[~off] - other_in).max(axis=-1).min() > 10 * step
        # ...and frame 2i carries +ΔL on white tag pixels, frame 2i+1 -ΔL (and the opposite on black): the L*
        # difference is 2ΔL in 8-bit L units.
        diff = (_lstar(first) - _lstar(second)) * 2.55
        assert np.abs(diff[white] - 2 * DELTA_L).max() <= 1.5
        assert np.abs(diff[black] + 2 * DELTA_L).max() <= 1.5
        # Untouched outside the tags, bit for bit.
        assert np.all(first[off] == colour)
        assert np.all(second[off] == colour)


def _lstar(rgb: U8) -> npt.NDArray[np.float64]:
    return lstar(code_to_linear(rgb) @ LUMINANCE_WEIGHTS)


def test_a_24_fps_video_is_retimed_and_phases_keep_alternating(tmp_path: Path, arena_yaml: Path) -> None:
    colours = [(60, 70, 80), (110, 120, 130), (160, 150, 140), (200, 190, 180)]
    video = tmp_path / "film.mkv"
    with FfvWriter(video, W, H, 24) as writer:  # 24 fps into a 60 Hz projector: 2.5 output frames each
        for c in colours:
            writer.write(np.full((H, W, 3), c, np.uint8))
    out = tmp_path / "out.mkv"
    run = subprocess.run(
        _cli(
            "--config", str(arena_yaml), "--video", str(video), "--sink", "file", "--output", str(out), "--frames", "10"
        ),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    assert "24 fps, not the arena's input_rate_hz 30" in run.stderr
    assert "2 or 3 output frames" in run.stderr
    assert "opposite phase" in run.stderr
    with open_frames(out) as source:
        frames = list(source)
    assert len(frames) == 10
    mask = grid_tag_map(load_arena_config(arena_yaml)).render_mask()
    off, white = mask == 0, mask > 0
    # Output frame j shows input frame floor(j * 24 / 60): 3, 2, 3, 2 frames of each.
    shown = [colours.index(tuple(int(v) for v in f[off][0])) for f in frames]
    assert shown == [0, 0, 0, 1, 1, 2, 2, 2, 3, 3]
    # The phase follows the output frame alone: + on white tag pixels for even j, - for odd j.
    for j, f in enumerate(frames):
        c_in = code_to_linear(np.array(colours[shown[j]], np.uint8))
        brighter = float((code_to_linear(f[white]) - c_in).mean()) > 0
        assert brighter == (j % 2 == 0), j


def test_file_sink_without_output_is_a_usage_error(arena_yaml: Path) -> None:
    run = subprocess.run(
        _cli("--config", str(arena_yaml), "--sink", "file", "--frames", "2"), capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 2
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1, run.stderr
    assert "--output" in lines[0], run.stderr


def test_bad_listen_address_and_key_file(tmp_path: Path, arena_yaml: Path) -> None:
    with pytest.raises(SenderError):
        parse_listen("127.0.0.1")
    with pytest.raises(SenderError):
        parse_listen("127.0.0.1:70000")
    assert parse_listen("[::1]:9870") == ("::1", 9870)
    short = tmp_path / "key"
    short.write_bytes(b"short\n")
    run = subprocess.run(
        _cli("--config", str(arena_yaml), "--sink", "null", "--frames", "2", "--auth-key-file", str(short)),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 2
    assert len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert "key" in run.stderr, run.stderr


# --- (b) the listener under a flood, and a clean stop on SIGTERM ---------------------------------------


def _wait_for(path: Path, pattern: str, timeout_s: float) -> re.Match[str]:
    def found() -> re.Match[str] | None:
        return re.search(pattern, path.read_text(encoding="utf-8", errors="replace"))

    with contextlib.suppress(AssertionError):  # said below, with the file
        wait_until(found, timeout_s)
    if (m := found()) is None:
        raise AssertionError(f"{pattern!r} did not appear in {path} within {timeout_s} s:\n{path.read_text()}")
    return m


def _malformed(rng: np.random.Generator, valid: bytes, k: int) -> bytes:
    kind = k % 4
    if kind == 0:  # random bytes of a random length
        return rng.integers(0, 256, int(rng.integers(0, 160)), dtype=np.uint8).tobytes()
    if kind == 1:  # a valid packet with one byte changed: bad CRC, or a bad header
        data = bytearray(valid)
        data[int(rng.integers(0, len(data)))] ^= 1 + int(rng.integers(0, 255))
        return bytes(data)
    if kind == 2:  # truncated or padded
        return valid[: int(rng.integers(0, len(valid)))] if k % 8 == 2 else valid + b"\0"
    return b"IPTL" + rng.integers(0, 256, 108, dtype=np.uint8).tobytes()  # right magic, garbage after


def _rx_queue_bytes(port: int) -> int:
    """Bytes waiting in the receive queue of the UDP socket on 127.0.0.1:``port`` (Linux's /proc/net/udp)."""
    local = f"0100007F:{port:04X}"
    for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
        fields = line.split()
        if fields[1] == local:
            return int(fields[4].split(":")[1], 16)
    return 0


def test_listener_survives_a_flood_and_stops_on_sigterm(tmp_path: Path, arena_yaml: Path) -> None:
    log = tmp_path / "stderr.txt"
    with log.open("w") as err:
        proc = subprocess.Popen(
            _cli("--config", str(arena_yaml), "--sink", "null", "--listen", "127.0.0.1:0", "--stats-every", "0.5"),
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
    try:
        port = int(_wait_for(log, r"listening for pose packets on udp 127\.0\.0\.1:(\d+)", 30).group(1))
        rng = np.random.default_rng(7)
        valid = [
            encode_pose(_pose(1, 1, (0.1, 0.2, 1.0))),
            encode_pose(_pose(2, 1, (1e300, -1e300, 0.0))),  # valid, absurdly far: must not break drawing
            encode_pose(_pose(3, 5, (0.0, 0.0, 1.0), Q_LEVEL)),
            encode_pose(_pose(1, 2, (0.12, 0.2, 1.0))),
        ]
        # The drone's packets come from an address of their own (127.0.0.2, loopback): from the flooding
        # address they would meet its per-source rate limit, empty or not depending on how fast a loaded
        # machine reads the socket, and the count below would be luck.
        with (
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock,
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as drone,
        ):
            drone.bind(("127.0.0.2", 0))
            target = ("127.0.0.1", port)
            sent_valid = 0
            for k in range(10_000):
                if k % 2500 == 0:
                    drone.sendto(valid[sent_valid], target)
                    sent_valid += 1
                sock.sendto(_malformed(rng, valid[0], k), target)
                if k % 25 == 24:  # bounded pace: the receive buffer never overflows
                    wait_until(lambda: _rx_queue_bytes(port) < 65_536, 10.0, "the sender reading its socket")
            assert sent_valid == len(valid)
        _wait_for(log, r"t=\d+\.\ds .*accepted=4 rejected=10000", 15)  # a periodic line saw them all
        wait_until(lambda: len(re.findall(r"t=\d+\.\ds frames=", log.read_text())) >= 2, 15.0, "two periodic lines")
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=10)
        stop_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = log.read_text(encoding="utf-8")
    assert rc == 0, text
    assert stop_s < 1.0, f"took {stop_s:.2f} s to stop"
    last = text.strip().splitlines()[-1]
    assert "done:" in last, last
    assert re.search(r"\bmissed=\d+\b", last), last
    accepted = int(re.search(r"accepted=(\d+)", last).group(1))  # type: ignore[union-attr]
    rejected = int(re.search(r"rejected=(\d+)", last).group(1))  # type: ignore[union-attr]
    assert accepted == 4, last
    assert rejected >= 10_000, last
    assert "error=" not in last, last
    assert "overlay_errors" not in last, last
    # It kept producing frames at the projector rate meanwhile.
    periodic = [int(m) for m in re.findall(r"t=\d+\.\ds frames=(\d+)", text)]
    assert len(periodic) >= 2
    assert periodic == sorted(periodic)
    assert periodic[-1] > periodic[0]
    assert float(re.search(r"fps=([\d.]+)", last).group(1)) > 20, last  # type: ignore[union-attr]


@pytest.mark.asyncio
async def test_authenticated_listener_counts_each_rejection(tmp_path: Path, arena: ArenaConfig) -> None:
    import asyncio

    from ipt.protocol import PacketFilter
    from ipt.sender.cli import _read_key

    key = b"ipt-test-key-0123456789abcdef"
    key_file = tmp_path / "key"
    key_file.write_bytes(key + b"\n")  # as `echo` writes it
    key_file.chmod(0o600)  # a key file others can read is refused
    assert _read_key(str(key_file)) == key

    loop = asyncio.get_running_loop()
    bound: asyncio.Future[int] = loop.create_future()
    lines: list[str] = []

    def log(line: str) -> None:
        lines.append(line)
        found = re.search(r"udp 127\.0\.0\.1:(\d+)", line)
        if found and not bound.done():
            bound.set_result(int(found.group(1)))

    ar, stop, packet_filter = ArOverlay(arena), asyncio.Event(), PacketFilter(key, [1])
    run = asyncio.create_task(
        run_sender(
            arena,
            NullSink(),
            _FlatScene(),
            listen=("127.0.0.1", 0),
            packet_filter=packet_filter,
            overlay=ar,
            log=log,
            install_signal_handlers=False,
            stop=stop,
        )
    )
    try:
        port = await asyncio.wait_for(bound, 10)
        datagrams = [
            encode_pose(_pose(1, 1, (0.1, 0.0, 1.0)), key),  # accepted
            encode_pose(_pose(1, 2, (0.1, 0.0, 1.0))),  # no tag
            encode_pose(_pose(2, 1, (0.1, 0.0, 1.0)), key),  # not an allowed vehicle
            encode_pose(_pose(1, 1, (0.1, 0.0, 1.0)), key),  # replayed
            encode_pose(_pose(1, 3, (0.1, 0.0, 1.0)), b"another-key-0123456789"),  # wrong key
        ]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            for data in datagrams:
                sock.sendto(data, ("127.0.0.1", port))
        with contextlib.suppress(AssertionError):  # the counts are checked below
            await until(lambda: sum(packet_filter.counts.values()) == len(datagrams), 5.0)
    finally:
        stop.set()
    stats = await run
    assert ar.vehicle_ids() == [1]
    expected = {"accepted": 1, "unauthenticated": 1, "unknown_vehicle": 1, "replayed": 1, "bad_auth": 1}
    assert {k: v for k, v in stats.packets.items() if v} == expected, lines[-1]


# --- (c) the AR overlay ----------------------------------------------------------------------------------


def _grey() -> U8:
    return np.full((H, W, 3), GREY, np.uint8)


def _px(ar: ArOverlay, x_m: float, y_m: float, du: float = 0.0, dv: float = 0.0) -> tuple[int, int]:
    u, v = ar.pixel_of(x_m, y_m)
    return math.floor(u + du), math.floor(v + dv)  # (column, row) of the pixel containing that point


def test_vehicle_is_drawn_at_its_arena_position(arena: ArenaConfig) -> None:
    ar = ArOverlay(arena)
    ar.update(_pose(0, 1, (0.2, -0.1, 1.0), Q_LEVEL), now_s=0.0)
    assert ar.pixel_of(0.2, -0.1) == pytest.approx((224.0, 176.0))  # 320 px per metre, centre (160, 144)
    frame = ar.draw(_grey(), now_s=0.0)
    col, row = _px(ar, 0.2, -0.1)
    assert tuple(frame[row, col]) == PALETTE[0]
    assert tuple(frame[row, col + round(ar.radius_px) + 6]) == GREY  # beyond the rim
    changed = np.argwhere(np.any(frame != GREY, axis=2))
    r = ar.radius_px
    assert changed[:, 0].min() >= row - 3 * r
    assert changed[:, 0].max() <= row + 3 * r
    assert changed[:, 1].min() >= col - 3 * r
    assert changed[:, 1].max() <= col + 4 * r
    assert len(changed) < 0.1 * W * H  # a small region only


def test_vehicle_fades_and_is_forgotten(arena: ArenaConfig) -> None:
    ar = ArOverlay(arena, fade_after_s=1.0, forget_after_s=3.0)
    ar.update(_pose(5, 1, (0.0, 0.0, 1.0), Q_LEVEL), now_s=10.0)
    col, row = _px(ar, 0.0, 0.0)
    colour = np.array(PALETTE[5], dtype=float)
    assert ar.alpha(5, 10.9) == 1.0
    assert np.array_equal(ar.draw(_grey(), now_s=10.9)[row, col], colour)
    assert ar.alpha(5, 12.0) == pytest.approx(0.5)
    half = ar.draw(_grey(), now_s=12.0)[row, col].astype(float)
    assert np.abs(half - (0.5 * colour + 0.5 * np.array(GREY))).max() <= 1.0
    assert ar.vehicle_ids() == [5]
    frame = ar.draw(_grey(), now_s=13.5)
    assert ar.vehicle_ids() == []
    assert np.array_equal(frame, _grey())
    # Heard from again: back at full strength.
    ar.update(_pose(5, 2, (0.0, 0.0, 1.0), Q_LEVEL), now_s=14.0)
    assert np.array_equal(ar.draw(_grey(), now_s=14.0)[row, col], colour)


def test_heading_arrow_points_along_image_up(arena: ArenaConfig) -> None:
    assert heading_rad(Q_DOWN_EAST) == pytest.approx(0.0, abs=1e-9)
    assert heading_rad(Q_DOWN_NORTH) == pytest.approx(math.pi / 2)
    assert heading_rad(Q_LEVEL) is None
    ar = ArOverlay(arena)
    r = ar.radius_px
    ar.update(_pose(1, 1, (0.0, 0.0, 1.0), Q_DOWN_EAST), now_s=0.0)
    east = ar.draw(_grey(), now_s=0.0)
    ar = ArOverlay(arena)
    ar.update(_pose(1, 1, (0.0, 0.0, 1.0), Q_DOWN_NORTH), now_s=0.0)
    north = ar.draw(_grey(), now_s=0.0)
    ahead, behind = 1.6 * r, -1.6 * r  # outside the circle, inside the arrow's reach of 2r
    for frame, (du, dv) in ((east, (1.0, 0.0)), (north, (0.0, -1.0))):  # north is up: v decreases
        c, rr = _px(ar, 0.0, 0.0, du * ahead, dv * ahead)
        assert tuple(frame[rr, c]) != GREY, "the arrow should cover the point ahead"
        c, rr = _px(ar, 0.0, 0.0, du * behind, dv * behind)
        assert tuple(frame[rr, c]) == GREY, "nothing should be drawn behind"
        c, rr = _px(ar, 0.0, 0.0, -dv * ahead, du * ahead)  # to the side
        assert tuple(frame[rr, c]) == GREY
    assert ar.heading_px(0.0) == pytest.approx((1.0, 0.0))
    assert ar.heading_px(math.pi / 2) == pytest.approx((0.0, -1.0))


def test_trail_fades_behind_a_moving_vehicle(arena: ArenaConfig) -> None:
    ar = ArOverlay(arena, trail_s=3.0)
    for k in range(11):
        ar.update(_pose(2, k + 1, (-0.3 + 0.03 * k, 0.0, 1.0), Q_LEVEL), now_s=0.1 * k)
    frame = ar.draw(_grey(), now_s=1.0)
    c_old, r_old = _px(ar, -0.27, 0.0)
    c_mid, r_mid = _px(ar, -0.12, 0.0)
    old, mid = frame[r_old, c_old].astype(float), frame[r_mid, c_mid].astype(float)
    grey, colour = np.array(GREY, float), np.array(PALETTE[2], float)
    assert 0 < np.abs(old - grey).sum() < np.abs(mid - grey).sum() < np.abs(colour - grey).sum()
    track = ar.track(2)
    assert track is not None
    assert len(track.trail) == 11
    # A RESET starts a new trail.
    reset = PosePacket(2, 20, 0, (0.2, 0.0, 1.0), Q_LEVEL, flags=QualityFlags.RESET)
    ar.update(reset, now_s=1.1)
    track = ar.track(2)
    assert track is not None
    assert len(track.trail) == 1


def test_absurd_positions_are_harmless(arena: ArenaConfig) -> None:
    ar = ArOverlay(arena)
    ar.update(_pose(1, 1, (1e300, -1e300, 0.0)), now_s=0.0)
    ar.update(_pose(2, 1, (5.0, 0.0, 0.0)), now_s=0.0)  # off the screen
    ar.update(_pose(3, 1, (0.4, 0.0, 0.0)), now_s=0.0)
    ar.update(_pose(3, 2, (-0.4, 0.0, 0.0)), now_s=0.1)  # a jump: no line across the arena
    frame = ar.draw(_grey(), now_s=0.1)
    c, r = _px(ar, 0.0, 0.0)
    assert tuple(frame[r, c]) == GREY
    with pytest.raises(ValueError, match="frame"):
        ar.draw(np.zeros((10, 10, 3), np.uint8), now_s=0.0)


# --- (d) the clock counts missed deadlines -------------------------------------------------------------


class _FlatScene:
    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s
        self.calls: list[int] = []

    def frame(self, index: int, rate_hz: float) -> U8:
        self.calls.append(index)
        if self.delay_s:
            time.sleep(self.delay_s)  # real: content slower than the projector, in the sender's own thread
        return _grey()


@pytest.mark.asyncio
async def test_slow_content_is_counted_as_missed_deadlines(arena: ArenaConfig) -> None:
    lines: list[str] = []
    sink = NullSink()
    scene = _FlatScene(delay_s=0.040)  # 40 ms per input frame; 2 output frames are 33 ms at 60 Hz
    stats = await run_sender(
        arena, sink, scene, frames=24, listen=None, log=lines.append, install_signal_handlers=False
    )
    assert stats.frames == 24
    assert sink.frames_shown == 24
    assert sink.last_index == 23
    assert scene.calls == list(range(12))  # input frame i = j // 2, each asked once
    # After each late frame the clock restarts from it; the next input frame (every other output
    # frame) then takes 40 ms for a 33 ms slot again: about one miss per input frame.
    assert stats.missed >= 8, lines
    assert re.search(rf"\bmissed={stats.missed}\b", lines[-1])


@pytest.mark.asyncio
async def test_fast_content_keeps_the_pace(arena: ArenaConfig) -> None:
    lines: list[str] = []
    t0 = time.monotonic()
    stats = await run_sender(
        arena, NullSink(), _FlatScene(), frames=30, listen=None, log=lines.append, install_signal_handlers=False
    )
    took = time.monotonic() - t0
    assert stats.frames == 30
    assert stats.missed <= 3, lines  # slack for a busy machine
    assert 29 / 60 - 0.02 <= took < 2.0  # paced: 30 frames take half a second
    assert "missed=" in lines[-1]


class _RecordingSink(NullSink):
    """Paced, done with each frame when show returns (so the sender reuses its arrays): keeps copies."""

    def __init__(self) -> None:
        super().__init__()
        self.frames: list[U8] = []

    def show(self, frame_rgb: U8, index: int) -> None:
        super().show(frame_rgb, index)
        self.frames.append(frame_rgb.copy())


class _CountingModulator(IptModulator):
    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.row_calls: list[tuple[int, int]] = []

    def phases_rows(self, frame_rgb: U8, out: tuple[U8, U8], row0: int, row1: int) -> None:
        self.row_calls.append((row0, row1))
        super().phases_rows(frame_rgb, out, row0, row1)


@pytest.mark.asyncio
async def test_paced_frames_are_the_modulated_content_in_reused_buffers(arena: ArenaConfig) -> None:
    # Paced and borrowing: phases begun one output frame early, written into a ring of reused arrays.
    scene = GeneratedScene(W, H)
    mask = grid_tag_map(arena).render_mask()
    mod = _CountingModulator(mask, DELTA_L)
    sink = _RecordingSink()
    stats = await run_sender(
        arena, sink, scene, frames=14, listen=None, log=lambda _: None, install_signal_handlers=False, modulator=mod
    )
    assert stats.frames == 14
    reference = IptModulator(mask, DELTA_L)
    for j, frame in enumerate(sink.frames):
        plus, minus = reference.phases(scene.frame(j // 2, 30.0))
        assert np.array_equal(frame, plus if j % 2 == 0 else minus), j
    assert (0, round(H * 0.4)) in mod.row_calls  # some input frames were begun early...
    assert (round(H * 0.4), H) in mod.row_calls  # ...and finished at their first output frame


@pytest.mark.asyncio
async def test_unpaced_file_sink_and_stop_event(tmp_path: Path, arena: ArenaConfig) -> None:
    import asyncio

    out = tmp_path / "f.mkv"
    stats = await run_sender(
        arena,
        FileSink(out, 60.0),
        _FlatScene(),
        frames=5,
        listen=None,
        log=lambda s: None,
        install_signal_handlers=False,
    )
    assert stats.frames == 5
    assert stats.missed == 0
    with open_frames(out) as source:
        assert len(list(source)) == 5
    stop = asyncio.Event()
    asyncio.get_running_loop().call_later(0.3, stop.set)
    t0 = time.monotonic()
    stats = await run_sender(
        arena, NullSink(), _FlatScene(), listen=None, log=lambda s: None, install_signal_handlers=False, stop=stop
    )
    assert 0.25 < time.monotonic() - t0 < 1.3
    assert stats.frames > 5


class _BrokenScene(_FlatScene):
    def frame(self, index: int, rate_hz: float) -> U8:
        if index == 3:
            raise ContentError("input frame 3 is unreadable")
        return super().frame(index, rate_hz)


@pytest.mark.asyncio
async def test_a_failing_scene_stops_the_run_and_leaves_no_file(tmp_path: Path, arena: ArenaConfig) -> None:
    out = tmp_path / "broken.mkv"
    lines: list[str] = []
    with pytest.raises(ContentError, match="frame 3"):
        await run_sender(
            arena, FileSink(out, 60.0, W, H), _BrokenScene(), frames=20, listen=None, log=lines.append,
            install_signal_handlers=False,
        )  # fmt: skip
    assert not out.exists()
    assert list(tmp_path.glob("*.mkv")) == []  # no partial file left behind either


class _FlakyScene:
    """Input frames ``fail`` raise (a video that cannot be read there); the others are flat colours that
    say their index (R = 10 + index), so that a test can tell which input frame an output frame shows."""

    def __init__(self, fail: range) -> None:
        self.fail = fail
        self.given: U8 | None = None

    def frame(self, index: int, rate_hz: float) -> U8:
        if index in self.fail:
            raise OSError(f"decoder error at input frame {index}")
        self.given = np.full((H, W, 3), (10 + index, 120, 140), np.uint8)
        return self.given.copy()

    def last_frame(self) -> U8 | None:
        return None if self.given is None else self.given.copy()


def _input_shown(frame: U8, mask: npt.NDArray[np.int8]) -> int:
    """The input frame a flat-colour output frame shows (read where the mask leaves the content alone)."""
    return int(frame[mask == 0][:, 0].mean().round()) - 10


@pytest.mark.asyncio
async def test_a_failing_video_source_shows_the_last_good_frame_with_phases_alternating(arena: ArenaConfig) -> None:
    mask = grid_tag_map(arena).render_mask()
    sink = _RecordingSink()
    lines: list[str] = []
    stats = await run_sender(
        arena, sink, _FlakyScene(fail=range(4, 9)), frames=30, listen=None, log=lines.append,
        install_signal_handlers=False,
    )  # fmt: skip
    assert stats.frames == 30
    assert sink.frames_shown == 30
    shown = [_input_shown(f, mask) for f in sink.frames]
    # Input frames 4..8 failed: their output frames (8..17) show input frame 3, the last good one...
    assert shown == [j // 2 if not 8 <= j < 18 else 3 for j in range(30)], shown
    # ...still modulated, the phases alternating at every output frame as before (tag pixels go up on even
    # frames and down on odd ones, where the mask is +1).
    white = mask > 0
    for j in range(1, 30):
        if shown[j] == shown[j - 1]:
            up = sink.frames[j - 1] if j % 2 == 1 else sink.frames[j]
            down = sink.frames[j] if j % 2 == 1 else sink.frames[j - 1]
            assert _l8(up)[white].mean() > _l8(down)[white].mean() + DELTA_L / 2, j
    assert stats.content_errors == 5
    assert sum("video source failed (OSError: decoder error at input frame 4)" in ln for ln in lines) == 1, lines
    assert sum("video source is back (5 input frames were replaced" in ln for ln in lines) == 1, lines
    assert "content_errors=5" in lines[-1]
    assert "missed=" in lines[-1]


@pytest.mark.asyncio
async def test_a_video_source_failing_from_the_start_shows_black_until_it_works(arena: ArenaConfig) -> None:
    mask = grid_tag_map(arena).render_mask()
    sink = _RecordingSink()
    stats = await run_sender(
        arena, sink, _FlakyScene(fail=range(0, 2)), frames=8, listen=None, log=lambda _: None,
        install_signal_handlers=False,
    )  # fmt: skip
    assert stats.content_errors == 2
    assert all(not f[mask == 0].any() for f in sink.frames[:4])  # nothing good yet: black around the tags
    assert [_input_shown(f, mask) for f in sink.frames[4:]] == [2, 2, 3, 3]


class _FlakySink(_RecordingSink):
    """Fails to show output frames ``fail`` (the display was lost), as a window sink does."""

    retries = True

    def __init__(self, fail: range) -> None:
        super().__init__()
        self.fail = fail
        self.indices: list[int] = []

    def show(self, frame_rgb: U8, index: int) -> None:
        if index in self.fail:
            raise DisplayError(f"the window was lost at frame {index}")
        super().show(frame_rgb, index)
        self.indices.append(index)


@pytest.mark.asyncio
async def test_a_failing_display_is_reported_and_the_loop_goes_on(arena: ArenaConfig) -> None:
    scene = GeneratedScene(W, H)
    mask = grid_tag_map(arena).render_mask()
    sink = _FlakySink(fail=range(5, 12))
    lines: list[str] = []
    stats = await run_sender(
        arena, sink, scene, frames=24, listen=None, log=lines.append, install_signal_handlers=False
    )
    assert stats.frames == 24
    assert stats.display_errors == 7
    assert sink.indices == [j for j in range(24) if not 5 <= j < 12]  # back at frame 12, nothing skipped after
    reference = IptModulator(mask, DELTA_L, clip_allowance_l8=arena.modulation.clip_allowance_l8)
    for j, frame in zip(sink.indices, sink.frames, strict=True):  # each the right phase of the right input
        plus, minus = reference.phases(scene.frame(j // 2, 30.0))
        assert np.array_equal(frame, plus if j % 2 == 0 else minus), j
    assert sum("the null sink failed at output frame 5 (DisplayError" in ln for ln in lines) == 1, lines
    assert sum("sink is back at output frame 12 after 7 failed frames" in ln for ln in lines) == 1, lines
    assert "display_errors=7" in lines[-1]


@pytest.mark.asyncio
async def test_a_failing_file_sink_ends_the_run(tmp_path: Path, arena: ArenaConfig) -> None:
    class _FullDisk(FileSink):
        def show(self, frame_rgb: U8, index: int) -> None:
            if index == 3:
                raise DisplayError("no space left on device")
            super().show(frame_rgb, index)

    with pytest.raises(DisplayError, match="no space left"):
        await run_sender(
            arena, _FullDisk(tmp_path / "f.mkv", 60.0, W, H), _FlatScene(), frames=10, listen=None,
            log=lambda _: None, install_signal_handlers=False,
        )  # fmt: skip


@pytest.mark.asyncio
async def test_port_in_use_is_a_clear_error(arena: ArenaConfig) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        with pytest.raises(SenderError, match=rf"cannot listen on 127\.0\.0\.1:{port}"):
            await run_sender(
                arena, NullSink(), _FlatScene(), frames=2, listen=("127.0.0.1", port), log=lambda s: None,
                install_signal_handlers=False,
            )  # fmt: skip


# --- sinks ------------------------------------------------------------------------------------------------


def test_make_sink_by_name(tmp_path: Path) -> None:
    assert isinstance(make_sink("null"), NullSink)
    assert isinstance(make_sink("file", output=tmp_path / "x.mkv", fps=60.0), FileSink)
    with pytest.raises(DisplayError):
        make_sink("file")
    with pytest.raises(DisplayError):
        make_sink("hologram")


def test_window_sink_without_pygame_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pygame", None)  # makes `import pygame` fail
    with pytest.raises(DisplayError, match=r"pip install 'ipt\[display\]'"):
        WindowSink()


def test_window_sink_headless(monkeypatch: pytest.MonkeyPatch) -> None:
    # pygame-ce is in the dev extra, so this runs everywhere the tests run (no silent skip).
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")
    sink = WindowSink(display_index=0, fullscreen=False)
    frame = _grey()
    frame[10, 20] = (200, 30, 40)
    try:
        sink.show(frame, 0)
        sink.show(frame, 1)
        assert sink.pixel(20, 10) == (200, 30, 40)
        assert sink.pixel(0, 0) == GREY
        assert not sink.quit_requested
        with pytest.raises(DisplayError):
            sink.show(np.zeros((8, 8, 3), np.uint8), 2)
    finally:
        sink.close()
    with pytest.raises(DisplayError, match="does not exist"):
        WindowSink(display_index=7).show(frame, 0)
    assert os.environ["SDL_VIDEODRIVER"] == "dummy"


def test_present_clock_counts_repeated_and_unseen_frames() -> None:
    clock = PresentClock(1 / 60)
    period = 1 / 60
    for t in (0.0, period, 2 * period, 4 * period, 4 * period + 0.002, 5 * period, 8.1 * period):
        clock.add(1000.0 + t)
    summary = clock.summary()
    assert summary["presents"] == 7
    # 2 -> 4: the frame at 2 stayed up one refresh too long; 5 -> 8.1: two more.
    assert summary["repeated_vsyncs"] == 3
    # 4 -> 4 + 2 ms: both flips in one refresh, the first never shown.
    assert summary["dropped_frames"] == 1
    assert summary["present_interval_p50_ms"] == pytest.approx(16.65, abs=0.1)
    assert summary["present_interval_max_ms"] == pytest.approx(3.1 * 1000 / 60, abs=0.01)
    with pytest.raises(DisplayError, match="refresh period"):
        PresentClock(0.0)


def test_window_sink_times_its_flips(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")
    times = iter([10.0, 10.0167, 10.0500, 10.0667])  # the third frame comes a refresh late
    sink = WindowSink(display_index=0, fullscreen=False, rate_hz=60.0, clock=lambda: next(times))
    try:
        for j in range(4):
            sink.show(_grey(), j)
    finally:
        sink.close()
    pacing = sink.pacing()
    assert pacing["presents"] == 4
    assert pacing["repeated_vsyncs"] == 1
    assert pacing["dropped_frames"] == 0


@pytest.mark.asyncio
async def test_the_statistics_line_reports_the_window_pacing(
    arena: ArenaConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    monkeypatch.setenv("SDL_AUDIODRIVER", "dummy")
    lines: list[str] = []
    sink = WindowSink(display_index=0, fullscreen=False, rate_hz=arena.projector.rate_hz)
    stats = await run_sender(
        arena, sink, _FlatScene(), frames=12, listen=None, log=lines.append, install_signal_handlers=False
    )
    assert stats.pacing is not None
    assert stats.pacing["presents"] == stats.frames == 12
    last = lines[-1]
    assert re.search(rf"repeated_vsyncs={stats.pacing['repeated_vsyncs']} dropped_frames=\d+ present_p99=", last)
    assert stats.to_dict()["pacing"]["presents"] == 12


class _GrowingScene:
    """Flat frames (value 60 + 20 i) whose size changes at input frame 3 and back at 5."""

    def frame(self, index: int, rate_hz: float) -> U8:
        w, h = (400, 300) if index in (3, 4) else (W, H)
        return np.full((h, w, 3), 60 + 20 * index, np.uint8)


@pytest.mark.asyncio
async def test_a_frame_of_another_size_is_said_once_and_resized(arena: ArenaConfig) -> None:
    mask = grid_tag_map(arena).render_mask()
    sink = _RecordingSink()
    lines: list[str] = []
    stats = await run_sender(
        arena, sink, _GrowingScene(), frames=12, listen=None, log=lines.append, install_signal_handlers=False
    )
    assert stats.frames == 12
    assert stats.content_errors == 0
    notes = [ln for ln in lines if "resized to" in ln]
    assert notes == [f"ipt-sender: the scene's frames are 400x300 from input frame 3 on; resized to {W}x{H}"]
    # Every input frame was shown, at the projector size, phases alternating.
    assert [_input_shown(f, mask) + 10 for f in sink.frames[::2]] == [60 + 20 * k for k in range(6)]
    white = mask > 0
    for j in range(0, 12, 2):
        assert _l8(sink.frames[j])[white].mean() > _l8(sink.frames[j + 1])[white].mean() + DELTA_L / 2


def _mpeg_ts(path: Path, width: int, height: int, frames: int, first: int) -> bytes:
    import av

    with av.open(str(path), "w", format="mpegts") as container:
        stream = container.add_stream("mpeg2video", rate=30)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        for k in range(frames):
            image = np.full((height, width, 3), first + 20 * k, np.uint8)
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path.read_bytes()


@pytest.mark.asyncio
async def test_a_video_that_changes_size_mid_stream_keeps_the_projection_going(
    tmp_path: Path, arena: ArenaConfig
) -> None:
    # Two MPEG transport streams back to back: the picture size changes at the join, as a broadcast or a
    # re-encoded clip can. The reader refuses frames of another size than the first; the sender says so in
    # one line and shows the last good frame, modulated, phases alternating.
    from ipt.sender.content import VideoScene

    video = tmp_path / "joined.ts"
    video.write_bytes(_mpeg_ts(tmp_path / "a.ts", 64, 48, 4, 60) + _mpeg_ts(tmp_path / "b.ts", 96, 64, 4, 140))
    mask = grid_tag_map(arena).render_mask()
    sink = _RecordingSink()
    lines: list[str] = []
    with VideoScene(video, W, H, fps=30.0) as scene:
        stats = await run_sender(
            arena, sink, scene, frames=16, listen=None, log=lines.append, install_signal_handlers=False
        )
    assert stats.frames == 16
    assert stats.content_errors > 0
    failed = [ln for ln in lines if "the video source failed" in ln]
    assert len(failed) == 1, lines
    assert "is 96x64, the first frame is 64x48" in failed[0]
    assert "showing the last good frame, phases still alternating" in failed[0]
    white = mask > 0
    for j in range(0, 16, 2):
        assert _l8(sink.frames[j])[white].mean() > _l8(sink.frames[j + 1])[white].mean() + DELTA_L / 2
