"""The ``ipt`` profile's pairs: for every 8-bit colour, the two codes a tag pixel of it flickers between.

Pure and compiled (numba, :mod:`ipt.sender.jit`; the per-colour CIELAB and CIEDE2000 are
:mod:`ipt.sender.cielab`, the table and its cache file :mod:`ipt.sender.pairtable`). What one colour's
pair is (:func:`_ipt_pair`; :mod:`ipt.sender.modulator` says why): around the input's linear colour
``c`` (luminance ``Y``) the two phases are ``c ± v``, ``v`` water-filled within each channel's room so
that their L* differ by 2ΔL, quantised to 8-bit codes whose linear mean misses ``c`` by less than half a
code step.

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

**The table.** A pair depends only on the colour, so pairs are kept in a table of all 2^24 colours (128
MB per ΔL and allowance, :class:`~ipt.sender.pairtable.PairTable`, shared in a process). Index and codes
are the pixel's bytes read little-endian (``r | g << 8 | b << 16``), so that the frame kernel reads and
writes a pixel as one 32-bit word. The table is filled either lazily (a colour the first time a frame
has it, about a microsecond; the simulator and the measurements) or completely before a projection
starts (:meth:`~ipt.sender.pairtable.PairTable.complete_with_cache`): computed once on all cores (about
15 s on 2 cores here) and kept in a cache file (:func:`~ipt.sender.pairtable.cache_path`), read back in
a fraction of a second by the next run. Photographic content shows hundreds of thousands of new colours
a second; filling them as they come cost the sender seconds of missed frames at every new scene.

**The frame kernels** that write whole frames from the table are :mod:`ipt.sender.framekernel`.
"""

from __future__ import annotations

import math
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from ipt.errors import IptError
from ipt.sender import jit as jit_module
from ipt.sender.cielab import de00
from ipt.sender.cielab import de00_c as _de00_c
from ipt.sender.cielab import lab_c as _lab_c
from ipt.sender.cielab import lstar_c as _lstar_c
from ipt.sender.colour import CODE_TO_LINEAR, L8_PER_LSTAR, lstar
from ipt.sender.jit import jit

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
    return de00(100.0, 0.0, 0.0, 100.0 - dl, 0.0, 0.0)


# --- one colour ---------------------------------------------------------------------------------------

_VALID: Final = np.uint64(1 << 63)
_LOW24: Final = np.uint64(0xFFFFFF)
_SHIFT_DOWN: Final = np.uint64(24)
_MIDS: Final = (CODE_TO_LINEAR[:-1] + CODE_TO_LINEAR[1:]) / 2
"""Linear light half way between consecutive codes: the nearest code to x is the number of mids below x."""


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


def _cost_metric(l0: float, a0: float, b0: float, c0: float, c1: float, c2: float, s0: float, s1: float,
                 s2: float) -> F64:  # fmt: skip
    """M of ``ΔE00² ≈ xᵀMx`` at linear colour ``c`` (CIELAB ``l0, a0, b0``) for channel moves ``x`` in the
    directions ``s`` (±1 each), from finite differences."""
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
    return m


def _free_set_move(m: F64, w: F64, subset: int) -> tuple[bool, float, float, float]:
    """The least ``xᵀMx`` for ``w·x = 1`` with only the channels of ``subset`` (bit i: channel i) free:
    whether it exists with ``x >= 0``, and ``x``."""
    f0, f1, f2 = (subset & 1) != 0, (subset & 2) != 0, (subset & 4) != 0
    y0 = y1 = y2 = 0.0
    n = int(f0) + int(f1) + int(f2)
    if n == 1:
        k = 0 if f0 else (1 if f1 else 2)
        if m[k, k] <= 0.0:
            return False, 0.0, 0.0, 0.0
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
            return False, 0.0, 0.0, 0.0
        xi = (m[j, j] * w[i] - m[i, j] * w[j]) / det
        xj = (m[i, i] * w[j] - m[i, j] * w[i]) / det
        if xi < 0.0 or xj < 0.0:
            return False, 0.0, 0.0, 0.0
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
        g0, g1, g2 = w[0], w[1], w[2]
        a11, a12, a13 = m[0, 0], m[0, 1], m[0, 2]
        a22, a23, a33 = m[1, 1], m[1, 2], m[2, 2]
        c11 = a22 * a33 - a23 * a23
        c12 = a13 * a23 - a12 * a33
        c13 = a12 * a23 - a13 * a22
        det = a11 * c11 + a12 * c12 + a13 * c13
        if det <= 0.0:
            return False, 0.0, 0.0, 0.0
        c22 = a11 * a33 - a13 * a13
        c23 = a12 * a13 - a11 * a23
        c33 = a11 * a22 - a12 * a12
        y0 = (c11 * g0 + c12 * g1 + c13 * g2) / det
        y1 = (c12 * g0 + c22 * g1 + c23 * g2) / det
        y2 = (c13 * g0 + c23 * g1 + c33 * g2) / det
        if y0 < 0.0 or y1 < 0.0 or y2 < 0.0:
            return False, 0.0, 0.0, 0.0
    return True, y0, y1, y2


def _cheapest_direction(m: F64, w: F64) -> tuple[float, float, float]:
    """The inward channel move ``x >= 0`` that buys the most room ``w·x`` per unit of ``xᵀMx``, over the 7
    sets of free channels; all channels alike if none is usable."""
    g0, g1, g2 = w[0], w[1], w[2]
    best_q = 0.0
    x0 = x1 = x2 = 0.0
    for subset in range(1, 8):  # bit i set: channel i free to move
        ok, y0, y1, y2 = _free_set_move_c(m, w, subset)
        if not ok:
            continue
        q = g0 * y0 + g1 * y1 + g2 * y2  # room per unit of x^T M x along this direction
        if q > best_q:
            best_q = q
            x0, x1, x2 = y0, y1, y2
    if best_q <= 0.0:  # no usable metric (never seen): move every channel towards mid-grey alike
        x0 = x1 = x2 = 1.0
    return x0, x1, x2


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
    m = _cost_metric_c(l0, a0, b0, c0, c1, c2, s0, s1, s2)
    x0, x1, x2 = _cheapest_direction_c(m, w)
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


# The compiled versions. Each function calls the compiled version of the ones above it, looked up as a
# global when it is compiled (at its first call).
_nearest_c: Any = jit(_nearest)
_floor_code_c: Any = jit(_floor_code)
_de_from_c: Any = jit(_de_from)
_amplitude_c: Any = jit(_amplitude)
_fill_c: Any = jit(_fill)
_step_c: Any = jit(_step)
_balanced_c: Any = jit(_balanced)
_cost_metric_c: Any = jit(_cost_metric)
_free_set_move_c: Any = jit(_free_set_move)
_cheapest_direction_c: Any = jit(_cheapest_direction)
_allowance_move_c: Any = jit(_allowance_move)
_pair_around_c: Any = jit(_pair_around)
_fused_de_c: Any = jit(_fused_de)
_ipt_pair_c: Any = jit(_ipt_pair)
_fill_range_c: Any = jit(_fill_range)
_fill_codes_c: Any = jit(_fill_codes)
_compute_codes_c: Any = jit(_compute_codes)

JIT_UNAVAILABLE: str | None = jit_module.JIT_UNAVAILABLE
"""Why numba cannot compile here, or None if it can (:data:`ipt.sender.jit.JIT_UNAVAILABLE`, settled by
the compiles above). The ``ipt`` profile needs it."""
