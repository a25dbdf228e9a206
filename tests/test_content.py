"""The content scenes: the generated map, a still image, a looped video."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ipt.sender.content import ContentError, ContentSource, GeneratedScene, StillImageScene, VideoScene
from ipt.videoio import FfvWriter, VideoError

W, H = 320, 360


@pytest.fixture(scope="module")
def scene() -> GeneratedScene:
    return GeneratedScene(W, H, seed=3)


def _mad(a: npt.NDArray[np.uint8], b: npt.NDArray[np.uint8]) -> float:
    return float(np.mean(np.abs(a.astype(np.int16) - b.astype(np.int16))))


def test_generated_frame_shape_and_dtype(scene: GeneratedScene) -> None:
    f = scene.frame(0, 60.0)
    assert f.shape == (H, W, 3)
    assert f.dtype == np.uint8
    assert f.flags["C_CONTIGUOUS"]


@settings(max_examples=20, deadline=None)
@given(
    w=st.integers(8, 400),
    h=st.integers(8, 400),
    index=st.integers(0, 100_000),
    rate=st.sampled_from([24.0, 59.94, 60.0, 120.0]),
)
def test_generated_any_size_and_time(w: int, h: int, index: int, rate: float) -> None:
    f = GeneratedScene(w, h, seed=1).frame(index, rate)
    assert f.shape == (h, w, 3)
    assert f.dtype == np.uint8


def test_generated_is_deterministic(scene: GeneratedScene) -> None:
    again = GeneratedScene(W, H, seed=3)
    for index in (0, 77, 1234):
        assert np.array_equal(scene.frame(index, 60.0), again.frame(index, 60.0))
    # Asking out of order gives the same picture: no hidden state between calls.
    assert np.array_equal(scene.frame(77, 60.0), again.frame(77, 60.0))
    assert not np.array_equal(scene.frame(77, 60.0), GeneratedScene(W, H, seed=4).frame(77, 60.0))


def test_same_time_at_different_rates(scene: GeneratedScene) -> None:
    # Frame 120 at 60 Hz and frame 240 at 120 Hz are both t = 2 s.
    assert np.array_equal(scene.frame(120, 60.0), scene.frame(240, 120.0))


def test_frames_change_slowly() -> None:
    scene = GeneratedScene(640, 720, seed=3)
    rate = 60.0
    steps = [_mad(scene.frame(k, rate), scene.frame(k + 1, rate)) for k in range(300, 360)]
    far = _mad(scene.frame(300, rate), scene.frame(300 + 20 * 60, rate))
    assert all(d > 0 for d in steps), "every input frame should differ from the previous one"
    # Most steps only move the marker; a whole-pixel pan or zoom step of the map is bigger, but a
    # consecutive pair always stays far closer than two frames 20 s apart.
    assert float(np.median(steps)) < 0.2
    assert max(steps) < far / 3, f"largest step {max(steps):.2f}, 20 s apart {far:.2f}"


def test_route_grows(scene: GeneratedScene) -> None:
    # Within one search cycle the route (saturated blue) covers more of the screen as it grows.
    def blue(img: npt.NDArray[np.uint8]) -> int:
        r, g, b = (img[..., c].astype(int) for c in range(3))
        return int(np.count_nonzero((b > 200) & (r < 80) & (g > 100) & (g < 160)))

    early, late = scene.frame(int(3.0 * 60), 60.0), scene.frame(int(7.0 * 60), 60.0)
    assert blue(late) > blue(early) > 0


def test_has_saturated_white_and_black() -> None:
    f = GeneratedScene(480, 540, seed=0).frame(500, 60.0)
    white = np.all(f >= 250, axis=2).mean()
    black = np.all(f <= 5, axis=2).mean()
    assert white > 0.01
    assert black > 0.01
    # and plenty of mid-tones too: it is a map, not a bar code
    assert np.all((f > 60) & (f < 245), axis=2).mean() > 0.4


def test_bad_arguments() -> None:
    with pytest.raises(ContentError, match="width_px"):
        GeneratedScene(0, 10)
    with pytest.raises(ContentError, match="rate_hz"):
        GeneratedScene(10, 10).frame(0, 0.0)


def test_still_image_resizes() -> None:
    img = np.zeros((30, 40, 3), dtype=np.uint8)
    img[:, :20] = (255, 0, 0)
    img[:, 20:] = (0, 0, 255)
    still: ContentSource = StillImageScene(img, 80, 60)
    f = still.frame(5, 60.0)
    assert f.shape == (60, 80, 3)
    assert f.dtype == np.uint8
    assert f[30, 5].tolist() == [255, 0, 0]
    assert f[30, 75].tolist() == [0, 0, 255]
    f[:] = 0  # the caller owns the returned array
    assert np.array_equal(still.frame(6, 60.0), cv2.resize(img, (80, 60), interpolation=cv2.INTER_AREA))


def test_still_image_rejects_non_rgb() -> None:
    with pytest.raises(ContentError, match="H×W×3 uint8"):
        StillImageScene(np.zeros((30, 40), dtype=np.uint8), 80, 60)


def _write_numbered_video(path: Path, n: int, fps: float) -> None:
    """Frame k is filled with the value 10·k + 5 (so k can be read back from any pixel)."""
    with FfvWriter(path, 32, 24, fps) as writer:
        for k in range(n):
            writer.write(np.full((24, 32, 3), 10 * k + 5, dtype=np.uint8))


def _number(img: npt.NDArray[np.uint8]) -> int:
    return (int(img[img.shape[0] // 2, img.shape[1] // 2, 0]) - 5) // 10


@pytest.mark.parametrize("cache_bytes", [512 * 2**20, 0], ids=["cached", "reopened"])
def test_video_scene_loops(tmp_path: Path, cache_bytes: int) -> None:
    path = tmp_path / "clip.mkv"
    _write_numbered_video(path, 5, fps=10)
    with VideoScene(path, 16, 12, cache_bytes=cache_bytes) as video:
        assert video.fps == pytest.approx(10.0)
        frames = [video.frame(i, 10.0) for i in range(12)]
        assert all(f.shape == (12, 16, 3) and f.dtype == np.uint8 for f in frames)
        assert [_number(f) for f in frames] == [0, 1, 2, 3, 4, 0, 1, 2, 3, 4, 0, 1]
        # At twice the file's rate every file frame is shown twice.
        assert [_number(video.frame(i, 20.0)) for i in range(12)] == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 0, 0]
        # Going back in time works too.
        assert _number(video.frame(3, 10.0)) == 3
        if cache_bytes == 0:
            assert video.reopens >= 2
        else:
            assert video.reopens == 0


@pytest.mark.parametrize("cache_bytes", [512 * 2**20, 0], ids=["cached", "reopened"])
def test_video_scene_keeps_the_last_frame_it_gave_for_when_the_file_fails(tmp_path: Path, cache_bytes: int) -> None:
    path = tmp_path / "clip.mkv"
    _write_numbered_video(path, 3, fps=10)
    with VideoScene(path, 16, 12, cache_bytes=cache_bytes) as video:
        assert video.last_frame() is None  # nothing given yet
        for i in (0, 1, 2, 4, 4, 1):  # streamed, served again, from the cache (or re-opened), looped
            given = video.frame(i, 10.0)
            given[:] = 0  # the caller draws on its copy (the sender's overlay)...
            last = video.last_frame()
            assert last is not None
            assert _number(last) == i % 3
        if cache_bytes == 0:  # not cached: the file goes away, reading fails, the last good frame stays
            path.unlink()
            with pytest.raises(VideoError, match=r"clip\.mkv"):
                video.frame(3, 10.0)  # file frame 0: before the last one read, so the file is re-opened
            last = video.last_frame()
            assert last is not None
            assert _number(last) == 1


def test_video_scene_ntsc_rate_maps_one_to_one(tmp_path: Path) -> None:
    path = tmp_path / "ntsc.mkv"
    _write_numbered_video(path, 20, fps=60000 / 1001)
    with VideoScene(path, 32, 24) as video:
        assert [_number(video.frame(i, 60000 / 1001)) for i in range(20)] == list(range(20))


def test_video_scene_from_image_folder(tmp_path: Path) -> None:
    for k in range(3):
        img = np.full((24, 32, 3), 10 * k + 5, dtype=np.uint8)
        assert cv2.imwrite(str(tmp_path / f"f{k}.png"), img)
    video = VideoScene(tmp_path, 32, 24)
    assert video.fps is None  # a folder has no rate: one file frame per input frame
    assert [_number(video.frame(i, 120.0)) for i in range(7)] == [0, 1, 2, 0, 1, 2, 0]
    video.close()
    with VideoScene(tmp_path, 32, 24, fps=60.0) as video:
        assert [_number(video.frame(i, 120.0)) for i in range(6)] == [0, 0, 1, 1, 2, 2]
