"""``ipt-receiver doctor``: a fake for each failure, the map hash everywhere it is printed, and a real run on this
machine whose lines and exit status agree with what it reports."""

from __future__ import annotations

import hashlib
import re
import shutil
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from ipt.config.camera_info import load_camera_info
from ipt.config.models import shipped_config_path
from ipt.receiver.capture import CapturedFrame, CaptureError
from ipt.receiver.doctor import FAIL, OK, SKIP, Check, Mode, Probes, _send_target, main_lines, run_checks

LINE = re.compile(r"^\[( ok |FAIL|skip)\] (.+?): .+$")
"""A check's line: its status, its name (no ': ' in it) and what was found."""


def _config(tmp_path: Path, **fields: str) -> Path:
    """A receiver YAML in ``tmp_path`` with the shipped arena and camera and the given top-level fields."""
    body = {
        "arena": str(shipped_config_path("arena.yaml")),
        "camera": str(shipped_config_path("camera.yaml")),
        "source": "sim",
        "send": "[127.0.0.1:9870]",
        **fields,
    }
    path = tmp_path / "receiver.yaml"
    path.write_text("".join(f"{k}: {v}\n" for k, v in body.items()), encoding="utf-8")
    return path


def _by_name(checks: list[Check], name: str) -> Check:
    found = [c for c in checks if c.name == name]
    assert len(found) == 1, [c.line() for c in checks]
    return found[0]


def _quiet_probes(**kw: object) -> Probes:
    """Probes that find no camera, compiled kernels, and no clock report (each test overrides one)."""
    base: dict[str, object] = {
        "dev_dir": Path("/nonexistent-dev"),
        "picamera2": lambda: None,
        "kernels_compiled": lambda: True,
        "run_command": lambda argv: None,
    }
    return Probes(**{**base, **kw})  # type: ignore[arg-type]


class _Clock:
    """A clock that advances by ``step`` seconds per reading (no sleeping)."""

    def __init__(self, step: float) -> None:
        self.t, self.step = 100.0, step

    def __call__(self) -> float:
        self.t += self.step
        return self.t


class _FakeCamera:
    """A camera giving ``w``×``h`` frames ``1 / fps`` apart, that vanishes after ``vanish_after`` frames."""

    live, retry_open, name = True, True, "device:0"
    raw_format = "MJPG"

    def __init__(self, fps: float, w: int = 640, h: int = 360, vanish_after: int | None = None) -> None:
        self.fps, self.w, self.h, self.vanish_after, self.k = fps, w, h, vanish_after, 0
        self.closed = False

    def open(self) -> None:
        pass

    def read(self) -> CapturedFrame | None:
        if self.vanish_after is not None and self.k >= self.vanish_after:
            raise CaptureError("/dev/video0: grabbing a frame failed")
        self.k += 1
        return CapturedFrame(self.k, round(self.k * 1e6 / self.fps), np.zeros((self.h, self.w), np.uint8))

    def close(self) -> None:
        self.closed = True


def _camera_probes(tmp_path: Path, modes: list[Mode], camera: _FakeCamera) -> Probes:
    dev = tmp_path / "dev"
    dev.mkdir(exist_ok=True)
    (dev / "video0").touch()
    (dev / "video-metadata").touch()  # not a videoN node
    return _quiet_probes(
        dev_dir=dev, v4l2_modes=lambda node: modes, open_camera=lambda cfg, cam: camera, clock=_Clock(1 / 240)
    )


# --- a fake for each failure ----------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["missing", "folder", "not yaml", "bad field"])
def test_an_unreadable_config_is_its_line_exit_1_no_traceback(tmp_path: Path, kind: str) -> None:
    path = tmp_path / "receiver.yaml"
    if kind == "folder":
        path.mkdir()
    elif kind == "not yaml":
        path.write_text("send: [unclosed\n", encoding="utf-8")
    elif kind == "bad field":
        path.write_text("sned: []\n", encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "doctor", "--config", str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    first = proc.stdout.splitlines()[0]
    assert first.startswith(f"[FAIL] config: {path}") or first.startswith("[FAIL] config: "), first
    assert "-> fix" in first


def test_configured_camera_without_a_mode_at_the_rate_fails_with_what_it_offers(tmp_path: Path) -> None:
    modes = [Mode("YUYV", 640, 360, 30.0), Mode("MJPG", 1280, 720, 60.0)]
    cfg = _config(tmp_path, source="device:0", fps="120")
    checks = run_checks(cfg, _camera_probes(tmp_path, modes, _FakeCamera(120)))
    line = _by_name(checks, "camera device:0")
    assert line.status == FAIL
    assert "no mode at 640x360 at 120 FPS or more" in line.detail
    assert "YUYV 640x360@30" in line.fix


def test_a_fitting_camera_names_the_format_and_measures_the_rate(tmp_path: Path) -> None:
    modes = [Mode("MJPG", 640, 360, 120.0), Mode("YUYV", 640, 360, 120.0), Mode("YUYV", 640, 360, 30.0)]
    cfg = _config(tmp_path, source="device:0", fps="120")
    camera = _FakeCamera(120)
    checks = run_checks(cfg, _camera_probes(tmp_path, modes, camera))
    line = _by_name(checks, "camera device:0")
    assert line.status == OK, line.line()
    assert "the receiver would use YUYV" in line.detail  # luma uncompressed beats MJPG
    rate = _by_name(checks, "camera device:0 rate")
    assert rate.status == OK, rate.line()
    assert "120.0 FPS measured" in rate.detail
    assert "pixel format MJPG" in rate.detail
    assert camera.closed
    assert _by_name(checks, "camera.yaml").status == OK


def test_a_camera_that_disappears_during_doctor_is_its_line(tmp_path: Path) -> None:
    modes = [Mode("MJPG", 640, 360, 120.0)]
    cfg = _config(tmp_path, source="device:0", fps="120")
    lines: list[str] = []
    code = main_lines(cfg, lines.append, _camera_probes(tmp_path, modes, _FakeCamera(120, vanish_after=5)))
    assert code == 1
    rate = [line for line in lines if line.startswith("[FAIL] camera device:0 rate")]
    assert len(rate) == 1, lines
    assert "stopped giving frames after 5 frames: /dev/video0: grabbing a frame failed" in rate[0]
    assert "-> check the cable" in rate[0]


def test_a_slow_camera_and_a_calibration_of_another_size_fail(tmp_path: Path) -> None:
    modes = [Mode("GREY", 640, 360, 120.0)]
    cfg = _config(tmp_path, source="device:0", fps="120")
    checks = run_checks(cfg, _camera_probes(tmp_path, modes, _FakeCamera(60, w=320, h=240)))
    rate = _by_name(checks, "camera device:0 rate")
    assert rate.status == FAIL
    assert "60.0 FPS measured" in rate.detail
    size = _by_name(checks, "camera.yaml")
    assert size.status == FAIL
    assert "640x360 but device:0's frames are 320x240" in size.detail


def test_a_configured_camera_that_is_not_there_fails(tmp_path: Path) -> None:
    cfg = _config(tmp_path, source="device:3")
    checks = run_checks(cfg, _quiet_probes(open_camera=lambda cfg, cam: _FakeCamera(120, vanish_after=0)))
    assert _by_name(checks, "cameras").status == FAIL
    assert "device:3 is not here" in _by_name(checks, "cameras").detail


def test_a_bad_arena_fails_and_a_good_one_shows_the_map_hash(tmp_path: Path) -> None:
    bad = tmp_path / "arena.yaml"
    bad.write_text("projector: {width_px: -5}\n", encoding="utf-8")
    line = _by_name(run_checks(_config(tmp_path, arena=str(bad)), _quiet_probes()), "arena")
    assert line.status == FAIL
    assert str(bad) in line.detail
    good = _by_name(run_checks(_config(tmp_path), _quiet_probes()), "arena")
    assert good.status == OK
    assert re.search(r"map hash sha256:[0-9a-f]{64}", good.detail)


def test_key_file_missing_open_to_others_or_short_fails_private_passes(tmp_path: Path) -> None:
    key = tmp_path / "key"
    probes = _quiet_probes()

    def check() -> Check:
        return _by_name(run_checks(_config(tmp_path, auth_key_file=str(key)), probes), "key")

    assert check().status == FAIL
    assert "no such" in check().detail.lower() or "No such" in check().detail
    key.write_bytes(b"k" * 32)
    key.chmod(0o644)
    assert check().status == FAIL
    assert check().fix == f"chmod o-rwx {key}"
    key.chmod(0o640)  # the sender's and the daemon's rule (ipt.keyfile): closed to others, a group may read
    assert check().status == OK, check().line()
    key.chmod(0o600)
    assert check().status == OK, check().line()
    key.write_bytes(b"short")
    assert check().status == FAIL


def test_a_target_that_does_not_parse_or_cannot_be_reached_fails() -> None:
    assert _send_target("nonsense").status == FAIL
    blocked = _send_target("255.255.255.255:9870")  # broadcast without SO_BROADCAST: connect refuses, nothing sent
    assert blocked.status == FAIL
    assert "cannot open a UDP socket" in blocked.detail
    assert _send_target("127.0.0.1:9870").status == OK


def test_kernels_that_do_not_compile_fail() -> None:
    checks = run_checks(shipped_config_path("receiver.yaml"), _quiet_probes(kernels_compiled=lambda: False))
    line = _by_name(checks, "kernels")
    assert line.status == FAIL
    assert "MemoryDenyWriteExecute" in line.fix


@pytest.mark.parametrize(("answer", "status"), [("yes", OK), ("no", FAIL), (None, SKIP)])
def test_clock_synchronisation(answer: str | None, status: str) -> None:
    asked: list[list[str]] = []

    def run(argv: list[str]) -> str | None:
        asked.append(argv)
        return answer

    checks = run_checks(shipped_config_path("receiver.yaml"), _quiet_probes(run_command=run))
    assert _by_name(checks, "clock").status == status
    assert asked == [["timedatectl", "show", "--property=NTPSynchronized", "--value"]]


class _FakeAutopilot:
    """A loopback UDP autopilot: answers every datagram with a HEARTBEAT (or stays silent)."""

    def __init__(self, answer: bool) -> None:
        from pymavlink.dialects.v20 import common

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port = self.sock.getsockname()[1]
        self.mav = common.MAVLink(None, srcSystem=1, srcComponent=1)
        self.answer, self.heard = answer, 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.serve, daemon=True)

    def serve(self) -> None:
        from pymavlink.dialects.v20 import common

        while not self.stop.is_set() and self.heard < 20:
            try:
                _, addr = self.sock.recvfrom(2048)
            except TimeoutError:
                continue
            self.heard += 1
            if self.answer:
                hb = self.mav.heartbeat_encode(common.MAV_TYPE_QUADROTOR, common.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4)
                self.sock.sendto(hb.pack(self.mav), addr)

    def __enter__(self) -> _FakeAutopilot:
        self.thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop.set()
        self.thread.join(2)
        self.sock.close()


@pytest.fixture
def autopilot(request: pytest.FixtureRequest) -> Iterator[_FakeAutopilot]:
    with _FakeAutopilot(answer=request.param) as ap:
        yield ap


@pytest.mark.parametrize("autopilot", [True], indirect=True)
def test_mavlink_heartbeat_from_a_loopback_autopilot(tmp_path: Path, autopilot: _FakeAutopilot) -> None:
    cfg = _config(tmp_path, mavlink=f"{{link: 'udpout:127.0.0.1:{autopilot.port}'}}")
    line = _by_name(run_checks(cfg, _quiet_probes()), f"mavlink udpout:127.0.0.1:{autopilot.port}")
    assert line.status == OK, line.line()
    assert "HEARTBEAT from system 1 component 1, autopilot type 3" in line.detail


@pytest.mark.parametrize("autopilot", [False], indirect=True)
def test_mavlink_without_heartbeat_fails_within_the_timeout(tmp_path: Path, autopilot: _FakeAutopilot) -> None:
    cfg = _config(tmp_path, mavlink=f"{{link: 'udpout:127.0.0.1:{autopilot.port}'}}")
    line = _by_name(
        run_checks(cfg, _quiet_probes(heartbeat_timeout_s=0.3)), f"mavlink udpout:127.0.0.1:{autopilot.port}"
    )
    assert line.status == FAIL
    assert "no HEARTBEAT came within 0.3 s" in line.detail
    assert autopilot.heard >= 1  # our HEARTBEAT went out


def test_a_check_that_breaks_is_its_line_not_a_traceback(tmp_path: Path) -> None:
    def broken(node: Path) -> list[Mode]:
        raise RuntimeError("driver went away")

    dev = tmp_path / "dev"
    dev.mkdir()
    (dev / "video0").touch()
    checks = run_checks(_config(tmp_path), _quiet_probes(dev_dir=dev, v4l2_modes=broken))
    line = _by_name(checks, "cameras")
    assert line.status == FAIL
    assert "RuntimeError: driver went away" in line.detail


# --- the map hash everywhere -----------------------------------------------------------------------------


def test_map_export_prints_the_sha256_of_the_layout_it_wrote(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "ipt.cli", "map", "export", "--image", "m.png", "--layout", "l.json"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    digest = hashlib.sha256((tmp_path / "l.json").read_bytes()).hexdigest()
    assert f"map hash sha256:{digest}" in proc.stdout
    doctor = _by_name(run_checks(shipped_config_path("receiver.yaml"), _quiet_probes()), "arena")
    assert f"map hash sha256:{digest}" in doctor.detail


@pytest.mark.slow
def test_sender_and_receiver_print_the_same_map_hash(tmp_path: Path) -> None:
    sender = subprocess.run(
        [sys.executable, "-m", "ipt.sender.cli", "--sink", "null", "--frames", "2", "--listen", "127.0.0.1:0"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert sender.returncode == 0, sender.stderr
    receiver = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "run", "--source", "sim", "--max-frames", "2"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert receiver.returncode == 0, receiver.stderr
    ours = re.findall(r"ipt-sender: map hash sha256:([0-9a-f]{64})", sender.stderr)
    theirs = re.findall(r"ipt-receiver: running: .*map hash sha256:([0-9a-f]{64})", receiver.stderr)
    assert len(ours) == 1, sender.stderr
    assert theirs == ours


# --- a real run on this machine ---------------------------------------------------------------------------


def test_a_real_run_here_agrees_with_this_machine(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "ipt.receiver.cli", "doctor"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert "Traceback" not in proc.stderr, proc.stderr
    *lines, summary = proc.stdout.splitlines()
    for line in lines:
        assert LINE.match(line), line
        if line.startswith("[FAIL]"):
            assert " -> " in line, line  # what to do
    failed = [line for line in lines if line.startswith("[FAIL]")]
    assert summary.startswith(f"doctor: {len(lines)} checks, {len(failed)} failed")
    assert proc.returncode == (1 if failed else 0)
    by_name = {line.split("] ", 1)[1].split(": ", 1)[0]: line for line in lines}
    assert {"config", "arena", "kernels", "clock", "send 127.0.0.1:9870"} <= set(by_name)
    has_video = any(p.name[5:].isdigit() for p in Path("/dev").glob("video*"))
    assert ("no V4L2 camera" in proc.stdout) == (not has_video)
    timedatectl = shutil.which("timedatectl")
    answer = None
    if timedatectl is not None:
        probe = subprocess.run(
            [timedatectl, "show", "--property=NTPSynchronized", "--value"],
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
        answer = probe.stdout.strip() if probe.returncode == 0 else None
    expected = {None: "[skip] clock", "yes": "[ ok ] clock"}.get(answer, "[FAIL] clock")
    assert by_name["clock"].startswith(expected)
    from ipt.receiver.core import kernels

    kernels.ensure()
    assert by_name["kernels"].startswith("[ ok ]" if kernels.COMPILED else "[FAIL]")


# --- V4L2 enumeration against a fake driver -----------------------------------------------------------------


def test_the_ioctl_numbers_are_the_kernels() -> None:
    from ipt.receiver import doctor

    assert doctor.VIDIOC_ENUM_FMT == 0xC0405602
    assert doctor.VIDIOC_ENUM_FRAMESIZES == 0xC02C564A
    assert doctor.VIDIOC_ENUM_FRAMEINTERVALS == 0xC034564B


def test_v4l2_modes_reads_formats_sizes_and_the_best_rate(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A fake driver behind ``fcntl.ioctl``: MJPG at 640x360 (1/30, 1/120 s) and 1280x720 (1/60 s), and a
    stepwise size range (skipped)."""
    import errno
    import struct

    from ipt.receiver import doctor

    mjpg = int.from_bytes(b"MJPG", "little")
    sizes = [(1, 640, 360), (1, 1280, 720), (3, 0, 0)]
    intervals = {(640, 360): [(1, 30), (1, 120)], (1280, 720): [(1, 60)]}

    def ioctl(fd: int, request: int, buf: bytearray, mutate: bool) -> int:
        index = struct.unpack_from("<I", buf, 0)[0]
        if request == doctor.VIDIOC_ENUM_FMT and index == 0:
            struct.pack_into("<III32sI", buf, 0, 0, 1, 0, b"Motion-JPEG", mjpg)
        elif request == doctor.VIDIOC_ENUM_FRAMESIZES and index < len(sizes):
            kind, w, h = sizes[index]
            struct.pack_into("<IIIII", buf, 0, index, mjpg, kind, w, h)
        elif request == doctor.VIDIOC_ENUM_FRAMEINTERVALS:
            w, h = struct.unpack_from("<II", buf, 8)
            found = intervals.get((w, h), [])
            if index >= len(found):
                raise OSError(errno.EINVAL, "Invalid argument")
            struct.pack_into("<IIIIIII", buf, 0, index, mjpg, w, h, 1, *found[index])
        else:
            raise OSError(errno.EINVAL, "Invalid argument")
        return 0

    node = tmp_path / "video0"
    node.touch()
    monkeypatch.setattr("ipt.receiver.doctor.fcntl.ioctl", ioctl)
    assert doctor.v4l2_modes(node) == [Mode("MJPG", 640, 360, 120.0), Mode("MJPG", 1280, 720, 60.0)]


def test_a_camera_much_wider_than_the_work_width_is_said_to_be_binned(tmp_path: Path) -> None:
    wide = tmp_path / "camera-1280.yaml"
    camera = load_camera_info(shipped_config_path("camera.yaml"))
    assert camera.width_px == 640
    doubled = replace(camera, width_px=1280, height_px=2 * camera.height_px, fx_px=2 * camera.fx_px)
    wide.write_text(yaml.safe_dump(doubled.to_ros_dict()), encoding="utf-8")
    checks = run_checks(_config(tmp_path, camera=str(wide)), _quiet_probes())
    size = _by_name(checks, "camera.yaml")
    assert size.status == OK, size.line()
    assert f"1280x{2 * camera.height_px} (binned 2x2: posed at 640x{camera.height_px}" in size.detail
    plain = _by_name(run_checks(_config(tmp_path), _quiet_probes()), "camera.yaml")
    assert "binned" not in plain.detail
