"""The arena configuration and a strict YAML loader for any pydantic model.

Units are in the field names. Every model forbids unknown keys, so a typo in a YAML file is reported
instead of silently ignored.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ipt.errors import IptError
from ipt.fileio import read_text_file


class ConfigError(IptError):
    """A configuration file is missing, unreadable or invalid."""


MIN_PROJECTOR_RATE_HZ = 1.0
"""Slowest projector rate accepted: below it there is no flicker to speak of, and frame times grow absurd."""
MIN_CONTENT_RATE_HZ = 0.01
"""Slowest content (input video) rate accepted: one frame every 100 s."""
MAX_RATE_HZ = 1000.0
"""Fastest projector, content or camera rate accepted."""
MIN_CAMERA_RATE_HZ = 1.0
"""Slowest camera rate accepted (IPT needs twice the projector's rate; below 1 Hz a frame time is absurd)."""


class StrictModel(BaseModel):
    """Base for every settings model: unknown keys are errors, instances are immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class ProjectorConfig(StrictModel):
    """The projector (or projector array) that paints the arena floor."""

    width_px: int = Field(1920, ge=64, le=16384, description="Output width in projector pixels.")
    height_px: int = Field(2160, ge=64, le=16384, description="Output height in projector pixels.")
    rate_hz: float = Field(
        60.0,
        ge=MIN_PROJECTOR_RATE_HZ,
        le=MAX_RATE_HZ,
        description="Output (display) frame rate f_o in Hz, 1 to 1000.",
    )


class ScreenConfig(StrictModel):
    """The size of the projected image on the floor, measured once the projector is fixed."""

    width_m: float = Field(2.17, gt=0, le=100, description="Width of the projected image in metres.")
    height_m: float = Field(2.47, gt=0, le=100, description="Height of the projected image in metres.")


class FloorConfig(StrictModel):
    """Where the projected image lands on the floor, measured (``ipt calibrate arena --points``).

    A projector mounted even a little off-axis keystones: its pixels are not a uniform grid on the floor.
    The homography takes it exactly (a plane to a plane); without this section the layout is the uniform
    scale of ``screen``."""

    pixel_to_floor: tuple[
        tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]
    ] = Field(
        description="3x3 homography, rows of three: homogeneous projector pixels (u, v, 1), edge origin (pixel "
        "(i, j) covers [i, i+1) x [j, j+1), u right, v down) to homogeneous floor metres (x, y, 1) in the "
        "arena frame. Used instead of screen by every part: tag corners, the simulator, the AR overlay."
    )
    points: int = Field(4, ge=4, le=100000, description="How many measured points it was fitted to (for the record).")
    rms_m: float = Field(
        0.0, ge=0.0, le=100.0, description="RMS distance of those points from the fit, metres (for the record)."
    )

    @model_validator(mode="after")
    def _check(self) -> FloorConfig:
        h = [[float(x) for x in row] for row in self.pixel_to_floor]
        if not all(math.isfinite(x) for row in h for x in row):
            raise ValueError("pixel_to_floor must hold finite numbers")
        (a, b, c), (d, e, f), (g, i, k) = h
        det = a * (e * k - f * i) - b * (d * k - f * g) + c * (d * i - e * g)
        if not (math.isfinite(det) and abs(det) > 1e-300):
            raise ValueError("pixel_to_floor is singular (not a homography)")
        return self


def floor_homography_fits(floor: FloorConfig, width_px: int, height_px: int) -> str | None:
    """Why ``floor`` cannot be the floor mapping of a ``width_px`` x ``height_px`` image, or None if it can.

    The image must land on the floor in one piece (the projective denominator keeps its sign over it: no
    point at infinity inside) and unmirrored (v down in the image is y up on the floor, as in the uniform
    layout; a mirrored image would mirror every tag, and no detector decodes those)."""
    h = [[float(x) for x in row] for row in floor.pixel_to_floor]
    (a, b, c), (d, e, f), (g, i, k) = h
    det = a * (e * k - f * i) - b * (d * k - f * g) + c * (d * i - e * g)
    weights = []
    for u, v in ((0, 0), (width_px, 0), (width_px, height_px), (0, height_px)):
        w = g * u + i * v + k
        if not abs(w) > 0:
            return f"pixel_to_floor sends projector pixel ({u}, {v}) to infinity"
        weights.append(w)
    if min(weights) < 0 < max(weights):  # w is affine in (u, v): its sign at the corners holds inside
        return "pixel_to_floor sends part of the image to infinity (a horizon crosses it)"
    if not det * weights[0] < 0:  # the Jacobian's determinant, det / w³, negative: the tags keep their handedness
        return "pixel_to_floor mirrors the image (v down in the image must be y up on the floor)"
    return None


class TileConfig(StrictModel):
    """One projector of several that together make the canvas (NVIDIA Mosaic / Surround, or a window each):
    its part of the canvas and, once measured, where its pixels land on the floor."""

    x_px: int = Field(ge=0, le=16384, description="Left edge of this projector's part of the canvas, canvas pixels.")
    y_px: int = Field(ge=0, le=16384, description="Top edge of this projector's part of the canvas, canvas pixels.")
    width_px: int = Field(ge=16, le=16384, description="Width of this projector's part of the canvas, pixels.")
    height_px: int = Field(ge=16, le=16384, description="Height of this projector's part of the canvas, pixels.")
    pixel_to_floor: (
        tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]] | None
    ) = Field(
        None,
        description="3x3 homography from canvas pixels (u, v, 1), edge origin, inside this tile to floor metres "
        "(x, y, 1), measured by ipt calibrate arena --points. null: the uniform layout of screen (as if one "
        "projector made the whole canvas).",
    )
    points: int = Field(0, ge=0, le=100000, description="How many measured points it was fitted to (for the record).")
    rms_m: float = Field(
        0.0, ge=0.0, le=100.0, description="RMS distance of those points from the fit, metres (for the record)."
    )

    @property
    def floor(self) -> FloorConfig | None:
        """The measured mapping as a :class:`FloorConfig` (None until measured)."""
        if self.pixel_to_floor is None:
            return None
        return FloorConfig(pixel_to_floor=self.pixel_to_floor, points=max(4, self.points), rms_m=self.rms_m)

    def contains(self, u_px: float, v_px: float) -> bool:
        """Whether canvas point (u, v) is in this tile (edges included)."""
        return self.x_px <= u_px <= self.x_px + self.width_px and self.y_px <= v_px <= self.y_px + self.height_px


MIN_TAG_SIZE_PX = 64
"""Smallest side of a tag's black border square in projector pixels: 8 pixels per bit (tag36h11 is 8 cells
across its border). Smaller cells blur into their neighbours through the projector's and camera's optics."""


class LandingPadConfig(StrictModel):
    """A square of small tags around a landing pad: what a camera 0.25 m above the floor can decode.

    The big tags of the grid whose quiet zone reaches into the square are left out, and small tags (ids
    after the grid's) fill it in rows, so that a drone on the pad sees several whole tags and one at 0.5 m
    sees both sizes."""

    name: str = Field(min_length=1, max_length=64, description="The pad's name (in messages).")
    centre_m: tuple[float, float] = Field(description="Centre of the pad in arena metres (x, y; ENU).")
    size_m: float = Field(0.8, gt=0, le=100, description="Side of the square of small tags, metres.")
    tag_size_px: int = Field(
        64,
        ge=8,
        description="Side of a small tag's black border square in projector pixels: a multiple of 8, at "
        f"least {MIN_TAG_SIZE_PX} (8 projector pixels per bit). A quiet zone one cell wide surrounds it.",
    )
    gap_px: int = Field(8, ge=0, le=1024, description="Projector pixels between the quiet zones of two small tags.")

    @model_validator(mode="after")
    def _check(self) -> LandingPadConfig:
        if self.tag_size_px % 8:
            raise ValueError(f"tag_size_px must be a multiple of 8, got {self.tag_size_px}")
        if self.tag_size_px < MIN_TAG_SIZE_PX:
            raise ValueError(
                f"landing pad '{self.name}': tags of {self.tag_size_px} px have {self.tag_size_px // 8} projector "
                f"px per bit, fewer than 8 (tag_size_px must be at least {MIN_TAG_SIZE_PX})"
            )
        return self


class TagMapConfig(StrictModel):
    """The grid of AprilTags hidden in the video (the paper's Fig. 3), and the landing pads' small tags."""

    family: Literal["tag36h11"] = Field("tag36h11", description="AprilTag family; only tag36h11 is supported.")
    rows: int = Field(9, ge=1, le=64, description="Number of tag rows, counted bottom to top.")
    cols: int = Field(9, ge=1, le=64, description="Number of tag columns, counted left to right.")
    tag_size_px: int = Field(
        160,
        ge=16,
        description="Side of a tag's black border square in projector pixels (a multiple of 8: tag36h11 is "
        "8 cells across its border). A white quiet zone one cell wide surrounds it.",
    )
    first_id: int = Field(0, ge=0, description="Id of the bottom-left tag; ids grow left to right, then up.")
    pads: tuple[LandingPadConfig, ...] = Field(
        (),
        max_length=16,
        description="Landing pads: squares of small tags in place of the big ones (ids after the grid's, pad "
        "by pad, each pad's rows bottom to top, left to right). None: the paper's grid alone.",
    )

    @model_validator(mode="after")
    def _check(self) -> TagMapConfig:
        if self.tag_size_px % 8:
            raise ValueError(f"tag_size_px must be a multiple of 8, got {self.tag_size_px}")
        if self.tag_size_px < MIN_TAG_SIZE_PX:
            raise ValueError(
                f"tags of {self.tag_size_px} px have {self.tag_size_px // 8} projector px per bit, fewer than 8 "
                f"(tag_size_px must be at least {MIN_TAG_SIZE_PX})"
            )
        if self.first_id + self.rows * self.cols > 587:
            raise ValueError("tag36h11 has 587 ids: first_id + rows * cols must not exceed 587")
        names = [p.name for p in self.pads]
        if len(set(names)) != len(names):
            raise ValueError("two landing pads have the same name")
        return self


class ModulationConfig(StrictModel):
    """How the tags are hidden in the video (the paper's Algorithm 1)."""

    profile: Literal["ipt", "paper"] = Field(
        "ipt",
        description="Modulation profile. 'ipt': exact float colour maths, pixels outside the tags untouched, the "
        "two phases balanced in linear light so that their average is the original colour (Talbot-Plateau); "
        "'paper': Algorithm 1 as published (8-bit CIELAB round trip, clipped phases unbalanced).",
    )
    delta_l: float = Field(4.0, gt=0, le=50, description="Lightness change ΔL in 8-bit CIELAB L units (0..255 scale).")
    clip_allowance_l8: float = Field(
        2.2,
        ge=0,
        le=8,
        description="Profile 'ipt' only: where the content leaves no room for a balanced pair of the full step "
        "(pure white and black, pure primaries, colours next to them), the centre of the pair may move so that "
        "the camera still sees the tags there, by as little as gives the full step, in the direction that costs "
        "least, and never so far that the average of the two phases differs from the input by more than a "
        "lightness change of this many 8-bit L units costs at white or black (CIEDE2000 0.49 for 2.2, the "
        "paper's own imbalance on white). 0: the average is exact everywhere (and pure white, black and "
        "primaries carry no tags).",
    )
    input_rate_hz: float = Field(
        30.0,
        ge=MIN_CONTENT_RATE_HZ,
        le=MAX_RATE_HZ,
        description="Frame rate f_i of the input video in Hz, 0.01 to 1000 (a video file's own rate wins).",
    )


class ArenaConfig(StrictModel):
    """Everything both sides must agree on: projector, screen size, tag map and modulation."""

    projector: ProjectorConfig = Field(default_factory=ProjectorConfig, description="The projector.")
    screen: ScreenConfig = Field(
        default_factory=ScreenConfig,
        description="The projected image on the floor (its size: the uniform layout, used without 'floor').",
    )
    floor: FloorConfig | None = Field(
        None,
        description="The measured projector-to-floor homography (ipt calibrate arena --points); null: the "
        "uniform layout of screen.",
    )
    projectors: tuple[TileConfig, ...] | None = Field(
        None,
        description="Several projectors making the canvas (projector.width_px x height_px) together, each with "
        "its own floor homography: tiles that cover the canvas without overlapping. Tags are kept out of the "
        "seams between them (a tag across a seam would be drawn by two projectors that disagree). null: one "
        "projector (see floor).",
    )
    tag_map: TagMapConfig = Field(default_factory=TagMapConfig, description="The hidden tag grid.")
    modulation: ModulationConfig = Field(default_factory=ModulationConfig, description="The modulation.")

    @model_validator(mode="after")
    def _check(self) -> ArenaConfig:
        tm, pr = self.tag_map, self.projector
        if self.floor is not None:
            problem = floor_homography_fits(self.floor, pr.width_px, pr.height_px)
            if problem is not None:
                raise ValueError(f"floor: {problem}")
        if self.projectors is not None:
            self._check_tiles()
        quiet_px = tm.tag_size_px // 8
        if pr.width_px / tm.cols < tm.tag_size_px + 2 * quiet_px:
            raise ValueError(
                f"{tm.cols} columns of {tm.tag_size_px} px tags (plus quiet zone) do not fit in {pr.width_px} px"
            )
        if pr.height_px / tm.rows < tm.tag_size_px + 2 * quiet_px:
            raise ValueError(
                f"{tm.rows} rows of {tm.tag_size_px} px tags (plus quiet zone) do not fit in {pr.height_px} px"
            )
        self._check_pads()
        return self

    def pad_grid(self, pad: LandingPadConfig) -> tuple[tuple[int, int, int, int], tuple[int, int, float, float]]:
        """Where the small tags of ``pad`` go: the grid's cells (col0, col1, row0, row1: half-open ranges,
        rows counted bottom to top) whose big tags they replace, every cell the pad's square reaches into;
        and (cols, rows, left_px, top_px) of the small tags that fill those cells, the block centred in
        them, left/top the projector pixel edges of its top-left quiet zone."""
        pr, sc, tm = self.projector, self.screen, self.tag_map
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
        return (col0, col1, row0, row1), (max(cols, 0), max(rows, 0), float(left), float(top))

    def _check_pads(self) -> None:
        """Every pad on the screen, no two overlapping, enough tag36h11 ids for their tags."""
        half_w, half_h = self.screen.width_m / 2, self.screen.height_m / 2
        squares: list[tuple[float, float, float]] = []
        n_small = 0
        for pad in self.tag_map.pads:
            x, y = pad.centre_m
            s = pad.size_m / 2
            if not (-half_w <= x - s and x + s <= half_w and -half_h <= y - s and y + s <= half_h):
                raise ValueError(
                    f"landing pad '{pad.name}' ({pad.size_m:g} m square at {x:g}, {y:g}) is off the screen "
                    f"(x within ±{half_w:g} m, y within ±{half_h:g} m)"
                )
            cols, rows, _, _ = self.pad_grid(pad)[1]
            if min(cols, rows) < 1:
                raise ValueError(f"landing pad '{pad.name}': not one of its tags fits in the grid cells it covers")
            for other, (ox, oy, os_) in zip(self.tag_map.pads, squares, strict=False):
                if abs(x - ox) < s + os_ and abs(y - oy) < s + os_:
                    raise ValueError(f"landing pads '{other.name}' and '{pad.name}' overlap")
            squares.append((x, y, s))
            n_small += cols * rows
        if n_small and self.tag_map.first_id + self.tag_map.rows * self.tag_map.cols + n_small > 587:
            raise ValueError(f"tag36h11 has 587 ids: the grid and the landing pads' {n_small} small tags need more")


    def _check_tiles(self) -> None:
        tiles, pr = self.projectors or (), self.projector
        if self.floor is not None:
            raise ValueError("give floor (one projector) or projectors (tiles), not both")
        if len(tiles) < 1:
            raise ValueError("projectors: list one tile or more")
        for n, t in enumerate(tiles):
            if t.x_px + t.width_px > pr.width_px or t.y_px + t.height_px > pr.height_px:
                raise ValueError(f"projectors[{n}]: reaches outside the {pr.width_px}x{pr.height_px} canvas")
            for m in range(n):
                o = tiles[m]
                if (
                    t.x_px < o.x_px + o.width_px
                    and o.x_px < t.x_px + t.width_px
                    and t.y_px < o.y_px + o.height_px
                    and o.y_px < t.y_px + t.height_px
                ):
                    raise ValueError(f"projectors[{n}]: overlaps projectors[{m}] in the canvas")
            if t.floor is not None:
                # The tile's own part of the canvas must land in one piece and unmirrored.
                shifted = [[*row] for row in t.floor.pixel_to_floor]
                offset = FloorConfig(
                    pixel_to_floor=tuple(
                        (r[0], r[1], r[0] * t.x_px + r[1] * t.y_px + r[2]) for r in shifted
                    )
                )
                problem = floor_homography_fits(offset, t.width_px, t.height_px)
                if problem is not None:
                    raise ValueError(f"projectors[{n}]: {problem}")
        if sum(t.width_px * t.height_px for t in tiles) != pr.width_px * pr.height_px:
            raise ValueError(f"projectors: the tiles must cover the whole {pr.width_px}x{pr.height_px} canvas")


#: Image width the receiver's pixel-sized defaults are stated for (the paper's 640x360 camera); they
#: scale with the actual width, since blur, motion and corner noise in pixels grow with resolution.
REFERENCE_WIDTH_PX = 640


class DemodulationConfig(StrictModel):
    """Recovering the tag image from two camera frames (the paper's Algorithm 2 and Section V-A/B)."""

    pairing: Literal["opposite_phase", "previous"] = Field(
        "opposite_phase",
        description="Which earlier frame a frame is subtracted from. 'previous' is the paper's (lag 1: with a "
        "120 FPS camera and 60 Hz phases only every other pair straddles a flip). 'opposite_phase' picks "
        "the lag whose time step is closest to an odd number of projector periods (lag 2 at 120 FPS, lag 3 "
        "at 180), falling back to the next best lags when it finds no tags.",
    )
    alignment: Literal["gradient", "sampled_lines"] = Field(
        "gradient",
        description="How the earlier frame is aligned to the current one. 'sampled_lines' is the paper's "
        "integer shift from N columns and rows (equation 5). 'gradient' is the floor's full homography "
        "between the two frames (phase correlation, then Lucas-Kanade with eight parameters) on their "
        "gradient magnitudes, which the tags' sign flip between phases does not disturb: a vibrating drone "
        "turns by up to a degree between the two frames, which a shift alone leaves misaligned.",
    )
    lookahead_frames: int = Field(
        2,
        ge=0,
        le=4,
        description="A frame whose earlier partners give no pose may wait for this many later frames and be "
        "paired with one of them (its pose goes out that much later, in order). Needed whenever the content "
        "changes between two projector frames (half the pairs of a 30 fps video at 60 Hz) or an exposure "
        "straddles a flip. 0: each pose as soon as its frame is processed, from earlier frames only.",
    )
    undistort: bool = Field(
        True,
        description="Undistort each frame once (with 'gradient' alignment), so that the floor moves by an "
        "exact homography between frames and the camera is a pinhole afterwards.",
    )
    polarity: Literal["tracked", "both"] = Field(
        "tracked",
        description="'both' runs the detector on the binary image and its inverse (the paper's phase is "
        "unknown). 'tracked' predicts the phase from earlier detections and tries the other only on a miss.",
    )
    predict_warp: bool = Field(
        True,
        description="With 'gradient' alignment: warp the earlier frame by the floor homography predicted from "
        "the recent poses before refining the shift, so that yaw, tilt and height changes between the "
        "paired frames are aligned too, not only the translation.",
    )
    lightness: Literal["cielab", "luma"] = Field(
        "luma",
        description="How lightness is taken from a camera frame. 'cielab' is the paper's 8-bit CIELAB L. "
        "'luma' maps the BT.601 luma of the frame through a table to L: the same for grey pixels, a "
        "fifth of the cost, and the difference of two phases shows the tags just as well.",
    )
    clip_factor: float | None = Field(
        1.2,
        gt=0.0,
        le=100.0,
        description="With 'sampled_lines' alignment: the difference image is clipped to ± this many times its "
        "median magnitude before it is normalised, so that edges of the video left by motion (tens of L "
        "units) cannot outweigh the tags' 2ΔL in the mean filter. None: no clipping (the paper). ('gradient' "
        "alignment leaves out what changed more than the tags can instead.)",
    )
    sample_lines: int = Field(3, ge=1, le=64, description="N: columns (and rows) sampled for the alignment.")
    max_shift_px: int | None = Field(
        None,
        ge=0,
        le=64,
        description="b: the largest alignment shift tried, in pixels. Default: the paper's 5 px at 640 px "
        "wide, scaled with the image width (motion in pixels grows with resolution).",
    )
    blur_ksize: int | None = Field(
        None,
        ge=1,
        le=31,
        description="Side of the mean filter, in pixels. Default: 5 at 640 px wide, scaled with the width "
        "(odd). The paper names the filter but not its size.",
    )
    morph_ksize: int | None = Field(
        None,
        ge=1,
        le=31,
        description="Side of the square opening/closing element. Default: as for blur_ksize.",
    )


class DetectorConfig(StrictModel):
    """AprilTag 3 (pupil-apriltags) settings."""

    quad_decimate: float = Field(
        3.0,
        ge=1.0,
        le=8.0,
        description="Decimation before quad detection (edges are refined at full size). 3 finds as many "
        "tags as 2 on the binary tag image at 640x360 and 1280x720, as accurately, in two thirds of the time.",
    )
    quad_sigma: float = Field(0.0, ge=0.0, le=5.0, description="Gaussian blur sigma before quad detection.")
    refine_edges: bool = Field(True, description="Snap quad edges to strong gradients.")
    decode_sharpening: float = Field(0.25, ge=0.0, le=2.0, description="Sharpening of decoded images.")
    threads: int = Field(1, ge=1, le=16, description="Detector worker threads.")
    max_hamming: int = Field(1, ge=0, le=2, description="Decodes with more bit errors than this are dropped.")
    border_margin_px: float = Field(
        2.0,
        ge=0.0,
        description="Tags with a corner closer than this to the image edge are dropped: a tag cut by the edge "
        "can still decode, with the edge taken for its border.",
    )
    isolation: Literal["process", "inline"] = Field(
        "process",
        description="Where AprilTag's C code runs. 'process': in a helper process that is replaced, without "
        "a gap in detection, once its memory grew by recycle_mb (pupil-apriltags 1.0.4 leaks a few hundred "
        "bytes per call; see docs/reliability.md), and restarted if it crashes. 'inline': in the calling "
        "thread, with memory growing by the leak, for short runs; on a 2-core test machine it had 1.3 ms "
        "less capture-to-send latency at the median and 3.8 ms at p99. Linux only; elsewhere 'process' "
        "runs inline.",
    )
    recycle_mb: float = Field(
        4.0,
        gt=0.0,
        le=4096.0,
        description="With isolation 'process': the helper is replaced once its own memory (RssAnon) grew "
        "by this many MB since it warmed up. At 120 frames/s the leak reaches 4 MB in one to five minutes.",
    )


class TrackConfig(StrictModel):
    """Pose from every visible edge of the hidden map (method 'track', see ipt/receiver/track.py)."""

    search_px: float = Field(
        4.0,
        gt=0.5,
        le=20.0,
        description="How far (pixels at 640 wide) each edge sample looks along its normal for its step.",
    )
    min_inliers: int = Field(
        30,
        ge=10,
        le=10000,
        description="Fewest edge samples on their steps for a pose (about one tag's worth: the cell check and "
        "the inlier fraction reject a wrong pose, and a view mostly in the drone's shadow or cut by a "
        "content change has few samples left).",
    )
    min_inlier_fraction: float = Field(
        0.15,
        gt=0,
        le=1,
        description="Fewest edge samples on their steps, as a fraction of those that could see signal: a "
        "pose that explains less of the visible map is not taken.",
    )
    min_cell_agreement: float = Field(
        0.8,
        ge=0.5,
        le=1,
        description="Of the cells in view whose difference is clearly signed, at least this fraction must have "
        "the sign the map gives them at the pose found: a pose off by a cell or more agrees with about half.",
    )
    verify_every: int = Field(
        15,
        ge=0,
        le=10000,
        description="Every this many tracked frames AprilTag checks the track (a pose whose tags it decodes "
        "elsewhere restarts it). 0: never.",
    )
    rolling_shutter: bool = Field(
        False,
        description="The camera has a rolling shutter (most Pi and USB cameras): fit, beside each frame's pose "
        "(that of its centre row), how the pose moves from the top row to the bottom one while the drone "
        "vibrates. Measured on the suite's 8 s rolling flight (6 ms readout): X/Y/Z MAE 4.7/2.8/1.6 -> "
        "4.2/2.1/0.7 mm, tilt 0.40 -> 0.35 deg, yield 72.7 -> 71.2 %; on a global-shutter camera it costs yield "
        "(shadow-vibration, first 4 s: 85.4 -> 76.0 %: the six extra unknowns fit noise), so it is off by "
        "default.",
    )


class PoseConfig(StrictModel):
    """Pose from tag corners (OpenCV solvePnP with IPPE) or from the whole visible map."""

    method: Literal["track", "apriltag"] = Field(
        "track",
        description="'apriltag': every pose from the corners of the tags AprilTag decodes in its frame (the "
        "paper). 'track': AprilTag acquires, then every pose is fitted to all the cell edges of the map in "
        "view (partial tags, tags half in shadow or at the image border included), from the previous pose; "
        "AprilTag takes over again whenever the track is lost. Needs 'gradient' alignment.",
    )
    track: TrackConfig = Field(default_factory=TrackConfig, description="Settings of method 'track'.")

    min_tags: int = Field(
        2,
        ge=1,
        le=64,
        description="Fewest tags a pose may rest on. One small tag leaves the tilt ambiguous (IPPE's two "
        "solutions): on the simulated flight 37 % of single-tag poses were more than 5 cm off.",
    )
    refine_lm: bool = Field(
        True,
        description="Refine IPPE's solution by Levenberg-Marquardt on the reprojection error. OpenCV's IPPE "
        "fits a homography to all points and does not minimise reprojection error; on the simulated "
        "arena refinement cuts the position error of a single frame from centimetres to millimetres.",
    )
    max_reprojection_rms_px: float | None = Field(
        None,
        gt=0,
        description="Poses whose corner reprojection RMS exceeds this are rejected. Default: 2.5 px at 640 px "
        "wide, scaled with the width (corner noise from binarisation grows with the filter sizes).",
    )
    max_speed_mps: float | None = Field(
        3.0,
        gt=0,
        description="Motion gate: a pose farther from the last accepted one (within the last 0.25 s) than "
        "this speed allows, plus 5 cm, is rejected as doubtful. None turns the gate off.",
    )
    max_prediction_error_m: float | None = Field(
        0.015,
        gt=0,
        description="Consistency gate: a pose farther than this from where the recent poses (a constant-"
        "velocity fit over the last 0.15 s) put the camera at its capture time is rejected as doubtful. "
        "It catches the tilt/translation ambiguity of a view with few tags, where a 2° tilt error moves "
        "the position several centimetres. Until there are enough recent poses to predict from (the start, "
        "after a gap), a pose goes out only if its own position uncertainty is within this bound. Stated for "
        "heights up to 0.8 m; above, the bound grows with the height (3 times at 2.4 m), as a pixel's floor "
        "distance does. None turns the gate off.",
    )
    outlier_tag_px: float | None = Field(
        None,
        gt=0,
        description="A tag whose own reprojection RMS exceeds this (and three times the median) is dropped "
        "and the pose solved again without it. Default: 2 px at 640 px wide, scaled with the width.",
    )


class PipelineConfig(StrictModel):
    """The receiver's per-frame processing."""

    demodulation: DemodulationConfig = Field(default_factory=DemodulationConfig, description="Demodulation.")
    detector: DetectorConfig = Field(default_factory=DetectorConfig, description="Tag detection.")
    pose: PoseConfig = Field(default_factory=PoseConfig, description="Pose estimation.")

    @property
    def luminance_only(self) -> bool:
        """Whether a frame's luma is all the processing needs (lightness 'luma'): frame sources then hand
        over grey frames, taken without a detour through RGB (a YUV camera's Y plane, a JPEG decoded to
        grey). The paper's CIELAB lightness needs the colours."""
        return self.demodulation.lightness == "luma"

    @classmethod
    def profile(cls, name: str) -> PipelineConfig:
        """The settings of a named profile: ``ipt`` (the defaults) or ``paper`` (the paper as published)."""
        if name == "ipt":
            return cls()
        if name == "paper":
            return cls(
                demodulation=DemodulationConfig(
                    pairing="previous",
                    alignment="sampled_lines",
                    lookahead_frames=0,
                    undistort=False,
                    polarity="both",
                    predict_warp=False,
                    lightness="cielab",
                    clip_factor=None,
                    blur_ksize=3,
                    morph_ksize=3,
                ),
                detector=DetectorConfig(quad_decimate=1.0, border_margin_px=0.0),
                pose=PoseConfig(
                    method="apriltag",
                    min_tags=1,
                    refine_lm=False,
                    max_reprojection_rms_px=3.0,
                    outlier_tag_px=1e9,
                    max_speed_mps=None,
                    max_prediction_error_m=None,
                ),
            )
        raise ConfigError(f"unknown pipeline profile '{name}' (choose from {', '.join(PROFILES)})")


PROFILES = ("ipt", "paper")
"""Named pipeline settings; ``paper`` keeps the published pipeline available beside ours."""


def finite_float(value: object) -> float | None:
    """``value`` as a float if it is a real number that fits one (not bool, not inf/nan), else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:  # an integer too large for a float
        return None
    return number if math.isfinite(number) else None


M = TypeVar("M", bound=BaseModel)


_MAX_PROBLEMS = 12
"""Problems named in one configuration error; the rest are counted ("... and N more")."""
_MAX_PART_CHARS = 200
"""Longest description of one problem (a key or a value can be megabytes long in a broken file)."""


def _shorten(text: str, limit: int = _MAX_PART_CHARS) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _describe_validation_error(exc: ValidationError) -> str:
    parts = []
    errors = exc.errors()
    for err in errors[:_MAX_PROBLEMS]:
        where = ".".join(str(p) for p in err["loc"]) or "(top level)"
        if not where.isprintable():
            where = repr(where)
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        elif err["type"] == "missing":
            msg = "missing key"
        parts.append(_shorten(f"{where}: {msg}"))
    if len(errors) > _MAX_PROBLEMS:
        parts.append(f"... and {len(errors) - _MAX_PROBLEMS} more")
    return "; ".join(parts)


def read_yaml_mapping(path: Path, error: type[IptError] = ConfigError) -> dict[str, Any]:
    """Read a YAML file whose top level is a mapping; raise ``error`` naming the file otherwise."""
    text = read_text_file(path, error, "a YAML file")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise error(f"{path}: not valid YAML{where}") from None
    except RecursionError:
        raise error(f"{path}: not usable YAML: nested too deeply") from None
    except Exception as exc:
        # PyYAML's own constructors raise plain exceptions for some scalars they claim to resolve:
        # ValueError for a date like 2001-13-45 or an integer of more than 4300 digits, KeyError for
        # `!!bool maybe`, AttributeError for `!!timestamp x`, IndexError for an empty `!!int`.
        what = _shorten(str(exc) or type(exc).__name__)
        raise error(f"{path}: not usable YAML: a value cannot be read ({what})") from None
    if data is None:
        raise error(f"{path}: the file is empty")
    if not isinstance(data, dict):
        raise error(f"{path}: expected a mapping of keys at the top level, got {type(data).__name__}")
    return data


def load_yaml_model(path: str | Path, model: type[M]) -> M:
    """Load ``path`` as YAML and validate it as ``model``; any problem is one :class:`ConfigError`."""
    p = Path(path)
    data = read_yaml_mapping(p)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{p}: {_describe_validation_error(exc)}") from None


def load_arena_config(path: str | Path) -> ArenaConfig:
    """Load an arena YAML file (see the shipped ``arena.yaml``)."""
    return load_yaml_model(path, ArenaConfig)


def shipped_config_path(name: str) -> Path:
    """Path of an example config shipped inside the package (e.g. ``arena.yaml``)."""
    return Path(str(resources.files("ipt.config") / name))
