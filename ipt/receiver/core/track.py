"""Pose from the whole visible hidden map: every edge of every tag cell in view votes.

AprilTag needs a whole tag, border and quiet zone, to decode it. Once the pose is roughly known (from a
detection, or from the recent poses and the image alignment), the receiver knows where every cell edge
of the hidden map falls in the image, and which way the difference image must step across it: up by
2ΔL from a black cell to a white one (times the phase's sign), half that to the untouched floor. So the
pose can be refined against the difference image directly: each edge sample searches along its normal
for the step, and the pose moves to put the samples on their steps (Gauss-Newton, robust weights). Tags
cut by the image border, tags half in the drone's shadow and tags too small to decode all contribute
their visible edges; samples in shadow find no step and drop out.

Pure: a difference image, the camera model and a pose guess in; a pose, its covariance and how well the
map fitted out.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from ipt.receiver.core import kernels
from ipt.receiver.core.kernels import band_signs, cell_agreement, measure, peaks
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.pose import PoseEstimate, estimate_from_step

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]
B = npt.NDArray[np.bool_]

#: Tags whose cells would be narrower than this in the image are left out: the difference's smoothing
#: blurs their edges into each other (a landing pad's small tags seen from high up).
MIN_CELL_PX = 2.5
#: With at least this many clear data cells in view, their agreement with the map (a fraction) is the check.
MANY_CELLS = 20
#: When fewer of the evenly spread samples than this land on lit pixels of the image (a low view mostly in
#: the drone's shadow: the tags near it reach far out of the image), the samples are spread over those
#: predicted on lit pixels instead (:func:`_select`); views with more keep the even spread unchanged.
FEW_LIT_SAMPLES = 100
#: Spread over the lit edges only, a right pose from a clear pair puts most samples on their steps (80-90 %
#: at 0.40-0.45 m); fits with fewer than this fraction came from weak pairs and were up to 8 cm off (a guess
#: carried by a poor alignment, settled a few cells away): no pose.
LIT_MIN_INLIER_FRACTION = 0.3
#: The coarse search prefers small shifts: its correlation is weighted by a Gaussian of the shift with σ this
#: fraction of the image's width (:func:`coarse_shift`). The guess it corrects comes from the last poses, a few
#: pixels to tens of pixels off; the map repeats itself a tag pitch away (the tags differ only in their data
#: cells), and a view mostly in the drone's shadow (0.4-0.45 m) peaked there, ~290 px off, over the near peak.
#: A quarter of the width took two-projectors (uncalibrated) from 99.0 to 95.9 % (its far guesses need far
#: shifts); half keeps it at 99.0 % and the descent 0.8-0.4 m of takeoff-open-floor at 97.9 % (none: 92.6 %).
SHIFT_PRIOR = 0.5
#: With fewer (a low view mostly in the drone's shadow: ~10-20 data cells lit), down to this many, more of
#: them must agree (:meth:`TrackResult.cells_confirm`); with fewer still, the cells cannot confirm a pose.
FEW_CELLS = 10


@dataclass(frozen=True)
class TrackResult:
    """The pose refined against the map's edges."""

    rvec: F64
    """Rotation arena → camera (Rodrigues), as OpenCV's solvePnP gives it."""
    tvec: F64
    """Arena origin in the camera frame, metres."""
    inliers: int
    """Edge samples that found their step and agree with the pose."""
    tried: int
    """Edge samples predicted where the difference image carries signal."""
    rms_px: float
    """RMS distance of the inliers from their steps after the fit."""
    tags: tuple[int, ...]
    """Ids of the tags with inliers."""
    cov_rt: F64
    """6x6 covariance of the fit's last update (δ, Δt): a small rotation δ applied on the arena → camera
    side (R ← exp([δ]×)·R) and the change of ``tvec``."""
    sign: int
    """The sign of the difference's steps (+1: white cells brighter) over most of the image."""
    flipped_rows: tuple[int, int] | None = None
    """Rows (first, last) where the sign was the other one (a rolling shutter's flip inside the frame)."""
    cell_agreement: float = 1.0
    """Of the data cells in view whose difference is clearly positive or negative, the fraction whose sign
    is the map's at this pose: near 1 when the pose is right, near one half when it is off by a cell; 0 when
    fewer than :data:`MANY_CELLS` are clear (see :meth:`cells_confirm`)."""
    cells_clear: int = 0
    """How many data cells in view were clearly positive or negative."""
    cells_agreeing: int = 0
    """How many of those had the map's sign at this pose."""

    def cells_confirm(self, min_agreement: float) -> bool:
        """The data cells confirm the pose: with :data:`MANY_CELLS` or more clear, at least ``min_agreement``
        of them agree with the map; with fewer (down to :data:`FEW_CELLS`), fewer may disagree: from none
        of :data:`FEW_CELLS` to the fraction ``1 - min_agreement`` of :data:`MANY_CELLS`. A pose a tag off
        (the map's tags differ only in their data cells) agrees with ~50-70 % of them: the fewer cells
        are counted, the likelier it reaches a given fraction by chance, so the fewer may disagree."""
        n = self.cells_clear
        if n >= MANY_CELLS:
            return self.cells_agreeing / n >= min_agreement
        if n < FEW_CELLS:
            return False
        allowed = int((1.0 - min_agreement) * MANY_CELLS * (n - FEW_CELLS) / (MANY_CELLS - FEW_CELLS) + 1e-9)
        return n - self.cells_agreeing <= allowed

    @property
    def inlier_fraction(self) -> float:
        return self.inliers / self.tried if self.tried else 0.0

    def estimate(self) -> PoseEstimate:
        """The camera's pose in the arena, with the fit's covariance carried to its position (m²) and to a
        small rotation about the arena axes (rad²)."""
        return estimate_from_step(self.rvec, self.tvec, self.cov_rt, self.tags, self.rms_px)


@dataclass(frozen=True)
class TrackSettings:
    """How the edges are searched and the pose fitted."""

    search_px: float = 4.0
    """How far along its normal each sample looks for its step, in the first pass (pixels)."""
    iterations: int = 3
    min_inliers: int = 60
    """Fewer samples on their steps than this: no pose."""
    min_tags: int = 2
    """Inliers must come from at least this many tags (one tag leaves the tilt ambiguous)."""
    contrast: float = 2.0
    """A step must rise this many times the difference image's noise (its median absolute slope)."""
    border_px: float = 3.0
    """Samples closer than this to the image border are not used."""
    max_samples: int = 700
    """At most this many edge samples are used (spread over the tags in view)."""
    bands: int = 6
    """Bands of rows whose sign is decided apart (a rolling shutter flips it inside a frame)."""
    rolling_shutter: bool = False
    """Fit, beside the pose (of the centre row), how it changes from the top row to the bottom one: a rolling
    shutter sees the rows from different poses while the drone vibrates."""


#: The fit has converged when its last step moved no sample by more than this (pixels).
CONVERGED_PX = 0.05


def _select(
    edges: MapEdges,
    camera_matrix: F64,
    r: F64,
    t: F64,
    size: tuple[int, int],
    most: int,
    lit: U8 | None = None,
    border_px: float = 0.0,
) -> tuple[I64, bool]:
    """Indices of the edge samples of the tags that may be in view, at most ``most`` of them, spread evenly;
    with ``lit`` (the pixels that carry signal), spread over those the pose puts on lit pixels instead when
    fewer than :data:`FEW_LIT_SAMPLES` of the even spread would land there; and whether it did so."""
    w, h = size
    centres = edges.tag_centres_m @ r.T + t
    depth = centres[:, 2]
    ahead = depth > 0.05
    k = camera_matrix
    uv = np.full((len(depth), 2), -1e9)
    uv[ahead] = (k[:2, :2] @ (centres[ahead, :2] / depth[ahead, None]).T).T + k[:2, 2]
    reach = k[0, 0] * edges.tag_radius_m / np.maximum(depth, 0.05)
    near = ahead & (uv[:, 0] > -reach) & (uv[:, 0] < w + reach) & (uv[:, 1] > -reach) & (uv[:, 1] < h + reach)
    if edges.tag_cell_m is not None:
        near &= k[0, 0] * edges.tag_cell_m / np.maximum(depth, 0.05) >= MIN_CELL_PX
    chosen = np.flatnonzero(near[edges.tag])
    if len(chosen) <= most:
        return chosen, False
    even = chosen[np.linspace(0, len(chosen) - 1, most).astype(np.int64)]
    if lit is None or int(_on_lit(edges, camera_matrix, r, t, even, lit, border_px).sum()) >= FEW_LIT_SAMPLES:
        return even, False
    seen = chosen[_on_lit(edges, camera_matrix, r, t, chosen, lit, border_px)]
    if len(seen) > most:
        seen = seen[np.linspace(0, len(seen) - 1, most).astype(np.int64)]
    return (seen, True) if len(seen) > FEW_LIT_SAMPLES else (even, False)


def _on_lit(edges: MapEdges, camera_matrix: F64, r: F64, t: F64, samples: I64, lit: U8, border_px: float) -> B:
    """Which of the edge ``samples`` the pose (``r``, ``t``) puts on a lit pixel of ``lit`` (non-zero), inside
    the image by ``border_px``: the test :func:`~ipt.receiver.core.kernels.measure` makes."""
    h, w = lit.shape
    cam = edges.points_m.take(samples, axis=0) @ r.T + t
    z = cam[:, 2]
    ahead = z > 0
    z = np.where(ahead, z, 1.0)
    u = camera_matrix[0, 0] * cam[:, 0] / z + camera_matrix[0, 2]
    v = camera_matrix[1, 1] * cam[:, 1] / z + camera_matrix[1, 2]
    inside = ahead & (u > border_px) & (u < w - 1 - border_px) & (v > border_px) & (v < h - 1 - border_px)
    on = np.zeros(len(samples), np.bool_)
    rows = (v[inside] + 0.5).astype(np.int64)
    cols = (u[inside] + 0.5).astype(np.int64)
    on[inside] = lit[rows, cols] != 0
    return on


def fast_median(values: npt.NDArray[np.floating[Any]]) -> float:
    """The median of a non-empty 1-D array (numpy's own costs ~10x more on the few hundred values here)."""
    values = values.ravel()
    n = len(values)
    if n == 0:
        return 0.0
    half = n // 2
    part = np.partition(values, half if n % 2 else (half - 1, half))
    return float(part[half]) if n % 2 else 0.5 * (float(part[half - 1]) + float(part[half]))


def slope_noise(diff: F32, valid: npt.NDArray[np.uint8] | None) -> float:
    """The median absolute slope of ``diff`` along rows (where valid): what a step must stand out from.
    (Every fourth row, every second column, gathered in one compiled pass: :func:`~ipt.receiver.core.kernels.
    slopes_sampled`.)"""
    return max(fast_median(kernels.slopes_sampled(diff, _NO_MASK if valid is None else valid)), 1e-3)


def track_pose(
    diff: F32,
    camera_matrix: F64,
    edges: MapEdges,
    rvec: F64,
    tvec: F64,
    settings: TrackSettings = TrackSettings(),
    sign: int | None = None,
    valid: npt.NDArray[np.uint8] | None = None,
    coarse_px: float = 0.0,
    noise: float | None = None,
) -> TrackResult | None:
    """Refine the pose (``rvec``, ``tvec``: arena → camera) so that the map's edges sit on the steps of
    ``diff`` (the signed difference of an undistorted pair in this frame's geometry: this frame minus the
    other, smoothed; ``camera_matrix`` a pinhole). ``sign`` is the difference's polarity if known; without
    it each band of rows decides its own from the data. ``valid`` (0/255) marks the pixels that carry
    signal. With ``coarse_px`` > 0 a first pass searches that far on a blurred copy of ``diff`` (for a
    guess that may be several pixels off). ``noise`` is :func:`slope_noise` of ``diff`` if known. None if
    too few edges agree."""
    h, w = diff.shape
    rot, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    r, t = np.asarray(rot, np.float64), np.asarray(tvec, np.float64).reshape(3)
    lit = valid if valid is not None and valid.shape == diff.shape else None
    chosen, seen_only = _select(edges, camera_matrix, r, t, (w, h), settings.max_samples, lit, settings.border_px)
    if len(chosen) < settings.min_inliers:
        return None
    fit = _Fit(edges, chosen, camera_matrix, (w, h), settings, valid)
    fit.band_sign = None if sign is None else np.full(settings.bands, float(sign))
    radius = max(2, int(np.ceil(settings.search_px)))
    if coarse_px > 0:
        blurred = np.asarray(cv2.GaussianBlur(diff, (0, 0), max(1.0, coarse_px / 4)), np.float32)
        noise = slope_noise(blurred, valid)
        for _ in range(2):
            if not fit.step(blurred, noise, max(radius, int(np.ceil(coarse_px))), r, t):
                return None
            r, t = fit.r, fit.t
    noise = slope_noise(diff, valid) if noise is None else noise
    for it in range(settings.iterations):
        radius_now = radius if it == 0 else max(2, (radius + 1) // 2)
        if not fit.step(diff, noise, radius_now, r, t):
            return None
        r, t = fit.r, fit.t
        if fit.converged:
            break
    result = fit.result(diff, valid)
    if result is not None and seen_only and result.inlier_fraction < LIT_MIN_INLIER_FRACTION:
        return None
    return result


_NO_MASK = np.zeros((0, 0), np.uint8)
"""No valid mask: every pixel may be measured."""


class _Fit:
    """The Gauss-Newton fit of the pose to the edge samples' steps, one step at a time.

    The pose is (R, t) of arena → camera; each step updates it as R ← exp([δ]×)·R, t ← t + Δt, so the
    Jacobian of a point's projection is closed-form: ∂X/∂δ = −[R·P]×, ∂X/∂t = I (a pinhole without
    distortion: the frames were undistorted)."""

    def __init__(
        self,
        edges: MapEdges,
        chosen: I64,
        camera_matrix: F64,
        size: tuple[int, int],
        settings: TrackSettings,
        valid: npt.NDArray[np.uint8] | None,
    ) -> None:
        self.edges, self.k, self.size, self.settings, self.valid = edges, camera_matrix, size, settings, valid
        # (take and compress below: numpy's fancy indexing of rows costs several times more, same result)
        self.obj, self.nrm = edges.points_m.take(chosen, axis=0), edges.normals_m.take(chosen, axis=0)
        self.step_value, self.owner = edges.step[chosen], edges.tag[chosen]
        self.step_sign = np.sign(self.step_value).astype(np.float64)
        self.step_size = np.abs(self.step_value).astype(np.float64)
        self.band_sign: F64 | None = None
        self.r = np.eye(3)
        self.t = np.zeros(3)
        self.inliers = np.zeros(0, bool)
        self.a_rows = np.zeros((0, 6))
        self.offsets = np.zeros(0)
        self.idx = np.zeros(0, np.int64)
        self.sol = np.zeros(6)
        self.sweep = np.zeros(6)
        # The sweep's prior (per unknown: (residual σ / expected size)², residual σ 0.3 px): a rotation of
        # ~0.5° and a move of ~5 mm over a readout, as a vibrating drone's camera makes in ~6 ms.
        self.prior = np.array([(0.3 / 0.009) ** 2] * 3 + [(0.3 / 0.005) ** 2] * 3)
        self.tried = 0
        self.converged = False

    def step(self, image: F32, noise: float, radius: int, r: F64, t: F64) -> bool:
        """One Gauss-Newton step searching ``radius`` pixels on ``image``; False when too few samples agree."""
        s = self.settings
        k = self.k
        valid = self.valid if self.valid is not None else _NO_MASK
        idx, raw, band, rows, place = measure(
            self.obj, self.nrm, self.step_sign, r, t, k, image, valid, radius, s.border_px, s.bands, self.sweep
        )
        self.tried = len(idx)
        if self.tried < s.min_inliers:
            return False
        if self.band_sign is None:
            self.band_sign = band_signs(raw, band, s.bands)
        threshold = s.contrast * noise * self.step_size[idx] / 2
        offsets, strong = peaks(raw, band, self.band_sign, threshold)
        if strong.sum() < s.min_inliers:
            return False
        a_rows = rows
        if s.rolling_shutter:
            # Six more unknowns: the change of pose from the top row to the bottom one, kept small by a prior.
            a_rows = np.hstack([rows, rows * place[:, None]])
        keep = strong.copy()
        fitted = np.zeros(0, np.bool_)  # the samples ``sol`` was fitted to: the same ones give the same fit
        sol = np.zeros(a_rows.shape[1])
        for _ in range(2):  # robust: drop samples far from the fit (from the median absolute deviation)
            if keep.sum() < 12:
                return False
            if np.array_equal(keep, fitted):
                break  # the same fit, the same cut: nothing would change
            sol, fitted = self._solve(np.compress(keep, a_rows, axis=0), offsets[keep]), keep
            res = offsets - a_rows @ sol
            scale = max(1.4826 * fast_median(np.abs(res[keep])), 0.25)
            keep = strong & (np.abs(res) < 3.0 * scale)
        # (the number of tags seen: bincount costs a tenth of np.unique here)
        if keep.sum() < s.min_inliers or np.count_nonzero(np.bincount(self.owner[idx][keep])) < s.min_tags:
            return False
        a_kept = np.compress(keep, a_rows, axis=0)
        if not np.array_equal(keep, fitted):
            sol = self._solve(a_kept, offsets[keep])
        self.idx, self.a_rows, self.offsets, self.inliers, self.sol = idx, a_rows, offsets, keep, sol
        rot, _ = cv2.Rodrigues(sol[:3].reshape(3, 1))
        self.r = np.asarray(rot, np.float64) @ r
        self.t = t + sol[3:6]
        if s.rolling_shutter:
            self.sweep = self.sweep + sol[6:]
        self.converged = float(np.abs(a_kept @ sol).max()) < CONVERGED_PX
        return True

    def _normal(self, a: F64) -> F64:
        """aᵀa, with the rolling-shutter prior on the sweep's unknowns when they are fitted."""
        n = a.T @ a
        if a.shape[1] > 6:
            n[np.arange(6, 12), np.arange(6, 12)] += self.prior
        return n

    def _solve(self, a: F64, b: F64) -> F64:
        """Least squares by the normal equations (cheaper than an SVD, as exact here): the pose's change
        from the current estimate (and the sweep's)."""
        rhs = a.T @ b
        if a.shape[1] > 6:
            rhs[6:] -= self.prior * self.sweep  # the prior holds the whole sweep near zero, not each step
        return np.asarray(np.linalg.solve(self._normal(a), rhs), np.float64)

    def result(self, diff: F32, valid: npt.NDArray[np.uint8] | None) -> TrackResult | None:
        inl = self.inliers
        a_inl = np.compress(inl, self.a_rows, axis=0)
        residual = self.offsets[inl] - a_inl @ self.sol
        rms = float(np.sqrt(np.mean(residual**2)))
        try:
            full = np.linalg.inv(self._normal(a_inl))
            cov = np.asarray(max(rms, 0.1) ** 2 * full[:6, :6], np.float64)
        except np.linalg.LinAlgError:
            return None
        band_sign = self.band_sign if self.band_sign is not None else np.ones(self.settings.bands)
        main = 1 if band_sign.sum() >= 0 else -1
        other = np.flatnonzero(band_sign != main)
        h = diff.shape[0]
        bands = self.settings.bands
        flipped = (int(other.min() * h / bands), int((other.max() + 1) * h / bands) - 1) if len(other) else None
        # (the tags present, by bincount: np.unique's sort costs ten times more)
        tags = tuple(sorted({self.edges.tag_ids[t] for t in np.flatnonzero(np.bincount(self.owner[self.idx][inl]))}))
        present = np.flatnonzero(np.bincount(self.owner))
        agreeing, clear = _cell_agreement(diff, self.k, self.edges, self.r, self.t, present, band_sign, valid)
        rvec, _ = cv2.Rodrigues(self.r)
        return TrackResult(
            np.asarray(rvec, np.float64).reshape(3),
            self.t.copy(),
            int(inl.sum()),
            self.tried,
            rms,
            tags,
            cov,
            main,
            flipped,
            agreeing / clear if clear >= MANY_CELLS else 0.0,
            clear,
            agreeing,
        )


def _cell_agreement(
    diff: F32,
    camera_matrix: F64,
    edges: MapEdges,
    r: F64,
    t: F64,
    tags: I64,
    band_sign: F64,
    valid: npt.NDArray[np.uint8] | None,
) -> tuple[int, int]:
    """How many of the visible data cells' centres are clear, and how many of those have the sign the map
    gives them at this pose: (agreeing, clear)."""
    tag_on = np.zeros(len(edges.tag_ids), np.bool_)
    tag_on[tags] = True
    agreeing, clear = cell_agreement(
        diff,
        camera_matrix,
        r,
        t,
        edges.cells_m,
        edges.cell_tag,
        edges.cell_value,
        tag_on,
        band_sign,
        valid if valid is not None else _NO_MASK,
    )
    return int(agreeing), int(clear)


class MaskRenderer:
    """The hidden map's mask as the camera would see it at a pose (at half resolution), for the coarse
    search of a guess that may be many pixels off."""

    def __init__(self, mask: npt.NDArray[np.int8], pixel_to_arena: F64) -> None:
        # In 16-bit fixed point (x256): exact for a mask of -1/0/+1, and a seventh of float32's time on a
        # 1920x2160 map (a restarted daemon's first pose waits for it).
        self._mask = np.asarray(cv2.pyrDown(mask.astype(np.int16) * 256), np.float32) / 256
        # Half-resolution mask index s → projector pixels (edge origin; s covers 2s and 2s + 1, centre 2s + 1)
        # → arena metres.
        self._half_to_arena = pixel_to_arena @ np.array([[2.0, 0.0, 1.0], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]])

    def render(self, camera_matrix: F64, rvec: F64, tvec: F64, size: tuple[int, int]) -> F32:
        """The mask (+1 white cells, -1 black, 0 elsewhere) at half the image size ``size`` (w, h)."""
        r, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
        floor_to_image = camera_matrix @ np.column_stack([r[:, 0], r[:, 1], np.asarray(tvec).reshape(3)])
        half = np.diag([0.5, 0.5, 1.0])
        # Pixel centres: the image's half-resolution pixel i covers full-resolution pixels 2i and 2i+1.
        centre = np.array([[1.0, 0.0, -0.25], [0.0, 1.0, -0.25], [0.0, 0.0, 1.0]])
        h_map = centre @ half @ floor_to_image @ self._half_to_arena
        w, h = size
        out = cv2.warpPerspective(self._mask, h_map, ((w + 1) // 2, (h + 1) // 2), flags=cv2.INTER_LINEAR)
        return np.asarray(out, np.float32)


@functools.lru_cache(maxsize=4)
def _near_prior(w: int, h: int) -> F64:
    """Weights of the circular correlation's shifts (w x h, unshifted at [0, 0]): a Gaussian of the shift's
    length with σ :data:`SHIFT_PRIOR` of the image's width, so that a far peak must be that much stronger
    than a near one to be taken."""
    sigma = SHIFT_PRIOR * w
    dx = np.minimum(np.arange(w), w - np.arange(w)).astype(np.float64)
    dy = np.minimum(np.arange(h), h - np.arange(h)).astype(np.float64)
    return np.asarray(np.exp(-(dy[:, None] ** 2 + dx[None, :] ** 2) / (2 * sigma * sigma)), np.float64)


@functools.lru_cache(maxsize=4)
def _hanning(w: int, h: int) -> F32:
    return np.asarray(cv2.createHanningWindow((w, h), cv2.CV_32F), np.float32)


def coarse_shift(
    diff: F32, predicted_mask_half: F32, valid: npt.NDArray[np.uint8] | None
) -> tuple[float, float, float]:
    """The image shift (dx, dy, full-resolution pixels) that best lays the predicted mask on the difference,
    by cross-correlation at half resolution (near shifts preferred: :data:`SHIFT_PRIOR`), and the normalised
    peak (its sign is the difference's)."""
    small = np.asarray(cv2.pyrDown(diff), np.float32)
    if valid is not None:
        small = small * (cv2.resize(valid, small.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0)
    h, w = small.shape
    window = _hanning(w, h)
    mask = np.ascontiguousarray(predicted_mask_half[:h, :w], np.float32)
    # OpenCV's float32 transforms: several times cheaper than numpy's float64 ones at this size.
    fa = cv2.dft(small * window, flags=cv2.DFT_COMPLEX_OUTPUT)
    fb = cv2.dft(mask * window, flags=cv2.DFT_COMPLEX_OUTPUT)
    corr = np.asarray(
        cv2.idft(cv2.mulSpectrums(fa, fb, 0, conjB=True), flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE), np.float64
    )
    magnitude = np.abs(corr)
    peak = int(np.argmax(magnitude * _near_prior(w, h)))
    py, px = divmod(peak, w)
    value = float(corr.flat[peak])
    norm = float(np.sqrt((small * small * window).sum() * (mask * mask * window).sum())) + 1e-9

    def vertex(a: float, b: float, c: float) -> float:  # sub-pixel: the parabola through three samples
        den = a - 2 * b + c
        return 0.5 * (a - c) / den if den < 0 else 0.0

    fx = vertex(magnitude[py, (px - 1) % w], magnitude[py, px], magnitude[py, (px + 1) % w])
    fy = vertex(magnitude[(py - 1) % h, px], magnitude[py, px], magnitude[(py + 1) % h, px])
    dy = (py if py <= h // 2 else py - h) + fy
    dx = (px if px <= w // 2 else px - w) + fx
    return 2.0 * dx, 2.0 * dy, value / norm


def shifted_pose(
    camera_matrix: F64, rvec: F64, tvec: F64, dx: float, dy: float, size: tuple[int, int]
) -> tuple[F64, F64] | None:
    """The pose whose view of the floor is that of (``rvec``, ``tvec``) moved by (dx, dy) pixels."""
    w, h = size
    img = np.array([[0.25 * w, 0.25 * h], [0.75 * w, 0.25 * h], [0.75 * w, 0.75 * h], [0.25 * w, 0.75 * h]])
    return _pose_seeing(camera_matrix, (rvec, tvec), img, img + np.array([dx, dy]))


def carried_pose(camera_matrix: F64, size: tuple[int, int], rt: tuple[F64, F64], warp: F64) -> tuple[F64, F64] | None:
    """The pose whose view of the floor is that of ``rt`` (rvec, tvec) carried by the image homography ``warp``."""
    w, h = size
    img = np.array([[0.2 * w, 0.2 * h], [0.8 * w, 0.2 * h], [0.8 * w, 0.8 * h], [0.2 * w, 0.8 * h]])
    return _pose_seeing(camera_matrix, rt, img, cv2.perspectiveTransform(img.reshape(1, -1, 2), warp).reshape(-1, 2))


def _pose_seeing(camera_matrix: F64, rt: tuple[F64, F64], image_px: F64, moved_px: F64) -> tuple[F64, F64] | None:
    """The pose that sees at ``moved_px`` the floor points the pose ``rt`` sees at ``image_px`` (a level view's
    four points, IPPE); None if ``rt`` does not see them on the floor or the solve fails."""
    floor = floor_points(camera_matrix, rt[0], rt[1], image_px)
    if floor is None:
        return None
    ok, rvec, tvec = cv2.solvePnP(floor, moved_px, camera_matrix, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    return np.asarray(rvec, np.float64).reshape(3), np.asarray(tvec, np.float64).reshape(3)


def floor_points(camera_matrix: F64, rvec: F64, tvec: F64, image_px: F64) -> F64 | None:
    """The floor points (N×3, z = 0) that the pinhole camera at (``rvec``, ``tvec``) sees at ``image_px``."""
    r_cam, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    t = np.asarray(tvec, np.float64).reshape(3)
    rays = (np.linalg.inv(camera_matrix) @ np.column_stack([image_px, np.ones(len(image_px))]).T).T
    dirs = (r_cam.T @ rays.T).T
    centre = -r_cam.T @ t
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -centre[2] / dirs[:, 2]
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        return None
    return np.asarray(centre + s[:, None] * dirs, np.float64)
