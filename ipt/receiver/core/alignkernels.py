"""The alignment's inner loop (:func:`ipt.receiver.core.imagealign.refine_homography`), as plain Python that
:mod:`ipt.receiver.core.kernels` compiles (numba), and the same with numpy where numba cannot compile: a
Lucas-Kanade step's readings at the samples (the earlier frame and its gradients, for the second-order step),
residuals and rows of the linear system in one pass (:func:`align_system`).

Which samples. A sample counts where it lands inside the moving frame, reads more than 0 and, when ``lit``
is not empty, on a pixel of ``lit`` (nearest) that is not 0. Its residual is the reading minus the target's
``values``; those within ``robust_k`` times 1.25 times the mean absolute residual of the counted samples are
kept (the normal equations are then one matrix product). The row is the efficient second-order (ESM) one:
the mean of the target's gradient (``target_ix``, ``target_iy``, per normalised unit) and the moving frame's,
carried into the target's pixels by ``back``'s local Jacobian, times the homography's derivatives at the
sample's normalised coordinates (``col · scale − 1``, ``row · scale − offset_y``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]


def align_system(
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
    ``rows``) carried by ``back`` (3x3, target pixel → moving pixel); the samples that count and are kept
    (see the module's note) give their rows of the system into the first rows of ``sd`` (N x 8) and their
    residuals into ``residual`` (N), in float64. Returns how many samples counted and how many were kept."""
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
        value = w00 * moving[y0, x0] + w01 * moving[y0, x0 + 1] + w10 * moving[y0 + 1, x0]
        value = value + w11 * moving[y0 + 1, x0 + 1]
        if value <= 0.0:
            continue
        mgx = w00 * moving_gx[y0, x0] + w01 * moving_gx[y0, x0 + 1] + w10 * moving_gx[y0 + 1, x0]
        mgx = mgx + w11 * moving_gx[y0 + 1, x0 + 1]
        mgy = w00 * moving_gy[y0, x0] + w01 * moving_gy[y0, x0 + 1] + w10 * moving_gy[y0 + 1, x0]
        mgy = mgy + w11 * moving_gy[y0 + 1, x0 + 1]
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


def align_system_numpy(
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
    """:func:`align_system` with OpenCV's remap and numpy (where numba cannot compile)."""
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
