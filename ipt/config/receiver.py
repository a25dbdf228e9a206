"""Settings of the receiver daemon (``ipt-receiver run``): where frames come from and where poses go.

Relative paths in a receiver YAML file (``arena``, ``camera``, ``auth_key_file`` and the path of a
``video:`` source) are resolved against the folder of that file, so a config and its companions can be
moved together. Paths given on the command line are relative to the working directory as usual.
"""

from __future__ import annotations

import importlib.util
import re
import termios
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, ValidationError, field_validator

from ipt.config.models import (
    ConfigError,
    PipelineConfig,
    StrictModel,
    _describe_validation_error,
    load_yaml_model,
)
from ipt.keyfile import KeyFileError, read_key_file

FOURCC_ALIASES = {"Y800": "GREY", "Y8  ": "GREY", "JPEG": "MJPG", "YUY2": "YUYV"}
"""Other names of the V4L2 pixel formats the receiver decodes itself, as camera documentation uses them."""

DEFAULT_SEND_TARGET = "127.0.0.1:9870"
"""Where poses go unless configured otherwise: a listener on this machine."""

SourceKind = Literal["sim", "video", "images", "device", "picamera2"]

SOURCE_FORMS = "sim, video:PATH, images:DIR, device:N or picamera2[:N]"


@dataclass(frozen=True)
class SourceSpec:
    """A parsed ``source`` value: ``sim``, ``video:PATH``, ``images:DIR``, ``device:N`` or ``picamera2[:N]``."""

    kind: SourceKind
    path: Path | None = None
    """The recording, for ``video`` (a file or a folder) and ``images`` (a folder)."""
    device: int | None = None
    """The V4L2 device number (``/dev/videoN``) for ``device``; the camera number for ``picamera2``."""

    def __str__(self) -> str:
        if self.kind in ("video", "images"):
            return f"{self.kind}:{self.path}"
        if self.kind in ("device", "picamera2"):
            return f"{self.kind}:{self.device}"
        return "sim"


def parse_source(text: str) -> SourceSpec:
    """A ``source`` value as a :class:`SourceSpec`; ``ValueError`` naming the accepted forms otherwise."""
    if text == "sim":
        return SourceSpec("sim")
    if text == "picamera2":
        return SourceSpec("picamera2", device=0)
    kind, sep, arg = text.partition(":")
    if sep and kind in ("video", "images"):
        if not arg:
            raise ValueError(f"{kind}: needs a path, as in {kind}:{'flight.mkv' if kind == 'video' else 'frames/'}")
        if "\0" in arg:
            raise ValueError(f"{kind}: the path cannot contain a NUL character")
        return SourceSpec("video" if kind == "video" else "images", path=Path(arg))
    if sep and kind in ("device", "picamera2"):
        if not re.fullmatch(r"[0-9]{1,3}", arg):
            raise ValueError(f"{kind}: needs a camera number, as in {kind}:0, got {arg!r}")
        return SourceSpec("device" if kind == "device" else "picamera2", device=int(arg))
    raise ValueError(f"source must be {SOURCE_FORMS}, got {text!r}")


def parse_host_port(text: str) -> tuple[str, int]:
    """``"HOST:PORT"`` (or ``"[IPv6]:PORT"``) as ``(host, port)``; ``ValueError`` otherwise."""
    m = re.fullmatch(r"\[([0-9A-Fa-f:.%a-zA-Z]+)\]:([0-9]{1,5})|([^\s:\[\]]+):([0-9]{1,5})", text)
    if m is None:
        raise ValueError(f"send target must be HOST:PORT (or [IPv6]:PORT), got {text!r}")
    host = m.group(1) or m.group(3)
    port = int(m.group(2) or m.group(4))
    if not 1 <= port <= 65535:
        raise ValueError(f"send target {text!r}: port {port} is outside 1..65535")
    return host, port


@dataclass(frozen=True)
class LinkSpec:
    """A parsed MAVLink link: ``udpout:HOST:PORT`` or ``serial:DEVICE:BAUD``."""

    kind: Literal["udpout", "serial"]
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0

    def __str__(self) -> str:
        if self.kind == "udpout":
            host = f"[{self.host}]" if ":" in self.host else self.host
            return f"udpout:{host}:{self.port}"
        return f"serial:{self.device}:{self.baud}"


def parse_link(text: str) -> LinkSpec:
    """``udpout:HOST:PORT`` or ``serial:DEVICE:BAUD`` as a :class:`LinkSpec`; ``ValueError`` otherwise."""
    kind, sep, rest = text.partition(":")
    if sep and kind == "udpout":
        try:
            host, port = parse_host_port(rest)
        except ValueError:
            raise ValueError(f"udpout: needs HOST:PORT, as in udpout:127.0.0.1:14540, got {text!r}") from None
        return LinkSpec("udpout", host=host, port=port)
    if sep and kind == "serial":
        device, sep2, baud_text = rest.rpartition(":")
        if not sep2 or not device or not re.fullmatch(r"[0-9]{3,8}", baud_text):
            raise ValueError(f"serial: needs DEVICE:BAUD, as in serial:/dev/ttyAMA0:921600, got {text!r}")
        baud = int(baud_text)
        if not hasattr(termios, f"B{baud}"):
            raise ValueError(f"serial: {baud} is not a baud rate this system supports (e.g. 57600, 115200, 921600)")
        return LinkSpec("serial", device=device, baud=baud)
    raise ValueError(f"a MAVLink link must be udpout:HOST:PORT or serial:DEVICE:BAUD, got {text!r}")


MAX_CAMERA_OFFSET_M = 10.0
"""Largest camera offset from the body origin accepted along each axis (a drone is not 20 m across)."""

Vector3 = tuple[float, float, float]
Matrix3 = tuple[Vector3, Vector3, Vector3]
OffsetM = Annotated[float, Field(ge=-MAX_CAMERA_OFFSET_M, le=MAX_CAMERA_OFFSET_M)]


class MavlinkConfig(StrictModel):
    """MAVLink to the flight controller (see docs/flight-controllers.md): off unless ``link`` is set.

    Every number must be finite (``nan`` or ``.inf`` is refused when the file loads, naming the key): a
    NaN lever arm made every ODOMETRY unsendable, a huge one overflowed the packing and ended the daemon.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    link: str | None = Field(
        None,
        description="Where the autopilot is: 'udpout:HOST:PORT' (UDP to that address, replies read from it) or "
        "'serial:DEVICE:BAUD' (e.g. serial:/dev/ttyAMA0:921600). null: no MAVLink output.",
    )
    dialect: str = Field(
        "common",
        description="pymavlink dialect to encode with (common, ardupilotmega, development, ...); every one that "
        "includes common.xml has the messages used here.",
    )
    system_id: int = Field(
        1, ge=1, le=255, description="MAVLink system id: the vehicle's (the autopilot's MAV_SYS_ID / SYSID_THISMAV)."
    )
    component_id: int = Field(
        197,
        ge=1,
        le=255,
        description="MAVLink component id of this receiver (197: MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY).",
    )
    odometry: bool = Field(True, description="Send ODOMETRY (frame MAV_FRAME_LOCAL_FRD, child MAV_FRAME_BODY_FRD).")
    max_rate_hz: float | None = Field(
        50.0,
        gt=0,
        le=1000,
        description="At most this many ODOMETRY (and VISION_POSITION_ESTIMATE) per second of capture time: "
        "consecutive ones are at least 1/max_rate_hz apart, and each carries the newest pose. ArduPilot's EKF "
        "drops external navigation closer than 20 ms to the last it took, PX4's EKF2 samples closer than its "
        "observation interval (about 10 ms by default). null: every pose.",
    )
    vision_position_estimate: bool = Field(
        False, description="Also send VISION_POSITION_ESTIMATE (for autopilots that do not take ODOMETRY)."
    )
    r_frd_cam: Matrix3 | None = Field(
        None,
        description="Camera mounting: the 3x3 rotation camera (OpenCV optical: x right, y down, z forward) -> body "
        "FRD, as three rows. null: looking straight down with the top of the image towards the nose, i.e. "
        "[[0, -1, 0], [1, 0, 0], [0, 0, 1]].",
    )
    camera_position_frd_m: tuple[OffsetM, OffsetM, OffsetM] = Field(
        (0.0, 0.0, 0.0),
        description="The camera's optical centre from the body origin, body FRD metres (each within ±10 m). Set it "
        "here OR in the autopilot (EKF2_EV_POS_X/Y/Z, VISO_POS_X/Y/Z), never both: here, the poses sent are the "
        "body origin's.",
    )
    fix_timeout_s: float = Field(
        0.5,
        gt=0,
        le=60,
        description="No pose for this long after one: the fix is lost (STATUSTEXT, HEARTBEAT standby).",
    )
    reset_jump_m: float = Field(
        0.5,
        gt=0,
        le=1000,
        description="A pose this far from the previous one sent increments reset_counter (as does a re-initialised "
        "track), so the autopilot resets to it rather than fighting the step.",
    )
    zero_quality_std_m: float = Field(
        0.1,
        ge=0.001,
        le=100,
        description="quality falls linearly from 100 (no position uncertainty) to 1 at this 3-D position standard "
        "deviation.",
    )
    min_attitude_std_rad: float = Field(
        0.005,
        ge=0,
        le=1,
        description="Floor on each attitude standard deviation reported (radians; 0.005 is 0.3 degrees): the pose's "
        "own attitude uncertainty is used when larger.",
    )
    autopilot_timeout_s: float = Field(
        5.0, gt=0, le=600, description="Say so on stderr when no autopilot HEARTBEAT was heard for this long."
    )

    @field_validator("link")
    @classmethod
    def _check_link(cls, value: str | None) -> str | None:
        if value is not None:
            parse_link(value)
        return value

    @field_validator("dialect")
    @classmethod
    def _check_dialect(cls, value: str) -> str:
        if (
            not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", value)
            or importlib.util.find_spec(f"pymavlink.dialects.v20.{value}") is None
        ):
            raise ValueError(f"unknown MAVLink dialect {value!r} (e.g. common, ardupilotmega, development)")
        return value

    @field_validator("r_frd_cam")
    @classmethod
    def _check_rotation(cls, value: Matrix3 | None) -> Matrix3 | None:
        if value is None:
            return value
        r = [list(row) for row in value]
        for i in range(3):
            for j in range(3):
                dot = sum(r[k][i] * r[k][j] for k in range(3))
                if abs(dot - (1.0 if i == j else 0.0)) > 1e-4:
                    raise ValueError("must be a rotation matrix (orthonormal rows)")
        det = (
            r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1])
            - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
            + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
        )
        if det < 0:
            raise ValueError("must be a rotation (determinant +1), not a reflection")
        return value

    @property
    def link_spec(self) -> LinkSpec | None:
        """The parsed :attr:`link`."""
        return None if self.link is None else parse_link(self.link)


_ROS_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")


class Ros2Config(StrictModel):
    """ROS 2 topics over DDS (see README "ROS 2"): off unless enabled (or ``--ros2``)."""

    enabled: bool = Field(False, description="Publish /ipt/pose, /ipt/odom and /tf over DDS (needs ipt[ros2]).")
    domain_id: int | None = Field(
        None,
        ge=0,
        le=232,
        description="DDS domain (ROS_DOMAIN_ID). null: the environment's ROS_DOMAIN_ID, else 0. The network "
        "setup comes from CYCLONEDDS_URI, as for any CycloneDDS program.",
    )
    qos: Literal["sensor_data", "reliable"] = Field(
        "sensor_data",
        description="QoS of /ipt/pose and /ipt/odom: 'sensor_data' (best effort, keep last 5: a subscriber must "
        "ask for best effort or sensor data QoS, or it gets nothing) or 'reliable' (keep last 10; any "
        "subscriber matches). /tf is always reliable, keep last 100, as tf2 listeners expect.",
    )
    namespace: str | None = Field(
        None,
        description="This vehicle's name when several fly: topics become /ipt/<namespace>/pose ... and the body "
        "frames <namespace>/base_link and <namespace>/camera. null: /ipt/pose, base_link, camera.",
    )
    frame_id: str = Field("arena", min_length=1, description="The arena's frame (header.frame_id of the poses).")
    base_frame_id: str = Field(
        "base_link", min_length=1, description="The vehicle body's frame (FLU), placed by the MAVLink mounting."
    )
    camera_frame_id: str = Field(
        "camera", min_length=1, description="The camera's frame (OpenCV optical axes: x right, y down, z forward)."
    )
    tf: bool = Field(True, description="Also publish arena -> camera and arena -> base_link on /tf.")

    @field_validator("namespace")
    @classmethod
    def _check_namespace(cls, value: str | None) -> str | None:
        if value is not None and not _ROS_NAME.fullmatch(value):
            raise ValueError(f"must be a ROS name (a letter, then letters, digits or _), got {value!r}")
        return value

    @field_validator("frame_id", "base_frame_id", "camera_frame_id")
    @classmethod
    def _check_frame(cls, value: str) -> str:
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_/]*", value):
            raise ValueError(f"must be a frame name (letters, digits, _ and /), got {value!r}")
        return value


class RecordConfig(StrictModel):
    """The flight log (``--record``): an MCAP file that Foxglove and ros2 bag open."""

    path: Path | None = Field(
        None,
        description="Where to write the MCAP recording (relative to this file's folder); null: no recording. "
        "It is written as PATH.partial beside it and renamed when the run ends.",
    )
    image_hz: float = Field(
        0.0,
        ge=0,
        le=30,
        description="Also record the raw difference image (the frame minus the one a projector period before, "
        "before any alignment) this many times per second of capture time, JPEG, on /ipt/difference. 0: none.",
    )

    @field_validator("path")
    @classmethod
    def _check_path(cls, value: Path | None) -> Path | None:
        if value is not None and "\0" in str(value):
            raise ValueError("a file name cannot contain a NUL character")
        return value


class CameraControls(StrictModel):
    """Settings of a real camera (device:N or picamera2), applied when it is opened."""

    exposure_us: float | None = Field(
        None,
        gt=0,
        le=1_000_000,
        description="Manual exposure time in microseconds (keep it under one frame; short exposures blur less). "
        "null: leave the camera's current exposure.",
    )
    gain: float | None = Field(
        None,
        ge=0,
        description="Manual gain: the V4L2 driver's own units for device:N, the analogue gain for picamera2. "
        "null: leave it.",
    )
    auto_exposure: bool = Field(
        False,
        description="Leave automatic exposure on. Off by default: it changes the brightness between the two frames "
        "the tags are recovered from.",
    )
    auto_white_balance: bool = Field(False, description="Leave automatic white balance on (off by default).")
    fourcc: str | None = Field(
        None,
        min_length=4,
        max_length=4,
        description="V4L2 pixel format to ask a device:N camera for (its four-character code, as "
        "'v4l2-ctl --list-formats-ext' lists them). The receiver takes the luma straight from 'GREY' (8-bit mono, "
        "also called Y8 or Y800), 'YUYV' (its Y bytes) and 'MJPG' (JPEG decoded to grey; many USB cameras reach "
        "120 FPS only compressed), without OpenCV's conversion to RGB; any other format is converted by OpenCV. "
        "null: the driver's default. (A picamera2 camera gives the Y plane of YUV420 by itself.)",
    )

    @field_validator("fourcc")
    @classmethod
    def _check_fourcc(cls, value: str | None) -> str | None:
        if value is None:
            return value
        if not re.fullmatch(r"[A-Z0-9][A-Z0-9 ]{3}", value):
            raise ValueError(f"must be a V4L2 pixel format code such as GREY, YUYV or MJPG, got {value!r}")
        return FOURCC_ALIASES.get(value, value)


class ReceiverConfig(StrictModel):
    """The receiver daemon: camera, arena, frame source, pose outputs and the processing."""

    arena: Path = Field(
        description="Arena YAML (projector, screen, tag map, modulation); relative to this file's folder."
    )
    camera: Path = Field(
        description="ROS camera_info YAML of the drone's camera (its size is the frame size expected); "
        "relative to this file's folder."
    )
    source: str = Field(
        "sim",
        description="Where frames come from: 'sim' (the simulated arena, rendered live), 'video:PATH' "
        "(a video file or image folder; PATH relative to this file's folder), 'images:DIR' (a folder of images, in "
        "name order), 'device:N' (V4L2 camera /dev/videoN through OpenCV) or 'picamera2[:N]' (a Raspberry Pi "
        "camera through picamera2). 'ipt-receiver --list-cameras' says which cameras are there.",
    )
    fps: float | None = Field(
        None,
        ge=1,  # ipt.config.models.MIN_CAMERA_RATE_HZ: a pacing wait of 1/fps must stay a sane number
        le=1000,
        description="Camera frame rate in Hz. Default: the video file's rate; 120 for the simulator; the "
        "device's own setting for a camera.",
    )
    realtime: bool = Field(
        False,
        description="Pace a 'video' or 'sim' source to its frame rate and treat it as a live camera (the "
        "newest frame wins when processing falls behind). A 'device' source is always live.",
    )
    vehicle_id: int = Field(0, ge=0, le=65535, description="This drone's id in the pose packets (uint16).")
    send: list[str] = Field(
        default_factory=lambda: [DEFAULT_SEND_TARGET],
        min_length=1,
        max_length=16,
        description="UDP destinations of the pose packets, each 'HOST:PORT'; every pose goes to every one.",
    )
    auth_key_file: Path | None = Field(
        None,
        description="File holding the shared authentication key (at least 16 bytes; one trailing newline is "
        "ignored); read once at start. Without it the packets are sent unauthenticated.",
    )
    stats_interval_s: float = Field(
        5.0,
        ge=0.1,  # 1e-6 printed 13,051 lines in 1.4 s
        le=3600,
        description="Seconds between the statistics lines printed on stderr (0.1 to 3600).",
    )
    queue_size: int = Field(
        1,
        ge=1,
        le=64,
        description="Frames held between capture and processing when reading a recording. A live camera ignores "
        "it: it keeps the newest three and hands them over as a run of consecutive frames when processing "
        "is behind (a pose needs frames close together), the newest alone when it keeps up.",
    )
    camera_controls: CameraControls = Field(
        default_factory=CameraControls, description="Exposure, gain and automatic controls of a real camera."
    )
    mavlink: MavlinkConfig = Field(
        default_factory=MavlinkConfig, description="MAVLink output to the flight controller (off unless link is set)."
    )
    ros2: Ros2Config = Field(default_factory=Ros2Config, description="ROS 2 topics over DDS (off unless enabled).")
    record: RecordConfig = Field(
        default_factory=RecordConfig, description="The MCAP flight log (off unless a path is set)."
    )
    pipeline: PipelineConfig = Field(default_factory=PipelineConfig, description="The per-frame processing.")

    @field_validator("arena", "camera", "auth_key_file")
    @classmethod
    def _check_path(cls, value: Path | None) -> Path | None:
        if value is not None and "\0" in str(value):
            raise ValueError("a file name cannot contain a NUL character")
        return value

    @field_validator("source")
    @classmethod
    def _check_source(cls, value: str) -> str:
        parse_source(value)
        return value

    @field_validator("send")
    @classmethod
    def _check_send(cls, value: list[str]) -> list[str]:
        for target in value:
            parse_host_port(target)
        return value

    @property
    def source_spec(self) -> SourceSpec:
        """The parsed :attr:`source`."""
        return parse_source(self.source)

    @property
    def send_targets(self) -> list[tuple[str, int]]:
        """The parsed :attr:`send` list."""
        return [parse_host_port(t) for t in self.send]


def _resolve(base: Path, path: Path) -> Path:
    return path if path.is_absolute() else base / path


def resolve_relative_paths(cfg: ReceiverConfig, base: Path) -> ReceiverConfig:
    """``cfg`` with its relative paths (arena, camera, key file, video source) taken relative to ``base``."""
    updates: dict[str, Any] = {"arena": _resolve(base, cfg.arena), "camera": _resolve(base, cfg.camera)}
    if cfg.auth_key_file is not None:
        updates["auth_key_file"] = _resolve(base, cfg.auth_key_file)
    spec = cfg.source_spec
    if spec.kind in ("video", "images") and spec.path is not None:
        updates["source"] = f"{spec.kind}:{_resolve(base, spec.path)}"
    if cfg.record.path is not None:
        updates["record"] = cfg.record.model_copy(update={"path": _resolve(base, cfg.record.path)})
    return cfg.model_copy(update=updates)


def load_receiver_config(path: str | Path) -> ReceiverConfig:
    """Load a receiver YAML file (see the shipped ``receiver.yaml``); relative paths are resolved against
    the file's folder. Any problem is one :class:`ConfigError` naming the file."""
    p = Path(path)
    cfg = load_yaml_model(p, ReceiverConfig)
    return resolve_relative_paths(cfg, p.parent)


def with_overrides(cfg: ReceiverConfig, **updates: Any) -> ReceiverConfig:
    """``cfg`` with some fields replaced (e.g. from command-line flags), validated again."""
    data = cfg.model_dump()
    data.update(updates)
    try:
        return ReceiverConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(_describe_validation_error(exc)) from None


def read_auth_key(path: Path) -> bytes:
    """The shared key in ``path`` (see :func:`ipt.keyfile.read_key_file`: a private regular file, its bytes less
    one trailing newline, at least 16 bytes); any problem is one :class:`ConfigError` line."""
    try:
        return read_key_file(path)
    except KeyFileError as exc:
        raise ConfigError(str(exc)) from None
