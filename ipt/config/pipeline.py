"""The receiver's processing settings: demodulation, tag detection, tracking and pose (:class:`PipelineConfig`).

Units are in the field names; :meth:`PipelineConfig.profile` gives the named profiles (:data:`PROFILES`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

from pydantic import Field, field_validator

from ipt.config.base import ConfigError, StrictModel

if TYPE_CHECKING:
    from ipt.config.camera_info import CameraInfo

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
        "straddles a flip. 0: each pose as soon as its frame is processed, from earlier frames only. With 2, a "
        "frame no pair solved waits one frame more, for the bridge across a content change with the frame three "
        "on (ipt.receiver.core.bridge).",
    )
    work_width_px: int = Field(
        640,
        ge=0,
        le=100_000,
        description="With 'gradient' alignment: a camera at least twice this wide has each frame's lightness "
        "binned before anything else (each k x k block of pixels averaged, k the largest whole number that "
        "keeps it at least this wide and divides both sides), and the receiver works with the coarser camera "
        "that makes (its pixel sizes, e.g. max_reprojection_rms_px, are then that camera's). The ipt profile's "
        "settings are made for about 640 pixels across: a 1280x720 camera's frames then cost less than half as "
        "much and are posed at least as precisely. 0: never bin.",
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

    def binning(self, camera: CameraInfo) -> int:
        """The side of the pixel blocks ``camera``'s frames are averaged over (:attr:`work_width_px`; 1: none)."""
        return camera.binning_for(self.work_width_px) if self.alignment == "gradient" else 1


class DetectorConfig(StrictModel):
    """AprilTag 3 (dt-apriltags: the C library pupil-apriltags ships, with aarch64 wheels) settings."""

    quad_decimate: float = Field(
        3.0,
        ge=1.0,
        le=8.0,
        description="Decimation before quad detection (edges are refined at full size): 1 (none), 1.5 or a "
        "whole number, the factors AprilTag carries out (it shrinks the image by the whole part of any other "
        "and then misplaces every quad). 3 finds as many tags as 2 on the binary tag image at 640x360 and "
        "1280x720, as accurately, in two thirds of the time; smaller tags in view get less "
        "(ipt/receiver/core/scales.py).",
    )
    quad_sigma: float = Field(0.0, ge=0.0, le=5.0, description="Gaussian blur sigma before quad detection.")
    refine_edges: bool = Field(True, description="Snap quad edges to strong gradients.")
    decode_sharpening: float = Field(0.25, ge=0.0, le=2.0, description="Sharpening of decoded images.")
    threads: int = Field(1, ge=1, le=16, description="Detector worker threads.")
    max_hamming: int = Field(
        1, ge=0, le=2, description="Bit errors a decode may have: AprilTag's table corrects this many, no more."
    )
    border_margin_px: float = Field(
        2.0,
        ge=0.0,
        description="Tags with a corner closer than this to the image edge are dropped: a tag cut by the edge "
        "can still decode, with the edge taken for its border.",
    )
    isolation: Literal["process", "inline"] = Field(
        "process",
        description="Where AprilTag's C code runs. 'process': in a helper process that is replaced, without "
        "a gap in detection, once its memory grew by recycle_mb (the C library leaks tens to hundreds of "
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

    @field_validator("quad_decimate")
    @classmethod
    def _honoured(cls, value: float) -> float:
        if value != 1.5 and value != int(value):
            raise ValueError(f"{value:g} is not a factor AprilTag carries out: use 1, 1.5, 2, 3, ... 8")
        return value


class TrackConfig(StrictModel):
    """Pose from every visible edge of the hidden map (method 'track', see ipt/receiver/core/track.py)."""

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
        description="The camera has a rolling shutter (most Pi and USB cameras; set it as you would tell a VIO "
        "system): fit, beside each frame's pose (that of its centre row), how the pose moves from the top row "
        "to the bottom one while the drone vibrates, and let the motion gate allow for the pose's larger "
        "uncertainty (3 sigma). Measured on the suite's 8 s rolling flight (6 ms readout): yield 74.1 -> "
        "87.4 %, X/Y/Z MAE 5.7/3.0/1.9 -> 5.6/3.3/1.3 mm (the sweep with a fixed gate: 76.8 %). Off by "
        "default: on a global shutter the six extra unknowns fit noise (shadow-vibration: X MAE 1.9 -> 3.8 "
        "mm, yaw 0.04 -> 0.11 deg).",
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
        "this speed allows, plus 5 cm (2.5 cm until 8 poses went out in that time: the start, after a gap), is "
        "rejected as doubtful. None turns the gate off.",
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
    tracker: Literal["dense", "sparse"] = Field(
        "sparse",
        description="How a frame is posed once the track runs ('track' pose method). 'sparse' (the default): "
        "first the sparse chain (ipt.receiver.core.sparsechain), which reads the raw frames only along the map's "
        "edges; a frame it does not pose, acquisition and a check every few frames take the dense way "
        "(docs/receiver-cores.md, 'The sparse tracker in the pipeline'). 'dense': every frame undistorted, aligned "
        "with its partners by their content and their difference tracked (ipt.receiver.core.track): slower, for "
        "comparison.",
    )

    @property
    def luminance_only(self) -> bool:
        """Whether a frame's luma is all the processing needs (lightness 'luma'): frame sources then hand
        over grey frames, taken without a detour through RGB (a YUV camera's Y plane, a JPEG decoded to
        grey). The paper's CIELAB lightness needs the colours."""
        return self.demodulation.lightness == "luma"

    def with_rolling_shutter(self) -> PipelineConfig:
        """These settings told that the camera has a rolling shutter (``pose.track.rolling_shutter``, as a
        receiver.yaml sets it for such a camera)."""
        track = self.pose.track.model_copy(update={"rolling_shutter": True})
        return self.model_copy(update={"pose": self.pose.model_copy(update={"track": track})})

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
