"""The simulated arena: a projector showing modulated video and a camera flying over it.

Timing: camera frame ``k`` is exposed for ``exposure_ms`` centred on ``k / fps``. The projector flips
frames every ``1 / (rate_hz · (1 + ppm·1e-6))`` seconds, the first flip at ``projector_offset_ms``; an
exposure that straddles a flip sees both phases in proportion. The ground truth of frame ``k`` is the
camera pose at ``k / fps``.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.models import ArenaConfig
from ipt.sender.content import Scene
from ipt.sender.modulator import JIT_UNAVAILABLE, FrameTiming, make_modulator, phase_sign
from ipt.sim.config import SimConfig
from ipt.sim.flight import FlightState, RectangleFlight
from ipt.sim.render import CameraRenderer, Exposure
from ipt.tagmap import TagMap, arena_to_pixel_matrix, grid_tag_map

U8 = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class SimFrame:
    """A rendered camera frame with its ground truth."""

    index: int
    time_s: float
    image_rgb: U8
    truth: FlightState


def flight_of(sim: SimConfig) -> RectangleFlight:
    """The configured flight path."""
    f = sim.flight
    return RectangleFlight(
        size_m=f.size_m,
        centre_m=f.centre_m,
        altitude_m=f.altitude_m,
        altitude_wobble_m=f.altitude_wobble_m,
        peak_speed_mps=f.peak_speed_mps,
        heading_rad=float(np.deg2rad(f.heading_deg)),
        yaw_wobble_rad=float(np.deg2rad(f.yaw_wobble_deg)),
    )


class SimulatedArena:
    """Renders the camera's view frame by frame; deterministic for a given seed."""

    def __init__(self, arena: ArenaConfig, sim: SimConfig, scene: Scene, tag_map: TagMap | None = None) -> None:
        self.arena, self.sim, self.scene = arena, sim, scene
        self.tag_map = tag_map if tag_map is not None else grid_tag_map(arena)
        mod = arena.modulation
        self.notes: list[str] = []
        """What the simulator changed from the configuration, and why (shown by the tools that run it)."""
        profile = mod.profile
        if profile == "ipt" and JIT_UNAVAILABLE is not None:
            # The simulator only plays the projector: it may use the paper's profile where the ipt one
            # cannot run (a hardened service forbids the JIT's executable memory). Say so.
            self.notes.append(f"{JIT_UNAVAILABLE}: the simulated projector uses the paper modulation profile")
            profile = "paper"
        self.modulator = make_modulator(
            profile, self.tag_map.render_mask(), mod.delta_l, clip_allowance_l8=mod.clip_allowance_l8
        )
        self.flight = flight_of(sim)
        self.timing = FrameTiming(mod.input_rate_hz, arena.projector.rate_hz)
        self.projector_period_s = 1.0 / (arena.projector.rate_hz * (1.0 + sim.projector_clock_ppm * 1e-6))
        self.renderer = CameraRenderer(
            sim.camera, arena_to_pixel_matrix(arena), (arena.projector.width_px, arena.projector.height_px)
        )
        self._rng = np.random.default_rng(sim.seed)
        self._inputs: OrderedDict[int, U8] = OrderedDict()

    def projector_index(self, t_s: float) -> int:
        """Index of the projector frame on the floor at time ``t_s`` (frame 0 until the first flip)."""
        offset = (self.sim.projector_offset_ms * 1e-3) % self.projector_period_s
        return int(np.floor((t_s - offset) / self.projector_period_s)) + 1

    def _input_frame(self, index: int) -> U8:
        if index not in self._inputs:
            rgb = self.scene.frame(index, self.arena.modulation.input_rate_hz)
            pr = self.arena.projector
            if rgb.shape[:2] != (pr.height_px, pr.width_px):
                rgb = cv2.resize(rgb, (pr.width_px, pr.height_px), interpolation=cv2.INTER_AREA)
            self._inputs[index] = rgb
            while len(self._inputs) > 3:
                self._inputs.popitem(last=False)
        return self._inputs[index]

    def projector_crop(self, index: int, region: tuple[int, int, int, int]) -> U8:
        """Region (x0, y0, x1, y1) of projector output frame ``index``, modulated as the sender would (the
        arena's ``modulation.profile``)."""
        x0, y0, x1, y1 = region
        rgb = self._input_frame(self.timing.input_of(index))[y0:y1, x0:x1]
        return self.modulator.phase_region(np.ascontiguousarray(rgb), phase_sign(index), region)

    def render(self, k: int) -> SimFrame:
        """Camera frame ``k``."""
        cam = self.sim.camera
        t = k / cam.fps
        n = cam.time_samples
        exposure_s = cam.exposure_ms * 1e-3
        instants = [t + exposure_s * ((i + 0.5) / n - 0.5) for i in range(n)]
        exposures = [Exposure(self.flight.state(ti), self.projector_index(ti)) for ti in instants]
        image = self.renderer.render(exposures, self.projector_crop, self._rng)
        return SimFrame(k, t, image, self.flight.state(t))

    def frames(self, count: int) -> Iterator[SimFrame]:
        """Frames 0 .. count-1 in order."""
        for k in range(count):
            yield self.render(k)
