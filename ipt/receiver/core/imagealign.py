"""Image alignment of two camera frames: the floor homography between them, from their content.

The two frames of a pair are a projector period apart (16.7 ms); the drone moved and, vibrating, turned
by up to a degree, so the floor moved in the image by a translation plus a small perspective change.
The floor homography is found on the frames' gradient magnitudes at half resolution (the same for a tag
in either phase, so the hidden tags' sign flip does not pull the match): phase correlation for the
translation, whatever its size, then Lucas-Kanade with all eight homography parameters, composed onto
the current frame's side and read at its strongest gradients (chosen once per frame). Each step's
Jacobian is the efficient second-order (ESM) one, the mean of both frames' gradients, where the
inverse-compositional form took the current frame's alone: its steps are those of a second-order method,
and on the suite's vibrating flights six of them land nearer the true floor homography (shadow-vibration,
its first 200 frames each against the one two before, the middle of the image against the warp of the true
poses: median 1.7 → 1.1 px) and give better poses (below, at ``LK_STEPS``). Pixels without signal in
either frame (the drone's shadow, the floor outside the projection) are left out of the fit, and a robust
weight drops what else moved differently.

Pure: arrays in, a 3x3 warp out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from ipt.receiver.core import kernels

U8 = npt.NDArray[np.uint8]
F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

_HALF = np.diag([0.5, 0.5, 1.0])
_DOUBLE = np.diag([2.0, 2.0, 1.0])
#: Margin (half-resolution pixels) left out at the image border.
MARGIN = 8
#: Lucas-Kanade steps, and the step size (half-resolution pixels at the image corners) below which it stops.
#: With the inverse-compositional Jacobian the fit often still moved the corners by tenths of a pixel a step
#: after six steps on a vibrating flight; ten took shadow-vibration's MAE from 1.76 / 1.45 to 1.58 / 1.33 mm
#: (x / y) and fast from 88.6 to 89.9 %, but the suite's take-off from 75.6 to 73.6 % (its lowest 0.4 m:
#: 17.1 → 10.0 %). The ESM Jacobian with six (diagnostic replays against the inverse-compositional six,
#: same code otherwise): shadow-vibration 99.4 → 99.5 %, MAE 1.88 / 1.38 → 1.64 / 1.25 mm; fast 88.2 → 89.8 %;
#: moving-content 99.2 → 99.4 %; take-off 75.1 → 75.5 % (lowest 0.4 m 15.3 → 16.7 %). With ten, better still
#: on shadow-vibration (1.49 / 1.13 mm) and fast (91.1 %) but take-off's lowest 0.4 m fell to 11.4 % (a view
#: mostly in the drone's shadow, where a longer fit wanders; stopping when a step raises the residual gave
#: 14.6 %): six it stays.
LK_STEPS, LK_DONE_PX = 6, 0.02
#: Residuals beyond this many robust standard deviations get no weight.
ROBUST_K = 3.0
#: Most pixels the fit looks at (those with the strongest gradients).
MAX_SAMPLES = 6000


def gradient_magnitude(img: F32) -> F32:
    """Smoothed L1 gradient magnitude: the same for a tag in either phase."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    return np.asarray(cv2.GaussianBlur(np.abs(gx) + np.abs(gy), (5, 5), 1.0), dtype=np.float32)


def alignment_features(lightness_u8: U8) -> F32:
    """What the alignment matches: the gradient magnitude at half resolution."""
    return gradient_magnitude(np.asarray(cv2.pyrDown(lightness_u8), dtype=np.float32))


_HANNING: dict[tuple[int, int], F32] = {}


def _hanning(w: int, h: int) -> F32:
    if (w, h) not in _HANNING:
        _HANNING[(w, h)] = np.asarray(cv2.createHanningWindow((w, h), cv2.CV_32F), dtype=np.float32)
    return _HANNING[(w, h)]


def phase_correlate(a: F32, b: F32) -> tuple[float, float]:
    """The shift (dx, dy) of ``b`` against ``a``, by phase correlation with a Hanning window.

    OpenCV 5's ``phaseCorrelate`` multiplies its inputs by the window in place, so it gets copies: the
    features are kept per frame and used again."""
    h, w = a.shape
    (dx, dy), _ = cv2.phaseCorrelate(a.copy(), b.copy(), _hanning(w, h))
    return float(dx), float(dy)


def translation(dx: float, dy: float) -> F64:
    """The 3x3 warp that moves content by (dx, dy)."""
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


A = TypeVar("A", np.uint8, np.float32)


def warp_image(img: npt.NDArray[A], warp: F64, border: int = cv2.BORDER_REPLICATE) -> npt.NDArray[A]:
    """``img`` carried by the 3x3 ``warp`` (what is at p ends up at warp·p); bilinear, same dtype."""
    h, w = img.shape[:2]
    # np.allclose(warp[2], (0, 0, 1)) written out (its own overhead is ten times the test's)
    if abs(warp[2, 0]) <= 1e-8 and abs(warp[2, 1]) <= 1e-8 and abs(warp[2, 2] - 1.0) <= 1e-8 + 1e-5:
        out = cv2.warpAffine(img, warp[:2], (w, h), flags=cv2.INTER_LINEAR, borderMode=border)
    else:
        out = cv2.warpPerspective(img, warp, (w, h), flags=cv2.INTER_LINEAR, borderMode=border)
    return np.asarray(out, dtype=img.dtype)


@dataclass
class AlignTarget:
    """A frame prepared as the fixed image of the fit (computed once per frame)."""

    features: F32
    """Half-resolution gradient magnitude."""
    weight: F32
    """Where the fit may look (0/1), half resolution."""
    rows: npt.NDArray[np.intp]
    cols: npt.NDArray[np.intp]
    norm: F64
    """Coordinates are taken relative to the image centre and divided by half the width (conditioning)."""
    flat: npt.NDArray[np.intp]
    """rows · width + cols: the samples' places in the flattened image."""
    values: F32
    """The target's features at the samples."""
    ix: F32
    iy: F32
    """The target's gradients at the samples, per normalised unit of x and y."""

    @classmethod
    def of(cls, features: F32, signal: U8 | None = None) -> AlignTarget:
        """``features`` (half resolution) and, optionally, the frame's signal mask at full resolution."""
        h, w = features.shape
        weight = np.zeros((h, w), np.float32)
        weight[MARGIN : h - MARGIN, MARGIN : w - MARGIN] = 1.0
        if signal is not None:
            half = cv2.resize(signal, (w, h), interpolation=cv2.INTER_NEAREST) > 0
            weight *= half
        gx = cv2.Sobel(features, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(features, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        # Keep the pixels with the most gradient (the rest adds little but time), at most MAX_SAMPLES.
        strength = (np.abs(gx) + np.abs(gy)) * weight
        flat = strength.ravel()
        candidates = np.flatnonzero(flat > 0)
        if len(candidates) > MAX_SAMPLES:
            cut = np.partition(flat[candidates], len(candidates) - MAX_SAMPLES)[len(candidates) - MAX_SAMPLES]
            candidates = candidates[flat[candidates] >= cut][:MAX_SAMPLES]
        rows, cols = np.divmod(candidates, w)
        s = 2.0 / w
        norm = np.array([[s, 0.0, -1.0], [0.0, s, -h / w], [0.0, 0.0, 1.0]])  # pixels → centred, scaled
        flat_idx = rows * w + cols
        # (take from the flattened images: the same values as gx[rows, cols], at a fifth of the cost)
        ix, iy = gx.ravel().take(flat_idx) / s, gy.ravel().take(flat_idx) / s  # gradients per normalised unit
        return cls(
            features,
            weight,
            rows,
            cols,
            norm,
            flat_idx,
            features.ravel().take(flat_idx),
            np.ascontiguousarray(ix, np.float32),
            np.ascontiguousarray(iy, np.float32),
        )


def _update(params: F64) -> F64:
    """The homography of the eight parameters (at 0: the identity)."""
    p = params
    return np.array([[1.0 + p[0], p[1], p[2]], [p[3], 1.0 + p[4], p[5]], [p[6], p[7], 1.0]])


def refine_homography(target: AlignTarget, moving: F32, start: F64, moving_lit: U8 | None = None) -> F64 | None:
    """The half-resolution warp carrying ``moving`` onto ``target``, refined from ``start`` (3x3, half
    resolution); None if the fit is degenerate or runs away. ``moving_lit`` (half resolution, 0 where the
    moving frame has no signal) leaves out the samples that land in the moving frame's shadow: its edge moves
    with the camera, not with the floor, and the target's own mask cannot know where it lies in the other
    frame (shadow-vibration: 98.9 → 99.3 % of frames posed, MAE 1.97 / 1.74 → 1.72 / 1.42 mm)."""
    if len(target.rows) < 200:
        return None
    norm, inv_norm = target.norm, np.linalg.inv(target.norm)
    # In normalised coordinates the warp is n·W·n⁻¹; the fit finds M with moving(M⁻¹ x) = target(x).
    m = norm @ start @ inv_norm
    # The samples only: moving(W⁻¹ x) and its gradients at the target's sample pixels x, their residuals and
    # the normal equations in one compiled pass (warping the whole image each step cost ten times more).
    lit = np.zeros((0, 0), np.uint8) if moving_lit is None else moving_lit
    moving_gx = np.asarray(cv2.Sobel(moving, cv2.CV_32F, 1, 0, ksize=3, scale=0.125), np.float32)
    moving_gy = np.asarray(cv2.Sobel(moving, cv2.CV_32F, 0, 1, ksize=3, scale=0.125), np.float32)
    scale, offset_y = float(norm[0, 0]), float(-norm[1, 2])
    sd, residual = np.empty((len(target.rows), 8)), np.empty(len(target.rows))
    for _ in range(LK_STEPS):
        back = inv_norm @ np.linalg.inv(m) @ norm
        counted, kept = kernels.align_system(
            moving, moving_gx, moving_gy, lit, back, target.cols, target.rows, target.values,
            target.ix, target.iy, scale, offset_y, ROBUST_K, sd, residual,
        )  # fmt: skip
        if counted < 200:
            return None
        hess, rhs = sd[:kept].T @ sd[:kept], sd[:kept].T @ residual[:kept]
        try:
            dp = np.asarray(np.linalg.solve(hess, rhs), np.float64)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(dp)):
            return None
        # Composed on the target's side: moving(M⁻¹ x) = target(U x) gives the new M = U·M.
        m = _update(dp) @ m
        m /= m[2, 2]
        corners = np.array([[-1.0, -0.56, 1.0], [1.0, 0.56, 1.0]])
        moved = corners @ (_update(dp) - np.eye(3)).T
        if np.abs(moved[:, :2]).max() / norm[0, 0] < LK_DONE_PX:
            break
        if np.abs(m - np.eye(3)).max() > 0.5:
            return None
    return np.asarray(inv_norm @ m @ norm, np.float64)


def floor_warp_between(
    target: AlignTarget, moving_features: F32, predicted: F64 | None = None, moving_signal: U8 | None = None
) -> F64 | None:
    """The full-resolution warp that carries the earlier frame (``moving_features``) onto the target's
    frame: ``predicted`` (full resolution, from the poses) corrected by phase correlation and refined as a
    homography, where the earlier frame has signal (``moving_signal``, its full-resolution signal mask, if
    given); None if the fit failed."""
    a = moving_features
    start = np.eye(3) if predicted is None else _HALF @ predicted @ _DOUBLE
    shifted = warp_image(a, start) if predicted is not None else a
    dx, dy = phase_correlate(shifted, target.features)
    start = translation(dx, dy) @ start
    lit = None
    if moving_signal is not None:
        h, w = a.shape
        lit = np.asarray(cv2.resize(moving_signal, (w, h), interpolation=cv2.INTER_NEAREST), np.uint8)
    refined = refine_homography(target, a, start, lit)
    if refined is None:
        return None
    return np.asarray(_DOUBLE @ refined @ _HALF, np.float64)
