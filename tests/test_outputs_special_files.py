"""Issue 33 item 1: an output never replaces what its path names.

A symbolic link is followed to its target (the link stays a link), a character device is written through
(as ``> /dev/null`` does in a shell), a named pipe, a socket or a block device is refused with one line
before anything is written. At 5def445 every atomic write renamed a regular file over the path: as root,
``--output /dev/null`` replaced the system's /dev/null. The devices here are private copies made with
``mknod`` inside the test's folder (skipped where that is not allowed), never the system's own.
"""

from __future__ import annotations

import contextlib
import errno
import os
import socket
import stat
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml

from ipt.config.camera_info import CameraInfo, save_camera_info
from ipt.fileio import WriteError, atomic_path, output_group, write_text_atomic

ARENA = {
    "projector": {"width_px": 320, "height_px": 288, "rate_hz": 60},
    "screen": {"width_m": 1.0, "height_m": 0.9},
    "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
    "modulation": {"delta_l": 8, "input_rate_hz": 30},
}
CAMERA = CameraInfo(width_px=64, height_px=48, fx_px=60.0, fy_px=60.0, cx_px=31.5, cy_px=23.5, name="special")


def _device(path: Path, minor: int) -> Path:
    """A private character device ``1, minor`` (3: null, 7: full) at ``path``, or skip."""
    try:
        os.mknod(path, stat.S_IFCHR | 0o666, os.makedev(1, minor))
    except (PermissionError, OSError) as exc:
        pytest.skip(f"cannot make a device node here: {exc}")
    return path


def _kind(path: Path) -> str:
    mode = os.lstat(path).st_mode
    return (
        "link"
        if stat.S_ISLNK(mode)
        else "chr"
        if stat.S_ISCHR(mode)
        else "fifo"
        if stat.S_ISFIFO(mode)
        else ("sock" if stat.S_ISSOCK(mode) else "reg" if stat.S_ISREG(mode) else "other")
    )


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if "partial" in p.name)


def test_a_link_is_followed_and_kept(tmp_path: Path) -> None:
    real = tmp_path / "real.txt"
    real.write_text("old\n", encoding="utf-8")
    link = tmp_path / "link.txt"
    link.symlink_to("real.txt")
    write_text_atomic(link, "new\n")
    assert _kind(link) == "link", "the link was replaced by a file"
    assert real.read_text(encoding="utf-8") == "new\n"
    assert _leftovers(tmp_path) == []


def test_a_dangling_link_makes_its_target(tmp_path: Path) -> None:
    link = tmp_path / "link.txt"
    link.symlink_to("made.txt")
    write_text_atomic(link, "x")
    assert _kind(link) == "link"
    assert (tmp_path / "made.txt").read_text(encoding="utf-8") == "x"


def test_a_link_to_dev_null_writes_through(tmp_path: Path) -> None:
    link = tmp_path / "out.tum"
    link.symlink_to(os.devnull)
    write_text_atomic(link, "discarded\n")
    assert _kind(link) == "link"
    assert stat.S_ISCHR(os.stat(os.devnull).st_mode)
    assert _leftovers(tmp_path) == []


def test_a_character_device_is_written_through(tmp_path: Path) -> None:
    null = _device(tmp_path / "null", 3)
    with output_group():
        write_text_atomic(null, "discarded\n")
    assert _kind(null) == "chr"
    assert _leftovers(tmp_path) == []


def test_a_full_device_is_one_write_error(tmp_path: Path) -> None:
    full = _device(tmp_path / "full", 7)
    with pytest.raises(WriteError) as info:
        write_text_atomic(full, "x" * 100_000)
    assert info.value.errno == errno.ENOSPC
    assert str(info.value) == f"{full}: cannot write (No space left on device)"
    assert _kind(full) == "chr"


@contextlib.contextmanager
def _socket_at(path: Path) -> Iterator[None]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(path))
        yield
    finally:
        sock.close()


@pytest.mark.parametrize("kind", ["fifo", "sock"])
def test_a_pipe_or_socket_is_refused_before_the_body_runs(tmp_path: Path, kind: str) -> None:
    target = tmp_path / "out"
    with contextlib.ExitStack() as stack:
        if kind == "fifo":
            os.mkfifo(target)
        else:
            stack.enter_context(_socket_at(target))
        ran = []
        with pytest.raises(WriteError) as info, atomic_path(target):
            ran.append(True)
        assert ran == []
        words = "a named pipe" if kind == "fifo" else "a socket"
        assert str(info.value) == f"{target}: cannot write ({words}, not a regular file: an output never replaces one)"
        assert _kind(target) == kind
        assert _leftovers(tmp_path) == []


def test_a_pipe_that_appears_during_a_group_is_not_replaced(tmp_path: Path) -> None:
    target = tmp_path / "out.txt"

    def pipe_in_the_way() -> None:
        with output_group():
            write_text_atomic(target, "x")
            os.mkfifo(target)

    with pytest.raises(WriteError, match="named pipe"):
        pipe_in_the_way()
    assert _kind(target) == "fifo"
    assert _leftovers(tmp_path) == []


def _files(z: Path) -> None:
    (z / "arena.yaml").write_text(yaml.safe_dump(ARENA), encoding="utf-8")
    save_camera_info(CAMERA, z / "camera.yaml")
    (z / "truth.tum").write_text("".join(f"{t} 0 0 1 0 0 0 1\n" for t in range(5)), encoding="utf-8")
    (z / "frames").mkdir()
    for i in range(2):
        cv2.imwrite(str(z / "frames" / f"f{i}.png"), np.full((48, 64, 3), 100, np.uint8))


def _run(z: Path, *argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *argv], cwd=z, capture_output=True, text=True, timeout=120, check=False,
        stdin=subprocess.DEVNULL,
    )  # fmt: skip


REPLAY = ("ipt.receiver.cli", "replay", "--config", "arena.yaml", "--camera", "camera.yaml", "--fps", "120",
          "--video", "frames", "--output")  # fmt: skip
EVAL = ("ipt.cli", "eval", "--truth", "truth.tum", "--poses", "truth.tum", "--json")
SENDER = ("ipt.sender.cli", "--config", "arena.yaml", "--sink", "file", "--frames", "2", "--listen", "127.0.0.1:0",
          "--output")  # fmt: skip


def _one_line(proc: subprocess.CompletedProcess[str], *words: str) -> None:
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, proc.stderr
    last = proc.stderr.splitlines()[-1]
    assert [line for line in proc.stderr.splitlines() if ": error: " in line] == [last]
    for word in words:
        assert word in last, (word, last)


@pytest.mark.parametrize("argv", [REPLAY, EVAL, SENDER], ids=["replay", "eval", "sender"])
def test_the_tools_write_through_devices_and_refuse_pipes(tmp_path: Path, argv: tuple[str, ...]) -> None:
    _files(tmp_path)
    (tmp_path / "link").symlink_to(os.devnull)
    os.mkfifo(tmp_path / "fifo")
    linked = _run(tmp_path, *argv, "link")
    assert linked.returncode == 0, linked.stderr
    assert _kind(tmp_path / "link") == "link"
    _one_line(_run(tmp_path, *argv, "fifo"), "fifo", "named pipe")
    assert _kind(tmp_path / "fifo") == "fifo"
    full = _device(tmp_path / "full", 7)
    _one_line(_run(tmp_path, *argv, "full"), "full", "No space left")
    assert _kind(full) == "chr"
    assert _leftovers(tmp_path) == []


def _record(path: Path) -> Any:
    pytest.importorskip("mcap_ros2")
    from ipt.receiver.outputs.ros.record import McapRecorder

    recorder = McapRecorder(path)
    recorder.start()
    recorder.close()
    return recorder


def test_the_flight_log_follows_links_and_writes_through_devices(tmp_path: Path) -> None:
    (tmp_path / "link.mcap").symlink_to("real.mcap")
    assert _record(tmp_path / "link.mcap").completed
    assert _kind(tmp_path / "link.mcap") == "link"
    assert (tmp_path / "real.mcap").read_bytes().startswith(b"\x89MCAP")
    null = _device(tmp_path / "null", 3)
    _record(null)
    assert _kind(null) == "chr"
    assert _leftovers(tmp_path) == []


def test_the_flight_log_refuses_a_pipe(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "log.mcap")
    with pytest.raises(WriteError, match="named pipe"):
        _record(tmp_path / "log.mcap")
    assert _kind(tmp_path / "log.mcap") == "fifo"
    assert _leftovers(tmp_path) == []
