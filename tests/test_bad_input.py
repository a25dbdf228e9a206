"""Bad input to the receiver (issue 14): black, saturated and all-shadow frames, garbage, frames of another
size, JPEGs that do not decode, gaps in capture times. No exception escapes, the frame gives no pose, its
reason is counted, and the frames after it give poses again. On real rendered frames, through the pipeline
and through the daemon as a subprocess."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ipt.config.camera_info import load_camera_info
from ipt.config.models import PipelineConfig, load_arena_config
from ipt.receiver.core.pipeline import FrameResult, Pipeline
from ipt.receiver.detect.detector import pipeline_detector
from ipt.tagmap import grid_tag_map
from ipt.tum import read_tum
from ipt.videoio import open_frames

FPS = 120.0


@pytest.fixture(scope="module")
def frames(short_flight: Path) -> list[np.ndarray]:
    with open_frames(short_flight / "frames.mkv") as src:
        return list(src)


def _t_us(k: int) -> int:
    return round(k / FPS * 1e6)


def _spoiled(frames: list[np.ndarray]) -> dict[int, tuple[np.ndarray, str | None]]:
    """Frames of the flight replaced by bad ones, with the reason each must give (None: any but "pose")."""
    h, w = frames[0].shape[:2]
    noise = np.random.default_rng(14).integers(0, 256, (h, w, 3), dtype=np.uint8)
    return {
        12: (np.zeros((h, w, 3), np.uint8), "dark"),  # black: lens cap, camera not exposing
        13: (np.full((h, w, 3), 255, np.uint8), "saturated"),
        20: (np.asarray(frames[20] * 0.03, np.uint8), "dark"),  # all in shadow, no ambient light
        26: (np.asarray(frames[26] * 0.25, np.uint8), None),  # all in shadow, some ambient: no signal
        32: (noise, None),  # NaN-free garbage
        40: (np.ascontiguousarray(frames[40][: h // 2]), "wrong_size"),
    }


@pytest.mark.parametrize("grey", [False, True])
def test_bad_frames_give_no_pose_a_counted_reason_and_the_flight_goes_on(
    short_flight: Path, frames: list[np.ndarray], grey: bool
) -> None:
    bad = _spoiled(frames)
    camera = load_camera_info(short_flight / "camera.yaml")
    tag_map = grid_tag_map(load_arena_config(short_flight / "arena.yaml"))
    p = Pipeline(tag_map, camera, PipelineConfig(), 60.0, pipeline_detector(PipelineConfig().detector, tag_map.by_id))
    out: list[FrameResult] = []
    try:
        for k, frame in enumerate(frames):
            image = bad[k][0] if k in bad else frame
            if grey and image.ndim == 3:
                image = np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), np.uint8)
            out += p.process(k, image, _t_us(k))
        out += p.flush()
    finally:
        p.close()
    assert [r.index for r in out] == list(range(len(frames)))
    for k, (_, reason) in bad.items():
        assert out[k].pose is None, f"frame {k} gave a pose"
        assert out[k].reason != "pose"
        if reason is not None:
            assert out[k].reason == reason
    assert sum(p.reasons.values()) == len(frames)
    assert p.reasons["dark"] == 2
    assert p.reasons["saturated"] == p.reasons["wrong_size"] == 1
    # The flight goes on: poses again soon after each bad frame, none of them far off.
    truth = read_tum(short_flight / "groundtruth.tum")
    for k in bad:
        assert any(r.pose is not None for r in out[k + 1 : k + 6]), f"no pose within 5 frames after frame {k}"
    worst_m = max(float(np.linalg.norm(r.pose.position_m - truth.positions_m[r.index])) for r in out if r.pose)
    assert worst_m < 0.02


def test_a_gap_in_capture_times_is_named_and_pairing_starts_afresh(short_flight: Path, frames: list) -> None:  # type: ignore[type-arg]
    camera = load_camera_info(short_flight / "camera.yaml")
    cfg = PipelineConfig.model_validate({"demodulation": {"lookahead_frames": 0}})  # no later partners
    tag_map = grid_tag_map(load_arena_config(short_flight / "arena.yaml"))
    p = Pipeline(tag_map, camera, cfg, 60.0, pipeline_detector(cfg.detector, tag_map.by_id))
    out: list[FrameResult] = []
    try:
        for k in range(30):  # frames 10..19 lost, and the flight resumes 0.3 s later than its frame times
            if not 10 <= k < 20:
                out += p.process(k, frames[k], _t_us(k) + (300_000 if k >= 20 else 0))
        out += p.flush()
    finally:
        p.close()
    by_index = {r.index: r for r in out}
    assert by_index[20].reason == "time_gap"
    assert by_index[20].pose is None
    assert p.reasons["time_gap"] == 1
    assert all(by_index[k].partner is None or by_index[k].partner >= 20 for k in range(20, 30))
    assert any(by_index[k].pose is not None for k in range(21, 30))


@pytest.mark.slow
def test_the_daemon_counts_bad_frames_of_a_folder_and_exits_cleanly(short_flight: Path, tmp_path: Path) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    with open_frames(short_flight / "frames.mkv") as src:
        frames = [f for _, f in zip(range(40), src, strict=False)]
    h, w = frames[0].shape[:2]
    for k, rgb in enumerate(frames):
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        if k == 10:
            bgr = np.zeros_like(bgr)
        elif k == 11:
            bgr = np.full_like(bgr, 255)
        elif k == 20:
            bgr = cv2.resize(bgr, (w // 2, h // 2))
        path = folder / f"{k:03d}.{'jpg' if k == 30 else 'png'}"
        cv2.imwrite(str(path), bgr)
        if k == 30:  # a JPEG cut short: it does not decode
            path.write_bytes(path.read_bytes()[:200])
    done = subprocess.run(
        [
            *(sys.executable, "-m", "ipt.receiver.cli", "run", "--source", f"images:{folder}"),
            *("--camera", str(short_flight / "camera.yaml"), "--fps", str(FPS), "--send", "127.0.0.1:9"),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    final = [line for line in done.stderr.splitlines() if line.startswith("ipt-receiver: final:")]
    assert len(final) == 1, done.stderr
    assert "dark=1" in final[0]
    assert "saturated=1" in final[0]
    assert "unreadable frames skipped 2" in final[0]  # the small image and the broken JPEG
    assert "38 frames (38 captured)" in final[0]
    assert "030.jpg" in done.stderr  # the skipped file is named


def test_the_dark_test_by_counting_is_numpys_percentile() -> None:
    # exposure_problem decides "99th percentile below the dark level" by counting where that settles it:
    # the same answer as np.percentile on samples of every size, around the level and far from it.
    from ipt.receiver.core.framecheck import _percentile_99_below

    rng = np.random.default_rng(0)
    for _ in range(5000):
        spread = np.clip(rng.normal(rng.integers(0, 30), rng.integers(1, 10), rng.integers(1, 400)), 0, 255)
        sample, level = spread.astype(np.uint8), int(rng.integers(5, 20))
        assert _percentile_99_below(sample, level) == (np.percentile(sample, 99) < level)
