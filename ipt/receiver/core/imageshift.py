"""How far the image moved between two frames of one projector field, and the chain's predictions turned to agree
(issue 29: a visual gyro for the sparse tracker's starts).

The chain predicts a frame's pose by carrying its last poses on at constant velocity (:mod:`~ipt.receiver.core.
sparsechain`). A drone's 5-8 Hz vibration turns the camera by a few milliradians between frames, which poses 8 ms
apart, each a fit with its own noise, cannot carry on: a new video frame's first joint fit starts ~5 px off and takes
7-9 iterations, half the chain's fitting on a moving video (docs/receiver-cores.md, stops 67-68; no curve through the
poses starts it closer). Two camera frames of one projector field show the same floor in the same lightness, so the
image's shift between them is the camera's own motion: measured on a half-size image with OpenCV's pyramidal
Lucas-Kanade at a grid of points (the median of their moves), a median 0.23 / 0.29 / 0.35 px from the truth's shift
at the image centre on moving-content / fast / takeoff (docs/receiver-cores.md, stop 69). A shift across a phase
change (the floor's lightness flips by 2ΔL along the map's edges, which biases it) or a new video frame (the content
changes) is not measured: it takes the mean of the measured shifts beside it. The prediction is then turned (about
the camera's centre) so that the floor point on the newest pose's optical axis lands where the shifts since that
frame put it.

Pure: lightness frames in, shifts and poses out.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]
RT = tuple[F64, F64]

GRID = (8, 4)
"""Points across and down the measured image, evenly from 10 % to 90 % of its width and height."""
MIN_TRACKED = 8
"""A shift from fewer points that OpenCV's tracker followed is not taken."""
MEASURE_WIDTH_PX = 400
"""The frames are halved (:func:`cv2.pyrDown`) until no wider than this (640 → 320, 1280 → 320)."""
MAX_TURN_RAD = 0.03
"""A turn larger than this (~14 px at the 640-pixel camera's focal length) is not taken: the prediction stays as the
poses carried it (a shift measured wrongly, or a frame the chain has not followed)."""
_WINDOW = (11, 11)
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 10, 0.03)
BRIDGE_FRAMES = 3
"""An unmeasured shift takes the measured ones up to this many frames before it and (up to the predicted frame)
after it."""


class ImageShifts:
    """The image's shift between consecutive frames of one projector phase, measured as frames are added, for the
    chain's predictions (:meth:`between`, :meth:`turned`). ``camera_matrix``: the frames' (distorted) camera's."""

    def __init__(self, camera_matrix: F64) -> None:
        self.shift_px: dict[int, F64] = {}
        """The image's shift (x, y pixels) from frame j to j+1, by j, where measured."""
        k = np.asarray(camera_matrix, np.float64)
        self._inv_f = (1.0 / float(k[0, 0]), 1.0 / float(k[1, 1]))
        self._last: tuple[int, int | None, U8, U8 | None] | None = None
        """The newest frame added: index, phase, lightness, its measured image (made when a shift needed it)."""
        self._points: F32 | None = None
        self._size = (0, 0)

    def clear(self) -> None:
        self.shift_px.clear()
        self._last = None

    def forget(self, before: int) -> None:
        for j in [j for j in self.shift_px if j < before]:
            del self.shift_px[j]

    def add(self, k: int, lum: U8, phase: int | None) -> None:
        """Frame ``k``'s lightness (raw, distorted) and projector phase (None: not known): its shift from ``k-1``
        measured if that frame was added with the same phase."""
        last, small = self._last, None
        if last is not None and phase is not None and last[0] == k - 1 and last[1] == phase:
            earlier = last[3] if last[3] is not None else _measured_image(last[2])
            small = _measured_image(lum)
            shift = self._measure(earlier, small, lum.shape[1] / small.shape[1])
            if shift is not None:
                self.shift_px[k - 1] = shift
        self._last = (k, phase, lum, small)

    def _measure(self, earlier: U8, later: U8, scale: float) -> F64 | None:
        h, w = earlier.shape
        if self._points is None or self._size != (w, h):
            gx, gy = np.meshgrid(np.linspace(0.1, 0.9, GRID[0]) * (w - 1), np.linspace(0.1, 0.9, GRID[1]) * (h - 1))
            self._points = np.stack([gx.ravel(), gy.ravel()], 1).astype(np.float32).reshape(-1, 1, 2)
            self._size = (w, h)
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            earlier, later, self._points, None, winSize=_WINDOW, maxLevel=2, criteria=_CRITERIA
        )
        tracked = status.ravel() == 1
        if int(tracked.sum()) < MIN_TRACKED:
            return None
        flow = (moved - self._points).reshape(-1, 2)[tracked]
        return np.asarray(np.median(flow, axis=0), np.float64) * scale

    def between(self, b: int, k: int) -> F64 | None:
        """The image's shift from frame ``b`` to ``k`` (pixels): the measured shifts summed, each unmeasured one
        taken as the mean of the nearest measured before it and after it (:data:`BRIDGE_FRAMES`); None where one
        has neither."""
        total = np.zeros(2)
        for i in range(b, k):
            step = self.shift_px.get(i)
            if step is None:
                before = self._nearest(range(i - 1, i - 1 - BRIDGE_FRAMES, -1))
                after = self._nearest(range(i + 1, min(k, i + 1 + BRIDGE_FRAMES)))
                found = [s for s in (before, after) if s is not None]
                if not found:
                    return None
                step = np.mean(found, axis=0)
            total += step
        return total

    def _nearest(self, frames: range) -> F64 | None:
        return next((self.shift_px[j] for j in frames if j in self.shift_px), None)

    def turned(self, predicted: RT, newest: RT, shift_px: F64) -> RT:
        """``predicted`` (rvec, tvec: arena → camera) turned about the camera's centre so that the floor point
        (z = 0) on the optical axis of the pose ``newest`` lands ``shift_px`` from the principal point; as it was
        where that point is not on the floor ahead of both cameras, or the turn exceeds :data:`MAX_TURN_RAD`."""
        r_new, _ = cv2.Rodrigues(np.asarray(newest[0], np.float64).reshape(3, 1))
        p_new = -r_new.T @ np.asarray(newest[1], np.float64).reshape(3)
        ray = r_new[2]  # (the optical axis in the arena's frame)
        if ray[2] >= 0 or p_new[2] <= 0:
            return predicted
        r, _ = cv2.Rodrigues(np.asarray(predicted[0], np.float64).reshape(3, 1))
        t = np.asarray(predicted[1], np.float64).reshape(3)
        sx, sy, sz = (r @ (p_new - ray * (p_new[2] / ray[2])) + t).tolist()
        wx, wy = float(shift_px[0]) * self._inv_f[0], float(shift_px[1]) * self._inv_f[1]
        if sz <= 0:
            return predicted
        ax, ay, az = sy - wy * sz, sz * wx - sx, sx * wy - sy * wx  # seen × wanted, wanted = (wx, wy, 1)
        sine = math.sqrt(ax * ax + ay * ay + az * az)
        angle = math.atan2(sine, sx * wx + sy * wy + sz)
        if not 1e-12 < angle <= MAX_TURN_RAD:
            return predicted
        turn, _ = cv2.Rodrigues(np.array([ax, ay, az]) * (angle / sine))
        r_turned = turn @ r
        rvec, _ = cv2.Rodrigues(r_turned)
        return rvec.reshape(3), r_turned @ (r.T @ t)


def _measured_image(lum: U8) -> U8:
    """``lum`` halved until no wider than :data:`MEASURE_WIDTH_PX`."""
    small = lum
    while small.shape[1] > MEASURE_WIDTH_PX:
        small = cv2.pyrDown(small)
    return small
