"""The sparse tracker's inner loop (:mod:`ipt.receiver.core.sparse`), as plain Python that
:mod:`ipt.receiver.core.kernels` compiles (numba): the map's edge samples projected through the camera's own
lens model (OpenCV's k1, k2, p1, p2, k3: the points are distorted, the image never undistorted) and the two raw
frames of a pair read along each sample's floor normal.

**The model** (:func:`moments`). The pair: y = I_k − g·I_j − c·M ≈ Δg·I_j + Δc·M − F′·δ + g·I_j′·ε − C′·φ
(M the map's blurred step, F = g·I_j + c·M, C = g·I_j + (c/2)·M the content, φ its motion), each profile
centred so that its own brightness level drops out. It holds whatever the floor shows, but over a flat
floor it sees only δ + ε (the two frames' steps together). Each frame alone: I_k = content + (c/2)·M(o − δ),
I_j = content − (c/2g)·M(o − ε), the content taken for a straight line along the profile (projected out),
weighted by a frame's pixel noise variance over the variance the line leaves (at most 1): over a flat floor
these place each frame's step apart; over busy content they weigh nothing.

:func:`profiles` calls :data:`edge_row` and :data:`read_profile` (which call :data:`project_floor`, :data:`distort`
and :data:`bilinear_u8`): globals that ``kernels._compile_sparse`` replaces by their compiled versions first.
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


def distort_py(x: float, y: float, dist: F64, jac: F64) -> tuple[float, float]:
    """The normalised image point (x, y) = (X/Z, Y/Z) through OpenCV's lens model (``dist``: k1, k2, p1, p2,
    k3): the distorted normalised point, and its 2x2 Jacobian d(xd, yd)/d(x, y) into ``jac``."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    slope = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    cross = 2.0 * x * y * slope + 2.0 * p1 * x + 2.0 * p2 * y
    jac[0, 0] = radial + 2.0 * x * x * slope + 2.0 * p1 * y + 6.0 * p2 * x
    jac[0, 1] = cross
    jac[1, 0] = cross
    jac[1, 1] = radial + 2.0 * y * y * slope + 6.0 * p1 * y + 2.0 * p2 * x
    return xd, yd


distort: Any = distort_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def bilinear_u8_py(image: U8, x: float, y: float) -> float:
    """``image`` (8-bit) at (x, y), bilinear; the caller keeps (x, y) at least a pixel inside."""
    x0 = int(x)
    y0 = int(y)
    fx = x - x0
    fy = y - y0
    # unsigned indices (x, y are never negative): no check for an index counted from the end
    xa, xb, ya, yb = np.uint64(x0), np.uint64(x0 + 1), np.uint64(y0), np.uint64(y0 + 1)
    top = image[ya, xa] * (1.0 - fx) + image[ya, xb] * fx
    bottom = image[yb, xa] * (1.0 - fx) + image[yb, xb] * fx
    return float(top * (1.0 - fy) + bottom * fy)


bilinear_u8: Any = bilinear_u8_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def distort_point_py(x: float, y: float, dist: F64) -> tuple[float, float]:
    """:func:`distort_py`'s point alone (the same arithmetic, to the bit), without its Jacobian."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return xd, yd


distort_point: Any = distort_point_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def project_floor_py(r: F64, t: F64, k: F64, dist: F64, px: float, py: float) -> tuple[bool, float, float]:
    """The image place (u, v) of the floor point (px, py, 0) at the pose (r, t) (:func:`edge_row_py`'s, to the
    bit); False (and zeros) behind the camera."""
    z = r[2, 0] * px + r[2, 1] * py + t[2]
    if z <= 1e-6:
        return False, 0.0, 0.0
    xd, yd = distort_point((r[0, 0] * px + r[0, 1] * py + t[0]) / z, (r[1, 0] * px + r[1, 1] * py + t[1]) / z, dist)
    return True, k[0, 0] * xd + k[0, 1] * yd + k[0, 2], k[1, 1] * yd + k[1, 2]


project_floor: Any = project_floor_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def read_profile_py(
    image: U8,
    r: F64,
    t: F64,
    k: F64,
    dist: F64,
    ox: float,
    oy: float,
    dx: float,
    dy: float,
    mid_u: float,
    mid_v: float,
    lines: int,
    out: F32,
    row: int,
    lams: F64,
) -> bool:
    """``image`` into row ``row`` of ``out``: at its width's floor points (ox, oy) + o·(dx, dy), o = −radius..radius
    (``lams``: o / radius), seen at the pose (r, t): three points projected exactly (the ends, and the middle
    (``mid_u``, ``mid_v``): the caller's :func:`edge_row_py` place of (ox, oy)), the others on the parabola through them
    (the lens and the perspective bend a few pixels' profile by far less than 0.01 px), bilinear, averaged over
    ``lines`` parallel lines a pixel apart along the edge (the dense difference's smoothing: a camera's noise is several
    times the map's step). False where the profile leaves the image or the floor is behind the camera."""
    h, w = image.shape
    width = out.shape[1]
    radius = width // 2
    ok, lo_u, lo_v = project_floor(r, t, k, dist, ox - radius * dx, oy - radius * dy)
    if not ok:
        return False
    ok, hi_u, hi_v = project_floor(r, t, k, dist, ox + radius * dx, oy + radius * dy)
    if not ok:
        return False
    # the parabola's coefficients in each coordinate: p(λ) = p0 + λ·b + λ²·a
    b_u, a_u = 0.5 * (hi_u - lo_u), 0.5 * (hi_u + lo_u) - mid_u
    b_v, a_v = 0.5 * (hi_v - lo_v), 0.5 * (hi_v + lo_v) - mid_v
    along = math.hypot(b_u, b_v)
    if along <= 0.0:
        return False
    tx, ty = -b_v / along, b_u / along  # a pixel along the edge
    first = -(lines // 2)
    far = max(-first, first + lines - 1) + 1e-6  # |λ| <= 1: no point is further from the middle than ru, rv
    ru, rv = abs(b_u) + abs(a_u) + far * abs(tx) + 1e-6, abs(b_v) + abs(a_v) + far * abs(ty) + 1e-6
    inside = ru <= mid_u < w - 1.0 - ru and rv <= mid_v < h - 1.0 - rv  # (then none needs the check)
    for o in range(width):
        lam = lams[o]
        u = mid_u + lam * (b_u + lam * a_u)
        v = mid_v + lam * (b_v + lam * a_v)
        total = 0.0
        for line in range(lines):
            ul, vl = u + (first + line) * tx, v + (first + line) * ty
            if not (inside or (0.0 <= ul < w - 1.0 and 0.0 <= vl < h - 1.0)):
                return False
            total += bilinear_u8(image, ul, vl)
        out[row, o] = total / lines
    return True


read_profile: Any = read_profile_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def edge_row_py(
    r: F64, t: F64, k: F64, dist: F64, ox: float, oy: float, mx: float, my: float, out: F64, at: int, res: F64, jac: F64
) -> None:
    """The floor point (ox, oy, 0) with floor normal (mx, my) seen at the pose (r, t) through ``k`` and lens
    ``dist``: its image place (u, v), the image length of one metre along the normal, and into ``out`` from ``at`` the
    row of the linear system, d(displacement along the image normal, pixels)/d(δ rotation, Δt), the rotation
    applied on the arena → camera side. (u, v, length) into ``res``, length 0 when the point is behind the
    camera; ``jac`` is scratch (2x2)."""
    res[2] = 0.0
    p0 = r[0, 0] * ox + r[0, 1] * oy
    p1 = r[1, 0] * ox + r[1, 1] * oy
    p2 = r[2, 0] * ox + r[2, 1] * oy
    x0, x1, z = p0 + t[0], p1 + t[1], p2 + t[2]
    if z <= 1e-6:
        return
    xn, yn = x0 / z, x1 / z
    xd, yd = distort(xn, yn, dist, jac)
    res[0] = k[0, 0] * xd + k[0, 1] * yd + k[0, 2]
    res[1] = k[1, 1] * yd + k[1, 2]
    # d(u, v)/d(camera point) = diag(fx, fy) · jac · d(x, y)/d(X, Y, Z)
    a00, a01 = k[0, 0] * jac[0, 0], k[0, 0] * jac[0, 1]
    a10, a11 = k[1, 1] * jac[1, 0], k[1, 1] * jac[1, 1]
    d00, d01, d02 = a00 / z, a01 / z, -(a00 * xn + a01 * yn) / z
    d10, d11, d12 = a10 / z, a11 / z, -(a10 * xn + a11 * yn) / z
    m0 = r[0, 0] * mx + r[0, 1] * my
    m1 = r[1, 0] * mx + r[1, 1] * my
    m2 = r[2, 0] * mx + r[2, 1] * my
    gx = d00 * m0 + d01 * m1 + d02 * m2
    gy = d10 * m0 + d11 * m1 + d12 * m2
    length = math.sqrt(gx * gx + gy * gy)
    if length < 1e-9:
        return
    nx, ny = gx / length, gy / length
    g0 = nx * d00 + ny * d10
    g1 = nx * d01 + ny * d11
    g2 = nx * d02 + ny * d12
    out[at] = p1 * g2 - p2 * g1
    out[at + 1] = p2 * g0 - p0 * g2
    out[at + 2] = p0 * g1 - p1 * g0
    out[at + 3] = g0
    out[at + 4] = g1
    out[at + 5] = g2
    res[2] = length


edge_row: Any = edge_row_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def profiles(
    obj: F64,
    nrm: F64,
    r: F64,
    t: F64,
    r_other: F64,
    t_other: F64,
    k: F64,
    dist: F64,
    image: U8,
    other: U8,
    radius: int,
    border_px: float,
    lines: int,
) -> tuple[I64, F32, F32, F64]:
    """For the edge samples (floor points ``obj``, floor normals ``nrm``) seen in ``image`` at the pose (``r``, ``t``:
    arena → camera) through the camera ``k`` with lens ``dist``: which samples are in view (inside by ``border_px``,
    in front of the camera), and both frames read at the same ``2·radius + 1`` floor points along the normal, spaced
    one pixel of ``image`` apart at the sample (each the mean of ``lines`` readings along the edge,
    :func:`read_profile_py`): ``image`` at the pose (r, t), ``other`` at (``r_other``, ``t_other``). Also, per sample,
    the rows of the linear system of both frames (14: d(displacement along the image normal, in profile steps)/d(δ
    rotation, Δt) of this frame, then of the other, then d(the content's displacement along the profile)/d(its motion
    on the floor, x and y)). A sample whose profile leaves either image is dropped."""
    n = obj.shape[0]
    h, w = image.shape
    width = 2 * radius + 1
    idx = np.empty(n, np.int64)
    pk = np.empty((n, width), np.float32)
    pj = np.empty((n, width), np.float32)
    a_rows = np.empty((n, 14))
    flat_rows = a_rows.reshape(14 * n)  # (indexed, not a view of each row: a view costs numba's reference counts)
    scratch = np.empty((2, 2))
    lams = (np.arange(width) - radius) / radius  # each profile point's place on the parabola, −1..1
    here = np.empty(3)
    there = np.empty(3)
    count = 0
    for i in range(n):
        ox, oy, mx, my = obj[i, 0], obj[i, 1], nrm[i, 0], nrm[i, 1]
        edge_row(r, t, k, dist, ox, oy, mx, my, flat_rows, 14 * count, here, scratch)
        u, v, length = here[0], here[1], here[2]
        if length <= 0.0 or not (border_px < u < w - 1 - border_px and border_px < v < h - 1 - border_px):
            continue
        edge_row(r_other, t_other, k, dist, ox, oy, mx, my, flat_rows, 14 * count + 6, there, scratch)
        if there[2] <= 0.0:
            continue
        step_m = 1.0 / length  # floor metres per pixel of ``image`` along the normal
        scale = 1.0 / (step_m * there[2])  # the other frame's pixels → profile steps
        for c in range(6, 12):
            a_rows[count, c] *= scale
        # The content's own motion on the floor (x, y metres) moves it along the profile by this much.
        a_rows[count, 12] = mx / step_m
        a_rows[count, 13] = my / step_m
        dx, dy = step_m * mx, step_m * my
        if not read_profile(image, r, t, k, dist, ox, oy, dx, dy, u, v, lines, pk, count, lams):
            continue
        u, v = there[0], there[1]
        if not read_profile(other, r_other, t_other, k, dist, ox, oy, dx, dy, u, v, lines, pj, count, lams):
            continue
        idx[count] = i
        count += 1
    return idx[:count], pk[:count], pj[:count], a_rows[:count]


def centred_moments_py(u: F64, y: F64, mean_u: F64, gram: F64, uy: F64, yy: F64, i: int) -> None:
    """Add profile ``i``'s pair equations to its moments, each basis profile and the target ``y[:, 0]`` less its
    mean (the constant's share): the upper triangle of Σ u uᵀ into ``gram[i]``, Σ u y into ``uy[i]``, Σ y² into
    ``yy[i]``; ``mean_u`` is scratch. (Indexed: a view costs numba's reference counts, 3 % of a replay.)"""
    width = y.shape[0]
    mean_y = 0.0
    for o in range(width):
        mean_y += y[o, 0]
    mean_y /= width
    for c in range(5):
        total = 0.0
        for o in range(width):
            total += u[o, c]
        mean_u[c] = total / width
    total = yy[i]  # centred in place, each sum in a register (the same terms in the same order as in memory)
    for o in range(width):
        yc = y[o, 0] - mean_y
        y[o, 0] = yc
        total += yc * yc
        for c in range(5):
            u[o, c] = u[o, c] - mean_u[c]
    yy[i] = total
    for a in range(5):
        total = uy[i, a]
        for o in range(width):
            total += u[o, a] * y[o, 0]
        uy[i, a] = total
        for b in range(a, 5):
            total = gram[i, a, b]
            for o in range(width):
                total += u[o, a] * u[o, b]
            gram[i, a, b] = total


centred_moments: Any = centred_moments_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def moments(
    pk: F32,
    pj: F32,
    sv: F64,
    gain: float,
    step: float,
    cdf: F64,
    pdf: F64,
    noise2: float,
    weights: F64,
    esm_partner: bool,
) -> tuple[F64, F64, F64]:
    """Per profile, the moments of the linearised model that the fit needs: with basis profiles u (5) whose
    unknowns are the gain's change, the step's, this frame's displacement δ, the partner's ε and the
    content's own displacement, and the targets y, their Gram matrix Σ u uᵀ (5x5), Σ u y and Σ y², summed
    over the pair's equations and each frame's own (see the module's notes). ``weights`` (n, 2: this frame,
    the partner) holds the own equations' weights: a negative one is set here from ``noise2``, the others
    kept (a fit whose weights moved with every iteration would never settle)."""
    n, width = pk.shape
    gram = np.zeros((n, 5, 5))
    uy = np.zeros((n, 5))
    yy = np.zeros(n)
    u = np.empty((width, 5))
    y = np.empty((width, 1))
    mean_u = np.empty(5)
    # The straight line's second basis vector (the first is the constant): o − centre, unit length.
    line = np.arange(width) - (width - 1) / 2.0
    line /= math.sqrt(np.sum(line * line))
    for i in range(n):
        for o in range(width):
            lo = o - 1 if o > 0 else 0
            hi = o + 1 if o < width - 1 else width - 1
            inverse = 0.5 if hi - lo == 2 else 1.0  # 1 / (hi − lo): halving is exact, to the bit
            slope = (pj[i, hi] - pj[i, lo]) * inverse
            m = sv[i] * cdf[o]
            u[o, 0] = pj[i, o]
            u[o, 1] = m
            # this frame's slope: the model's and its own, averaged (second order, as ESM: a noisy slope
            # of either alone makes the steps overshoot and swing)
            own = (pk[i, hi] - pk[i, lo]) * inverse
            u[o, 2] = -0.5 * (gain * slope + step * sv[i] * pdf[o] + own)
            # the partner's: its slope and, where it will be, this frame's less the step's (ESM as above), so
            # that both frames moved together see the map's step alone (the content's slopes cancel)
            u[o, 3] = 0.5 * (gain * slope + own - step * sv[i] * pdf[o]) if esm_partner else gain * slope
            u[o, 4] = -(gain * slope + 0.5 * step * sv[i] * pdf[o])  # the content's slope alone
            y[o, 0] = pk[i, o] - gain * pj[i, o] - step * m
        centred_moments(u, y, mean_u, gram, uy, yy, i)
        for frame in range(2):  # each frame alone: this one (δ, +c/2), then the partner (ε, −c/2g)
            profile = pk if frame == 0 else pj
            per_step = 0.5 if frame == 0 else -0.5 / gain
            own_step(
                profile,
                per_step * step,
                per_step,
                2 + frame,
                sv[i],
                cdf,
                pdf,
                line,
                noise2,
                weights,
                frame,
                u,
                y,
                gram,
                uy,
                yy,
                i,
            )
        for a in range(5):
            for b in range(a):
                gram[i, a, b] = gram[i, b, a]
    return gram, uy, yy


def own_step_py(
    profile: F32,
    half: float,
    per_step: float,
    col: int,
    sv: float,
    cdf: F64,
    pdf: F64,
    line: F64,
    noise2: float,
    weights: F64,
    frame: int,
    u: F64,
    y: F64,
    gram: F64,
    uy: F64,
    yy: F64,
    i: int,
) -> None:
    """Add one frame's own equations to profile ``i``'s moments (:func:`moments`): the frame's profile
    (``profile[i]``) less its step (``half``·M, M = ``sv``·``cdf``; ``per_step`` = d half / d c) is a straight line,
    the step's change (basis 1) and the frame's displacement (basis ``col``) explaining the rest; weighted by
    ``weights[i, frame]`` (set here from ``noise2`` if negative). ``u`` (width x 5), ``y`` (width x 1) are scratch."""
    width = profile.shape[1]
    for o in range(width):
        m = sv * cdf[o]
        y[o, 0] = profile[i, o] - half * m
        u[o, 1] = per_step * m
        u[o, col] = -half * sv * pdf[o]
    detrend(y, 0, line)
    detrend(u, 1, line)
    detrend(u, col, line)
    left = 0.0
    for o in range(width):
        left += y[o, 0] * y[o, 0]
    if weights[i, frame] < 0.0:
        weights[i, frame] = min(1.0, noise2 * width / max(left, 1e-9))
    weight = weights[i, frame]
    yy_i, uy_1, uy_c, g_11, g_1c, g_cc = yy[i], uy[i, 1], uy[i, col], gram[i, 1, 1], gram[i, 1, col], gram[i, col, col]
    for o in range(width):
        yy_i += weight * y[o, 0] * y[o, 0]
        uy_1 += weight * u[o, 1] * y[o, 0]
        uy_c += weight * u[o, col] * y[o, 0]
        g_11 += weight * u[o, 1] * u[o, 1]
        g_1c += weight * u[o, 1] * u[o, col]
        g_cc += weight * u[o, col] * u[o, col]
    yy[i], uy[i, 1], uy[i, col], gram[i, 1, 1], gram[i, 1, col], gram[i, col, col] = yy_i, uy_1, uy_c, g_11, g_1c, g_cc


own_step: Any = own_step_py  # compiled by kernels._compile_sparse into :func:`moments` (as a call, a third of its time)


def detrend_py(v: F64, col: int, line: F64) -> None:
    """Column ``col`` of ``v`` less its mean and its component along the unit vector ``line`` (which sums to zero)."""
    width = v.shape[0]
    mean = 0.0
    along = 0.0
    for o in range(width):
        mean += v[o, col]
        along += v[o, col] * line[o]
    mean /= width
    for o in range(width):
        v[o, col] -= mean + along * line[o]


detrend: Any = detrend_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def normal_py(
    gram: F64, uy: F64, a_rows: F64, keep: npt.NDArray[np.bool_], fit_gain: bool, fit_flow: bool
) -> tuple[F64, F64, F64, F64]:
    """The normal equations (16x16, and the right-hand side) of the kept profiles from their moments: the
    unknowns are the gain's change, the step's, this frame's pose change (6, through its rows ``a_rows[:, :6]``),
    the partner's (6, ``a_rows[:, 6:12]``) and the content's motion on the floor (2, ``a_rows[:, 12:]``). Also
    Σ aaᵀ of the partner's rows and of the content's (their priors' shapes). The gain's change (unless
    ``fit_gain``) and the content's motion (unless ``fit_flow``) are left as zeros (:func:`solve_step` holds them)."""
    n = gram.shape[0]
    first = 0 if fit_gain else 1
    last = 16 if fit_flow else 14
    big = np.zeros((16, 16))
    rhs = np.zeros(16)
    held = np.zeros((6, 6))
    flow = np.zeros((2, 2))
    col = np.array([0, 1, 2, 2, 2, 2, 2, 2, 3, 3, 3, 3, 3, 3, 4, 4])  # each unknown's basis profile
    v = np.ones(16)  # and its factor there
    for i in range(n):
        if not keep[i]:
            continue
        for p in range(6):
            v[2 + p] = a_rows[i, p]
            v[8 + p] = a_rows[i, 6 + p]
        v[14] = a_rows[i, 12]
        v[15] = a_rows[i, 13]
        for p in range(first, last):
            rhs[p] += v[p] * uy[i, col[p]]
            for q in range(p, last):
                big[p, q] += v[p] * v[q] * gram[i, col[p], col[q]]
        for p in range(6):
            for q in range(p, 6):
                held[p, q] += a_rows[i, 6 + p] * a_rows[i, 6 + q]
        if fit_flow:
            for p in range(2):
                for q in range(2):
                    flow[p, q] += a_rows[i, 12 + p] * a_rows[i, 12 + q]
    for p in range(16):
        for q in range(p):
            big[p, q] = big[q, p]
    for p in range(6):
        for q in range(p):
            held[p, q] = held[q, p]
    return big, rhs, held, flow


normal: Any = normal_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def residuals_py(gram: F64, uy: F64, yy: F64, a_rows: F64, sol: F64) -> F64:
    """Each profile's sum of squared residuals after the change ``sol`` of the 16 unknowns (from its moments:
    Σ(y − u·c)² = Σy² − 2c·Σuy + cᵀ(Σuuᵀ)c, c the profile's coefficients of its four basis profiles)."""
    n = gram.shape[0]
    out = np.empty(n)
    coef = np.empty(5)
    for i in range(n):
        coef[0] = sol[0]
        coef[1] = sol[1]
        coef[2] = 0.0
        coef[3] = 0.0
        coef[4] = a_rows[i, 12] * sol[14] + a_rows[i, 13] * sol[15]
        for p in range(6):
            coef[2] += a_rows[i, p] * sol[2 + p]
            coef[3] += a_rows[i, 6 + p] * sol[8 + p]
        total = yy[i]
        for a in range(5):
            total -= 2.0 * coef[a] * uy[i, a]
            for b in range(5):
                total += coef[a] * gram[i, a, b] * coef[b]
        out[i] = max(total, 0.0)
    return out


residuals: Any = residuals_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def cholesky_solve_py(a: F64, b: F64) -> tuple[F64, bool]:
    """``a``⁻¹·``b`` for a symmetric positive definite ``a`` (small), by Cholesky; False if ``a`` is not."""
    n = a.shape[0]
    low = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            total = a[i, j]
            for p in range(j):
                total -= low[i, p] * low[j, p]
            if i == j:
                if total <= 0.0:
                    return np.zeros(n), False
                low[i, i] = math.sqrt(total)
            else:
                low[i, j] = total / low[j, j]
    y = np.empty(n)
    for i in range(n):
        total = b[i]
        for p in range(i):
            total -= low[i, p] * y[p]
        y[i] = total / low[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        total = y[i]
        for p in range(i + 1, n):
            total -= low[p, i] * x[p]
        x[i] = total / low[i, i]
    return x, True


cholesky_solve: Any = cholesky_solve_py  # compiled by ``ipt.receiver.core.kernels._compile_sparse``


def solve_step(
    gram: F64,
    uy: F64,
    yy: F64,
    a_rows: F64,
    keep: npt.NDArray[np.bool_],
    other_moved: F64,
    other_sigma_px: float,
    flow_sigma_px: float,
    fit_gain: bool,
    width: int,
) -> tuple[F64, F64, F64, bool]:
    """One Gauss-Newton step of the 16 unknowns from the kept profiles' moments: the normal equations
    (:func:`normal`), the partner's pose held near its own by a prior (``other_moved`` its change so far, σ
    ``other_sigma_px`` at each sample), the content's motion near none (σ ``flow_sigma_px``; 0: held at none),
    the gain's change held at zero unless ``fit_gain``; solved. Returns
    the change, each profile's sum of squared residuals after it, the normal matrix, and False if singular."""
    big, rhs, held, flow = normal(gram, uy, a_rows, keep, fit_gain, flow_sigma_px > 0.0)
    count = 0
    total = 0.0
    for i in range(len(keep)):
        if keep[i]:
            count += 1
            total += yy[i]
    sigma2 = max(total / max(count * width, 1), 1.0)
    scale = sigma2 / (other_sigma_px * other_sigma_px)
    for p in range(2):
        for q in range(2):
            if flow_sigma_px > 0.0:
                big[14 + p, 14 + q] += sigma2 / (flow_sigma_px * flow_sigma_px) * flow[p, q]
    for p in range(6):
        pulled = 0.0
        for q in range(6):
            big[8 + p, 8 + q] += scale * held[p, q]
            pulled += scale * held[p, q] * other_moved[q]
        rhs[8 + p] -= pulled
    for u in (0, 14, 15):  # held at zero: the gain's change unless fitted, the content's motion unless fitted
        if (u == 0 and fit_gain) or (u > 0 and flow_sigma_px > 0.0):
            continue
        for p in range(16):
            big[u, p] = 0.0
            big[p, u] = 0.0
        big[u, u] = 1.0
        rhs[u] = 0.0
    sol, ok = cholesky_solve(big, rhs)
    if not ok:
        return sol, np.full(len(keep), np.inf), big, False
    return sol, residuals(gram, uy, yy, a_rows, sol), big, True
