"""The simulator's real-flight effects: shadow, vibration, pilot, moving content, lab cameras, rolling
shutter, altitude profiles, and the scenario files of benchmarks/flights/."""

from __future__ import annotations

import itertools
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ipt.config.models import ArenaConfig, ConfigError, load_yaml_model
from ipt.geometry import R_BODY_CAM_DOWNWARD, rotation_angle_rad
from ipt.sender.photos import PanningPhotoScene
from ipt.sim.arena import SimulatedArena, flight_of, scene_for
from ipt.sim.config import (
    AutoGainConfig,
    ShadowConfig,
    SimCameraConfig,
    SimConfig,
    SimFlightConfig,
    describe_flight,
)
from ipt.sim.flight import FlightState
from ipt.sim.render import AutoGain, Exposure
from ipt.sim.shadow import lit_fraction, shadow_centre_m
from ipt.videoio import open_frames

ROOT = Path(__file__).resolve().parents[1]
FLIGHTS = ROOT / "benchmarks" / "flights"
ARENA = ArenaConfig()
SCENARIOS = ("moving-content", "shadow-vibration", "realcam", "rolling", "takeoff", "fast", "smooth")


def _static_sim(**camera: object) -> SimConfig:
    """A hover without pilot or vibration over the map app, noise-free unless asked otherwise."""
    cam = SimCameraConfig.model_validate({"read_noise": 0.0, "full_well_e": 1e12, **camera})
    flight = SimFlightConfig(path="hover", altitude_wobble_m=0.0, yaw_wobble_deg=0.0, vibration=None, pilot=None)
    return SimConfig.smooth().model_copy(update={"camera": cam, "flight": flight})


# --- the scenario files ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", [*SCENARIOS, "hover-2.5m", "independent"])
def test_every_scenario_file_is_a_valid_flight(name: str) -> None:
    sim = load_yaml_model(FLIGHTS / f"{name}.yaml", SimConfig)
    assert describe_flight(sim)
    flight_of(sim).state(0.5)  # the flight can be flown


@pytest.mark.parametrize("path", sorted((ROOT / "benchmarks" / "heldout").glob("*.yaml")), ids=lambda p: p.stem)
def test_every_held_out_flight_is_a_valid_flight_unlike_the_suites(path: Path) -> None:
    # benchmarks/heldout: flights the receiver is checked on and never tuned on; none is a suite flight.
    sim = load_yaml_model(path, SimConfig)
    assert sim.description.startswith("held out")
    flight_of(sim).state(0.5)
    blank = {"description": ""}
    suite = [load_yaml_model(p, SimConfig).model_copy(update=blank) for p in FLIGHTS.glob("*.yaml")]
    assert sim.model_copy(update=blank) not in suite


def test_the_default_flight_is_the_realistic_one() -> None:
    default, written = SimConfig(), load_yaml_model(FLIGHTS / "moving-content.yaml", SimConfig)
    assert default.shadow is not None
    assert default.flight.vibration is not None
    assert default.flight.pilot is not None
    assert default.content.kind == "photos"
    for part in ("flight", "shadow", "content", "camera", "projector_dither_levels"):
        assert getattr(default, part) == getattr(written, part), part


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("flightt: {}\n", "flightt: unknown key"),
        ("shadow: {radius_m: -0.1}\n", "shadow.radius_m"),
        ("camera: {readout_ms: 9.0}\n", "readout_ms 9.0 is longer than a frame"),
        ("arena: {modulation: {delta_ll: 3}}\n", "modulation.delta_ll: unknown key"),
        ("flight: {vibration: {frequency_hz: [7, 5]}}\n", "frequency_hz"),
    ],
)
def test_a_bad_scenario_file_is_one_line_naming_the_file_and_the_key(tmp_path: Path, text: str, key: str) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(text, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_yaml_model(bad, SimConfig)
    assert str(bad) in str(info.value)
    assert key in str(info.value)
    proc = subprocess.run(
        [sys.executable, "-m", "ipt.cli", "sim", "--sim-config", str(bad), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1
    assert str(bad) in lines[0]
    assert key in lines[0]
    assert not (tmp_path / "o").exists()


# --- the flight -----------------------------------------------------------------------------------------


def _body_rotations(sim: SimConfig, times: np.ndarray) -> list[np.ndarray]:
    f = flight_of(sim)
    return [f.state(float(t)).r_arena_cam @ R_BODY_CAM_DOWNWARD.T for t in times]


def test_the_airframe_vibrates_as_a_hand_flown_quadrotor() -> None:
    sim, smooth = SimConfig(), SimConfig.smooth()
    times = np.arange(0.0, 8.0, 1 / 600)
    # The vibration is the rotation between the vibrating body and the same flight without it (the
    # pilot's wandering tilts the body too, so compare with the flight that has the pilot only).
    pilot_only = sim.model_copy(update={"flight": sim.flight.model_copy(update={"vibration": None})})
    shaken, base, calm = (_body_rotations(s, times) for s in (sim, pilot_only, smooth))
    vibration = [b.T @ r for b, r in zip(base, shaken, strict=True)]
    size_deg = np.rad2deg([rotation_angle_rad(v) for v in vibration])
    assert 1.0 < size_deg.max() < 2.2  # ±1.5° in roll and in pitch, a little yaw
    rate = np.rad2deg([rotation_angle_rad(a.T @ b) for a, b in itertools.pairwise(vibration)]) * 600
    assert 45 < rate.max() < 80  # degrees per second: "up to about 60°/s"
    period = 10  # one projector period (1/60 s) at 600 samples per second

    def steps(rs: list[np.ndarray]) -> np.ndarray:
        return np.rad2deg([rotation_angle_rad(a.T @ b) for a, b in zip(rs[:-period], rs[period:], strict=True)])

    # About 1° of rotation between two frames one projector period apart; the smooth flight turns less.
    assert 0.9 < np.percentile(steps(shaken), 95) < 1.4
    assert np.percentile(steps(calm), 95) < 0.6


def test_the_pilot_adds_accelerations_of_up_to_three_and_a_half_mps2() -> None:
    smooth_peak = 1.64  # the smooth rectangle's own: minimum-jerk edges at 1 m/s
    for name, low, high in (("moving-content", smooth_peak + 0.02, 2.8), ("fast", 3.0, 3.8)):
        f = flight_of(load_yaml_model(FLIGHTS / f"{name}.yaml", SimConfig))
        dt = 1e-3
        acc = [
            np.linalg.norm((f.state(t + dt).velocity_mps - f.state(t - dt).velocity_mps)[:2]) / (2 * dt)
            for t in np.arange(0.01, 8.0, 0.01)
        ]
        assert low < max(acc) < high, (name, max(acc))


def test_takeoff_ground_truth_spans_a_quarter_metre_to_two_point_two() -> None:
    f = flight_of(load_yaml_model(FLIGHTS / "takeoff.yaml", SimConfig))
    z = np.array([f.state(k / 120).position_m[2] for k in range(8 * 120)])
    assert z.min() == pytest.approx(0.25, abs=0.005)
    assert z.max() == pytest.approx(2.2, abs=0.005)
    assert z[:50].max() < 0.26
    assert z[-50:].max() < 0.26


# --- the shadow -------------------------------------------------------------------------------------------


def test_the_shadow_is_the_body_scaled_from_the_projector() -> None:
    cfg = ShadowConfig(radius_m=0.17, projector_position_m=(0.3, 0.0, 3.0), aperture_m=0.0)
    body = np.array([0.5, 0.2, 0.8])
    centre = shadow_centre_m(body, cfg)
    assert centre == pytest.approx([0.3 + 0.2 * 3 / 2.2, 0.2 * 3 / 2.2], abs=1e-9)
    radius_on_floor = 0.17 * 3.0 / 2.2
    r = np.array([0.0, 0.5, 0.98, 1.02, 2.0]) * radius_on_floor
    xs = (centre[0] + r).astype(np.float32)
    ys = np.full_like(xs, centre[1])
    lit = lit_fraction(xs, ys, body, np.array([0.0, 0.0, 1.0]), cfg)
    assert list(lit) == [0.0, 0.0, 0.0, 1.0, 1.0]
    soft = lit_fraction(xs, ys, body, np.array([0.0, 0.0, 1.0]), cfg.model_copy(update={"aperture_m": 0.04}))
    assert 0.0 < soft[2] < soft[3] < 1.0  # a penumbra across the edge


def test_the_shadow_darkens_part_of_the_view_at_point_eight_metres() -> None:
    sim = _static_sim().model_copy(update={"shadow": ShadowConfig()})
    world = SimulatedArena(ARENA, sim, scene_for(sim, ARENA))
    image = world.render(0).image_rgb.astype(float).mean(axis=2)
    without = SimulatedArena(ARENA, _static_sim(), scene_for(sim, ARENA)).render(0).image_rgb.astype(float).mean(axis=2)
    dark = image < 0.6 * without
    assert 0.1 < dark.mean() < 0.45  # "up to a third of the view"
    ys, xs = np.nonzero(dark)
    assert abs(xs.mean() - 320) < 200
    assert abs(ys.mean() - 180) < 150


# --- the content ------------------------------------------------------------------------------------------


def test_photographs_pan_within_the_band_and_cut() -> None:
    scene = PanningPhotoScene(640, 720, seed=3, pan_px_per_frame=(3.0, 10.0), cut_every_s=1.0)
    steps = []
    for i in range(1, 29):  # within the first shot at 30 Hz
        (x0, y0), (x1, y1) = scene.offset_px(i - 1, 30.0), scene.offset_px(i, 30.0)
        steps.append(np.hypot(x1 - x0, y1 - y0))
    assert min(steps) >= 2.0
    assert max(steps) <= 11.5
    assert np.mean(steps) > 4.0
    a, b = scene.frame(10, 30.0), scene.frame(11, 30.0)
    assert a.shape == (720, 640, 3)
    assert not np.array_equal(a, b)
    cut = np.abs(scene.frame(29, 30.0).astype(int) - scene.frame(30, 30.0).astype(int)).mean()
    assert cut > 3 * np.abs(a.astype(int) - b.astype(int)).mean()
    assert np.array_equal(PanningPhotoScene(640, 720, seed=3, cut_every_s=1.0).frame(11, 30.0), b)


# --- the camera -------------------------------------------------------------------------------------------


def _blockiness(grey: np.ndarray) -> float:
    """Mean step across 8-pixel block boundaries over the mean step elsewhere (1: no blocks)."""
    d = np.abs(np.diff(grey.astype(float), axis=1))
    at = d[:, 7::8].mean()
    mask = np.ones(d.shape[1], bool)
    mask[7::8] = False
    return float(at / d[:, mask].mean())


def test_a_lab_camera_gives_grey_jpeg_frames(tmp_path: Path) -> None:
    sim = load_yaml_model(FLIGHTS / "realcam.yaml", SimConfig)
    world = SimulatedArena(ARENA, sim, scene_for(sim, ARENA))
    frame = world.render(3).image_rgb
    assert frame.shape == (400, 640)
    assert frame.dtype == np.uint8
    raw_sim = sim.model_copy(update={"camera": sim.camera.model_copy(update={"jpeg_quality": None})})
    raw = SimulatedArena(ARENA, raw_sim, scene_for(raw_sim, ARENA)).render(3).image_rgb
    assert _blockiness(frame) > 1.05 * _blockiness(raw)
    # ipt sim writes them grey (FFV1 'gray'), at 119.88 FPS.
    out = tmp_path / "realcam"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "ipt.cli",
            "sim",
            "--sim-config",
            str(FLIGHTS / "realcam.yaml"),
            "--out",
            str(out),
            "--seconds",
            "0.05",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    with open_frames(out / "frames.mkv") as src:
        assert src.fps == pytest.approx(119.88)
        first = next(iter(src))
    assert np.array_equal(first[:, :, 0], first[:, :, 1])  # grey, read back as RGB
    truth = (out / "groundtruth.tum").read_text().split("\n")
    rows = [line.split() for line in truth if line and not line.startswith("#")]
    assert float(rows[1][0]) == pytest.approx(1 / 119.88, abs=1e-6)


def test_auto_gain_drifts_and_steps() -> None:
    gain = AutoGain(AutoGainConfig(drift_pct=4.0, drift_period_s=3.0, step_pct=3.0, steps_per_s=0.5), seed=1)
    f = np.array([gain.factor(t) for t in np.arange(0, 20, 1 / 120)])
    assert 0.85 < f.min() < 0.98
    assert 1.02 < f.max() < 1.15
    jumps = np.abs(np.diff(f))
    assert jumps.max() > 0.025
    assert np.sum(jumps > 0.02) >= 3
    assert AutoGain(AutoGainConfig(), seed=1).factor(5.0) == 1.0


def test_vignetting_darkens_the_corners() -> None:
    flat = _static_sim(vignetting=0.35)
    world = SimulatedArena(ARENA, flat, scene_for(flat, ARENA))
    assert world.renderer._vignette[0, 0] == pytest.approx(0.65, abs=0.01)
    assert world.renderer._vignette[180, 320] == pytest.approx(1.0, abs=1e-3)


def test_a_rolling_shutter_frame_has_the_flip_inside_it() -> None:
    sim = _static_sim(readout_ms=6.0, exposure_ms=0.2, time_samples=1, blur_sigma_px=0.0)
    world = SimulatedArena(ARENA, sim, scene_for(sim, ARENA))
    renderer = world.renderer
    # Find a frame whose rows see two projector frames, and the row where the floor changes.
    for k in range(1, 12):
        t = k / sim.camera.fps
        (sample,) = renderer.frame_samples(t, world.flight.state, world.projector_indices)
        if sample.row_index[0] != sample.row_index[-1]:
            break
    else:
        pytest.fail("no frame had the flip inside it")
    j = int(sample.row_index[0])
    flip_row = int(np.argmax(sample.row_index > j)) // sim.camera.supersample
    assert 20 < flip_row < 340
    frame = world.render(k).image_rgb.astype(float).mean(axis=2)
    # The same view lit by frame j alone and by frame j + 1 alone (a global shutter at that instant).
    gs = _static_sim(exposure_ms=0.2, time_samples=1, blur_sigma_px=0.0)
    still = SimulatedArena(ARENA, gs, scene_for(gs, ARENA))
    state = world.flight.state(t)
    lit_j = still.renderer.render([Exposure(state, j)], still.projected, np.random.default_rng(0))
    lit_next = still.renderer.render([Exposure(state, j + 1)], still.projected, np.random.default_rng(0))
    a, b = lit_j.astype(float).mean(axis=2), lit_next.astype(float).mean(axis=2)
    # Rows above the flip match frame j, rows below it match frame j + 1.
    top, bottom = slice(0, flip_row - 4), slice(flip_row + 4, 360)
    assert np.abs(frame[top] - a[top]).mean() < 0.3 * np.abs(frame[top] - b[top]).mean()
    assert np.abs(frame[bottom] - b[bottom]).mean() < 0.3 * np.abs(frame[bottom] - a[bottom]).mean()


def test_dithering_moves_each_projector_pixel_by_at_most_its_levels() -> None:
    sim = SimConfig.smooth(projector_dither_levels=1)
    world = SimulatedArena(ARENA, sim, scene_for(sim, ARENA))
    region = (300, 400, 700, 800)
    plain = world.projector_crop(4, region).astype(int)
    moved = world.projected(4, region).astype(int) - plain
    assert set(np.unique(moved)) <= {-1, 0, 1}
    assert 0.3 < np.mean(moved != 0) < 0.7
    assert not np.array_equal(world.projected(5, region).astype(int) - world.projector_crop(5, region), moved)


def test_frames_do_not_depend_on_the_order_they_are_rendered_in() -> None:
    sim = SimConfig()
    a = SimulatedArena(ARENA, sim, scene_for(sim, ARENA))
    b = SimulatedArena(ARENA, sim, scene_for(sim, ARENA))
    first = [a.render(k).image_rgb for k in (0, 1, 2)]
    assert np.array_equal(b.render(2).image_rgb, first[2])
    assert np.array_equal(b.render(0).image_rgb, first[0])


def test_a_pose_state_above_the_floor_is_required() -> None:
    sim = _static_sim()
    world = SimulatedArena(ARENA, sim, scene_for(sim, ARENA))
    below = FlightState(np.array([0.0, 0.0, -0.1]), R_BODY_CAM_DOWNWARD, np.zeros(3))
    with pytest.raises(ValueError, match="above the floor"):
        world.renderer.render([Exposure(below, 0)], world.projected, np.random.default_rng(0))
