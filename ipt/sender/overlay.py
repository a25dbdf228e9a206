"""The AR overlay: where each vehicle is, drawn on the content before it is modulated.

Pure: poses and times go in, pixels come out; no sockets, no clocks. The sender feeds every accepted
:class:`~ipt.protocol.PosePacket` to :meth:`ArOverlay.update` with its own monotonic time, and calls
:meth:`ArOverlay.draw` on each new input frame before modulation, so the tags stay hidden under the
overlay like under any other content.

What is drawn, per vehicle, at its arena position converted to projector pixels:

- a filled circle in the vehicle's colour with a light rim;
- a heading arrow: the camera's image-up direction (its -y axis) rotated into the arena and projected
  on the floor, which for the default downward mounting is the drone's nose
  (:data:`ipt.geometry.R_BODY_CAM_DOWNWARD`); no arrow when image-up is nearly vertical;
- its id as a label;
- a trail of its recent positions, fainter with age.

A vehicle not heard from for ``fade_after_s`` fades out linearly and is dropped after ``forget_after_s``.
At most ``max_vehicles`` (:data:`DEFAULT_MAX_VEHICLES`) are kept: a new one while that many others are
still shown is refused and counted (:attr:`ArOverlay.refused`), so no flood of vehicle ids can make a
frame's overlay work grow (the sender's packet filter refuses them earlier, with the same limit).

Speed: nothing is done per frame pixel. The marker is drawn (and, when fading, blended) in a small box
around the vehicle; the trail is a few polylines drawn straight into the frame, each faded by mixing
its colour with the content sampled under it. So the cost does not grow with the frame size. Colours
keep 8-bit CIELAB L between about 60 and 220, so that adding or removing a ΔL of up to 35 does not
clip under the overlay: the tags stay readable under it.

Thread safety: :meth:`update` and :meth:`draw` may be called from different threads (the sender updates
from its event loop and draws in its render thread); a lock guards the state.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Final

import cv2
import numpy as np
import numpy.typing as npt

from ipt.config.models import ArenaConfig
from ipt.geometry import matrix_from_quat_wxyz
from ipt.protocol import PosePacket, QualityFlags
from ipt.tagmap import arena_to_pixel_matrix, pixel_to_arena_m

U8 = npt.NDArray[np.uint8]

# RGB, middle lightness (8-bit L 135..180), moderately saturated (see the module doc).
PALETTE: Final = (
    (225, 85, 60),
    (40, 135, 225),
    (55, 165, 85),
    (190, 110, 215),
    (225, 160, 35),
    (30, 160, 170),
    (215, 85, 145),
    (115, 115, 215),
)
_RIM: Final = (214, 214, 214)
_INK: Final = (58, 58, 64)  # arrow and label text
_HALO: Final = (214, 214, 214)  # behind the label text

_SHIFT: Final = 4  # sub-pixel bits of cv2 drawing
_ONE: Final = 1 << _SHIFT
_FONT: Final = cv2.FONT_HERSHEY_SIMPLEX

MIN_HEADING_NORM: Final = 0.1
"""Image-up must have at least this horizontal component (sin ≈ 6°) for a heading to be defined."""

_TRAIL_OPACITY: Final = 0.8  # of the newest part of a trail
_TRAIL_BANDS: Final = 8  # a trail fades in this many steps
_TRAIL_JUMP_M: Final = 0.5  # consecutive positions further apart than this are not joined
_FAR_PX: Final = 1_000_000.0  # beyond this (in any direction) a vehicle is not drawn at all

DEFAULT_MAX_VEHICLES: Final = 16
"""Vehicles the overlay (and the sender's packet filter) tracks at most, unless told otherwise."""


def heading_rad(quat_wxyz: tuple[float, float, float, float] | npt.ArrayLike) -> float | None:
    """Arena yaw (radians, counter-clockwise from +x) of the camera's image-up direction on the floor.

    Image-up is the camera's -y axis (OpenCV optical frame), rotated into the arena by ``quat_wxyz``
    and projected on the floor. ``None`` when it is nearly vertical (see :data:`MIN_HEADING_NORM`).
    """
    r = matrix_from_quat_wxyz(np.asarray(quat_wxyz, dtype=np.float64))
    up_x, up_y = -float(r[0, 1]), -float(r[1, 1])
    if math.hypot(up_x, up_y) < MIN_HEADING_NORM:
        return None
    return math.atan2(up_y, up_x)


@dataclass
class VehicleTrack:
    """What the overlay knows about one vehicle."""

    vehicle_id: int
    position_m: tuple[float, float, float]
    heading_rad: float | None
    last_heard_s: float
    trail: deque[tuple[float, float, float]] = field(default_factory=deque)
    """Recent positions as (u_px, v_px, time_s), oldest first, in edge-origin projector pixels."""


class ArOverlay:
    """Per-vehicle state from pose packets, and its drawing on projector-sized RGB frames.

    Args:
        arena: gives the projector size and the arena→pixel mapping.
        fade_after_s: silence after which a vehicle starts to fade out.
        forget_after_s: silence after which it is dropped (must exceed ``fade_after_s``).
        trail_s: how far back the trail reaches.
        trail_points: most points kept per trail.
        marker_radius_m: radius of the vehicle's circle on the floor.
        max_vehicles: most vehicles kept (and drawn) at once; more are refused and counted.
    """

    def __init__(
        self,
        arena: ArenaConfig,
        *,
        fade_after_s: float = 1.0,
        forget_after_s: float = 5.0,
        trail_s: float = 3.0,
        trail_points: int = 64,
        marker_radius_m: float = 0.05,
        max_vehicles: int = DEFAULT_MAX_VEHICLES,
    ) -> None:
        if max_vehicles < 1:
            raise ValueError(f"max_vehicles must be at least 1, got {max_vehicles}")
        if not 0 <= fade_after_s < forget_after_s:
            raise ValueError(f"need 0 <= fade_after_s < forget_after_s, got {fade_after_s}, {forget_after_s}")
        if not trail_s > 0 or trail_points < 2 or not marker_radius_m > 0:
            raise ValueError("trail_s and marker_radius_m must be positive and trail_points at least 2")
        self.width_px = arena.projector.width_px
        self.height_px = arena.projector.height_px
        self.fade_after_s = fade_after_s
        self.forget_after_s = forget_after_s
        self.trail_s = trail_s
        self.trail_points = trail_points
        # The arena's floor mapping: uniform, or measured (keystone); with several projectors, each tile's,
        # used for the floor points that land in its part of the canvas.
        rects: list[tuple[float, float, float, float] | None] = [None]
        tiles: list[int | None] = [None]
        if arena.projectors is not None:
            tiles = list(range(len(arena.projectors)))
            rects = [(t.x_px, t.y_px, t.x_px + t.width_px, t.y_px + t.height_px) for t in arena.projectors]
        self._maps: list[tuple[tuple[tuple[float, ...], ...], tuple[float, float, float, float] | None]] = []
        for tile, rect in zip(tiles, rects, strict=True):
            m = arena_to_pixel_matrix(arena, tile)
            box = rect if rect is not None else (0.0, 0.0, float(self.width_px), float(self.height_px))
            u0, v0 = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
            cx, cy, _ = pixel_to_arena_m(arena, u0, v0, tile)  # (0, 0) when uniform
            if float(m[2] @ np.array([cx, cy, 1.0])) < 0:
                m = -m  # the same mapping, with the projective weight positive on the image (see pixel_of)
            self._maps.append((tuple(tuple(float(x) for x in row) for row in m), rect))
        cx, cy, _ = pixel_to_arena_m(arena, self.width_px / 2, self.height_px / 2)
        # Pixels per metre along u and v (at the image's centre, for a measured mapping).
        jac = self._jacobian(cx, cy)
        px_per_m = min(math.hypot(jac[0][0], jac[1][0]), math.hypot(jac[0][1], jac[1][1]))
        self.radius_px = max(4.0, marker_radius_m * px_per_m)
        self._rim_px = max(1, round(self.radius_px / 8))
        self._arrow_px = max(2, round(self.radius_px / 5))
        self._trail_px = max(2, round(self.radius_px / 4))
        self._trail_step_px = float(self._trail_px)  # a new trail point only when the vehicle moved this far
        self._jump_px = _TRAIL_JUMP_M * px_per_m
        self._font_scale = max(0.3, self.radius_px / 28)
        self._font_px = max(1, round(self.radius_px / 18))
        self.max_vehicles = max_vehicles
        self.refused = 0
        """Poses of new vehicles not taken because ``max_vehicles`` others were being shown."""
        self._tracks: dict[int, VehicleTrack] = {}
        self._lock = threading.Lock()

    # -- state --

    def _map_of(self, x_m: float, y_m: float) -> tuple[tuple[float, ...], ...]:
        """The mapping that draws floor point (x, y): the one projector's, or the tile's whose part of the
        canvas it lands in (the first tile's for a point outside them all)."""
        if len(self._maps) == 1:
            return self._maps[0][0]
        for m, rect in self._maps:
            (a, b, c), (d, e, f), (g, h, k) = m
            w = g * x_m + h * y_m + k
            if w > 0 and rect is not None:
                u, v = (a * x_m + b * y_m + c) / w, (d * x_m + e * y_m + f) / w
                if rect[0] <= u <= rect[2] and rect[1] <= v <= rect[3]:
                    return m
        return self._maps[0][0]

    def pixel_of(self, x_m: float, y_m: float) -> tuple[float, float]:
        """Projector pixel (edge origin: the top-left pixel covers [0, 1) x [0, 1)) of an arena floor point."""
        (a, b, c), (d, e, f), (g, h, k) = self._map_of(x_m, y_m)
        w = g * x_m + h * y_m + k  # exactly 1 for the uniform layout (g = h = 0), so its pixels are as before
        if not w > 0:  # beyond the keystoned image's horizon: nowhere in the image
            return math.inf, math.inf
        return (a * x_m + b * y_m + c) / w, (d * x_m + e * y_m + f) / w

    def _jacobian(self, x_m: float, y_m: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """d(u, v) / d(x, y) at a floor point: pixels per metre, and which way the floor's axes run there."""
        (a, b, c), (d, e, f), (g, h, k) = self._map_of(x_m, y_m)
        w = g * x_m + h * y_m + k
        u, v = (a * x_m + b * y_m + c) / w, (d * x_m + e * y_m + f) / w
        return ((a - u * g) / w, (b - u * h) / w), ((d - v * g) / w, (e - v * h) / w)

    def heading_px(self, heading: float, x_m: float = 0.0, y_m: float = 0.0) -> tuple[float, float]:
        """Unit direction in projector pixels (u right, v down) of the arena yaw ``heading`` at the floor point
        (``x_m``, ``y_m``) (a keystoned image turns and stretches directions differently across the floor)."""
        (ja, jb), (jc, jd) = self._jacobian(x_m, y_m)
        cx, sy = math.cos(heading), math.sin(heading)
        du, dv = ja * cx + jb * sy, jc * cx + jd * sy
        norm = math.hypot(du, dv)
        return du / norm, dv / norm

    def update(self, packet: PosePacket, now_s: float) -> None:
        """Take in an accepted pose of one vehicle, received at ``now_s`` (the caller's monotonic clock)."""
        x, y, z = packet.position_m
        heading = heading_rad(packet.quat_wxyz)
        u, v = self.pixel_of(x, y)
        with self._lock:
            track = self._tracks.get(packet.vehicle_id)
            if track is None and len(self._tracks) >= self.max_vehicles:
                self._prune(now_s)
                if len(self._tracks) >= self.max_vehicles:
                    self.refused += 1
                    return
            if track is None:
                track = self._tracks[packet.vehicle_id] = VehicleTrack(
                    packet.vehicle_id, (x, y, z), heading, now_s, deque(maxlen=self.trail_points)
                )
            else:
                track.position_m, track.heading_rad, track.last_heard_s = (x, y, z), heading, now_s
            if packet.flags & QualityFlags.RESET:
                track.trail.clear()  # the estimator restarted: do not join the old path to the new one
            if not (abs(u) < _FAR_PX and abs(v) < _FAR_PX):
                return
            if track.trail:
                lu, lv, _ = track.trail[-1]
                if math.hypot(u - lu, v - lv) < self._trail_step_px:
                    track.trail[-1] = (lu, lv, now_s)  # still here: keep the point fresh
                    return
            track.trail.append((u, v, now_s))

    def alpha(self, vehicle_id: int, now_s: float) -> float:
        """Opacity of a vehicle at ``now_s``: 1 until ``fade_after_s``, then down to 0 at ``forget_after_s``."""
        with self._lock:
            track = self._tracks.get(vehicle_id)
            return 0.0 if track is None else self._alpha(track, now_s)

    def _alpha(self, track: VehicleTrack, now_s: float) -> float:
        silence = now_s - track.last_heard_s
        if silence <= self.fade_after_s:
            return 1.0
        return max(0.0, 1.0 - (silence - self.fade_after_s) / (self.forget_after_s - self.fade_after_s))

    def prune(self, now_s: float) -> None:
        """Drop the vehicles not heard from for longer than ``forget_after_s``."""
        with self._lock:
            self._prune(now_s)

    def _prune(self, now_s: float) -> None:
        stale = [k for k, t in self._tracks.items() if now_s - t.last_heard_s > self.forget_after_s]
        for k in stale:
            del self._tracks[k]

    def vehicle_ids(self) -> list[int]:
        """Ids of the vehicles currently known, in increasing order."""
        with self._lock:
            return sorted(self._tracks)

    def track(self, vehicle_id: int) -> VehicleTrack | None:
        """A copy of what is known about one vehicle, or ``None``."""
        with self._lock:
            t = self._tracks.get(vehicle_id)
            if t is None:
                return None
            return VehicleTrack(t.vehicle_id, t.position_m, t.heading_rad, t.last_heard_s, deque(t.trail))

    # -- drawing --

    def draw(self, frame_rgb: U8, now_s: float) -> U8:
        """Draw every known vehicle into ``frame_rgb`` (H×W×3 uint8 RGB at projector size) and return it."""
        if frame_rgb.shape != (self.height_px, self.width_px, 3) or frame_rgb.dtype != np.uint8:
            raise ValueError(
                f"expected a {self.height_px}x{self.width_px}x3 uint8 frame, got {frame_rgb.shape} {frame_rgb.dtype}"
            )
        with self._lock:
            self._prune(now_s)
            for vehicle_id in sorted(self._tracks):
                track = self._tracks[vehicle_id]
                a = self._alpha(track, now_s)
                if a <= 0.0:
                    continue
                colour = PALETTE[vehicle_id % len(PALETTE)]
                self._draw_trail(frame_rgb, track, colour, a, now_s)
                self._draw_marker(frame_rgb, track, colour, a)
        return frame_rgb

    def _box(self, us: list[float], vs: list[float], pad: float) -> tuple[int, int, int, int] | None:
        """Integer pixel box [x0, x1) x [y0, y1) around centre-origin points, clipped to the frame."""
        x0 = max(0, math.floor(min(us) - pad))
        y0 = max(0, math.floor(min(vs) - pad))
        x1 = min(self.width_px, math.ceil(max(us) + pad) + 1)
        y1 = min(self.height_px, math.ceil(max(vs) + pad) + 1)
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, y0, x1, y1

    def _draw_trail(self, frame: U8, track: VehicleTrack, colour: tuple[int, int, int], a: float, now_s: float) -> None:
        """The recent path as polylines, fainter with age.

        The trail is cut into age bands; each band is one polyline whose colour is the vehicle's mixed
        with the content sampled under the band's points, at the band's opacity. The lines are drawn
        straight into the frame, touching only their own pixels: a trail costs a few OpenCV calls
        however long it is and whatever the frame size.
        """
        recent = [p for p in track.trail if now_s - p[2] <= self.trail_s]
        if len(recent) < 2:
            return
        data = np.array(recent, dtype=np.float64)
        pts, times = data[:, :2] - 0.5, data[:, 2]  # pixel-centre coordinates, as cv2 draws
        fixed = np.rint(pts * _ONE).astype(np.int32)
        bands = np.minimum(_TRAIL_BANDS - 1, ((now_s - times) / self.trail_s * _TRAIL_BANDS).astype(np.int64))
        cols, rows = np.rint(pts[:, 0]).astype(np.int64), np.rint(pts[:, 1]).astype(np.int64)
        inside = (cols >= 0) & (cols < self.width_px) & (rows >= 0) & (rows < self.height_px)
        under = np.zeros((len(recent), 3), dtype=np.float64)
        under[inside] = frame[rows[inside], cols[inside]]
        # A jump (a bad pose, or a vehicle that was away) leaves a gap rather than a long line.
        jump = (np.abs(np.diff(pts, axis=0)).max(axis=1) > self._jump_px).tolist()
        band = bands.tolist()
        starts: list[int] = []
        ends: list[int] = []  # piece k is points starts[k]..ends[k] inclusive; pieces share their end points
        start, n = 0, len(recent)
        while start < n - 1:
            if jump[start]:
                start += 1
                continue
            end = start + 1
            while end < n - 1 and band[end] == band[start] and not jump[end]:
                end += 1
            starts.append(start)
            ends.append(end)
            start = end
        if not starts:
            return
        # Per piece: mean age, and mean colour under its points (inside the frame), from running sums.
        first, stop = np.array(starts), np.array(ends) + 1
        sum_t = np.concatenate(([0.0], np.cumsum(times)))
        sum_in = np.concatenate(([0], np.cumsum(inside)))
        sum_under = np.vstack([np.zeros((1, 3)), np.cumsum(under, axis=0)])
        age = now_s - (sum_t[stop] - sum_t[first]) / (stop - first)
        opacity = a * _TRAIL_OPACITY * np.clip(1.0 - age / self.trail_s, 0.0, None)
        seen = sum_in[stop] - sum_in[first]
        bg = (sum_under[stop] - sum_under[first]) / np.maximum(seen, 1)[:, None]
        mixed = np.rint(bg + (np.asarray(colour, dtype=np.float64) - bg) * opacity[:, None]).astype(np.int64)
        pieces = zip(starts, ends, opacity.tolist(), seen.tolist(), mixed.tolist(), strict=True)
        for s0, s1, op, count, c in pieces:
            if op >= 1 / 255 and count > 0:
                line_colour = (c[0], c[1], c[2])
                cv2.polylines(frame, [fixed[s0 : s1 + 1]], False, line_colour, self._trail_px, cv2.LINE_AA, _SHIFT)

    def _draw_marker(self, frame: U8, track: VehicleTrack, colour: tuple[int, int, int], a: float) -> None:
        x, y, _ = track.position_m
        u, v = self.pixel_of(x, y)
        if not (abs(u) < _FAR_PX and abs(v) < _FAR_PX):
            return
        cu, cv_ = u - 0.5, v - 0.5  # cv2 draws in pixel-centre coordinates
        r = self.radius_px
        arrow = 2.0 * r
        label = str(track.vehicle_id)
        (tw, th), base = cv2.getTextSize(label, _FONT, self._font_scale, self._font_px + 2)
        lu, lv = cu + 0.8 * r, cv_ - 0.9 * r  # label origin (bottom-left of the text)
        us = [cu - arrow, cu + arrow, lu + tw]
        vs = [cv_ - arrow, cv_ + arrow, lv - th - base]
        box = self._box(us, vs, self._arrow_px + 3)
        if box is None:
            return
        x0, y0, x1, y1 = box
        roi = frame[y0:y1, x0:x1]
        layer = roi if a >= 1.0 else roi.copy()

        def fixed(pu: float, pv: float) -> tuple[int, int]:
            return round((pu - x0) * _ONE), round((pv - y0) * _ONE)

        centre = fixed(cu, cv_)
        cv2.circle(layer, centre, round((r + self._rim_px) * _ONE), _RIM, -1, cv2.LINE_AA, _SHIFT)
        cv2.circle(layer, centre, round(r * _ONE), colour, -1, cv2.LINE_AA, _SHIFT)
        if track.heading_rad is not None:
            du, dv = self.heading_px(track.heading_rad, x, y)
            tip = fixed(cu + arrow * du, cv_ + arrow * dv)
            cv2.arrowedLine(layer, centre, tip, _INK, self._arrow_px, cv2.LINE_AA, _SHIFT, 0.3)
        org = (round(lu - x0), round(lv - y0))
        cv2.putText(layer, label, org, _FONT, self._font_scale, _HALO, self._font_px + 2, cv2.LINE_AA)
        cv2.putText(layer, label, org, _FONT, self._font_scale, _INK, self._font_px, cv2.LINE_AA)
        if layer is not roi:
            cv2.addWeighted(layer, a, roi, 1.0 - a, 0.0, dst=roi)
