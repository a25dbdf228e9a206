"""Settings of the simulated arena: the drone's camera, the flight, its shadow, the content and the projector.

The defaults are a realistic flight, not a textbook one: a pilot-flown quadrotor that vibrates and casts
its own shadow under a ceiling projector, over photographic video that pans and cuts. Every effect has a
physical reason, given in its description, and can be switched off (``SimConfig.smooth()`` is the old,
kind flight: no shadow, no vibration, the slowly animated map). Scenario files
(``benchmarks/flights/*.yaml``) are YAML forms of this model.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from ipt.config.models import ArenaConfig, StrictModel, _describe_validation_error


class AutoGainConfig(StrictModel):
    """A camera's automatic gain: it drifts and steps between frames (lab cameras rarely lock it)."""

    drift_pct: float = Field(
        0.0, ge=0, le=50, description="Amplitude of the slow gain drift, percent of the gain (0: none)."
    )
    drift_period_s: float = Field(3.0, gt=0, le=3600, description="Period of the slow drift, seconds.")
    step_pct: float = Field(
        0.0, ge=0, le=50, description="Size of a sudden gain step, percent (each step up or down at random)."
    )
    steps_per_s: float = Field(0.0, ge=0, le=100, description="Mean number of gain steps per second (Poisson).")


class SimCameraConfig(StrictModel):
    """The drone's downward camera: optics, timing, sensor and what it sends."""

    width_px: int = Field(640, ge=32, le=8192, description="Image width in pixels.")
    height_px: int = Field(360, ge=32, le=8192, description="Image height in pixels.")
    fx_px: float = Field(460.0, gt=0, description="Focal length along x, pixels.")
    fy_px: float = Field(460.0, gt=0, description="Focal length along y, pixels.")
    cx_px: float = Field(319.5, description="Principal point x (OpenCV: pixel centres are integers).")
    cy_px: float = Field(179.5, description="Principal point y.")
    distortion: tuple[float, float, float, float, float] = Field(
        (-0.08, 0.03, 0.0004, -0.0003, 0.0), description="plumb_bob k1 k2 p1 p2 k3."
    )
    fps: float = Field(
        120.0,
        gt=0,
        le=1000,
        description="Frame rate; frame k is exposed around k / fps. Real '120 FPS' cameras run at 119.88 "
        "or drift: set it so, and the phase against the projector walks.",
    )
    exposure_ms: float = Field(4.0, gt=0, description="Exposure time, centred on the frame time.")
    readout_ms: float = Field(
        0.0,
        ge=0,
        description="Rolling shutter: the rows are exposed one after the other over this time, top row first "
        "(e.g. 6 for a Pi Camera Module 3 at 120 FPS), so a projector flip can land inside a frame. Frame k's "
        "time is the middle row's. 0: a global shutter.",
    )
    mono: bool = Field(
        False,
        description="A monochrome sensor (e.g. OV9281): frames are grey, the luminance of the light (Rec. 709 "
        "weights in linear light). False: an RGB camera.",
    )
    jpeg_quality: int | None = Field(
        None,
        ge=1,
        le=100,
        description="Each frame is JPEG-compressed at this quality, as a USB 2.0 camera must to carry 120 FPS "
        "(MJPEG; ~80 is typical). The blocks are quantised frame by frame, so they do not cancel when two "
        "frames are subtracted. null: uncompressed.",
    )
    auto_gain: AutoGainConfig = Field(
        default_factory=AutoGainConfig, description="Automatic gain drift and steps (none by default)."
    )
    vignetting: float = Field(
        0.0,
        ge=0,
        lt=1,
        description="Fraction of the light lost in the image corners (quadratic fall-off with the radius, "
        "as a small lens's relative illumination). 0: none.",
    )
    gain: float = Field(0.85, gt=0, description="Linear signal of full projector white (1 = saturation).")
    ambient: float = Field(0.04, ge=0, description="Room light on the floor, in units of projector white.")
    blur_sigma_px: float = Field(0.6, ge=0, description="Optical blur (Gaussian sigma) in camera pixels.")
    read_noise: float = Field(0.003, ge=0, description="Read noise, fraction of full scale (linear).")
    full_well_e: float = Field(4000.0, gt=0, description="Electrons at saturation (sets the shot noise).")
    supersample: int = Field(2, ge=1, le=4, description="Render at this multiple of the size, then average.")
    time_samples: int = Field(3, ge=1, le=16, description="Instants rendered per exposure (motion blur).")

    @model_validator(mode="after")
    def _check(self) -> SimCameraConfig:
        frame_s = 1.0 / self.fps
        if self.exposure_ms * 1e-3 > frame_s:
            raise ValueError(f"exposure {self.exposure_ms} ms is longer than a frame at {self.fps} FPS")
        if self.readout_ms * 1e-3 > frame_s:
            raise ValueError(f"readout_ms {self.readout_ms} is longer than a frame at {self.fps} FPS")
        return self


class VibrationConfig(StrictModel):
    """The airframe's attitude vibration on top of the tilt that follows acceleration."""

    amplitude_deg: float = Field(
        1.5,
        ge=0,
        le=20,
        description="Peak roll and pitch oscillation in degrees (a hand-flown 250-class quadrotor: 1-2°). At "
        "6 Hz, 1.5° is an angular rate of up to ~60°/s: about 1° between frames one projector period apart.",
    )
    frequency_hz: tuple[float, float] = Field(
        (5.0, 7.0), description="Band of the oscillation's frequencies (its attitude loop's; several mixed)."
    )
    yaw_amplitude_deg: float = Field(0.4, ge=0, le=20, description="Peak yaw oscillation in the same band.")

    @field_validator("frequency_hz")
    @classmethod
    def _band(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not 0 < v[0] <= v[1] <= 100:
            raise ValueError(f"frequency_hz must be a band 0 < low <= high <= 100 Hz, got {list(v)}")
        return v


class PilotConfig(StrictModel):
    """The pilot's corrections: slow wandering about the intended path, which adds accelerations (tilt)."""

    drift_m: float = Field(
        0.03, ge=0, le=1, description="Peak distance from the intended path, metres (each horizontal axis)."
    )
    drift_hz: tuple[float, float] = Field(
        (0.2, 0.7), description="Band of the corrections' frequencies (a pilot's: a second or two)."
    )

    @field_validator("drift_hz")
    @classmethod
    def _band(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not 0 < v[0] <= v[1] <= 20:
            raise ValueError(f"drift_hz must be a band 0 < low <= high <= 20 Hz, got {list(v)}")
        return v


class TakeoffConfig(StrictModel):
    """Path 'takeoff': up from the landing pad, a hover high up, and back down (repeated if longer)."""

    low_m: float = Field(0.25, gt=0.05, le=10, description="Camera height on the pad before take-off, metres.")
    high_m: float = Field(2.2, gt=0.05, le=10, description="Camera height at the top, metres.")
    hold_low_s: float = Field(0.5, ge=0, le=600, description="Time at low_m before the climb (and after landing).")
    climb_s: float = Field(3.0, gt=0, le=600, description="Duration of the climb (and of the descent).")
    hold_high_s: float = Field(1.0, ge=0, le=600, description="Time at high_m between climb and descent.")

    @model_validator(mode="after")
    def _check(self) -> TakeoffConfig:
        if self.high_m <= self.low_m:
            raise ValueError(f"high_m ({self.high_m}) must be above low_m ({self.low_m})")
        return self


class SimFlightConfig(StrictModel):
    """Where the drone flies: a path, then a pilot's wandering and the airframe's vibration on top."""

    path: Literal["rectangle", "takeoff", "hover"] = Field(
        "rectangle",
        description="'rectangle': the paper's flight, corner to corner at altitude_m. 'takeoff': climb and "
        "descent over centre_m (see takeoff). 'hover': over centre_m at altitude_m.",
    )
    size_m: tuple[float, float] = Field((1.0, 1.2), description="Rectangle sides along arena x and y.")
    centre_m: tuple[float, float] = Field((0.0, 0.0), description="Rectangle centre (or hover point) in the arena.")
    altitude_m: float = Field(0.8, gt=0.1, le=10, description="Mean camera height above the floor.")
    altitude_wobble_m: float = Field(0.03, ge=0, description="Amplitude of the slow height wobble.")
    peak_speed_mps: float = Field(1.0, gt=0, le=10, description="Top speed, reached mid-edge (rectangle).")
    heading_deg: float = Field(0.0, description="Mean heading (yaw of the body x axis from arena x).")
    yaw_wobble_deg: float = Field(8.0, ge=0, le=90, description="Amplitude of the slow yaw wobble.")
    takeoff: TakeoffConfig = Field(default_factory=TakeoffConfig, description="The 'takeoff' path's profile.")
    vibration: VibrationConfig | None = Field(
        default_factory=VibrationConfig, description="Attitude vibration; null: none (a textbook flight)."
    )
    pilot: PilotConfig | None = Field(
        default_factory=PilotConfig, description="The pilot's wandering about the path; null: none."
    )


class ShadowConfig(StrictModel):
    """The drone's own shadow: its body between the projector and the floor."""

    radius_m: float = Field(
        0.17,
        gt=0,
        le=2,
        description="Radius of the body as a disk, metres (0.17: a 270 mm quadrotor with its propellers).",
    )
    opacity: float = Field(1.0, ge=0, le=1, description="Fraction of the projector's light the disk stops (1: opaque).")
    projector_position_m: tuple[float, float, float] = Field(
        (0.3, 0.0, 3.0),
        description="The projector lens in the arena frame, metres (a ceiling mount: 3 m up, 0.3 m off "
        "centre). The shadow falls along the lines from it, so it is H/(H-h) times the body and moves with "
        "the drone.",
    )
    aperture_m: float = Field(
        0.04,
        ge=0,
        le=1,
        description="Diameter of the projector's lens: the shadow's soft edge (penumbra) is this times h/(H-h).",
    )

    @field_validator("projector_position_m")
    @classmethod
    def _above(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not 0.5 <= v[2] <= 100:
            raise ValueError(f"the projector must be 0.5-100 m above the floor, got z = {v[2]}")
        return v


class SimContentConfig(StrictModel):
    """What the projector shows (before the tags are hidden in it)."""

    kind: Literal["photos", "map", "dark"] = Field(
        "photos",
        description="'photos': photographic scenes that pan and cut (a video never seen before); 'map': the "
        "built-in map app of the paper's experiment, slowly animated; 'dark': a dark AR scene (night-mode map, "
        "game): the photographs dimmed to a tenth under bright thin lines and labels that pan. `ipt sim "
        "--content FILE` shows a video file or image folder instead.",
    )
    pan_px_per_frame: tuple[float, float] = Field(
        (3.0, 10.0),
        description="'photos' and 'dark': the pan's speed in projector pixels per content frame, varying within "
        "this band.",
    )
    cut_every_s: float = Field(2.5, gt=0, le=3600, description="'photos' and 'dark': seconds between scene cuts.")

    @field_validator("pan_px_per_frame")
    @classmethod
    def _band(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not 0 <= v[0] <= v[1] <= 200:
            raise ValueError(f"pan_px_per_frame must be a band 0 <= low <= high <= 200, got {list(v)}")
        return v


class KeystoneConfig(StrictModel):
    """A projector mounted off-axis: its image lands on the floor as a quadrilateral, not the arena's layout.

    The receiver is told the arena file's layout; the floor truly gets this one. ``ipt sim`` also writes the
    survey a user would make of it (``survey.csv``: marks measured with a tape), for ``ipt calibrate arena``."""

    corner_shift_m: tuple[
        tuple[float, float], tuple[float, float], tuple[float, float], tuple[float, float]
    ] = Field(
        ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0)),
        description="Where the projected image's corners truly land, (dx, dy) metres from where the arena file "
        "puts them, in the order top-left, top-right, bottom-right, bottom-left of the image (projector pixels "
        "(0, 0), (W, 0), (W, H), (0, H)). The image between them follows the homography they define.",
    )
    tile_corner_shift_m: (
        tuple[tuple[tuple[float, float], tuple[float, float], tuple[float, float], tuple[float, float]], ...] | None
    ) = Field(
        None,
        description="For an arena of several projectors (its projectors: tiles): the same per tile, in the "
        "tiles' order, each of its corners in its own part of the canvas (then corner_shift_m is not used). "
        "Survey marks are a survey_grid in each tile.",
    )
    survey_grid: tuple[int, int] = Field(
        (3, 3),
        description="The survey's marks: columns x rows of projector pixels spread over the image, 5 % in from "
        "its edges (what 'ipt calibrate arena --marks --grid' draws).",
    )
    survey_noise_m: float = Field(
        0.001, ge=0, le=0.1, description="Standard deviation of each measured coordinate of a mark, metres."
    )

    @model_validator(mode="after")
    def _small(self) -> KeystoneConfig:
        shifts = [self.corner_shift_m, *(self.tile_corner_shift_m or ())]
        if any(not math.isfinite(c) or abs(c) > 5 for corners in shifts for corner in corners for c in corner):
            raise ValueError("corner_shift_m: each shift must be finite and within 5 m")
        return self

    @field_validator("survey_grid")
    @classmethod
    def _grid(cls, v: tuple[int, int]) -> tuple[int, int]:
        if not (1 <= v[0] <= 50 and 1 <= v[1] <= 50 and v[0] * v[1] >= 4):
            raise ValueError(f"survey_grid: 1-50 columns and rows, 4 marks or more, got {list(v)}")
        return v


class SimConfig(StrictModel):
    """The simulated arena: a camera flying over the projected, modulated floor."""

    description: str = Field("", max_length=2000, description="What this flight is for (shown by the suite).")
    camera: SimCameraConfig = Field(default_factory=SimCameraConfig, description="The drone's camera.")
    flight: SimFlightConfig = Field(default_factory=SimFlightConfig, description="The flight path.")
    shadow: ShadowConfig | None = Field(
        default_factory=ShadowConfig, description="The drone's shadow on the floor; null: none."
    )
    content: SimContentConfig = Field(default_factory=SimContentConfig, description="The projected content.")
    projector_offset_ms: float = Field(
        1.3, description="Time of the projector's first frame flip after t = 0 (phase against the camera)."
    )
    projector_clock_ppm: float = Field(
        0.0, ge=-1e5, le=1e5, description="Projector clock error in ppm (e.g. -1000 for 59.94 Hz at 60 Hz)."
    )
    projector_dither_levels: int = Field(
        1,
        ge=0,
        le=8,
        description="The projector's own temporal dithering: each output pixel is moved up or down by up to "
        "this many 8-bit levels, afresh every projector frame (DLP and LCD projectors dither). 0: none.",
    )
    keystone: KeystoneConfig | None = Field(
        None,
        description="The projector's image lands keystoned on the floor (the receiver is not told, unless it is "
        "given a calibrated arena); null: exactly where the arena file says.",
    )
    arena: dict[str, Any] = Field(
        default_factory=dict,
        description="Changes to the arena for this flight, e.g. {modulation: {delta_l: 3}}: merged into the "
        "arena file given to `ipt sim`. The receiver is scored with the merged arena too.",
    )
    seed: int = Field(0, ge=0, description="Seed for the noise, the pilot, the vibration and the content.")

    @field_validator("arena")
    @classmethod
    def _arena_changes_fit(cls, v: dict[str, Any]) -> dict[str, Any]:
        apply_arena_changes(ArenaConfig(), v)
        return v

    @classmethod
    def smooth(cls, **changes: Any) -> SimConfig:
        """The kind, textbook flight of earlier versions: no shadow, vibration or pilot, the map app."""
        base = cls(
            flight=SimFlightConfig(vibration=None, pilot=None),
            shadow=None,
            content=SimContentConfig(kind="map"),
            projector_dither_levels=0,
        )
        return base.model_copy(update=changes)


def _merge(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def apply_arena_changes(arena: ArenaConfig, changes: dict[str, Any]) -> ArenaConfig:
    """``arena`` with a flight's ``arena:`` changes merged in; ``ValueError`` naming the key otherwise."""
    if not changes:
        return arena
    try:
        return ArenaConfig.model_validate(_merge(arena.model_dump(), changes))
    except ValidationError as exc:
        raise ValueError(f"arena: {_describe_validation_error(exc)}") from None


def describe_flight(sim: SimConfig) -> str:
    """One line saying what the flight has (for the demo's and the suite's output)."""
    f, cam = sim.flight, sim.camera
    if f.path == "rectangle":
        parts = [
            f"a {f.size_m[0]:g} x {f.size_m[1]:g} m rectangle at {f.altitude_m:g} m, up to {f.peak_speed_mps:g} m/s"
        ]
    elif f.path == "takeoff":
        parts = [f"take-off from {f.takeoff.low_m:g} m to {f.takeoff.high_m:g} m and back"]
    else:
        parts = [f"a hover at {f.altitude_m:g} m"]
    if f.pilot is not None:
        parts.append(f"hand-flown (±{100 * f.pilot.drift_m:g} cm)")
    if f.vibration is not None:
        lo, hi = f.vibration.frequency_hz
        parts.append(f"vibrating ±{f.vibration.amplitude_deg:g}° at {lo:g}-{hi:g} Hz")
    if sim.shadow is not None:
        z = sim.shadow.projector_position_m[2]
        parts.append(f"its shadow ({sim.shadow.radius_m:g} m body, projector {z:g} m up)")
    if sim.content.kind == "photos":
        lo, hi = sim.content.pan_px_per_frame
        parts.append(f"over photographs panning {lo:g}-{hi:g} px/frame")
    elif sim.content.kind == "dark":
        parts.append("over a dark scene (photographs dimmed to a tenth, bright lines and labels)")
    else:
        parts.append("over the map app")
    sensor = "mono" if cam.mono else "colour"
    shutter = f"rolling shutter {cam.readout_ms:g} ms" if cam.readout_ms else "global shutter"
    extra = [f"MJPEG q{cam.jpeg_quality}"] if cam.jpeg_quality is not None else []
    if cam.auto_gain.drift_pct or cam.auto_gain.step_pct:
        extra.append("auto-gain")
    if cam.vignetting:
        extra.append("vignetting")
    parts.append(
        f"{sensor} {cam.width_px}x{cam.height_px} camera at {cam.fps:g} FPS, {shutter}"
        + "".join(f", {e}" for e in extra)
    )
    return "; ".join(parts)
