"""The pose from the hidden map without a whole tag: where on the whole map does this difference fit?

AprilTag needs a whole tag; a drone taking off from the open floor sees only tags cut by the image border
or by its own shadow. The partial tags still show dozens of whole code cells, and the map says where
every cell is. A nearly level camera sees the floor as a similarity of it (scale f/h, a yaw, a shift),
and the map's cells are axis-aligned, so:

1. the yaw modulo 90° is the peak of the difference's gradient orientations (modulo 90°);
2. for each of the four yaws and each height on a grid, the difference, warped into the map's
   resolution and orientation, is placed over the whole map by one FFT cross-correlation: the tags share
   their borders, so only the right placement also agrees on the data cells, and beats the others;
3. the best placements, refined in height, are the hypotheses, for the tracker to confirm or refuse
   (:func:`~ipt.receiver.core.track.track_pose` and the checks on its fit).

Pure: the map's mask once, then arrays in, pose hypotheses out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.tagmap import TAG36H11_CELLS, TagMap, pixel_to_arena

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]


class MapSearchError(IptError):
    """The map cannot be searched (it has no tags, or its cells are not axis-aligned squares)."""


@dataclass(frozen=True)
class SearchSettings:
    """How widely and how finely the search looks."""

    min_height_m: float = 0.35
    max_height_m: float = 1.2
    height_ratio: float = 1.1
    """Consecutive heights of the coarse grid differ by this factor."""
    fine_ratio: float = 1.015
    """The refinement around the best heights steps by this factor."""
    cells_per_px: float = 0.75
    """The map's resolution, in code cells per map pixel."""
    min_valid_share: float = 0.05
    """A difference valid on less than this share of the image is not searched."""
    min_score: float = 0.3
    """A placement whose normalised correlation is weaker than this is no hypothesis (noise alone gives ~0.2,
    the right placement 0.6-1)."""
    hypotheses: int = 3
    search_cells: float = 0.6
    """A hypothesis may be this many code cells off (:attr:`Hypothesis.search_px`)."""
    local_energy: bool = False
    """Normalise each placement by the map's energy under it (one more transform per placement), rather
    than by the map's mean."""


@dataclass(frozen=True)
class Hypothesis:
    """A level camera's pose that lays the map on the difference."""

    rvec: F64
    """Rotation arena → camera (Rodrigues)."""
    tvec: F64
    """Arena origin in the camera frame, metres."""
    position_m: F64
    yaw_rad: float
    """The camera's x axis from the arena's x axis, counter-clockwise."""
    score: float
    """The normalised correlation (its sign: the difference's phase)."""
    search_px: float
    """How far off in the image the map may lie at this pose (from the coarse grid and the tilt), pixels."""


def level_pose(position_m: F64, yaw_rad: float) -> tuple[F64, F64]:
    """(rvec, tvec) of a camera at ``position_m`` looking straight down, its x axis at ``yaw_rad``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    r_cam_arena = np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])  # rows: the camera axes in the arena
    rvec, _ = cv2.Rodrigues(r_cam_arena)
    return np.asarray(rvec, np.float64).reshape(3), np.asarray(-r_cam_arena @ position_m, np.float64)


def yaw_mod_90(diff: F32, valid: U8 | None) -> tuple[float, float]:
    """The yaw modulo 90° (radians, in [0, π/2)) whose axes the difference's edges run along, and how
    peaked the orientations are (the peak's share of the gradient weight within ±5° of it)."""
    small = np.asarray(cv2.pyrDown(diff), np.float32)
    gx = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3)
    weight = np.hypot(gx, gy)
    if valid is not None:
        inner = cv2.erode(valid, np.ones((9, 9), np.uint8))  # not the shadow's rim
        weight *= cv2.resize(inner, small.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
    angle = np.mod(np.arctan2(gy, gx), np.pi / 2)
    bins = 90
    hist = np.bincount(
        np.minimum((angle * (bins / (np.pi / 2))).astype(np.int64), bins - 1).ravel(),
        weights=weight.ravel().astype(np.float64),
        minlength=bins,
    )
    total = float(hist.sum())
    if total <= 0:
        return 0.0, 0.0
    smooth = np.convolve(np.concatenate([hist[-2:], hist, hist[:2]]), np.ones(5) / 5, mode="valid")
    k = int(np.argmax(smooth))
    a, b, c = smooth[(k - 1) % bins], smooth[k], smooth[(k + 1) % bins]
    den = a - 2 * b + c
    frac = 0.5 * (a - c) / den if den < 0 else 0.0
    yaw = ((k + 0.5 + frac) % bins) * (np.pi / 2) / bins
    near = sum(hist[(k + j) % bins] for j in range(-5, 6))
    return float(yaw), float(near / total)


def _blurred(mask: npt.NDArray[np.int8], sigma_px: float, factor: int) -> tuple[F32, F64]:
    """``mask`` blurred by a Gaussian of ``sigma_px`` (its pixels), at a ``factor`` coarser resolution, and the
    homography from its pixel indices to the result's. The mean over ``factor`` x ``factor`` squares first (a box:
    variance (factor² − 1) / 12), then the Gaussian that makes up the rest: at a map index of ~15 mask pixels a
    blur of σ 6 on 4 million pixels cost a replay 29-74 ms of processor time here, this 4.5-14 ms, the map the same
    within 0.07 of its ±1 (stop 71). The last rows and columns that make no whole square (fewer than ``factor``) are
    left out: a tag there would lose a sliver of a map index."""
    h, w = mask.shape[0] // factor * factor, mask.shape[1] // factor * factor
    small = cv2.resize(mask[:h, :w].astype(np.float32), (w // factor, h // factor), interpolation=cv2.INTER_AREA)
    rest_px = math.sqrt(max(sigma_px * sigma_px - (factor * factor - 1) / 12.0, 0.25)) / factor
    centre = (factor - 1) / (2.0 * factor)  # a square's first pixel centre, in its own pixels
    to_small = np.array([[1.0 / factor, 0.0, -centre], [0.0, 1.0 / factor, -centre], [0.0, 0.0, 1.0]])
    return np.asarray(cv2.GaussianBlur(small, (0, 0), rest_px), np.float32), to_small


class MapSearch:
    """The whole map, rendered once at a coarse resolution with its spectrum, for :meth:`search`."""

    def __init__(
        self,
        mask: npt.NDArray[np.int8],
        pixel_to_arena: F64,
        cell_m: float,
        settings: SearchSettings = SearchSettings(),
    ) -> None:
        """``mask``: the map's mask in projector pixels (+1 white, -1 black, 0 floor); ``pixel_to_arena``: its
        projector pixels (edge origin) to arena metres; ``cell_m``: the code cell side of most of its tags."""
        self.settings = settings
        if not np.any(mask) or not cell_m > 0:
            raise MapSearchError("the map has no tags to search")
        self.cell_m = cell_m
        self.res_m = cell_m * settings.cells_per_px
        h_px, w_px = mask.shape
        corners = cv2.perspectiveTransform(
            np.array([[[0.0, 0.0], [w_px, 0.0], [w_px, h_px], [0.0, h_px]]]), pixel_to_arena
        )[0]
        self.origin_m = corners.min(axis=0)
        size = np.ceil((corners.max(axis=0) - self.origin_m) / self.res_m).astype(int) + 1
        # Map index (i, j) is the arena point origin + (i, j)·res; it samples the mask blurred to that scale.
        index_to_arena = np.array(
            [[self.res_m, 0.0, self.origin_m[0]], [0.0, self.res_m, self.origin_m[1]], [0.0, 0.0, 1.0]]
        )
        edge_to_index = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
        to_mask = edge_to_index @ np.linalg.inv(pixel_to_arena) @ index_to_arena
        px_per_index = float(np.sqrt(abs(np.linalg.det(to_mask[:2, :2]))))
        blurred, to_blurred = _blurred(mask, max(0.5, 0.4 * px_per_index), max(1, int(px_per_index // 3)))
        self.map = np.asarray(
            cv2.warpPerspective(
                blurred,
                to_blurred @ to_mask,
                (int(size[0]), int(size[1])),
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            ),
            np.float32,
        )
        self.mean_energy = float(np.mean(self.map[self.map != 0] ** 2))
        self._spectra: dict[tuple[int, int], tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]] = {}

    @classmethod
    def of(
        cls, tag_map: TagMap, settings: SearchSettings = SearchSettings(), mask: npt.NDArray[np.int8] | None = None
    ) -> MapSearch:
        """The search of ``tag_map``, at the code cell of most of its tags (a landing pad's are smaller); ``mask``:
        its :meth:`~ipt.tagmap.TagMap.render_mask` if already made (20 ms at 1920x2160: the pipeline makes it once)."""
        sides = [float(np.linalg.norm(np.subtract(t.corners_m[1], t.corners_m[0]))) for t in tag_map.tags]
        cell_m = float(np.median(sides)) / (TAG36H11_CELLS - 2) if sides else 0.0
        return cls(tag_map.render_mask() if mask is None else mask, pixel_to_arena(tag_map), cell_m, settings)

    def _spectrum(self, shape: tuple[int, int]) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
        """The map's spectrum and its square's, zero-padded to ``shape`` (rows, cols), in OpenCV's packed form for a
        real image (half the complex spectrum: the transforms cost a third of the complex ones')."""
        if shape not in self._spectra:
            padded = np.zeros(shape, np.float32)
            padded[: self.map.shape[0], : self.map.shape[1]] = self.map
            self._spectra[shape] = (
                cv2.dft(padded),
                cv2.dft(padded * padded),
            )
        return self._spectra[shape]

    def search(self, diff: F32, valid: U8 | None, camera_matrix: F64) -> list[Hypothesis]:
        """The best level poses laying the map on ``diff`` (undistorted, pinhole ``camera_matrix``; ``valid``
        0/255 where it carries signal), best first; none if the difference shows no map."""
        s = self.settings
        weight = np.ones(diff.shape, np.float32) if valid is None else (valid > 0).astype(np.float32)
        if float(weight.mean()) < s.min_valid_share:
            return []
        yaw0, _ = yaw_mod_90(diff, valid)
        pyramid = _Pyramid(np.asarray(diff, np.float32) * weight, weight)
        heights = _grid(s.min_height_m, s.max_height_m, s.height_ratio)
        found = [self._place(pyramid, camera_matrix, h, yaw0) for h in heights]
        coarse = sorted((p for row in found for p in row), key=lambda p: -abs(p[0]))
        refined: list[tuple[float, float, float, F64]] = []
        for _score, height, yaw, _ in coarse[: s.hypotheses]:
            fine = [height * s.fine_ratio**k for k in range(-2, 3)]
            best = max(
                (p for h in fine for p in self._place(pyramid, camera_matrix, h, yaw, turns=(0,))),
                key=lambda p: abs(p[0]),
            )
            refined.append(best)
        out = []
        for score, height, yaw, xy in sorted(refined, key=lambda p: -abs(p[0])):
            if abs(score) < s.min_score:
                continue
            position = np.array([xy[0], xy[1], height])
            rvec, tvec = level_pose(position, yaw)
            search_px = s.search_cells * float(camera_matrix[0, 0]) * self.cell_m / height
            out.append(Hypothesis(rvec, tvec, position, yaw, score, search_px))
        return out

    def _place(
        self, pyramid: _Pyramid, k: F64, height: float, yaw0: float, turns: tuple[int, ...] = (0, 1, 2, 3)
    ) -> list[tuple[float, float, float, F64]]:
        """For each yaw ``yaw0`` + turn·90°, the best placement on the map at ``height``: (normalised
        correlation, height, yaw, camera x, y in metres)."""
        out = []
        for turn in turns:
            yaw = yaw0 + turn * np.pi / 2
            patch, weight, offset = pyramid.patch(k, height, yaw, self.res_m)
            rows = cv2.getOptimalDFTSize(self.map.shape[0] + patch.shape[0])
            cols = cv2.getOptimalDFTSize(self.map.shape[1] + patch.shape[1])
            f_map, f_energy = self._spectrum((rows, cols))
            big = np.zeros((rows, cols), np.float32)
            big[: patch.shape[0], : patch.shape[1]] = patch
            corr = _correlate(big, f_map)
            if self.settings.local_energy:
                big[: patch.shape[0], : patch.shape[1]] = weight
                energy = _correlate(big, f_energy)
            else:
                energy = np.full(corr.shape, self.mean_energy * float(weight.sum()), np.float32)
            # Normalised correlation: the patch's energy once, the map's under the patch's support per shift.
            norm = float(np.sqrt((patch * patch).sum())) * np.sqrt(np.maximum(energy, 0.05 * float(weight.sum())))
            ncc = np.divide(corr, norm, out=np.zeros_like(corr), where=norm > 0)  # (a flat view: nothing to place)
            peak = int(np.argmax(np.abs(ncc)))
            ty, tx = divmod(peak, cols)
            ty = ty - rows if ty > rows - patch.shape[0] else ty
            tx = tx - cols if tx > cols - patch.shape[1] else tx
            xy = self.origin_m + self.res_m * (np.array([tx, ty], np.float64) - offset)
            out.append((float(ncc.flat[peak]), height, float(yaw % (2 * np.pi)), xy))
        return out


def _correlate(patch: F32, f_map: npt.NDArray[np.float32]) -> F32:
    """corr(t) = Σ_q patch(q)·map(q + t), circularly (the map's spectrum given)."""
    f_patch = cv2.dft(patch)  # (packed, as the map's)
    spec = cv2.mulSpectrums(f_map, f_patch, 0, conjB=True)
    return np.asarray(cv2.idft(spec, flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE), np.float32)


class _Pyramid:
    """The masked difference and its weight, box-averaged by powers of two (for warps that shrink a lot)."""

    def __init__(self, diff: F32, weight: F32) -> None:
        self.levels = [(diff, weight)]
        for _ in range(4):
            d, w = self.levels[-1]
            if min(d.shape) < 16:
                break
            size = (d.shape[1] // 2, d.shape[0] // 2)
            self.levels.append(
                (cv2.resize(d, size, interpolation=cv2.INTER_AREA), cv2.resize(w, size, interpolation=cv2.INTER_AREA))
            )

    def patch(self, k: F64, height: float, yaw: float, res_m: float) -> tuple[F32, F32, F64]:
        """The difference (and its weight) seen from ``height`` at ``yaw`` in map pixels, and the offset o:
        patch index q is the arena point camera + (q + o)·res."""
        c, s = math.cos(yaw), math.sin(yaw)
        # image (u, v) → arena offset from the camera: h·((u−cx)/fx·(c, s) + (v−cy)/fy·(s, −c)).
        lin = height * np.array([[c / k[0, 0], s / k[1, 1]], [s / k[0, 0], -c / k[1, 1]]]) / res_m
        shrink = 1.0 / float(np.sqrt(abs(np.linalg.det(lin))))  # image pixels per map pixel
        level = max(0, min(len(self.levels) - 1, math.floor(math.log2(max(shrink, 1.0)))))
        d, w = self.levels[level]
        f = 2.0**level
        # level pixel (x, y) ↔ image pixel f·(x + 0.5) − 0.5
        to_image = np.array([[f, 0.0, 0.5 * f - 0.5], [0.0, f, 0.5 * f - 0.5], [0.0, 0.0, 1.0]])
        centred = np.array([[1.0, 0.0, -k[0, 2]], [0.0, 1.0, -k[1, 2]], [0.0, 0.0, 1.0]])
        a = np.eye(3)
        a[:2, :2] = lin
        level_to_patch = a @ centred @ to_image
        hl, wl = d.shape
        box = np.array([[0.0, 0.0, 1.0], [wl, 0.0, 1.0], [wl, hl, 1.0], [0.0, hl, 1.0]]) - [0.5, 0.5, 0.0]
        corners = (level_to_patch @ box.T)[:2].T
        low = np.floor(corners.min(axis=0))
        size = np.ceil(corners.max(axis=0) - low).astype(int) + 1
        level_to_patch[:2, 2] -= low
        m = level_to_patch[:2]
        dsize = (int(size[0]), int(size[1]))
        patch = cv2.warpAffine(d, m, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        weight = cv2.warpAffine(w, m, dsize, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        return np.asarray(patch, np.float32), np.asarray(weight, np.float32), np.asarray(low, np.float64)


def _grid(low: float, high: float, ratio: float) -> list[float]:
    n = max(1, math.ceil(math.log(high / low) / math.log(ratio)))
    return [low * ratio**i for i in range(n + 1)]
