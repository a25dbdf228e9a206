"""Motion capture against IPT: the time offset, the SE(3) fit and the body rotation, and ipt eval on MCAP."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ipt.align import AlignError, align, fit_se3, time_offset_by_speed
from ipt.geometry import matrix_from_quat_wxyz, matrix_from_ypr, quat_wxyz_from_matrix, rotation_angle_rad
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.outputs.mavlink.output import Mounting
from ipt.receiver.outputs.ros.frames import RosMessageMaker, RosNames, StampClock
from ipt.receiver.outputs.ros.record import McapRecorder
from ipt.tum import Trajectory, read_tum, write_tum

R_MOCAP = matrix_from_ypr(0.6, 0.02, -0.03)  # mocap world -> arena
T_MOCAP = np.array([1.5, -0.7, 0.04])
R_BODY_CAM = matrix_from_ypr(1.2, 0.05, 3.1)  # camera axes -> the mocap rigid body's
OFFSET_S = 1234.5678


def _flight(rate_hz: float, seconds: float = 8.0) -> Trajectory:
    """A camera flying a figure of eight at varying speed, 0.8 m up, turning to face its way."""
    t = np.arange(0.0, seconds, 1.0 / rate_hz)
    phase = 2 * np.pi * t / seconds + 0.4 * np.sin(2 * np.pi * t / 3.0)  # speeding up and slowing down
    pos = np.stack([0.9 * np.sin(phase), 0.5 * np.sin(2 * phase), 0.8 + 0.05 * np.sin(3 * phase)], axis=1)
    quats = np.array([quat_wxyz_from_matrix(matrix_from_ypr(0.5 * np.sin(p), 0.03, -0.02)) for p in phase])
    return Trajectory(t + 10.0, pos, quats)


def _as_mocap(truth: Trajectory, noise_m: float = 0.0, seed: int = 0) -> Trajectory:
    """What the mocap system records of ``truth``: its own frame, its own clock, its own body axes."""
    rng = np.random.default_rng(seed)
    pos = (truth.positions_m - T_MOCAP) @ R_MOCAP + rng.normal(0.0, noise_m, truth.positions_m.shape)
    quats = np.array(
        [quat_wxyz_from_matrix(R_MOCAP.T @ matrix_from_quat_wxyz(q) @ R_BODY_CAM.T) for q in truth.quats_wxyz]
    )
    return Trajectory(truth.times_s + OFFSET_S, pos, quats)


def test_kabsch_recovers_a_rotation_and_translation() -> None:
    rng = np.random.default_rng(3)
    src = rng.normal(size=(50, 3))
    r, t = fit_se3(src, src @ R_MOCAP.T + T_MOCAP)
    np.testing.assert_allclose(r, R_MOCAP, atol=1e-12)
    np.testing.assert_allclose(t, T_MOCAP, atol=1e-12)
    assert np.linalg.det(fit_se3(src, -src)[0]) == pytest.approx(1.0)  # a proper rotation, never a reflection


def test_alignment_finds_offset_transform_and_body_rotation_of_exact_data() -> None:
    est = _flight(120.0)
    mocap = _as_mocap(_flight(240.0))  # a mocap system sampling faster, on another clock
    coarse, corr = time_offset_by_speed(mocap, est)
    assert abs(coarse - OFFSET_S) <= 0.006
    assert corr > 0.99
    a = align(mocap, est)
    assert abs(a.offset_s - OFFSET_S) < 0.0006
    assert np.degrees(rotation_angle_rad(a.r_arena_mocap.T @ R_MOCAP)) < 0.01
    np.testing.assert_allclose(a.t_arena_mocap_m, T_MOCAP, atol=2e-4)
    assert np.degrees(rotation_angle_rad(a.r_mocap_body_cam.T @ R_BODY_CAM)) < 0.05
    assert a.rms_m < 5e-4
    aligned = a.apply(mocap)
    inside = (est.times_s > aligned.times_s[0]) & (est.times_s < aligned.times_s[-1])
    interp = np.stack([np.interp(est.times_s[inside], aligned.times_s, aligned.positions_m[:, k]) for k in range(3)], 1)
    assert np.abs(interp - est.positions_m[inside]).max() < 1e-3


def test_alignment_of_noisy_poses_with_gaps() -> None:
    est = _flight(120.0)
    rng = np.random.default_rng(11)
    keep = rng.random(len(est)) > 0.3  # 70 % yield
    noisy = Trajectory(est.times_s[keep], est.positions_m[keep] + rng.normal(0, 0.003, (int(keep.sum()), 3)),
                       est.quats_wxyz[keep])  # fmt: skip
    noisy.positions_m[::97] += 0.2  # and a few wild poses
    a = align(_as_mocap(_flight(100.0), noise_m=0.0005, seed=2), noisy)
    assert abs(a.offset_s - OFFSET_S) < 0.002
    np.testing.assert_allclose(a.t_arena_mocap_m, T_MOCAP, atol=3e-3)
    assert np.degrees(rotation_angle_rad(a.r_arena_mocap.T @ R_MOCAP)) < 0.3
    assert a.rms_m < 0.006  # the wild poses left out of the fit


def test_nothing_to_align_is_an_error() -> None:
    still = Trajectory(np.arange(0, 2, 0.01), np.zeros((200, 3)), np.tile([1.0, 0, 0, 0], (200, 1)))
    with pytest.raises(AlignError, match="does not move"):
        align(still, _flight(120.0))
    short = Trajectory(np.arange(0, 0.02, 0.01), np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)))
    with pytest.raises(AlignError, match="too short"):
        align(short, _flight(120.0))


def _eval(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ipt.cli", "eval", *map(str, args)], capture_output=True, text=True, timeout=120
    )


def test_ipt_eval_aligns_a_mocap_file(tmp_path: Path) -> None:
    write_tum(tmp_path / "poses.tum", _flight(120.0))
    write_tum(tmp_path / "mocap.tum", _as_mocap(_flight(240.0)))
    proc = _eval("--truth", tmp_path / "mocap.tum", "--poses", tmp_path / "poses.tum", "--align", "--no-paper",
                 "--json", tmp_path / "r.json")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert f"truth time = estimate time + {OFFSET_S:.4f} s" in proc.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert max(report[f"mae_{axis}_m"] for axis in "xyz") < 1e-3, proc.stdout
    assert report["mae_yaw_deg"] < 0.05
    unaligned = _eval("--truth", tmp_path / "mocap.tum", "--poses", tmp_path / "poses.tum")
    assert unaligned.returncode == 2  # a different clock: no overlap at all without --align
    assert "no overlap in time" in unaligned.stderr
    bad = _eval("--truth", tmp_path / "mocap.tum", "--poses", tmp_path / "poses.tum", "--time-offset", "1")
    assert bad.returncode == 2
    assert bad.stderr.strip() == "ipt eval: error: --time-offset needs --align and a finite number of seconds"


def test_ipt_eval_reads_an_mcap_recording_like_its_tum(tmp_path: Path) -> None:
    truth = _flight(120.0, seconds=1.0)
    path = tmp_path / "flight.mcap"
    rec = McapRecorder(path)
    clock = StampClock(lambda: 1_800_000_000_000_000_000, lambda: 0.0)
    maker = RosMessageMaker(RosNames(), Mounting(), clock)
    rec.start()
    for k, (t, p, q) in enumerate(zip(truth.times_s, truth.positions_m, truth.quats_wxyz, strict=True)):
        pose = PoseEstimate(p + 0.001, matrix_from_quat_wxyz(q), (1, 2), 0.3, np.eye(3) * 1e-6, np.eye(3) * 1e-6)
        items = maker.frame(k, round(t * 1e6), 0.0, "pose", 2, pose)
        if k == 0:
            rec.set_metadata({"capture_time_offset_ns": str(clock.offset_ns)})
        rec.put(items)
    assert rec.close()
    write_tum(tmp_path / "truth.tum", truth)
    proc = _eval("--truth", tmp_path / "truth.tum", "--poses", path, "--no-paper", "--json", tmp_path / "r.json")
    assert proc.returncode == 0, proc.stderr
    assert "yield 120/120" in proc.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["mae_x_m"] == pytest.approx(0.001, abs=1e-6)  # the 1 mm we added (the TUM file rounds to 1 µm)
    wrong = _eval("--truth", tmp_path / "truth.tum", "--poses", path, "--topic", "/ipt/drone1/pose")
    assert wrong.returncode == 2
    assert wrong.stderr.strip().splitlines() == [f"ipt eval: error: {path}: no messages on /ipt/drone1/pose"]
    read_tum(tmp_path / "truth.tum")  # (the TUM written above is a valid one)
