"""The receiver's inner loops, compiled (numba): the map tracker's, the alignment's and the pair difference's.

- **The tracker** (:mod:`ipt.receiver.core.track`): one Gauss-Newton step projects a few hundred edge samples,
  reads the difference image along each sample's normal and finds the step's sub-pixel offset. Written as
  numpy array operations, that is some sixty small array calls per step (~1 ms at 640×360, most of it call
  overhead); here it is two loops over the samples (~0.1 ms). The difference's noise level
  (:func:`ipt.receiver.core.track.slope_noise`) gathers its sampled slopes here too.
- **The alignment** (:func:`ipt.receiver.core.imagealign.refine_homography`): a Lucas-Kanade step's readings at
  the samples (the earlier frame and its gradients, for the second-order step), residuals and rows of the
  linear system in one pass (:func:`align_system`; it costs what the first-order step did with remap and
  numpy, 1.2–2.2 ms a pair).
- **The pair difference** (:func:`ipt.receiver.core.demodulator.pair_difference`): the brightness match's samples
  and the difference, its valid pixels and its changed ones in one pass over the image each
  (:func:`sample_pair`, :func:`difference_pass`) instead of numpy's eight.

Pure: arrays in, arrays out. Where numba cannot compile (no executable memory), the tracker's kernels run as
plain Python (correct, only slower) and the others as the numpy operations they replace (a pass over every
pixel in plain Python would take seconds).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]

COMPILED = True
"""Whether the kernels below are compiled (False: numba is unavailable and they run as Python, or as numpy
where they have a fallback); known once :func:`ensure` has run."""

NOT_COMPILED_BECAUSE: str | None = None
"""Why the kernels are not compiled (numba's import error), or None."""
NOT_CACHED_BECAUSE: str | None = None
"""Why numba keeps no disk cache of the kernels (no writable cache folder: set ``NUMBA_CACHE_DIR``), or None."""

_lock = threading.Lock()
_ready = threading.Event()
_dispatchers: list[Any] = []
"""numba's dispatcher of every compiled kernel, the helpers included (for :func:`status`)."""


class _Kernel:
    """A kernel, compiled on first use (or by :func:`ensure`, e.g. in :func:`warm_in_background`), so that
    importing this module does not import numba (a quarter of a second) on a daemon's start-up path."""

    def __init__(self, fn: Callable[..., Any], fallback: Callable[..., Any] | None = None) -> None:
        self.py_func = fn
        self.fallback = fallback
        """What runs where numba cannot compile, if not ``fn`` itself: the same result with numpy."""
        self.compiled: Any = None

    def __call__(self, *args: Any) -> Any:
        if self.compiled is None:
            ensure()
        return self.compiled(*args)


def _jit(fn: Callable[..., Any]) -> Any:
    """``fn`` compiled by numba (cached on disk where possible), else ``fn`` itself."""
    global COMPILED, NOT_COMPILED_BECAUSE, NOT_CACHED_BECAUSE
    try:
        import numba
    except (ImportError, OSError) as exc:  # OSError: llvmlite refused executable memory
        COMPILED = False
        NOT_COMPILED_BECAUSE = f"{type(exc).__name__}: {exc}"
        return fn
    try:
        compiled = numba.njit(nogil=True, cache=True)(fn)
    except RuntimeError as exc:  # no writable cache location: compile in every process
        NOT_CACHED_BECAUSE = str(exc)
        compiled = numba.njit(nogil=True)(fn)
    _dispatchers.append(compiled)
    return compiled


def ensure() -> None:
    """Compile the kernels (or load them from numba's disk cache), once per process."""
    global bilinear, slopes, system_row
    with _lock:
        if _ready.is_set():
            return
        # The kernels call bilinear, slopes (which calls bilinear) and system_row: each must be compiled
        # before its callers, and be this module's global when they are.
        bilinear = _jit(_bilinear)
        slopes = _jit(_slopes)
        system_row = _jit(_system_row)
        for kernel in (
            measure,
            peaks,
            band_signs,
            cell_agreement,
            slopes_sampled,
            align_system,
            sample_pair,
            difference_pass,
        ):
            kernel.compiled = _jit(kernel.py_func)
            if not COMPILED and kernel.fallback is not None:
                kernel.compiled = kernel.fallback
        _ready.set()


def _bilinear(image: F32, x: float, y: float) -> float:
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


bilinear: Any = _bilinear  # compiled by ensure()


def _slopes(image: F32, u: float, v: float, nx: float, ny: float, radius: int, sign: float, out: F32) -> None:
    """The ``2·radius`` slopes of ``image`` along the unit normal (nx, ny) through (u, v), between the
    ``2·radius + 1`` profile samples at offsets −radius..radius, times ``sign``, into ``out``."""
    before = bilinear(image, u - radius * nx, v - radius * ny)
    for o in range(1, 2 * radius + 1):
        now = bilinear(image, u + (o - radius) * nx, v + (o - radius) * ny)
        out[o - 1] = (now - before) * sign
        before = now


slopes: Any = _slopes  # compiled by ensure()


def _system_row(g0: float, g1: float, g2: float, p0: float, p1: float, p2: float, out: F64) -> None:
    """One row of the track's linear system into ``out``: the image normal times d(u, v)/d(camera point)
    is g = (g0, g1, g2); times d(camera point)/d(δ rotation, Δt) that is (RP × g)ᵀ for the rotation
    (nᵀ·(−[RP]×)), with RP = (p0, p1, p2), and g for the translation."""
    out[0] = p1 * g2 - p2 * g1
    out[1] = p2 * g0 - p0 * g2
    out[2] = p0 * g1 - p1 * g0
    out[3] = g0
    out[4] = g1
    out[5] = g2


system_row: Any = _system_row  # compiled by ensure()


def _measure(
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


measure = _Kernel(_measure)


def _peaks(raw: F32, band: I64, band_sign: F64, threshold: F64) -> tuple[F64, npt.NDArray[np.bool_]]:
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


peaks = _Kernel(_peaks)


def _band_signs(raw: F32, band: I64, bands: int) -> F64:
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


band_signs = _Kernel(_band_signs)


def _cell_agreement(
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
) -> float:
    """Of the data cells of the tags marked in ``tag_on`` whose centres (``cells_m``) fall inside the image
    on a valid pixel (``valid`` empty: all are), the fraction whose difference has the sign the map gives
    them (``cell_value``, ±1, under the band's sign), counting only clear cells (more than 0.3 × the median
    magnitude); 0 when fewer than 20 cells can say."""
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
    if count < 20:
        return 0.0
    magnitude = np.abs(values[:count])
    limit = 0.3 * np.median(magnitude)
    clear = 0
    agree = 0
    for i in range(count):
        if magnitude[i] > limit:
            clear += 1
            if (values[i] > 0) == (expected[i] > 0):
                agree += 1
    return agree / clear if clear >= 20 else 0.0


cell_agreement = _Kernel(_cell_agreement)


def _slopes_sampled(diff: F32, valid: U8) -> F32:
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


slopes_sampled = _Kernel(_slopes_sampled)


def _align_system(
    moving: F32,
    moving_gx: F32,
    moving_gy: F32,
    lit: U8,
    back: F64,
    cols: I64,
    rows: I64,
    values: F32,
    target_ix: F32,
    target_iy: F32,
    scale: float,
    offset_y: float,
    robust_k: float,
    sd: F64,
    residual: F64,
) -> tuple[int, int]:
    """One Lucas-Kanade step of :func:`ipt.receiver.core.imagealign.refine_homography`: ``moving`` and its
    gradients (``moving_gx``, ``moving_gy``) read bilinearly at the target's sample pixels (``cols``,
    ``rows``) carried by ``back`` (3x3, target pixel → moving pixel). A sample counts where it lands inside,
    reads more than 0 and, when ``lit`` is not empty, on a pixel of ``lit`` (nearest) that is not 0. Its
    residual is the reading minus the target's ``values``; those within ``robust_k`` times 1.25 times the
    mean absolute residual of the counted samples are kept: their rows of the linear system into the first
    rows of ``sd`` (N x 8) and their residuals into ``residual`` (N), in float64 (the normal equations are
    then one matrix product). The row is the efficient second-order (ESM) one: the mean of the target's
    gradient (``target_ix``, ``target_iy``, per normalised unit) and the moving frame's, carried into the
    target's pixels by ``back``'s local Jacobian, times the homography's derivatives at the sample's
    normalised coordinates (``col · scale − 1``, ``row · scale − offset_y``). Returns how many
    samples counted and how many were kept."""
    h, w = moving.shape
    use_lit = lit.shape[0] == h and lit.shape[1] == w
    n = cols.shape[0]
    e = np.empty(n, np.float64)
    gxs = np.empty(n, np.float64)
    gys = np.empty(n, np.float64)
    ok = np.zeros(n, np.bool_)
    counted = 0
    total = 0.0
    for i in range(n):
        c, r = cols[i], rows[i]
        z = back[2, 0] * c + back[2, 1] * r + back[2, 2]
        x = (back[0, 0] * c + back[0, 1] * r + back[0, 2]) / z
        y = (back[1, 0] * c + back[1, 1] * r + back[1, 2]) / z
        if not (0.0 <= x <= w - 1.0 and 0.0 <= y <= h - 1.0):
            continue
        if use_lit and lit[min(int(y + 0.5), h - 1), min(int(x + 0.5), w - 1)] == 0:
            continue
        x0 = min(int(x), w - 2)
        y0 = min(int(y), h - 2)
        fx = x - x0
        fy = y - y0
        w00, w01, w10, w11 = (1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy
        value = (
            w00 * moving[y0, x0] + w01 * moving[y0, x0 + 1] + w10 * moving[y0 + 1, x0] + w11 * moving[y0 + 1, x0 + 1]
        )
        if value <= 0.0:
            continue
        mgx = (
            w00 * moving_gx[y0, x0]
            + w01 * moving_gx[y0, x0 + 1]
            + w10 * moving_gx[y0 + 1, x0]
            + w11 * moving_gx[y0 + 1, x0 + 1]
        )
        mgy = (
            w00 * moving_gy[y0, x0]
            + w01 * moving_gy[y0, x0 + 1]
            + w10 * moving_gy[y0 + 1, x0]
            + w11 * moving_gy[y0 + 1, x0 + 1]
        )
        # d(source)/d(target pixel), then the carried gradient per target pixel, per normalised unit
        dxc, dxr = (back[0, 0] - x * back[2, 0]) / z, (back[0, 1] - x * back[2, 1]) / z
        dyc, dyr = (back[1, 0] - y * back[2, 0]) / z, (back[1, 1] - y * back[2, 1]) / z
        gxs[i] = 0.5 * (target_ix[i] + (mgx * dxc + mgy * dyc) / scale)
        gys[i] = 0.5 * (target_iy[i] + (mgx * dxr + mgy * dyr) / scale)
        e[i] = value - values[i]
        ok[i] = True
        total += abs(e[i])
        counted += 1
    if counted == 0:
        return 0, 0
    cut = robust_k * (1.25 * total / counted + 1e-6)
    kept = 0
    for i in range(n):
        if not ok[i] or abs(e[i]) >= cut:
            continue
        xn, yn = cols[i] * scale - 1.0, rows[i] * scale - offset_y
        ix, iy = gxs[i], gys[i]
        q = -(ix * xn + iy * yn)
        row = sd[kept]
        row[0], row[1], row[2], row[3] = ix * xn, ix * yn, ix, iy * xn
        row[4], row[5], row[6], row[7] = iy * yn, iy, q * xn, q * yn
        residual[kept] = e[i]
        kept += 1
    return counted, kept


def _align_system_numpy(
    moving: F32,
    moving_gx: F32,
    moving_gy: F32,
    lit: U8,
    back: F64,
    cols: I64,
    rows: I64,
    values: F32,
    target_ix: F32,
    target_iy: F32,
    scale: float,
    offset_y: float,
    robust_k: float,
    sd: F64,
    residual: F64,
) -> tuple[int, int]:
    """:func:`_align_system` with OpenCV's remap and numpy (where numba cannot compile)."""
    import cv2

    h, w = moving.shape
    src = back @ np.stack([cols, rows, np.ones(len(cols))]).astype(np.float64)
    x, y, z = src[0] / src[2], src[1] / src[2], src[2]
    map_x, map_y = x.astype(np.float32).reshape(-1, 1), y.astype(np.float32).reshape(-1, 1)
    read = [
        np.asarray(cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT), np.float64).ravel()
        for img in (moving, moving_gx, moving_gy)
    ]
    counted = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1) & (read[0] > 0)
    if lit.shape == moving.shape:
        counted &= cv2.remap(lit, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT).ravel() > 0
    e = read[0] - values
    n = int(counted.sum())
    if n == 0:
        return 0, 0
    keep = counted & (np.abs(e) < robust_k * (1.25 * float(np.abs(e[counted]).mean()) + 1e-6))
    dxc, dxr = (back[0, 0] - x * back[2, 0]) / z, (back[0, 1] - x * back[2, 1]) / z
    dyc, dyr = (back[1, 0] - y * back[2, 0]) / z, (back[1, 1] - y * back[2, 1]) / z
    ix = 0.5 * (target_ix + (read[1] * dxc + read[2] * dyc) / scale)
    iy = 0.5 * (target_iy + (read[1] * dxr + read[2] * dyr) / scale)
    xn, yn = cols * scale - 1.0, rows * scale - offset_y
    q = -(ix * xn + iy * yn)
    rows_kept = np.stack([ix * xn, ix * yn, ix, iy * xn, iy * yn, iy, q * xn, q * yn], axis=1)[keep]
    kept = len(rows_kept)
    sd[:kept] = rows_kept
    residual[:kept] = e[keep]
    return n, kept


align_system = _Kernel(_align_system, _align_system_numpy)


def _sample_pair(moved: U8, later: U8, moved_signal: U8, later_signal: U8, step: int) -> tuple[F32, F32]:
    """The two frames of a pair (``moved``: the earlier one carried onto the later one) on every ``step``-th
    row and column where both have signal: (earlier values, later values), as float32."""
    h, w = later.shape
    rows, cols = (h + step - 1) // step, (w + step - 1) // step
    xs = np.empty(rows * cols, np.float32)
    ys = np.empty(rows * cols, np.float32)
    count = 0
    for y in range(0, h, step):
        for x in range(0, w, step):
            if later_signal[y, x] > 0 and moved_signal[y, x] > 0:
                xs[count] = moved[y, x]
                ys[count] = later[y, x]
                count += 1
    return xs[:count], ys[:count]


def _sample_pair_numpy(moved: U8, later: U8, moved_signal: U8, later_signal: U8, step: int) -> tuple[F32, F32]:
    """:func:`_sample_pair` with numpy (where numba cannot compile)."""
    both = (later_signal[::step, ::step] > 0) & (moved_signal[::step, ::step] > 0)
    return moved[::step, ::step][both].astype(np.float32), later[::step, ::step][both].astype(np.float32)


sample_pair = _Kernel(_sample_pair, _sample_pair_numpy)


def _difference_pass(
    moved: U8,
    later: U8,
    moved_seen: U8,
    coverage: U8,
    gain: float,
    offset: float,
    limit: float,
    diff: F32,
    seen: U8,
    changed: U8,
) -> None:
    """The pair's raw difference, ``later − (gain · moved + offset)`` (``moved``: the earlier frame carried
    onto the later one), into ``diff``; into ``seen`` the lesser of ``coverage`` and ``moved_seen`` (where the
    later and the carried earlier frame see the floor); 1 into ``changed`` where the difference exceeds
    ``limit`` (else 0). One pass instead of numpy's eight over the whole image."""
    h, w = later.shape
    g, o = np.float32(gain), np.float32(offset)
    for y in range(h):
        for x in range(w):
            d = np.float32(later[y, x]) - (g * np.float32(moved[y, x]) + o)
            diff[y, x] = d
            seen[y, x] = min(coverage[y, x], moved_seen[y, x])
            changed[y, x] = 1 if abs(d) > limit else 0


def _difference_pass_numpy(
    moved: U8,
    later: U8,
    moved_seen: U8,
    coverage: U8,
    gain: float,
    offset: float,
    limit: float,
    diff: F32,
    seen: U8,
    changed: U8,
) -> None:
    """:func:`_difference_pass` with numpy (where numba cannot compile)."""
    np.subtract(later.astype(np.float32), np.float32(gain) * moved.astype(np.float32) + np.float32(offset), out=diff)
    np.minimum(coverage, moved_seen, out=seen)
    np.greater(np.abs(diff), limit, out=changed.view(np.bool_))


difference_pass = _Kernel(_difference_pass, _difference_pass_numpy)


def warm() -> None:
    """Compile the kernels now (or load them from numba's disk cache: a fraction of a second), so that the
    first frame a camera delivers does not wait seconds for the compiler."""
    image = np.zeros((8, 8), np.float32)
    one = np.zeros((1, 3))
    rt = np.eye(3)
    t = np.array([0.0, 0.0, 1.0])
    k = np.eye(3)
    no_mask = np.zeros((0, 0), np.uint8)
    measure(one, one, np.ones(1), rt, t, k, image, no_mask, 2, 1.0, 2, np.zeros(6))
    peaks(np.zeros((1, 4), np.float32), np.zeros(1, np.int64), np.ones(2), np.ones(1))
    band_signs(np.zeros((1, 4), np.float32), np.zeros(1, np.int64), 2)
    cell_agreement(image, k, rt, t, one, np.zeros(1, np.int64), np.ones(1), np.ones(1, np.bool_), np.ones(2), no_mask)
    slopes_sampled(image, no_mask)
    slopes_sampled(image, np.zeros((8, 8), np.uint8))
    ints = np.zeros(1, np.int64)
    u8 = np.zeros((8, 8), np.uint8)
    sample_pair(u8, u8, u8, u8, 4)
    difference_pass(u8, u8, u8, u8, 1.0, 0.0, 1.0, image, u8.copy(), u8.copy())
    f32 = np.zeros(1, np.float32)
    align_system(
        image, image, image, no_mask, rt, ints, ints, f32, f32, f32, 0.1, 0.5, 3.0, np.zeros((1, 8)), np.zeros(1)
    )


_warming = False


def warm_in_background() -> None:
    """Start :func:`warm` on a thread of its own (once per process): a daemon's start-up (sockets, the
    camera, the AprilTag helper) goes on meanwhile, and the first pair or track waits for it only if it is
    not done."""
    global _warming
    with _lock:
        if _warming or _ready.is_set():
            return
        _warming = True
    threading.Thread(target=warm, name="ipt-kernels", daemon=True).start()
