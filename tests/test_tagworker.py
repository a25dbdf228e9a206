"""The detector's helper process: the same detections as inline, replaced when its memory grows,
restarted when it dies or hangs, and never outliving its parent. Real pupil-apriltags, real processes."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import textwrap
import time

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from waiting import wait_until

from ipt.config.models import DetectorConfig, load_arena_config, shipped_config_path
from ipt.receiver.detect.detector import DetectorError, TagDetection, TagDetector, c_settings
from ipt.receiver.detect.tagworker import ProcessBackend, rss_anon_kb
from ipt.tagmap import grid_tag_map

U8 = npt.NDArray[np.uint8]


def _alive(pid: int) -> bool:
    """Whether ``pid`` is a running process (not a zombie)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.fixture(scope="module")
def views() -> list[U8]:
    """Perspective views of the shipped tag map at 640x360 (corners at fractional pixels), and one at
    1280x720 so that the shared image memory has to grow."""
    floor = grid_tag_map(load_arena_config(shipped_config_path("arena.yaml"))).render_image()
    h, w = floor.shape
    out = []
    for k, size in enumerate([(640, 360), (640, 360), (640, 360), (1280, 720)]):
        x0, y0 = 100 + 170 * k, 150 + 130 * k
        src = np.float32([[x0, y0], [x0 + 700, y0 + 20], [x0 + 690, y0 + 400], [x0 - 10, y0 + 390]])
        dst = np.float32([[0, 0], [size[0], 0], [size[0], size[1]], [0, size[1]]])
        view = cv2.warpPerspective(floor, cv2.getPerspectiveTransform(src, dst), size, flags=cv2.INTER_AREA)
        out.append(np.ascontiguousarray(view))
    assert all(v.shape[0] <= h and v.shape[1] <= w * 2 for v in out)
    return out


def _noise(rng: np.random.Generator) -> U8:
    """Blobby binary noise: many outlines, most with fewer than four corners (where the C code leaks)."""
    cells = (rng.random((90, 160)) > 0.5).astype(np.uint8) * 255
    blurred = cv2.GaussianBlur(cv2.resize(cells, (640, 360), interpolation=cv2.INTER_NEAREST), (0, 0), 2)
    return np.where(blurred > 127, 255, 0).astype(np.uint8)


def _same(a: tuple[TagDetection, ...], b: tuple[TagDetection, ...]) -> bool:
    return len(a) == len(b) and all(
        x.tag_id == y.tag_id
        and x.hamming == y.hamming
        and x.decision_margin == y.decision_margin
        and np.array_equal(x.corners_px, y.corners_px)
        for x, y in zip(a, b, strict=True)
    )


def test_helper_process_gives_exactly_the_inline_detections(views: list[U8]) -> None:
    inline = TagDetector(DetectorConfig(isolation="inline"))
    isolated = TagDetector(DetectorConfig(isolation="process"))
    try:
        assert isolated.isolated
        assert not inline.isolated
        assert isolated.effective_settings() == inline.effective_settings()
        found = 0
        for view in views:  # the last one is larger: the shared memory grows under the helper
            for image in (view, np.ascontiguousarray(255 - view)):
                a, b = isolated.detect(image), inline.detect(image)
                assert _same(a, b), (a, b)
                found += len(a)
        assert found >= 8, "the views show tags"
    finally:
        inline.close()
        isolated.close()


def test_helper_is_replaced_without_a_gap_once_its_memory_grows(views: list[U8]) -> None:
    backend = ProcessBackend(
        c_settings(DetectorConfig()), recycle_mb=0.001, warm_calls=5, check_every=5
    )
    inline = TagDetector(DetectorConfig(isolation="inline"))
    try:
        first = backend.helper_pids[0]
        baseline = rss_anon_kb(first)
        assert baseline is not None
        rng = np.random.default_rng(0)
        deadline = time.monotonic() + 30.0
        while backend.helper_pids[0] == first and time.monotonic() < deadline:
            backend.detect_raw(_noise(rng))
        assert backend.helper_pids[0] != first, "a fresh helper took over"
        assert backend.recycles >= 1
        assert backend.restarts == 0
        # The new helper answers like the old one, and the old one ends.
        view = views[0]
        raw = backend.detect_raw(view)
        assert [(d[0], d[1]) for d in raw] == [
            (d[0], d[1]) for d in inline.backend.detect_raw(view)
        ]
        deadline = time.monotonic() + 10.0
        while _alive(first) and time.monotonic() < deadline:
            for _ in range(5):
                backend.detect_raw(_noise(rng))
        assert not _alive(first), "the replaced helper exited"
    finally:
        inline.close()
        backend.close()


def test_killed_helper_fails_one_call_and_the_next_gets_a_new_one(views: list[U8]) -> None:
    det = TagDetector(DetectorConfig())
    try:
        assert isinstance(det.backend, ProcessBackend)
        expected = det.detect(views[0])
        assert expected
        pid = det.backend.helper_pids[0]
        os.kill(pid, signal.SIGKILL)
        with pytest.raises(DetectorError, match="exit code -9"):
            det.detect(views[0])
        assert _same(det.detect(views[0]), expected)
        assert det.backend.helper_pids[0] != pid
        assert det.backend.restarts == 1
    finally:
        det.close()


def test_hung_helper_is_given_up_after_the_reply_timeout(views: list[U8]) -> None:
    backend = ProcessBackend(c_settings(DetectorConfig()), reply_timeout_s=0.5)
    try:
        pid = backend.helper_pids[0]
        os.kill(pid, signal.SIGSTOP)
        t0 = time.monotonic()
        with pytest.raises(DetectorError, match="hung"):
            backend.detect_raw(views[0])
        assert time.monotonic() - t0 < 3.0
        assert not _alive(pid)
        assert backend.detect_raw(views[0])
    finally:
        backend.close()


def test_close_ends_every_helper_and_later_calls_say_so(views: list[U8]) -> None:
    backend = ProcessBackend(c_settings(DetectorConfig()))
    pids = backend.helper_pids
    backend.close()
    assert backend.helper_pids == []
    assert not any(_alive(p) for p in pids)
    with pytest.raises(DetectorError, match="closed"):
        backend.detect_raw(views[0])
    backend.close()  # idempotent


def test_a_helper_that_cannot_start_is_one_clear_error() -> None:
    settings = c_settings(DetectorConfig())
    settings["quad_decimate"] = "not a number"  # type: ignore[assignment]
    with pytest.raises(DetectorError, match=r"did not start \(exit code 1"):
        ProcessBackend(settings)


def test_helper_ends_when_its_parent_is_killed() -> None:
    script = textwrap.dedent(
        """
        import sys, time
        from ipt.config.models import DetectorConfig
        from ipt.receiver.detect.detector import TagDetector
        det = TagDetector(DetectorConfig())
        print(det.backend.helper_pids[0], flush=True)
        time.sleep(60)
        """
    )
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        helper = int(parent.stdout.readline())
        assert _alive(helper)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        with contextlib.suppress(AssertionError):  # said below
            wait_until(lambda: not _alive(helper), 5.0)
        assert not _alive(helper), "the helper saw its input close and exited"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()
        if parent.stdout is not None:
            parent.stdout.close()


def test_helper_ignores_the_terminal_interrupt_its_parent_handles(views: list[U8]) -> None:
    backend = ProcessBackend(c_settings(DetectorConfig()))
    try:
        pid = backend.helper_pids[0]
        os.kill(pid, signal.SIGINT)
        os.kill(pid, signal.SIGTERM)
        # A round trip through the helper: the signals were delivered before it answered (at its read's return).
        assert backend.detect_raw(views[0])
        assert backend.restarts == 0
        assert _alive(pid)
    finally:
        backend.close()
