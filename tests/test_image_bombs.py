"""Issue 33 item 2: image bombs. An image whose header gives more pixels than the cap is refused (a still
image) or skipped and counted (a frame of a folder) before it is decoded."""

from __future__ import annotations

import io
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from ipt.config.camera_info import CameraInfo, save_camera_info
from ipt.imageio import MAX_IMAGE_PIXELS, ImageError, header_size, read_image, too_many_pixels, write_image
from ipt.receiver.capture.recording import VideoCapture
from ipt.videoio import open_frames

TINY_ARENA = {
    "projector": {"width_px": 320, "height_px": 288, "rate_hz": 60},
    "screen": {"width_m": 1.0, "height_m": 0.9},
    "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
    "modulation": {"delta_l": 8, "input_rate_hz": 30},
}
CAMERA = CameraInfo(width_px=64, height_px=48, fx_px=60.0, fy_px=60.0, cx_px=31.5, cy_px=23.5, name="bombs")


def png_header(width: int, height: int) -> bytes:
    """A PNG whose header says ``width`` x ``height`` grey pixels, followed by a few rows' worth of data: what a
    bomb looks like to anything that reads only its header (OpenCV allocates the whole image, then fails)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(100))) + chunk(b"IEND", b"")


def test_the_header_size_is_read_without_decoding() -> None:
    assert header_size(png_header(20000, 20000)) == (20000, 20000)
    assert header_size(b"not an image") is None
    assert too_many_pixels(png_header(6000, 4000)) is None  # a 24-megapixel photo is admitted
    assert MAX_IMAGE_PIXELS >= 6000 * 4000
    why = too_many_pixels(png_header(20000, 20000))
    assert why is not None
    assert "20000x20000 pixels (400.0 megapixels)" in why


@pytest.mark.parametrize("suffix", [".bmp", ".jpg", ".tiff", ".webp"])
def test_the_header_size_of_every_format_pillow_reads(suffix: str) -> None:
    """A camera's formats (BMP, JPEG) by Pillow's common plugins, loaded first; TIFF and WebP by the rest,
    loaded when those find nothing."""
    ok, data = cv2.imencode(suffix, np.zeros((30, 40), np.uint8))
    assert ok
    assert header_size(data.tobytes()) == (40, 30)


def test_a_still_image_bomb_is_refused_with_one_line(tmp_path: Path) -> None:
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(png_header(20000, 20000))
    with pytest.raises(ImageError, match=r"bomb\.png: 20000x20000 pixels .*more than the 50 megapixels"):
        read_image(bomb)


def _folder(tmp_path: Path, bomb_at: int, bomb: bytes) -> Path:
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        if i == bomb_at:
            (folder / f"{i}.png").write_bytes(bomb)
        else:
            write_image(folder / f"{i}.png", np.full((48, 64, 3), 80 + 40 * i, np.uint8))
    return folder


@pytest.mark.parametrize("bomb_at", [0, 1])
def test_a_folder_skips_and_counts_a_bomb_even_without_skip_bad(tmp_path: Path, bomb_at: int) -> None:
    # The sender plays a folder without skip_bad: a bomb must not stop it, nor be decoded.
    with open_frames(_folder(tmp_path, bomb_at, png_header(20000, 20000))) as source:
        frames = list(source)
        assert [f.shape for f in frames] == [(48, 64, 3)] * 2
        assert source.skipped == 1
        assert source.last_skipped is not None
        assert "megapixels" in source.last_skipped
        assert f"{bomb_at}.png" in source.last_skipped


def test_a_recording_skips_a_frame_larger_than_the_first_undecoded(tmp_path: Path) -> None:
    with open_frames(_folder(tmp_path, 1, png_header(640, 480)), skip_bad=True, grey=True) as source:
        assert len(list(source)) == 2
        assert source.skipped == 1
        assert source.last_skipped is not None
        assert "more than the first image 0.png's 64x48; not decoded" in source.last_skipped


def test_a_camera_recording_skips_a_first_frame_larger_than_the_camera(tmp_path: Path) -> None:
    folder = _folder(tmp_path, 0, png_header(640, 480))
    capture = VideoCapture(folder, 120.0, False, size=(64, 48), grey=True)
    capture.open()
    try:
        got = [frame.image.shape for frame in iter(capture.read, None)]
    finally:
        capture.close()
    assert got == [(48, 64), (48, 64)]
    assert capture.skipped == 1
    assert capture.last_skipped is not None
    assert "640x480 pixels (0.3 megapixels), more than the camera's 64x48; not decoded" in capture.last_skipped


def _run(*args: str | Path, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", *[str(a) for a in args]], cwd=cwd, capture_output=True, text=True, timeout=120,
        check=False, stdin=subprocess.DEVNULL,
    )  # fmt: skip


def test_the_sender_refuses_a_still_image_bomb(tmp_path: Path) -> None:
    arena = tmp_path / "arena.yaml"
    arena.write_text(yaml.safe_dump(TINY_ARENA), encoding="utf-8")
    (tmp_path / "bomb.png").write_bytes(png_header(20000, 20000))
    proc = _run("ipt.sender.cli", "--config", arena, "--image", "bomb.png", "--sink", "null", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "bomb.png: 20000x20000 pixels (400.0 megapixels), more than the 50 megapixels" in lines[0], lines


def test_replay_over_a_folder_skips_a_bomb_and_says_why(tmp_path: Path) -> None:
    arena = tmp_path / "arena.yaml"
    arena.write_text(yaml.safe_dump(TINY_ARENA), encoding="utf-8")
    save_camera_info(CAMERA, tmp_path / "camera.yaml")
    _folder(tmp_path, 1, png_header(20000, 20000))
    proc = _run(
        "ipt.receiver.cli", "replay", "--config", arena, "--camera", "camera.yaml", "--video", "frames", "--fps",
        "120", "--output", "poses.tum", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "1.png: 20000x20000 pixels (400.0 megapixels)" in proc.stderr, proc.stderr
    assert "1 unreadable frames skipped" in proc.stderr, proc.stderr


def test_the_sender_skips_and_says_a_bomb_in_its_video_folder(tmp_path: Path) -> None:
    arena = tmp_path / "arena.yaml"
    arena.write_text(yaml.safe_dump(TINY_ARENA), encoding="utf-8")
    _folder(tmp_path, 1, png_header(20000, 20000))
    proc = _run(
        "ipt.sender.cli", "--config", arena, "--video", "frames", "--sink", "file", "--frames", "8", "--output",
        "out.mkv", cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    said = [line for line in proc.stderr.splitlines() if "1.png: 20000x20000 pixels" in line]
    assert len(said) == 1, proc.stderr
    assert "skipped" in said[0]
    with open_frames(tmp_path / "out.mkv") as out:
        assert len(list(out)) == 8


@pytest.mark.parametrize("top_first", [False, True])
def test_a_plain_bmp_s_size_is_read_without_pillow_as_pillow_reads_it(top_first: bool) -> None:
    """An uncompressed 24-bit BMP (the benchmarks' frames; rows stored bottom first, or top first with a negative
    height) gives the size Pillow gives, and a bomb of one is refused, without Pillow's plugins."""
    from PIL import Image

    ok, encoded = cv2.imencode(".bmp", np.zeros((30, 40, 3), np.uint8))
    assert ok
    data = bytearray(encoded.tobytes())
    if top_first:
        struct.pack_into("<i", data, 22, -30)
    with Image.open(io.BytesIO(bytes(data))) as img:
        assert img.size == (40, 30)
    assert header_size(bytes(data)) == (40, 30)
    struct.pack_into("<ii", data, 18, 20000, 20000)  # a bomb's header: 20000x20000, its pixels never there
    why = too_many_pixels(bytes(data))
    assert why is not None
    assert "20000x20000 pixels" in why
