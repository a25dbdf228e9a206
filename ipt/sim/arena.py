"""The simulated arena: a projector showing modulated video and a camera flying over it.

Timing: camera frame ``k`` is exposed for ``exposure_ms`` centred on ``k / fps`` (its middle row's, with a
rolling shutter). The projector flips frames every ``1 / (rate_hz · (1 + ppm·1e-6))`` seconds, the first
flip at ``projector_offset_ms``; an exposure that straddles a flip sees both phases in proportion. The
ground truth of frame ``k`` is the camera pose at ``k / fps``, in the floor's frame. Every frame has its
own random stream (seeded by the flight's seed and the frame number), so frames can be rendered in any
order, or in several processes, and come out the same.

Geometry: the projector's pixels land on the floor where the arena says (:mod:`ipt.tagmap`), unless the
flight keystones them (``keystone``): then by its own homography, which the receiver is not told.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.calib.floor import grid_pixels
from ipt.config.models import ArenaConfig, ConfigError, FloorConfig, floor_homography_fits
from ipt.sender.content import ContentSource, GeneratedScene
from ipt.sender.modulator import JIT_UNAVAILABLE, FrameTiming, make_modulator, phase_sign
from ipt.sender.photos import PanningPhotoScene
from ipt.sim.config import SimConfig, apply_arena_changes
from ipt.sim.darkscene import DarkScene
from ipt.sim.flight import Flight, FlightState, HoverPath, Oscillation, Path, RectangleFlight, TakeoffPath
from ipt.sim.render import CameraRenderer
from ipt.tagmap import TagMap, arena_to_pixel_matrix, grid_tag_map, pixel_to_arena_m

U8 = npt.NDArray[np.uint8]
I64 = npt.NDArray[np.int64]
F64 = npt.NDArray[np.float64]

#: Dithering patterns kept (projector frame j uses pattern j mod this); each is one byte per pixel.
DITHER_PATTERNS = 6


@dataclass(frozen=True)
class SimFrame:
    """A rendered camera frame with its ground truth."""

    index: int
    time_s: float
    image_rgb: U8
    """H×W×3 uint8 RGB, or H×W uint8 grey from a mono camera."""
    truth: FlightState


def flight_of(sim: SimConfig) -> Flight:
    """The configured flight: its path, with the pilot's wandering and the airframe's vibration."""
    f = sim.flight
    path: Path
    if f.path == "rectangle":
        path = RectangleFlight(
            size_m=f.size_m,
            centre_m=f.centre_m,
            altitude_m=f.altitude_m,
            altitude_wobble_m=f.altitude_wobble_m,
            peak_speed_mps=f.peak_speed_mps,
        )
    elif f.path == "takeoff":
        t = f.takeoff
        path = TakeoffPath(f.centre_m, t.low_m, t.high_m, t.hold_low_s, t.climb_s, t.hold_high_s)
    else:
        path = HoverPath(f.centre_m, f.altitude_m, f.altitude_wobble_m)
    rng = np.random.default_rng([sim.seed, 3])
    drift = (Oscillation(), Oscillation())
    if f.pilot is not None:
        drift = (
            Oscillation.random(rng, f.pilot.drift_m, f.pilot.drift_hz),
            Oscillation.random(rng, f.pilot.drift_m, f.pilot.drift_hz),
        )
    vibration = (Oscillation(), Oscillation(), Oscillation())
    if f.vibration is not None:
        v = f.vibration
        peak, peak_yaw = np.deg2rad(v.amplitude_deg), np.deg2rad(v.yaw_amplitude_deg)
        vibration = (
            Oscillation.random(rng, float(peak), v.frequency_hz),
            Oscillation.random(rng, float(peak), v.frequency_hz),
            Oscillation.random(rng, float(peak_yaw), v.frequency_hz),
        )
    return Flight(path, float(np.deg2rad(f.heading_deg)), float(np.deg2rad(f.yaw_wobble_deg)), drift, vibration)


def scene_for(sim: SimConfig, arena: ArenaConfig) -> ContentSource:
    """The content the flight's settings ask for (``content.kind``), at the projector's size."""
    pr = arena.projector
    c = sim.content
    if c.kind == "map":
        return GeneratedScene(pr.width_px, pr.height_px, seed=sim.seed)
    if c.kind == "dark":
        return DarkScene(pr.width_px, pr.height_px, sim.seed, c.pan_px_per_frame, c.cut_every_s)
    return PanningPhotoScene(pr.width_px, pr.height_px, sim.seed, c.pan_px_per_frame, c.cut_every_s)


def _four_point_homography(image: list[tuple[float, float]], floor: list[tuple[float, float]]) -> F64:
    """The homography through four correspondences, in float64 (OpenCV's getPerspectiveTransform is float32);
    ``ValueError`` if three are on one line."""
    a = []
    for (u, v), (x, y) in zip(image, floor, strict=True):
        a.append([u, v, 1, 0, 0, 0, -u * x, -v * x, x])
        a.append([0, 0, 0, u, v, 1, -u * y, -v * y, y])
    sys_ = np.array(a, np.float64)
    if abs(float(np.linalg.det(sys_[:, :8]))) < 1e-300:
        raise ValueError("three corners on one line")
    return np.append(np.linalg.solve(sys_[:, :8], sys_[:, 8]), 1.0).reshape(3, 3)


def _shifted(
    arena: ArenaConfig, rect: tuple[int, int, int, int], shifts: Sequence[tuple[float, float]], tile: int | None
) -> FloorConfig:
    """The mapping of canvas ``rect`` (x, y, w, h) whose corners land ``shifts`` away from where ``arena``
    (tile ``tile``) puts them."""
    x0, y0, w, h = rect
    xs, ys = (float(x0), float(x0 + w)), (float(y0), float(y0 + h))
    image = [(xs[0], ys[0]), (xs[1], ys[0]), (xs[1], ys[1]), (xs[0], ys[1])]
    floor = [
        (x + dx, y + dy)
        for (x, y, _), (dx, dy) in zip((pixel_to_arena_m(arena, u, v, tile) for u, v in image), shifts, strict=True)
    ]
    m = _four_point_homography(image, floor)
    rows = tuple(tuple(float(x) for x in r) for r in m)
    measured = FloorConfig(pixel_to_floor=rows)
    shifted = tuple((r[0], r[1], r[0] * x0 + r[1] * y0 + r[2]) for r in rows)  # the tile's own pixels
    problem = floor_homography_fits(FloorConfig(pixel_to_floor=shifted), w, h)
    if problem is not None:
        raise ValueError(problem)
    return measured


def true_arena(arena: ArenaConfig, sim: SimConfig) -> ArenaConfig:
    """The arena as the floor truly gets it: ``arena`` itself, or with a keystoned flight's (``sim.keystone``)
    true floor homographies in place of its layout (the one projector's, or each tile's).
    :class:`ConfigError` if the keystone is not a usable one."""
    k = sim.keystone
    if k is None:
        return arena
    pr = arena.projector
    try:
        if arena.projectors is None:
            if k.tile_corner_shift_m is not None:
                raise ValueError("tile_corner_shift_m is for an arena of several projectors (projectors:)")
            return arena.model_copy(
                update={"floor": _shifted(arena, (0, 0, pr.width_px, pr.height_px), k.corner_shift_m, None)}
            )
        shifts = k.tile_corner_shift_m
        if shifts is None or len(shifts) != len(arena.projectors):
            raise ValueError(f"tile_corner_shift_m must list one entry per projector ({len(arena.projectors)})")
        tiles = []
        for n, (t, corners) in enumerate(zip(arena.projectors, shifts, strict=True)):
            f = _shifted(arena, (t.x_px, t.y_px, t.width_px, t.height_px), corners, n)
            tiles.append(t.model_copy(update={"pixel_to_floor": f.pixel_to_floor}))
        return arena.model_copy(update={"projectors": tuple(tiles)})
    except ValueError as exc:
        raise ConfigError(f"keystone: the corner shifts give no usable image on the floor ({exc})") from None


def survey_points(arena: ArenaConfig, sim: SimConfig) -> list[tuple[float, float, float, float]]:
    """The survey of a keystoned floor a user would make: (u_px, v_px, x_m, y_m) of each mark of the flight's
    ``survey_grid`` (in each projector's part of the canvas), where it truly lands, measured with
    ``survey_noise_m`` of noise (seeded by the flight)."""
    if sim.keystone is None:
        return []
    k, truth = sim.keystone, true_arena(arena, sim)
    rng = np.random.default_rng([sim.seed, 17])
    pr = arena.projector
    rects = [(t.x_px, t.y_px, t.width_px, t.height_px) for t in arena.projectors or ()] or [
        (0, 0, pr.width_px, pr.height_px)
    ]
    out = []
    for n, (x0, y0, w, h) in enumerate(rects):
        for u, v in grid_pixels(w, h, *k.survey_grid):
            tile = n if arena.projectors is not None else None
            x, y, _ = pixel_to_arena_m(truth, x0 + u, y0 + v, tile)
            nx, ny = rng.normal(0.0, k.survey_noise_m, 2) if k.survey_noise_m > 0 else (0.0, 0.0)
            out.append((float(x0 + u), float(y0 + v), x + float(nx), y + float(ny)))
    return out


class SimulatedArena:
    """Renders the camera's view frame by frame; deterministic for a given seed."""

    def __init__(self, arena: ArenaConfig, sim: SimConfig, scene: ContentSource, tag_map: TagMap | None = None) -> None:
        arena = apply_arena_changes(arena, sim.arena)
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
        truth = true_arena(arena, sim)  # where the projector's pixels truly land
        tiles = [
            (arena_to_pixel_matrix(truth, n), (t.x_px, t.y_px, t.x_px + t.width_px, t.y_px + t.height_px))
            for n, t in enumerate(truth.projectors or ())
        ]
        self.renderer = CameraRenderer(
            sim.camera,
            tiles[0][0] if tiles else arena_to_pixel_matrix(truth),
            (arena.projector.width_px, arena.projector.height_px),
            shadow=sim.shadow,
            seed=sim.seed,
            tiles=tiles,
        )
        self._inputs: OrderedDict[int, U8] = OrderedDict()
        self._dither: dict[int, tuple[U8, U8]] = {}

    def projector_index(self, t_s: float) -> int:
        """Index of the projector frame on the floor at time ``t_s`` (frame 0 until the first flip)."""
        return int(self.projector_indices(np.array([t_s]))[0])

    def projector_indices(self, times_s: F64) -> I64:
        """:meth:`projector_index` of each time."""
        offset = (self.sim.projector_offset_ms * 1e-3) % self.projector_period_s
        return np.floor((np.asarray(times_s) - offset) / self.projector_period_s).astype(np.int64) + 1

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

    def _dither_patterns(self, index: int) -> tuple[U8, U8]:
        """Projector frame ``index``'s dithering as two 8-bit images: the levels added, the levels taken."""
        key = index % DITHER_PATTERNS
        if key not in self._dither:
            pr, levels = self.arena.projector, self.sim.projector_dither_levels
            rng = np.random.default_rng([self.sim.seed, 11, key])
            step = rng.integers(-levels, levels + 1, (pr.height_px, pr.width_px), dtype=np.int8)
            up, down = np.maximum(step, 0).astype(np.uint8), np.maximum(-step, 0).astype(np.uint8)
            self._dither[key] = (cv2.merge([up, up, up]), cv2.merge([down, down, down]))
        return self._dither[key]

    def projected(self, index: int, region: tuple[int, int, int, int]) -> U8:
        """What the projector puts on the floor in ``region`` during frame ``index``: :meth:`projector_crop`
        with the projector's own temporal dithering (the same level on the three colours of a pixel)."""
        crop = self.projector_crop(index, region)
        if self.sim.projector_dither_levels == 0:
            return crop
        x0, y0, x1, y1 = region
        up, down = self._dither_patterns(index)
        out = np.asarray(cv2.add(crop, up[y0:y1, x0:x1]), dtype=np.uint8)  # saturating
        return np.asarray(cv2.subtract(out, down[y0:y1, x0:x1]), dtype=np.uint8)

    def render(self, k: int) -> SimFrame:
        """Camera frame ``k``."""
        t = k / self.sim.camera.fps
        rng = np.random.default_rng([self.sim.seed, 5, k])
        image = self.renderer.render_frame(t, self.flight.state, self.projector_indices, self.projected, rng)
        return SimFrame(k, t, image, self.flight.state(t))

    def frames(self, count: int, start: int = 0) -> Iterator[SimFrame]:
        """Frames ``start`` .. ``start + count - 1`` in order."""
        for k in range(start, start + count):
            yield self.render(k)
