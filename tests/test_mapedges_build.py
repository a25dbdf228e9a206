"""The map's edge samples, built for all tags at once (``ipt.receiver.core.mapedges``), are those the per-tag
loop they replace built, to the last bit: on the shipped arena and on a map of tags of several sizes, some
seen in perspective (issue 29, target 4: the pipeline's set-up before the first pose)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from ipt.config.models import load_arena_config, shipped_config_path
from ipt.receiver.core.mapedges import SAMPLE_FRACTIONS, MapEdges
from ipt.tagmap import TAG36H11_CELLS, TagMap, TagPlacement, grid_tag_map, tag36h11_bitmap


def _per_tag_loop(tag_map: TagMap) -> MapEdges:
    """The construction as it was before (one tag at a time), the reference."""
    points, normals, steps, owners, centres, radii, cells = [], [], [], [], [], [], []
    cell_pts, cell_vals, cell_owner = [], [], []
    lo, hi = 1.0, float(TAG36H11_CELLS - 1)
    src = np.array([[lo, hi], [hi, hi], [hi, lo], [lo, lo]], np.float32)
    n = TAG36H11_CELLS
    fractions = np.asarray(SAMPLE_FRACTIONS, np.float64)
    k = len(fractions)
    for t_index, tag in enumerate(tag_map.tags):
        corners = np.asarray(tag.corners_m, np.float64)
        h = cv2.getPerspectiveTransform(src, corners[:, :2].astype(np.float32)).astype(np.float64)
        value = np.pad(tag36h11_bitmap(tag.tag_id).astype(np.int64) * 2 - 1, 1)
        vertical = value[1 : n + 1, 1 : n + 2] - value[1 : n + 1, 0 : n + 1]
        horizontal = value[1 : n + 2, 1 : n + 1] - value[0 : n + 1, 1 : n + 1]
        vr, vc = np.nonzero(vertical)
        hr, hc = np.nonzero(horizontal)
        p = np.concatenate(
            [
                np.column_stack([np.repeat(vc, k), (vr[:, None] + fractions).ravel()]),
                np.column_stack([(hc[:, None] + fractions).ravel(), np.repeat(hr, k)]),
            ]
        ).astype(np.float64)
        nrm_c = np.repeat(np.array([[1.0, 0.0], [0.0, 1.0]]), [len(vr) * k, len(hr) * k], axis=0)
        stp = np.concatenate([np.repeat(vertical[vr, vc], k), np.repeat(horizontal[hr, hc], k)])
        pm = cv2.perspectiveTransform(p[None], h)[0]
        d = cv2.perspectiveTransform((p + 0.01 * nrm_c)[None], h)[0] - pm
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        points.append(np.column_stack([pm, np.zeros(len(pm))]))
        normals.append(np.column_stack([d, np.zeros(len(d))]))
        steps.append(np.asarray(stp, np.float64))
        owners.append(np.full(len(pm), t_index, np.int64))
        data = np.arange(2, n - 2)
        grid = np.stack(np.meshgrid(data + 0.5, data + 0.5), axis=-1).reshape(-1, 2)
        cell_pts.append(np.column_stack([cv2.perspectiveTransform(grid[None], h)[0], np.zeros(len(grid))]))
        cell_vals.append(value[1:-1, 1:-1][np.ix_(data, data)].reshape(-1).astype(np.float64))
        cell_owner.append(np.full(len(grid), t_index, np.int64))
        outer = cv2.perspectiveTransform(np.array([[[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]]]), h)[0]
        centre = outer.mean(axis=0)
        centres.append((*centre, 0.0))
        radii.append(float(np.linalg.norm(outer - centre, axis=1).max()))
        cells.append(float(np.linalg.norm(corners[1] - corners[0])) / (hi - lo))
    return MapEdges(
        np.concatenate(points),
        np.concatenate(normals),
        np.concatenate(steps),
        np.concatenate(owners),
        tuple(t.tag_id for t in tag_map.tags),
        np.asarray(centres, np.float64),
        np.asarray(radii, np.float64),
        float(min(cells)),
        np.concatenate(cell_pts),
        np.concatenate(cell_vals),
        np.concatenate(cell_owner),
        np.asarray(cells, np.float64),
    )


def _tag(tag_id: int, corners_m: list[tuple[float, float]]) -> TagPlacement:
    # Pixels are not used by the edges: any four points will do.
    return TagPlacement(
        tag_id, tuple((10.0 * x, 10.0 * y) for x, y in corners_m), tuple((x, y, 0.0) for x, y in corners_m)
    )


def _multi_size_map() -> TagMap:
    """Tags of 0.4, 0.25 and 0.08 m, one rotated by 30°, one a perspective quadrilateral, ids far apart."""
    tags = [_tag(0, [(0.0, 0.0), (0.4, 0.0), (0.4, 0.4), (0.0, 0.4)])]
    tags.append(_tag(586, [(1.0, 0.0), (1.25, 0.0), (1.25, 0.25), (1.0, 0.25)]))
    c, s = np.cos(np.pi / 6), np.sin(np.pi / 6)
    square = np.array([[0.0, 0.0], [0.08, 0.0], [0.08, 0.08], [0.0, 0.08]])
    tags.append(_tag(17, [(2.0 + c * x - s * y, 1.0 + s * x + c * y) for x, y in square]))
    tags.append(_tag(300, [(0.0, 2.0), (0.5, 2.05), (0.45, 2.4), (0.02, 2.3)]))
    return TagMap(400, 300, tuple(tags))


def _assert_same(new: MapEdges, old: MapEdges) -> None:
    for field in dataclasses.fields(MapEdges):
        a, b = getattr(new, field.name), getattr(old, field.name)
        if isinstance(b, np.ndarray):
            assert a.dtype == b.dtype, field.name
            assert a.shape == b.shape, field.name
            assert np.array_equal(a, b), f"{field.name}: differs by up to {np.abs(a - b).max()}"
        else:
            assert a == b, field.name


@pytest.mark.parametrize("which", ["shipped arena", "several sizes"])
def test_edges_for_all_tags_at_once_equal_the_per_tag_loop(which: str) -> None:
    if which == "shipped arena":
        tag_map = grid_tag_map(load_arena_config(shipped_config_path("arena.yaml")))
    else:
        tag_map = _multi_size_map()
    new = MapEdges.from_tag_map(tag_map)
    _assert_same(new, _per_tag_loop(tag_map))
    assert new.tag_cell_m is not None
    assert len(np.unique(new.tag_cell_m)) > 1  # both maps mix tag sizes
    # Every tag's samples, in the map's order of tags.
    assert np.array_equal(np.unique(new.tag), np.arange(len(tag_map.tags)))
    assert np.all(np.diff(new.tag) >= 0)


def _old_render_mask(tag_map: TagMap) -> np.ndarray:
    """The mask as it was drawn before (cells warped as 1 black / 2 white, then two boolean writes)."""
    mask = np.zeros((tag_map.height_px, tag_map.width_px), np.int8)
    n = TAG36H11_CELLS
    for tag in tag_map.tags:
        cells = tag36h11_bitmap(tag.tag_id).astype(np.uint8) + 1
        src = np.array([[1.0, 9.0], [9.0, 9.0], [9.0, 1.0], [1.0, 1.0]], np.float32)
        h_edge = cv2.getPerspectiveTransform(src, np.asarray(tag.corners_px, np.float32))
        outer = cv2.perspectiveTransform(np.array([[[0.0, 0.0], [n, 0.0], [n, n], [0.0, n]]]), h_edge)[0]
        x0, y0 = max(0, int(np.floor(outer[:, 0].min()))), max(0, int(np.floor(outer[:, 1].min())))
        x1 = min(mask.shape[1], int(np.ceil(outer[:, 0].max())))
        y1 = min(mask.shape[0], int(np.ceil(outer[:, 1].max())))
        if x1 <= x0 or y1 <= y0:
            continue
        to_roi = np.array([[1, 0, -x0 - 0.5], [0, 1, -y0 - 0.5], [0, 0, 1]], np.float64)
        h = to_roi @ h_edge @ np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]], np.float64)
        warped = cv2.warpPerspective(cells, h, (x1 - x0, y1 - y0), flags=cv2.INTER_NEAREST, borderValue=0)
        roi = mask[y0:y1, x0:x1]
        roi[warped == 2] = 1
        roi[warped == 1] = -1
    return mask


def _overlapping_map() -> TagMap:
    """Tags whose quiet zones overlap, one cut by the image's edge, one tilted."""

    def px_tag(tag_id: int, corners_px: list[tuple[float, float]]) -> TagPlacement:
        return TagPlacement(tag_id, tuple(corners_px), tuple((x / 100, y / 100, 0.0) for x, y in corners_px))

    return TagMap(
        200,
        150,
        (
            px_tag(5, [(10.0, 90.0), (90.0, 90.0), (90.0, 10.0), (10.0, 10.0)]),
            px_tag(6, [(85.0, 100.0), (150.0, 95.0), (145.0, 30.0), (80.0, 35.0)]),
            px_tag(7, [(170.0, 140.0), (230.0, 140.0), (230.0, 80.0), (170.0, 80.0)]),
        ),
    )


@pytest.mark.parametrize("which", ["shipped arena", "several sizes", "overlapping"])
def test_render_mask_equals_the_boolean_writes(which: str) -> None:
    tag_map = {
        "shipped arena": lambda: grid_tag_map(load_arena_config(shipped_config_path("arena.yaml"))),
        "several sizes": _multi_size_map,
        "overlapping": _overlapping_map,
    }[which]()
    mask = tag_map.render_mask()
    assert mask.dtype == np.int8
    assert np.array_equal(mask, _old_render_mask(tag_map))
    assert set(np.unique(mask).tolist()) == {-1, 0, 1}
