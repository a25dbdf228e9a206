"""The arena configuration: projector, screen, floor, tag map and modulation (:class:`ArenaConfig`).

Units are in the field names. Every model forbids unknown keys, so a typo in a YAML file is reported
instead of silently ignored. The strict base and the YAML loaders are :mod:`ipt.config.base`, the
receiver's processing settings :mod:`ipt.config.pipeline`; both are re-exported here, so that
``from ipt.config.models import X`` keeps working for all of them.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from ipt.config.base import (
    ConfigError,
    StrictModel,
    _describe_validation_error,
    finite_float,
    load_yaml_model,
    read_yaml_mapping,
    shipped_config_path,
)
from ipt.config.pipeline import (
    PROFILES,
    REFERENCE_WIDTH_PX,
    DemodulationConfig,
    DetectorConfig,
    PipelineConfig,
    PoseConfig,
    TrackConfig,
)

__all__ = [
    "MAX_RATE_HZ",
    "MIN_CAMERA_RATE_HZ",
    "MIN_CONTENT_RATE_HZ",
    "MIN_PROJECTOR_RATE_HZ",
    "MIN_TAG_SIZE_PX",
    "PROFILES",
    "REFERENCE_WIDTH_PX",
    "ArenaConfig",
    "ConfigError",
    "DemodulationConfig",
    "DetectorConfig",
    "FloorConfig",
    "LandingPadConfig",
    "ModulationConfig",
    "PipelineConfig",
    "PoseConfig",
    "ProjectorConfig",
    "ScreenConfig",
    "StrictModel",
    "TagMapConfig",
    "TileConfig",
    "TrackConfig",
    "_describe_validation_error",
    "finite_float",
    "floor_homography_fits",
    "load_arena_config",
    "load_yaml_model",
    "read_yaml_mapping",
    "shipped_config_path",
]


MIN_PROJECTOR_RATE_HZ = 1.0
"""Slowest projector rate accepted: below it there is no flicker to speak of, and frame times grow absurd."""
MIN_CONTENT_RATE_HZ = 0.01
"""Slowest content (input video) rate accepted: one frame every 100 s."""
MAX_RATE_HZ = 1000.0
"""Fastest projector, content or camera rate accepted."""
MIN_CAMERA_RATE_HZ = 1.0
"""Slowest camera rate accepted (IPT needs twice the projector's rate; below 1 Hz a frame time is absurd)."""


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


MIN_SCREEN_M = 0.1
"""The smallest projected image, metres a side: below it no drone camera could fly over a tag (5e-324 m gave
a division by zero in the simulator)."""


class ScreenConfig(StrictModel):
    """The size of the projected image on the floor, measured once the projector is fixed."""

    width_m: float = Field(
        2.17, ge=MIN_SCREEN_M, le=100, description="Width of the projected image in metres, 0.1 to 100."
    )
    height_m: float = Field(
        2.47, ge=MIN_SCREEN_M, le=100, description="Height of the projected image in metres, 0.1 to 100."
    )


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

    def _check_pads(self) -> None:
        """Every pad on the screen, no two overlapping. (Where their small tags go, and whether they fit, is
        the tag map's geometry: :func:`ipt.tagmap.pad_grid`, :func:`ipt.tagmap.pads_problem`.)"""
        half_w, half_h = self.screen.width_m / 2, self.screen.height_m / 2
        squares: list[tuple[float, float, float]] = []
        for pad in self.tag_map.pads:
            x, y = pad.centre_m
            s = pad.size_m / 2
            if not (-half_w <= x - s and x + s <= half_w and -half_h <= y - s and y + s <= half_h):
                raise ValueError(
                    f"landing pad '{pad.name}' ({pad.size_m:g} m square at {x:g}, {y:g}) is off the screen "
                    f"(x within ±{half_w:g} m, y within ±{half_h:g} m)"
                )
            for other, (ox, oy, os_) in zip(self.tag_map.pads, squares, strict=False):
                if abs(x - ox) < s + os_ and abs(y - oy) < s + os_:
                    raise ValueError(f"landing pads '{other.name}' and '{pad.name}' overlap")
            squares.append((x, y, s))

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


def load_arena_config(path: str | Path) -> ArenaConfig:
    """Load an arena YAML file (see the shipped ``arena.yaml``)."""
    return load_yaml_model(path, ArenaConfig)
