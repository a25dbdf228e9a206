"""The tag map: which tag36h11 tag sits where, in projector pixels and in arena metres.

Shared by both sides: the sender draws the modulation mask from it, the receiver looks up the arena
corners of each detected id from the same code and the same arena config.

Coordinates:
- projector pixels are continuous with the origin at the top-left *corner* of the top-left pixel, so
  pixel (i, j) covers [i, i+1) x [j, j+1) (the convention AprilTag reports corners in);
- arena metres are ENU with the origin at the centre of the projected image, y towards the top edge,
  projector pixels mapping to them by the uniform scale of ``screen``, or, where the arena was measured
  (``floor:``, ``ipt calibrate arena --points``), by the measured homography in the user's floor frame
  (:func:`pixel_to_floor_matrix`). Every part maps through the functions here, so they all agree.

Corner order, in both lists of a tag: bottom-left, bottom-right, top-right, top-left as the tag is seen
in the projector image: counter-clockwise seen from above in the arena, and the order in which
AprilTag 3 (dt-apriltags) reports the corners of a tag it decodes.
"""

from __future__ import annotations

import ctypes
import functools
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.models import ArenaConfig, LandingPadConfig, finite_float
from ipt.errors import IptError
from ipt.fileio import WriteError, output_group, read_text_file, write_text_atomic
from ipt.imageio import write_image

TAG36H11_CELLS = 10
"""Cells across a rendered tag36h11 tag: a one-cell white quiet zone around the 8-cell black border."""
_BORDER_CELLS = 8


MAX_PROJECTOR_PX = 16384
"""Largest projector width or height a layout may state (the limit of the arena configuration too)."""


class TagMapError(IptError):
    """A tag layout is invalid or cannot be read."""


class _ApriltagFamily(ctypes.Structure):
    """``apriltag_family_t`` of the AprilTag 3 C library (public header ``apriltag.h``)."""

    _fields_ = [
        ("ncodes", ctypes.c_uint32),
        ("codes", ctypes.POINTER(ctypes.c_uint64)),
        ("width_at_border", ctypes.c_int),
        ("total_width", ctypes.c_int),
        ("reversed_border", ctypes.c_bool),
        ("nbits", ctypes.c_uint32),
        ("bit_x", ctypes.POINTER(ctypes.c_uint32)),
        ("bit_y", ctypes.POINTER(ctypes.c_uint32)),
        ("h", ctypes.c_int32),
        ("name", ctypes.c_char_p),
    ]


@functools.cache
def _tag36h11_family() -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
    """The codes and bit positions of tag36h11, read from the library the detector itself uses.

    Taking them from the ``libapriltag`` bundled with the detector's binding (dt-apriltags: in its package
    folder; pupil-apriltags had it in ``lib*/``) guarantees that the tags we draw are the ones the detector
    decodes, in its canonical orientation.
    """
    import dt_apriltags

    pkg = Path(dt_apriltags.__file__).parent
    patterns = ("libapriltag.so*", "*apriltag*.dylib", "*apriltag*.dll", "lib*/libapriltag.so*")
    candidates = [found for pattern in patterns for found in sorted(pkg.glob(pattern))]
    if not candidates:
        raise TagMapError(f"cannot find the AprilTag library inside {pkg}")
    lib = ctypes.CDLL(str(candidates[0]))
    create = lib.tag36h11_create
    create.restype = ctypes.POINTER(_ApriltagFamily)
    fam = create().contents
    if fam.nbits != 36 or fam.width_at_border != _BORDER_CELLS or fam.total_width != TAG36H11_CELLS:
        raise TagMapError("unexpected tag36h11 family layout in the AprilTag library")
    codes = tuple(int(fam.codes[i]) for i in range(fam.ncodes))
    bit_x = tuple(int(fam.bit_x[i]) for i in range(fam.nbits))
    bit_y = tuple(int(fam.bit_y[i]) for i in range(fam.nbits))
    return codes, bit_x, bit_y


def tag36h11_count() -> int:
    """Number of ids in tag36h11 (587)."""
    return len(_tag36h11_family()[0])


@functools.cache
def tag36h11_bitmap(tag_id: int) -> npt.NDArray[np.uint8]:
    """The 10x10 cell image of tag ``tag_id``: 1 for white cells, 0 for black, quiet zone included."""
    codes, bit_x, bit_y = _tag36h11_family()
    if not 0 <= tag_id < len(codes):
        raise TagMapError(f"tag36h11 has ids 0..{len(codes) - 1}, not {tag_id}")
    cells = np.zeros((TAG36H11_CELLS, TAG36H11_CELLS), np.uint8)
    cells[0, :] = cells[-1, :] = cells[:, 0] = cells[:, -1] = 1
    code, nbits = codes[tag_id], len(bit_x)
    offset = (TAG36H11_CELLS - _BORDER_CELLS) // 2
    for i in range(nbits):
        if code >> (nbits - 1 - i) & 1:
            cells[bit_y[i] + offset, bit_x[i] + offset] = 1
    cells.setflags(write=False)
    return cells


@dataclass(frozen=True)
class TagPlacement:
    """One tag of the map: its id and its four border corners (see the module doc for the order)."""

    tag_id: int
    corners_px: tuple[tuple[float, float], ...]
    corners_m: tuple[tuple[float, float, float], ...]


@dataclass(frozen=True)
class TagMap:
    """All tags of an arena, with the projector size they are drawn for."""

    width_px: int
    height_px: int
    tags: tuple[TagPlacement, ...]

    @functools.cached_property
    def by_id(self) -> dict[int, TagPlacement]:
        """Tags keyed by id."""
        return {t.tag_id: t for t in self.tags}

    def corners_m(self, tag_id: int) -> npt.NDArray[np.float64] | None:
        """The 4x3 arena corners of ``tag_id``, or None if the id is not in the map."""
        t = self.by_id.get(tag_id)
        return None if t is None else np.asarray(t.corners_m, dtype=np.float64)

    def render_mask(self) -> npt.NDArray[np.int8]:
        """The modulation mask T_mask: +1 on white tag cells, -1 on black, 0 where untouched."""
        mask = np.zeros((self.height_px, self.width_px), np.int8)
        for tag in self.tags:
            _draw_tag(mask, tag)
        return mask

    def render_image(self) -> npt.NDArray[np.uint8]:
        """The exported map image: 255 where the mask is +1, 0 where -1, 127 elsewhere."""
        mask = self.render_mask()
        img = np.full(mask.shape, 127, np.uint8)
        img[mask > 0] = 255
        img[mask < 0] = 0
        return img

    def layout_json(self) -> str:
        """The exported layout file's text (what :func:`export_map` writes and the map hash digests)."""
        return json.dumps(self.layout_dict(), indent=1) + "\n"

    def layout_dict(self) -> dict[str, Any]:
        """The layout in the exported JSON shape."""
        return {
            "projector": {"width_px": self.width_px, "height_px": self.height_px},
            "tags": [
                {
                    "id": t.tag_id,
                    "corners_px": [list(c) for c in t.corners_px],
                    "corners_m": [list(c) for c in t.corners_m],
                }
                for t in self.tags
            ],
        }


def _draw_tag(mask: npt.NDArray[np.int8], tag: TagPlacement) -> None:
    """Draw one tag (quiet zone included) into ``mask`` by nearest-neighbour warping of its cells."""
    # The mask's own values as bytes: 1 white, 255 (-1 as int8) black, 0 outside the tag (left as it was).
    cells = np.where(tag36h11_bitmap(tag.tag_id) > 0, np.uint8(1), np.uint8(255))
    lo, hi = (TAG36H11_CELLS - _BORDER_CELLS) / 2, (TAG36H11_CELLS + _BORDER_CELLS) / 2
    src = np.array([[lo, hi], [hi, hi], [hi, lo], [lo, lo]], np.float64)  # BL, BR, TR, TL in cell units
    dst = np.asarray(tag.corners_px, np.float64)
    h_edge = cv2.getPerspectiveTransform(src.astype(np.float32), dst.astype(np.float32))
    # Outer quiet-zone outline in projector pixels, to bound the region we touch.
    outer = np.array([[0, 0], [TAG36H11_CELLS, 0], [TAG36H11_CELLS, TAG36H11_CELLS], [0, TAG36H11_CELLS]], float)
    outer_px = cv2.perspectiveTransform(outer[None], h_edge)[0]
    x0 = max(0, math.floor(outer_px[:, 0].min()))
    y0 = max(0, math.floor(outer_px[:, 1].min()))
    x1 = min(mask.shape[1], math.ceil(outer_px[:, 0].max()))
    y1 = min(mask.shape[0], math.ceil(outer_px[:, 1].max()))
    if x1 <= x0 or y1 <= y0:
        return
    # warpPerspective samples at pixel centres (i + 0.5 in edge coordinates): shift both ends by half a pixel.
    to_roi = np.array([[1, 0, -x0 - 0.5], [0, 1, -y0 - 0.5], [0, 0, 1]], np.float64)
    cell_centre_to_edge = np.array([[1, 0, 0.5], [0, 1, 0.5], [0, 0, 1]], np.float64)
    h = to_roi @ h_edge @ cell_centre_to_edge
    warped = cv2.warpPerspective(
        cells, h, (x1 - x0, y1 - y0), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    )
    np.copyto(mask[y0:y1, x0:x1], warped.view(np.int8), where=warped != 0)


def tile_of(arena: ArenaConfig, u_px: float, v_px: float) -> int | None:
    """Index of the projector tile (``arena.projectors``) whose part of the canvas holds (u, v), or None for
    a one-projector arena (or a point outside every tile)."""
    for n, tile in enumerate(arena.projectors or ()):
        if tile.contains(u_px, v_px):
            return n
    return None


def _measured(arena: ArenaConfig, tile: int | None) -> tuple[tuple[float, ...], ...] | None:
    """The measured homography that maps ``tile`` (or the one projector), None for the uniform layout."""
    if arena.projectors is not None:
        return None if tile is None else arena.projectors[tile].pixel_to_floor
    return arena.floor.pixel_to_floor if arena.floor is not None else None


def pixel_to_floor_matrix(arena: ArenaConfig, tile: int | None = None) -> npt.NDArray[np.float64]:
    """3x3 homography taking homogeneous projector pixels (u, v, 1), edge origin, to arena floor metres
    (x_m, y_m, 1): the measured one (``floor.pixel_to_floor``, or tile ``tile``'s of ``projectors``) if the
    arena has it, else the uniform scale of ``screen``. The one mapping every part uses (through this
    module's functions)."""
    h = _measured(arena, tile)
    if h is not None:
        return np.array(h, np.float64)
    sx = arena.screen.width_m / arena.projector.width_px
    sy = arena.screen.height_m / arena.projector.height_px
    w2, h2 = arena.projector.width_px / 2, arena.projector.height_px / 2
    return np.array([[sx, 0, -w2 * sx], [0, -sy, h2 * sy], [0, 0, 1]])


def pixel_to_arena_m(
    arena: ArenaConfig, u_px: float, v_px: float, tile: int | None = None
) -> tuple[float, float, float]:
    """Arena ENU metres (z = 0, the floor) of the projector point (u, v) in edge-origin pixels (of the canvas;
    with several projectors, through tile ``tile``'s mapping, by default the tile holding the point)."""
    if arena.projectors is not None and tile is None:
        tile = tile_of(arena, u_px, v_px)
    h = _measured(arena, tile)
    if h is not None:
        (a, b, c), (d, e, f), (g, i, k) = h
        w = g * u_px + i * v_px + k
        return ((a * u_px + b * v_px + c) / w, (d * u_px + e * v_px + f) / w, 0.0)
    sx = arena.screen.width_m / arena.projector.width_px
    sy = arena.screen.height_m / arena.projector.height_px
    return ((u_px - arena.projector.width_px / 2) * sx, (arena.projector.height_px / 2 - v_px) * sy, 0.0)


def arena_to_pixel_matrix(arena: ArenaConfig, tile: int | None = None) -> npt.NDArray[np.float64]:
    """3x3 matrix taking homogeneous arena floor points (x_m, y_m, 1) to projector pixels (edge origin): the
    inverse of :func:`pixel_to_floor_matrix`."""
    h = _measured(arena, tile)
    if h is not None:
        return np.asarray(np.linalg.inv(np.array(h, np.float64)), np.float64)
    sx = arena.screen.width_m / arena.projector.width_px
    sy = arena.screen.height_m / arena.projector.height_px
    return np.array([[1 / sx, 0, arena.projector.width_px / 2], [0, -1 / sy, arena.projector.height_px / 2], [0, 0, 1]])


def pixel_to_arena(tag_map: TagMap) -> npt.NDArray[np.float64]:
    """3x3 homography from projector pixels (edge origin) to arena floor metres, from the map's own tags
    (least squares over every corner: exact for a grid, and for a map whose tags were measured)."""
    px = np.concatenate([np.asarray(t.corners_px, np.float64) for t in tag_map.tags])
    m = np.concatenate([np.asarray(t.corners_m, np.float64)[:, :2] for t in tag_map.tags])
    if len(tag_map.tags) == 1:  # four points: the homography is exact
        return np.asarray(cv2.getPerspectiveTransform(px.astype(np.float32), m.astype(np.float32)), np.float64)
    h, _ = cv2.findHomography(px, m, 0)
    return np.asarray(h, np.float64)


def _square_tag(arena: ArenaConfig, tag_id: int, left: float, top: float, s: float) -> TagPlacement:
    """The tag whose black border square has its top-left corner at (left, top) projector px, side ``s``."""
    px = ((left, top + s), (left + s, top + s), (left + s, top), (left, top))
    corners_px = tuple((float(u), float(v)) for u, v in px)
    # One tile's mapping for all four corners (the tile holding the tag's centre), so a tag stays a square.
    tile = tile_of(arena, left + s / 2, top + s / 2)
    corners_m = tuple(pixel_to_arena_m(arena, u, v, tile) for u, v in corners_px)
    return TagPlacement(tag_id, corners_px, corners_m)


def grid_tag_map(arena: ArenaConfig) -> TagMap:
    """The arena config's map: the evenly spaced grid (ids left to right, then bottom to top; with several
    projectors, the ids of tags that would cross a seam are left out), and the landing pads' small tags
    (:func:`pad_tags`) in the grid cells their squares reach into."""
    tm, pr = arena.tag_map, arena.projector
    pitch_x = pr.width_px / tm.cols
    pitch_y = pr.height_px / tm.rows
    s = tm.tag_size_px
    tags = []
    for row in range(tm.rows):  # row 0 is the bottom row
        for col in range(tm.cols):
            left = round((col + 0.5) * pitch_x - s / 2)
            top = round(pr.height_px - (row + 0.5) * pitch_y - s / 2)
            if arena.projectors is not None:
                # Kept out of the seams: a tag (with its quiet zone) drawn by two projectors that disagree on
                # the floor would be a broken tag.
                q = s // 8
                tile = tile_of(arena, left + s / 2, top + s / 2)
                box = [(u, v) for u in (left - q, left + s + q) for v in (top - q, top + s + q)]
                if tile is None or not all(arena.projectors[tile].contains(u, v) for u, v in box):
                    continue
            tags.append(_square_tag(arena, tm.first_id + row * tm.cols + col, left, top, s))
    small = pad_tags(arena)
    if small:
        gone = set()
        for pad in tm.pads:
            (col0, col1, row0, row1), _ = pad_grid(arena, pad)
            gone |= {tm.first_id + row * tm.cols + col for row in range(row0, row1) for col in range(col0, col1)}
        tags = [t for t in tags if t.tag_id not in gone] + [t for group in small for t in group]
    return TagMap(pr.width_px, pr.height_px, tuple(tags))


class PadGrid(NamedTuple):
    """Where the small tags of a landing pad go (:func:`pad_grid`)."""

    cells: tuple[int, int, int, int]
    """The grid's cells whose big tags they replace: (col0, col1, row0, row1), half-open ranges, rows counted
    bottom to top; every cell the pad's square reaches into."""
    block: tuple[int, int, float, float]
    """(cols, rows, left_px, top_px) of the small tags that fill those cells, the block centred in them;
    left/top are the projector pixel edges of its top-left quiet zone."""


def pad_grid(arena: ArenaConfig, pad: LandingPadConfig) -> PadGrid:
    """Where the small tags of ``pad`` go in the map of ``arena``: the cells and the block of small tags
    (:class:`PadGrid`), laid out on the uniform scale of ``screen`` (the projector's pixels; a measured
    ``floor:`` moves the tags' metres, not their pixels)."""
    pr, sc, tm = arena.projector, arena.screen, arena.tag_map
    px_per_m_x, px_per_m_y = pr.width_px / sc.width_m, pr.height_px / sc.height_m
    pitch_x, pitch_y = pr.width_px / tm.cols, pr.height_px / tm.rows
    half = pad.size_m / 2
    u0 = pr.width_px / 2 + (pad.centre_m[0] - half) * px_per_m_x
    u1 = pr.width_px / 2 + (pad.centre_m[0] + half) * px_per_m_x
    y0 = pr.height_px / 2 + (pad.centre_m[1] - half) * px_per_m_y  # pixels up from the bottom edge
    y1 = pr.height_px / 2 + (pad.centre_m[1] + half) * px_per_m_y
    col0, col1 = max(0, math.floor(u0 / pitch_x)), min(tm.cols, math.ceil(u1 / pitch_x))
    row0, row1 = max(0, math.floor(y0 / pitch_y)), min(tm.rows, math.ceil(y1 / pitch_y))
    pitch = pad.tag_size_px * 10 // 8 + pad.gap_px
    hole_w, hole_h = (col1 - col0) * pitch_x, (row1 - row0) * pitch_y
    cols, rows = int((hole_w - pad.gap_px) // pitch), int((hole_h - pad.gap_px) // pitch)
    block_w, block_h = cols * pitch - pad.gap_px, rows * pitch - pad.gap_px
    left = round(col0 * pitch_x + (hole_w - block_w) / 2)
    top = round(pr.height_px - row1 * pitch_y + (hole_h - block_h) / 2)
    return PadGrid((col0, col1, row0, row1), (max(cols, 0), max(rows, 0), float(left), float(top)))


def pads_problem(arena: ArenaConfig) -> str | None:
    """What keeps the landing pads of ``arena`` from being laid out, or None: a pad in whose grid cells not
    one of its small tags fits, or more tags in all than tag36h11 has ids. (The arena config itself checks
    what it describes: every pad on the screen, no two overlapping, their names and tag sizes.)"""
    tm = arena.tag_map
    n_small = 0
    for pad in tm.pads:
        cols, rows, _, _ = pad_grid(arena, pad).block
        if min(cols, rows) < 1:
            return f"landing pad '{pad.name}': not one of its tags fits in the grid cells it covers"
        n_small += cols * rows
    if n_small and tm.first_id + tm.rows * tm.cols + n_small > 587:
        return f"tag36h11 has 587 ids: the grid and the landing pads' {n_small} small tags need more"
    return None


def pad_tags(arena: ArenaConfig) -> list[tuple[TagPlacement, ...]]:
    """The small tags of each landing pad of the arena config: rows bottom to top, left to right, ids
    counting on from the grid's last. Raises :class:`TagMapError` where the pads cannot be laid out
    (:func:`pads_problem`)."""
    problem = pads_problem(arena)
    if problem is not None:
        raise TagMapError(f"arena tag_map.pads: {problem}")
    tm = arena.tag_map
    next_id = tm.first_id + tm.rows * tm.cols
    out = []
    for pad in tm.pads:
        _, (cols, rows, left0, top0) = pad_grid(arena, pad)
        s = pad.tag_size_px
        quiet = s // 8
        pitch = s + 2 * quiet + pad.gap_px
        bottom0 = top0 + rows * pitch - pad.gap_px  # the block's bottom edge
        group = []
        for row in range(rows):
            for col in range(cols):
                top = bottom0 - (row + 1) * pitch + pad.gap_px + quiet
                group.append(_square_tag(arena, next_id, left0 + col * pitch + quiet, top, s))
                next_id += 1
        out.append(tuple(group))
    return out


def _outer_px(tag: TagPlacement) -> npt.NDArray[np.float64]:
    """The four corners of ``tag``'s quiet zone in projector pixels (its border square grown by a cell)."""
    c = np.asarray(tag.corners_px, np.float64)
    centre = c.mean(axis=0)
    return np.asarray(centre + (c - centre) * (TAG36H11_CELLS / _BORDER_CELLS), np.float64)


def export_map(tag_map: TagMap, image_path: str | Path, layout_path: str | Path) -> None:
    """Write the map image (8-bit grey PNG at projector resolution) and the layout JSON, atomically.

    Both appear together or neither does. Raises :class:`TagMapError` naming the path when one cannot be
    written (no such folder, a folder in the way, no permission, a full or read-only disk).
    """
    img = tag_map.render_image()
    try:
        with output_group():  # both files, or neither
            write_image(image_path, img, TagMapError, suffix=".png")  # lossless, whatever the name says
            write_text_atomic(layout_path, tag_map.layout_json())
    except WriteError as exc:
        raise TagMapError(str(exc)) from None


def _float_list(path: Path, where: str, value: Any, n: int) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n:
        raise TagMapError(f"{path}: {where}: expected a list of {n} numbers")
    out = []
    for v in value:
        number = finite_float(v)
        if number is None:
            raise TagMapError(f"{path}: {where}: expected finite numbers, got {v!r:.40}")
        out.append(number)
    return tuple(out)


def load_layout(path: str | Path) -> TagMap:
    """Read a layout JSON (the shape :func:`export_map` writes) and check it thoroughly."""
    p = Path(path)
    text = read_text_file(p, TagMapError, "a layout JSON file")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise TagMapError(f"{p}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    except RecursionError:
        raise TagMapError(f"{p}: not a layout: nested too deeply") from None
    except ValueError:  # an integer of more digits than Python converts (sys.get_int_max_str_digits)
        raise TagMapError(f"{p}: not a layout: a number has too many digits") from None
    if not isinstance(data, dict) or not isinstance(data.get("projector"), dict):
        raise TagMapError(f"{p}: expected an object with 'projector' and 'tags'")
    proj = data["projector"]
    w, h = proj.get("width_px"), proj.get("height_px")
    if (
        isinstance(w, bool)
        or isinstance(h, bool)
        or not isinstance(w, int)
        or not isinstance(h, int)
        or not 0 < w <= MAX_PROJECTOR_PX
        or not 0 < h <= MAX_PROJECTOR_PX
    ):
        raise TagMapError(f"{p}: projector: width_px and height_px must be integers in 1..{MAX_PROJECTOR_PX}")
    raw_tags = data.get("tags")
    if not isinstance(raw_tags, list) or not raw_tags:
        raise TagMapError(f"{p}: tags: expected a non-empty list")
    seen: set[int] = set()
    tags = []
    n_ids = tag36h11_count()
    for i, t in enumerate(raw_tags):
        where = f"tags[{i}]"
        if not isinstance(t, dict):
            raise TagMapError(f"{p}: {where}: expected an object")
        tid = t.get("id")
        if isinstance(tid, bool) or not isinstance(tid, int) or not 0 <= tid < n_ids:
            raise TagMapError(f"{p}: {where}: id must be an integer in 0..{n_ids - 1}")
        if tid in seen:
            raise TagMapError(f"{p}: {where}: duplicate id {tid}")
        seen.add(tid)
        cpx, cm = t.get("corners_px"), t.get("corners_m")
        if not isinstance(cpx, list) or len(cpx) != 4 or not isinstance(cm, list) or len(cm) != 4:
            raise TagMapError(f"{p}: {where}: corners_px and corners_m must each list 4 corners")
        corners_px = tuple(_float_list(p, f"{where}.corners_px", c, 2) for c in cpx)
        corners_m = tuple(_float_list(p, f"{where}.corners_m", c, 3) for c in cm)
        tags.append(TagPlacement(tid, corners_px, corners_m))  # type: ignore[arg-type]
    tm = TagMap(w, h, tuple(tags))
    problem = layout_problem(tm)
    if problem is not None:
        raise TagMapError(f"{p}: {problem}")
    return tm


MIN_BIT_PX = 8
"""Fewest projector pixels per bit (code cell) a tag of a map may have (``MIN_TAG_SIZE_PX`` / 8)."""


def layout_problem(tag_map: TagMap) -> str | None:
    """What makes ``tag_map`` undrawable or undecodable, or None: a tag off the projector image, a tag
    with fewer than :data:`MIN_BIT_PX` projector pixels per bit, or two tags (quiet zones included) that
    overlap."""
    tags = tag_map.tags
    outers = [_outer_px(t) for t in tags]
    for t, outer in zip(tags, outers, strict=True):
        c = np.asarray(t.corners_px, np.float64)
        side = float(np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1).min())
        if side < MIN_BIT_PX * _BORDER_CELLS:
            return (
                f"tag {t.tag_id} has {side / _BORDER_CELLS:.1f} projector px per bit, fewer than {MIN_BIT_PX} "
                f"(a border side of at least {MIN_BIT_PX * _BORDER_CELLS} px)"
            )
        if outer.min() < 0 or (outer[:, 0] > tag_map.width_px).any() or (outer[:, 1] > tag_map.height_px).any():
            size = f"{tag_map.width_px}x{tag_map.height_px}"
            return f"tag {t.tag_id} (with its quiet zone) is off the {size} projector image"
    boxes = np.array([[o[:, 0].min(), o[:, 1].min(), o[:, 0].max(), o[:, 1].max()] for o in outers])
    for i in range(len(tags)):
        near = np.flatnonzero(
            (boxes[i + 1 :, 0] < boxes[i, 2])
            & (boxes[i, 0] < boxes[i + 1 :, 2])
            & (boxes[i + 1 :, 1] < boxes[i, 3])
            & (boxes[i, 1] < boxes[i + 1 :, 3])
        )
        for j in near + i + 1:
            area, _ = cv2.intersectConvexConvex(outers[i].astype(np.float32), outers[j].astype(np.float32))
            if area > 1.0:  # more than a pixel: shared edges and rounding are not overlaps
                return f"tags {tags[i].tag_id} and {tags[j].tag_id} overlap (quiet zones included)"
    return None
