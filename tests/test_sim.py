"""The simulated arena: flight dynamics, camera geometry, exposure timing, and the whole chain."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ipt.config.camera_info import load_camera_info
from ipt.config.models import ArenaConfig, DetectorConfig, PipelineConfig, PoseConfig, load_arena_config
from ipt.eval import evaluate
from ipt.geometry import R_BODY_CAM_DOWNWARD, rotation_angle_rad
from ipt.receiver.core.pose import solve_pose
from ipt.receiver.detect.detector import TagDetector
from ipt.receiver.replay import replay
from ipt.sender.content import GeneratedScene
from ipt.sim.arena import SimulatedArena
from ipt.sim.config import SimCameraConfig, SimConfig
from ipt.sim.flight import GRAVITY_MPS2, FlightState, RectangleFlight
from ipt.sim.render import CameraRenderer, Exposure, camera_info_of, linear_to_srgb_u8, srgb_to_linear
from ipt.tagmap import arena_to_pixel_matrix, grid_tag_map
from ipt.tum import read_tum

ARENA = ArenaConfig()


def test_flight_reaches_the_paper_speed_and_height() -> None:
    f = RectangleFlight()
    ts = np.arange(0, 2 * f.loop_s, 0.005)
    states = [f.state(t) for t in ts]
    speeds = [np.linalg.norm(s.velocity_mps) for s in states]
    heights = [s.position_m[2] for s in states]
    assert max(speeds) == pytest.approx(1.0, abs=0.02)
    assert min(heights) > 0.75
    assert max(heights) < 0.85
    # The route is a rectangle 1.0 m x 1.2 m around the centre.
    xs = [s.position_m[0] for s in states]
    ys = [s.position_m[1] for s in states]
    assert max(xs) == pytest.approx(0.5, abs=0.01)
    assert min(ys) == pytest.approx(-0.6, abs=0.01)


def test_flight_tilts_with_its_acceleration() -> None:
    f = RectangleFlight(altitude_wobble_m=0.0)
    dt = 1e-4
    for t in (0.3, 1.1, 2.9, 4.4):
        a = (f.state(t + dt).velocity_mps - f.state(t - dt).velocity_mps) / (2 * dt)
        r_arena_body = f.state(t).r_arena_cam @ R_BODY_CAM_DOWNWARD.T
        tilt = np.arccos(r_arena_body[2, 2])
        assert tilt == pytest.approx(np.arctan2(np.linalg.norm(a[:2]), GRAVITY_MPS2), abs=1e-3)
    assert np.allclose(f.state(0.7).r_arena_cam.T @ f.state(0.7).r_arena_cam, np.eye(3))


def test_srgb_tables_round_trip() -> None:
    codes = np.arange(256, dtype=np.uint8).reshape(16, 16)
    assert np.array_equal(linear_to_srgb_u8(srgb_to_linear(codes)), codes)


def _map_crop(index: int, region: tuple[int, int, int, int]) -> np.ndarray:
    x0, y0, x1, y1 = region
    grey = grid_tag_map(ARENA).render_image()[y0:y1, x0:x1]
    return np.repeat(grey[:, :, None], 3, axis=2)


def test_rendered_view_of_the_printed_map_gives_back_the_camera_pose() -> None:
    # No modulation here: the floor shows the tag map itself, so this checks the camera geometry
    # (homography, distortion, pixel conventions) against the detector and pose independently.
    cam_cfg = SimCameraConfig(read_noise=0.0, full_well_e=1e12, blur_sigma_px=0.0)
    renderer = CameraRenderer(cam_cfg, arena_to_pixel_matrix(ARENA), (1920, 2160))
    yaw = np.deg2rad(20)
    r_yaw = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    truth = FlightState(np.array([0.13, -0.21, 0.8]), r_yaw @ R_BODY_CAM_DOWNWARD, np.zeros(3))
    image = renderer.render([Exposure(truth, 0)], _map_crop, np.random.default_rng(0))
    tm = grid_tag_map(ARENA)
    grey = image[:, :, 1]
    detections = TagDetector(DetectorConfig(), known_ids=tm.by_id).detect(grey)
    assert len(detections) >= 4
    pose = solve_pose(detections, tm, camera_info_of(cam_cfg), PoseConfig())
    assert pose is not None
    assert np.linalg.norm(pose.position_m - truth.position_m) < 0.003
    assert np.rad2deg(rotation_angle_rad(pose.r_arena_cam.T @ truth.r_arena_cam)) < 0.2


def test_exposure_straddling_a_flip_mixes_both_phases() -> None:
    sim = SimConfig(projector_offset_ms=0.0)
    world = SimulatedArena(ARENA, sim, GeneratedScene(1920, 2160))
    period = 1 / 60
    assert world.projector_index(0.0) == 1  # the first flip is at t = 0
    assert world.projector_index(period * 0.5) == 1
    assert world.projector_index(period * 1.5) == 2
    # Frame 2 (t = 16.7 ms) is exposed from 14.7 to 18.7 ms: across the flip at 16.7 ms.
    cam = sim.camera
    t = 2 / cam.fps
    half = cam.exposure_ms * 1e-3 / 2
    assert world.projector_index(t - half) != world.projector_index(t + half)


def test_projector_crop_is_the_modulated_frame() -> None:
    world = SimulatedArena(ARENA, SimConfig(), GeneratedScene(1920, 2160))
    region = (100, 200, 400, 500)
    plus = world.projector_crop(0, region).astype(int)
    minus = world.projector_crop(1, region).astype(int)
    mask = world.tag_map.render_mask()[200:500, 100:400]
    diff = (plus - minus).sum(axis=2)
    assert diff[mask > 0].mean() > 5 > abs(diff[mask == 0].mean())
    assert diff[mask < 0].mean() < -5


@pytest.mark.slow
def test_sim_writes_video_camera_and_truth(short_flight: Path) -> None:
    assert (short_flight / "frames.mkv").stat().st_size > 10_000
    cam = load_camera_info(short_flight / "camera.yaml")
    assert (cam.width_px, cam.height_px) == (640, 360)
    truth = read_tum(short_flight / "groundtruth.tum")
    assert len(truth) == 60
    assert truth.times_s[1] == pytest.approx(1 / 120, abs=1e-6)
    assert not list(short_flight.glob("*.partial*"))


@pytest.mark.slow
def test_replayed_flight_meets_the_core_targets(short_flight: Path, tmp_path: Path) -> None:
    arena = load_arena_config(short_flight / "arena.yaml")
    tm = grid_tag_map(arena)
    poses = tmp_path / "poses.tum"
    summary = replay(
        arena, tm, short_flight / "camera.yaml", short_flight / "frames.mkv", poses, 120.0, PipelineConfig(), None
    )
    assert summary.frames == 60
    report = evaluate(read_tum(short_flight / "groundtruth.tum"), read_tum(poses))
    assert report.yield_fraction >= 0.30
    assert max(report.mae_x_m, report.mae_y_m, report.mae_z_m) <= 0.030
