"""Camera intrinsics from views of a flat board: a chessboard or a ChArUco board.

Pure apart from OpenCV: grey images go in, a :class:`~ipt.config.camera_info.CameraInfo` (pinhole with
plumb_bob distortion, what the receiver reads) and the reprojection error come out. Reading images and
grabbing them from a live camera live in :mod:`ipt.calib.cli`.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import CameraInfo
from ipt.errors import IptError

F32 = npt.NDArray[np.float32]
U8 = npt.NDArray[np.uint8]

MIN_VIEWS = 3
"""Fewest views with the board found that a calibration is computed from (10-20 from varied angles is better)."""
MIN_CHARUCO_CORNERS = 6
"""A ChArUco view with fewer interpolated corners than this is not used."""
CHARUCO_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_100", "DICT_5X5_50", "DICT_5X5_100", "DICT_6X6_250", "DICT_7X7_1000")
BOARD_SIDE_RANGE = (3, 100)
"""Corners (chessboard) or squares (ChArUco) along a side of the board: OpenCV's chessboard finder needs 3 or
more; past 100 the board is a typo (100000x100000 asked numpy for 149 GiB)."""
SQUARE_M_RANGE = (0.001, 1.0)
"""Side of one square, metres: a printed board's squares are millimetres to decimetres."""
MIN_MARKER_RATIO = 0.1
"""A ChArUco marker is at least this fraction of its square (and smaller than the square)."""


class CalibrationError(IptError):
    """Calibration cannot be done with what was given (no board found, too few views, bad sizes)."""


@dataclass(frozen=True)
class Board:
    """A flat calibration target."""

    kind: Literal["chessboard", "charuco"]
    cols: int
    """Chessboard: inner corners along a row. ChArUco: squares along a row."""
    rows: int
    """Chessboard: inner corners along a column. ChArUco: squares along a column."""
    square_m: float
    """Side of one square, metres (sets the unit of the views' poses, not the intrinsics)."""
    marker_m: float = 0.0
    """ChArUco: side of an ArUco marker inside a white square, metres."""
    dictionary: str = "DICT_5X5_100"
    """ChArUco: the ArUco dictionary (OpenCV's name)."""

    def __post_init__(self) -> None:
        lo, hi = BOARD_SIDE_RANGE
        if not (lo <= self.cols <= hi and lo <= self.rows <= hi):
            raise CalibrationError(
                f"--cols and --rows must each be {lo} to {hi} {self._unit()}, got {self.cols}x{self.rows}"
            )
        if not SQUARE_M_RANGE[0] <= self.square_m <= SQUARE_M_RANGE[1]:  # also refuses nan
            raise CalibrationError(
                f"--square-m must be {SQUARE_M_RANGE[0]:g} to {SQUARE_M_RANGE[1]:g} m, got {self.square_m:g}"
            )
        if self.kind == "charuco":
            if not MIN_MARKER_RATIO * self.square_m <= self.marker_m < self.square_m:
                raise CalibrationError(
                    f"--marker-m: the ChArUco marker size must be at least {MIN_MARKER_RATIO:g} of the square and "
                    f"smaller than it ({MIN_MARKER_RATIO * self.square_m:g} to {self.square_m:g} m), "
                    f"got {self.marker_m:g}"
                )
            if self.dictionary not in CHARUCO_DICTIONARIES:
                raise CalibrationError(
                    f"unknown ArUco dictionary {self.dictionary!r} (one of {', '.join(CHARUCO_DICTIONARIES)})"
                )
            markers, have = self.cols * self.rows // 2, int(self.dictionary.rsplit("_", 1)[1])
            if markers > have:
                raise CalibrationError(
                    f"a {self.cols}x{self.rows} ChArUco board has {markers} markers; --dictionary "
                    f"{self.dictionary} has only {have}"
                )

    def _unit(self) -> str:
        return "inner corners" if self.kind == "chessboard" else "squares"

    def describe(self) -> str:
        """E.g. "chessboard 9x6 inner corners, 25 mm squares"."""
        return f"{self.kind} {self.cols}x{self.rows} {self._unit()}, {self.square_m * 1e3:g} mm squares"

    def charuco(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board object (ChArUco only)."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_m, self.marker_m, dictionary)

    def chessboard_points_m(self) -> F32:
        """The inner corners on the board plane (z = 0), in OpenCV's detection order."""
        grid = np.mgrid[0 : self.cols, 0 : self.rows].T.reshape(-1, 2) * self.square_m
        return np.hstack([grid, np.zeros((len(grid), 1))]).astype(np.float32)


class BoardFinder:
    """Finds a :class:`Board` in grey images: (board points, image points) or None."""

    def __init__(self, board: Board) -> None:
        self.board = board
        self._charuco = board.charuco() if board.kind == "charuco" else None
        self._detector = cv2.aruco.CharucoDetector(self._charuco) if self._charuco is not None else None
        self._chess = board.chessboard_points_m() if board.kind == "chessboard" else None

    def find(self, gray: U8) -> tuple[F32, F32] | None:
        """The board's points (N×3, metres) and where they are in ``gray`` (N×2, OpenCV pixels)."""
        if gray.ndim != 2 or gray.dtype != np.uint8:
            raise CalibrationError(f"expected an 8-bit grey image, got {gray.shape} {gray.dtype}")
        if self._chess is not None:
            flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
            found, corners = cv2.findChessboardCornersSB(gray, (self.board.cols, self.board.rows), flags=flags)
            if not found or corners is None:
                return None
            return self._chess, np.asarray(corners, np.float32).reshape(-1, 2)
        if self._detector is None or self._charuco is None:
            raise CalibrationError("internal: the ChArUco detector is missing")
        corners, ids, _, _ = self._detector.detectBoard(gray)
        if corners is None or ids is None or len(corners) < MIN_CHARUCO_CORNERS:
            return None
        obj, img = self._charuco.matchImagePoints(corners, ids)
        return np.asarray(obj, np.float32).reshape(-1, 3), np.asarray(img, np.float32).reshape(-1, 2)


@dataclass(frozen=True)
class CameraCalibration:
    """The result of :func:`calibrate_camera`."""

    camera: CameraInfo
    rms_px: float
    """Reprojection RMS over every corner of every view used (OpenCV's figure), pixels."""
    views: tuple[str, ...]
    """The views the board was found in (and that were used)."""
    view_rms_px: tuple[float, ...]
    """Each used view's own reprojection RMS."""
    skipped: tuple[str, ...]
    """Views without the board."""


def calibrate_camera(
    views: Iterable[tuple[str, U8]],
    board: Board,
    *,
    name: str = "camera",
    fix_k3: bool = True,
) -> CameraCalibration:
    """Intrinsics and plumb_bob distortion from named grey views of ``board``.

    ``fix_k3`` keeps the sixth-order radial term at zero (it overfits a few views of an ordinary lens).
    Raises :class:`CalibrationError` when the views differ in size or fewer than :data:`MIN_VIEWS` show the
    board."""
    finder = BoardFinder(board)
    obj_pts: list[F32] = []
    img_pts: list[F32] = []
    used: list[str] = []
    skipped: list[str] = []
    size: tuple[int, int] | None = None
    first = ""
    total = 0
    for view_name, gray in views:
        total += 1
        h, w = gray.shape[:2]
        if size is None:
            size, first = (w, h), view_name
        elif size != (w, h):
            raise CalibrationError(
                f"{view_name}: {w}x{h}, but {first} is {size[0]}x{size[1]}: one camera mode at a time"
            )
        found = finder.find(gray)
        if found is None:
            skipped.append(view_name)
            continue
        obj_pts.append(found[0])
        img_pts.append(found[1])
        used.append(view_name)
    if total == 0 or size is None:
        raise CalibrationError("no images to calibrate from")
    if len(used) < MIN_VIEWS:
        hint = " (cols and rows count inner corners)" if board.kind == "chessboard" else ""
        raise CalibrationError(
            f"the {board.describe()} was found in {len(used)} of {total} images; at least {MIN_VIEWS} are needed{hint}"
        )
    flags = cv2.CALIB_FIX_K3 if fix_k3 else 0
    rms, k, dist, rvecs, tvecs = cv2.calibrateCamera(obj_pts, img_pts, size, None, None, flags=flags)
    k = np.asarray(k, np.float64)
    dist = np.asarray(dist, np.float64).ravel()
    per_view = []
    for o, i, rv, tv in zip(obj_pts, img_pts, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, rv, tv, k, dist)
        per_view.append(float(np.sqrt(np.mean(np.sum((np.asarray(proj).reshape(-1, 2) - i) ** 2, axis=1)))))
    coeffs = [float(v) for v in dist[:5]] + [0.0] * max(0, 5 - len(dist))
    camera = CameraInfo(
        width_px=size[0],
        height_px=size[1],
        fx_px=float(k[0, 0]),
        fy_px=float(k[1, 1]),
        cx_px=float(k[0, 2]),
        cy_px=float(k[1, 2]),
        distortion=tuple(coeffs),
        name=name,
    )
    return CameraCalibration(camera, float(rms), tuple(used), tuple(per_view), tuple(skipped))
