"""The generated map app's base map, drawn once from a seed, and the drawing helpers its frames share.

:func:`draw_base_map` paints a city map into an image larger than the screen (blocks, parks, water, a
river, a street network, labels); :class:`~ipt.sender.content.GeneratedScene` crops it at each frame's
pan and zoom and draws the animated parts on top. Pure: a seeded random generator and an image in,
pixels out; the drawing order (and so the generator's draws) is part of what the map looks like.
"""

from __future__ import annotations

import math
from typing import Final

import cv2
import numpy as np
import numpy.typing as npt

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]
Colour = tuple[int, int, int]
Label = tuple[str, tuple[int, int], float, Colour]

_LAND: Final = (243, 241, 236)
_BLOCK: Final = (235, 232, 225)
_BUILDING: Final = (222, 218, 211)
_BUILDING_EDGE: Final = (190, 184, 176)
_LANDMARK: Final = (247, 222, 196)
_LANDMARK_EDGE: Final = (214, 170, 130)
_PARK: Final = (196, 230, 184)
_PARK_EDGE: Final = (150, 200, 140)
_TREE: Final = (150, 205, 140)
_WATER: Final = (164, 206, 246)
_WATER_EDGE: Final = (120, 170, 225)
_MINOR_ROAD: Final = (255, 255, 255)
_MINOR_EDGE: Final = (120, 120, 124)
_MAJOR_ROAD: Final = (255, 216, 96)
_MAJOR_EDGE: Final = (150, 100, 20)
_CENTRE_LINE: Final = (230, 170, 40)
_PARK_TEXT: Final = (30, 100, 40)
_WATER_TEXT: Final = (30, 80, 160)
_POI_COLOURS: Final = ((230, 90, 60), (60, 120, 230), (240, 150, 20), (150, 80, 200))
TEXT: Final = (34, 34, 38)
"""Dark text on the map and the interface."""
WHITE: Final = (255, 255, 255)

FONT: Final = cv2.FONT_HERSHEY_SIMPLEX
SHIFT: Final = 4
"""Sub-pixel bits of cv2 drawing."""
ONE: Final = 1 << SHIFT

_STREETS: Final = (
    "Zhongshan Rd", "Renmin Ave", "Jiefang Rd", "Harbour St", "Station Rd", "Garden Ln", "Market St",
    "River Rd", "Park Ave", "Lake St", "Hill Rd", "Bridge St", "Canal Rd", "Elm St", "Mill Ln",
    "North Ave", "College Rd", "Temple St", "Silk Rd", "Orchard Ln",
)  # fmt: skip
PLACES: Final = (
    "Library", "Museum", "City Hall", "Hospital", "Stadium", "Cinema", "Hotel", "Bank", "School",
    "Mall", "Post Office", "Theatre", "Market", "Gallery", "Cafe", "Pharmacy", "Gym", "Bakery",
)  # fmt: skip
"""Names of points of interest (and of the route's destination)."""
_PARKS: Final = ("Central Park", "Riverside Park", "Plum Garden", "Green Square", "Bamboo Park")


def fixed_point(points: F64) -> npt.NDArray[np.int32]:
    """Float pixel coordinates as cv2's fixed-point integers (``shift=SHIFT``)."""
    return np.round(points * ONE).astype(np.int32)


def put_text(
    img: U8,
    s: str,
    org: tuple[int, int],
    scale: float,
    color: Colour,
    thickness: int,
    halo: Colour | None = None,
) -> None:
    """Anti-aliased text, over a halo of ``halo`` if given."""
    if halo is not None:
        cv2.putText(img, s, org, FONT, scale, halo, thickness + max(2, thickness * 2), cv2.LINE_AA)
    cv2.putText(img, s, org, FONT, scale, color, thickness, cv2.LINE_AA)


def draw_base_map(img: U8, u: float, rng: np.random.Generator) -> tuple[F64, F64]:
    """Paint the map into ``img`` (drawing unit ``u``: 1 at 1080 lines); the x and y of its street grid."""
    return _Painter(img, u, rng).paint()


class _Painter:
    """One base map being painted: the image, the drawing unit, the generator, the labels gathered."""

    def __init__(self, img: U8, u: float, rng: np.random.Generator) -> None:
        self.img, self.u, self.rng = img, u, rng
        self.labels: list[Label] = []

    def _t(self, x: float) -> int:
        """A thickness or length of ``x`` at 1080 lines, in pixels (at least 1)."""
        return max(1, round(x * self.u))

    def _positions(self, extent: int) -> F64:
        """Road positions along one axis: an irregular grid."""
        xs = [-self.rng.uniform(0, 120) * self.u]
        while xs[-1] < extent + 150 * self.u:
            xs.append(xs[-1] + self.rng.uniform(150, 290) * self.u)
        return np.array(xs)

    def paint(self) -> tuple[F64, F64]:
        img = self.img
        bh, bw = img.shape[:2]
        img[:] = _LAND
        # Road positions: an irregular grid. Every third road (roughly) is a major one.
        xs, ys = self._positions(bw), self._positions(bh)
        major_x = self.rng.random(len(xs)) < 0.3
        major_y = self.rng.random(len(ys)) < 0.3
        self._blocks(xs, ys)
        self._river(bw, bh)
        self._streets(xs, ys, major_x, major_y, bw, bh)
        self._names(xs, ys)
        return xs, ys

    def _blocks(self, xs: F64, ys: F64) -> None:
        """Blocks between the roads: parks, water, or built-up land with buildings."""
        img, u, rng = self.img, self.u, self.rng
        park_names = list(_PARKS)
        rng.shuffle(park_names)
        pad = 10 * u
        for i in range(len(xs) - 1):
            for j in range(len(ys) - 1):
                x0, x1 = xs[i] + pad, xs[i + 1] - pad
                y0, y1 = ys[j] + pad, ys[j + 1] - pad
                kind = rng.random()
                p0, p1 = (round(x0), round(y0)), (round(x1), round(y1))
                if kind < 0.12:
                    self._park(x0, y0, x1, y1, park_names)
                elif kind < 0.17:
                    cv2.rectangle(img, p0, p1, _WATER, -1)
                else:
                    cv2.rectangle(img, p0, p1, _BLOCK, -1)
                    self._buildings(x0, y0, x1, y1)

    def _park(self, x0: float, y0: float, x1: float, y1: float, park_names: list[str]) -> None:
        img, rng = self.img, self.rng
        p0, p1 = (round(x0), round(y0)), (round(x1), round(y1))
        cv2.rectangle(img, p0, p1, _PARK, -1)
        cv2.rectangle(img, p0, p1, _PARK_EDGE, self._t(2))
        if rng.random() < 0.5:  # a pond
            c = (round((x0 + x1) / 2), round((y0 + y1) / 2))
            axes = (round((x1 - x0) * 0.25), round((y1 - y0) * 0.18))
            cv2.ellipse(img, c, axes, float(rng.uniform(0, 180)), 0, 360, _WATER, -1, cv2.LINE_AA)
        if park_names:
            self.labels.append((park_names.pop(), p0, 0.55, _PARK_TEXT))
        # Paths through the park, and a few trees as darker dots.
        for _ in range(int(rng.integers(6, 14))):
            c = (round(rng.uniform(x0, x1)), round(rng.uniform(y0, y1)))
            cv2.circle(img, c, self._t(rng.uniform(4, 9)), _TREE, -1, cv2.LINE_AA)

    def _buildings(self, x0: float, y0: float, x1: float, y1: float) -> None:
        img, u, rng = self.img, self.u, self.rng
        n = int(rng.integers(3, 9))
        for _ in range(n):
            bw_ = rng.uniform(30, 90) * u
            bh_ = rng.uniform(30, 90) * u
            if bw_ > x1 - x0 - 8 * u or bh_ > y1 - y0 - 8 * u:
                continue
            bx = rng.uniform(x0 + 4 * u, x1 - 4 * u - bw_)
            by = rng.uniform(y0 + 4 * u, y1 - 4 * u - bh_)
            landmark = rng.random() < 0.08
            fill, edge = (_LANDMARK, _LANDMARK_EDGE) if landmark else (_BUILDING, _BUILDING_EDGE)
            p0, p1 = (round(bx), round(by)), (round(bx + bw_), round(by + bh_))
            cv2.rectangle(img, p0, p1, fill, -1)
            cv2.rectangle(img, p0, p1, edge, self._t(1.2))
        if rng.random() < 0.45:  # a point of interest: a coloured icon and its name
            cx, cy = round((x0 + x1) / 2), round((y0 + y1) / 2)
            colour = _POI_COLOURS[int(rng.integers(len(_POI_COLOURS)))]
            cv2.circle(img, (cx, cy), self._t(9), WHITE, -1, cv2.LINE_AA)
            cv2.circle(img, (cx, cy), self._t(7), colour, -1, cv2.LINE_AA)
            self.labels.append((str(rng.choice(PLACES)), (cx + self._t(12), cy + self._t(5)), 0.45, TEXT))

    def _river(self, bw: int, bh: int) -> None:
        """A river winding across the map, under the roads (so the roads become bridges)."""
        u, rng = self.u, self.rng
        t = np.linspace(0.0, 1.0, 60)
        y_mid = rng.uniform(0.3, 0.7) * bh
        river = np.stack(
            [t * (bw + 200 * u) - 100 * u, y_mid + 90 * u * np.sin(t * 2 * math.pi * rng.uniform(1.0, 2.0))],
            axis=1,
        )
        cv2.polylines(self.img, [fixed_point(river)], False, _WATER_EDGE, self._t(52), cv2.LINE_AA, SHIFT)
        cv2.polylines(self.img, [fixed_point(river)], False, _WATER, self._t(46), cv2.LINE_AA, SHIFT)
        self.labels.append(("Pearl River", (round(bw * 0.55), round(y_mid + 8 * u)), 0.6, _WATER_TEXT))

    def _streets(self, xs: F64, ys: F64, major_x: npt.NDArray[np.bool_], major_y: npt.NDArray[np.bool_],
                 bw: int, bh: int) -> None:  # fmt: skip
        """The streets: all outlines first, then all fills, so that crossings merge."""
        rng = self.rng
        roads: list[tuple[F64, bool]] = []
        for x, major in zip(xs, major_x, strict=True):
            roads.append((np.array([[x, -10.0], [x, bh + 10.0]]), bool(major)))
        for y, major in zip(ys, major_y, strict=True):
            roads.append((np.array([[-10.0, y], [bw + 10.0, y]]), bool(major)))
        diag = np.array([[rng.uniform(0, 0.3) * bw, -10.0], [rng.uniform(0.7, 1.0) * bw, bh + 10.0]])
        roads.append((diag, True))
        for edge in (True, False):
            for line, major in roads:
                width = (22 if major else 13) + (4 if edge else 0)
                colour = (_MAJOR_EDGE if major else _MINOR_EDGE) if edge else (_MAJOR_ROAD if major else _MINOR_ROAD)
                cv2.polylines(self.img, [fixed_point(line)], False, colour, self._t(width), cv2.LINE_AA, SHIFT)
        # Centre lines on the major roads.
        for line, major in roads:
            if major:
                cv2.polylines(self.img, [fixed_point(line)], False, _CENTRE_LINE, self._t(1.5), cv2.LINE_AA, SHIFT)

    def _names(self, xs: F64, ys: F64) -> None:
        """Street names along the horizontal roads, then the place names; dark text on a white halo."""
        u = self.u
        names = list(_STREETS)
        self.rng.shuffle(names)
        for k, y in enumerate(ys):
            for x in xs[1::3] if k % 2 else xs[2::3]:
                name = names[(k * 7 + round(x)) % len(names)]
                self.labels.append((name, (round(x + 30 * u), round(y + 6 * u)), 0.5, TEXT))
        for s, org, scale, colour in self.labels:
            put_text(self.img, s, org, scale * u, colour, self._t(1.3), WHITE)
