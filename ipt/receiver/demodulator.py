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
from typing import TypeVar

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
    """(dx, dy): content at (x, y) in the previous frame is at (x + dx, y + dy) in the current one (after
    the predicted warp, if one was given)."""
    warp: npt.NDArray[np.float64]
    """The whole 3x3 warp that carried the previous frame onto the current one."""


def _luma_to_lightness_table() -> U8:
    ramp = np.repeat(np.arange(256, dtype=np.uint8)[:, None, None], 3, axis=2)
    return np.asarray(cv2.cvtColor(ramp, cv2.COLOR_RGB2Lab)[:, 0, 0], dtype=np.uint8)


#: 8-bit CIELAB L of the grey pixel (v, v, v), indexed by v.
_LUMA_TO_L = _luma_to_lightness_table()


def lightness(frame_rgb: U8, method: str = "cielab") -> U8:
    """The L channel of 8-bit CIELAB (L scaled to 0..255), as in Algorithm 2 step 2-3.

    ``method="luma"`` takes the BT.601 luma instead and maps it through the grey ramp's L: exact for grey
    pixels, close for colours, and about five times cheaper than the full conversion.
    """
    if frame_rgb.ndim != 3 or frame_rgb.shape[2] != 3 or frame_rgb.dtype != np.uint8:
        raise DemodulationError(f"expected an H×W×3 uint8 RGB frame, got {frame_rgb.shape} {frame_rgb.dtype}")
    if method == "luma":
        return np.asarray(cv2.LUT(cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2GRAY), _LUMA_TO_L), dtype=np.uint8)
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
    hist = np.asarray(cv2.calcHist([img], [0], None, [256], [0, 256]), dtype=np.float64).ravel()
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


F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]


def _gradient_magnitude(img: F32) -> F32:
    """Smoothed L1 gradient magnitude: the same for a tag in either phase, so the flip does not matter."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return np.asarray(cv2.GaussianBlur(np.abs(gx) + np.abs(gy), (5, 5), 1.0), dtype=np.float32)


def alignment_features(lightness_u8: U8) -> F32:
    """What :func:`gradient_shift` matches: the gradient magnitude at half resolution.

    A frame is paired more than once (as the current frame, then as the earlier one), so callers may
    compute this once per frame and pass it in.
    """
    return _gradient_magnitude(np.asarray(cv2.pyrDown(lightness_u8), dtype=np.float32))


def _translate(img: F32, dx: float, dy: float) -> F32:
    """``img`` moved by (dx, dy): what is at (x, y) ends up at (x + dx, y + dy); bilinear."""
    h, w = img.shape
    m = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], np.float32)
    return np.asarray(cv2.warpAffine(img, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE))


A = TypeVar("A", np.uint8, np.float32)


def _warp(img: npt.NDArray[A], warp: F64, border: int = cv2.BORDER_REPLICATE) -> npt.NDArray[A]:
    """``img`` carried by the 3x3 ``warp`` (what is at p ends up at warp·p); bilinear, same dtype."""
    h, w = img.shape
    if np.allclose(warp[2], (0.0, 0.0, 1.0)):
        out = cv2.warpAffine(img, warp[:2], (w, h), flags=cv2.INTER_LINEAR, borderMode=border)
    else:
        out = cv2.warpPerspective(img, warp, (w, h), flags=cv2.INTER_LINEAR, borderMode=border)
    return np.asarray(out, dtype=img.dtype)


_HALF = np.diag([0.5, 0.5, 1.0])
_DOUBLE = np.diag([2.0, 2.0, 1.0])


def translation(dx: float, dy: float) -> F64:
    """The 3x3 warp that moves content by (dx, dy)."""
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


_HANNING: dict[tuple[int, int], F32] = {}


def _hanning(w: int, h: int) -> F32:
    if (w, h) not in _HANNING:
        _HANNING[(w, h)] = np.asarray(cv2.createHanningWindow((w, h), cv2.CV_32F), dtype=np.float32)
    return _HANNING[(w, h)]


#: Lucas-Kanade steps after phase correlation, and the margin they ignore (half-resolution pixels).
_LK_STEPS, _LK_MARGIN = 3, 16


class _LucasKanade:
    """Translation-only Lucas-Kanade against a fixed target image, in the inverse-compositional form:
    the target's gradients and the 2x2 normal matrix are computed once, each step only moves the other
    image and takes two dot products."""

    def __init__(self, target: F32) -> None:
        h, w = target.shape
        self.inner = (slice(_LK_MARGIN, h - _LK_MARGIN), slice(_LK_MARGIN, w - _LK_MARGIN))
        self.target = np.ascontiguousarray(target[self.inner])
        self.gx = np.ascontiguousarray(cv2.Sobel(target, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)[self.inner])
        self.gy = np.ascontiguousarray(cv2.Sobel(target, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)[self.inner])
        gxx, gxy, gyy = (float(np.vdot(u, v)) for u, v in ((self.gx, self.gx), (self.gx, self.gy), (self.gy, self.gy)))
        self.hess = np.array([[gxx, gxy], [gxy, gyy]], np.float64)

    def refine(self, moving: F32, dx: float, dy: float) -> tuple[float, float] | None:
        """(dx, dy) that carries ``moving`` onto the target, refined from the given start; None if a step
        is degenerate or too large (no gradient, or the start was too far off)."""
        if abs(np.linalg.det(self.hess)) < 1e-9:
            return None
        for _ in range(_LK_STEPS):
            residual = np.ascontiguousarray(_translate(moving, dx, dy)[self.inner]) - self.target
            grad = np.array([float(np.vdot(self.gx, residual)), float(np.vdot(self.gy, residual))])
            step = np.linalg.solve(self.hess, grad)
            if not np.all(np.isfinite(step)) or np.abs(step).max() > 2.0:
                return None
            dx, dy = dx + float(step[0]), dy + float(step[1])
        return dx, dy


def gradient_shift(
    prev_l: U8,
    now_l: U8,
    predicted: F64 | None = None,
    features: tuple[F32, F32] | None = None,
) -> tuple[float, float]:
    """Sub-pixel (dx, dy) of the floor between two frames, from their gradient magnitudes.

    ``predicted`` (3x3, full-resolution pixels) is a warp of the earlier frame onto the current one known
    beforehand, e.g. the floor homography from the recent poses; the shift returned is what remains after
    it, so the whole warp is ``translation(dx, dy) @ predicted``. ``features`` are the two frames'
    :func:`alignment_features` if already computed.

    Phase correlation at half resolution gives the shift to about 0.3 px, whatever its size; three
    Lucas-Kanade steps refine it (to about 0.07 px on the simulated arena). (Starting Lucas-Kanade at zero
    after a prediction, without phase correlation, lost 14 % of the poses of the 720p flight.) Gradient
    magnitudes are used because the tags change sign between the phases and would otherwise pull
    the match away.
    """
    a, b = features if features is not None else (alignment_features(prev_l), alignment_features(now_l))
    if predicted is not None:
        a = _warp(a, _HALF @ predicted @ _DOUBLE)
    h, w = a.shape
    if h <= 3 * _LK_MARGIN or w <= 3 * _LK_MARGIN:
        (dx, dy), _ = cv2.phaseCorrelate(a, b, _hanning(w, h))
        return 2.0 * dx, 2.0 * dy
    (dx, dy), _ = cv2.phaseCorrelate(a, b, _hanning(w, h))
    refined = _LucasKanade(b).refine(a, dx, dy)
    if refined is not None:
        dx, dy = refined
    return 2.0 * dx, 2.0 * dy


def covered_box(warp: F64, width: int, height: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the largest axis-aligned box, in whole pixels, that the earlier frame still covers
    after ``warp`` (a few pixels of the warped frame's slanted edges are given up for a cheap slice)."""
    corners = np.array([[[0.0, 0.0], [width - 1.0, 0.0], [width - 1.0, height - 1.0], [0.0, height - 1.0]]])
    (tl, tr, br, bl) = np.asarray(cv2.perspectiveTransform(corners, warp), np.float64)[0]
    x0 = max(0, int(np.ceil(max(tl[0], bl[0]))))
    x1 = min(width, int(np.floor(min(tr[0], br[0]))) + 1)
    y0 = max(0, int(np.ceil(max(tl[1], tr[1]))))
    y1 = min(height, int(np.floor(min(bl[1], br[1]))) + 1)
    return x0, y0, max(x0, x1), max(y0, y1)


def _outside_box(img: npt.NDArray[np.generic], box: tuple[int, int, int, int], value: float) -> None:
    x0, y0, x1, y1 = box
    img[:y0] = value
    img[y1:] = value
    img[:, :x0] = value
    img[:, x1:] = value


def subpixel_difference(prev_l: U8, now_l: U8, dx: float, dy: float, predicted: F64 | None = None) -> F32:
    """now − prev carried by ``translation(dx, dy) @ predicted``, zero where prev does not reach."""
    warp = translation(dx, dy) if predicted is None else translation(dx, dy) @ predicted
    moved = _warp(prev_l.astype(np.float32), warp, border=cv2.BORDER_CONSTANT)
    diff = np.asarray(cv2.subtract(now_l.astype(np.float32), moved), dtype=np.float32)
    _outside_box(diff, covered_box(warp, now_l.shape[1], now_l.shape[0]), 0.0)
    return diff


def clipped_difference(prev_l: U8, now_l: U8, warp: F64, clip_factor: float) -> U8:
    """now − prev carried by ``warp``, clipped to ± ``clip_factor`` times its median magnitude and mapped
    onto 0..255 (128: no difference, also where prev does not reach), in 8-bit arithmetic throughout.

    The same as clipping :func:`subpixel_difference` and normalising it, up to the rounding of the warped
    frame to whole lightness units, at a fraction of the float passes.
    """
    h, w = now_l.shape
    box = covered_box(warp, w, h)
    x0, y0, x1, y1 = box
    if x1 <= x0 or y1 <= y0:  # the earlier frame covers none of this one (a wild motion prediction)
        return np.full((h, w), 128, np.uint8)
    moved = _warp(prev_l, warp)
    magnitude = cv2.absdiff(now_l[y0:y1, x0:x1], moved[y0:y1, x0:x1])
    limit = max(clip_factor * _median_u8(np.asarray(magnitude, np.uint8)), 1.0)
    gain = 127.5 / limit
    out = np.asarray(cv2.addWeighted(now_l, gain, moved, -gain, 127.5, dtype=cv2.CV_8U), dtype=np.uint8)
    _outside_box(out, box, 128)
    return out


def demodulate(
    prev_l: U8,
    now_l: U8,
    cfg: DemodulationConfig,
    *,
    predicted: F64 | None = None,
    features: tuple[F32, F32] | None = None,
) -> DemodResult:
    """Algorithm 2, steps 4-10, on two lightness images of the same size.

    ``predicted`` and ``features`` are passed to :func:`gradient_shift` ('gradient' alignment only).
    """
    if prev_l.shape != now_l.shape or prev_l.dtype != np.uint8 or now_l.dtype != np.uint8:
        raise DemodulationError(f"frames differ: {prev_l.shape} {prev_l.dtype} vs {now_l.shape} {now_l.dtype}")
    diff: npt.NDArray[np.int16] | F32
    if cfg.alignment == "gradient":
        fdx, fdy = gradient_shift(prev_l, now_l, predicted, features)
        shift = (fdx, fdy)
        warp = translation(fdx, fdy) if predicted is None else translation(fdx, fdy) @ predicted
        if cfg.clip_factor is not None:
            return _binarise(clipped_difference(prev_l, now_l, warp, cfg.clip_factor), cfg, shift, warp)
        diff = subpixel_difference(prev_l, now_l, fdx, fdy, predicted)
    else:
        dx, dy = estimate_shift(prev_l, now_l, cfg.sample_lines, max_shift_for(cfg, now_l.shape[1]))
        diff = aligned_difference(prev_l, now_l, dx, dy)
        shift = (float(dx), float(dy))
        warp = translation(dx, dy)
    if cfg.clip_factor is not None:
        magnitude = np.abs(diff[::4, ::4])
        limit = max(cfg.clip_factor * float(np.median(magnitude)), 1.0)
        diff = np.asarray(cv2.min(cv2.max(diff.astype(np.float32), -limit), limit), dtype=np.float32)
    norm = np.asarray(cv2.normalize(diff, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U), dtype=np.uint8)
    return _binarise(norm, cfg, shift, warp)


def _binarise(norm: U8, cfg: DemodulationConfig, shift: tuple[float, float], warp: F64) -> DemodResult:
    """Steps 7-10: mean filter, threshold at the median, opening and closing."""
    width = norm.shape[1]
    blur = ksize_for(cfg.blur_ksize, width)
    morph = ksize_for(cfg.morph_ksize, width)
    if blur > 1:
        norm = cv2.blur(norm, (blur, blur))
    thresh = _median_u8(norm)
    _, thresholded = cv2.threshold(norm, thresh, 255, cv2.THRESH_BINARY)  # 255 where norm > thresh
    binary = np.asarray(thresholded, dtype=np.uint8)
    if morph > 1:
        kernel = np.ones((morph, morph), np.uint8)
        binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
        binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, kernel)
    return DemodResult(binary=binary, shift_px=shift, warp=warp)
