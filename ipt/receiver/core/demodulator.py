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

The ``ipt`` profile works differently (see :mod:`ipt.receiver.core.pipeline`), with the pieces below the
paper's: each frame undistorted once (:class:`Undistorter`), its lightness (BT.601 luma, or a mono
camera's grey, through a table to L), a mask of where it can carry signal at all (:func:`signal_mask`:
not in the drone's shadow, not beyond the projection), and the pair's difference signed, brightness-
matched and masked where content changed (:func:`pair_difference`); the homography that aligns the pair
comes from :mod:`ipt.receiver.core.imagealign`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.models import REFERENCE_WIDTH_PX, DemodulationConfig
from ipt.errors import IptError
from ipt.receiver.core import kernels
from ipt.receiver.core.imagealign import translation

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


#: 8-bit CIELAB L of the grey pixel (v, v, v), indexed by v: OpenCV's own figures, kept here because the
#: conversion costs a tenth of a second on its first call (it builds its tables), on every daemon's start-up
#: path. ``tests/test_receiver_stages.py`` checks them against :func:`_luma_to_lightness_table`.
_LUMA_TO_L = np.array(
    [
        0, 1, 1, 2, 2, 3, 5, 5, 6, 7, 7, 8, 9, 9, 10, 11,
        12, 12, 14, 15, 16, 17, 18, 19, 21, 23, 24, 25, 27, 27, 28, 30,
        31, 33, 34, 35, 36, 38, 39, 40, 41, 42, 43, 45, 46, 47, 48, 50,
        51, 52, 53, 54, 55, 57, 58, 59, 60, 61, 62, 63, 65, 66, 67, 68,
        69, 70, 71, 73, 74, 75, 76, 77, 78, 79, 80, 82, 82, 83, 85, 86,
        87, 88, 89, 90, 91, 92, 93, 94, 95, 97, 98, 99, 100, 101, 102, 103,
        104, 105, 106, 107, 108, 109, 110, 111, 112, 113, 114, 115, 116, 117, 119, 119,
        121, 122, 123, 124, 125, 126, 127, 128, 129, 130, 131, 132, 133, 134, 135, 136,
        137, 138, 139, 140, 141, 142, 143, 144, 145, 146, 147, 148, 149, 150, 151, 152,
        153, 154, 155, 156, 156, 157, 158, 159, 160, 161, 162, 163, 164, 165, 166, 167,
        168, 169, 170, 171, 172, 173, 174, 175, 176, 177, 178, 179, 180, 180, 181, 182,
        183, 184, 185, 186, 187, 188, 189, 190, 191, 192, 193, 194, 195, 196, 196, 197,
        198, 199, 200, 201, 202, 203, 204, 205, 206, 207, 208, 208, 209, 210, 211, 212,
        213, 214, 215, 216, 217, 218, 219, 219, 220, 221, 222, 223, 224, 225, 226, 227,
        228, 228, 229, 230, 231, 232, 233, 234, 235, 236, 237, 237, 238, 239, 240, 241,
        242, 243, 244, 245, 245, 246, 247, 248, 249, 250, 251, 252, 253, 253, 254, 255,
    ],
    dtype=np.uint8,
)


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


# --- the ipt profile: undistorted luminance, signal masks, a signed and masked difference ----------------


class Undistorter:
    """Undistorts camera frames once each, so that the floor's motion between two frames is an exact
    homography and the camera a pinhole (:attr:`camera_matrix`, no distortion) for everything after.

    The undistorted image keeps the size and the camera matrix of the camera; what falls outside the
    sensor (corners of a barrel-distorted lens) is 0 and is left out by :func:`signal_mask`.
    """

    def __init__(self, camera_matrix: F64, dist_coeffs: F64, size: tuple[int, int]) -> None:
        self.camera_matrix = np.asarray(camera_matrix, np.float64)
        self.size = size
        self.identity = not np.any(np.asarray(dist_coeffs))
        if not self.identity:
            self._maps = cv2.initUndistortRectifyMap(
                self.camera_matrix, np.asarray(dist_coeffs, np.float64), None, self.camera_matrix, size, cv2.CV_16SC2
            )
            ones = np.full((size[1], size[0]), 255, np.uint8)
            self.coverage = np.asarray(
                cv2.remap(ones, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT), np.uint8
            )
        else:
            self.coverage = np.full((size[1], size[0]), 255, np.uint8)

    def __call__(self, image: U8) -> U8:
        if self.identity:
            return image
        out: U8 = np.asarray(cv2.remap(image, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT), np.uint8)
        return out


def binned(lum: U8, k: int) -> U8:
    """``lum`` with each k × k block of pixels averaged into one (the frames of
    :meth:`~ipt.config.camera_info.CameraInfo.binned`'s camera; k divides both sides)."""
    if k == 1:
        return lum
    h, w = lum.shape
    return np.asarray(cv2.resize(lum, (w // k, h // k), interpolation=cv2.INTER_AREA), np.uint8)


def luminance(frame: U8, method: str = "luma") -> U8:
    """The frame's lightness: an RGB frame through :func:`lightness`; a grey one (a mono camera's, or the
    luma plane of a YUV or JPEG frame) through the table that ``"luma"`` maps an RGB frame's luma by, which
    is also the CIELAB L of a grey pixel, so that a scene gives the same lightness either way."""
    if frame.ndim == 2 and frame.dtype == np.uint8:
        return np.asarray(cv2.LUT(frame, _LUMA_TO_L), dtype=np.uint8)
    return lightness(frame, method)


def percentiles_u8(values: U8, percents: tuple[float, ...]) -> tuple[float, ...]:
    """``np.percentile(values, percents)`` of 8-bit values, exactly (numpy's linear interpolation between the
    same two order statistics, by the same floating-point steps), from their histogram: a fifth of the cost."""
    n = values.size
    cumulative = np.cumsum(np.bincount(values.ravel(), minlength=256))
    out = []
    for q in percents:
        virtual = (n - 1) * (q / 100)
        lo = min(int(np.floor(virtual)), n - 1)
        gamma = virtual - np.floor(virtual)
        a, b = (int(np.searchsorted(cumulative, i, side="right")) for i in (lo, min(lo + 1, n - 1)))
        out.append(b - (b - a) * (1 - gamma) if gamma >= 0.5 else a + (b - a) * gamma)
    return tuple(float(v) for v in out)


#: Lightness below ``DARK_FRACTION`` of the way from the frame's darkest tenth to its median is taken for
#: floor without projector light (the drone's shadow, beyond the projection): no signal can be there.
DARK_FRACTION = 0.35
#: The mask keeps this far (pixels at 640 wide) from the dark regions: their soft edges carry no signal.
DARK_MARGIN_PX = 5
#: The lightness is averaged over a square of this side (pixels at 640 wide) before it is compared with the
#: level: in a dark scene lit floor is only a few levels above shadow, under a camera noise of as much, and
#: pixel by pixel the test would shred the lit floor (issue 30); the average is 5x less noisy.
MASK_BOX_PX = 5


def dark_level(values: U8, fraction: float = DARK_FRACTION) -> float:
    """The lightness at or below which a frame's floor is taken for unlit, from a sample of its pixels: ``fraction``
    of the way from their darkest tenth to their median, at least 12."""
    low, mid = percentiles_u8(values, (10, 50))
    return max(12.0, low + fraction * (mid - low))


def signal_mask(lum: U8, coverage: U8 | None = None) -> U8:
    """255 where the frame may carry the hidden tags: lit by the projector (the lightness, averaged over
    :data:`MASK_BOX_PX`, above the level :data:`DARK_FRACTION` sets), inside the sensor's view."""
    _h, w = lum.shape
    box = max(1, round(MASK_BOX_PX * w / REFERENCE_WIDTH_PX))
    smooth = np.asarray(cv2.blur(lum, (box, box)), np.uint8) if box > 1 else lum
    level = dark_level(smooth[::4, ::4])
    # 255 where lum > level (for 8-bit pixels OpenCV compares with floor(level): the same test, 5x cheaper)
    lit = np.asarray(cv2.threshold(smooth, level, 255, cv2.THRESH_BINARY)[1], np.uint8)
    if coverage is not None:
        lit = np.minimum(lit, coverage)
    # The average carries the lit level up to half a box into a dark region's soft edge (the shadow's
    # penumbra, which has no signal): the margin grows by as much. Without that, the held-out flight under a
    # big shadow (low-fast-big-shadow) fell from 87.0 to 72.1 % (its fits counted penumbra samples as tried).
    margin = max(1, round((DARK_MARGIN_PX + MASK_BOX_PX // 2) * w / REFERENCE_WIDTH_PX))
    return erode_ellipse(cv2.morphologyEx(lit, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)), 2 * margin + 1)


def undistorted_lit(lum: U8, undistort: Undistorter | None) -> tuple[U8, U8]:
    """A frame's lightness undistorted (by ``undistort``, if any) and its :func:`signal_mask`."""
    if undistort is None:
        return lum, signal_mask(lum)
    lum = undistort(lum)
    return lum, signal_mask(lum, undistort.coverage)


@functools.lru_cache(maxsize=8)
def _ellipse_rectangles(size: int) -> tuple[npt.NDArray[np.uint8], ...]:
    """OpenCV's ``size`` × ``size`` ellipse (``MORPH_ELLIPSE``) as the union of the centred rectangles it is made of:
    one per width of its rows (each row a centred run), as tall as the rows at least that wide."""
    ellipse = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    runs = ellipse.sum(axis=1)
    return tuple(np.ones((int(np.count_nonzero(runs >= w)), int(w)), np.uint8) for w in sorted(set(runs[runs > 0])))


def erode_ellipse(image: U8, size: int) -> U8:
    """``cv2.erode(image, the size × size ellipse)``, the same pixels: the minimum of the erosions by the
    ellipse's rectangles (:func:`_ellipse_rectangles`; the minimum over a union is the minimum of the minima, and
    outside the image erosion takes nothing either way), each separable where the ellipse is not: 260 µs against
    340 at 640×360 (15 px), 2.7 ms against 4.8 at 1280×720 (29 px)."""
    out: U8 | None = None
    for rectangle in _ellipse_rectangles(size):
        eroded = np.asarray(cv2.erode(image, rectangle), np.uint8)
        out = eroded if out is None else np.minimum(out, eroded, out=out)
    assert out is not None
    return out


#: A difference larger than this many times the typical tag step is content that changed (a new video
#: frame, the shadow's edge): such pixels are left out rather than clipped.
CHANGE_FACTOR = 3.0
#: Gaussian smoothing of the signed difference (pixels at 640 wide).
DIFF_SIGMA_PX = 1.0


def median_f32(values: F32) -> float:
    """``np.median`` of a non-empty 1-D float32 array, exactly (the mean of the two middle values taken in
    float32, as numpy takes it), without numpy's overhead on the few thousand values here."""
    n = len(values)
    half = n // 2
    if n % 2:
        return float(np.partition(values, half)[half])
    part = np.partition(values, (half - 1, half))
    return float((part[half - 1] + part[half]) / np.float32(2))


@dataclass
class PairDifference:
    """The signed difference of a pair in the later frame's geometry, and where it means something."""

    diff: F32
    """later − (gain · earlier carried by the warp + offset), smoothed; 0 where not valid."""
    valid: U8
    """255 where both frames carry signal and nothing but the tags changed."""
    amplitude: float
    """The typical size of the tag step (the median absolute difference where valid)."""
    changed: float
    """Fraction of the pixels lit in both frames that changed more than the tags can (content, shadow)."""
    noise: float | None = None
    """The difference's typical slope where valid (see :func:`ipt.receiver.core.track.slope_noise`), once known."""


def warp_masks(signal: U8, coverage: U8, warp: F64) -> tuple[U8, U8]:
    """``signal`` and ``coverage`` (0/255 masks of one frame) carried by ``warp`` (nearest neighbour), in
    one warp of 16-bit pixels (the signal in the low byte, the coverage in the high one): the same pixels
    as two 8-bit warps, in less than half their time."""
    h, w = signal.shape
    packed = np.left_shift(coverage, 8, dtype=np.uint16) | signal
    masks = np.asarray(cv2.warpPerspective(packed, warp, (w, h), flags=cv2.INTER_NEAREST), np.uint16)
    return (masks & 0xFF).astype(np.uint8), (masks >> 8).astype(np.uint8)


def pair_difference(
    earlier: U8,
    later: U8,
    warp: F64,
    earlier_signal: U8,
    later_signal: U8,
    coverage: U8 | None = None,
    sigma_px: float = DIFF_SIGMA_PX,
) -> PairDifference:
    """:class:`PairDifference` of two undistorted frames; ``warp`` carries the earlier onto the later.

    The earlier frame's brightness is matched to the later one's first (gain and offset fitted by least
    squares over the pixels both light: a camera's automatic gain steps between frames), so that what
    remains is the tags' ±ΔL and whatever content changed. Valid are the pixels both frames see
    (``coverage``: inside the undistorted sensor) where nothing changed more than the tags can; dark
    content keeps its signal, so darkness alone does not invalidate a pixel (the shadow's difference is
    only noise, which the pose stages do not take for steps).
    """
    h, w = later.shape
    moved = np.asarray(cv2.warpPerspective(earlier, warp, (w, h), flags=cv2.INTER_LINEAR), np.uint8)
    cover = np.full((h, w), 255, np.uint8) if coverage is None else coverage
    moved_signal, moved_seen = warp_masks(earlier_signal, cover, warp)
    # The brightness match from every fourth row and column both frames light (compiled, as the pass below).
    x, y = kernels.sample_pair(moved, later, moved_signal, later_signal, 4)
    if len(x) < 50:
        empty = np.zeros((h, w), np.float32)
        return PairDifference(empty, np.zeros((h, w), np.uint8), 0.0, 1.0)
    xm, ym = float(x.mean()), float(y.mean())
    var = float(((x - xm) ** 2).mean())
    gain = float(((x - xm) * (y - ym)).mean()) / var if var > 1e-6 else 1.0
    gain = min(max(gain, 0.5), 2.0)
    offset = ym - gain * xm
    sampled = np.abs(y - (np.float32(gain) * x + np.float32(offset)))
    amplitude = max(median_f32(sampled), 0.5)
    limit = CHANGE_FACTOR * amplitude * 2.0
    # Then every pixel in one pass: the difference, where both frames see the floor, what changed.
    diff = np.empty((h, w), np.float32)
    seen = np.empty((h, w), np.uint8)
    changed_px = np.empty((h, w), np.uint8)
    kernels.difference_pass(moved, later, moved_seen, cover, gain, offset, limit, diff, seen, changed_px)
    changed = float(np.mean(sampled > limit))
    return _finish_difference(diff, seen, changed_px, amplitude, changed, sigma_px)


def _finish_difference(
    diff: F32, valid: U8, changed_px: U8, amplitude: float, changed: float, sigma_px: float
) -> PairDifference:
    """``diff`` with the pixels that changed more than the tags can (``changed_px`` 1) and their neighbours
    left out of ``valid`` (in place), 0 where not valid, smoothed."""
    w = diff.shape[1]
    grown = cv2.dilate(changed_px, np.ones((5, 5), np.uint8))
    np.copyto(valid, 0, where=grown > 0)
    np.copyto(diff, 0.0, where=valid == 0)
    sigma = sigma_px * w / REFERENCE_WIDTH_PX
    if sigma > 0:
        diff = np.asarray(cv2.GaussianBlur(diff, (0, 0), sigma), np.float32)
    return PairDifference(diff, valid, amplitude, changed)


def valid_difference(diff: F32, seen: U8, sample: npt.NDArray[np.bool_], sigma_px: float) -> PairDifference:
    """The :class:`PairDifference` of a raw difference: the pixels outside ``seen`` (0/255; changed in
    place) and those that changed more than the tags can (with their neighbours) left out, the rest
    smoothed. ``sample`` marks the pixels of ``diff[::4, ::4]`` that both frames light."""
    amplitude = max(median_f32(np.abs(diff[::4, ::4][sample])), 0.5)
    changed_px = np.abs(diff) > CHANGE_FACTOR * amplitude * 2.0
    changed = float(np.mean(changed_px[::4, ::4][sample]))
    return _finish_difference(diff, seen, changed_px.view(np.uint8), amplitude, changed, sigma_px)


def binarise_difference(pair: PairDifference, sign: int, ksize: int) -> U8:
    """The difference as AprilTag wants it: 0/255, the tags' borders dark when ``sign`` is right
    (+1: the later frame is the +ΔL phase), thresholded at zero difference, then opened and closed."""
    scale = 127.0 / (2.5 * max(pair.amplitude, 0.5))
    img = np.asarray(cv2.convertScaleAbs(pair.diff, alpha=sign * scale, beta=128.0), np.uint8)
    if ksize > 1:
        img = cv2.blur(img, (ksize, ksize))
    _, binary = cv2.threshold(img, 128, 255, cv2.THRESH_BINARY)
    binary = np.asarray(binary, np.uint8)
    if ksize > 1:
        kernel = np.ones((ksize, ksize), np.uint8)
        binary = np.asarray(
            cv2.morphologyEx(cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel), cv2.MORPH_CLOSE, kernel), np.uint8
        )
    return binary


def demodulate(prev_l: U8, now_l: U8, cfg: DemodulationConfig) -> DemodResult:
    """Algorithm 2, steps 4-10, on two lightness images of the same size: the paper's integer shift from
    sampled lines, the difference, optionally clipped (``cfg.clip_factor``), normalised and binarised."""
    if prev_l.shape != now_l.shape or prev_l.dtype != np.uint8 or now_l.dtype != np.uint8:
        raise DemodulationError(f"frames differ: {prev_l.shape} {prev_l.dtype} vs {now_l.shape} {now_l.dtype}")
    dx, dy = estimate_shift(prev_l, now_l, cfg.sample_lines, max_shift_for(cfg, now_l.shape[1]))
    diff: npt.NDArray[np.int16] | F32 = aligned_difference(prev_l, now_l, dx, dy)
    if cfg.clip_factor is not None:
        magnitude = np.abs(diff[::4, ::4])
        limit = max(cfg.clip_factor * float(np.median(magnitude)), 1.0)
        diff = np.asarray(cv2.min(cv2.max(diff.astype(np.float32), -limit), limit), dtype=np.float32)
    norm = np.asarray(cv2.normalize(diff, None, 0, 255, cv2.NORM_MINMAX, dtype=cv2.CV_8U), dtype=np.uint8)
    return _binarise(norm, cfg, (float(dx), float(dy)), translation(dx, dy))


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
