"""Issue 33 items 3 and 5: content decoded and resized ahead of need, off the render's path; a loop's seam
prepared before it is due; the sender says once when the content cannot keep up.

The sender-level tests build the content as ``ipt-sender --video`` does (``ipt.sender.cli._scene``) and
give it an injected slow decoder: the file's frames, with a delay at each opening of the file and at each
frame. They run the real sender loop, paced, into the null sink, and count missed deadlines.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest

from ipt.config.models import ArenaConfig
from ipt.imageio import write_image
from ipt.sender import cli as sender_cli
from ipt.sender.content import VideoScene
from ipt.sender.display import NullSink
from ipt.sender.prefetch import PrefetchedVideo
from ipt.sender.server import run_sender
from ipt.videoio import FfvWriter, FrameSource, open_frames

U8 = npt.NDArray[np.uint8]
W, H = 320, 288
ARENA = {
    "projector": {"width_px": W, "height_px": H, "rate_hz": 60},
    "screen": {"width_m": 1.0, "height_m": 0.9},
    "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
    "modulation": {"delta_l": 8, "input_rate_hz": 30, "profile": "paper"},
}


def _video(path: Path, frames: int, fps: float, size: tuple[int, int] = (W, H)) -> Path:
    rng = np.random.default_rng(frames)
    with FfvWriter(path, size[0], size[1], fps) as writer:
        for _ in range(frames):
            writer.write(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8))
    return path


# --- the same frames as VideoScene ------------------------------------------------------------------


@pytest.mark.parametrize(("fps", "rate_hz"), [(30.0, 30.0), (24.0, 30.0), (60.0, 30.0)])
def test_the_frames_are_videoscenes_across_loops(tmp_path: Path, fps: float, rate_hz: float) -> None:
    path = _video(tmp_path / "v.mkv", 7, fps, (96, 64))
    indices = list(range(40))
    with VideoScene(path, 80, 48, cache_bytes=0) as old:
        want = [old.frame(i, rate_hz) for i in indices]
    for cache_bytes in (0, None):  # streamed at every loop, and decoded once and kept
        with PrefetchedVideo(path, 80, 48, cache_bytes=cache_bytes) as new:
            got = [new.frame(i, rate_hz) for i in indices]
        for i, (a, b) in enumerate(zip(want, got, strict=True)):
            assert np.array_equal(a, b), (cache_bytes, i)


def test_a_frame_asked_again_or_earlier_is_served(tmp_path: Path) -> None:
    path = _video(tmp_path / "v.mkv", 5, 30.0, (64, 48))
    with VideoScene(path, 64, 48, cache_bytes=0) as old, PrefetchedVideo(path, 64, 48, cache_bytes=0) as new:
        for i in (0, 1, 1, 3, 2, 12, 0, 7):
            assert np.array_equal(old.frame(i, 30.0), new.frame(i, 30.0)), i
        last = new.last_frame()
        assert last is not None
        assert np.array_equal(last, old.frame(7, 30.0))


def test_a_caller_may_modify_the_frame(tmp_path: Path) -> None:
    path = _video(tmp_path / "v.mkv", 3, 30.0, (64, 48))
    with PrefetchedVideo(path, 64, 48) as new:
        first = new.frame(0, 30.0)
        keep = first.copy()
        first[:] = 0
        assert np.array_equal(new.frame(3, 30.0), keep)


# --- the injected slow decoder -------------------------------------------------------------------------


class _Slow(FrameSource):
    """A real source whose opening costs ``open_s`` and each frame ``frame_s`` (slept: it stands for decoding)."""

    def __init__(self, inner: FrameSource, frame_s: float) -> None:
        self._inner, self._frame_s = inner, frame_s
        self.path, self.width, self.height = inner.path, inner.width, inner.height
        self.frame_count, self.fps = inner.frame_count, inner.fps

    def __next__(self) -> U8:
        frame = next(self._inner)
        time.sleep(self._frame_s)  # real: it stands for decoding, which the prefetch thread must overlap
        return frame

    def close(self) -> None:
        self._inner.close()


def _slow_decoder(monkeypatch: pytest.MonkeyPatch, open_s: float, frame_s: float) -> None:
    def slow_open(path: Any, **kwargs: Any) -> FrameSource:
        time.sleep(open_s)  # real: it stands for opening a file, which must happen ahead of its lap
        return _Slow(open_frames(path, **kwargs), frame_s)

    for module in ("ipt.videoio", "ipt.sender.content", "ipt.sender.prefetch"):
        monkeypatch.setattr(f"{module}.open_frames", slow_open, raising=False)


async def _play(arena: ArenaConfig, content: Path, frames: int) -> tuple[int, list[str]]:
    """The sender, paced into the null sink, with the content ``ipt-sender --video`` makes: missed deadlines and
    the log, with a last line saying how often the content thread had to wait for a frame (``waits=None``: the
    content has no buffer to wait on)."""
    args = argparse.Namespace(video=str(content), image=None)
    scene, rate_hz = sender_cli._scene(args, arena)
    lines: list[str] = []
    try:
        stats = await run_sender(
            arena, NullSink(), scene, frames=frames, listen=None, log=lines.append, install_signal_handlers=False,
            input_rate_hz=rate_hz,
        )  # fmt: skip
    finally:
        close = getattr(scene, "close", None)
        if close is not None:
            close()
    assert stats.frames == frames
    lines.append(f"waits={getattr(scene, 'waits', None)}")
    return stats.missed, lines


@pytest.fixture
def arena() -> ArenaConfig:
    return ArenaConfig.model_validate(ARENA)


@pytest.mark.asyncio
async def test_the_loop_seam_is_prepared_ahead(
    tmp_path: Path, arena: ArenaConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A 24-frame clip (0.8 s) whose every opening costs 0.3 s: at each loop the file is opened again (its frames
    # are not kept: no cache); on the render's path that opening cost a deadline or more at every seam.
    clip = _video(tmp_path / "clip.mkv", 24, 30.0)
    monkeypatch.setattr("ipt.sender.prefetch.CACHE_BYTES", 0, raising=False)
    _slow_decoder(monkeypatch, open_s=0.3, frame_s=0.004)
    missed, lines = await _play(arena, clip, 360)  # six seconds: seven seams
    # The decoder kept ahead: the content thread never waited for a frame (5def445's code missed 14 deadlines
    # here; a machine loaded 10 times over its cores can cost a few without any content).
    assert lines[-1] == "waits=0", lines
    assert missed <= 5, lines


@pytest.mark.asyncio
async def test_large_photos_are_decoded_ahead(
    tmp_path: Path, arena: ArenaConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Four photos, each taking 0.15 s to decode (a 24-megapixel JPEG here), shown one an input frame (33 ms).
    folder = tmp_path / "photos"
    folder.mkdir()
    for k in range(4):
        write_image(folder / f"photo{k}.jpg", np.full((H * 2, W * 2, 3), 60 * k, np.uint8))
    _slow_decoder(monkeypatch, open_s=0.0, frame_s=0.15)
    missed, lines = await _play(arena, folder, 120)
    assert lines[-1] == "waits=0", lines  # 5def445's code missed 59 of the 120 deadlines here
    assert missed <= 5, lines


@pytest.mark.asyncio
async def test_content_that_cannot_keep_up_is_said_once(
    tmp_path: Path, arena: ArenaConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    clip = _video(tmp_path / "clip.mkv", 12, 30.0)
    monkeypatch.setattr("ipt.sender.prefetch.CACHE_BYTES", 0, raising=False)
    _slow_decoder(monkeypatch, open_s=0.0, frame_s=0.06)  # 60 ms a frame for frames due every 33 ms
    _, lines = await _play(arena, clip, 180)
    said = [line for line in lines if "cannot keep up" in line]
    assert len(said) == 1, lines
    assert "clip.mkv" in said[0]
    assert "ms a frame" in said[0]
