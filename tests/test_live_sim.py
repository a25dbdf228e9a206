"""benchmarks/live_sim.py: the daemon's live rule on measured processing times, stretched by ``--slow``. A worker
infinitely fast takes every frame in order, so its poses are exactly a replay's; a slow one drops frames and its
poses come out late; the command refuses a folder that is not a rendered flight in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from benchmodule import BENCHMARKS, load_benchmark
from flightpipeline import flight_frames, flight_pipeline

from ipt.config.models import PipelineConfig

LIVE_SIM = BENCHMARKS / "live_sim.py"
FPS = 120.0


def _bench() -> ModuleType:
    return load_benchmark("live_sim")


@pytest.fixture(scope="module")
def frames(short_flight: Path) -> list[np.ndarray]:
    return flight_frames(short_flight)


def test_an_instant_worker_takes_every_frame_and_poses_as_a_replay(
    short_flight: Path, frames: list[np.ndarray]
) -> None:
    bench = _bench()
    live = flight_pipeline(short_flight, PipelineConfig())
    replay = flight_pipeline(short_flight, PipelineConfig())
    try:
        out = bench.live_round(live, frames, FPS, 1e-6)
        expected = {}
        for k, frame in enumerate(frames):
            expected.update({r.index: r for r in replay.process(k, frame, round(k * 1e6 / FPS))})
        expected.update({r.index: r for r in replay.flush()})
    finally:
        live.close()
        replay.close()
    assert sorted(out) == list(range(len(frames)))
    posed = [k for k in out if out[k][1].pose is not None]
    assert len(posed) > len(frames) // 2
    for k in range(len(frames)):
        got, want = out[k][1], expected[k]
        assert (got.pose is None) == (want.pose is None)
        if got.pose is not None and want.pose is not None:
            np.testing.assert_array_equal(got.pose.position_m, want.pose.position_m)


def test_a_slow_worker_drops_frames_and_its_poses_come_out_late(short_flight: Path, frames: list[np.ndarray]) -> None:
    bench = _bench()
    pipeline = flight_pipeline(short_flight, PipelineConfig())
    try:
        out = bench.live_round(pipeline, frames, FPS, 20.0)
    finally:
        pipeline.close()
    assert len(out) < len(frames)  # frames it never took have no result
    truth = bench.read_tum(short_flight / "groundtruth.tum")
    figures = bench._figures(out, len(frames), FPS, truth)
    assert figures["frames_processed"] == len(out)
    if figures["poses"]:
        assert figures["latency_ms"]["p50"] > 1e3 / FPS  # each pose waited at least a frame's stretched processing


def test_a_folder_without_a_flight_is_refused_in_one_line(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(LIVE_SIM), "--video", str(tmp_path)], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2
    assert "no camera.yaml and groundtruth.tum" in proc.stderr
    assert "Traceback" not in proc.stderr
