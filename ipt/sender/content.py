"""The video content in which the tags are hidden.

The paper projects a screen recording of a map application searching for a route. :class:`GeneratedScene`
is a procedurally drawn stand-in, so that no video file is needed: a city map (blocks, parks, water,
a street network, labels) under a phone-style interface, with a route that grows from a start pin to an
end pin, a moving location marker and a slow pan and zoom. :class:`StillImageScene` shows one image and
:class:`VideoScene` plays a video file or image folder in a loop.

All content sources answer the same question, :meth:`ContentSource.frame`: the RGB picture (H×W×3 uint8)
of input frame ``index`` when input frames come at ``rate_hz``, that is at time ``index / rate_hz``
seconds. The generated map's base map is drawn by :mod:`ipt.sender.basemap`.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import TracebackType
from typing import Final, Protocol, Self

import cv2
import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.imageio import read_image
from ipt.sender.basemap import ONE as _ONE
from ipt.sender.basemap import PLACES, draw_base_map
from ipt.sender.basemap import SHIFT as _SHIFT
from ipt.sender.basemap import TEXT as _TEXT
from ipt.sender.basemap import WHITE as _WHITE
from ipt.sender.basemap import fixed_point as _fixed
from ipt.sender.basemap import put_text as _text
from ipt.videoio import FrameSource, VideoError, open_frames

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]


class ContentError(IptError):
    """A scene cannot be made from the values or the image given."""


class ContentSource(Protocol):
    """Video content: input frame ``index`` at ``rate_hz`` as an H×W×3 uint8 RGB image."""

    def frame(self, index: int, rate_hz: float) -> U8: ...


def _check_size(width_px: int, height_px: int) -> None:
    for name, value in (("width_px", width_px), ("height_px", height_px)):
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ContentError(f"{name} must be a positive integer, not {value!r}")


def file_frame_index(index: int, fps: float | None, rate_hz: float) -> int:
    """The frame of a file at ``fps`` (before looping; ``None``: a folder, one frame each) shown as input
    frame ``index`` at ``rate_hz``: the one rule of :class:`VideoScene` and the sender's prefetching reader."""
    _check_rate(rate_hz)
    if index < 0:
        raise ContentError(f"frame index must not be negative, not {index}")
    if fps is None:
        return index
    # The small tolerance keeps e.g. index 3 at 59.94 Hz of a 59.94 fps file on frame 3, not 2.
    return math.floor(index * fps / rate_hz + 1e-6)


def _check_rate(rate_hz: float) -> None:
    try:
        ok = math.isfinite(rate_hz) and rate_hz > 0
    except TypeError:
        ok = False
    if not ok:
        raise ContentError(f"rate_hz must be a positive number, not {rate_hz!r}")


# --- the generated map ------------------------------------------------------------------------------

# Colours are RGB.
_ROUTE: Final = (38, 130, 255)
_ROUTE_EDGE: Final = (10, 60, 170)
_START_PIN: Final = (30, 170, 80)
_END_PIN: Final = (235, 50, 45)
_BLACK: Final = (0, 0, 0)
_GREY_TEXT: Final = (110, 110, 115)

# Motion: slow enough to look like a person panning a map, fast enough to change every few frames.
_PAN_AMPLITUDE_PX: Final = 48.0  # at 1080 lines; peak speed 2π·48/70 ≈ 4.3 px/s
_PAN_PERIODS_S: Final = (70.0, 95.0)
_ZOOM_MAX: Final = 1.06
_ZOOM_PERIOD_S: Final = 120.0
_SEARCH_CYCLE_S: Final = 14.0  # searching 0–1.5 s, route grows until 7.5 s, then shown in full
_SEARCH_S: Final = 1.5
_GROW_S: Final = 6.0
_MARKER_LAP_S: Final = 40.0


def _smoothstep(x: float) -> float:
    x = min(1.0, max(0.0, x))
    return x * x * (3.0 - 2.0 * x)


def _rounded_rect(
    img: U8, x0: int, y0: int, x1: int, y1: int, r: int, color: tuple[int, int, int], line_type: int
) -> None:
    """Fill the rectangle [x0, x1) × [y0, y1) with corners rounded to radius ``r``."""
    r = max(0, min(r, (x1 - x0 - 1) // 2, (y1 - y0 - 1) // 2))
    cv2.rectangle(img, (x0 + r, y0), (x1 - 1 - r, y1 - 1), color, -1)
    cv2.rectangle(img, (x0, y0 + r), (x1 - 1, y1 - 1 - r), color, -1)
    if r > 0:
        for cx, cy in ((x0 + r, y0 + r), (x1 - 1 - r, y0 + r), (x0 + r, y1 - 1 - r), (x1 - 1 - r, y1 - 1 - r)):
            cv2.circle(img, (cx, cy), r, color, -1, line_type)


class GeneratedScene:
    """A procedurally drawn stand-in for a screen recording of a map app searching for a route.

    The map is drawn once, larger than the screen, in ``__init__``; each frame crops it at the current
    pan and zoom, scales the crop to the screen and draws the small animated parts on top: the route
    growing from the start pin to the end pin (a 14 s cycle), the location marker moving along it, a
    search spinner, the clock. The picture is a pure function of ``seed`` and ``index / rate_hz``.

    The pan moves the crop by whole base-map pixels and the zoom changes its size by whole pixels, so
    the map part of consecutive frames is often identical, as in a real screen recording; the marker
    moves with sub-pixel precision every frame.
    """

    def __init__(self, width_px: int, height_px: int, seed: int = 0) -> None:
        _check_size(width_px, height_px)
        self.width_px = width_px
        self.height_px = height_px
        self.seed = seed
        w, h = width_px, height_px
        self._u = u = max(0.3, min(w, h) / 1080.0)  # drawing unit: 1 at 1080 lines
        self._pan_px = _PAN_AMPLITUDE_PX * u
        margin = math.ceil(self._pan_px) + 4
        self._base_w, self._base_h = w + 2 * margin, h + 2 * margin
        rng = np.random.default_rng(seed)
        self._base = np.empty((self._base_h, self._base_w, 3), dtype=np.uint8)
        self._xs, self._ys = draw_base_map(self._base, u, rng)
        self._route = self._pick_route(rng)
        seg = np.diff(self._route, axis=0)
        self._route_cum = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
        km = self._route_cum[-1] / u * 0.0025
        self._route_text = f"{max(1, round(km * 4.5))} min  {km:.1f} km"
        self._dest_name = str(rng.choice(PLACES))
        # The view changes only every few frames: keep the last scaled map (a pure function of the view).
        self._map_cache: tuple[tuple[int, int, int, int], U8] | None = None
        self._layout()
        self._chrome = {searching: self._render_chrome(searching) for searching in (False, True)}

    # -- the base map, drawn once --

    def _t(self, x: float) -> int:
        """A thickness or length of ``x`` at 1080 lines, in pixels (at least 1)."""
        return max(1, round(x * self._u))

    def _pick_route(self, rng: np.random.Generator) -> F64:
        """A staircase path along the street grid from a start crossing to an end crossing."""
        xs, ys = self._xs, self._ys
        cx, cy = self._base_w / 2, self._base_h / 2
        half_w, half_h = self.width_px * 0.36, self.height_px * 0.30
        ix = np.flatnonzero((xs > cx - half_w) & (xs < cx + half_w))
        iy = np.flatnonzero((ys > cy - half_h) & (ys < cy + half_h))
        if len(ix) < 2 or len(iy) < 2:  # a tiny screen: a straight route across the middle
            return np.array([[cx - half_w, cy + half_h], [cx + half_w, cy - half_h]])
        i0, i1 = int(ix[0]), int(ix[-1])
        j0, j1 = int(iy[-1]), int(iy[0])  # from lower left to upper right
        moves = ["x"] * (i1 - i0) + ["y"] * (j0 - j1)
        rng.shuffle(moves)
        i, j = i0, j0
        points = [(xs[i], ys[j])]
        for k, m in enumerate(moves):
            if m == "x":
                i += 1
            else:
                j -= 1
            if k + 1 == len(moves) or moves[k + 1] != m:  # a turn (or the end)
                points.append((xs[i], ys[j]))
        return np.array(points, dtype=np.float64)

    # -- per frame --

    def _view(self, t: float) -> tuple[int, int, int, int]:
        """The crop (x0, y0, width, height) of the base map shown at time ``t``."""
        w, h = self.width_px, self.height_px
        zoom = 1.0 + (_ZOOM_MAX - 1.0) * 0.5 * (1.0 - math.cos(2 * math.pi * t / _ZOOM_PERIOD_S))
        cw, ch = min(w, round(w / zoom)), min(h, round(h / zoom))
        cx = self._base_w / 2 + self._pan_px * math.sin(2 * math.pi * t / _PAN_PERIODS_S[0])
        cy = self._base_h / 2 + self._pan_px * math.sin(2 * math.pi * t / _PAN_PERIODS_S[1] + 1.0)
        x0 = min(max(0, round(cx - cw / 2)), self._base_w - cw)
        y0 = min(max(0, round(cy - ch / 2)), self._base_h - ch)
        return x0, y0, cw, ch

    def _point_at(self, distance: float) -> F64:
        """The base-map point ``distance`` pixels along the route."""
        cum, route = self._route_cum, self._route
        k = int(np.clip(np.searchsorted(cum, distance, side="right") - 1, 0, len(route) - 2))
        seg = cum[k + 1] - cum[k]
        a = 0.0 if seg <= 0 else (distance - cum[k]) / seg
        return np.asarray(route[k] + a * (route[k + 1] - route[k]), dtype=np.float64)

    def frame(self, index: int, rate_hz: float) -> U8:
        """The screen at time ``index / rate_hz``: a new H×W×3 uint8 RGB array."""
        _check_rate(rate_hz)
        t = index / rate_hz
        w, h = self.width_px, self.height_px
        view = self._view(t)
        x0, y0, cw, ch = view
        cached = self._map_cache
        if cached is None or cached[0] != view:
            crop = self._base[y0 : y0 + ch, x0 : x0 + cw]
            scaled = crop.copy() if (cw, ch) == (w, h) else cv2.resize(crop, (w, h), interpolation=cv2.INTER_LINEAR)
            cached = self._map_cache = (view, scaled)
        out: U8 = cached[1].copy()
        sx, sy = w / cw, h / ch

        def to_screen(p: F64) -> F64:
            return np.asarray((p - (x0, y0) + 0.5) * (sx, sy) - 0.5, dtype=np.float64)

        # The route, grown to the current progress of the search cycle.
        phase = t % _SEARCH_CYCLE_S
        searching = phase < _SEARCH_S
        total = float(self._route_cum[-1])
        grown = total * _smoothstep((phase - _SEARCH_S) / _GROW_S)
        if grown > 0:
            keep = self._route_cum < grown
            pts = np.vstack([self._route[keep], self._point_at(grown)])
            fixed = _fixed(to_screen(pts))
            cv2.polylines(out, [fixed], False, _ROUTE_EDGE, self._t(16 * sx), cv2.LINE_AA, _SHIFT)
            cv2.polylines(out, [fixed], False, _ROUTE, self._t(11 * sx), cv2.LINE_AA, _SHIFT)
        start, end = to_screen(self._route[0]), to_screen(self._route[-1])
        self._pin(out, start, _START_PIN)
        self._pin(out, end, _END_PIN)

        # The location marker travels the route from start to end and back every _MARKER_LAP_S seconds.
        along = total * (0.5 - 0.5 * math.cos(2 * math.pi * t / _MARKER_LAP_S))
        self._marker(out, to_screen(self._point_at(along)), t)

        self._interface(out, t, searching, phase)
        return out

    def _pin(self, img: U8, at: F64, colour: tuple[int, int, int]) -> None:
        u = self._u
        r = 13 * u
        head = at - (0.0, 2.6 * r)
        tip = np.array([at, head + np.array([-0.85 * r, 0.5 * r]), head + np.array([0.85 * r, 0.5 * r])])
        cv2.fillConvexPoly(img, _fixed(tip), colour, cv2.LINE_AA, _SHIFT)
        c = tuple(_fixed(head).tolist())
        cv2.circle(img, c, round(r * _ONE), _BLACK, self._t(1.5), cv2.LINE_AA, _SHIFT)
        cv2.circle(img, c, round(r * _ONE), colour, -1, cv2.LINE_AA, _SHIFT)
        cv2.circle(img, c, round(0.42 * r * _ONE), _WHITE, -1, cv2.LINE_AA, _SHIFT)

    def _marker(self, img: U8, at: F64, t: float) -> None:
        u = self._u
        h, w = img.shape[:2]
        # A pulsing translucent halo, blended only inside its own small box.
        pulse = 0.5 + 0.5 * math.sin(2 * math.pi * t / 1.6)
        halo = (22 + 10 * pulse) * u
        bx0, by0 = max(0, int(at[0] - halo) - 2), max(0, int(at[1] - halo) - 2)
        bx1, by1 = min(w, int(at[0] + halo) + 3), min(h, int(at[1] + halo) + 3)
        if bx1 > bx0 and by1 > by0:
            roi = img[by0:by1, bx0:bx1]
            layer = roi.copy()
            c = tuple(_fixed(at - (bx0, by0)).tolist())
            cv2.circle(layer, c, round(halo * _ONE), _ROUTE, -1, cv2.LINE_AA, _SHIFT)
            cv2.addWeighted(layer, 0.28, roi, 0.72, 0.0, dst=roi)
        c = tuple(_fixed(at).tolist())
        cv2.circle(img, c, round(11 * u * _ONE), _WHITE, -1, cv2.LINE_AA, _SHIFT)
        cv2.circle(img, c, round(7.5 * u * _ONE), _ROUTE, -1, cv2.LINE_AA, _SHIFT)

    def _layout(self) -> None:
        """Where the interface goes on the screen (pixels)."""
        t_, w, h = self._t, self.width_px, self.height_px
        self._bar = t_(40)  # status bar height
        self._card_m = t_(24)  # search card margin
        self._card_top = self._bar + self._card_m
        self._card_bottom = self._card_top + t_(110)
        self._nav = t_(64)  # navigation bar height
        self._sheet_top = h - self._nav - t_(170)
        self._spinner_at = (w - self._card_m - t_(50), (self._card_top + self._card_bottom) // 2)

    def _render_chrome(self, searching: bool) -> list[tuple[int, U8, U8]]:
        """The static interface of one state as bands (first row, RGB, mask) to paste on each frame.

        The outlines of the panels are drawn hard-edged so that the mask is exact; everything inside
        them is anti-aliased.
        """
        u, w, h, t_ = self._u, self.width_px, self.height_px, self._t
        img = np.zeros((h, w, 3), dtype=np.uint8)
        mask = np.zeros((h, w), dtype=np.uint8)

        def panel(x0: int, y0: int, x1: int, y1: int, r: int, colour: tuple[int, int, int]) -> None:
            _rounded_rect(img, x0, y0, x1, y1, r, colour, cv2.LINE_8)
            _rounded_rect(mask, x0, y0, x1, y1, r, (255, 255, 255), cv2.LINE_8)

        # Status bar: black, with signal bars and a battery (the clock is drawn per frame).
        panel(0, 0, w, self._bar, 0, _BLACK)
        for k in range(4):
            x = w - t_(150) + k * t_(9)
            cv2.rectangle(img, (x, t_(30) - k * t_(5) - t_(6)), (x + t_(5), t_(30)), _WHITE, -1)
        cv2.rectangle(img, (w - t_(90), t_(12)), (w - t_(40), t_(30)), _WHITE, t_(2))
        cv2.rectangle(img, (w - t_(86), t_(16)), (w - t_(56), t_(26)), _WHITE, -1)

        # Search card floating under the status bar, with a hard shadow.
        m, top, bottom = self._card_m, self._card_top, self._card_bottom
        panel(m + t_(3), top + t_(4), w - m + t_(3), bottom + t_(4), t_(16), (170, 170, 170))
        panel(m, top, w - m, bottom, t_(16), _WHITE)
        cv2.circle(img, (m + t_(34), top + t_(35)), t_(8), _START_PIN, -1, cv2.LINE_AA)
        cv2.circle(img, (m + t_(34), top + t_(78)), t_(8), _END_PIN, -1, cv2.LINE_AA)
        _text(img, "My location", (m + t_(60), top + t_(44)), 0.75 * u, _TEXT, t_(2))
        _text(img, self._dest_name, (m + t_(60), top + t_(88)), 0.75 * u, _TEXT, t_(2))

        # Route sheet above the navigation bar, then the bar: black with back / home / recent buttons.
        sheet_top, nav = self._sheet_top, self._nav
        panel(0, sheet_top, w, h, t_(22), _WHITE)
        grip = (w // 2 - t_(40), sheet_top + t_(10)), (w // 2 + t_(40), sheet_top + t_(15))
        cv2.rectangle(img, *grip, (200, 200, 200), -1)
        if searching:
            _text(img, "Searching for routes...", (t_(32), sheet_top + t_(70)), 0.9 * u, _TEXT, t_(2))
        else:
            _text(img, self._route_text, (t_(32), sheet_top + t_(75)), 1.2 * u, _BLACK, t_(3))
            _text(img, "Fastest route  Light traffic", (t_(32), sheet_top + t_(125)), 0.65 * u, _GREY_TEXT, t_(2))
            bx0, by0 = w - t_(250), sheet_top + t_(45)
            _rounded_rect(img, bx0, by0, w - t_(32), by0 + t_(80), t_(40), _ROUTE, cv2.LINE_AA)
            _text(img, "GO", (bx0 + t_(80), by0 + t_(55)), 1.1 * u, _WHITE, t_(3))
        panel(0, h - nav, w, h, 0, _BLACK)
        cy, s = h - nav // 2, t_(12)
        x = w // 4
        tri = np.array([[x - s, cy], [x + s, cy - s], [x + s, cy + s]], dtype=np.int32)
        cv2.fillConvexPoly(img, tri, _WHITE, cv2.LINE_AA)
        cv2.circle(img, (w // 2, cy), s, _WHITE, t_(3), cv2.LINE_AA)
        x = 3 * w // 4
        cv2.rectangle(img, (x - s, cy - s), (x + s, cy + s), _WHITE, t_(3))

        # Cut into bands of consecutive rows that hold some interface.
        rows = np.flatnonzero(mask.any(axis=1))
        bands: list[tuple[int, U8, U8]] = []
        if len(rows):
            breaks = np.flatnonzero(np.diff(rows) > 1)
            for r0, r1 in zip(rows[np.r_[0, breaks + 1]], rows[np.r_[breaks, len(rows) - 1]], strict=True):
                bands.append((int(r0), img[r0 : r1 + 1].copy(), mask[r0 : r1 + 1].copy()))
        return bands

    def _interface(self, img: U8, t: float, searching: bool, phase: float) -> None:
        """Phone-style chrome: black status and navigation bars, a search card, a route sheet."""
        u, w, t_ = self._u, self.width_px, self._t
        for r0, layer, mask in self._chrome[searching]:
            cv2.copyTo(layer, mask, img[r0 : r0 + len(layer)])  # in place: the view has the right shape
        minutes = 9 * 60 + 41 + int(t // 60)
        _text(img, f"{minutes // 60 % 24:02d}:{minutes % 60:02d}", (t_(24), t_(28)), 0.7 * u, _WHITE, t_(2))
        if searching:  # a spinner in the search card and a progress bar in the sheet
            angle = (t * 360.0) % 360.0
            cv2.ellipse(img, self._spinner_at, (t_(18), t_(18)), angle, 0, 270, _ROUTE, t_(5), cv2.LINE_AA)
            x0, x1, y = t_(32), w - t_(32), self._sheet_top + t_(110)
            cv2.rectangle(img, (x0, y), (x1, y + t_(8)), (225, 225, 225), -1)
            cv2.rectangle(img, (x0, y), (x0 + round((x1 - x0) * phase / _SEARCH_S), y + t_(8)), _ROUTE, -1)


# --- other content -----------------------------------------------------------------------------------


def _resize(image: U8, width_px: int, height_px: int) -> U8:
    if image.shape[:2] == (height_px, width_px):
        return np.ascontiguousarray(image)
    return np.ascontiguousarray(cv2.resize(image, (width_px, height_px), interpolation=cv2.INTER_AREA))


class StillImageScene:
    """One RGB image, resized once (``cv2.INTER_AREA``) to the screen size, shown in every frame."""

    def __init__(self, image_rgb: U8, width_px: int, height_px: int) -> None:
        _check_size(width_px, height_px)
        if (
            not isinstance(image_rgb, np.ndarray)
            or image_rgb.dtype != np.uint8
            or image_rgb.ndim != 3
            or image_rgb.shape[2] != 3
            or image_rgb.shape[0] == 0
            or image_rgb.shape[1] == 0
        ):
            shape = getattr(image_rgb, "shape", None)
            dtype = getattr(image_rgb, "dtype", type(image_rgb).__name__)
            raise ContentError(f"a still image must be an H×W×3 uint8 RGB array, not {dtype} {shape}")
        self.width_px, self.height_px = width_px, height_px
        self._image = _resize(image_rgb, width_px, height_px)

    @classmethod
    def from_file(cls, path: str | Path, width_px: int, height_px: int) -> StillImageScene:
        """Read an image file (anything OpenCV decodes; grey becomes RGB), see :mod:`ipt.imageio`."""
        return cls(read_image(path, "rgb", ContentError), width_px, height_px)

    def frame(self, index: int, rate_hz: float) -> U8:
        """The image (a new array each call, so the caller may modify it)."""
        _check_rate(rate_hz)
        return self._image.copy()


class VideoScene:
    """A video file or image folder, resized to the screen (``cv2.INTER_AREA``) and played in a loop.

    Input frame ``index`` at ``rate_hz`` shows file frame ``floor(index / rate_hz · fps)`` modulo the
    number of frames, where ``fps`` is the file's frame rate (or the ``fps`` given, which wins; with
    neither, as for an image folder, file frame ``index`` is shown). Frames are treated as equally
    spaced even in a variable-frame-rate file.

    Decoding streams: frames are read in order and only the last one is kept, except that during the
    first pass the resized frames are also cached while they fit in ``cache_bytes``. If the whole file
    fit, every later lap is served from that cache; otherwise the file is re-opened at each lap (and
    whenever an earlier frame than the last one read is asked for).
    """

    def __init__(
        self,
        path: str | Path,
        width_px: int,
        height_px: int,
        fps: float | None = None,
        cache_bytes: int = 512 * 2**20,
    ) -> None:
        _check_size(width_px, height_px)
        if fps is not None and not (math.isfinite(fps) and fps > 0):
            raise ContentError(f"fps must be a positive number, not {fps!r}")
        self.path = Path(path)
        self.width_px, self.height_px = width_px, height_px
        self._source: FrameSource | None = open_frames(self.path)
        self.fps = fps if fps is not None else self._source.fps
        self._cache_limit = max(0, cache_bytes) // (width_px * height_px * 3)
        self._cache: list[U8] | None = []  # None once the first pass outgrew the budget
        self._length: int | None = None  # frames in the file, known after the first pass
        self._next = 0  # index of the file frame the source yields next
        self._last: tuple[int, U8] | None = None
        self._given: U8 | None = None  # the frame last returned (unmodified; callers get copies)
        self.reopens = 0

    def file_index(self, index: int, rate_hz: float) -> int:
        """The file frame (before looping) shown as input frame ``index`` at ``rate_hz``."""
        return file_frame_index(index, self.fps, rate_hz)

    def frame(self, index: int, rate_hz: float) -> U8:
        """File frame for input frame ``index`` at ``rate_hz``: a new array the caller may modify."""
        j = self.file_index(index, rate_hz)
        if self._length is not None:
            j %= self._length
            if self._cache is not None and len(self._cache) == self._length:
                return self._give(self._cache[j])
        if self._cache is not None and j < len(self._cache):
            return self._give(self._cache[j])
        if self._last is not None and self._last[0] == j:
            return self._give(self._last[1])
        if j < self._next:
            self._reopen()
        while True:
            source = self._source if self._source is not None else self._reopen()
            try:
                raw = next(source)
            except StopIteration:
                self._end_of_file()
                assert self._length is not None
                j %= self._length
                if self._cache is not None and len(self._cache) == self._length:
                    return self._give(self._cache[j])
                self._reopen()
                continue
            k = self._next
            self._next += 1
            caching = self._length is None and self._cache is not None
            if k != j and not caching:
                continue
            image = _resize(raw, self.width_px, self.height_px)
            if caching and self._cache is not None:
                if len(self._cache) < self._cache_limit:
                    self._cache.append(image)
                else:
                    self._cache = None
            if k == j:
                self._last = (j, image)
                return self._give(image)

    def _give(self, image: U8) -> U8:
        self._given = image
        return image.copy()

    def last_frame(self) -> U8 | None:
        """A copy of the last frame :meth:`frame` returned (as it was returned), or None before the first: what
        the sender shows while the file cannot be read."""
        return None if self._given is None else self._given.copy()

    def _end_of_file(self) -> None:
        if self._length is None:
            if self._next == 0:
                raise VideoError(f"{self.path}: contains no frames")
            self._length = self._next
        if self._source is not None:
            self._source.close()
            self._source = None

    def _reopen(self) -> FrameSource:
        if self._source is not None:
            self._source.close()
        self._source = open_frames(self.path)
        self._next = 0
        self.reopens += 1
        return self._source

    def close(self) -> None:
        """Release the file (a later :meth:`frame` re-opens it if it needs to)."""
        if self._source is not None:
            self._source.close()
            self._source = None

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
