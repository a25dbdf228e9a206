"""``ipt demo``: the closed loop of sender, simulated camera and receiver, over real loopback UDP."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from waiting import until

from ipt.config.models import ArenaConfig, load_arena_config, shipped_config_path
from ipt.protocol import PosePacket, encode_pose
from ipt.sender.content import GeneratedScene
from ipt.sender.overlay import PALETTE, ArOverlay
from ipt.sender.server import run_sender
from ipt.sim.config import SimConfig
from ipt.sim.demo import ClosedLoopArena, LockstepProjector, SimClock
from ipt.tum import read_tum

DEMO = [sys.executable, "-m", "ipt.cli", "demo"]
RUN_TIMEOUT_S = 240.0
"""Upper bound on a demo subprocess here (0.5 s of flight takes well under 15 s)."""


@pytest.fixture(scope="module")
def arena() -> ArenaConfig:
    return load_arena_config(shipped_config_path("arena.yaml"))


def _summary(path: Path) -> dict[str, str]:
    """summary.txt's ``key: value`` lines."""
    pairs = (line.split(": ", 1) for line in path.read_text(encoding="utf-8").splitlines() if ": " in line)
    return {k: v for k, v in pairs}


def _leading_int(text: str) -> int:
    m = re.match(r"\d+", text)
    assert m is not None, text
    return int(m.group())


def test_demo_flies_the_closed_loop_and_scores_it(tmp_path: Path) -> None:
    out = tmp_path / "results"
    proc = subprocess.run(
        [*DEMO, "--seconds", "0.5", "--out", str(out)], capture_output=True, text=True, timeout=RUN_TIMEOUT_S
    )
    assert proc.returncode == 0, proc.stderr
    assert "X Error [m]" in proc.stdout
    assert "paper IPT" in proc.stdout
    assert str(out) in proc.stdout
    assert "x real time" in proc.stderr  # the status line
    for name in ("errors.png", "report.json", "poses.tum", "groundtruth.tum", "summary.txt"):
        assert (out / name).is_file(), name

    summary = _summary(out / "summary.txt")
    poses, sent = _leading_int(summary["poses"]), _leading_int(summary["packets sent"])
    assert _leading_int(summary["camera frames"]) == 60
    assert poses > 0
    assert sent == poses
    assert _leading_int(summary["packets accepted"]) == sent  # every one came round over loopback
    assert _leading_int(summary["packets rejected"]) == 0
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert report["n_estimates"] == poses
    assert report["closed_loop"]["packets_accepted"] == sent

    truth, est = read_tum(out / "groundtruth.tum"), read_tum(out / "poses.tum")
    assert len(truth) == 60
    assert len(est) == poses
    at = np.searchsorted(truth.times_s, est.times_s)
    assert np.all(at < len(truth))
    assert np.allclose(truth.times_s[at], est.times_s, atol=1e-6)
    errors = np.linalg.norm(est.positions_m - truth.positions_m[at], axis=1)
    assert float(np.median(errors)) < 0.030


def test_ctrl_c_stops_cleanly_and_scores_what_was_flown(tmp_path: Path) -> None:
    out = tmp_path / "results"
    proc = subprocess.Popen(
        [*DEMO, "--seconds", "30", "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stderr is not None
        deadline = time.monotonic() + 60.0
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stderr, selectors.EVENT_READ)
            while True:  # the status lines: wait until some poses went round
                assert sel.select(timeout=max(0.0, deadline - time.monotonic())), "no status line in time"
                line = proc.stderr.readline()
                assert line, "the demo ended before it was interrupted"
                m = re.search(r"simulated, (\d+) poses/s", line)
                if m and int(m.group(1)) > 0:
                    break
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, stderr
    assert "X Error [m]" in stdout
    summary = _summary(out / "summary.txt")
    assert "(interrupted)" in summary["simulated flight"]
    assert _leading_int(summary["packets accepted"]) == _leading_int(summary["packets sent"]) > 0
    assert len(read_tum(out / "poses.tum")) == _leading_int(summary["poses"])


@pytest.mark.asyncio
async def test_the_camera_sees_the_senders_output_with_the_drone_on_it(arena: ArenaConfig) -> None:
    pr = arena.projector
    projector = LockstepProjector(per_input=2)
    clock = SimClock()
    ar = ArOverlay(arena)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    listening: asyncio.Future[tuple[str, int]] = loop.create_future()
    sender = loop.create_task(
        run_sender(
            arena,
            projector,
            projector.gated(GeneratedScene(pr.width_px, pr.height_px, seed=0)),
            paced=False,
            listen=("127.0.0.1", 0),
            overlay=ar,
            log=lambda line: None,
            install_signal_handlers=False,
            stop=stop,
            overlay_clock=clock.now,
            on_listening=listening.set_result,
        )
    )
    try:
        address = await asyncio.wait_for(listening, 30)
        before = await asyncio.to_thread(projector.frame, 0)
        await asyncio.to_thread(projector.frame, 1)  # the same input frame: nothing more is let through
        await until(lambda: projector.held_for == 1, what="the sender held at the gate for input frame 1")
        assert projector.newest == 1  # the frames of input 1 are made only when asked for

        x, y = 0.3, -0.2  # a drone there, heard at simulated time 0.01 s
        clock.set(0.01)
        packet = PosePacket(vehicle_id=0, seq=0, capture_time_us=10_000, position_m=(x, y, 0.8), quat_wxyz=(0, 1, 0, 0))
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.sendto(encode_pose(packet), address)
        with contextlib.suppress(AssertionError):  # the track is checked below
            await until(ar.vehicle_ids, 2.0)
        track = ar.track(0)
        assert track is not None
        assert track.last_heard_s == 0.01
        after = await asyncio.to_thread(projector.frame, 2)

        u, v = ar.pixel_of(x, y)
        r = int(ar.radius_px * 0.6)
        x0, y0, x1, y1 = int(u) - r, int(v) - r, int(u) + r, int(v) + r
        colour = np.array(PALETTE[0], dtype=np.int16)

        def marker_share(frame: np.ndarray) -> float:
            patch = frame[y0:y1, x0:x1].astype(np.int16)
            return float(np.mean(np.abs(patch - colour).max(axis=2) <= 12))

        assert marker_share(before) < 0.05  # no drone before the packet
        assert marker_share(after) > 0.7  # its marker after it (modulated ±ΔL on tag pixels; the arrow on top)

        # The simulated camera's floor is exactly the sender's output frame.
        world = ClosedLoopArena(arena, SimConfig(), projector)
        region = (x0 - 100, y0 - 80, x1 + 120, y1 + 60)
        crop = await asyncio.to_thread(world.projector_crop, 2, region)
        assert np.array_equal(crop, after[region[1] : region[3], region[0] : region[2]])
        shown = projector.shown(2)
        assert shown is not None
        assert shown is after
    finally:
        stop.set()
        projector.stop()
        stats = await asyncio.wait_for(sender, 30)
    assert stats.accepted == 1
