"""Camera intrinsics in the ROS ``camera_info`` YAML format (what ``camera_calibration`` writes).

Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from ipt.config.models import finite_float, read_yaml_mapping
from ipt.errors import IptError
from ipt.fileio import write_text_atomic


class CameraInfoError(IptError):
    """A camera_info file is missing, unreadable or invalid."""


_ROS_KEYS = {
    "image_width",
    "image_height",
    "camera_name",
    "camera_matrix",
    "distortion_model",
    "distortion_coefficients",
    "rectification_matrix",
    "projection_matrix",
}


@dataclass(frozen=True)
class CameraInfo:
    """Pinhole intrinsics with plumb_bob (Brown–Conrady k1 k2 p1 p2 k3) distortion."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    name: str = "camera"

    @property
    def camera_matrix(self) -> npt.NDArray[np.float64]:
        """The 3x3 intrinsic matrix K."""
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    @property
    def dist_coeffs(self) -> npt.NDArray[np.float64]:
        """Distortion coefficients as OpenCV expects them."""
        return np.asarray(self.distortion, dtype=np.float64)

    def binning_for(self, work_width_px: int) -> int:
        """The largest whole k that keeps this camera's frames at least ``work_width_px`` wide when each k × k
        block of pixels is averaged into one, and divides both sides (1: no binning; also for 0)."""
        if work_width_px <= 0:
            return 1
        for k in range(self.width_px // work_width_px, 1, -1):
            if self.width_px % k == 0 and self.height_px % k == 0:
                return k
        return 1

    def binned(self, k: int) -> CameraInfo:
        """The camera whose pixel is a k × k block of this one's (what ``cv2.resize`` with ``INTER_AREA`` makes
        of its frames, k dividing both sides): the same lens, a coarser grid. Pixel centres are at whole
        coordinates, so a block's centre, ((k − 1) / 2, (k − 1) / 2) from its first pixel, is the new pixel."""
        if k == 1:
            return self
        if k < 1 or self.width_px % k or self.height_px % k:
            raise CameraInfoError(f"cannot bin a {self.width_px}x{self.height_px} camera by {k}")
        half = (k - 1) / 2
        return replace(
            self,
            width_px=self.width_px // k,
            height_px=self.height_px // k,
            fx_px=self.fx_px / k,
            fy_px=self.fy_px / k,
            cx_px=(self.cx_px - half) / k,
            cy_px=(self.cy_px - half) / k,
        )

    def to_ros_dict(self) -> dict[str, Any]:
        """The camera_info mapping, ready for ``yaml.safe_dump``."""
        k = [float(v) for v in self.camera_matrix.ravel()]
        p = [self.fx_px, 0.0, self.cx_px, 0.0, 0.0, self.fy_px, self.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0]
        return {
            "image_width": self.width_px,
            "image_height": self.height_px,
            "camera_name": self.name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": k},
            "distortion_model": "plumb_bob",
            "distortion_coefficients": {"rows": 1, "cols": len(self.distortion), "data": list(self.distortion)},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]},
            "projection_matrix": {"rows": 3, "cols": 4, "data": [float(v) for v in p]},
        }


def _show(value: object, limit: int = 60) -> str:
    """``repr(value)``, cut to ``limit`` characters: a message quotes a bad value, not a megabyte of it."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _matrix(path: Path, data: dict[str, Any], key: str, shapes: set[tuple[int, int]]) -> list[float]:
    block = data.get(key)
    if not isinstance(block, dict):
        raise CameraInfoError(f"{path}: {key}: expected a mapping with rows, cols and data")
    rows, cols, values = block.get("rows"), block.get("cols"), block.get("data")
    if not isinstance(rows, int) or not isinstance(cols, int) or not isinstance(values, list):
        raise CameraInfoError(f"{path}: {key}: expected integer rows and cols and a data list")
    if (rows, cols) not in shapes:
        raise CameraInfoError(f"{path}: {key}: unexpected shape {rows}x{cols}")
    if len(values) != rows * cols:
        raise CameraInfoError(f"{path}: {key}: {rows}x{cols} needs {rows * cols} values, got {len(values)}")
    out = []
    for v in values:
        number = finite_float(v)
        if number is None:
            raise CameraInfoError(f"{path}: {key}: every value must be a finite number, got {v!r:.40}")
        out.append(number)
    return out


MIN_FOCAL_WIDTHS = 0.05
"""Shortest focal length accepted, in image widths (a 0.05-width focal length sees 170° across: no lens here)."""
MAX_FOCAL_WIDTHS = 20.0
"""Longest focal length accepted, in image widths (20 widths sees 2.9° across: a telescope, not a drone camera)."""
MAX_DISTORTION = 10.0
"""Largest distortion coefficient accepted, either sign (calibrated lenses stay well within ±2)."""


def _check_intrinsics(path: Path, width: int, height: int, k: list[float], dist: list[float]) -> None:
    """Refuse intrinsics no real camera has (they gave 0 poses and no word why): focal lengths outside
    0.05–20 image widths, a distortion coefficient beyond ±10, a principal point outside the image."""
    lo, hi = MIN_FOCAL_WIDTHS * width, MAX_FOCAL_WIDTHS * width
    for name, f in (("fx", k[0]), ("fy", k[4])):
        if not lo <= f <= hi:
            raise CameraInfoError(
                f"{path}: camera_matrix: {name}={f:g} px is not a camera's focal length for an image {width} px wide "
                f"(expected {lo:g} to {hi:g} px)"
            )
    for name, c, size in (("cx", k[2], width), ("cy", k[5], height)):
        if not -0.5 <= c <= size - 0.5:
            raise CameraInfoError(
                f"{path}: camera_matrix: the principal point {name}={c:g} px is outside the image (0 to {size - 1} px)"
            )
    for i, d in enumerate(dist):
        if abs(d) > MAX_DISTORTION:
            raise CameraInfoError(
                f"{path}: distortion_coefficients: value {i + 1} is {d:g}, beyond ±{MAX_DISTORTION:g} (not a lens)"
            )


def load_camera_info(path: str | Path) -> CameraInfo:
    """Read a ROS camera_info YAML file. Raises :class:`CameraInfoError` naming the file and the problem."""
    p = Path(path)
    data = read_yaml_mapping(p, CameraInfoError)
    unknown = sorted(_show(k) for k in set(data) - _ROS_KEYS)
    if unknown:
        more = f" and {len(unknown) - 8} more" if len(unknown) > 8 else ""
        raise CameraInfoError(f"{p}: unknown key(s) {', '.join(unknown[:8])}{more} (not a camera_info file?)")
    for key in ("image_width", "image_height"):
        v = data.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 65536:
            raise CameraInfoError(f"{p}: {key}: expected a positive integer, got {_show(v)}")
    model = data.get("distortion_model", "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial"):
        raise CameraInfoError(f"{p}: distortion_model: {_show(model)} is not supported (use plumb_bob)")
    k = _matrix(p, data, "camera_matrix", {(3, 3)})
    if "distortion_coefficients" in data:
        dist = _matrix(p, data, "distortion_coefficients", {(1, n) for n in (4, 5, 8)} | {(n, 1) for n in (4, 5, 8)})
    else:
        dist = [0.0] * 5
    fx, fy, cx, cy = k[0], k[4], k[2], k[5]
    if fx <= 0 or fy <= 0:
        raise CameraInfoError(f"{p}: camera_matrix: focal lengths must be positive (fx={fx}, fy={fy})")
    if k[1] != 0.0 or k[3] != 0.0 or k[6] != 0.0 or k[7] != 0.0 or k[8] != 1.0:
        raise CameraInfoError(f"{p}: camera_matrix: expected [fx 0 cx; 0 fy cy; 0 0 1]")
    _check_intrinsics(p, int(data["image_width"]), int(data["image_height"]), k, dist)
    name = data.get("camera_name", "camera")
    return CameraInfo(
        width_px=int(data["image_width"]),
        height_px=int(data["image_height"]),
        fx_px=fx,
        fy_px=fy,
        cx_px=cx,
        cy_px=cy,
        distortion=tuple(dist),
        name=str(name),
    )


def save_camera_info(info: CameraInfo, path: str | Path) -> None:
    """Write ``info`` as ROS camera_info YAML, atomically (a temp file renamed into place)."""
    write_text_atomic(path, yaml.safe_dump(info.to_ros_dict(), sort_keys=False))
