"""The map tracker's inner loops (:mod:`ipt.receiver.core.track`), as plain Python that
:mod:`ipt.receiver.core.kernels` compiles (numba): one Gauss-Newton step projects a few hundred edge samples,
reads the difference image along each sample's normal and finds the step's sub-pixel offset, in two loops
over the samples (:func:`measure`, :func:`peaks`); the band signs, the cells' agreement and the difference's
sampled slopes (:func:`ipt.receiver.core.track.slope_noise`).

:func:`slopes_py` calls :data:`bilinear` and :func:`measure` calls :data:`slopes` and :data:`system_row`: the
module's globals, which :func:`ipt.receiver.core.kernels.ensure` replaces by their compiled versions before
it compiles their callers.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]


def bilinear_py(image: F32, x: float, y: float) -> float:
    """``image`` at (x, y), bilinear, coordinates clamped to the image (a replicated border)."""
    h, w = image.shape
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0 = min(int(x), w - 2)
    y0 = min(int(y), h - 2)
    fx = x - x0
    fy = y - y0
    top = image[y0, x0] * (1.0 - fx) + image[y0, x0 + 1] * fx
    bottom = image[y0 + 1, x0] * (1.0 - fx) + image[y0 + 1, x0 + 1] * fx
    return float(top * (1.0 - fy) + bottom * fy)


bilinear: Any = bilinear_py  # compiled by :func:`ipt.receiver.core.kernels.ensure`


def slopes_py(image: F32, u: float, v: float, nx: float, ny: float, radius: int, sign: float, out: F32) -> None:
    """The ``2·radius`` slopes of ``image`` along the unit normal (nx, ny) through (u, v), between the
    ``2·radius + 1`` profile samples at offsets −radius..radius, times ``sign``, into ``out``."""
    before = bilinear(image, u - radius * nx, v - radius * ny)
    for o in range(1, 2 * radius + 1):
        now = bilinear(image, u + (o - radius) * nx, v + (o - radius) * ny)
        out[o - 1] = (now - before) * sign
        before = now


slopes: Any = slopes_py  # compiled by :func:`ipt.receiver.core.kernels.ensure`


def system_row_py(g0: float, g1: float, g2: float, p0: float, p1: float, p2: float, out: F64) -> None:
    """One row of the track's linear system into ``out``: the image normal times d(u, v)/d(camera point)
    is g = (g0, g1, g2); times d(camera point)/d(δ rotation, Δt) that is (RP × g)ᵀ for the rotation
    (nᵀ·(−[RP]×)), with RP = (p0, p1, p2), and g for the translation."""
    out[0] = p1 * g2 - p2 * g1
    out[1] = p2 * g0 - p0 * g2
    out[2] = p0 * g1 - p1 * g0
    out[3] = g0
    out[4] = g1
    out[5] = g2


system_row: Any = system_row_py  # compiled by :func:`ipt.receiver.core.kernels.ensure`


def measure(
    obj: F64,
    nrm: F64,
    step_sign: F64,
    r: F64,
    t: F64,
    k: F64,
    image: F32,
    valid: U8,
    radius: int,
    border_px: float,
    bands: int,
    sweep: F64,
) -> tuple[I64, F32, I64, F64, F64]:
    """For the edge samples (arena points ``obj`` with floor normals ``nrm``, the map's step sign per sample)
    seen at the pose (``r``, ``t``: arena → camera) through the pinhole ``k``: which samples can be measured
    (inside the image by ``border_px``, in front of the camera, on a valid pixel when ``valid`` is not empty),
    their slopes along the image normal at offsets −radius..radius (``2·radius`` values between the
    ``2·radius + 1`` profile samples, times the map's sign: a step of the map's sign is positive), the band
    of rows each falls in, the rows of the linear system (d offset / d(δ rotation, Δt)) and each sample's
    place in the rolling shutter's sweep, s = row / (H − 1) − ½.

    ``sweep`` (6: rotation, translation) is how far the pose moves from the top row to the bottom one (a
    rolling shutter exposes them one after the other): a sample in row v is seen from the pose moved by
    s·sweep (to first order), and d offset / d sweep is s times its row of the system."""
    n = obj.shape[0]
    h, w = image.shape
    use_valid = valid.shape[0] == h and valid.shape[1] == w
    width = 2 * radius
    idx = np.empty(n, np.int64)
    raw = np.empty((n, width), np.float32)
    band = np.empty(n, np.int64)
    a_rows = np.empty((n, 6))
    place = np.empty(n)
    moving = np.abs(sweep).max() > 0.0
    count = 0
    for i in range(n):
        p0 = r[0, 0] * obj[i, 0] + r[0, 1] * obj[i, 1] + r[0, 2] * obj[i, 2]
        p1 = r[1, 0] * obj[i, 0] + r[1, 1] * obj[i, 1] + r[1, 2] * obj[i, 2]
        p2 = r[2, 0] * obj[i, 0] + r[2, 1] * obj[i, 1] + r[2, 2] * obj[i, 2]
        x0, x1, z = p0 + t[0], p1 + t[1], p2 + t[2]
        if z <= 0.0:
            continue
        sw = 0.0
        if moving:
            # The row this point lies in (seen from the centre row's pose), then the pose of that row.
            sw = (k[1, 1] * x1 / z + k[1, 2]) / (h - 1) - 0.5
            w0, w1, w2 = sw * sweep[0], sw * sweep[1], sw * sweep[2]
            p0, p1, p2 = p0 + w1 * p2 - w2 * p1, p1 + w2 * p0 - w0 * p2, p2 + w0 * p1 - w1 * p0
            x0, x1, z = p0 + t[0] + sw * sweep[3], p1 + t[1] + sw * sweep[4], p2 + t[2] + sw * sweep[5]
            if z <= 0.0:
                continue
        u = k[0, 0] * x0 / z + k[0, 2]
        v = k[1, 1] * x1 / z + k[1, 2]
        if not (border_px < u < w - 1 - border_px and border_px < v < h - 1 - border_px):
            continue
        if use_valid and valid[int(v + 0.5), int(u + 0.5)] == 0:
            continue
        # d(u, v)/d(camera point): [[d00, 0, d02], [0, d11, d12]]
        d00 = k[0, 0] / z
        d02 = -k[0, 0] * x0 / (z * z)
        d11 = k[1, 1] / z
        d12 = -k[1, 1] * x1 / (z * z)
        n0 = r[0, 0] * nrm[i, 0] + r[0, 1] * nrm[i, 1] + r[0, 2] * nrm[i, 2]
        n1 = r[1, 0] * nrm[i, 0] + r[1, 1] * nrm[i, 1] + r[1, 2] * nrm[i, 2]
        n2 = r[2, 0] * nrm[i, 0] + r[2, 1] * nrm[i, 1] + r[2, 2] * nrm[i, 2]
        nx = d00 * n0 + d02 * n2
        ny = d11 * n1 + d12 * n2
        length = math.sqrt(nx * nx + ny * ny)
        if length < 1e-9:
            continue
        nx /= length
        ny /= length
        slopes(image, u, v, nx, ny, radius, step_sign[i], raw[count])
        band[count] = min(int(v * bands / h), bands - 1)
        system_row(nx * d00, ny * d11, nx * d02 + ny * d12, p0, p1, p2, a_rows[count])
        idx[count] = i
        place[count] = v / (h - 1) - 0.5
        count += 1
    return idx[:count], raw[:count], band[:count], a_rows[:count], place[:count]


def peaks(raw: F32, band: I64, band_sign: F64, threshold: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
    """Each sample's step offset from the edge's predicted place (pixels along the normal, sub-pixel by a
    parabola through the steepest slope and its neighbours), and whether the step is clear: steeper than
    ``threshold`` (per sample) and not at the end of the profile. Slopes count under their band's sign."""
    n, width = raw.shape
    radius = width // 2
    offsets = np.zeros(n)
    strong = np.zeros(n, np.bool_)
    last = width - 1
    for i in range(n):
        s = band_sign[band[i]]
        j = 0
        peak = raw[i, 0] * s
        for o in range(1, width):
            value = raw[i, o] * s
            if value > peak:
                peak, j = value, o
        frac = 0.0
        if 0 < j < last:
            left = raw[i, j - 1] * s
            right = raw[i, j + 1] * s
            den = left - 2.0 * peak + right
            if den < 0.0:
                frac = 0.5 * (left - right) / den
            strong[i] = peak > threshold[i]
        offsets[i] = j + 0.5 + frac - radius  # slope index j lies between profile samples j and j + 1
    return offsets, strong


def band_signs(raw: F32, band: I64, bands: int) -> F64:
    """Per band of rows, the sign under which more samples find a clear step (+1 or -1); a band without
    samples takes the sign of the nearest band with some (+1 if none has any)."""
    votes = np.zeros(bands)
    counts = np.zeros(bands, np.int64)
    n, width = raw.shape
    for i in range(n):
        up = raw[i, 0]
        down = raw[i, 0]
        for o in range(1, width):
            up = max(up, raw[i, o])
            down = min(down, raw[i, o])
        diff = up + down  # (best rise) − (best fall, as a rise of the other sign) = max + min
        votes[band[i]] += 1.0 if diff > 0 else (-1.0 if diff < 0 else 0.0)
        counts[band[i]] += 1
    out = np.ones(bands)
    for b in range(bands):
        if counts[b] > 0:
            out[b] = 1.0 if votes[b] >= 0 else -1.0
    for b in range(bands):
        if counts[b] == 0:
            best = -1
            for other in range(bands):
                if counts[other] > 0 and (best < 0 or abs(other - b) < abs(best - b)):
                    best = other
            out[b] = out[best] if best >= 0 else 1.0
    return out


def cell_agreement(
    diff: F32,
    k: F64,
    r: F64,
    t: F64,
    cells_m: F64,
    cell_tag: I64,
    cell_value: F64,
    tag_on: npt.NDArray[np.bool_],
    band_sign: F64,
    valid: U8,
) -> tuple[int, int]:
    """Of the data cells of the tags marked in ``tag_on`` whose centres (``cells_m``) fall inside the image
    on a valid pixel (``valid`` empty: all are), how many are clear (their difference more than 0.3 × the
    median magnitude) and how many of those have the sign the map gives them (``cell_value``, ±1, under the
    band's sign): (agreeing, clear)."""
    h, w = diff.shape
    use_valid = valid.shape[0] == h and valid.shape[1] == w
    bands = band_sign.shape[0]
    n = cells_m.shape[0]
    values = np.empty(n)
    expected = np.empty(n)
    count = 0
    for i in range(n):
        if not tag_on[cell_tag[i]]:
            continue
        x0 = r[0, 0] * cells_m[i, 0] + r[0, 1] * cells_m[i, 1] + r[0, 2] * cells_m[i, 2] + t[0]
        x1 = r[1, 0] * cells_m[i, 0] + r[1, 1] * cells_m[i, 1] + r[1, 2] * cells_m[i, 2] + t[1]
        z = r[2, 0] * cells_m[i, 0] + r[2, 1] * cells_m[i, 1] + r[2, 2] * cells_m[i, 2] + t[2]
        if z <= 0.0:
            continue
        u = k[0, 0] * x0 / z + k[0, 2]
        v = k[1, 1] * x1 / z + k[1, 2]
        if not (0.0 <= u <= w - 1 and 0.0 <= v <= h - 1):
            continue
        ui, vi = int(u + 0.5), int(v + 0.5)
        if use_valid and valid[vi, ui] == 0:
            continue
        b = min(vi * bands // h, bands - 1)
        values[count] = diff[vi, ui] * band_sign[b]
        expected[count] = cell_value[i]
        count += 1
    if count == 0:
        return 0, 0
    magnitude = np.abs(values[:count])
    limit = 0.3 * np.median(magnitude)
    clear = 0
    agree = 0
    for i in range(count):
        if magnitude[i] > limit:
            clear += 1
            if (values[i] > 0) == (expected[i] > 0):
                agree += 1
    return agree, clear


def slopes_sampled(diff: F32, valid: U8) -> F32:
    """The absolute differences of horizontal neighbours two pixels apart, on every fourth row and every
    second column of ``diff``, in row order, where ``valid`` (same grid, the right-hand pixel) is not 0 (all
    of them when none is, or when ``valid`` is empty)."""
    h, w = diff.shape
    use_valid = valid.shape[0] == h and valid.shape[1] == w
    cols = (w + 1) // 2 - 1
    values = np.empty(((h + 3) // 4) * max(cols, 0), np.float32)
    count = 0
    if use_valid:
        for y in range(0, h, 4):
            for c in range(1, cols + 1):
                if valid[y, 2 * c] > 0:
                    values[count] = abs(diff[y, 2 * c] - diff[y, 2 * c - 2])
                    count += 1
    if count == 0:
        for y in range(0, h, 4):
            for c in range(1, cols + 1):
                values[count] = abs(diff[y, 2 * c] - diff[y, 2 * c - 2])
                count += 1
    return values[:count]
