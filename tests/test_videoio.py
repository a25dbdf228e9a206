"""Frames in and out: FFV1 round trips, image folders, and the errors users see."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from ipt.videoio import FfvWriter, VideoError, open_frames


def _random_frames(n: int, width: int, height: int, seed: int = 0) -> list[npt.NDArray[np.uint8]]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(n)]


def _write(path: Path, frames: list[npt.NDArray[np.uint8]], fps: float | Fraction = 120) -> None:
    h, w = frames[0].shape[:2]
    with FfvWriter(path, w, h, fps) as writer:
        for f in frames:
            writer.write(f)


def test_ffv1_round_trip_is_bit_exact(tmp_path: Path) -> None:
    frames = _random_frames(5, 64, 48)
    # Pure colours catch a swapped channel order, which random noise alone would hide in a mean.
    frames[0][:16] = (255, 0, 0)
    frames[0][16:32] = (0, 255, 0)
    frames[0][32:] = (0, 0, 255)
    out = tmp_path / "frames.mkv"
    _write(out, frames)
    with open_frames(out) as src:
        assert (src.width, src.height) == (64, 48)
        back = list(src)
    assert len(back) == len(frames)
    for i, (a, b) in enumerate(zip(frames, back, strict=True)):
        assert b.dtype == np.uint8
        assert b.shape == (48, 64, 3)
        assert b.flags["C_CONTIGUOUS"]
        assert np.array_equal(a, b), f"frame {i} differs"


def test_odd_frame_size_round_trips(tmp_path: Path) -> None:
    frames = _random_frames(2, 33, 17, seed=1)
    out = tmp_path / "odd.mkv"
    _write(out, frames, fps=30)
    with open_frames(out) as src:
        back = list(src)
    assert all(np.array_equal(a, b) for a, b in zip(frames, back, strict=True))


@pytest.mark.parametrize(
    ("fps", "expected"),
    [(120, 120.0), (30, 30.0), (59.94, 59.94), (Fraction(60000, 1001), 60000 / 1001), (2.5, 2.5)],
)
def test_fps_preserved(tmp_path: Path, fps: float | Fraction, expected: float) -> None:
    out = tmp_path / "rate.mkv"
    _write(out, _random_frames(3, 16, 16), fps=fps)
    with open_frames(out) as src:
        assert src.fps == pytest.approx(expected, rel=1e-12)


def test_writer_rate_as_fraction(tmp_path: Path) -> None:
    w120 = FfvWriter(tmp_path / "a.mkv", 8, 8, 120)
    w5994 = FfvWriter(tmp_path / "b.mkv", 8, 8, 59.94)
    try:
        assert w120.rate == Fraction(120, 1)
        assert w5994.rate == Fraction(2997, 50)
    finally:
        w120.abort()
        w5994.abort()
    assert list(tmp_path.iterdir()) == []


def _write_then_fail(out: Path, frames: list[npt.NDArray[np.uint8]], seen: list[Path]) -> None:
    h, w = frames[0].shape[:2]
    with FfvWriter(out, w, h, 60) as writer:
        for f in frames:
            writer.write(f)
        seen.extend(out.parent.iterdir())
        raise RuntimeError("boom")


def test_writer_into_missing_folder(tmp_path: Path) -> None:
    with pytest.raises(VideoError, match="cannot create"):
        FfvWriter(tmp_path / "no-such-dir" / "x.mkv", 8, 8, 30)


def test_partial_file_removed_on_exception(tmp_path: Path) -> None:
    out = tmp_path / "broken.mkv"
    seen_partial: list[Path] = []
    with pytest.raises(RuntimeError, match="boom"):
        _write_then_fail(out, _random_frames(2, 32, 24), seen_partial)
    # While writing, only a temporary file beside the target existed...
    assert len(seen_partial) == 1
    assert seen_partial[0].name.endswith(".partial.mkv")
    assert seen_partial[0] != out
    # ...and afterwards nothing is left at all.
    assert list(tmp_path.iterdir()) == []


def test_failed_write_leaves_existing_target_alone(tmp_path: Path) -> None:
    out = tmp_path / "keep.mkv"
    _write(out, _random_frames(2, 16, 16, seed=3))
    before = out.read_bytes()
    with pytest.raises(RuntimeError, match="boom"):
        _write_then_fail(out, _random_frames(1, 16, 16, seed=4), [])
    assert out.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["keep.mkv"]


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((24, 32, 3), dtype=np.float32),
        np.zeros((24, 32), dtype=np.uint8),
        np.zeros((24, 32, 4), dtype=np.uint8),
        np.zeros((32, 24, 3), dtype=np.uint8),
    ],
    ids=["float32", "grey", "rgba", "transposed"],
)
def test_writer_rejects_wrong_frames(tmp_path: Path, bad: npt.NDArray[np.generic]) -> None:
    out = tmp_path / "x.mkv"
    with pytest.raises(VideoError, match=r"x\.mkv"), FfvWriter(out, 32, 24, 30) as writer:
        writer.write(bad)  # type: ignore[arg-type]
    assert not out.exists()


def test_writer_accepts_non_contiguous_frames(tmp_path: Path) -> None:
    big = _random_frames(1, 64, 48, seed=5)[0]
    view = big[::2, ::2]  # 24 x 32, not contiguous
    out = tmp_path / "view.mkv"
    with FfvWriter(out, 32, 24, 30) as writer:
        writer.write(view)
    with open_frames(out) as src:
        assert np.array_equal(next(src), view)


def _save_png(path: Path, rgb: npt.NDArray[np.uint8]) -> None:
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def test_folder_natural_order(tmp_path: Path) -> None:
    # Each image is filled with its own number, so the order read back is visible in the pixels.
    numbers = [1, 2, 10, 3, 20, 11]
    for n in numbers:
        _save_png(tmp_path / f"frame{n}.png", np.full((6, 8, 3), n, dtype=np.uint8))
    (tmp_path / "notes.txt").write_text("not an image")
    with open_frames(tmp_path) as src:
        assert src.frame_count == len(numbers)
        assert src.fps is None
        assert (src.width, src.height) == (8, 6)
        order = [int(frame[0, 0, 0]) for frame in src]
    assert order == sorted(numbers)


def test_folder_rgb_order_and_grey_images(tmp_path: Path) -> None:
    colour = np.zeros((4, 5, 3), dtype=np.uint8)
    colour[..., 0] = 200  # red
    _save_png(tmp_path / "a.png", colour)
    assert cv2.imwrite(str(tmp_path / "b.png"), np.full((4, 5), 77, dtype=np.uint8))
    with open_frames(tmp_path) as src:
        first, second = list(src)
    assert first[0, 0].tolist() == [200, 0, 0]
    assert second.shape == (4, 5, 3)
    assert second[0, 0].tolist() == [77, 77, 77]


def test_folder_size_mismatch(tmp_path: Path) -> None:
    _save_png(tmp_path / "img1.png", np.zeros((6, 8, 3), dtype=np.uint8))
    _save_png(tmp_path / "img2.png", np.zeros((7, 8, 3), dtype=np.uint8))
    with open_frames(tmp_path) as src:
        next(src)
        with pytest.raises(VideoError, match=r"img2\.png.*8x7.*8x6"):
            next(src)


def test_empty_folder(tmp_path: Path) -> None:
    (tmp_path / "readme.txt").write_text("no images here")
    with pytest.raises(VideoError, match="no images"):
        open_frames(tmp_path)


def test_missing_path(tmp_path: Path) -> None:
    with pytest.raises(VideoError, match=r"missing\.mkv: no such file"):
        open_frames(tmp_path / "missing.mkv")


def test_empty_file_is_an_error(tmp_path: Path) -> None:
    bad = tmp_path / "frames.mkv"
    bad.write_bytes(b"")
    with pytest.raises(VideoError, match=r"frames\.mkv: not a video file"):
        open_frames(bad)


def test_text_file_is_an_error(tmp_path: Path) -> None:
    bad = tmp_path / "frames.mkv"
    bad.write_text("this is not a video\n" * 50)
    with pytest.raises(VideoError, match=r"frames\.mkv: not a video file") as info:
        open_frames(bad)
    assert "\n" not in str(info.value)


def test_video_without_frames_is_an_error(tmp_path: Path) -> None:
    out = tmp_path / "empty.mkv"
    with FfvWriter(out, 16, 16, 30):
        pass
    assert out.exists()
    with pytest.raises(VideoError, match=r"empty\.mkv: contains no frames"):
        open_frames(out)


def test_file_with_no_video_stream(tmp_path: Path) -> None:
    import av

    out = tmp_path / "audio.mka"
    with av.open(str(out), mode="w", format="matroska") as container:
        stream = container.add_stream("pcm_s16le", rate=8000)
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 800), dtype=np.int16), format="s16", layout="mono")
        frame.sample_rate = 8000
        for packet in stream.encode(frame):
            container.mux(packet)
        for packet in stream.encode(None):
            container.mux(packet)
    with pytest.raises(VideoError, match=r"audio\.mka: has no video stream"):
        open_frames(out)


def test_iteration_is_lazy_and_stops(tmp_path: Path) -> None:
    frames = _random_frames(4, 16, 8, seed=7)
    out = tmp_path / "lazy.mkv"
    _write(out, frames)
    src = open_frames(out)
    assert np.array_equal(next(src), frames[0])
    src.close()
    with pytest.raises(StopIteration):
        next(src)
