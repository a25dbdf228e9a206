"""The ``ipt`` profile's pairs: for every 8-bit colour, the two codes a tag pixel of it flickers between.

Pure and compiled (numba). What one colour's pair is (:func:`_ipt_pair`; :mod:`ipt.sender.modulator`
says why): around the input's linear colour ``c`` (luminance ``Y``) the two phases are ``c ± v``, ``v``
water-filled within each channel's room so that their L* differ by 2ΔL, quantised to 8-bit codes whose
linear mean misses ``c`` by less than half a code step.

**The clip allowance.** Pure white and black, pure primaries and colours next to them leave no room for
that step. There the centre of the pair may move, by as little as gives the full step and at most a
*budget* in CIEDE2000 (:func:`allowance_budget_de00`: what a lightness change of ``clip_allowance_l8``
costs at white or black, 0.45 for 2). The move is the one that buys room at the least CIEDE2000: the
colour difference is approximated by a quadratic form around ``c`` (finite differences), and the move
of least cost per unit of room, channels only moving inwards, is solved exactly (a 3-channel quadratic
programme); its length is then found by bisection on the exact CIEDE2000 and the exact step. On white
that is a darkening, as before; on pure red it is mostly a little green and a little less red, which
costs about half the CIEDE2000 of darkening it for the same step. The 8-bit pair is checked last: if its
fused colour (the linear mean of the two codes) misses ``c`` by more than the budget, the move is
shortened until it does not. So no pixel's fused colour differs from the input by more than the budget,
or by more than 8-bit quantisation where the budget is smaller than that.

**The table.** A pair depends only on the colour, so pairs are kept in a table of all 2^24 colours
(128 MB per ΔL and allowance, :class:`PairTable`, shared in a process). Index and codes are the pixel's
bytes read little-endian (``r | g << 8 | b << 16``), so that the frame kernel reads and writes a pixel
as one 32-bit word. The table is filled either lazily (a colour the first time a frame has it, about a
microsecond; the simulator and the measurements) or completely before a projection starts
(:meth:`PairTable.complete`): computed once on all cores (about 15 s on 2 cores here) and kept in a
cache file (:func:`cache_path`), read back in a fraction of a second by the next run. Photographic
content shows hundreds of thousands of new colours a second; filling them as they come cost the
sender seconds of missed frames at every new scene.

**The frame kernel** (:func:`_modulate_rows`) writes both output frames of an input frame in one pass:
pixels outside the tags copied, tag pixels looked up (and filled if new). It reads each pixel as one
unaligned 32-bit load, writes it as one 32-bit store (the fourth byte is overwritten by the next pixel;
the last pixel of a range is written byte by byte, so ranges written by different threads never
overlap) and prefetches the table entry of the pixel 64 ahead: on photographic content the entries of a
frame span megabytes, and waiting for each in turn doubled the time of the pass.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.fileio import atomic_path
from ipt.sender.colour import CODE_TO_LINEAR, L8_PER_LSTAR, LUMINANCE_WEIGHTS, RGB_TO_XYZ, WHITE_XYZ, lstar

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]
U64 = npt.NDArray[np.uint64]


class PairsError(IptError):
    """The pairs cannot be computed here (numba cannot compile), or a value given is unusable."""


COLOURS: Final = 1 << 24
"""Entries of a pair table: every 8-bit RGB colour."""

ALGORITHM_VERSION: Final = 2
"""Changes whenever :func:`_ipt_pair` would give any colour another pair; part of the cache file's name
and header, so that a cache made by another version is never read. (Loading also recomputes a sample of
entries and compares them, in case a change forgot to bump this.)"""

AMPLITUDE_STEPS: Final = 1 << 16
"""Intervals of the luminance grid on which the amplitude a(Y) is solved (then interpolated linearly)."""

PREFETCH_PX: Final = 64
"""How many pixels ahead the frame kernel asks for a table entry (measured: 32-64 halve the time of a
photographic frame against none; 8-16 gain less)."""

_STEP_TOLERANCE: Final = 1e-4
"""A step within this fraction of 2ΔL counts as the full step."""


def amplitude_grid(delta_l: float, steps: int = AMPLITUDE_STEPS) -> F64:
    """``a(Y)`` at ``Y = k / steps``: the half-difference of luminance whose L* differ by 2ΔL around Y.

    Solves ``L*(Y + a) - L*(Y - a) = 2·ΔL·100/255`` for ``0 <= a <= Y`` by bisection to float64
    precision (``a = Y`` where even that is not enough: the darkest greys). ``a`` is not limited by
    ``Y + a <= 1``: that bound is the per-channel one applied later.
    """
    if not (math.isfinite(delta_l) and 0 < delta_l <= 127):
        raise PairsError(f"ΔL must be in (0, 127] 8-bit L units, got {delta_l}")
    target = 2.0 * delta_l / L8_PER_LSTAR
    y = np.linspace(0.0, 1.0, steps + 1)
    lo, hi = np.zeros_like(y), y.copy()
    for _ in range(64):
        a = (lo + hi) / 2
        above = lstar(y + a) - lstar(y - a) > target
        hi = np.where(above, a, hi)
        lo = np.where(above, lo, a)
    out: F64 = (lo + hi) / 2
    return out


def allowance_budget_de00(clip_allowance_l8: float) -> float:
    """The CIEDE2000 budget of a clip allowance: the colour difference of pure white and the grey whose
    L* is ``clip_allowance_l8`` 8-bit L units lower (the same at black, CIEDE2000 weighs lightness
    symmetrically about L* = 50). 2 → 0.449."""
    if not (math.isfinite(clip_allowance_l8) and clip_allowance_l8 >= 0):
        raise PairsError(f"the clip allowance must be a non-negative number, got {clip_allowance_l8}")
    dl = clip_allowance_l8 / L8_PER_LSTAR
    return _de00_py(100.0, 0.0, 0.0, 100.0 - dl, 0.0, 0.0)


# --- one colour ---------------------------------------------------------------------------------------

_VALID: Final = np.uint64(1 << 63)
_LOW24: Final = np.uint64(0xFFFFFF)
_SHIFT_DOWN: Final = np.uint64(24)
_MIDS: Final = (CODE_TO_LINEAR[:-1] + CODE_TO_LINEAR[1:]) / 2
"""Linear light half way between consecutive codes: the nearest code to x is the number of mids below x."""
_XYZ_N: Final = RGB_TO_XYZ / WHITE_XYZ[:, None]
"""Linear sRGB to XYZ relative to the white point (X/Xn, Y/Yn, Z/Zn)."""
_EPS: Final = (6.0 / 29.0) ** 3
_KAPPA: Final = 3.0 * (6.0 / 29.0) ** 2


def _nearest(x: float, mids: F64) -> int:
    """The 8-bit code nearest to linear ``x`` (``np.searchsorted(mids, x)``)."""
    lo, hi = 0, mids.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if mids[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


def _floor_code(x: float, lin: F64) -> int:
    """The largest 8-bit code whose linear light is at most ``x`` (0 if none)."""
    lo, hi = 0, lin.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if lin[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return max(lo - 1, 0)


def _lstar(y: float) -> float:
    """CIE L* of relative luminance ``y`` (as :func:`ipt.sender.colour.lstar`)."""
    if y > 0.008856451679035631:  # (6/29)^3
        return 116.0 * float(y ** (1.0 / 3.0)) - 16.0
    return 116.0 * (y / 0.12841854934601665 + 4.0 / 29.0) - 16.0  # 3 (6/29)^2


def _lab_f(t: float) -> float:
    if t > _EPS:
        return float(t ** (1.0 / 3.0))
    return t / _KAPPA + 4.0 / 29.0


def _lab(c0: float, c1: float, c2: float) -> tuple[float, float, float]:
    """CIELAB of linear sRGB (as :func:`ipt.sender.colour.linear_to_lab`)."""
    fx = _lab_f_c(_XYZ_N[0, 0] * c0 + _XYZ_N[0, 1] * c1 + _XYZ_N[0, 2] * c2)
    fy = _lab_f_c(_XYZ_N[1, 0] * c0 + _XYZ_N[1, 1] * c1 + _XYZ_N[1, 2] * c2)
    fz = _lab_f_c(_XYZ_N[2, 0] * c0 + _XYZ_N[2, 1] * c1 + _XYZ_N[2, 2] * c2)
    return 116.0 * fy - 16.0, 500.0 * (fx - fy), 200.0 * (fy - fz)


def _de00_py(l1: float, a1: float, b1: float, l2: float, a2: float, b2: float) -> float:
    """CIEDE2000 of two CIELAB colours (kL = kC = kH = 1): the scalar form of
    :func:`ipt.invisibility.ciede2000` (Sharma, Wu & Dalal 2005, eqs. 1-17)."""
    p7 = 6103515625.0  # 25^7
    c_bar = (math.hypot(a1, b1) + math.hypot(a2, b2)) / 2.0
    c7 = c_bar**7
    g = 0.5 * (1.0 - math.sqrt(c7 / (c7 + p7)))
    a1p, a2p = (1.0 + g) * a1, (1.0 + g) * a2
    c1p, c2p = math.hypot(a1p, b1), math.hypot(a2p, b2)
    h1p = 0.0 if (a1p == 0.0 and b1 == 0.0) else math.degrees(math.atan2(b1, a1p)) % 360.0
    h2p = 0.0 if (a2p == 0.0 and b2 == 0.0) else math.degrees(math.atan2(b2, a2p)) % 360.0
    chroma_product = c1p * c2p
    dl = l2 - l1
    dc = c2p - c1p
    if chroma_product == 0.0:
        dh = 0.0
    else:
        dh = h2p - h1p
        if dh > 180.0:
            dh -= 360.0
        elif dh < -180.0:
            dh += 360.0
    dhh = 2.0 * math.sqrt(chroma_product) * math.sin(math.radians(dh) / 2.0)
    l_bar = (l1 + l2) / 2.0
    cp_bar = (c1p + c2p) / 2.0
    h_sum = h1p + h2p
    if chroma_product == 0.0:
        h_bar = h_sum
    elif abs(h1p - h2p) <= 180.0:
        h_bar = h_sum / 2.0
    elif h_sum < 360.0:
        h_bar = (h_sum + 360.0) / 2.0
    else:
        h_bar = (h_sum - 360.0) / 2.0
    t = (
        1.0
        - 0.17 * math.cos(math.radians(h_bar - 30.0))
        + 0.24 * math.cos(math.radians(2.0 * h_bar))
        + 0.32 * math.cos(math.radians(3.0 * h_bar + 6.0))
        - 0.20 * math.cos(math.radians(4.0 * h_bar - 63.0))
    )
    d_theta = 30.0 * math.exp(-(((h_bar - 275.0) / 25.0) ** 2))
    cp7 = cp_bar**7
    r_c = 2.0 * math.sqrt(cp7 / (cp7 + p7))
    lm = (l_bar - 50.0) ** 2
    s_l = 1.0 + 0.015 * lm / math.sqrt(20.0 + lm)
    s_c = 1.0 + 0.045 * cp_bar
    s_h = 1.0 + 0.015 * cp_bar * t
    r_t = -math.sin(math.radians(2.0 * d_theta)) * r_c
    tl, tc, th = dl / s_l, dc / s_c, dhh / s_h
    return math.sqrt(max(tl * tl + tc * tc + th * th + r_t * tc * th, 0.0))


def _balanced(k: int, c: float, p: int, lin: F64, mids: F64) -> int:
    """The ``-`` code that balances ``+`` code ``p`` around code ``k`` (linear ``c``): nearest to 2c - lin(p);
    -1 if the mean of the two would miss ``c`` by more than 8-bit quantisation (half a code step at ``k``)."""
    q = min(int(_nearest_c(2.0 * c - lin[p], mids)), k)
    tol = max(lin[min(k + 1, 255)] - c, c - lin[max(k - 1, 0)]) / 2.0
    if abs(lin[p] + lin[q] - 2.0 * c) > 2.0 * tol:
        return -1
    return q


def _amplitude(y: float, agrid: F64) -> float:
    """a(Y), linearly interpolated in :func:`amplitude_grid`."""
    n = agrid.shape[0] - 1
    x = y * n
    k = min(max(int(x), 0), n - 1)
    return float(agrid[k] + (agrid[k + 1] - agrid[k]) * (x - k))


def _fill(c0: float, c1: float, c2: float, a: float, w: F64) -> tuple[float, float, float]:
    """The half-difference v (linear RGB) whose luminance is ``a``, within the room of each channel.

    Water-filling: v_i = min(t·c_i, m_i) with m_i = min(c_i, 1 - c_i), t such that w·v = a. Channels that
    reach their bound are held there and the others raised; t = a / Y (chromaticity held) when none does.
    With no t enough, v = m.
    """
    w0, w1, w2 = w[0], w[1], w[2]
    m0, m1, m2 = min(c0, 1.0 - c0), min(c1, 1.0 - c1), min(c2, 1.0 - c2)
    s0 = s1 = s2 = False
    t = 0.0
    for _ in range(4):
        need, slope = a, 0.0
        if s0:
            need -= w0 * m0
        elif c0 > 0.0:
            slope += w0 * c0
        if s1:
            need -= w1 * m1
        elif c1 > 0.0:
            slope += w1 * c1
        if s2:
            need -= w2 * m2
        elif c2 > 0.0:
            slope += w2 * c2
        t = need / slope if slope > 0.0 else 0.0
        changed = False
        if not s0 and c0 > 0.0 and t * c0 > m0:
            s0 = changed = True
        if not s1 and c1 > 0.0 and t * c1 > m1:
            s1 = changed = True
        if not s2 and c2 > 0.0 and t * c2 > m2:
            s2 = changed = True
        if not changed:
            break
    v0 = m0 if s0 else max(0.0, min(t * c0, m0))
    v1 = m1 if s1 else max(0.0, min(t * c1, m1))
    v2 = m2 if s2 else max(0.0, min(t * c2, m2))
    return v0, v1, v2


def _step(c0: float, c1: float, c2: float, agrid: F64, w: F64) -> float:
    """The L* step (L* units) of the continuous pair around linear colour ``c``: up to 2ΔL, less where the
    channels' room does not allow it."""
    y = w[0] * c0 + w[1] * c1 + w[2] * c2
    v0, v1, v2 = _fill_c(c0, c1, c2, _amplitude_c(y, agrid), w)
    reach = w[0] * v0 + w[1] * v1 + w[2] * v2
    return float(_lstar_c(y + reach) - _lstar_c(y - reach))


def _de_from(l0: float, a0: float, b0: float, c0: float, c1: float, c2: float) -> float:
    """CIEDE2000 between CIELAB (l0, a0, b0) and linear colour ``c``."""
    l1, a1, b1 = _lab_c(c0, c1, c2)
    return float(_de00_c(l0, a0, b0, l1, a1, b1))


def _allowance_move(
    c0: float, c1: float, c2: float, target: float, budget: float, agrid: F64, w: F64
) -> tuple[float, float, float]:
    """How far the centre of ``c``'s pair moves (linear RGB) under the allowance (see the module doc).

    The cheapest direction: with each channel moving inwards (up below 0.5, down above) by ``x_i``, the
    room gained is ``w·x`` and ``ΔE00² ≈ xᵀMx`` (M from finite differences at ``c``); the least ``xᵀMx``
    for ``w·x = 1``, ``x >= 0``, is found over the 7 sets of free channels. Its length: the least that
    gives the full step, within ``budget``.
    """
    l0, a0, b0 = _lab_c(c0, c1, c2)
    s0 = -1.0 if c0 > 0.5 else 1.0
    s1 = -1.0 if c1 > 0.5 else 1.0
    s2 = -1.0 if c2 > 0.5 else 1.0
    h = 1e-3
    m = np.empty((3, 3))
    sg = (s0, s1, s2)
    for i in range(3):
        d = [0.0, 0.0, 0.0]
        d[i] = h * sg[i]
        e = _de_from_c(l0, a0, b0, c0 + d[0], c1 + d[1], c2 + d[2])
        m[i, i] = e * e / (h * h)
    for i in range(3):
        for j in range(i + 1, 3):
            d = [0.0, 0.0, 0.0]
            d[i] = h * sg[i]
            d[j] = h * sg[j]
            e = _de_from_c(l0, a0, b0, c0 + d[0], c1 + d[1], c2 + d[2])
            m[i, j] = m[j, i] = (e * e / (h * h) - m[i, i] - m[j, j]) / 2.0
    g0, g1, g2 = w[0], w[1], w[2]
    best_q = 0.0
    x0 = x1 = x2 = 0.0
    for subset in range(1, 8):  # bit i set: channel i free to move
        f0, f1, f2 = (subset & 1) != 0, (subset & 2) != 0, (subset & 4) != 0
        y0 = y1 = y2 = 0.0
        n = int(f0) + int(f1) + int(f2)
        if n == 1:
            k = 0 if f0 else (1 if f1 else 2)
            if m[k, k] <= 0.0:
                continue
            val = w[k] / m[k, k]
            if k == 0:
                y0 = val
            elif k == 1:
                y1 = val
            else:
                y2 = val
        elif n == 2:
            i = 0 if f0 else 1
            j = 2 if f2 else 1
            det = m[i, i] * m[j, j] - m[i, j] * m[i, j]
            if det <= 0.0:
                continue
            xi = (m[j, j] * w[i] - m[i, j] * w[j]) / det
            xj = (m[i, i] * w[j] - m[i, j] * w[i]) / det
            if xi < 0.0 or xj < 0.0:
                continue
            if i == 0:
                y0 = xi
            else:
                y1 = xi
            if j == 2:
                y2 = xj
            else:
                y1 = xj
        else:
            # 3x3: x = M^-1 g by cofactors
            a11, a12, a13 = m[0, 0], m[0, 1], m[0, 2]
            a22, a23, a33 = m[1, 1], m[1, 2], m[2, 2]
            c11 = a22 * a33 - a23 * a23
            c12 = a13 * a23 - a12 * a33
            c13 = a12 * a23 - a13 * a22
            det = a11 * c11 + a12 * c12 + a13 * c13
            if det <= 0.0:
                continue
            c22 = a11 * a33 - a13 * a13
            c23 = a12 * a13 - a11 * a23
            c33 = a11 * a22 - a12 * a12
            y0 = (c11 * g0 + c12 * g1 + c13 * g2) / det
            y1 = (c12 * g0 + c22 * g1 + c23 * g2) / det
            y2 = (c13 * g0 + c23 * g1 + c33 * g2) / det
            if y0 < 0.0 or y1 < 0.0 or y2 < 0.0:
                continue
        q = g0 * y0 + g1 * y1 + g2 * y2  # room per unit of x^T M x along this direction
        if q > best_q:
            best_q = q
            x0, x1, x2 = y0, y1, y2
    if best_q <= 0.0:  # no usable metric (never seen): move every channel towards mid-grey alike
        x0 = x1 = x2 = 1.0
    d0, d1, d2 = s0 * x0, s1 * x1, s2 * x2
    # Longest move that stays in the RGB cube.
    s_max = 1e300
    for ci, di in ((c0, d0), (c1, d1), (c2, d2)):
        if di > 0.0:
            s_max = min(s_max, (1.0 - ci) / di)
        elif di < 0.0:
            s_max = min(s_max, ci / -di)
    if not s_max < 1e300:
        return 0.0, 0.0, 0.0
    # The longest move within the budget ...
    if _de_from_c(l0, a0, b0, c0 + s_max * d0, c1 + s_max * d1, c2 + s_max * d2) <= budget:
        s_cap = s_max
    else:
        lo, hi = 0.0, s_max
        for _ in range(24):
            mid = (lo + hi) / 2.0
            if _de_from_c(l0, a0, b0, c0 + mid * d0, c1 + mid * d1, c2 + mid * d2) <= budget:
                lo = mid
            else:
                hi = mid
        s_cap = lo
    full = target * (1.0 - _STEP_TOLERANCE)
    if _step_c(c0 + s_cap * d0, c1 + s_cap * d1, c2 + s_cap * d2, agrid, w) < full:
        return s_cap * d0, s_cap * d1, s_cap * d2
    # ... and within it, the shortest that gives the full step.
    lo, hi = 0.0, s_cap
    for _ in range(24):
        mid = (lo + hi) / 2.0
        if _step_c(c0 + mid * d0, c1 + mid * d1, c2 + mid * d2, agrid, w) >= full:
            hi = mid
        else:
            lo = mid
    return hi * d0, hi * d1, hi * d2


def _pair_around(
    c0: float,
    c1: float,
    c2: float,
    k0: int,
    k1: int,
    k2: int,
    lin: F64,
    mids: F64,
    agrid: F64,
    w: F64,
    target: float,
) -> np.uint64:
    """The 8-bit pair centred on linear colour ``c`` (codes ``k`` nearest to it), packed.

    Codes: for each channel the + code is one of the two around c_i + v_i and the - code balances it
    (nearest to 2 c_i - lin(+); a + code that cannot be balanced within half a code step is skipped, the
    lower one always can); of those (up to 8) combinations, the one whose L* difference is nearest to 2ΔL
    wins, so that the quantisation of a few dominant colours does not bias the signal.
    """
    w0, w1, w2 = w[0], w[1], w[2]
    y = w0 * c0 + w1 * c1 + w2 * c2
    v0, v1, v2 = _fill_c(c0, c1, c2, _amplitude_c(y, agrid), w)
    lo0 = min(max(_floor_code_c(c0 + v0, lin), k0), 255) if v0 > 0.0 else k0
    lo1 = min(max(_floor_code_c(c1 + v1, lin), k1), 255) if v1 > 0.0 else k1
    lo2 = min(max(_floor_code_c(c2 + v2, lin), k2), 255) if v2 > 0.0 else k2
    n0 = 2 if (v0 > 0.0 and lo0 < 255) else 1
    n1 = 2 if (v1 > 0.0 and lo1 < 255) else 1
    n2 = 2 if (v2 > 0.0 and lo2 < 255) else 1
    best = 1e300
    p0, q0, p1, q1, p2, q2 = k0, k0, k1, k1, k2, k2
    for i0 in range(n0):
        e0 = lo0 + i0
        f0 = _balanced_c(k0, c0, e0, lin, mids)
        if f0 < 0:
            continue
        for i1 in range(n1):
            e1 = lo1 + i1
            f1 = _balanced_c(k1, c1, e1, lin, mids)
            if f1 < 0:
                continue
            for i2 in range(n2):
                e2 = lo2 + i2
                f2 = _balanced_c(k2, c2, e2, lin, mids)
                if f2 < 0:
                    continue
                y_up = w0 * lin[e0] + w1 * lin[e1] + w2 * lin[e2]
                y_down = w0 * lin[f0] + w1 * lin[f1] + w2 * lin[f2]
                miss = abs(_lstar_c(y_up) - _lstar_c(y_down) - target)
                if miss < best:
                    best = miss
                    p0, q0, p1, q1, p2, q2 = e0, f0, e1, f1, e2, f2
    up = np.uint64(p0) | (np.uint64(p1) << np.uint64(8)) | (np.uint64(p2) << np.uint64(16))
    down = np.uint64(q0) | (np.uint64(q1) << np.uint64(8)) | (np.uint64(q2) << np.uint64(16))
    return _VALID | up | (down << _SHIFT_DOWN)


def _fused_de(e: np.uint64, l0: float, a0: float, b0: float, lin: F64) -> float:
    """CIEDE2000 between CIELAB (l0, a0, b0) and the linear mean of the packed pair ``e``."""
    sh8, sh16, m8 = np.uint64(8), np.uint64(16), np.uint64(255)
    down = e >> _SHIFT_DOWN
    f0 = (lin[e & m8] + lin[down & m8]) / 2.0
    f1 = (lin[(e >> sh8) & m8] + lin[(down >> sh8) & m8]) / 2.0
    f2 = (lin[(e >> sh16) & m8] + lin[(down >> sh16) & m8]) / 2.0
    return float(_de_from_c(l0, a0, b0, f0, f1, f2))


def _ipt_pair(
    r: int, g: int, b: int, lin: F64, mids: F64, agrid: F64, w: F64, target: float, budget: float
) -> np.uint64:
    """The pair of one colour: ``valid | up | down << 24``, each code packed ``r | g << 8 | b << 16``.

    ``target`` is 2ΔL in L* units, ``budget`` the allowance in CIEDE2000 (0: none).
    """
    c0, c1, c2 = lin[r], lin[g], lin[b]
    if budget <= 0.0 or _step_c(c0, c1, c2, agrid, w) >= target * (1.0 - _STEP_TOLERANCE):
        return np.uint64(_pair_around_c(c0, c1, c2, r, g, b, lin, mids, agrid, w, target))
    d0, d1, d2 = _allowance_move_c(c0, c1, c2, target, budget, agrid, w)
    l0, a0, b0 = _lab_c(c0, c1, c2)
    e = np.uint64(0)
    lo, hi = 0.0, 1.0
    for it in range(12):
        f = hi if it == 0 else (lo + hi) / 2.0
        n0, n1, n2 = c0 + f * d0, c1 + f * d1, c2 + f * d2
        k0, k1, k2 = _nearest_c(n0, mids), _nearest_c(n1, mids), _nearest_c(n2, mids)
        cand = _pair_around_c(n0, n1, n2, k0, k1, k2, lin, mids, agrid, w, target)
        if _fused_de_c(cand, l0, a0, b0, lin) <= budget:
            e = cand
            if it == 0:  # the whole move quantises within the budget
                break
            lo = f
        else:
            hi = f
    if e == 0:  # even a short move quantises beyond the budget: the exact pair, shrunk
        e = _pair_around_c(c0, c1, c2, r, g, b, lin, mids, agrid, w, target)
    return np.uint64(e)


def _fill_range(
    start: int, stop: int, table: U64, lin: F64, mids: F64, agrid: F64, w: F64, target: float, budget: float
) -> None:
    """Fill the table entries ``start..stop`` (colour index ``r | g << 8 | b << 16``) not yet filled."""
    for i in range(start, stop):
        if table[i] == 0:
            table[i] = _ipt_pair_c(
                np.int64(i & 255), np.int64((i >> 8) & 255), np.int64(i >> 16), lin, mids, agrid, w, target, budget
            )


def _fill_codes(codes: U8, table: U64, lin: F64, mids: F64, agrid: F64, w: F64, target: float, budget: float) -> None:
    """Fill the table entries of the colours ``codes`` (N×3)."""
    for j in range(codes.shape[0]):
        r, g, b = np.int64(codes[j, 0]), np.int64(codes[j, 1]), np.int64(codes[j, 2])
        i = r | (g << 8) | (b << 16)
        if table[i] == 0:
            table[i] = _ipt_pair_c(r, g, b, lin, mids, agrid, w, target, budget)


def _compute_codes(codes: U8, out: U64, lin: F64, mids: F64, agrid: F64, w: F64, target: float, budget: float) -> None:
    """The entries of the colours ``codes`` (N×3) into ``out``, computed afresh (no table)."""
    for j in range(codes.shape[0]):
        r, g, b = np.int64(codes[j, 0]), np.int64(codes[j, 1]), np.int64(codes[j, 2])
        out[j] = _ipt_pair_c(r, g, b, lin, mids, agrid, w, target, budget)


# --- frames -------------------------------------------------------------------------------------------


def _modulate_rows(
    rgb: U8,
    mask: npt.NDArray[np.int8],
    table: U64,
    lin: F64,
    mids: F64,
    agrid: F64,
    w: F64,
    target: float,
    budget: float,
    out_plus: U8,
    out_minus: U8,
    want_plus: bool,
    want_minus: bool,
    row0: int,
    row1: int,
) -> None:
    """Rows ``row0..row1`` of both phases (those wanted); fills the table entries it needs (see the module
    doc). All arrays C-contiguous; ``rgb`` and the outputs H×W×3, ``mask`` H×W."""
    width = mask.shape[1]
    first, last = row0 * width, row1 * width - 1  # pixel indices
    if last < first:
        return
    src = rgb.reshape(-1)
    plus = out_plus.reshape(-1)
    minus = out_minus.reshape(-1)
    flat_mask = mask.reshape(-1)
    m8, sh8, sh16 = np.uint32(255), np.uint32(8), np.uint32(16)
    low24 = np.uint32(0xFFFFFF)
    px: Any
    for i in range(first, last + 1):
        j = 3 * i
        ahead = i + PREFETCH_PX
        if ahead < last and flat_mask[ahead] != 0:
            _prefetch(table, np.int64(_load_u32(src, 3 * ahead) & low24))
        if i < last:
            px = _load_u32(src, j) & low24
        else:
            px = np.uint32(src[j]) | (np.uint32(src[j + 1]) << sh8) | (np.uint32(src[j + 2]) << sh16)
        m = flat_mask[i]
        if m == 0:
            up = down = px
        else:
            e = table[np.int64(px)]
            if e == 0:
                red, green, blue = np.int64(px & m8), np.int64((px >> sh8) & m8), np.int64(px >> sh16)
                e = _ipt_pair_c(red, green, blue, lin, mids, agrid, w, target, budget)
                table[np.int64(px)] = e
            brighter = np.uint32(e & _LOW24)
            darker = np.uint32((e >> _SHIFT_DOWN) & _LOW24)
            up, down = (brighter, darker) if m > 0 else (darker, brighter)
        if i < last:
            if want_plus:
                _store_u32(plus, j, up)
            if want_minus:
                _store_u32(minus, j, down)
        else:
            if want_plus:
                plus[j], plus[j + 1], plus[j + 2] = up & m8, (up >> sh8) & m8, (up >> sh16) & m8
            if want_minus:
                minus[j], minus[j + 1], minus[j + 2] = down & m8, (down >> sh8) & m8, (down >> sh16) & m8


# --- compiling ----------------------------------------------------------------------------------------

JIT_UNAVAILABLE: str | None = None
"""Why numba cannot compile here (e.g. memory that is both writable and executable is forbidden, as
under systemd's MemoryDenyWriteExecute), or None if it can. The ``ipt`` profile needs it."""


def _unavailable(*_args: Any) -> Any:
    raise PairsError(f"the ipt modulation profile needs numba, but {JIT_UNAVAILABLE}")


def _jit(fn: Callable[..., Any]) -> Any:
    """``fn`` compiled by numba (nogil, so worker threads run in parallel); cached on disk if possible.

    Where numba cannot run, a stand-in that raises :class:`PairsError` when called, so that the module
    (and the ``paper`` profile) still imports.
    """
    global JIT_UNAVAILABLE
    try:
        import numba
    except (ImportError, OSError) as exc:  # OSError: llvmlite refused executable memory
        JIT_UNAVAILABLE = f"numba cannot compile here ({type(exc).__name__}: {exc})"
        return _unavailable
    try:
        return numba.njit(nogil=True, cache=True)(fn)
    except RuntimeError:  # no writable cache location: compile in every process
        return numba.njit(nogil=True)(fn)


def _intrinsics() -> tuple[Any, Any, Any]:
    """Three LLVM operations numba does not offer: an unaligned 32-bit load and store at a byte offset of a
    uint8 array, and a prefetch of an array element (no bounds checks: the kernel keeps them in range)."""
    try:
        from llvmlite import ir
        from numba import types
        from numba.core import cgutils as numba_cgutils
        from numba.extending import intrinsic
    except (ImportError, OSError):
        return _unavailable, _unavailable, _unavailable
    cgutils: Any = numba_cgutils  # untyped

    def pointer(context: Any, builder: Any, array_type: Any, array: Any, index: Any) -> Any:
        ary = context.make_array(array_type)(context, builder, array)
        return cgutils.get_item_pointer(context, builder, array_type, ary, [index], wraparound=False)

    @intrinsic
    def load_u32(typingctx: Any, array: Any, index: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            ptr = pointer(context, builder, signature.args[0], args[0], args[1])
            return builder.load(builder.bitcast(ptr, ir.IntType(32).as_pointer()), align=1)

        return types.uint32(array, index), codegen

    @intrinsic
    def store_u32(typingctx: Any, array: Any, index: Any, value: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            ptr = pointer(context, builder, signature.args[0], args[0], args[1])
            word = context.cast(builder, args[2], signature.args[2], types.uint32)
            builder.store(word, builder.bitcast(ptr, ir.IntType(32).as_pointer()), align=1)
            return context.get_dummy_value()

        return types.void(array, index, value), codegen

    @intrinsic
    def prefetch(typingctx: Any, array: Any, index: Any) -> Any:
        def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
            ptr = pointer(context, builder, signature.args[0], args[0], args[1])
            i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
            fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
            fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0i8")
            # read, keep in all cache levels, data cache
            builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
            return context.get_dummy_value()

        return types.void(array, index), codegen

    return load_u32, store_u32, prefetch


_load_u32, _store_u32, _prefetch = _intrinsics()

# The compiled versions. Each function calls the compiled version of the ones above it, looked up as a
# global when it is compiled (at its first call).
_nearest_c: Any = _jit(_nearest)
_floor_code_c: Any = _jit(_floor_code)
_lstar_c: Any = _jit(_lstar)
_lab_f_c: Any = _jit(_lab_f)
_lab_c: Any = _jit(_lab)
_de00_c: Any = _jit(_de00_py)
_de_from_c: Any = _jit(_de_from)
_amplitude_c: Any = _jit(_amplitude)
_fill_c: Any = _jit(_fill)
_step_c: Any = _jit(_step)
_balanced_c: Any = _jit(_balanced)
_allowance_move_c: Any = _jit(_allowance_move)
_pair_around_c: Any = _jit(_pair_around)
_fused_de_c: Any = _jit(_fused_de)
_ipt_pair_c: Any = _jit(_ipt_pair)
_fill_range_c: Any = _jit(_fill_range)
_fill_codes_c: Any = _jit(_fill_codes)
_compute_codes_c: Any = _jit(_compute_codes)
_modulate_rows_c: Any = _jit(_modulate_rows)


# --- the table ----------------------------------------------------------------------------------------


def unpack(entries: U64) -> tuple[U8, U8]:
    """The (+, -) codes (N×3 each) of packed table entries."""
    shifts = np.array([0, 8, 16], dtype=np.uint64)
    up = ((entries[:, None] >> shifts) & np.uint64(255)).astype(np.uint8)
    down = (((entries[:, None] >> _SHIFT_DOWN) >> shifts) & np.uint64(255)).astype(np.uint8)
    return up, down


def colour_index(codes: U8) -> npt.NDArray[np.int64]:
    """Table index of N×3 colours."""
    c = codes.astype(np.int64)
    out: npt.NDArray[np.int64] = c[:, 0] | (c[:, 1] << 8) | (c[:, 2] << 16)
    return out


class PairTable:
    """The pairs of every 8-bit colour for one ΔL and clip allowance (see the module doc); get one with
    :func:`pair_table`, which shares them in a process."""

    def __init__(self, delta_l: float, clip_allowance_l8: float) -> None:
        self.delta_l = float(delta_l)
        self.clip_allowance_l8 = float(clip_allowance_l8)
        self.budget_de00 = allowance_budget_de00(clip_allowance_l8) if clip_allowance_l8 > 0 else 0.0
        """The allowance as CIEDE2000 (0: none)."""
        self.agrid = amplitude_grid(delta_l)
        # Written through once (128 MB) rather than np.zeros' untouched pages: faulting pages in one at a
        # time, at random, as new colours come (a page per colour at first) costs far more per page.
        self.table: U64 = np.empty(COLOURS, dtype=np.uint64)
        self.table.fill(0)
        self.lin = np.ascontiguousarray(CODE_TO_LINEAR)
        self.mids = np.ascontiguousarray(_MIDS)
        self.w = np.ascontiguousarray(LUMINANCE_WEIGHTS)
        self.target = 2.0 * delta_l / L8_PER_LSTAR
        self.complete = False
        """Every entry is filled."""
        self.lock = threading.Lock()
        """Held while the table is being completed."""

    def args(self) -> tuple[Any, ...]:
        """The table and its constants, as the compiled functions take them."""
        return self.table, self.lin, self.mids, self.agrid, self.w, self.target, self.budget_de00

    def pairs(self, codes: U8) -> tuple[U8, U8]:
        """The (+, -) codes of N colours (N×3 uint8): what a white tag pixel (mask +1) of that colour shows."""
        codes = np.ascontiguousarray(codes, dtype=np.uint8).reshape(-1, 3)
        _fill_codes_c(codes, *self.args())
        return unpack(self.table[colour_index(codes)])

    def fill(self, threads: int = 0, progress: Callable[[float], None] | None = None) -> None:
        """Fill every entry not yet filled, in ``threads`` threads (0: one per core); ``progress`` is
        called with the share done (0..1) as chunks finish."""
        threads = threads if threads > 0 else max(1, os.cpu_count() or 1)
        chunk = 1 << 16
        starts = range(0, COLOURS, chunk)
        args = self.args()
        with ThreadPoolExecutor(threads, thread_name_prefix="ipt-pairs") as pool:
            futures = [pool.submit(_fill_range_c, s, s + chunk, *args) for s in starts]
            for done, fut in enumerate(futures, 1):
                fut.result()
                if progress is not None:
                    progress(done / len(futures))
        self.complete = True

    def spot_check(self, entries: U64, count: int = 4096, seed: int = 0) -> int:
        """How many of ``count`` random colours (and the 8 corners of the cube) have another entry in
        ``entries`` (a whole table) than computing them again gives: 0 for a table made by this code."""
        rng = np.random.default_rng(seed)
        corners = [0, 0xFF, 0xFF00, 0xFFFF, 0xFF0000, 0xFF00FF, 0xFFFF00, 0xFFFFFF]
        index = np.concatenate([rng.integers(0, COLOURS, count), np.array(corners, np.int64)])
        codes = np.ascontiguousarray(np.stack([index & 255, (index >> 8) & 255, index >> 16], axis=1).astype(np.uint8))
        fresh = np.empty(len(index), dtype=np.uint64)
        _compute_codes_c(codes, fresh, *self.args()[1:])
        return int(np.count_nonzero(fresh != entries[index]))

    def complete_with_cache(self, cache_dir: os.PathLike[str] | None, log: Callable[[str], None]) -> str:
        """Make the table complete: from the cache file in ``cache_dir`` if it holds this table, else by
        computing it (progress through ``log``) and then writing the cache (``None``: no cache). Returns a
        sentence saying which, and how long it took."""
        with self.lock:
            if self.complete:
                return "colour table: already complete"
            t0 = time.perf_counter()
            path = None if cache_dir is None else cache_path(Path(cache_dir), self.delta_l, self.clip_allowance_l8)
            problem = None
            if path is not None and path.exists():
                problem = read_cache(path, self)
                if problem is None:
                    return f"colour table: read {path} in {time.perf_counter() - t0:.2f} s"
                log(f"colour table: {path}: {problem}; computing it again")
            log(
                f"colour table: computing the pairs of all {COLOURS:,} colours for ΔL {self.delta_l:g}, clip "
                f"allowance {self.clip_allowance_l8:g} (once; a minute or less)"
            )
            next_report = [0.1]

            def progress(share: float) -> None:
                if share >= next_report[0] - 1e-9:
                    log(f"colour table: {share:.0%} ({time.perf_counter() - t0:.0f} s)")
                    next_report[0] += 0.1

            self.fill(progress=progress)
            took = time.perf_counter() - t0
            if path is None:
                return f"colour table: computed in {took:.1f} s (no cache folder: computed at every start)"
            try:
                write_cache(path, self)
                remove_stale(path.parent)
            except OSError as exc:
                return (
                    f"colour table: computed in {took:.1f} s; cannot keep it in {path} ({exc}): computed at every start"
                )
            return f"colour table: computed in {took:.1f} s, kept in {path}"


_TABLES: dict[tuple[float, float], PairTable] = {}
_TABLES_LOCK = threading.Lock()


def pair_table(delta_l: float, clip_allowance_l8: float) -> PairTable:
    """The process's table for ΔL and clip allowance (made, empty, on first use)."""
    with _TABLES_LOCK:
        key = (float(delta_l), float(clip_allowance_l8))
        table = _TABLES.get(key)
        if table is None:
            table = _TABLES[key] = PairTable(delta_l, clip_allowance_l8)
        return table


# --- the cache file -----------------------------------------------------------------------------------

_MAGIC: Final = b"IPTPAIRS"
_HEADER_BYTES: Final = 4096
"""The header (magic, then JSON padded with spaces) takes the first 4096 bytes; the entries follow,
little-endian uint64, so that they are read straight into the table."""


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/ipt`` (``~/.cache/ipt`` when it is not set)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "ipt"


def cache_path(cache_dir: Path, delta_l: float, clip_allowance_l8: float) -> Path:
    """The cache file of one table."""
    return cache_dir / f"pairs-v{ALGORITHM_VERSION}-dl{delta_l:.6g}-a{clip_allowance_l8:.6g}.bin"


def _header(table: PairTable, sha256: str) -> dict[str, Any]:
    return {
        "format": "ipt pair table",
        "version": ALGORITHM_VERSION,
        "delta_l": table.delta_l,
        "clip_allowance_l8": table.clip_allowance_l8,
        "entries": COLOURS,
        "dtype": "<u8",
        "sha256": sha256,
    }


def write_cache(path: Path, table: PairTable) -> None:
    """Write the complete ``table`` to ``path`` (made beside it and renamed: never half a file)."""
    if not table.complete:
        raise PairsError("only a complete table is cached")
    path.parent.mkdir(parents=True, exist_ok=True)
    data = table.table.astype("<u8", copy=False)
    header = json.dumps(_header(table, hashlib.sha256(data.data).hexdigest())).encode()
    block = _MAGIC + header.ljust(_HEADER_BYTES - len(_MAGIC), b" ")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(block)
        f.write(data.data)


def read_cache(path: Path, table: PairTable) -> str | None:
    """Read ``path`` into ``table`` and mark it complete; or say why not (the table is then left as it was
    before, entries already filled lazily kept)."""
    try:
        with open(path, "rb") as f:
            block = f.read(_HEADER_BYTES)
            if len(block) < _HEADER_BYTES or not block.startswith(_MAGIC):
                return "not a pair table"
            try:
                header = json.loads(block[len(_MAGIC) :].decode())
            except (UnicodeDecodeError, ValueError):
                return "unreadable header"
            want = _header(table, "")
            for key in ("format", "version", "delta_l", "clip_allowance_l8", "entries", "dtype"):
                if not isinstance(header, dict) or header.get(key) != want[key]:
                    return f"made for another table ({key})"
            data = np.empty(COLOURS, dtype="<u8")
            if f.readinto(data.data.cast("B")) != data.nbytes or f.read(1):
                return "truncated or too long"
    except OSError as exc:
        return f"cannot read ({exc.strerror or exc})"
    if hashlib.sha256(data.data).hexdigest() != header.get("sha256"):
        return "checksum mismatch (damaged)"
    if table.spot_check(data) != 0:  # made by other code that kept the version number
        return "its entries differ from what this version computes"
    # The entries filled lazily so far are the same in `data`; a kernel running now keeps the old array.
    table.table = data.view(np.uint64)
    table.complete = True
    return None


def remove_stale(cache_dir: Path) -> None:
    """Delete cache files of other algorithm versions in ``cache_dir`` (they can never be read again)."""
    with contextlib.suppress(OSError):
        for p in cache_dir.glob("pairs-v*-dl*-a*.bin"):
            if not p.name.startswith(f"pairs-v{ALGORITHM_VERSION}-"):
                p.unlink(missing_ok=True)
