"""Uncompressed 24-bit BMP frames (what the benchmarks and ``ipt sim --frames-dir`` write) read by
:func:`ipt.imageio.decode_image`'s own path: the same RGB as OpenCV's decoder, as grey the luma a video of
the same frames gives, and every other BMP left to OpenCV as before."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from ipt.imageio import decode_image
from ipt.videoio import FfvWriter, open_frames

U8 = npt.NDArray[np.uint8]


def _bmp(bgr: U8) -> bytes:
    ok, buf = cv2.imencode(".bmp", bgr)
    assert ok
    return bytes(buf)


def _opencv(data: bytes, flag: int) -> U8:
    out = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
    assert out is not None
    return np.asarray(out, np.uint8)


@pytest.mark.parametrize("width", [1, 5, 8, 33, 64])  # rows padded to 4 bytes by 3, 1, 0, 1, 0 bytes
def test_a_24_bit_bmp_reads_as_opencv_reads_it_and_its_grey_is_the_luma(width: int) -> None:
    bgr = np.random.default_rng(width).integers(0, 256, (7, width, 3), dtype=np.uint8)
    data = _bmp(bgr)
    assert struct.unpack_from("<H", data, 28) == (24,)  # the file is the kind the own path reads
    rgb = decode_image(data, "rgb")
    assert rgb is not None
    assert rgb.flags["C_CONTIGUOUS"]
    np.testing.assert_array_equal(rgb, cv2.cvtColor(_opencv(data, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB))
    np.testing.assert_array_equal(decode_image(data, "unchanged"), _opencv(data, cv2.IMREAD_UNCHANGED))
    np.testing.assert_array_equal(decode_image(data, "grey"), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))


def test_the_grey_of_a_bmp_differs_from_opencvs_own_by_its_rounding_only() -> None:
    bgr = np.random.default_rng(1).integers(0, 256, (60, 80, 3), dtype=np.uint8)
    data = _bmp(bgr)
    grey, theirs = decode_image(data, "grey"), _opencv(data, cv2.IMREAD_GRAYSCALE)
    assert grey is not None
    diff = np.abs(grey.astype(int) - theirs)
    assert diff.max() == 1
    assert 0 < np.count_nonzero(diff) < diff.size  # noise has pixels either side of a half


def test_a_top_down_bmp_is_read_top_row_first() -> None:
    bgr = np.random.default_rng(2).integers(0, 256, (5, 6, 3), dtype=np.uint8)
    bottom_up = bytearray(_bmp(bgr))
    offset, stride = struct.unpack_from("<I", bottom_up, 10)[0], 20  # 6 pixels: 18 bytes, padded to 20
    rows = [bytes(bottom_up[offset + i * stride : offset + (i + 1) * stride]) for i in range(5)]
    top_down = bottom_up[:offset] + b"".join(reversed(rows))
    struct.pack_into("<i", top_down, 22, -5)
    np.testing.assert_array_equal(decode_image(bytes(top_down), "unchanged"), bgr)
    np.testing.assert_array_equal(_opencv(bytes(top_down), cv2.IMREAD_UNCHANGED), bgr)  # as OpenCV reads it


@pytest.mark.parametrize("top_down", [False, True])
def test_the_image_is_its_own_memory_not_a_view_of_the_file_bytes(top_down: bool) -> None:
    bgr = np.random.default_rng(3).integers(0, 256, (4, 4, 3), dtype=np.uint8)  # 12-byte rows: no padding
    data = bytearray(_bmp(bgr[::-1] if top_down else bgr))
    if top_down:  # the same rows, said to be stored top row first
        struct.pack_into("<i", data, 22, -4)
    images = {mode: decode_image(memoryview(data), mode) for mode in ("rgb", "grey", "unchanged")}
    np.testing.assert_array_equal(images["unchanged"], bgr)
    kept = {mode: np.array(img) for mode, img in images.items()}
    data[54:] = bytes(len(data) - 54)  # the reader's buffer overwritten by the next file
    for mode, img in images.items():
        np.testing.assert_array_equal(img, kept[mode])


def test_other_bmps_are_left_to_opencv() -> None:
    grey = np.random.default_rng(4).integers(0, 256, (6, 9), dtype=np.uint8)
    eight_bit = _bmp(grey)  # OpenCV writes a grey image as an 8-bit BMP with a palette
    assert struct.unpack_from("<H", eight_bit, 28) == (8,)
    np.testing.assert_array_equal(decode_image(eight_bit, "grey"), _opencv(eight_bit, cv2.IMREAD_GRAYSCALE))
    full = _bmp(np.dstack([grey] * 3))
    truncated = full[: len(full) - 10]  # pixels missing: whatever OpenCV makes of it, as before
    theirs = cv2.imdecode(np.frombuffer(truncated, np.uint8), cv2.IMREAD_GRAYSCALE)
    ours = decode_image(truncated, "grey")
    assert (ours is None and (theirs is None or theirs.size == 0)) or np.array_equal(ours, theirs)
    compressed = bytearray(full)
    struct.pack_into("<I", compressed, 30, 1)  # says RLE8: not the own path's
    theirs = cv2.imdecode(np.frombuffer(bytes(compressed), np.uint8), cv2.IMREAD_COLOR)
    ours = decode_image(bytes(compressed), "unchanged")
    assert (ours is None and (theirs is None or theirs.size == 0)) or np.array_equal(ours, theirs)


def test_a_bmp_folder_and_a_video_of_the_same_frames_give_the_same_grey_frames(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    frames = [rng.integers(0, 256, (36, 64, 3), dtype=np.uint8) for _ in range(3)]
    folder = tmp_path / "bmp"
    folder.mkdir()
    with FfvWriter(tmp_path / "frames.mkv", 64, 36, 120) as writer:
        for i, rgb in enumerate(frames):
            writer.write(rgb)
            (folder / f"{i:06d}.bmp").write_bytes(_bmp(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)))
    with open_frames(folder, grey=True) as images, open_frames(tmp_path / "frames.mkv", grey=True) as video:
        pairs = list(zip(images, video, strict=True))
    assert len(pairs) == 3
    for from_bmp, from_video in pairs:
        np.testing.assert_array_equal(from_bmp, from_video)
