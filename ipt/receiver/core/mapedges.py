"""The hidden map's cell edges and data cells as arena points (:class:`MapEdges`, what the track fits), built
for every tag at once.

Built once per pipeline, before the first pose: numpy passes over all the tags at once rather than a loop
of small operations per tag (a third of the time on the shipped arena's 107 tags), and one
:func:`cv2.perspectiveTransform` per tag over all of that tag's points (numpy's own arithmetic would round
the last bit differently: OpenCV's build fuses multiplies and adds), so the arrays are the same to the
last bit as those of the loop they replace, and so are the fits.

Pure: a tag map in, arrays out.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.tagmap import TAG36H11_CELLS, TagMap, tag36h11_bitmap

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]

#: Where along each cell edge it is sampled (fractions of the edge).
SAMPLE_FRACTIONS = (0.25, 0.75)

_N = TAG36H11_CELLS
_LO, _HI = 1.0, float(_N - 1)  # the black border square in cell units
_SRC = np.array([[_LO, _HI], [_HI, _HI], [_HI, _LO], [_LO, _LO]], np.float32)  # BL, BR, TR, TL
_OUTER = np.array([[0.0, 0.0], [_N, 0.0], [_N, _N], [0.0, _N]])
_DATA = np.arange(2, _N - 2)
_GRID = np.stack(np.meshgrid(_DATA + 0.5, _DATA + 0.5), axis=-1).reshape(-1, 2)  # the 6x6 data cells' centres


def _project(h: F64, xy: F64, owner: I64) -> F64:
    """Points ``xy`` (N, 2), sorted by their tag ``owner``, through their tags' homographies ``h`` (T, 3, 3).

    One :func:`cv2.perspectiveTransform` per tag over all of its points: numpy's own arithmetic would round
    differently in the last bit (OpenCV's build fuses multiplies and adds), and the fits must not change."""
    out = np.empty_like(xy)
    bounds = np.searchsorted(owner, np.arange(len(h) + 1))
    for t, (a, b) in enumerate(zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True)):
        if b > a:
            out[a:b] = cv2.perspectiveTransform(xy[None, a:b], h[t])[0]
    return out


def _edges(value: npt.NDArray[np.int64], fractions: F64) -> tuple[I64, F64, F64, F64]:
    """Every edge sample of every tag: its tag, its point and normal in cell units, its step; tag by tag,
    each tag's vertical edges (row-major) before its horizontal ones."""
    n, k = _N, len(fractions)
    vertical = value[:, 1 : n + 1, 1 : n + 2] - value[:, 1 : n + 1, 0 : n + 1]
    horizontal = value[:, 1 : n + 2, 1 : n + 1] - value[:, 0 : n + 1, 1 : n + 1]
    vt, vr, vc = np.nonzero(vertical)
    ht, hr, hc = np.nonzero(horizontal)
    tags = np.concatenate([vt, ht])
    order = np.argsort(tags, kind="stable")
    p = np.concatenate(
        [
            np.column_stack([np.repeat(vc, k), (vr[:, None] + fractions).ravel()]),
            np.column_stack([(hc[:, None] + fractions).ravel(), np.repeat(hr, k)]),
        ]
    ).astype(np.float64)
    nrm = np.repeat(np.array([[1.0, 0.0], [0.0, 1.0]]), [len(vr) * k, len(hr) * k], axis=0)
    step = np.concatenate([np.repeat(vertical[vt, vr, vc], k), np.repeat(horizontal[ht, hr, hc], k)])
    samples = (order[:, None] * k + np.arange(k)).ravel()  # each edge's k samples, in the edges' new order
    tag_of_sample = np.repeat(tags, k)
    return tag_of_sample[samples], p[samples], nrm[samples], step[samples].astype(np.float64)


@dataclass(frozen=True)
class MapEdges:
    """Every cell edge of the hidden map where the mask changes, as sample points on the floor."""

    points_m: F64
    """(N, 3) arena points (z = 0)."""
    normals_m: F64
    """(N, 3) unit vectors in the floor plane across the edge."""
    step: F64
    """(N,) the mask's change across the edge along the normal: ±2 between cells, ±1 to untouched floor."""
    tag: I64
    """(N,) index of the edge's tag in :attr:`tag_ids`."""
    tag_ids: tuple[int, ...]
    tag_centres_m: F64
    """(T, 3) centre of each tag."""
    tag_radius_m: F64
    """(T,) distance from each tag's centre to its farthest quiet-zone corner."""
    cell_m: float
    """The smallest cell side in the map, metres."""
    cells_m: F64
    """(M, 3) the centre of every data cell (the 6x6 inside the border) of every tag."""
    cell_value: F64
    """(M,) the mask there: +1 white, -1 black."""
    cell_tag: I64
    """(M,) index of the cell's tag."""
    tag_cell_m: F64 | None = None
    """(T,) the cell side of each tag (a map of several tag sizes), metres; None: all :attr:`cell_m`."""

    @functools.cached_property
    def tag_ranges(self) -> tuple[I64, I64] | None:
        """Each tag's samples as the range ``start[t] : start[t] + count[t]``, where they lie tag by tag (as
        :meth:`from_tag_map` lays them); None otherwise."""
        if np.any(np.diff(self.tag) < 0):
            return None
        count = np.bincount(self.tag, minlength=len(self.tag_ids)).astype(np.int64)
        return np.cumsum(count) - count, count

    @property
    def largest_cell_m(self) -> float:
        """The largest cell side in the map, metres (:attr:`cell_m` where all tags share one size)."""
        return float(np.max(self.tag_cell_m)) if self.tag_cell_m is not None else self.cell_m

    @classmethod
    def from_tag_map(cls, tag_map: TagMap, fractions: tuple[float, ...] = SAMPLE_FRACTIONS) -> MapEdges:
        """The edges of every tag of ``tag_map``, sampled at ``fractions`` along each, and the tags' centres,
        radii and data cells (for all the tags at once: see the module's docstring)."""
        tags = tag_map.tags
        corners = np.asarray([t.corners_m for t in tags], np.float64).reshape(len(tags), 4, 3)
        h = np.stack(
            [cv2.getPerspectiveTransform(_SRC, c[:, :2].astype(np.float32)).astype(np.float64) for c in corners]
        )
        bitmaps = np.stack([tag36h11_bitmap(t.tag_id) for t in tags]).astype(np.int64)
        value = np.pad(bitmaps * 2 - 1, ((0, 0), (1, 1), (1, 1)))  # +1 white, -1 black, 0 out
        owner, p, nrm, step = _edges(value, np.asarray(fractions, np.float64))
        # Each tag's points in one block: its edge samples, the same nudged along their normals, its data cells'
        # centres and its quiet zone's outer corners.
        t_index = np.arange(len(tags), dtype=np.int64)
        per_tag = np.bincount(owner, minlength=len(tags))
        start = np.concatenate([[0], np.cumsum(2 * per_tag + len(_GRID) + len(_OUTER))[:-1]])
        rank = np.arange(len(owner)) - np.concatenate([[0], np.cumsum(per_tag)[:-1]])[owner]  # index within its tag
        at_p = start[owner] + rank
        at_q = at_p + per_tag[owner]
        at_grid = (start + 2 * per_tag)[:, None] + np.arange(len(_GRID))
        at_outer = at_grid[:, -1:] + 1 + np.arange(len(_OUTER))
        xy = np.empty((int(start[-1] + 2 * per_tag[-1] + len(_GRID) + len(_OUTER)), 2))
        xy[at_p], xy[at_q], xy[at_grid], xy[at_outer] = p, p + 0.01 * nrm, _GRID, _OUTER
        slot_owner = np.repeat(t_index, 2 * per_tag + len(_GRID) + len(_OUTER))
        projected = _project(h, xy, slot_owner)
        pm = projected[at_p]
        d = projected[at_q] - pm
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        zeros = np.zeros((len(pm), 1))
        cells = projected[at_grid].reshape(-1, 2)
        outer = projected[at_outer]
        centres = outer.mean(axis=1)
        radii = np.linalg.norm(outer - centres[:, None], axis=-1).max(axis=1)
        sides = np.linalg.norm(corners[:, 1] - corners[:, 0], axis=-1) / (_HI - _LO)
        return cls(
            np.column_stack([pm, zeros]),
            np.column_stack([d, zeros]),
            step,
            owner.astype(np.int64),
            tuple(t.tag_id for t in tags),
            np.column_stack([centres, np.zeros(len(tags))]),
            radii,
            float(sides.min()),
            np.column_stack([cells, np.zeros((len(cells), 1))]),
            value[:, 1:-1, 1:-1][:, _DATA][:, :, _DATA].reshape(-1).astype(np.float64),
            np.repeat(t_index, len(_GRID)),
            sides,
        )
