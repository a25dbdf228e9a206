"""What the drone's camera sees of the projected floor: geometry, shadow, light, exposure, lens, sensor.

Pure: the projector frames, the camera pose over the exposure and the settings go in; a camera frame
(8-bit RGB, or grey for a mono sensor) comes out. The floor is the plane z = 0 of the arena; projector
pixels map to it linearly (:func:`ipt.tagmap.arena_to_pixel_matrix`), so each camera ray lands on a
projector pixel through one homography per instant. The lens distortion is applied exactly by tracing
every (supersampled) camera pixel through the inverse distortion once.

One frame, in the order light travels:

1. **Exposure.** ``time_samples`` instants spread over the exposure; with a rolling shutter
   (``readout_ms`` > 0) each row is exposed ``readout · (row / (H − 1) − ½)`` later than the frame time,
   so the pose is taken per band of rows and the projector frame per row: a flip can land mid-frame.
2. **Floor.** At each instant, each supersampled pixel takes the linear light of the projector frame on
   the floor then (bilinear); the instants are averaged, then the supersampled pixels.
3. **Shadow.** The drone's body stops part of the projector's light (:mod:`ipt.sim.shadow`); room
   light (``ambient``) is added everywhere.
4. **Lens.** Optical blur, then vignetting and the gain of the frame (automatic gain drifts and steps).
5. **Sensor.** Shot and read noise in linear units, then the camera's sRGB response to 8 bits; a mono
   sensor takes the luminance (Rec. 709 weights in linear light). A USB camera's JPEG compression last.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.sim.config import AutoGainConfig, ShadowConfig, SimCameraConfig
from ipt.sim.flight import FlightState
from ipt.sim.shadow import lit_fraction

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]

#: 8-bit sRGB code value → linear light.
_SRGB_TO_LINEAR = np.array(
    [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in np.arange(256) / 255.0], np.float32
)
#: Rec. 709 luminance of linear RGB: what a mono sensor's (roughly photopic) response integrates.
LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
#: Rows of the image whose pose is taken at one instant under a rolling shutter (at most this many bands).
ROLLING_BANDS = 24
#: Extra projector pixels fetched around the region a frame needs, so the next frames reuse the crop.
CROP_PAD_PX = 48


def srgb_to_linear(img: U8) -> F32:
    """Linear light (0..1) of an 8-bit sRGB image."""
    out: F32 = cv2.LUT(img, _SRGB_TO_LINEAR)
    return out


_LINEAR_STEPS = 65535
_lin = np.arange(_LINEAR_STEPS + 1) / _LINEAR_STEPS
_LINEAR_TO_SRGB = np.rint(
    255.0 * np.where(_lin <= 0.0031308, 12.92 * _lin, 1.055 * np.power(_lin, 1 / 2.4) - 0.055)
).astype(np.uint8)


def linear_to_srgb_u8(img: F32) -> U8:
    """8-bit sRGB code values of linear light (clipped to 0..1), through a 16-bit lookup table."""
    idx = np.clip(img * np.float32(_LINEAR_STEPS) + np.float32(0.5), 0, _LINEAR_STEPS).astype(np.uint16)
    out: U8 = _LINEAR_TO_SRGB[idx]
    return out


def camera_info_of(cfg: SimCameraConfig) -> CameraInfo:
    """The intrinsics the simulated camera is rendered with (written out as camera.yaml)."""
    return CameraInfo(
        width_px=cfg.width_px,
        height_px=cfg.height_px,
        fx_px=cfg.fx_px,
        fy_px=cfg.fy_px,
        cx_px=cfg.cx_px,
        cy_px=cfg.cy_px,
        distortion=tuple(cfg.distortion),
        name="ipt_sim",
    )


@dataclass(frozen=True)
class Exposure:
    """One instant of a global-shutter exposure: the camera pose then and the projector frame on the floor."""

    state: FlightState
    projector_index: int


class AutoGain:
    """A camera's automatic gain over time: a slow sinusoidal drift and random steps (fixed by a seed)."""

    def __init__(self, cfg: AutoGainConfig, seed: int, horizon_s: float = 3600.0) -> None:
        self.cfg = cfg
        rng = np.random.default_rng([seed, 7])
        self._phase = float(rng.uniform(0, 2 * np.pi))
        times: list[float] = []
        levels: list[float] = []
        if cfg.step_pct > 0 and cfg.steps_per_s > 0:
            t, level, step = 0.0, 0.0, cfg.step_pct / 100
            while True:
                t += float(rng.exponential(1.0 / cfg.steps_per_s))
                if t > horizon_s:
                    break
                # Up or down at random, but back towards 1 once three steps away (an auto-gain hunts).
                sign = -np.sign(level) if abs(level) >= 3 * step - 1e-9 else rng.choice((-1.0, 1.0))
                level += float(sign) * step
                times.append(t)
                levels.append(level)
        self._times, self._levels = np.array(times), np.array(levels)

    def factor(self, t_s: float) -> float:
        """The gain at ``t_s`` relative to the configured gain."""
        cfg = self.cfg
        drift = cfg.drift_pct / 100 * np.sin(2 * np.pi * t_s / cfg.drift_period_s + self._phase)
        i = int(np.searchsorted(self._times, t_s, side="right"))
        step = float(self._levels[i - 1]) if i > 0 else 0.0
        return float(max(0.05, 1.0 + drift + step))


def _homographies(states: Sequence[FlightState], arena_to_px: F64) -> F64:
    """Per state, the 3x3 map from normalised camera coordinates (x/z, y/z, 1) to projector pixels."""
    out = np.empty((len(states), 3, 3))
    for i, st in enumerate(states):
        if st.position_m[2] <= 0 or (st.r_arena_cam @ np.array([0.0, 0.0, 1.0]))[2] >= 0:
            raise ValueError("the simulated camera must be above the floor and look down at it")
        out[i] = arena_to_px @ floor_homography_m(st)
    return out


def floor_homography_m(state: FlightState) -> F64:
    """Normalised camera coordinates (x/z, y/z, 1) → floor points (x, y) in arena metres (homogeneous)."""
    r, c = state.r_arena_cam, state.position_m
    # A ray d = R·[xn, yn, 1] from c meets z = 0 at c − (c_z / d_z)·d; in homogeneous floor coordinates
    # that is (c_z·d_xy − d_z·c_xy, −d_z) up to scale.
    return np.array(
        [
            [c[2] * r[0, 0] - c[0] * r[2, 0], c[2] * r[0, 1] - c[0] * r[2, 1], c[2] * r[0, 2] - c[0] * r[2, 2]],
            [c[2] * r[1, 0] - c[1] * r[2, 0], c[2] * r[1, 1] - c[1] * r[2, 1], c[2] * r[1, 2] - c[1] * r[2, 2]],
            [-r[2, 0], -r[2, 1], -r[2, 2]],
        ]
    )


def _apply_rows(rays: F32, band_of_row: npt.NDArray[np.intp], homs: F64, offset: tuple[float, float]) -> F32:
    """Each row's rays through its band's homography, minus ``offset``: a remap map (H×W×2 float32)."""
    out = np.empty(rays.shape, np.float32)
    x, y = rays[:, :, 0], rays[:, :, 1]
    bands = np.unique(band_of_row)
    for b in bands:
        rows = band_of_row == b
        h = homs[b].astype(np.float32)
        xb, yb = x[rows], y[rows]
        den = h[2, 0] * xb + h[2, 1] * yb + h[2, 2]
        out[rows, :, 0] = (h[0, 0] * xb + h[0, 1] * yb + h[0, 2]) / den - np.float32(offset[0])
        out[rows, :, 1] = (h[1, 0] * xb + h[1, 1] * yb + h[1, 2]) / den - np.float32(offset[1])
    return out


def _compiled_apply_rows() -> Callable[..., Any] | None:
    """:func:`_apply_rows` compiled (numba), about 5x faster; None where numba cannot compile."""
    try:
        import numba
    except (ImportError, OSError):
        return None

    def kernel(rays: Any, band_of_row: Any, homs: Any, ox: float, oy: float, out: Any) -> None:
        for r in numba.prange(rays.shape[0]):
            h = homs[band_of_row[r]]
            h00, h01, h02, h10, h11, h12 = h[0, 0], h[0, 1], h[0, 2], h[1, 0], h[1, 1], h[1, 2]
            h20, h21, h22 = h[2, 0], h[2, 1], h[2, 2]
            for c in range(rays.shape[1]):
                x, y = np.float64(rays[r, c, 0]), np.float64(rays[r, c, 1])
                inv = 1.0 / (h20 * x + h21 * y + h22)
                out[r, c, 0] = (h00 * x + h01 * y + h02) * inv - ox
                out[r, c, 1] = (h10 * x + h11 * y + h12) * inv - oy

    try:
        return numba.njit(nogil=True, parallel=True, cache=True)(kernel)
    except RuntimeError:  # no writable cache location
        return numba.njit(nogil=True, parallel=True)(kernel)
    except OSError:  # llvmlite refused executable memory (a hardened service)
        return None


_KERNEL: list[Callable[..., Any] | None] = []


def ray_map(rays: F32, band_of_row: npt.NDArray[np.intp], homs: F64, offset: tuple[float, float]) -> F32:
    """The remap map: each row's rays through its band's homography, minus ``offset`` (H×W×2 float32)."""
    if not _KERNEL:
        _KERNEL.append(_compiled_apply_rows())
    kernel = _KERNEL[0]
    if kernel is not None:
        try:
            out = np.empty(rays.shape, np.float32)
            kernel(rays, band_of_row, homs, float(offset[0]), float(offset[1]), out)
            return out
        except OSError:  # compiling failed only now: fall back for good
            _KERNEL[0] = None
    return _apply_rows(rays, band_of_row, homs, offset)


ProjectorCrop = Callable[[int, tuple[int, int, int, int]], U8]
"""``crop(j, (x0, y0, x1, y1))``: that region of projector output frame ``j``, 8-bit sRGB (H×W×3)."""


@dataclass(frozen=True)
class _Sample:
    """One instant of the exposure: the pose of each band of rows and the projector frame of each row."""

    homographies: F64
    """(bands, 3, 3): normalised camera coordinates → projector pixels, per band."""
    row_index: I64
    """(supersampled rows,): the projector frame on the floor when each row was exposed."""


class CameraRenderer:
    """Renders camera frames of a floor lit by projector frames (edge-origin projector pixels)."""

    def __init__(
        self,
        cfg: SimCameraConfig,
        arena_to_px: F64,
        projector_size: tuple[int, int],
        shadow: ShadowConfig | None = None,
        seed: int = 0,
        tiles: Sequence[tuple[F64, tuple[int, int, int, int]]] = (),
    ) -> None:
        self.cfg = cfg
        self.arena_to_px = arena_to_px
        self.px_to_arena = np.linalg.inv(arena_to_px)
        self.proj_w, self.proj_h = projector_size
        # Several projectors: each lights the floor with its own part (x0, y0, x1, y1) of the canvas through
        # its own mapping; their light adds (a gap between them stays dark, an overlap is brighter). Kept as
        # the map from the first mapping's projector pixels to each tile's, as every sample holds the first.
        self._tiles = [(np.asarray(m, np.float64) @ self.px_to_arena, rect) for m, rect in tiles]
        self.shadow = shadow
        self.channels = 1 if cfg.mono else 3
        info = camera_info_of(cfg)
        ss = cfg.supersample
        self._rays_ss = _normalised_rays(info, cfg.width_px * ss, cfg.height_px * ss, ss)
        self._rays_half = np.ascontiguousarray(
            cv2.resize(
                _normalised_rays(info, cfg.width_px, cfg.height_px, 1),
                ((cfg.width_px + 1) // 2, (cfg.height_px + 1) // 2),
                interpolation=cv2.INTER_AREA,
            )
        )
        self._seed = seed
        self._noise_pool: F32 | None = None
        self._shape_ss = (ss * cfg.height_px, ss * cfg.width_px)
        rows = np.arange(self._shape_ss[0])
        row_cam = (rows + 0.5) / ss - 0.5
        self._row_offset_s = cfg.readout_ms * 1e-3 * (row_cam / max(cfg.height_px - 1, 1) - 0.5)
        bands = 1 if cfg.readout_ms == 0 else min(ROLLING_BANDS, cfg.height_px)
        self._band_of_row = np.minimum(rows * bands // self._shape_ss[0], bands - 1).astype(np.intp)
        self._band_offset_s = np.array([self._row_offset_s[self._band_of_row == b].mean() for b in range(bands)])
        self._one_band = np.zeros(self._shape_ss[0], np.intp)
        r = self._rays_ss
        self._border = np.concatenate([r[0], r[-1], r[:, 0], r[:, -1]]).astype(np.float64)
        self._vignette = _vignette(cfg)
        self.auto_gain = AutoGain(cfg.auto_gain, seed)
        self._lit: OrderedDict[int, tuple[tuple[int, int, int, int], F32]] = OrderedDict()

    # -- the exposure ---------------------------------------------------------------------------------

    def frame_samples(
        self, t_s: float, state_at: Callable[[float], FlightState], index_at: Callable[[F64], I64]
    ) -> list[_Sample]:
        """The instants of frame time ``t_s``'s exposure (rows staggered by the rolling shutter)."""
        cfg = self.cfg
        n = cfg.time_samples
        out = []
        for i in range(n):
            t = t_s + cfg.exposure_ms * 1e-3 * ((i + 0.5) / n - 0.5)
            states = [state_at(t + dt) for dt in self._band_offset_s]
            out.append(_Sample(_homographies(states, self.arena_to_px), index_at(t + self._row_offset_s)))
        return out

    def render_frame(
        self,
        t_s: float,
        state_at: Callable[[float], FlightState],
        index_at: Callable[[F64], I64],
        projector_crop: ProjectorCrop,
        rng: np.random.Generator,
    ) -> U8:
        """Camera frame at time ``t_s`` (its middle row's), for the flight ``state_at`` over the floor
        lit by projector frame ``index_at(t)`` at each time."""
        samples = self.frame_samples(t_s, state_at, index_at)
        return self._render(samples, state_at(t_s), self.auto_gain.factor(t_s), projector_crop, rng)

    def render(self, exposures: Sequence[Exposure], projector_crop: ProjectorCrop, rng: np.random.Generator) -> U8:
        """One global-shutter frame averaging the given instants (the first one's pose casts the shadow)."""
        rows = self._shape_ss[0]
        samples = [
            _Sample(_homographies([e.state], self.arena_to_px), np.full(rows, e.projector_index, np.int64))
            for e in exposures
        ]
        return self._render(samples, exposures[len(exposures) // 2].state, 1.0, projector_crop, rng)

    # -- the parts ------------------------------------------------------------------------------------

    def _region(self, samples: Sequence[_Sample]) -> tuple[int, int, int, int] | None:
        """The projector region (x0, y0, x1, y1) seen during the exposure, or None if none of it is."""
        homs = np.concatenate([s.homographies for s in samples])
        pts = np.concatenate([self._border, np.ones((len(self._border), 1))], axis=1)
        proj = np.einsum("bij,nj->bni", homs, pts)
        if np.any(proj[:, :, 2] <= 0):
            return (0, 0, self.proj_w, self.proj_h)
        uv = proj[:, :, :2] / proj[:, :, 2:]
        x0 = max(0, int(np.floor(uv[:, :, 0].min())) - 2)
        x1 = min(self.proj_w, int(np.ceil(uv[:, :, 0].max())) + 2)
        y0 = max(0, int(np.floor(uv[:, :, 1].min())) - 2)
        y1 = min(self.proj_h, int(np.ceil(uv[:, :, 1].max())) + 2)
        if x1 <= x0 or y1 <= y0:
            return None
        return (x0, y0, x1, y1)

    def _tile_views(self, samples: Sequence[_Sample]) -> list[tuple[Sequence[_Sample], tuple[int, int, int, int]]]:
        """Per projector: the samples through its mapping, and the part of its canvas region in view."""
        if not self._tiles:
            region = self._region(samples)
            return [] if region is None else [(samples, region)]
        out: list[tuple[Sequence[_Sample], tuple[int, int, int, int]]] = []
        for to_tile, (tx0, ty0, tx1, ty1) in self._tiles:
            mine = [_Sample(np.einsum("ij,bjk->bik", to_tile, s.homographies), s.row_index) for s in samples]
            region = self._region(mine)
            if region is None:
                continue
            x0, y0, x1, y1 = max(region[0], tx0), max(region[1], ty0), min(region[2], tx1), min(region[3], ty1)
            if x1 > x0 and y1 > y0:
                out.append((mine, (x0, y0, x1, y1)))
        return out

    def _lit_view(self, j: int, region: tuple[int, int, int, int], crop: ProjectorCrop) -> F32:
        """Linear light of ``region`` of projector frame ``j`` (a view whose origin is the region's)."""
        x0, y0, x1, y1 = region
        held = self._lit.get(j)
        if held is None or not (held[0][0] <= x0 and held[0][1] <= y0 and x1 <= held[0][2] and y1 <= held[0][3]):
            box = (
                max(0, x0 - CROP_PAD_PX),
                max(0, y0 - CROP_PAD_PX),
                min(self.proj_w, x1 + CROP_PAD_PX),
                min(self.proj_h, y1 + CROP_PAD_PX),
            )
            linear = srgb_to_linear(np.ascontiguousarray(crop(j, box)))
            if self.channels == 1:
                w = LUMINANCE_WEIGHTS
                linear = np.asarray(
                    linear[:, :, 0] * np.float32(w[0])
                    + linear[:, :, 1] * np.float32(w[1])
                    + linear[:, :, 2] * np.float32(w[2]),
                    np.float32,
                )
            held = (box, linear)
            self._lit[j] = held
            while len(self._lit) > 4:
                self._lit.popitem(last=False)
        self._lit.move_to_end(j)
        bx0, by0, _, _ = held[0]
        return held[1][y0 - by0 : y1 - by0, x0 - bx0 : x1 - bx0]

    def _shadow_light(self, state: FlightState) -> F32 | None:
        """Fraction of the projector's light reaching the floor each camera pixel sees (None: no shadow).

        Computed at half resolution and enlarged: the shadow's edge is soft over many pixels."""
        if self.shadow is None:
            return None
        m = floor_homography_m(state)
        rays = self._rays_half
        floor = ray_map(rays, np.zeros(rays.shape[0], np.intp), m[None], (0.0, 0.0))
        normal = state.r_arena_cam @ np.array([0.0, 0.0, -1.0])  # the camera looks down the body's -z
        half = lit_fraction(floor[:, :, 0], floor[:, :, 1], state.position_m, normal, self.shadow)
        return np.asarray(
            cv2.resize(half, (self.cfg.width_px, self.cfg.height_px), interpolation=cv2.INTER_LINEAR), np.float32
        )

    def _normal(self, rng: np.random.Generator, shape: tuple[int, ...]) -> F32:
        """Standard normal noise of ``shape``: a slice of a pool drawn once, at an offset drawn per frame.

        Drawing 700,000 normals took a sixth of a frame's time; slices of one pool at random offsets are
        as independent between frames as the pairing of two frames can tell."""
        size = int(np.prod(shape))
        if self._noise_pool is None or len(self._noise_pool) < 4 * size:
            self._noise_pool = np.random.default_rng([self._seed, 13]).standard_normal(8 * size, dtype=np.float32)
        start = int(rng.integers(0, len(self._noise_pool) - size))
        return self._noise_pool[start : start + size].reshape(shape)

    def _render(
        self,
        samples: Sequence[_Sample],
        mid_state: FlightState,
        gain_factor: float,
        projector_crop: ProjectorCrop,
        rng: np.random.Generator,
    ) -> U8:
        cfg = self.cfg
        shape = (*self._shape_ss, self.channels) if self.channels > 1 else self._shape_ss
        acc: F32 | None = None
        for tile_samples, region in self._tile_views(samples):
            offset = (region[0] + 0.5, region[1] + 0.5)  # remap samples at pixel centres: u − 0.5
            for s in tile_samples:
                bands = self._band_of_row if len(s.homographies) > 1 else self._one_band
                mp = ray_map(self._rays_ss, bands, s.homographies, offset)
                cuts = np.flatnonzero(np.diff(s.row_index)) + 1
                for r0, r1 in zip(np.r_[0, cuts], np.r_[cuts, len(s.row_index)], strict=True):
                    lit = self._lit_view(int(s.row_index[r0]), region, projector_crop)
                    seen = cv2.remap(lit, mp[r0:r1], None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
                    if acc is None and r0 == 0 and r1 == len(s.row_index):
                        acc = np.asarray(seen, np.float32)  # the first instant over the whole frame
                        continue
                    if acc is None:
                        acc = np.zeros(shape, np.float32)
                    part = acc[r0:r1]
                    cv2.add(part, seen, dst=part)
        if acc is None:
            acc = np.zeros(shape, np.float32)
        # The supersampled pixels average on the sensor; the instants average over the exposure.
        proj = np.asarray(
            cv2.resize(acc, (cfg.width_px, cfg.height_px), interpolation=cv2.INTER_AREA)
            if cfg.supersample > 1
            else acc,
            np.float32,
        ) * np.float32(1.0 / len(samples))
        shadow = self._shadow_light(mid_state)
        if shadow is not None:
            proj *= shadow if self.channels == 1 else shadow[:, :, None]
        light = proj + np.float32(cfg.ambient)
        if cfg.blur_sigma_px > 0:
            light = np.asarray(cv2.GaussianBlur(light, (0, 0), cfg.blur_sigma_px), np.float32)
        scale = self._vignette * np.float32(cfg.gain * gain_factor)
        signal = light * (scale if self.channels == 1 else scale[:, :, None])
        # Shot and read noise in linear units, then the camera's sRGB response.
        sigma = np.sqrt(np.clip(signal, 0, None) / np.float32(cfg.full_well_e) + np.float32(cfg.read_noise**2))
        noisy = signal + self._normal(rng, signal.shape) * sigma
        image = linear_to_srgb_u8(noisy.astype(np.float32))
        if cfg.jpeg_quality is not None:
            image = jpeg_round_trip(image, cfg.jpeg_quality)
        return image


def jpeg_round_trip(image: U8, quality: int) -> U8:
    """``image`` (grey or RGB) as a camera's JPEG encoder and a decoder leave it."""
    bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, data = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    out = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    return np.asarray(out if image.ndim == 2 else cv2.cvtColor(out, cv2.COLOR_BGR2RGB), np.uint8)


def _normalised_rays(info: CameraInfo, width: int, height: int, ss: int) -> F32:
    """Undistorted normalised coordinates of the centres of a ``width``×``height`` grid of (sub)pixels."""
    xs = (np.arange(width) + 0.5) / ss - 0.5
    ys = (np.arange(height) + 0.5) / ss - 0.5
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 1, 2).astype(np.float64)
    undist = cv2.undistortPoints(
        grid,
        info.camera_matrix,
        info.dist_coeffs,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10),
    )
    return np.ascontiguousarray(undist.reshape(height, width, 2).astype(np.float32))


def _vignette(cfg: SimCameraConfig) -> F32:
    """Relative illumination per pixel: 1 − v·(r / r_corner)² with r from the principal point."""
    ys, xs = np.mgrid[0 : cfg.height_px, 0 : cfg.width_px].astype(np.float32)
    r2 = (xs - np.float32(cfg.cx_px)) ** 2 + (ys - np.float32(cfg.cy_px)) ** 2
    corner2 = max(
        (x - cfg.cx_px) ** 2 + (y - cfg.cy_px) ** 2 for x in (0, cfg.width_px - 1) for y in (0, cfg.height_px - 1)
    )
    return np.asarray(1.0 - np.float32(cfg.vignetting) * r2 / np.float32(corner2), np.float32)
