"""Accuracy against ground truth: association, error statistics, table, figure and the CLI."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ipt.eval import (
    PAPER_IPT_TABLE_I,
    EvalError,
    associate,
    body_ypr_rad,
    evaluate,
    format_table,
    plot_report,
)
from ipt.geometry import (
    R_BODY_CAM_DOWNWARD,
    matrix_from_quat_wxyz,
    matrix_from_ypr,
    quat_wxyz_from_matrix,
    rot_z,
    ypr_from_matrix,
)
from ipt.tum import Trajectory, write_tum

F64 = npt.NDArray[np.float64]

#: A forward-looking camera: z_cam = x_body, x_cam = -y_body, y_cam = -z_body (columns: camera axes in
#: body FLU). Unlike R_BODY_CAM_DOWNWARD it is not symmetric, so it tells R from R.T.
R_BODY_CAM_FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _cam_quat(r_arena_body: F64, r_body_cam: F64 = R_BODY_CAM_DOWNWARD) -> F64:
    """Camera quaternion (R_arena_cam = R_arena_body @ R_body_cam) for a body attitude."""
    return quat_wxyz_from_matrix(r_arena_body @ r_body_cam)


def _flight(
    n: int = 60,
    pitch_deg: float = 10.0,
    roll_deg: float = -4.0,
    r_body_cam: F64 = R_BODY_CAM_DOWNWARD,
    yaw_offset_deg: float = 0.0,
    dt: float = 1.0 / 30.0,
) -> tuple[Trajectory, list[F64]]:
    """A camera trajectory of a tilted body circling and turning; also returns the body matrices."""
    t = 100.0 + dt * np.arange(n)
    phase = np.linspace(0.0, 2.0 * np.pi, n)
    pos = np.stack([np.cos(phase), np.sin(phase), 1.5 + 0.2 * np.sin(2 * phase)], axis=1)
    bodies = [
        rot_z(math.radians(yaw_offset_deg))
        @ matrix_from_ypr(float(p) * 0.8 - 2.5, math.radians(pitch_deg), math.radians(roll_deg))
        for p in phase
    ]
    quats = np.array([_cam_quat(b, r_body_cam) for b in bodies])
    return Trajectory.from_arrays(t, pos, quats), bodies


def _with(traj: Trajectory, positions_m: F64 | None = None, quats_wxyz: F64 | None = None) -> Trajectory:
    return Trajectory(
        traj.times_s.copy(),
        traj.positions_m.copy() if positions_m is None else positions_m,
        traj.quats_wxyz.copy() if quats_wxyz is None else quats_wxyz,
    )


# --- statistics -------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    d=st.tuples(*(st.floats(-0.5, 0.5, allow_nan=False) for _ in range(3))),
    stride=st.integers(1, 4),
)
def test_constant_offset_gives_mae_equal_to_offset(d: tuple[float, float, float], stride: int) -> None:
    truth, _ = _flight()
    sub = slice(0, None, stride)
    est = Trajectory(truth.times_s[sub], truth.positions_m[sub] + np.array(d), truth.quats_wxyz[sub])
    r = evaluate(truth, est)
    assert r.mae_x_m == pytest.approx(abs(d[0]), abs=1e-9)
    assert r.mae_y_m == pytest.approx(abs(d[1]), abs=1e-9)
    assert r.mae_z_m == pytest.approx(abs(d[2]), abs=1e-9)
    assert max(r.std_x_m, r.std_y_m, r.std_z_m) < 1e-9
    np.testing.assert_allclose(r.pos_err_m, np.broadcast_to(d, r.pos_err_m.shape), atol=1e-9)
    assert max(r.mae_yaw_deg, r.mae_pitch_deg, r.mae_roll_deg, r.mae_tilt_deg) < 1e-5
    assert r.max_pos_err_m == pytest.approx(float(np.linalg.norm(d)), abs=1e-9)
    assert r.n_estimates == len(est)


@pytest.mark.parametrize("r_body_cam", [R_BODY_CAM_DOWNWARD, R_BODY_CAM_FORWARD], ids=["down", "forward"])
def test_one_degree_yaw_offset_with_tilted_body(r_body_cam: F64) -> None:
    truth, _ = _flight(pitch_deg=10.0, roll_deg=-4.0, r_body_cam=r_body_cam)
    est, _ = _flight(pitch_deg=10.0, roll_deg=-4.0, r_body_cam=r_body_cam, yaw_offset_deg=1.0)
    r = evaluate(truth, est, r_body_cam)
    assert r.mae_yaw_deg == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(r.ypr_err_deg[:, 0], 1.0, atol=1e-6)  # signed: estimate - truth
    assert r.std_yaw_deg < 1e-6
    assert r.mae_pitch_deg < 1e-6
    assert r.mae_roll_deg < 1e-6
    # The body z axis, tilted by acos(cos(pitch) cos(roll)) from vertical, turns 1 deg about vertical.
    tilt = math.acos(math.cos(math.radians(10.0)) * math.cos(math.radians(4.0)))
    expected_tilt_deg = math.degrees(2.0 * math.asin(math.sin(tilt) * math.sin(math.radians(0.5))))
    assert r.mae_tilt_deg == pytest.approx(expected_tilt_deg, rel=1e-6)
    assert r.std_tilt_deg < 1e-6
    assert r.mae_rotation_deg == pytest.approx(1.0, abs=1e-6)
    assert r.mae_x_m == 0.0


def test_wrong_mounting_would_show_attitude_errors() -> None:
    # The truth is made with the forward camera; reading it as a downward one must not give the same
    # body attitudes -- the mounting matters and is applied.
    truth, bodies = _flight(r_body_cam=R_BODY_CAM_FORWARD)
    ypr = body_ypr_rad(truth.quats_wxyz, R_BODY_CAM_FORWARD)
    np.testing.assert_allclose(ypr, [ypr_from_matrix(b) for b in bodies], atol=1e-9)
    wrong = body_ypr_rad(truth.quats_wxyz, R_BODY_CAM_DOWNWARD)
    assert np.max(np.abs(wrong - ypr)) > 0.5


def test_downward_camera_of_a_level_body_looks_down() -> None:
    # Documented convention: R_arena_body = R_arena_cam @ R_BODY_CAM_DOWNWARD.T.
    r_arena_cam = matrix_from_quat_wxyz(_cam_quat(np.eye(3)))
    np.testing.assert_allclose(r_arena_cam[:, 2], [0.0, 0.0, -1.0], atol=1e-12)  # optical axis down
    np.testing.assert_allclose(r_arena_cam[:, 1], [-1.0, 0.0, 0.0], atol=1e-12)  # image down = backwards
    np.testing.assert_allclose(body_ypr_rad(_cam_quat(np.eye(3))[None, :]), [[0.0, 0.0, 0.0]], atol=1e-12)


def test_pitch_offset_is_pitch_and_tilt_error() -> None:
    truth, bodies = _flight(pitch_deg=0.0, roll_deg=0.0)
    est = _with(
        truth,
        quats_wxyz=np.array([_cam_quat(b @ matrix_from_ypr(0.0, math.radians(2.0), 0.0)) for b in bodies]),
    )
    r = evaluate(truth, est)
    assert r.mae_pitch_deg == pytest.approx(2.0, abs=1e-6)
    assert r.mae_tilt_deg == pytest.approx(2.0, abs=1e-6)
    assert r.mae_yaw_deg < 1e-6
    assert r.mae_roll_deg < 1e-6


def test_yaw_error_is_wrapped() -> None:
    truth = Trajectory.from_arrays(
        [0.0], [[0, 0, 0]], [_cam_quat(matrix_from_ypr(math.radians(179.0), 0, 0))]
    )
    est = Trajectory.from_arrays([0.0], [[0, 0, 0]], [_cam_quat(matrix_from_ypr(math.radians(-179.0), 0, 0))])
    r = evaluate(truth, est)
    assert r.ypr_err_deg[0, 0] == pytest.approx(2.0, abs=1e-9)
    assert r.mae_yaw_deg == pytest.approx(2.0, abs=1e-9)


def test_std_is_of_the_signed_error() -> None:
    truth, _ = _flight(n=4)
    est = _with(
        truth,
        positions_m=truth.positions_m + np.array([[0.1, 0, 0], [-0.1, 0, 0], [0.1, 0, 0], [-0.1, 0, 0]]),
    )
    r = evaluate(truth, est)
    assert r.mae_x_m == pytest.approx(0.1)
    assert r.std_x_m == pytest.approx(0.1)  # mean 0, so std = 0.1; the std of |e| would be 0


def test_yield_outliers_and_max_error() -> None:
    truth, _ = _flight(n=40)
    keep = np.arange(0, 40, 4)  # 10 of 40 frames
    pos = truth.positions_m[keep].copy()
    pos[3, 0] += 0.25
    pos[5] += [0.06, -0.06, 0.06]  # 3D 0.104 m > 0.10 m, although no axis exceeds 0.10 m
    pos[7, 1] += 0.05
    est = Trajectory(truth.times_s[keep], pos, truth.quats_wxyz[keep])
    r = evaluate(truth, est)
    assert (r.n_estimates, r.n_truth, r.n_dropped) == (10, 40, 0)
    assert r.yield_fraction == pytest.approx(0.25)
    assert r.n_outliers == 2
    assert r.max_pos_err_m == pytest.approx(0.25)


# --- association ------------------------------------------------------------------------------------


def test_interpolation_at_midpoints() -> None:
    q0 = quat_wxyz_from_matrix(matrix_from_ypr(0.0, 0.0, 0.0))
    q1 = quat_wxyz_from_matrix(matrix_from_ypr(math.radians(90.0), 0.0, 0.0))
    q2 = quat_wxyz_from_matrix(matrix_from_ypr(math.radians(90.0), math.radians(40.0), 0.0))
    truth = Trajectory.from_arrays([0.0, 1.0, 3.0], [[0, 0, 0], [2, 4, -2], [2, 4, 2]], [q0, q1, q2])
    est = Trajectory.from_arrays([0.5, 1.0, 2.0, 2.5], np.zeros((4, 3)), np.tile(q0, (4, 1)))
    a = associate(truth, est)
    np.testing.assert_allclose(
        a.truth_positions_m, [[1, 2, -1], [2, 4, -2], [2, 4, 0], [2, 4, 1]], atol=1e-12
    )
    yprs = np.degrees([ypr_from_matrix(matrix_from_quat_wxyz(q)) for q in a.truth_quats_wxyz])
    np.testing.assert_allclose(yprs, [[45, 0, 0], [90, 0, 0], [90, 20, 0], [90, 30, 0]], atol=1e-9)
    assert a.n_dropped == 0


def test_estimates_outside_truth_span_are_dropped_and_counted() -> None:
    truth, _ = _flight(n=30)
    t0, t1 = truth.times_s[0], truth.times_s[-1]
    times = [t0 - 1.0, t0 - 0.0005, t0 + 0.01, t1, t1 + 0.0005, t1 + 0.01, t1 + 5.0]
    est = Trajectory.from_arrays(times, np.zeros((7, 3)), np.tile([1.0, 0, 0, 0], (7, 1)))
    a = associate(truth, est, max_dt_s=0.001)
    assert a.n_dropped == 3
    np.testing.assert_array_equal(a.est_indices, [1, 2, 3, 4])
    np.testing.assert_allclose(a.truth_positions_m[0], truth.positions_m[0], atol=1e-12)  # the first
    np.testing.assert_allclose(a.truth_positions_m[3], truth.positions_m[-1], atol=1e-12)  # the last
    r = evaluate(truth, est, max_dt_s=0.001)
    assert (r.n_estimates, r.n_dropped) == (4, 3)
    assert "3 estimates outside" in format_table(r)


def test_no_overlap_is_an_eval_error() -> None:
    truth, _ = _flight(n=10)
    est = Trajectory(truth.times_s + 100.0, truth.positions_m, truth.quats_wxyz)
    with pytest.raises(EvalError, match="no overlap in time"):
        evaluate(truth, est)


# --- output -----------------------------------------------------------------------------------------


def _example_report_inputs() -> tuple[Trajectory, Trajectory]:
    truth, bodies = _flight(n=90)
    rng = np.random.default_rng(7)
    keep = np.sort(rng.choice(90, size=35, replace=False))
    noise = rng.normal(0.0, [0.07, 0.05, 0.02], (35, 3))
    quats = np.array(
        [_cam_quat(bodies[k] @ matrix_from_ypr(*np.radians(rng.normal(0.0, [0.4, 3.0, 3.5])))) for k in keep]
    )
    return truth, Trajectory(truth.times_s[keep], truth.positions_m[keep] + noise, quats)


def test_to_dict_is_json_with_units_in_keys() -> None:
    truth, est = _example_report_inputs()
    r = evaluate(truth, est)
    d = json.loads(json.dumps(r.to_dict()))
    for key in ("mae_x_m", "std_z_m", "mae_yaw_deg", "std_roll_deg", "max_pos_err_m", "n_outliers"):
        assert isinstance(d[key], int | float), key
    assert d["yield"] == pytest.approx(35 / 90)
    assert d["mae_x_m"] == pytest.approx(r.mae_x_m)
    assert "series" not in d
    series = json.loads(json.dumps(r.to_dict(include_series=True)))["series"]
    assert len(series["pos_err_m"]) == 35


def test_format_table_layout() -> None:
    truth, est = _example_report_inputs()
    r = evaluate(truth, est)
    text = format_table(r)
    lines = text.splitlines()
    assert lines[0].split() == ["X", "Error", "[m]", "Y", "Error", "[m]", "Z", "Error", "[m]"]
    assert "Yaw Error [deg]" in lines[5]
    assert "Pitch Error [deg]" in lines[5]
    assert "Roll Error [deg]" in lines[5]
    assert f"{r.mae_x_m:.4f} / {r.std_x_m:.4f}" in lines[2]
    assert lines[3].startswith("paper IPT")
    assert "0.0690 / 0.0886" in lines[3]
    assert f"{r.mae_roll_deg:.3f} / {r.std_roll_deg:.3f}" in text
    assert "3.342 / 4.305" in text
    assert "yield 35/90" in text
    assert "625/1800" in text
    assert f"max error {r.max_pos_err_m:.4f} m" in text
    assert "outliers > 10 cm" in text
    bare = format_table(r, paper=False)
    assert "paper IPT" not in bare
    assert "0.0886" not in bare
    assert set(PAPER_IPT_TABLE_I) == {"x", "y", "z", "yaw", "pitch", "roll"}


def test_plot_is_a_png(tmp_path: Path) -> None:
    truth, est = _example_report_inputs()
    path = tmp_path / "fig6.png"
    plot_report(truth, est, evaluate(truth, est), path)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > 20_000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fig6.png"]


# --- command line -----------------------------------------------------------------------------------


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    code = "import sys; from ipt.eval import eval_main; sys.exit(eval_main())"
    return subprocess.run(
        [sys.executable, "-c", code, *args], cwd=cwd, capture_output=True, text=True, timeout=120, check=False
    )


def test_cli_prints_table_and_writes_outputs(tmp_path: Path) -> None:
    truth, est = _example_report_inputs()
    write_tum(tmp_path / "truth.tum", truth)
    write_tum(tmp_path / "poses.tum", est)
    res = _run(
        "--truth", "truth.tum", "--poses", "poses.tum", "--plot", "f.png", "--json", "r.json", cwd=tmp_path
    )
    assert res.returncode == 0, res.stderr
    assert res.stderr == ""
    assert "X Error [m]" in res.stdout
    assert "Roll Error [deg]" in res.stdout
    assert "paper IPT" in res.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["n_estimates"] == 35
    assert report["n_truth"] == 90
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"


def test_cli_help() -> None:
    res = _run("--help", cwd=Path.cwd())
    assert res.returncode == 0
    assert "--truth" in res.stdout
    assert "mae / std" in res.stdout
    assert "yield" in res.stdout


def test_cli_missing_file_is_one_line_exit_2(tmp_path: Path) -> None:
    truth, _ = _flight(n=5)
    write_tum(tmp_path / "truth.tum", truth)
    res = _run("--truth", "truth.tum", "--poses", "missing.tum", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.splitlines() == ["ipt eval: error: missing.tum: no such file"]
    assert res.stdout == ""


def test_cli_malformed_file_is_one_line_exit_2(tmp_path: Path) -> None:
    truth, _ = _flight(n=5)
    write_tum(tmp_path / "truth.tum", truth)
    (tmp_path / "poses.tum").write_text("100.0 0 0 1 0 0 0 1\n100.1 0 0 1 0 0 0\n")
    res = _run("--truth", "truth.tum", "--poses", "poses.tum", cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("ipt eval: error: poses.tum:2: expected 8 fields")
    assert "Traceback" not in res.stderr


def test_cli_no_overlap_is_one_line_exit_2(tmp_path: Path) -> None:
    truth, _ = _flight(n=5)
    write_tum(tmp_path / "truth.tum", truth)
    write_tum(tmp_path / "poses.tum", Trajectory(truth.times_s + 50.0, truth.positions_m, truth.quats_wxyz))
    res = _run("--truth", "truth.tum", "--poses", "poses.tum", cwd=tmp_path)
    assert res.returncode == 2
    assert len(res.stderr.splitlines()) == 1
    assert "no overlap in time" in res.stderr


def test_cli_unwritable_output_is_one_line_exit_2(tmp_path: Path) -> None:
    truth, _ = _flight(n=5)
    write_tum(tmp_path / "truth.tum", truth)
    res = _run("--truth", "truth.tum", "--poses", "truth.tum", "--json", "no/such/dir/r.json", cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.splitlines() == [res.stderr.strip()]
    assert "no/such/dir/r.json: cannot write" in res.stderr
