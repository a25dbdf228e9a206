"""Issue 30's dark scene: the simulator's 'dark' content, its two suite flights and the signal measurement."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ipt.config.models import ArenaConfig, load_yaml_model
from ipt.receiver.core.demodulator import signal_mask
from ipt.sim.arena import flight_of, scene_for
from ipt.sim.config import SimConfig, describe_flight
from ipt.sim.darkscene import DarkScene

ROOT = Path(__file__).resolve().parents[1]
FLIGHTS = ROOT / "benchmarks" / "flights"


def _grey(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))


def test_the_dark_scene_is_dark_under_bright_thin_lines() -> None:
    frame = DarkScene(960, 1080, seed=4).frame(5, 30.0)
    assert frame.shape == (1080, 960, 3)
    assert frame.dtype == np.uint8
    grey = _grey(frame)
    assert np.median(grey) < 20  # the backdrop: photographs at a tenth of their code values
    bright = grey > 150
    assert 0.005 < bright.mean() < 0.15  # lines and labels, a small part of the picture
    # Thin: an opening with a 7-pixel square removes nearly all of them (no bright areas, only strokes).
    opened = cv2.morphologyEx(bright.astype(np.uint8), cv2.MORPH_OPEN, np.ones((7, 7), np.uint8))
    assert opened.sum() < 0.05 * bright.sum()


def test_the_dark_scene_is_fixed_by_its_seed_and_pans() -> None:
    a, b = DarkScene(640, 720, seed=7), DarkScene(640, 720, seed=7)
    assert np.array_equal(a.frame(12, 30.0), b.frame(12, 30.0))
    assert not np.array_equal(a.frame(12, 30.0), DarkScene(640, 720, seed=8).frame(12, 30.0))
    (x0, y0), (x1, y1) = a.overlay_offset_px(0), a.overlay_offset_px(8)
    assert 15 <= np.hypot(x1 - x0, y1 - y0) <= 25  # 2.5 projector pixels per content frame
    assert not np.array_equal(a.frame(0, 30.0), a.frame(1, 30.0))


@pytest.mark.parametrize(("name", "profile"), [("dark-scene", "paper"), ("dark-scene-ipt", "ipt")])
def test_the_dark_flights_load(name: str, profile: str) -> None:
    sim = load_yaml_model(FLIGHTS / f"{name}.yaml", SimConfig)
    assert sim.description
    assert "dark scene" in describe_flight(sim)
    assert sim.content.kind == "dark"
    assert sim.arena == {"modulation": {"profile": profile, "delta_l": 4}}
    cam = sim.camera
    assert (cam.ambient, cam.exposure_ms) == (0.02, 5)
    assert cam.gain == pytest.approx(3 * 0.85)
    assert sim.flight.altitude_m == 1.0
    assert sim.flight.peak_speed_mps == 0.9
    assert isinstance(scene_for(sim, ArenaConfig()), DarkScene)
    assert flight_of(sim).state(0.5).position_m[2] == pytest.approx(1.0, abs=0.05)


def test_dark_signal_measures_the_step_and_the_noise() -> None:
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "dark_signal.py"), str(FLIGHTS / "dark-scene.yaml"), "--frames=1"],
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    result = json.loads(out.stdout)
    dark = result["dark"]
    assert dark["pixels"] > 1000
    assert 1.5 < dark["step_mean_grey"] < 6  # issue 30: about 3 grey levels ...
    assert 1.0 < dark["noise_sd_grey"] < 3.5  # ... against about 2 of noise


def test_dark_signal_refuses_a_missing_flight_in_one_line(tmp_path: Path) -> None:
    missing = tmp_path / "nope.yaml"
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "dark_signal.py"), str(missing)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1
    assert "nope.yaml" in out.stderr
    assert "Traceback" not in out.stderr


def test_the_signal_mask_keeps_dim_lit_floor_under_camera_noise() -> None:
    # A dark scene under a gained-up camera: lit floor only 7 levels above the drone's shadow, with a
    # noise of 2.4 levels per pixel. The mask must keep the lit floor and leave the shadow out.
    rng = np.random.default_rng(30)
    h, w = 360, 640
    yy, xx = np.mgrid[0:h, 0:w]
    shadow = (xx - 320) ** 2 + (yy - 180) ** 2 < 100**2
    clean = np.where(shadow, 65.0, 72.0)
    lum = np.clip(np.rint(clean + rng.normal(0, 2.4, (h, w))), 0, 255).astype(np.uint8)
    mask = signal_mask(lum) > 0
    inner_lit = ~shadow & ((xx - 320) ** 2 + (yy - 180) ** 2 > 115**2)
    inner_lit[:10], inner_lit[-10:], inner_lit[:, :10], inner_lit[:, -10:] = False, False, False, False
    assert mask[inner_lit].mean() > 0.9
    assert mask[shadow].mean() < 0.02
