"""The hidden tags' signal in a flight's rendered frames, against the camera's noise (issue 30's dark scene).

    python benchmarks/dark_signal.py benchmarks/flights/dark-scene.yaml [--frames 12] [--seconds 8]

For frames spread over the flight (each the next one whose exposure lies within one projector frame: a frame
across a flip sees a blend of both phases, so its step is smaller), the simulator renders each camera frame
three more ways: without the sensor's noise, without the noise and with the projector's other phase (every
tag pixel's lightness step reversed, nothing else changed), and with the tags not hidden at all, the
projector lit by the bare content and no room light (which says where the content itself is dark). Then, in
the camera's 8-bit grey (BT.601 luma of the RGB frame, or a mono camera's own):

- the **tag step**: noise-free other phase − noise-free frame, over the pixels where it is at least half a
  grey level (the tags the camera sees lit): the step a pair of frames shows, before any noise;
- the **noise**: rendered frame − noise-free frame over the same pixels (its standard deviation: noise per
  pixel in one frame; a pair's difference has √2 times that);
- each in the **dark areas** (the content at that pixel, seen by the camera without room light or tags, at
  most ``--dark-grey`` grey levels: the dimmed backdrop, not the bright lines or labels), split further into
  **black** (content no brighter than a projector's code value 5, seen by this camera: where a paper-literal
  sender's ΔL 4 clips and the step is one-sided) and the rest; and over all tag pixels for comparison.

Per dark area: the median and mean step, the noise, their ratio, and ``cell_snr``: the SNR of the mean of
``--cell-px`` pixels of one code cell in a pair (step / (√2 · noise) · √cell_px; ~90 pixels at 1.0 m). JSON
on stdout. Rendering uses the simulator's own renderer (:class:`ipt.sim.arena.SimulatedArena`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.models import ConfigError, load_arena_config, load_yaml_model, shipped_config_path
from ipt.sender.modulator import phase_sign
from ipt.sim.arena import SimulatedArena, scene_for
from ipt.sim.config import SimConfig, apply_arena_changes
from ipt.sim.render import linear_to_srgb_u8, srgb_to_linear

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]

#: Projector code values at most this are black for a paper-literal sender: 8-bit CIELAB L below ΔL 4 there,
#: so the phase that takes light away clips and the step is one-sided.
BLACK_CODE = 5


class FlippedArena(SimulatedArena):
    """The same arena with every projector frame in the other phase (the tags' steps reversed)."""

    def projector_crop(self, index: int, region: tuple[int, int, int, int]) -> U8:
        x0, y0, x1, y1 = region
        rgb = self._input_frame(self.timing.input_of(index))[y0:y1, x0:x1]
        return self.modulator.phase_region(np.ascontiguousarray(rgb), -phase_sign(index), region)


class BareArena(SimulatedArena):
    """The same arena with the content projected as it is: no tags hidden in it."""

    def projector_crop(self, index: int, region: tuple[int, int, int, int]) -> U8:
        x0, y0, x1, y1 = region
        return np.ascontiguousarray(self._input_frame(self.timing.input_of(index))[y0:y1, x0:x1])


def grey(image: U8) -> F32:
    return np.asarray(image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), np.float32)


def _stats(step: F32, noise: F32, cell_px: float) -> dict[str, Any]:
    if step.size == 0:
        return {"pixels": 0}
    step_abs = np.abs(step)
    median, noise_sd = float(np.median(step_abs)), float(np.std(noise))
    return {
        "pixels": int(step.size),
        "step_median_grey": round(median, 2),
        "step_mean_grey": round(float(step_abs.mean()), 2),
        "noise_sd_grey": round(noise_sd, 2),
        "step_over_noise": round(median / noise_sd, 2) if noise_sd > 0 else None,
        "cell_snr": round(median / (math.sqrt(2) * noise_sd) * math.sqrt(cell_px), 1) if noise_sd > 0 else None,
    }


def _whole_phase_frames(arena: SimulatedArena, count: int, seconds: float) -> list[int]:
    """``count`` camera frames spread over ``seconds``, each moved on to the next one whose exposure lies in
    one projector frame (a frame across a flip sees a blend of the two phases and shows less of the step)."""
    cam = arena.sim.camera
    half_s = (cam.exposure_ms + cam.readout_ms) * 1e-3 / 2
    last = max(0, round(seconds * cam.fps) - 1)
    out = []
    for k in np.linspace(0, last, count).astype(int):
        for j in range(int(k), last + 1):
            t = j / cam.fps
            first, end = arena.projector_indices(np.array([t - half_s, t + half_s]))
            if first == end:
                out.append(j)
                break
    return out


def measure(sim: SimConfig, frames: int, seconds: float, dark_grey: float, cell_px: float) -> dict[str, Any]:
    arena = apply_arena_changes(load_arena_config(shipped_config_path("arena.yaml")), sim.arena)
    cam = sim.camera
    quiet = sim.model_copy(update={"camera": cam.model_copy(update={"read_noise": 0.0, "full_well_e": 1e12})})
    bare = quiet.model_copy(update={"camera": quiet.camera.model_copy(update={"ambient": 0.0})})
    scene = scene_for(sim, arena)
    noisy, clean = SimulatedArena(arena, sim, scene), SimulatedArena(arena, quiet, scene)
    flipped, content = FlippedArena(arena, quiet, scene), BareArena(arena, bare, scene)
    parts: dict[str, tuple[list[F32], list[F32]]] = {k: ([], []) for k in ("dark", "black", "dim", "all")}
    levels: list[float] = []
    measured = _whole_phase_frames(clean, frames, seconds)
    # The camera's grey of a projector at BLACK_CODE, without room light: content at most this is black.
    black_grey = float(linear_to_srgb_u8(srgb_to_linear(np.full((1, 1), BLACK_CODE, np.uint8)) * cam.gain)[0, 0])
    for k in measured:
        base = grey(clean.render(int(k)).image_rgb)
        step = grey(flipped.render(int(k)).image_rgb) - base
        noise = grey(noisy.render(int(k)).image_rgb) - base
        lit = grey(content.render(int(k)).image_rgb)
        tags = np.abs(step) >= 0.5
        dark = tags & (lit <= dark_grey)
        levels.extend(base[dark][::50].tolist())
        for name, where in (
            ("dark", dark),
            ("black", dark & (lit <= black_grey)),
            ("dim", dark & (lit > black_grey)),
            ("all", tags),
        ):
            parts[name][0].append(step[where])
            parts[name][1].append(noise[where])
    out: dict[str, Any] = {
        "frames": frames,
        "measured_frames": measured,
        "dark_grey": dark_grey,
        "black_grey": black_grey,
        "dark_area_grey_median": round(float(np.median(levels)), 1) if levels else None,
    }
    for name, (steps, noises) in parts.items():
        out[name] = _stats(np.concatenate(steps), np.concatenate(noises), cell_px)
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flight", type=Path, help="a flight file (benchmarks/flights/*.yaml)")
    p.add_argument("--frames", type=int, default=12, help="frames measured, spread over the flight (default 12)")
    p.add_argument("--seconds", type=float, default=8.0, help="length of the flight they are spread over (default 8)")
    p.add_argument("--dark-grey", type=float, default=40.0, help="content at most this grey is dark (default 40)")
    p.add_argument("--cell-px", type=float, default=90.0, help="camera pixels per code cell (default 90: 1.0 m)")
    args = p.parse_args()
    if not (1 <= args.frames <= 1000 and 0 < args.seconds <= 600 and args.cell_px > 0):
        print("dark_signal: --frames must be 1-1000, --seconds in (0, 600], --cell-px > 0", file=sys.stderr)
        return 2
    try:
        sim = load_yaml_model(args.flight, SimConfig)
    except (ConfigError, OSError) as exc:
        print(f"dark_signal: {args.flight}: {exc}", file=sys.stderr)
        return 2
    result = {"flight": args.flight.stem, **measure(sim, args.frames, args.seconds, args.dark_grey, args.cell_px)}
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
