"""What the drone's camera sees of the projected floor: geometry, light, exposure, lens and noise.

Pure: the projector frames, the camera pose over the exposure and the settings go in; an RGB camera
frame comes out. The floor is the plane z = 0 of the arena; projector pixels map to it linearly
(:func:`ipt.tagmap.arena_to_pixel_matrix`), so each camera ray lands on a projector pixel through one
homography per instant. The lens distortion is applied exactly by tracing every (supersampled) camera
pixel through the inverse distortion once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.sim.config import SimCameraConfig
from ipt.sim.flight import FlightState

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

#: 8-bit sRGB code value → linear light.
_SRGB_TO_LINEAR = np.array(
    [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in np.arange(256) / 255.0], np.float32
)


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
    """One instant of an exposure: the camera pose then and the projector frame on the floor then."""

    state: FlightState
    projector_index: int


class CameraRenderer:
    """Renders camera frames of a floor lit by projector frames (edge-origin projector pixels)."""

    def __init__(self, cfg: SimCameraConfig, arena_to_px: F64, projector_size: tuple[int, int]) -> None:
        self.cfg = cfg
        self.arena_to_px = arena_to_px
        self.proj_w, self.proj_h = projector_size
        info = camera_info_of(cfg)
        ss = cfg.supersample
        # Centres of the supersampled sub-pixels in camera pixel coordinates (OpenCV convention).
        xs = (np.arange(cfg.width_px * ss) + 0.5) / ss - 0.5
        ys = (np.arange(cfg.height_px * ss) + 0.5) / ss - 0.5
        grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 1, 2).astype(np.float64)
        undist = cv2.undistortPoints(
            grid,
            info.camera_matrix,
            info.dist_coeffs,
            criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10),
        )
        self._rays_norm = undist.reshape(ss * cfg.height_px, ss * cfg.width_px, 2).astype(np.float32)
        self._shape_ss = (ss * cfg.height_px, ss * cfg.width_px)

    def _floor_homography(self, state: FlightState) -> F64:
        """Normalised camera coordinates (x/z, y/z, 1) → projector pixels (edge origin)."""
        r = state.r_arena_cam
        c = state.position_m
        # A ray d = R·[xn, yn, 1] from c meets z = 0 at c − (c_z / d_z)·d; in homogeneous floor coordinates
        # that is (c_z·d_xy − d_z·c_xy, −d_z) up to scale.
        m = np.array(
            [
                [c[2] * r[0, 0] - c[0] * r[2, 0], c[2] * r[0, 1] - c[0] * r[2, 1], c[2] * r[0, 2] - c[0] * r[2, 2]],
                [c[2] * r[1, 0] - c[1] * r[2, 0], c[2] * r[1, 1] - c[1] * r[2, 1], c[2] * r[1, 2] - c[1] * r[2, 2]],
                [-r[2, 0], -r[2, 1], -r[2, 2]],
            ]
        )
        return np.asarray(self.arena_to_px @ m)

    def projector_maps(self, states: Sequence[FlightState]) -> list[F32]:
        """Per instant, the projector pixel (edge origin) that each supersampled camera pixel sees."""
        maps = []
        for st in states:
            if st.position_m[2] <= 0 or (st.r_arena_cam @ np.array([0.0, 0.0, 1.0]))[2] >= 0:
                raise ValueError("the simulated camera must be above the floor and look down at it")
            h = self._floor_homography(st)
            pts = cv2.perspectiveTransform(self._rays_norm.reshape(-1, 1, 2), h)
            maps.append(pts.reshape(*self._shape_ss, 2).astype(np.float32))
        return maps

    def _region(self, maps: Sequence[F32]) -> tuple[int, int, int, int] | None:
        """The projector region (x0, y0, x1, y1) seen during the exposure, or None if none of it is.

        The floor seen by the camera is the image of the sensor's outline, so the outline's extremes bound it.
        """
        edges = np.concatenate([np.concatenate([mp[0], mp[-1], mp[:, 0], mp[:, -1]]) for mp in maps])
        x0 = max(0, int(np.floor(edges[:, 0].min())) - 2)
        x1 = min(self.proj_w, int(np.ceil(edges[:, 0].max())) + 2)
        y0 = max(0, int(np.floor(edges[:, 1].min())) - 2)
        y1 = min(self.proj_h, int(np.ceil(edges[:, 1].max())) + 2)
        if x1 <= x0 or y1 <= y0:
            return None
        return (x0, y0, x1, y1)

    def render(
        self,
        exposures: Sequence[Exposure],
        projector_crop: Callable[[int, tuple[int, int, int, int]], U8],
        rng: np.random.Generator,
    ) -> U8:
        """One camera frame, averaging the instants of its exposure.

        ``projector_crop(index, (x0, y0, x1, y1))`` returns that region of projector frame ``index`` as
        8-bit sRGB; only the region the camera sees is ever asked for.
        """
        cfg = self.cfg
        maps = self.projector_maps([e.state for e in exposures])
        acc = np.zeros((*self._shape_ss, 3), np.float32)
        region = self._region(maps)
        if region is not None:
            x0, y0, _, _ = region
            lit: dict[int, F32] = {}
            for e, mp in zip(exposures, maps, strict=True):
                if e.projector_index not in lit:
                    lit[e.projector_index] = srgb_to_linear(projector_crop(e.projector_index, region))
                # remap samples at pixel centres: edge-origin u is centre-origin u − 0.5.
                shifted = mp - np.array([x0 + 0.5, y0 + 0.5], np.float32)
                acc += cv2.remap(
                    lit[e.projector_index], shifted, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
                )
        acc /= len(exposures)
        # Light: projector plus room light; the camera's gain; the supersampled pixels average on the sensor.
        signal = (acc + np.float32(cfg.ambient)) * np.float32(cfg.gain)
        if cfg.supersample > 1:
            signal = cv2.resize(signal, (cfg.width_px, cfg.height_px), interpolation=cv2.INTER_AREA)
        if cfg.blur_sigma_px > 0:
            signal = cv2.GaussianBlur(signal, (0, 0), cfg.blur_sigma_px)
        # Shot and read noise in linear units, then the camera's sRGB response.
        sigma = np.sqrt(np.clip(signal, 0, None) / np.float32(cfg.full_well_e) + np.float32(cfg.read_noise**2))
        noisy = signal + rng.standard_normal(signal.shape, dtype=np.float32) * sigma.astype(np.float32)
        return linear_to_srgb_u8(noisy.astype(np.float32))
