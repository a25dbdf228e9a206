"""Settings of the receiver daemon (``ipt-receiver run``): where frames come from and where poses go.

Relative paths in a receiver YAML file (``arena``, ``camera``, ``auth_key_file`` and the path of a
``video:`` source) are resolved against the folder of that file, so a config and its companions can be
moved together. Paths given on the command line are relative to the working directory as usual.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, field_validator

from ipt.config.models import (
    ConfigError,
    PipelineConfig,
    StrictModel,
    _describe_validation_error,
    load_yaml_model,
)

DEFAULT_SEND_TARGET = "127.0.0.1:9870"
"""Where poses go unless configured otherwise: a listener on this machine."""

MIN_KEY_BYTES = 16
"""Shortest authentication key accepted (the protocol's minimum, 128 bits)."""

SourceKind = Literal["sim", "video", "device"]


@dataclass(frozen=True)
class SourceSpec:
    """A parsed ``source`` value: ``sim``, ``video:PATH`` or ``device:N``."""

    kind: SourceKind
    path: Path | None = None
    """The recording, for ``video``."""
    device: int | None = None
    """The V4L2 device number (``/dev/videoN``), for ``device``."""

    def __str__(self) -> str:
        if self.kind == "video":
            return f"video:{self.path}"
        if self.kind == "device":
            return f"device:{self.device}"
        return "sim"


def parse_source(text: str) -> SourceSpec:
    """``"sim"``, ``"video:PATH"`` or ``"device:N"`` as a :class:`SourceSpec`; ``ValueError`` otherwise."""
    if text == "sim":
        return SourceSpec("sim")
    kind, sep, arg = text.partition(":")
    if sep and kind == "video":
        if not arg:
            raise ValueError("video: needs a path, as in video:flight.mkv")
        return SourceSpec("video", path=Path(arg))
    if sep and kind == "device":
        if not re.fullmatch(r"[0-9]{1,3}", arg):
            raise ValueError(f"device: needs a device number, as in device:0, got {arg!r}")
        return SourceSpec("device", device=int(arg))
    raise ValueError(f"source must be sim, video:PATH or device:N, got {text!r}")


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
        "(a recording; PATH relative to this file's folder) or 'device:N' (V4L2 camera /dev/videoN).",
    )
    fps: float | None = Field(
        None,
        gt=0,
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
        5.0, gt=0, le=3600, description="Seconds between the statistics lines printed on stderr."
    )
    queue_size: int = Field(
        2, ge=1, le=64, description="Frames held between capture and processing; a live source drops the oldest."
    )
    pipeline: PipelineConfig = Field(default_factory=PipelineConfig, description="The per-frame processing.")

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
    if spec.kind == "video" and spec.path is not None:
        updates["source"] = f"video:{_resolve(base, spec.path)}"
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
    """The shared key in ``path``: its bytes, less one trailing newline; at least :data:`MIN_KEY_BYTES`."""
    try:
        key = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such key file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the key file ({exc.strerror or exc})") from None
    if key.endswith(b"\r\n"):
        key = key[:-2]
    elif key.endswith(b"\n"):
        key = key[:-1]
    if len(key) < MIN_KEY_BYTES:
        raise ConfigError(f"{path}: the key is {len(key)} bytes; at least {MIN_KEY_BYTES} are needed")
    return key
