"""A dark AR scene: a night-mode map or game view, the content that leaves the hidden tags least light.

Issue 30: AR scenes are often dark (night-mode maps, space and game scenes). :class:`DarkScene` is the
panning photographs of :class:`~ipt.sender.photos.PanningPhotoScene` (the same shots, pans and cuts) with
their code values dimmed to :data:`BACKDROP_LEVEL` of themselves, so most of the picture sits within a few
levels of black, where a paper-literal sender's lightness step clips and is one-sided; on top, bright thin
lines (roads, routes, a grid) and text labels drawn once on a larger canvas that pans on its own, steadily,
in a direction of its own. Pure and deterministic: input frame ``index`` depends on the seed and the
index only; nothing is read from disk but what the photographs themselves use (no downloads).
"""

from __future__ import annotations

import math
from typing import Final

import cv2
import numpy as np
import numpy.typing as npt

from ipt.sender.basemap import PLACES
from ipt.sender.photos import CANVAS_SCALE, PanningPhotoScene, fold

U8 = npt.NDArray[np.uint8]

#: The backdrop's code values, as a fraction of the photographs' own (a tenth: the issue's dark scene).
BACKDROP_LEVEL: Final = 0.1
#: The overlay's pan, projector pixels per content frame (a map scrolled slowly under the user's finger).
OVERLAY_PAN_PX_PER_FRAME: Final = 2.5
#: Colours of the overlay's lines and labels (RGB): a night-mode palette, bright on black.
_LINE_COLOURS: Final = ((230, 230, 230), (80, 220, 255), (255, 200, 60), (120, 255, 140), (255, 110, 200))


class DarkScene:
    """Panning photographs dimmed to a tenth under bright thin lines and labels that pan (see the module doc)."""

    def __init__(
        self,
        width_px: int,
        height_px: int,
        seed: int = 0,
        pan_px_per_frame: tuple[float, float] = (3.0, 10.0),
        cut_every_s: float = 2.5,
    ) -> None:
        self.backdrop = PanningPhotoScene(width_px, height_px, seed, pan_px_per_frame, cut_every_s)
        self.width_px, self.height_px, self.seed = width_px, height_px, seed
        self._canvas_w, self._canvas_h = round(width_px * CANVAS_SCALE), round(height_px * CANVAS_SCALE)
        rng = np.random.default_rng([seed, 31])
        self._colour, self._alpha = _draw_overlay(rng, self._canvas_w, self._canvas_h, min(width_px, height_px))
        angle = rng.uniform(0, 2 * math.pi)
        self._direction = (math.cos(angle), math.sin(angle))
        self._start = rng.uniform(0, 1, 2)
        self._dim_lut = np.rint(np.arange(256) * BACKDROP_LEVEL).astype(np.uint8)

    def overlay_offset_px(self, index: int) -> tuple[int, int]:
        """Top-left corner of input frame ``index``'s view of the overlay canvas (a steady pan that bounces
        off the canvas edges)."""
        distance = OVERLAY_PAN_PX_PER_FRAME * index
        out = []
        for start, d, span in zip(
            self._start, self._direction, (self._canvas_w - self.width_px, self._canvas_h - self.height_px), strict=True
        ):
            out.append(round(fold(start * span + distance * d, span)))
        return out[0], out[1]

    def frame(self, index: int, rate_hz: float) -> U8:
        """Input frame ``index`` at ``rate_hz`` (H×W×3 uint8 RGB, a new array)."""
        dim = np.asarray(cv2.LUT(self.backdrop.frame(index, rate_hz), self._dim_lut), np.uint8)
        x, y = self.overlay_offset_px(index)
        view = (slice(y, y + self.height_px), slice(x, x + self.width_px))
        alpha = self._alpha[view].astype(np.uint16)[:, :, None]
        # The overlay is drawn antialiased on black: its colour is already weighted by its coverage.
        mixed = (dim.astype(np.uint16) * (255 - alpha) + 127) // 255 + self._colour[view]
        return np.asarray(np.minimum(mixed, 255), dtype=np.uint8)


def _draw_overlay(rng: np.random.Generator, width: int, height: int, screen_px: int) -> tuple[U8, U8]:
    """The overlay canvas: its colour weighted by its coverage (H×W×3, antialiased on black) and that
    coverage (H×W, 0..255): a loose grid of thin streets, a few winding routes and place labels."""
    colour = np.zeros((height, width, 3), np.uint8)
    alpha = np.zeros((height, width), np.uint8)
    unit = max(0.3, screen_px / 1080.0)  # drawing unit: 1 at 1080 lines

    def stroke(points: npt.NDArray[np.int32], rgb: tuple[int, int, int], thickness: int) -> None:
        cv2.polylines(colour, [points], False, rgb, thickness, cv2.LINE_AA)
        cv2.polylines(alpha, [points], False, 255, thickness, cv2.LINE_AA)

    spacing = int(rng.integers(140, 220) * unit)
    for x in range(int(rng.integers(0, spacing)), width, spacing):  # streets: slightly skewed verticals
        dx = int(rng.integers(-spacing // 4, spacing // 4 + 1))
        stroke(np.array([[x, 0], [x + dx, height - 1]], np.int32), _LINE_COLOURS[0], max(1, round(unit)))
    for y in range(int(rng.integers(0, spacing)), height, spacing):  # and horizontals
        dy = int(rng.integers(-spacing // 4, spacing // 4 + 1))
        stroke(np.array([[0, y], [width - 1, y + dy]], np.int32), _LINE_COLOURS[0], max(1, round(unit)))
    for _ in range(6):  # routes and contours: random walks with smooth turns
        n = 40
        heading = rng.uniform(0, 2 * math.pi) + np.cumsum(rng.normal(0, 0.25, n))
        step = rng.uniform(30, 60) * unit
        start = rng.uniform((0, 0), (width, height))
        pts = start + np.cumsum(np.stack([np.cos(heading), np.sin(heading)], axis=1) * step, axis=0)
        rgb = _LINE_COLOURS[int(rng.integers(1, len(_LINE_COLOURS)))]
        stroke(np.rint(pts).astype(np.int32), rgb, max(1, round(2 * unit)))
    font = cv2.FONT_HERSHEY_SIMPLEX
    for _ in range(max(8, width * height // (400 * 400))):  # labels
        text = str(rng.choice(PLACES))
        scale = float(rng.uniform(0.7, 1.3) * unit)
        org = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        rgb = _LINE_COLOURS[int(rng.integers(0, len(_LINE_COLOURS)))]
        thickness = max(1, round(2 * unit))
        cv2.putText(colour, text, org, font, scale, rgb, thickness, cv2.LINE_AA)
        cv2.putText(alpha, text, org, font, scale, 255, thickness, cv2.LINE_AA)
    return colour, alpha
