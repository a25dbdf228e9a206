"""Photographic content that never stands still: scenes that pan and cut, made without any file.

The paper's content (a map app) moves slowly; a lab projects video. :class:`PanningPhotoScene` is the
harder case the simulator flies over by default: every input frame moves by a few projector pixels
(3-10 by default, the speed varying within the band), each shot lasts a few seconds and then cuts to
another. The shots have the statistics of photographs rather than of drawings:

- *dead leaves*: overlapping shapes of random size (a power law) with textured interiors, the standard
  model of natural images' occlusions and their 1/f spectrum;
- *terrain*: a fractal (1/f²) landscape seen from above through an elevation colour map, hill-shaded;
- *photograph*: matplotlib's sample photograph, enlarged, with film grain;
- *clouds*: a sky gradient under soft 1/f noise;
- *test card*: colour bars and grey ramps (saturated colours and pure white, where hiding is hardest).

Pure and deterministic: the picture of input frame ``index`` depends on the seed and the index only.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from pathlib import Path
from typing import Final

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]

#: The canvas a shot pans over, as a multiple of the screen size.
CANVAS_SCALE: Final = 1.5
#: Period (s) over which the pan speed sweeps its band.
_SPEED_PERIOD_S = 1.7
SHOTS: Final = ("dead_leaves", "terrain", "photograph", "clouds", "dead_leaves", "test_card")


class PhotoSceneError(IptError):
    """The panning scene cannot be made with the values given."""


def _fractal_noise(rng: np.random.Generator, height: int, width: int, beta: float) -> F32:
    """Noise with a 1/f^beta power spectrum, scaled to 0..1 (made at most 1024 px wide, then enlarged)."""
    scale = max(1, math.ceil(max(height, width) / 1024))
    h, w = max(8, height // scale), max(8, width // scale)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    f = np.sqrt(fx * fx + fy * fy)
    f[0, 0] = 1.0
    spectrum = (rng.standard_normal(f.shape) + 1j * rng.standard_normal(f.shape)) / f ** (beta / 2)
    spectrum[0, 0] = 0.0
    field = np.fft.irfft2(spectrum, s=(h, w)).astype(np.float32)
    field -= field.min()
    field /= max(float(field.max()), 1e-9)
    return np.asarray(cv2.resize(field, (width, height), interpolation=cv2.INTER_CUBIC), dtype=np.float32)


def _dead_leaves(rng: np.random.Generator, height: int, width: int) -> U8:
    img = np.empty((height, width, 3), np.uint8)
    img[:] = rng.integers(40, 200, 3, dtype=np.uint8)
    r_min, r_max = 16.0, 0.3 * min(height, width)
    # Radii with density ∝ 1/r³ (scale invariance): enough leaves to cover the canvas about three times.
    mean_area = np.pi * 2 * r_min**2 * r_max**2 / (r_max**2 - r_min**2) * np.log(r_max / r_min)
    n = int(3 * height * width / mean_area)
    u = rng.uniform(0, 1, n)
    radii = 1.0 / np.sqrt(u / r_min**2 + (1 - u) / r_max**2)
    palette = rng.integers(0, 256, (24, 3)).astype(np.float64)
    for r in radii:
        cx, cy = int(rng.integers(0, width)), int(rng.integers(0, height))
        colour = palette[int(rng.integers(0, len(palette)))] * rng.uniform(0.55, 1.0)
        c = tuple(int(v) for v in np.clip(colour + rng.normal(0, 12, 3), 0, 255))
        if rng.uniform() < 0.6:
            cv2.circle(img, (cx, cy), int(r), c, -1, cv2.LINE_AA)
        else:
            w2, h2 = r * rng.uniform(0.6, 1.6), r * rng.uniform(0.6, 1.6)
            box = ((float(cx), float(cy)), (2 * w2, 2 * h2), float(rng.uniform(0, 180)))
            cv2.fillPoly(img, [np.int32(cv2.boxPoints(box))], c, cv2.LINE_AA)
    texture = _fractal_noise(rng, height, width, 1.6)
    shaded = img.astype(np.float32) * (0.75 + 0.5 * texture)[:, :, None]
    return np.asarray(np.clip(shaded, 0, 255), dtype=np.uint8)


_TERRAIN_STOPS: Final = (  # elevation 0..1 → RGB, roughly matplotlib's "terrain"
    (0.00, (30, 60, 150)),
    (0.20, (60, 140, 210)),
    (0.24, (220, 210, 150)),
    (0.40, (90, 160, 70)),
    (0.65, (150, 130, 90)),
    (0.85, (120, 100, 90)),
    (1.00, (250, 250, 250)),
)


def _terrain(rng: np.random.Generator, height: int, width: int) -> U8:
    z = _fractal_noise(rng, height, width, 2.2)
    stops = np.array([s for s, _ in _TERRAIN_STOPS])
    colours = np.array([c for _, c in _TERRAIN_STOPS], np.float32)
    rgb = np.stack([np.interp(z, stops, colours[:, k]) for k in range(3)], axis=-1).astype(np.float32)
    gy, gx = np.gradient(z * 400.0)
    shade = np.clip(0.75 + 0.25 * (-gx - gy) / np.sqrt(1 + gx * gx + gy * gy), 0.35, 1.15)
    return np.asarray(np.clip(rgb * shade[:, :, None], 0, 255), dtype=np.uint8)


def _photograph(rng: np.random.Generator, height: int, width: int) -> U8:
    import matplotlib  # its sample photograph ships with the package: nothing is downloaded

    path = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"
    data = np.fromfile(path, np.uint8)
    bgr = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if bgr is None:
        raise PhotoSceneError(f"{path}: matplotlib's sample photograph cannot be read")
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if rng.uniform() < 0.5:
        rgb = rgb[:, ::-1]
    big = cv2.resize(rgb, (width, height), interpolation=cv2.INTER_CUBIC).astype(np.float32)
    grain = rng.normal(0.0, 4.0, (height, width, 1)).astype(np.float32)
    return np.asarray(np.clip(big + grain, 0, 255), dtype=np.uint8)


def _clouds(rng: np.random.Generator, height: int, width: int) -> U8:
    sky = np.linspace(0.0, 1.0, height, dtype=np.float32)[:, None, None]
    top, bottom = np.array([40, 90, 190], np.float32), np.array([170, 200, 240], np.float32)
    base = top + (bottom - top) * sky
    cloud = np.clip((_fractal_noise(rng, height, width, 2.4) - 0.45) * 2.2, 0, 1)[:, :, None]
    img = base * (1 - cloud) + np.float32(250) * cloud
    return np.asarray(np.clip(img, 0, 255), dtype=np.uint8)


def _test_card(rng: np.random.Generator, height: int, width: int) -> U8:
    bars = np.array(
        [
            (255, 255, 255),
            (255, 255, 0),
            (0, 255, 255),
            (0, 255, 0),
            (255, 0, 255),
            (255, 0, 0),
            (0, 0, 255),
            (0, 0, 0),
        ],
        np.uint8,
    )
    img = np.empty((height, width, 3), np.uint8)
    top = int(height * 0.6)
    cols = (np.arange(width) * len(bars) // width).astype(int)
    img[:top] = bars[cols][None, :, :]
    ramp = np.linspace(0, 255, width).astype(np.uint8)
    img[top:] = ramp[None, :, None]
    steps = (np.arange(width) * 11 // width * 255 // 10).astype(np.uint8)
    img[int(height * 0.8) :] = steps[None, :, None]
    if rng.uniform() < 0.5:
        img = img[:, ::-1]
    return np.ascontiguousarray(img)


_MAKERS: Final = {
    "dead_leaves": _dead_leaves,
    "terrain": _terrain,
    "photograph": _photograph,
    "clouds": _clouds,
    "test_card": _test_card,
}


def fold(x: float, span: float) -> float:
    """``x`` folded into [0, span] like a ball bouncing between two walls."""
    if span <= 0:
        return 0.0
    x = x % (2 * span)
    return x if x <= span else 2 * span - x


class PanningPhotoScene:
    """Photographic shots that pan by ``pan_px_per_frame`` (a band) every input frame and cut every
    ``cut_every_s`` seconds; see the module doc."""

    def __init__(
        self,
        width_px: int,
        height_px: int,
        seed: int = 0,
        pan_px_per_frame: tuple[float, float] = (3.0, 10.0),
        cut_every_s: float = 2.5,
    ) -> None:
        if width_px < 8 or height_px < 8:
            raise PhotoSceneError(f"the screen must be at least 8x8 pixels, got {width_px}x{height_px}")
        low, high = pan_px_per_frame
        if not (0 <= low <= high and math.isfinite(high)):
            raise PhotoSceneError(f"pan_px_per_frame must be a band 0 <= low <= high, got {pan_px_per_frame}")
        if not (math.isfinite(cut_every_s) and cut_every_s > 0):
            raise PhotoSceneError(f"cut_every_s must be a positive number, got {cut_every_s}")
        self.width_px, self.height_px, self.seed = width_px, height_px, seed
        self.pan_px_per_frame = (float(low), float(high))
        self.cut_every_s = float(cut_every_s)
        self._canvases: OrderedDict[int, U8] = OrderedDict()

    def _canvas(self, shot: int) -> U8:
        if shot not in self._canvases:
            rng = np.random.default_rng([self.seed, shot])
            kind = SHOTS[shot % len(SHOTS)]
            h, w = round(self.height_px * CANVAS_SCALE), round(self.width_px * CANVAS_SCALE)
            self._canvases[shot] = _MAKERS[kind](rng, h, w)
            while len(self._canvases) > 2:
                self._canvases.popitem(last=False)
        return self._canvases[shot]

    def offset_px(self, index: int, rate_hz: float) -> tuple[int, int]:
        """Top-left corner of input frame ``index``'s view in its shot's canvas (whole pixels)."""
        t = index / rate_hz
        shot = int(t // self.cut_every_s)
        rng = np.random.default_rng([self.seed, shot, 1])
        heading, phase, start = rng.uniform(0, 2 * np.pi), rng.uniform(0, 2 * np.pi), rng.uniform(0, 1, 2)
        # Distance travelled: speed sweeps the band sinusoidally, so its integral is closed-form.
        t0 = t - shot * self.cut_every_s
        low, high = self.pan_px_per_frame
        mid, half = (low + high) / 2 * rate_hz, (high - low) / 2 * rate_hz  # px per second
        w = 2 * np.pi / _SPEED_PERIOD_S
        distance = mid * t0 - half / w * (np.cos(w * t0 + phase) - np.cos(phase))
        # A straight pan in the shot's direction, bouncing off the canvas edges (the speed is kept).
        direction = heading
        span_x = round(self.width_px * CANVAS_SCALE) - self.width_px
        span_y = round(self.height_px * CANVAS_SCALE) - self.height_px
        x = fold(start[0] * span_x + distance * np.cos(direction), span_x)
        y = fold(start[1] * span_y + distance * np.sin(direction), span_y)
        return round(x), round(y)

    def frame(self, index: int, rate_hz: float) -> U8:
        """Input frame ``index`` at ``rate_hz`` (H×W×3 uint8 RGB, a new array)."""
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise PhotoSceneError(f"rate_hz must be a positive number, not {rate_hz!r}")
        shot = int((index / rate_hz) // self.cut_every_s)
        x, y = self.offset_px(index, rate_hz)
        canvas = self._canvas(shot)
        return np.ascontiguousarray(canvas[y : y + self.height_px, x : x + self.width_px])
