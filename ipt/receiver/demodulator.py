"""Demodulation: from two camera frames of opposite phase to a binary image of the hidden tags.

The paper's Algorithm 2, pure (arrays in, arrays out):

1. lightness channel of 8-bit CIELAB;
2. sample-based alignment (Section V-A, equation 5): N columns give the vertical shift, N rows the
   horizontal one, each the integer shift within ±b that minimises the L1 difference;
3. subtraction, normalisation to 0..255, mean filter, threshold at the median, opening, closing.

Two deliberate, documented details:
- the *previous* frame is shifted onto the current one, so the tag image is in the current frame's
  geometry and the pose carries the current frame's capture time;
- the L1 cost of a shift is averaged over the overlap rather than summed, so that larger shifts are not
  favoured merely for comparing fewer pixels.

The difference shows the tags with dark borders when the current frame is the ``+ΔL`` phase and
inverted otherwise; :func:`demodulate` returns the binary image for the first case and the caller tries
its inverse too (AprilTag 3 looks for dark borders only).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.models import REFERENCE_WIDTH_PX, DemodulationConfig
from ipt.errors import IptError

U8 = npt.NDArray[np.uint8]


class DemodulationError(IptError):
    """Frames that cannot be demodulated together (size or type mismatch)."""


@dataclass(frozen=True)
class DemodResult:
    """The binary tag image of a frame pair, with the shift that aligned them."""

    binary: U8
    """255/0 image; tags have dark borders if the current frame was the +ΔL phase."""
    shift_px: tuple[float, float]
    """(dx, dy): content at (x, y) in the previous frame is at (x + dx, y + dy) in the current one."""


def lightness(frame_rgb: U8) -> U8:
    """The L channel of 8-bit CIELAB (L scaled to 0..255), as in Algorithm 2 step 2-3."""
    if frame_rgb.ndim != 3 or frame_rgb.shape[2] != 3 or frame_rgb.dtype != np.uint8:
        raise DemodulationError(f"expected an H×W×3 uint8 RGB frame, got {frame_rgb.shape} {frame_rgb.dtype}")
    return np.asarray(cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2Lab)[:, :, 0], dtype=np.uint8)


def _best_shift(prev_lines: npt.NDArray[np.int16], now_lines: npt.NDArray[np.int16], max_shift: int) -> int:
    """Equation 5 on sampled lines (each row of the arrays is one sampled line along the shift axis)."""
    n = prev_lines.shape[1]
    best, best_cost = 0, np.inf
    for m in range(-max_shift, max_shift + 1):
        if m >= 0:
            diff = prev_lines[:, : n - m] - now_lines[:, m:]
        else:
            diff = prev_lines[:, -m:] - now_lines[:, : n + m]
        cost = float(np.abs(diff).mean()) if diff.size else np.inf
        if cost < best_cost:
            best, best_cost = m, cost
    return best


def estimate_shift(prev_l: U8, now_l: U8, sample_lines: int, max_shift_px: int) -> tuple[int, int]:
    """(dx, dy) by the paper's sample-based method: N equally spaced columns and rows."""
    h, w = now_l.shape
    xs = np.linspace(0, w, sample_lines + 2)[1:-1].astype(int)
    ys = np.linspace(0, h, sample_lines + 2)[1:-1].astype(int)
    dy = _best_shift(prev_l[:, xs].T.astype(np.int16), now_l[:, xs].T.astype(np.int16), max_shift_px)
    dx = _best_shift(prev_l[ys, :].astype(np.int16), now_l[ys, :].astype(np.int16), max_shift_px)
    return dx, dy


def aligned_difference(prev_l: U8, now_l: U8, dx: int, dy: int) -> npt.NDArray[np.int16]:
    """now − shifted(prev) over the overlap; zero (no signal) on the strip the shift leaves uncovered."""
    h, w = now_l.shape
    diff = np.zeros((h, w), np.int16)
    ys_now, ys_prev = slice(max(dy, 0), h + min(dy, 0)), slice(max(-dy, 0), h - max(dy, 0))
    xs_now, xs_prev = slice(max(dx, 0), w + min(dx, 0)), slice(max(-dx, 0), w - max(dx, 0))
    diff[ys_now, xs_now] = now_l[ys_now, xs_now].astype(np.int16) - prev_l[ys_prev, xs_prev].astype(np.int16)
    return diff


def _median_u8(img: U8) -> int:
    hist = np.bincount(img.ravel(), minlength=256)
    return int(np.searchsorted(np.cumsum(hist), (img.size + 1) // 2))


#: The paper's shift bound b (chosen for a 640 px wide image, :data:`REFERENCE_WIDTH_PX`).
PAPER_MAX_SHIFT_PX = 5


def max_shift_for(cfg: DemodulationConfig, width_px: int) -> int:
    """The shift bound b for an image ``width_px`` wide (configured, or the paper's scaled to the width)."""
    if cfg.max_shift_px is not None:
        return cfg.max_shift_px
    return max(PAPER_MAX_SHIFT_PX, round(PAPER_MAX_SHIFT_PX * width_px / REFERENCE_WIDTH_PX))


#: Filter size that suits a 640 px wide image (measured on the simulated arena: 5 finds 1.7x the tags of 3).
BASE_KSIZE_PX = 5


def ksize_for(configured: int | None, width_px: int) -> int:
    """A filter side: as configured, or :data:`BASE_KSIZE_PX` scaled with the width to the nearest odd size."""
    if configured is not None:
        return configured
    return 2 * round(BASE_KSIZE_PX / 2 * width_px / REFERENCE_WIDTH_PX - 0.5) + 1


def _gradient_magnitude(img: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
    """Smoothed L1 gradient magnitude: the same for a tag in either phase, so the flip does not matter."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return np.asarray(cv2.GaussianBlur(np.abs(gx) + np.abs(gy), (5, 5), 1.0), dtype=np.float32)


def _translate(img: npt.NDArray[np.float32], dx: float, dy: float) -> npt.NDArray[np.float32]:
    """``img`` moved by (dx, dy): what is at (x, y) ends up at (x + dx, y + dy); bilinear."""
    h, w = img.shape
    m = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], np.float32)
    return np.asarray(cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))


_HANNING: dict[tuple[int, int], npt.NDArray[np.float32]] = {}


def _hanning(w: int, h: int) -> npt.NDArray[np.float32]:
    if (w, h) not in _HANNING:
        _HANNING[(w, h)] = np.asarray(cv2.createHanningWindow((w, h), cv2.CV_32F), dtype=np.float32)
    return _HANNING[(w, h)]


#: Lucas-Kanade steps after phase correlation, and the margin they ignore (half-resolution pixels).
_LK_STEPS, _LK_MARGIN = 3, 16


def gradient_shift(prev_l: U8, now_l: U8) -> tuple[float, float]:
    """Sub-pixel (dx, dy) of the floor between two frames, from their gradient magnitudes.

    Phase correlation at half resolution gives the shift to about 0.3 px, whatever its size; three
    Lucas-Kanade steps refine it (to about 0.07 px on the simulated arena). Gradient magnitudes are used
    because the tags change sign between the phases and would otherwise pull the match away.
    """
    a = _gradient_magnitude(cv2.pyrDown(prev_l).astype(np.float32))
    b = _gradient_magnitude(cv2.pyrDown(now_l).astype(np.float32))
    h, w = a.shape
    (dx, dy), _ = cv2.phaseCorrelate(a, b, _hanning(w, h))
    if h > 3 * _LK_MARGIN and w > 3 * _LK_MARGIN:
        inner = (slice(_LK_MARGIN, h - _LK_MARGIN), slice(_LK_MARGIN, w - _LK_MARGIN))
        for _ in range(_LK_STEPS):
            moved = _translate(a, dx, dy)
            gx = cv2.Sobel(moved, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)[inner]
            gy = cv2.Sobel(moved, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)[inner]
            r = (moved - b)[inner]
            hess = np.array([[np.sum(gx * gx), np.sum(gx * gy)], [np.sum(gx * gy), np.sum(gy * gy)]], np.float64)
            grad = np.array([np.sum(gx * r), np.sum(gy * r)], np.float64)
            if abs(np.linalg.det(hess)) < 1e-9:
                break
            step = np.linalg.solve(hess, grad)
            if not np.all(np.isfinite(step)) or np.abs(step).max() > 2.0:
                break
            dx, dy = dx + float(step[0]), dy + float(step[1])
    return 2.0 * dx, 2.0 * dy


def subpixel_difference(prev_l: U8, now_l: U8, dx: float, dy: float) -> npt.NDArray[np.float32]:
    """now − prev moved by (dx, dy), zero on the strip the move leaves uncovered."""
    h, w = now_l.shape
    diff = now_l.astype(np.float32) - _translate(prev_l.astype(np.float32), dx, dy)
    x0, x1 = max(0, int(np.ceil(dx))), w + min(0, int(np.floor(dx)))
    y0, y1 = max(0, int(np.ceil(dy))), h + min(0, int(np.floor(dy)))
    diff[:y0] = 0
    diff[y1:] = 0
    diff[:, :x0] = 0
    diff[:, x1:] = 0
    return diff


def demodulate(prev_l: U8, now_l: U8, cfg: DemodulationConfig) -> DemodResult:
    """Algorithm 2, steps 4-10, on two lightness images of the same size."""
    if prev_l.shape != now_l.shape or prev_l.dtype != np.uint8 or now_l.dtype != np.uint8:
        raise DemodulationError(f"frames differ: {prev_l.shape} {prev_l.dtype} vs {now_l.shape} {now_l.dtype}")
    diff: npt.NDArray[np.int16] | npt.NDArray[np.float32]
    if cfg.alignment == "gradient":
        fdx, fdy = gradient_shift(prev_l, now_l)
        diff = subpixel_difference(prev_l, now_l, fdx, fdy)
        shift = (fdx, fdy)
    else:
        dx, dy = estimate_shift(prev_l, now_l, cfg.sample_lines, max_shift_for(cfg, now_l.shape[1]))
        diff = aligned_difference(prev_l, now_l, dx, dy)
        shift = (float(dx), float(dy))
    norm = cv2.normalize(diff, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U)
    width = now_l.shape[1]
    blur = ksize_for(cfg.blur_ksize, width)
    morph = ksize_for(cfg.morph_ksize, width)
    if blur > 1:
        norm = cv2.blur(norm, (blur, blur))
    thresh = _median_u8(norm)
    binary = np.where(norm > thresh, np.uint8(255), np.uint8(0))
    if morph > 1:
        kernel = np.ones((morph, morph), np.uint8)
        binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
        binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, kernel)
    return DemodResult(binary=binary, shift_px=shift)
