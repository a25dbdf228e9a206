"""The arena's scale: how many metres one projector pixel covers on the floor (the paper measures this ratio
before flights, once the projector is fixed).

The arena config holds it as the size of the projected image (``screen.width_m``, ``screen.height_m``).
Both measurements here give one factor that multiplies that size (the aspect ratio of a projector pixel is
kept):

- **two measured points**: the tape-measured distance between two points of the projected map (two tags'
  centres, or two projector pixels) against that distance under the current config;
- **a camera at a measured height**: a calibrated camera looking down at the projected map (a plain,
  unmodulated map image) from a measured height. The pose is solved with the current config; every length
  of that solution, the height included, scales with the config, so the true height over the solved one is
  the factor.

Writing the new size back keeps the user's file as it was written (comments, order, other keys): only the
two numbers under ``screen:`` are replaced, the result is checked by parsing it, and it replaces the file
atomically after a backup (or goes to another file).
"""

from __future__ import annotations

import math
import re
import shutil
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml
from pydantic import ValidationError

from ipt.config.base import _describe_validation_error
from ipt.config.camera_info import CameraInfo
from ipt.config.models import ArenaConfig, ConfigError, DetectorConfig, PoseConfig
from ipt.errors import IptError
from ipt.fileio import atomic_path, read_text_file, write_text_atomic
from ipt.tagmap import TagMap, grid_tag_map, pixel_to_arena_m

U8 = npt.NDArray[np.uint8]


MAX_DISTANCE_M = 1000.0
"""Longest floor distance accepted for --distance-m (an arena is at most 100 m across)."""


class ArenaCalibrationError(IptError):
    """The arena scale cannot be measured or written with what was given."""


def scaled_arena(arena: ArenaConfig, factor: float) -> ArenaConfig:
    """``arena`` with its projected image ``factor`` times as large."""
    if not math.isfinite(factor) or factor <= 0:
        raise ArenaCalibrationError(f"the scale factor must be positive, got {factor}")
    screen = arena.screen.model_copy(
        update={"width_m": arena.screen.width_m * factor, "height_m": arena.screen.height_m * factor}
    )
    try:
        return ArenaConfig.model_validate({**arena.model_dump(), "screen": screen.model_dump()})
    except ValidationError as exc:
        raise ArenaCalibrationError(
            f"the measurement makes the projected image {screen.width_m:.4g} x {screen.height_m:.4g} m, which is "
            f"not a usable arena ({_describe_validation_error(exc)})"
        ) from None
    except ValueError as exc:
        raise ArenaCalibrationError(f"the scaled arena is not valid: {str(exc).splitlines()[0][:200]}") from None


def tag_centre_px(tag_map: TagMap, tag_id: int) -> tuple[float, float]:
    """The centre of tag ``tag_id`` in projector pixels (edge origin)."""
    tag = tag_map.by_id.get(tag_id)
    if tag is None:
        ids = sorted(tag_map.by_id)
        raise ArenaCalibrationError(f"tag {tag_id} is not in the map (ids {ids[0]}..{ids[-1]})")
    c = np.mean(np.asarray(tag.corners_px), axis=0)
    return float(c[0]), float(c[1])


def factor_from_points(
    arena: ArenaConfig, a_px: tuple[float, float], b_px: tuple[float, float], distance_m: float
) -> float:
    """The scale factor from the measured floor distance between projector pixels ``a_px`` and ``b_px``."""
    if not 0 < distance_m <= MAX_DISTANCE_M:  # also false for nan
        raise ArenaCalibrationError(
            f"--distance-m must be positive and at most {MAX_DISTANCE_M:g} m, got {distance_m:g}"
        )
    pr = arena.projector
    for u, v in (a_px, b_px):
        if not (0 <= u <= pr.width_px and 0 <= v <= pr.height_px):
            raise ArenaCalibrationError(f"point ({u:g}, {v:g}) is outside the {pr.width_px}x{pr.height_px} image")
    a = np.asarray(pixel_to_arena_m(arena, *a_px))
    b = np.asarray(pixel_to_arena_m(arena, *b_px))
    configured = float(np.linalg.norm(a - b))
    if configured < 1e-9:
        raise ArenaCalibrationError("the two points are the same")
    return distance_m / configured


@dataclass(frozen=True)
class HeightView:
    """What one image of the projected map gave."""

    name: str
    tags: int
    solved_height_m: float
    """The camera's height above the floor under the current arena config."""
    reprojection_rms_px: float


def factor_from_height(
    arena: ArenaConfig, camera: CameraInfo, views: Iterable[tuple[str, U8]], height_m: float
) -> tuple[float, list[HeightView], list[str]]:
    """The scale factor from images of the projected (unmodulated) map taken from ``height_m`` above the floor.

    Returns (factor, the views used, the names of views with fewer than two tags). The factor is the mean
    over the views used."""
    from ipt.receiver.core.pose import solve_pose
    from ipt.receiver.detect.detector import TagDetector

    if not math.isfinite(height_m) or height_m <= 0:
        raise ArenaCalibrationError(f"the measured height must be positive, got {height_m}")
    tag_map = grid_tag_map(arena)
    detector = TagDetector(DetectorConfig(max_hamming=0), known_ids=tag_map.by_id)
    pose_cfg = PoseConfig(min_tags=2, max_speed_mps=None)
    used: list[HeightView] = []
    skipped: list[str] = []
    total = 0
    try:
        for name, gray in views:
            total += 1
            if (gray.shape[1], gray.shape[0]) != (camera.width_px, camera.height_px):
                raise ArenaCalibrationError(
                    f"{name}: {gray.shape[1]}x{gray.shape[0]}, but the camera file is {camera.width_px}x"
                    f"{camera.height_px}"
                )
            dets = detector.detect(gray)
            pose = solve_pose(dets, tag_map, camera, pose_cfg) if len(dets) >= 2 else None
            if pose is None or pose.position_m[2] <= 0:
                skipped.append(name)
                continue
            used.append(HeightView(name, len(pose.tag_ids), float(pose.position_m[2]), pose.reprojection_rms_px))
    finally:
        detector.close()
    if total == 0:
        raise ArenaCalibrationError("no images of the projected map were given")
    if not used:
        raise ArenaCalibrationError(
            f"no image of the {total} shows two or more tags of the map clearly (project the plain map from "
            "'ipt map export', not the modulated video, and check focus and exposure)"
        )
    factor = float(np.mean([height_m / v.solved_height_m for v in used]))
    return factor, used, skipped


_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def _format(value: float) -> str:
    return f"{value:.6g}"


def arena_mapping(text: str, error: type[IptError]) -> dict[str, Any]:
    """The mapping an arena YAML file's ``text`` holds (empty text: none), for an in-place edit; raises
    ``error`` if it is not valid YAML or not a mapping."""
    try:
        original = yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as exc:
        raise error(f"the arena file is not valid YAML ({exc})") from None
    if original is None:
        original = {}
    if not isinstance(original, dict):
        raise error("the arena file is not a YAML mapping")
    return original


def update_screen_yaml(text: str, width_m: float, height_m: float) -> str:
    """``text`` (an arena YAML file) with ``screen.width_m`` and ``screen.height_m`` replaced, everything
    else (comments, order, other keys) as it was. Raises :class:`ArenaCalibrationError` if the result
    does not parse to the same mapping with the new numbers."""
    original = arena_mapping(text, ArenaCalibrationError)
    values = {"width_m": _format(width_m), "height_m": _format(height_m)}
    lines = text.splitlines(keepends=True)
    head = next((i for i, line in enumerate(lines) if re.match(r"screen\s*:", line)), None)
    if head is None or re.match(r"screen\s*:\s*[^\s#]", lines[head]):  # no block (or a flow mapping): write one
        block = "screen:\n" + "".join(f"  {k}: {v}\n" for k, v in values.items())
        if head is None:
            new_lines = [*lines]
            if new_lines and not new_lines[-1].endswith("\n"):
                new_lines[-1] += "\n"
            new_lines.append(block)
        else:
            new_lines = [*lines[:head], block, *lines[head + 1 :]]
    else:
        end = head + 1
        while end < len(lines) and (not lines[end].strip() or lines[end][:1] in (" ", "\t", "#")):
            end += 1
        body = lines[head + 1 : end]
        indent = next((re.match(r"[ \t]+", b).group(0) for b in body if re.match(r"[ \t]+\w", b)), "  ")  # type: ignore[union-attr]
        for key, value in values.items():
            pattern = re.compile(rf"^([ \t]+{key}[ \t]*:[ \t]*){_NUMBER}([ \t]*(?:#.*)?\r?\n?)$")
            for i, line in enumerate(body):
                m = pattern.match(line)
                if m:
                    body[i] = f"{m.group(1)}{value}{m.group(2)}"
                    break
            else:
                body.insert(0, f"{indent}{key}: {value}\n")
        new_lines = [*lines[: head + 1], *body, *lines[end:]]
    new_text = "".join(new_lines)
    expected: dict[str, Any] = {
        **original,
        "screen": {
            **(original.get("screen") or {}),
            **{"width_m": float(values["width_m"]), "height_m": float(values["height_m"])},
        },
    }
    try:
        parsed = yaml.safe_load(new_text)
    except yaml.YAMLError:
        parsed = None
    if parsed != expected:
        raise ArenaCalibrationError(
            "cannot update screen.width_m and screen.height_m in place in this file (an unusual layout); "
            "edit them by hand or write a new file with --output"
        )
    return new_text


def write_screen(
    config_path: Path, width_m: float, height_m: float, *, output: Path | None = None
) -> tuple[Path, Path | None]:
    """Write the new screen size: to ``output`` if given (``config_path`` untouched), else into
    ``config_path`` after copying it to ``<name>.bak``. Returns (written file, backup or None). The result
    is validated as an arena config before anything is replaced."""
    text = read_text_file(config_path, ArenaCalibrationError, "an arena YAML file")
    return write_arena_text(config_path, update_screen_yaml(text, width_m, height_m), output=output)


def write_arena_text(config_path: Path, new_text: str, *, output: Path | None = None) -> tuple[Path, Path | None]:
    """Write ``new_text``, the updated form of the arena file ``config_path``: to ``output`` if given
    (``config_path`` untouched), else into ``config_path`` after copying it to ``<name>.bak``. Returns
    (written file, backup or None). Nothing is written unless ``new_text`` is a valid arena config."""
    try:
        ArenaConfig.model_validate(yaml.safe_load(new_text) or {})
    except (ValueError, ConfigError) as exc:
        raise ArenaCalibrationError(f"{config_path}: the updated arena would not be valid: {exc}") from None
    if output is not None:
        write_text_atomic(output, new_text)
        return output, None
    backup = config_path.with_name(config_path.name + ".bak")
    with atomic_path(backup) as tmp:
        shutil.copyfile(config_path, tmp)  # the exact bytes the user had
    write_text_atomic(config_path, new_text)
    return config_path, backup
