"""The arena's floor mapping, measured: the projector-pixel-to-floor homography from surveyed points.

A projector mounted even a little off-axis keystones, so one scale (``screen``) leaves floor positions
centimetres off at the edges of the image. Here the user marks projector pixels on the floor (numbered
cross-hairs, :func:`marks_image`), measures where each landed (tape, laser, total station) in their own
floor frame and lists them in a CSV file with the header ``u_px,v_px,x_m,y_m``. Four or more points give the
homography by least squares on the floor distances (OpenCV ``findHomography``, all points, no robust
weighting: a wrong point is named instead of silently dropped); each point's residual and its distance from
where the other points put it (leave one out) are reported.

The result is written into the arena YAML as a ``floor:`` section (:class:`ipt.config.models.FloorConfig`),
the rest of the file kept as it was; every part then maps pixels to metres through it
(:func:`ipt.tagmap.pixel_to_floor_matrix`).
"""

from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt
import yaml

from ipt.calib.arena import arena_mapping
from ipt.config.models import ArenaConfig, FloorConfig, TileConfig, floor_homography_fits
from ipt.errors import IptError
from ipt.fileio import read_text_file

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]

HEADER = ("u_px", "v_px", "x_m", "y_m")
"""The columns of a points file."""
MAX_POINTS = 10000
"""Most points a file may list (a survey has tens)."""
FAR_M = 0.01
"""A point farther than this from where the other points put it is named."""
_DEGENERATE = 1e-6
"""Smallest ratio of the 8th to the 1st singular value of the normalised DLT system: below it the points do
not determine a homography (all, or all but one, on a line)."""


class FloorCalibrationError(IptError):
    """A points file is invalid or the points do not determine the floor mapping."""


@dataclass(frozen=True)
class SurveyPoint:
    """One measured point: a projector pixel and where it is on the floor."""

    row: int
    """Its line in the file (the header is line 1)."""
    u_px: float
    v_px: float
    x_m: float | None
    """None in a template not measured yet."""
    y_m: float | None


@dataclass(frozen=True)
class FloorFit:
    """The fitted mapping and how well each point agrees with it."""

    pixel_to_floor: F64
    """3x3, normalised so that its last entry is 1."""
    points: tuple[SurveyPoint, ...]
    residual_m: F64
    """(N,) distance of each measured point from the fit."""
    left_out_m: F64 | None
    """(N,) distance of each point from the fit to all the others (None with fewer than 5 points)."""
    far: tuple[int, ...]
    """Indices of the points more than :data:`FAR_M` from where the others put it, worst first; each
    judged without the points named before it (one wrong point pulls the fit towards it, and so its
    neighbours away)."""

    @property
    def rms_m(self) -> float:
        return float(np.sqrt(np.mean(self.residual_m**2)))

    def config(self) -> FloorConfig:
        h = self.pixel_to_floor
        rows = tuple(tuple(float(x) for x in r) for r in h)
        return FloorConfig(pixel_to_floor=rows, points=len(self.points), rms_m=round(self.rms_m, 7))


MAX_POINT_VALUE = 100_000.0
"""Largest magnitude of a survey value: projector pixels are at most 16384, floor positions a few tens of metres."""


def _number(path: Path, row: int, column: str, text: str, *, blank_ok: bool) -> float | None:
    text = text.strip()
    if not text:
        if blank_ok:
            return None
        raise FloorCalibrationError(f"{path}: row {row}: {column} is empty")
    try:
        value = float(text)
    except ValueError:
        raise FloorCalibrationError(f"{path}: row {row}: {column} is not a number ({text[:40]!r})") from None
    if not math.isfinite(value):
        raise FloorCalibrationError(f"{path}: row {row}: {column} is {text[:40]}, not a finite number")
    if abs(value) > MAX_POINT_VALUE:  # a floor 1e308 m away overflowed the fit (numpy warnings, then a traceback)
        raise FloorCalibrationError(
            f"{path}: row {row}: {column} is {text[:40]}, beyond ±{MAX_POINT_VALUE:g} (not a pixel or a floor position)"
        )
    return value


def parse_points(path: Path, text: str, width_px: int, height_px: int, *, measured: bool = True) -> list[SurveyPoint]:
    """The points of a CSV text (header ``u_px,v_px,x_m,y_m``, any column order, blank lines and ``#``
    lines skipped), each pixel inside the ``width_px`` x ``height_px`` image. ``measured=False`` lets the
    floor columns be empty (a template of marks). Raises :class:`FloorCalibrationError` naming the row."""
    lines = text.removeprefix("\ufeff").splitlines()  # a spreadsheet's "CSV UTF-8" starts with a byte-order mark
    rows = [(i + 1, line) for i, line in enumerate(lines) if line.strip() and not line.lstrip().startswith("#")]
    if not rows:
        raise FloorCalibrationError(f"{path}: empty; expected the header {','.join(HEADER)} and a point per row")
    head_row, head_line = rows[0]
    header = [c.strip().lower() for c in next(csv.reader([head_line]))]
    if sorted(header) != sorted(HEADER):
        missing = [c for c in HEADER if c not in header]
        what = f"missing {', '.join(missing)}" if missing else f"has {', '.join(header)[:80]}"
        raise FloorCalibrationError(f"{path}: row {head_row}: expected the header {','.join(HEADER)} ({what})")
    where = {name: header.index(name) for name in HEADER}
    if len(rows) - 1 > MAX_POINTS:
        raise FloorCalibrationError(f"{path}: {len(rows) - 1} points, more than the {MAX_POINTS} a survey may list")
    points = []
    for row, line in rows[1:]:
        cells = next(csv.reader([line]))
        if len(cells) != len(HEADER):
            raise FloorCalibrationError(f"{path}: row {row}: expected {len(HEADER)} values, got {len(cells)}")
        u, v = (_number(path, row, c, cells[where[c]], blank_ok=False) for c in ("u_px", "v_px"))
        x, y = (_number(path, row, c, cells[where[c]], blank_ok=not measured) for c in ("x_m", "y_m"))
        assert u is not None
        assert v is not None
        if not (0 <= u <= width_px and 0 <= v <= height_px):
            raise FloorCalibrationError(
                f"{path}: row {row}: pixel ({u:g}, {v:g}) is outside the {width_px}x{height_px} projector image"
            )
        points.append(SurveyPoint(row, u, v, x, y))
    return points


def read_points(path: Path, arena: ArenaConfig, *, measured: bool = True) -> list[SurveyPoint]:
    """:func:`parse_points` of the file ``path`` (a regular file of at most 1 MiB)."""
    text = read_text_file(path, FloorCalibrationError, "a CSV file of points (u_px,v_px,x_m,y_m)")
    return parse_points(path, text, arena.projector.width_px, arena.projector.height_px, measured=measured)


def _normalise(p: F64) -> F64:
    """Hartley's similarity: centroid to the origin, mean distance sqrt(2)."""
    c = p.mean(axis=0)
    d = float(np.mean(np.linalg.norm(p - c, axis=1)))
    s = math.sqrt(2) / d if d > 0 else 1.0
    return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])


def _determined(px: F64, m: F64) -> bool:
    """Whether the correspondences pin down one homography (the normalised DLT system has rank 8)."""
    tp, tm = _normalise(px), _normalise(m)
    a = (tp @ np.column_stack([px, np.ones(len(px))]).T).T
    b = (tm @ np.column_stack([m, np.ones(len(m))]).T).T
    rows = []
    for (u, v, _), (x, y, _) in zip(a, b, strict=True):
        rows.append([-u, -v, -1, 0, 0, 0, u * x, v * x, x])
        rows.append([0, 0, 0, -u, -v, -1, u * y, v * y, y])
    s = np.linalg.svd(np.asarray(rows), compute_uv=False)
    return len(s) >= 8 and bool(s[7] > _DEGENERATE * s[0])


def _on_one_line(p: F64) -> list[int]:
    """The largest set of (three or more) points on one line, within a thousandth of the points' spread."""
    tol = 1e-3 * max(float(np.ptp(p[:, 0])), float(np.ptp(p[:, 1])), 1e-12)
    best: list[int] = []
    for i in range(len(p)):
        for j in range(i + 1, len(p)):
            d = p[j] - p[i]
            n = float(np.hypot(*d))
            if n == 0:
                continue
            off = np.abs(d[0] * (p[:, 1] - p[i, 1]) - d[1] * (p[:, 0] - p[i, 0])) / n
            members = [int(k) for k in np.flatnonzero(off <= tol)]
            if len(members) > len(best):
                best = members
    return best if len(best) >= 3 else []


def _fit(px: F64, m: F64) -> F64:
    h, _ = cv2.findHomography(px, m, 0)  # DLT on all points, then Levenberg-Marquardt on the floor distances
    if h is None:
        raise FloorCalibrationError("no homography fits these points")
    return np.asarray(h, np.float64) / float(h[2, 2])


def _apply(h: F64, px: F64) -> F64:
    q = (h @ np.column_stack([px, np.ones(len(px))]).T).T
    return np.asarray(q[:, :2] / q[:, 2:3], np.float64)


def fit_floor(
    path: Path,
    points: list[SurveyPoint],
    width_px: int,
    height_px: int,
    *,
    origin_px: tuple[int, int] = (0, 0),
    where: str = "",
) -> FloorFit:
    """The least-squares homography of the measured ``points`` (from ``path``, for the messages), for the
    ``width_px`` x ``height_px`` image whose top-left is canvas pixel ``origin_px`` (a projector's tile;
    ``where`` names it in the messages)."""
    if len(points) < 4:
        raise FloorCalibrationError(
            f"{path}: {len(points)} point{'s' if len(points) != 1 else ''}{where}; the floor homography needs at "
            "least 4, no three on one line (9 or more, spread over the image, to check them)"
        )
    px = np.array([(p.u_px, p.v_px) for p in points], np.float64)
    m = np.array([(p.x_m, p.y_m) for p in points], np.float64)
    for label, pts in (("projector pixels", px), ("floor positions", m)):
        for i in range(len(pts)):
            same = np.flatnonzero(np.all(pts[:i] == pts[i], axis=1))
            if len(same):
                raise FloorCalibrationError(
                    f"{path}: row {points[i].row}: the same {label[:-1]} as row {points[int(same[0])].row}"
                )
    if not (_determined(px, m)):
        for label, pts in (("projector image", px), ("floor", m)):
            line = _on_one_line(pts)
            if len(line) >= len(points) - 1:
                rows = ", ".join(str(points[k].row) for k in line)
                raise FloorCalibrationError(
                    f"{path}: rows {rows}: on one line on the {label}; the homography needs four points with no "
                    "three on a line"
                )
        raise FloorCalibrationError(f"{path}: these points{where} do not determine a homography (nearly on one line?)")
    h = _fit(px, m)
    x0, y0 = origin_px
    problem = floor_homography_fits(
        FloorConfig(pixel_to_floor=tuple((float(r[0]), float(r[1]), float(r[0] * x0 + r[1] * y0 + r[2])) for r in h)),
        width_px,
        height_px,
    )
    if problem is not None:
        raise FloorCalibrationError(
            f"{path}: the points{where} give no usable mapping: {problem}; check the x_m, y_m columns"
        )
    residual = np.linalg.norm(_apply(h, px) - m, axis=1)
    left_out = _left_out(px, m, np.ones(len(points), bool), residual) if len(points) >= 5 else None
    far: list[int] = []
    if left_out is not None:
        used = np.ones(len(points), bool)
        check = left_out
        while used.sum() >= 5:
            worst = int(np.argmax(np.where(used, check, -1.0)))
            if check[worst] <= FAR_M:
                break
            far.append(worst)
            used[worst] = False
            if used.sum() >= 5:
                check = _left_out(px, m, used, residual)
    return FloorFit(h, tuple(points), residual, left_out, tuple(far))


def _left_out(px: F64, m: F64, used: npt.NDArray[np.bool_], residual: F64) -> F64:
    """Distance of each point (of those ``used``) from the fit to the other used points."""
    out = np.full(len(px), -1.0)
    for i in np.flatnonzero(used):
        keep = used.copy()
        keep[i] = False
        if not _determined(px[keep], m[keep]):
            out[i] = residual[i]  # the others alone do not pin it down: its own residual
            continue
        out[i] = float(np.linalg.norm(_apply(_fit(px[keep], m[keep]), px[i : i + 1])[0] - m[i]))
    return out


# --- the arena YAML -----------------------------------------------------------------------------------


def _floor_block(floor: FloorConfig) -> str:
    rows = "".join(f"    - [{', '.join(repr(float(x)) for x in r)}]\n" for r in floor.pixel_to_floor)
    return (
        "floor:                  # measured by ipt calibrate arena --points: projector pixels -> floor metres\n"
        "  pixel_to_floor:\n"
        f"{rows}"
        f"  points: {floor.points}\n"
        f"  rms_m: {floor.rms_m!r}\n"
    )


def update_floor_yaml(text: str, floor: FloorConfig) -> str:
    """``text`` (an arena YAML file) with its top-level ``floor:`` section replaced by ``floor`` (or added at
    the end), everything else (comments, order, other keys) as it was. Raises
    :class:`FloorCalibrationError` if the result does not parse to the same mapping with the new section."""
    return _replace_section(text, "floor", _floor_block(floor), floor.model_dump(mode="json"))


def update_tiles_yaml(text: str, tiles: tuple[TileConfig, ...]) -> str:
    """``text`` with its top-level ``projectors:`` section (the tiles) written anew from ``tiles``, everything
    else as it was (:func:`update_floor_yaml`)."""
    block = "projectors:             # tiles of the canvas; pixel_to_floor measured by ipt calibrate arena --points\n"
    for t in tiles:
        block += f"  - x_px: {t.x_px}\n    y_px: {t.y_px}\n    width_px: {t.width_px}\n    height_px: {t.height_px}\n"
        if t.pixel_to_floor is not None:
            block += "    pixel_to_floor:\n"
            block += "".join(f"      - [{', '.join(repr(float(x)) for x in r)}]\n" for r in t.pixel_to_floor)
        block += f"    points: {t.points}\n    rms_m: {t.rms_m!r}\n"
    return _replace_section(text, "projectors", block, [t.model_dump(mode="json") for t in tiles])


def _normalised_section(key: str, value: Any) -> Any:
    if value is None:
        return None
    if key == "floor":
        return FloorConfig.model_validate(value).model_dump(mode="json")
    return [TileConfig.model_validate(t).model_dump(mode="json") for t in value]


def _replace_section(text: str, key: str, block: str, value: Any) -> str:
    original = arena_mapping(text, FloorCalibrationError)
    lines = text.splitlines(keepends=True)
    head = next((i for i, line in enumerate(lines) if re.match(rf"{key}\s*:", line)), None)
    if head is None:
        new_lines = [*lines]
        if new_lines and not new_lines[-1].endswith("\n"):
            new_lines[-1] += "\n"
        new_lines.append(block)
    else:
        end = head + 1
        while end < len(lines) and (not lines[end].strip() or lines[end][:1] in (" ", "\t", "#", "-")):
            end += 1
        while end > head + 1 and not lines[end - 1].strip():  # keep the blank lines before the next key
            end -= 1
        new_lines = [*lines[:head], block, *lines[end:]]
    new_text = "".join(new_lines)
    expected: dict[str, Any] = {**original, key: value}
    try:
        parsed = yaml.safe_load(new_text)
        if isinstance(parsed, dict):
            parsed = {**parsed, key: _normalised_section(key, parsed.get(key))}
    except (yaml.YAMLError, ValueError):
        parsed = None
    if parsed != expected:
        raise FloorCalibrationError(
            f"cannot write the {key} section into this file in place (an unusual layout); write a new file "
            "with --output"
        )
    return new_text


# --- marks to measure ---------------------------------------------------------------------------------


def grid_pixels(width_px: int, height_px: int, cols: int, rows: int, margin: float = 0.05) -> list[tuple[int, int]]:
    """``cols`` x ``rows`` whole projector pixels spread over the image, ``margin`` of it in from each edge,
    row by row from the top left (where marks are easiest to measure and give the fit the most leverage)."""
    us = np.rint(np.linspace(margin, 1 - margin, cols) * width_px).astype(int) if cols > 1 else [width_px // 2]
    vs = np.rint(np.linspace(margin, 1 - margin, rows) * height_px).astype(int) if rows > 1 else [height_px // 2]
    return [(int(u), int(v)) for v in vs for u in us]


def marks_image(width_px: int, height_px: int, pixels: list[tuple[float, float]]) -> U8:
    """A black projector image with white numbered cross-hairs crossing at each of ``pixels`` (edge-origin
    coordinates: the crossing is the corner the pixel coordinate names), number 1 first."""
    img = np.zeros((height_px, width_px), np.uint8)
    arm = max(12, round(min(width_px, height_px) / 40))
    thick = max(1, arm // 12)
    font = cv2.FONT_HERSHEY_SIMPLEX
    scale = arm / 24
    one = 16  # cv2's fixed-point shift 4: sixteenths of a pixel

    def fixed(u: float, v: float) -> tuple[int, int]:
        return round((u - 0.5) * one), round((v - 0.5) * one)  # cv2 draws in pixel-centre coordinates

    for n, (u, v) in enumerate(pixels, start=1):
        cv2.line(img, fixed(u - arm, v), fixed(u + arm, v), 255, thick, cv2.LINE_AA, 4)
        cv2.line(img, fixed(u, v - arm), fixed(u, v + arm), 255, thick, cv2.LINE_AA, 4)
        cv2.circle(img, fixed(u, v), round(arm / 2 * one), 255, thick, cv2.LINE_AA, 4)
        label = str(n)
        (tw, th), _ = cv2.getTextSize(label, font, scale, thick + 1)
        lu = u + arm / 2 + 4 if u + arm / 2 + 4 + tw < width_px else u - arm / 2 - 4 - tw
        lv = v - arm / 2 - 4 if v - arm / 2 - 4 - th > 0 else v + arm / 2 + 4 + th
        cv2.putText(img, label, (round(lu), round(lv)), font, scale, 255, thick + 1, cv2.LINE_AA)
    return img


def template_csv(pixels: list[tuple[float, float]]) -> str:
    """The points file to fill in: the marks' pixels, the floor columns empty."""
    out = io.StringIO()
    out.write(",".join(HEADER) + "\n")
    for u, v in pixels:
        out.write(f"{u:g},{v:g},,\n")
    return out.getvalue()
