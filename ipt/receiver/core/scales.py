"""Detection sized to the tags in the image: filter and decimation from the expected cell size.

The binarisation's mean filter and opening/closing (:func:`~ipt.receiver.core.demodulator.binarise_difference`)
and AprilTag's quad decimation suit cells of about 13 px: the paper's 160 px tags seen from 0.8 m by a
640 px camera. From 2.5 m the same cells are 4 px and a 5 px filter erases them; a landing pad's 64 px tags
seen from 1 m are 4 px a cell too, and the same tags from 0.25 m are 17 px. So the sizes follow the cell
size in the image: from the height of the current track when there is one, and from a short cycle of
heights when the camera is lost.

The pose gates' bound on the distance from the predicted position grows with the height in the same way
(:func:`gate_growth`): a pixel covers more floor, and the noise of a pose from the map grows with it.

Pure: the map's tag sizes, the camera's focal length and a height in; filter and decimation sizes out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ipt.tagmap import TAG36H11_CELLS, TagMap

#: Filter side per pixel of a cell in the image (5 px for the 13 px cells the defaults were chosen for).
KSIZE_PER_CELL = 0.4
#: AprilTag's quad decimation per pixel of a cell: a decimated cell keeps at least this many pixels' worth.
CELL_PX_PER_DECIMATION = 3.0
#: A tag size is used for the scale only if its whole tag (quiet zone included) fits in this share of the
#: image's shorter side: a bigger tag is rarely seen whole.
WHOLE_TAG_SHARE = 0.9
#: Cells narrower than this (pixels) are not worth a detector run.
MIN_DECODE_CELL_PX = 3.0
#: The height assumed before the first pose (the paper's flights).
START_HEIGHT_M = 0.8
#: Heights (m) cycled through while lost with nothing to say which is likely: the pad, the paper's 0.8 m,
#: a lab's 1.6 m and 2.5 m.
SEARCH_HEIGHTS_M = (0.8, 2.5, 1.6, 0.3)


#: Height (m) the pose gates' bounds are stated for (the paper's flights at 0.8 m).
GATE_REFERENCE_HEIGHT_M = 0.8
#: The gates' bounds grow at most this much (at 2.4 m and above).
MAX_GATE_GROWTH = 3.0


def gate_growth(height_m: float) -> float:
    """The factor on the consistency gate's bound for a pose ``height_m`` above the floor: 1 up to the
    reference height, then in proportion to the height (the ground distance of a pixel), at most
    :data:`MAX_GATE_GROWTH`."""
    if not math.isfinite(height_m):
        return 1.0
    return min(max(height_m / GATE_REFERENCE_HEIGHT_M, 1.0), MAX_GATE_GROWTH)


@dataclass(frozen=True)
class DetectScale:
    """How to binarise the difference and decode tags at one scale."""

    ksize: int
    """Side of the mean filter and of the opening/closing element (odd, pixels)."""
    decimate: float
    """AprilTag's quad decimation."""


def tag_cells_m(tag_map: TagMap) -> tuple[float, ...]:
    """The distinct cell sides (m) of the map's tags, largest first (one per tag size, to a millimetre)."""
    sides = set()
    for tag in tag_map.tags:
        c = np.asarray(tag.corners_m, np.float64)[:, :2]
        border = float(np.linalg.norm(c[1] - c[0]))
        sides.add(round(border / (TAG36H11_CELLS - 2), 3))
    return tuple(sorted(sides, reverse=True))


def honoured_decimation(decimate: float) -> float:
    """The finest quad decimation AprilTag 3 carries out as asked that is no coarser than ``decimate``: 1 (none),
    1.5, or a whole number. The C library (``image_u8_decimate``) shrinks the image by 1.5 or by the whole part of
    any other factor, yet scales the quads' corners back by the factor asked: with 1.75 it looks at the full image
    and puts every corner 75 % too far out, and decodes nothing (at 1.25, 2.25, 2.5 and 2.75 likewise)."""
    if decimate < 1.5:
        return 1.0
    if decimate < 2.0:
        return 1.5
    return float(math.floor(decimate))


def scale_for_cell(cell_px: float, base: DetectScale) -> DetectScale:
    """The scale for cells ``cell_px`` wide in the image: never coarser than ``base`` (the configured one), and
    with a decimation AprilTag honours (:func:`honoured_decimation`)."""
    ksize = 2 * round((KSIZE_PER_CELL * cell_px - 1) / 2) + 1
    ksize = int(min(max(ksize, 1), base.ksize))
    decimate = min(max(cell_px / CELL_PX_PER_DECIMATION, 1.0), base.decimate)
    return DetectScale(ksize, honoured_decimation(round(decimate * 4) / 4))


def scale_at_height(
    height_m: float, cells_m: tuple[float, ...], focal_px: float, short_side_px: int, base: DetectScale
) -> DetectScale:
    """The scale for a camera ``height_m`` above the floor: for the largest tags that fit whole in the
    image there (or the smallest tags, if none do)."""
    h = max(height_m, 0.05)
    fitting = [c for c in cells_m if c * TAG36H11_CELLS * focal_px / h <= WHOLE_TAG_SHARE * short_side_px]
    cell_m = fitting[0] if fitting else min(cells_m)
    return scale_for_cell(cell_m * focal_px / h, base)


class ScaleChooser:
    """The scale to try for each acquisition attempt: those for the last known height first, and while
    they find nothing, the others from a cycle of heights, one an attempt."""

    def __init__(self, tag_map: TagMap, focal_px: float, short_side_px: int, base: DetectScale) -> None:
        self.cells_m = tag_cells_m(tag_map)
        self.focal_px, self.short_side_px, self.base = focal_px, short_side_px, base
        self.height_m: float | None = None
        """The last height a pose was found at (m), or None."""
        self._turn = -1
        """The place in the cycle of :meth:`to_try` (-1: the next call starts it)."""
        self._frame: int | None = None
        """The frame :attr:`_turn` is for (None: none yet, or the cycle starts again)."""
        self._search = self._unique([self.at(h) for h in SEARCH_HEIGHTS_M])

    @staticmethod
    def _unique(scales: list[DetectScale]) -> list[DetectScale]:
        out: list[DetectScale] = []
        for s in scales:
            if s not in out:
                out.append(s)
        return out

    def at(self, height_m: float) -> DetectScale:
        """The scale for a camera ``height_m`` above the floor."""
        return scale_at_height(height_m, self.cells_m, self.focal_px, self.short_side_px, self.base)

    def seen_at(self, height_m: float) -> None:
        """A pose was found at ``height_m``: the next frames start from its scale."""
        if math.isfinite(height_m) and height_m > 0:
            self.height_m = height_m
            self._restart_cycle()

    def forget(self) -> None:
        """After a gap or a jump in the video: the height is unknown again (search as at the start)."""
        self.height_m = None
        self._restart_cycle()

    def _restart_cycle(self) -> None:
        """The next call of :meth:`to_try`, for any frame (the current one too), takes the cycle's first
        scale."""
        self._turn, self._frame = -1, None

    def sizes_at(self, height_m: float) -> list[DetectScale]:
        """A scale for each tag size of the map that can be decoded from ``height_m`` (whole in the image,
        cells of at least :data:`MIN_DECODE_CELL_PX`), the largest tags first: a view over a pad's edge
        holds both sizes, and either may be the one whose tags are whole."""
        h = max(height_m, 0.05)
        out: list[DetectScale] = []
        for c in self.cells_m:
            cell_px = c * self.focal_px / h
            if cell_px >= MIN_DECODE_CELL_PX and cell_px * TAG36H11_CELLS <= WHOLE_TAG_SHARE * self.short_side_px:
                out.append(scale_for_cell(cell_px, self.base))
        return self._unique(out)

    def to_try(self, frame: int) -> list[DetectScale]:
        """The scale for acquiring ``frame``. Frames take turns over a cycle: each tag size decodable at
        the last known height (before any pose: :data:`START_HEIGHT_M`), then the search heights. Every
        attempt on one frame (its partners, both polarities) gets the same scale, so that the partner whose
        phase is right meets every scale in turn. One scale a frame keeps a lost receiver's frames as cheap
        as the single-scale receiver's (a live camera must not drop frames while it searches); the cycle
        starts again from the known height after every pose, so a track that slips is found again at
        once."""
        if frame != self._frame:
            self._frame = frame
            self._turn += 1
        height = self.height_m if self.height_m is not None else START_HEIGHT_M
        cycle = self._unique((self.sizes_at(height) or [self.at(height)]) + self._search)
        return [cycle[self._turn % len(cycle)]]
