"""How a video is decoded depends on how it is read: a recording fed to the daemon at a camera's rate
(``--realtime``) is decoded without frame threads, whose start and look-ahead cost ~0.1 s of processor time
before the first pose (issue 29, target 4); a replay, which reads as fast as it can, keeps them. The frames are
the same either way. The threads are seen as the operating system lists them (Linux: /proc)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from ipt.receiver.capture.recording import VideoCapture
from ipt.videoio import FfvWriter, open_frames

pytestmark = [
    pytest.mark.skipif(not os.path.isdir("/proc/self/task"), reason="lists threads through /proc"),
    pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="one processor: the decoder starts no frame threads"),
]


def _frame_threads() -> int:
    """This process's threads that decode frames for FFmpeg (named ``av:CODEC:dfN`` by PyAV)."""
    count = 0
    for task in os.listdir("/proc/self/task"):
        try:
            name = Path(f"/proc/self/task/{task}/comm").read_text(encoding="ascii").strip()
        except OSError:
            continue
        count += name.startswith("av:") and ":df" in name
    return count


MANY_CPUS = pytest.mark.skipif(
    len(os.sched_getaffinity(0)) < 2,
    reason="FFmpeg's automatic threading starts no frame threads for a process allowed one CPU (taskset -c N)",
)


@pytest.fixture
def video(tmp_path: Path) -> Path:
    rng = np.random.default_rng(3)
    path = tmp_path / "frames.mkv"
    with FfvWriter(path, 64, 48, 120) as writer:
        for _ in range(12):
            writer.write(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    return path


def _read_all(cap: VideoCapture) -> tuple[list[np.ndarray], int]:
    """Every frame of ``cap``, and the most frame-decoding threads seen while reading."""
    cap.open()
    frames, most = [], 0
    try:
        while (frame := cap.read()) is not None:
            frames.append(frame.image)
            most = max(most, _frame_threads())
    finally:
        cap.close()
    return frames, most


@MANY_CPUS
def test_paced_recording_decodes_without_frame_threads_and_gives_the_same_frames(video: Path) -> None:
    before = _frame_threads()
    now = [0.0]
    paced = VideoCapture(video, None, True, clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s))
    paced_frames, paced_threads = _read_all(paced)
    fast_frames, fast_threads = _read_all(VideoCapture(video, None, False))
    assert len(paced_frames) == len(fast_frames) == 12
    assert all(np.array_equal(a, b) for a, b in zip(paced_frames, fast_frames, strict=True))
    assert paced_threads == before  # no frame threads started for the paced reading
    assert fast_threads > before  # (the count sees them when they are there)


@MANY_CPUS
def test_open_frames_starts_frame_threads_only_unpaced(video: Path) -> None:
    before = _frame_threads()
    with open_frames(video, paced=True) as source:
        next(source)
        assert _frame_threads() == before
    with open_frames(video) as source:
        next(source)
        assert _frame_threads() > before


def test_grey_frames_of_an_ffv1_video_are_opencvs_luma_of_its_rgb_frames(tmp_path: Path) -> None:
    """Grey frames of FfvWriter's ``bgr0`` video are read in place (no conversion to RGB first): the same
    luma, to the bit, as OpenCV's of the RGB frames, at an odd width too (rows padded in the decoder)."""
    import cv2

    rng = np.random.default_rng(5)
    path = tmp_path / "odd.mkv"
    with FfvWriter(path, 37, 21, 30) as writer:
        for _ in range(4):
            writer.write(rng.integers(0, 256, (21, 37, 3), dtype=np.uint8))
    with open_frames(path) as rgb, open_frames(path, grey=True, paced=True) as grey:
        pairs = list(zip(rgb, grey, strict=True))
    assert len(pairs) == 4
    for colour, luma in pairs:
        assert luma.shape == (21, 37)
        assert luma.flags.c_contiguous
        assert np.array_equal(luma, cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY))
