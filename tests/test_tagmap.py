"""The tag map: grid layout, metre/pixel mapping, rendering checked by real AprilTag detection, layout files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import dt_apriltags
import numpy as np
import numpy.typing as npt
import pytest

from ipt.config.models import ArenaConfig
from ipt.receiver.detect.apriltag_c import free_pupil_detector
from ipt.tagmap import (
    TAG36H11_CELLS,
    TagMap,
    TagMapError,
    arena_to_pixel_matrix,
    export_map,
    grid_tag_map,
    load_layout,
    pixel_to_arena_m,
    tag36h11_bitmap,
    tag36h11_count,
)

PAPER = ArenaConfig()


@pytest.fixture(scope="module")
def paper_map() -> TagMap:
    return grid_tag_map(PAPER)


@pytest.fixture(scope="module")
def paper_image(paper_map: TagMap) -> npt.NDArray[np.uint8]:
    return paper_map.render_image()


def _detect(img: npt.NDArray[np.uint8]) -> dict[int, Any]:
    # Raw dt-apriltags output (its own pixel convention), freed in the order its C library needs.
    detector = dt_apriltags.Detector(families="tag36h11")
    try:
        dets = detector.detect(np.ascontiguousarray(img))
    finally:
        free_pupil_detector(detector)
    ids = [int(d.tag_id) for d in dets]
    assert len(ids) == len(set(ids)), "no tag is detected twice"
    return {int(d.tag_id): d for d in dets}


def _custom_arena(**tag_map: Any) -> ArenaConfig:
    return ArenaConfig.model_validate(
        {
            "projector": {"width_px": 640, "height_px": 480},
            "screen": {"width_m": 1.0, "height_m": 0.75},
            "tag_map": {"rows": 3, "cols": 4, "tag_size_px": 64, **tag_map},
        }
    )


# --- layout ----------------------------------------------------------------------------------------------


def test_grid_has_81_tags_with_ids_0_to_80(paper_map: TagMap) -> None:
    assert len(paper_map.tags) == 81
    assert [t.tag_id for t in paper_map.tags] == list(range(81))
    assert (paper_map.width_px, paper_map.height_px) == (1920, 2160)
    assert set(paper_map.by_id) == set(range(81))


def _centre_m(tm: TagMap, tag_id: int) -> npt.NDArray[np.float64]:
    c = tm.corners_m(tag_id)
    assert c is not None
    return c.mean(axis=0)


def test_id_placement(paper_map: TagMap) -> None:
    centres = np.array([_centre_m(paper_map, i) for i in range(81)])
    xmin, ymin = centres[:, 0].min(), centres[:, 1].min()
    xmax, ymax = centres[:, 0].max(), centres[:, 1].max()
    # id 0 bottom-left, 8 bottom-right, 9 one row up at the left, 80 top-right.
    assert centres[0, 0] == pytest.approx(xmin)
    assert centres[0, 1] == pytest.approx(ymin)
    assert centres[8, 0] == pytest.approx(xmax)
    assert centres[8, 1] == pytest.approx(ymin)
    assert centres[9, 0] == pytest.approx(xmin)
    assert centres[9, 1] > ymin
    assert centres[9, 1] == pytest.approx(np.sort(np.unique(centres[:, 1].round(9)))[1])
    assert centres[80, 0] == pytest.approx(xmax)
    assert centres[80, 1] == pytest.approx(ymax)
    # In pixels, the bottom row has the largest v.
    v_max = max(max(v for _, v in t.corners_px) for t in paper_map.tags)
    assert max(v for _, v in paper_map.by_id[0].corners_px) == v_max
    assert max(v for _, v in paper_map.by_id[80].corners_px) < v_max / 2
    # Ids grow left to right within a row.
    for row in range(9):
        xs = centres[row * 9 : row * 9 + 9, 0]
        assert np.all(np.diff(xs) > 0)
        assert np.ptp(centres[row * 9 : row * 9 + 9, 1]) == pytest.approx(0.0, abs=1e-12)


def test_tags_are_square_with_the_configured_size(paper_map: TagMap) -> None:
    s = PAPER.tag_map.tag_size_px
    for t in paper_map.tags:
        px = np.asarray(t.corners_px)
        assert np.ptp(px[:, 0]) == s
        assert np.ptp(px[:, 1]) == s
        assert np.all(px >= 0)
        assert np.all(px[:, 0] <= 1920)
        assert np.all(px[:, 1] <= 2160)


def test_corners_symmetric_about_origin(paper_map: TagMap) -> None:
    all_m = np.concatenate([np.asarray(t.corners_m) for t in paper_map.tags])
    px_m = PAPER.screen.width_m / PAPER.projector.width_px
    np.testing.assert_allclose(all_m.mean(axis=0), 0.0, atol=px_m / 2)
    np.testing.assert_allclose(all_m[:, 2], 0.0)
    # The outermost corners are mirror images of each other.
    assert all_m[:, 0].min() == pytest.approx(-all_m[:, 0].max(), abs=px_m)
    assert all_m[:, 1].min() == pytest.approx(-all_m[:, 1].max(), abs=px_m)


def test_corner_order_bl_br_tr_tl(paper_map: TagMap) -> None:
    for t in paper_map.tags:
        m = np.asarray(t.corners_m)[:, :2]
        bl, br, tr, tl = m
        assert bl[0] < br[0]
        assert bl[1] == pytest.approx(br[1])
        assert tr[1] > br[1]
        assert tr[0] == pytest.approx(br[0])
        assert tl[0] < tr[0]
        assert tl[1] == pytest.approx(tr[1])
        # Counter-clockwise seen from above: positive shoelace area.
        x, y = m[:, 0], m[:, 1]
        area = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
        assert area > 0
        px = np.asarray(t.corners_px)
        assert px[0, 1] > px[3, 1], "bottom corners have the larger v"
        assert px[1, 0] > px[0, 0]


def test_metre_pixel_mapping_are_inverses() -> None:
    for arena in (PAPER, _custom_arena()):
        a = arena_to_pixel_matrix(arena)
        w, h = arena.projector.width_px, arena.projector.height_px
        assert pixel_to_arena_m(arena, 0.0, 0.0) == pytest.approx(
            (-arena.screen.width_m / 2, arena.screen.height_m / 2, 0.0)
        )
        assert pixel_to_arena_m(arena, w, h) == pytest.approx((arena.screen.width_m / 2, -arena.screen.height_m / 2, 0))
        assert pixel_to_arena_m(arena, w / 2, h / 2) == pytest.approx((0.0, 0.0, 0.0))
        rng = np.random.default_rng(1)
        for u, v in rng.uniform([-100, -100], [w + 100, h + 100], (50, 2)):
            x, y, z = pixel_to_arena_m(arena, float(u), float(v))
            assert z == 0.0
            back = a @ np.array([x, y, 1.0])
            np.testing.assert_allclose(back[:2] / back[2], [u, v], atol=1e-9)
        for x, y in rng.uniform(-2, 2, (50, 2)):
            uvw = a @ np.array([x, y, 1.0])
            got = pixel_to_arena_m(arena, float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2]))
            np.testing.assert_allclose(got, [x, y, 0.0], atol=1e-12)


def test_layout_corners_m_follow_from_corners_px(paper_map: TagMap) -> None:
    a = arena_to_pixel_matrix(PAPER)
    for t in paper_map.tags:
        m = np.asarray(t.corners_m)
        uv = (a @ np.column_stack([m[:, :2], np.ones(4)]).T).T
        np.testing.assert_allclose(uv[:, :2], np.asarray(t.corners_px), atol=1e-9)


# --- rendering and detection -----------------------------------------------------------------------------


def test_rendered_map_detects_every_tag_at_its_corners(paper_map: TagMap, paper_image: npt.NDArray[np.uint8]) -> None:
    found = _detect(paper_image)
    assert set(found) == set(range(81))
    for tag_id, d in found.items():
        assert d.hamming == 0
        corners = np.asarray(d.corners, dtype=np.float64)
        expected = np.asarray(paper_map.by_id[tag_id].corners_px)
        assert np.abs(corners - expected).max() < 0.5, f"tag {tag_id}: {corners} vs {expected}"


def test_mask_values_and_regions(paper_map: TagMap) -> None:
    mask = paper_map.render_mask()
    assert mask.dtype == np.int8
    assert mask.shape == (2160, 1920)
    assert set(np.unique(mask).tolist()) == {-1, 0, 1}
    s = PAPER.tag_map.tag_size_px
    cell = s // 8
    for t in paper_map.tags:
        left, top = int(t.corners_px[3][0]), int(t.corners_px[3][1])
        region = mask[top - cell : top + s + cell, left - cell : left + s + cell]
        assert (region == 1).any()
        assert (region == -1).any()
        # One-cell black border just inside the corners, one-cell white quiet zone just outside.
        border = np.ones((s, s), bool)
        border[cell:-cell, cell:-cell] = False
        assert np.all(mask[top : top + s, left : left + s][border] == -1), t.tag_id
        quiet = np.ones((s + 2 * cell, s + 2 * cell), bool)
        quiet[cell:-cell, cell:-cell] = False
        assert np.all(region[quiet] == 1), t.tag_id
        # Nothing is drawn in the ring of pixels around the quiet zone.
        ring = mask[top - cell - 1 : top + s + cell + 1, left - cell - 1 : left + s + cell + 1]
        outer = np.ones(ring.shape, bool)
        outer[1:-1, 1:-1] = False
        assert np.all(ring[outer] == 0), t.tag_id
    # Each tag covers exactly its quiet-zone square: the total touched area adds up.
    assert int(np.count_nonzero(mask)) == 81 * (s + 2 * cell) ** 2


def test_render_image_matches_mask(paper_map: TagMap, paper_image: npt.NDArray[np.uint8]) -> None:
    mask = paper_map.render_mask()
    assert paper_image.dtype == np.uint8
    assert np.array_equal(paper_image == 255, mask == 1)
    assert np.array_equal(paper_image == 0, mask == -1)
    assert np.array_equal(paper_image == 127, mask == 0)


@pytest.mark.parametrize("tag_id", [0, 1, 80, 586])
def test_bitmap_rings(tag_id: int) -> None:
    cells = tag36h11_bitmap(tag_id)
    assert cells.shape == (TAG36H11_CELLS, TAG36H11_CELLS) == (10, 10)
    assert set(np.unique(cells).tolist()) <= {0, 1}
    ring1 = np.ones((10, 10), bool)
    ring1[1:-1, 1:-1] = False
    assert np.all(cells[ring1] == 1), "white outer ring"
    ring2 = np.zeros((10, 10), bool)
    ring2[1:-1, 1:-1] = True
    ring2[2:-2, 2:-2] = False
    assert np.all(cells[ring2] == 0), "black 8x8 border ring"
    assert not cells.flags.writeable


def test_bitmaps_are_distinct_and_count() -> None:
    assert tag36h11_count() == 587
    payloads = {tag36h11_bitmap(i)[2:-2, 2:-2].tobytes() for i in range(100)}
    assert len(payloads) == 100


@pytest.mark.parametrize("bad", [-1, 587])
def test_bitmap_bad_id(bad: int) -> None:
    with pytest.raises(TagMapError, match=r"0\.\.586"):
        tag36h11_bitmap(bad)


def test_bitmap_renders_and_decodes_as_its_id() -> None:
    # Each bitmap scaled up and padded decodes to its own id in the detector's canonical orientation.
    for tag_id in (0, 7, 42, 300, 586):
        cells = tag36h11_bitmap(tag_id)
        img = np.full((140, 140), 127, np.uint8)
        img[20:120, 20:120] = np.kron(cells, np.ones((10, 10), np.uint8)) * 255
        found = _detect(img)
        assert set(found) == {tag_id}
        corners = np.asarray(found[tag_id].corners)
        # Border corners: BL, BR, TR, TL in image coordinates.
        np.testing.assert_allclose(corners, [[30, 110], [110, 110], [110, 30], [30, 30]], atol=0.5)


@pytest.mark.parametrize("first_id", [0, 100])
def test_custom_arena_renders_and_detects(first_id: int) -> None:
    arena = _custom_arena(first_id=first_id)
    tm = grid_tag_map(arena)
    assert [t.tag_id for t in tm.tags] == list(range(first_id, first_id + 12))
    img = tm.render_image()
    assert img.shape == (480, 640)
    found = _detect(img)
    assert set(found) == set(range(first_id, first_id + 12))
    for tag_id, d in found.items():
        assert d.hamming == 0
        assert np.abs(np.asarray(d.corners) - np.asarray(tm.by_id[tag_id].corners_px)).max() < 0.5
    c0 = tm.corners_m(first_id)
    assert c0 is not None
    assert c0[:, 0].max() < 0, "first tag is bottom-left"
    assert c0[:, 1].max() < 0
    assert tm.corners_m(first_id + 12) is None


# --- export and load -------------------------------------------------------------------------------------


def test_export_and_load_round_trip(tmp_path: Path, paper_map: TagMap, paper_image: npt.NDArray[np.uint8]) -> None:
    image, layout = tmp_path / "map.png", tmp_path / "layout.json"
    export_map(paper_map, image, layout)
    back = load_layout(layout)
    assert back == paper_map
    assert back.by_id[40].corners_m == paper_map.by_id[40].corners_m
    png = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    assert png is not None
    assert png.dtype == np.uint8, "8-bit"
    assert png.shape == (2160, 1920), "single channel at projector size"
    assert set(np.unique(png).tolist()) == {0, 127, 255}
    assert np.array_equal(png, paper_image)
    assert image.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["layout.json", "map.png"], "no temporary files left"


def test_export_overwrites_existing_files(tmp_path: Path) -> None:
    tm = grid_tag_map(_custom_arena())
    image, layout = tmp_path / "m.png", tmp_path / "l.json"
    image.write_text("old")
    layout.write_text("old")
    export_map(tm, image, layout)
    assert load_layout(layout) == tm
    png = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    assert png is not None
    assert png.shape == (480, 640)


def _layout_file(tmp_path: Path, mutate: Any) -> Path:
    data = grid_tag_map(_custom_arena()).layout_dict()
    mutate(data)
    path = tmp_path / "broken-layout.json"
    path.write_text(json.dumps(data), encoding="utf-8")
    return path


def _set(data: dict[str, Any], *path_and_value: Any) -> None:
    """``_set(d, "tags", 0, "id", 5)`` sets ``d["tags"][0]["id"] = 5``."""
    *keys, value = path_and_value
    node: Any = data
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value


@pytest.mark.parametrize(
    ("mutate", "fragment"),
    [
        (lambda d: _set(d, "tags", 1, "id", 0), "duplicate id 0"),
        (lambda d: d["tags"][2].pop("corners_px"), "tags[2]"),
        (lambda d: d["tags"][3].pop("corners_m"), "tags[3]"),
        (lambda d: _set(d, "tags", 0, "corners_px", d["tags"][0]["corners_px"][:3]), "4 corners"),
        (lambda d: _set(d, "tags", 0, "corners_px", 1, 0, "ten"), "tags[0].corners_px"),
        (lambda d: _set(d, "tags", 0, "corners_m", 1, 2, None), "tags[0].corners_m"),
        (lambda d: _set(d, "tags", 0, "corners_m", 1, [0.0, 0.0]), "tags[0].corners_m"),
        (lambda d: _set(d, "tags", 0, "corners_px", 0, 0, True), "tags[0].corners_px"),
        (lambda d: _set(d, "tags", 0, "id", 587), "tags[0]"),
        (lambda d: _set(d, "tags", 0, "id", "0"), "tags[0]"),
        (lambda d: _set(d, "tags", 0, "id", True), "tags[0]"),
        (lambda d: _set(d, "tags", []), "tags"),
        (lambda d: d.pop("tags"), "tags"),
        (lambda d: d.pop("projector"), "projector"),
        (lambda d: _set(d, "projector", "width_px", -5), "projector"),
        (lambda d: _set(d, "tags", 0, 7), "tags[0]"),
    ],
)
def test_bad_layouts(tmp_path: Path, mutate: Any, fragment: str) -> None:
    path = _layout_file(tmp_path, mutate)
    with pytest.raises(TagMapError) as info:
        load_layout(path)
    msg = str(info.value)
    assert msg.startswith(str(path) + ":"), msg
    assert fragment in msg


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_layout_non_finite_values(tmp_path: Path, value: float) -> None:
    path = _layout_file(tmp_path, lambda d: _set(d, "tags", 1, "corners_px", 2, 1, value))
    assert "Infinity" in path.read_text() or "NaN" in path.read_text()
    with pytest.raises(TagMapError, match=r"broken-layout\.json: tags\[1\]\.corners_px"):
        load_layout(path)


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("missing.json", None),
        ("syntax.json", '{"projector": {"width_px": 640,'),
        ("empty.json", ""),
        ("list.json", "[1, 2]"),
        ("binary.json", b"\xff\xfe\x00garbage"),
    ],
)
def test_unreadable_layout_files(tmp_path: Path, name: str, text: str | bytes | None) -> None:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    elif text is not None:
        path.write_text(text, encoding="utf-8")
    with pytest.raises(TagMapError) as info:
        load_layout(path)
    assert str(info.value).startswith(str(path) + ":")


def test_layout_huge_integer(tmp_path: Path) -> None:
    path = _layout_file(tmp_path, lambda d: _set(d, "tags", 0, "corners_px", 0, 0, 10**400))
    with pytest.raises(TagMapError, match="broken-layout"):
        load_layout(path)


def test_layout_boolean_projector_size(tmp_path: Path) -> None:
    path = _layout_file(tmp_path, lambda d: _set(d, "projector", "width_px", True))
    with pytest.raises(TagMapError, match="projector"):
        load_layout(path)
