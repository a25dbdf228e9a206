"""Reading image after image into one kept buffer (:class:`ipt.fileio.FileBuffer`) and finding an image's size
from the first bytes of its file (:func:`ipt.imageio.header_size`): the same bytes and sizes as whole reads."""

from __future__ import annotations

import io
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from ipt.fileio import FileBuffer, ReadError, read_bytes_file
from ipt.imageio import HEADER_PREFIX_BYTES, header_size
from ipt.videoio import open_frames


def test_a_kept_buffer_gives_each_file_its_own_bytes(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    sizes = [5000, 12, 0, 70_000, 4999, 70_001, 1]
    files = []
    for i, n in enumerate(sizes):
        f = tmp_path / f"f{i}"
        f.write_bytes(rng.integers(0, 256, n, dtype=np.uint8).tobytes())
        files.append(f)
    buffer = FileBuffer()
    for f in files:
        assert bytes(buffer.read(f, max_bytes=100_000)) == f.read_bytes() == read_bytes_file(f, max_bytes=100_000)


def test_a_kept_buffer_refuses_what_a_whole_read_refuses(tmp_path: Path) -> None:
    big = tmp_path / "big"
    big.write_bytes(bytes(1001))
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    buffer = FileBuffer()
    with pytest.raises(ReadError, match="too large"):
        buffer.read(big, max_bytes=1000)
    with pytest.raises(ReadError, match="not a regular file"):
        buffer.read(fifo)  # no writer: a blocking open would wait for ever
    with pytest.raises(ReadError, match="no such file"):
        buffer.read(tmp_path / "absent")
    with pytest.raises(ReadError, match="is a directory"):
        buffer.read(tmp_path)
    assert bytes(buffer.read(big, max_bytes=1001)) == bytes(1001)  # the buffer still works after refusals


def test_an_image_folder_gives_the_frames_a_whole_read_decodes(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    images = [rng.integers(0, 256, (48, 64, 3), dtype=np.uint8) for _ in range(4)]
    for i, img in enumerate(images):
        assert cv2.imwrite(str(tmp_path / f"{i:03d}.bmp"), img)
    with open_frames(tmp_path, grey=True) as source:
        frames = list(source)
    assert len(frames) == 4
    for frame, image in zip(frames, images, strict=True):  # each its own array: the next read does not overwrite it
        assert np.array_equal(frame, cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))  # a 24-bit BMP's grey: the luma


def _jpeg_with_metadata_first(metadata_bytes: int) -> bytes:
    """A 40×30 JPEG whose frame header comes after an application segment padded to ``metadata_bytes``."""
    out = io.BytesIO()
    Image.new("RGB", (40, 30), (90, 120, 200)).save(out, "JPEG")
    jpeg = out.getvalue()
    segments = []
    left = metadata_bytes
    while left > 0:  # APP segments hold at most 65533 bytes each
        n = min(left, 65_000)
        segments.append(b"\xff\xe1" + (n + 2).to_bytes(2, "big") + bytes(n))
        left -= n
    return jpeg[:2] + b"".join(segments) + jpeg[2:]


@pytest.mark.parametrize("metadata_bytes", [100, HEADER_PREFIX_BYTES + 5000])
def test_a_size_is_found_before_or_after_the_first_bytes(metadata_bytes: int) -> None:
    data = _jpeg_with_metadata_first(metadata_bytes)
    assert (len(data) > HEADER_PREFIX_BYTES) == (metadata_bytes > HEADER_PREFIX_BYTES)
    assert header_size(data) == (40, 30)
    assert header_size(memoryview(data)) == (40, 30)
