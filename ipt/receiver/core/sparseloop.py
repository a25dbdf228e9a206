"""The sparse fit's Gauss-Newton iterations in one compiled call (:func:`iterate`), for the fits that read every
sample (the chain's fits: its known-partner fits, most of a flight's frames, and its joint fits, whose first steps
reach further over smoothed profiles).

:func:`ipt.receiver.core.sparse.fit_sparse` runs its iterations as a Python loop around three compiled kernels
(the profiles, their moments, the solve), with some twenty numpy calls a step besides them (the gain's and the
noise's medians, the coarse steps' smoothing, the outlier marks, the samples' moves, the damping, the pose's
update). :func:`iterate` is that loop, step for step, as plain Python that :mod:`ipt.receiver.core.kernels` compiles
with the three kernels called from inside it; the setup (which samples) and the checks after (``sparse._finish``)
stay with ``fit_sparse``, and so does a fit that smooths every step or reads half its samples (no chain's fit does).
On fits captured from replays (one core, thread time): shadow-vibration's 272 (known-partner), 2.41 -> 2.06 ms a
fit; fast's 277 (joint and known), 3.59 -> 3.24 ms. The same arithmetic, not the same bits (numpy's means and matrix
products sum in another order, OpenCV's rotation vectors and blur take other formulas): those fits' poses within
8e-8 m and 1.2e-7 rad of the Python loop's, the same outcomes and iterations (``tests/test_sparseloop.py``).

The helpers (:data:`HELPERS`) and :data:`profiles`, :data:`moments`, :data:`solve_step` are the module's globals that
``kernels._compile_sparse`` replaces by their compiled versions before it compiles :func:`iterate`. Where numba
cannot compile, ``fit_sparse`` keeps its own loop (this one, as Python, would read every pixel in the interpreter).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from ipt.receiver.core import sparsekernels

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]

DONE, FEW_IN_VIEW, FEW_KEPT, GAVE_UP = 0, 1, 2, 3
""":func:`iterate`'s outcome: ran to convergence or its last iteration, or why it stopped early."""
WHY = {FEW_IN_VIEW: "few_in_view", FEW_KEPT: "few_kept", GAVE_UP: "gave_up"}

profiles = sparsekernels.profiles
moments = sparsekernels.moments
solve_step = sparsekernels.solve_step


def median_of_py(values: npt.NDArray[np.floating]) -> float:
    """The median of a non-empty 1-D array (the middle one, or the mean of the middle two)."""
    n = len(values)
    half = n // 2
    part = np.partition(values, half)
    if n % 2:
        return float(part[half])
    return 0.5 * (float(np.max(part[:half])) + float(part[half]))


def rotate_by_py(v0: float, v1: float, v2: float, r: F64) -> None:
    """``r`` (3x3) turned by the rotation vector (v0, v1, v2), in place: R(v) @ r (Rodrigues' formula)."""
    theta = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    rot = np.eye(3)
    if theta > 1e-300:
        c, s = math.cos(theta), math.sin(theta)
        kx, ky, kz = v0 / theta, v1 / theta, v2 / theta
        c1 = 1.0 - c
        rot[0, 0], rot[0, 1], rot[0, 2] = c + c1 * kx * kx, c1 * kx * ky - s * kz, c1 * kx * kz + s * ky
        rot[1, 0], rot[1, 1], rot[1, 2] = c1 * ky * kx + s * kz, c + c1 * ky * ky, c1 * ky * kz - s * kx
        rot[2, 0], rot[2, 1], rot[2, 2] = c1 * kz * kx - s * ky, c1 * kz * ky + s * kx, c + c1 * kz * kz
    out = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = rot[i, 0] * r[0, j] + rot[i, 1] * r[1, j] + rot[i, 2] * r[2, j]
    r[:, :] = out


def profile_means_py(pk: F32, pj: F32) -> tuple[F32, F32]:
    """Each profile's mean in this frame and in the partner (float32, summed in order)."""
    m, w = pk.shape
    mk, mj = np.empty(m, np.float32), np.empty(m, np.float32)
    for i in range(m):
        sk = np.float32(0.0)
        sj = np.float32(0.0)
        for j in range(w):
            sk += pk[i, j]
            sj += pj[i, j]
        mk[i], mj[i] = sk / np.float32(w), sj / np.float32(w)
    return mk, mj


def pair_gain_py(pk: F32, pj: F32) -> float:
    """The pair's brightness ratio: the median over the profiles of their means' ratio (the partner's at least 1)."""
    mk, mj = profile_means(pk, pj)
    return median_of(mk / np.maximum(mj, np.float32(1.0)))


def pixel_noise_py(pk: F32) -> float:
    """A frame's pixel noise (variance) from its profiles' second differences (white noise: 6σ²), robustly."""
    m, w = pk.shape
    curvature = np.empty(m * (w - 2), np.float32)
    for i in range(m):
        for j in range(w - 2):
            curvature[i * (w - 2) + j] = abs(pk[i, j + 2] - np.float32(2.0) * pk[i, j + 1] + pk[i, j])
    return max((1.4826 * median_of(curvature)) ** 2 / 6.0, 0.01)


def smoothed_py(profiles: F32, sigma_px: float) -> F32:
    """Each profile blurred along itself by a Gaussian of ``sigma_px`` (its ends repeated), as ``sparse._smooth``
    (OpenCV's ``GaussianBlur``: 2·⌈2.5σ⌉ + 1 taps, the kernel in float32); ``profiles`` itself where σ is 0."""
    if sigma_px <= 0.0:
        return profiles
    half = math.ceil(2.5 * sigma_px)
    taps = np.empty(2 * half + 1)
    for j in range(2 * half + 1):
        o = (j - half) / sigma_px
        taps[j] = math.exp(-0.5 * o * o)
    taps32 = (taps / taps.sum()).astype(np.float32)
    m, w = profiles.shape
    out = np.empty((m, w), np.float32)
    for i in range(m):
        for c in range(w):
            acc = np.float32(0.0)
            for j in range(2 * half + 1):
                at = min(max(c + j - half, 0), w - 1)
                acc += taps32[j] * profiles[i, at]
            out[i, c] = acc
    return out


def lit_py(pk: F32, pj: F32, levels: F64) -> npt.NDArray[np.bool_]:
    """Per profile: lit in both frames, its mean above the frame's dark level (``levels``: this frame's, the
    partner's; :func:`~ipt.receiver.core.sparse.dark_levels`). A sample in the drone's shadow or beyond the
    projection carries no step: fitted, it pulls the step down and the pose towards the shadow's edge."""
    mk, mj = profile_means(pk, pj)
    shown: npt.NDArray[np.bool_] = (mk > levels[0]) & (mj > levels[1])
    return shown


def unlit_out_py(
    dark: F64, order: I64, obj: F64, nrm: F64, steps: F64, idx: I64, pk: F32, pj: F32, a_rows: F64
) -> tuple[I64, F64, F64, F64, I64, F32, F32, F64]:
    """The given samples (``order``: their places among the chosen; ``obj``, ``nrm``, ``steps``) and the read ones
    (``idx`` into the given, their profiles and rows) without those whose profiles are not lit (:func:`lit_py`;
    ``dark`` 0, 0: all are kept)."""
    if dark[0] <= 0.0 and dark[1] <= 0.0:
        return order, obj, nrm, steps, idx, pk, pj, a_rows
    shown = lit(pk, pj, dark)
    stays = np.ones(len(obj), np.bool_)
    stays[idx[~shown]] = False
    place = np.cumsum(stays) - 1  # each staying sample's new index
    return order[stays], obj[stays], nrm[stays], steps[stays], place[idx[shown]], pk[shown], pj[shown], a_rows[shown]


def pushed_py(a_rows: F64, sol: F64, keep: npt.NDArray[np.bool_]) -> tuple[F64, float, float]:
    """Each read sample's displacement by the step ``sol`` (pixels), the kept ones' largest and their RMS."""
    m = len(keep)
    push = np.empty(m)
    moved = 0.0
    sum2 = 0.0
    n_kept = 0
    for i in range(m):
        p = 0.0
        for q in range(6):
            p += a_rows[i, q] * sol[2 + q]
        push[i] = p
        if keep[i]:
            moved = max(moved, abs(p))
            sum2 += p * p
            n_kept += 1
    return push, moved, math.sqrt(sum2 / max(n_kept, 1))


def damped_py(sol: F64, push: F64, last_push: F64, idx: I64, keep: npt.NDArray[np.bool_], scale: bool) -> F64:
    """:func:`ipt.receiver.core.sparse.damped`: the step scaled by 1 / (1 + q) if it takes back the share q > 0 of
    the last (only if ``scale``); ``last_push`` (per chosen sample) updated either way."""
    m = len(idx)
    before = np.empty(m)
    for i in range(m):
        before[i] = last_push[idx[i]]
    last_push[:] = np.nan
    pb = 0.0
    bb = 0.0
    both = False
    for i in range(m):
        last_push[idx[i]] = push[i]
        if keep[i] and np.isfinite(before[i]):
            both = True
            pb += push[i] * before[i]
            bb += before[i] * before[i]
    if not (scale and both):
        return sol
    back = -pb / max(bb, 1e-12)
    return sol / (1.0 + min(back, 1.0)) if back > 0.0 else sol


def stepped_py(sol: F64, r: F64, t: F64, r_other: F64, t_other: F64, other_moved: F64, gain_step: F64) -> None:
    """The step ``sol`` applied in place: both poses, the partner's move so far, the gain and the map's step."""
    rotate_by(sol[2], sol[3], sol[4], r)
    rotate_by(sol[8], sol[9], sol[10], r_other)
    for q in range(3):
        t[q] += sol[5 + q]
        t_other[q] += sol[11 + q]
    for q in range(6):
        other_moved[q] += sol[8 + q]
    gain_step[0] += sol[0]
    gain_step[1] += sol[1]


HELPERS: tuple[str, ...] = ("median_of", "rotate_by", "profile_means", "pair_gain", "pixel_noise", "smoothed", "lit")
HELPERS += ("unlit_out", "pushed", "damped", "stepped")
"""The helpers :func:`iterate` calls, each the module's global ``name`` (``name_py`` compiled), callees first."""
median_of = median_of_py
rotate_by = rotate_by_py
profile_means = profile_means_py
pair_gain = pair_gain_py
pixel_noise = pixel_noise_py
smoothed = smoothed_py
lit = lit_py
unlit_out = unlit_out_py
pushed = pushed_py
damped = damped_py
stepped = stepped_py


def iterate(
    obj: F64,
    nrm: F64,
    steps: F64,
    r: F64,
    t: F64,
    r_other: F64,
    t_other: F64,
    k: F64,
    dist: F64,
    image: U8,
    other: U8,
    gain_step: F64,
    other_moved: F64,
    dark: F64,
    fine_model: F64,
    coarse_model: F64,
    reals: F64,
    counts: I64,
    flags: npt.NDArray[np.bool_],
) -> tuple[int, int, float, I64, npt.NDArray[np.bool_], F64, F64, F64]:
    """``fit_sparse``'s iterations over every sample (``obj``, ``nrm``, ``steps``: the chosen samples' floor points,
    normals and steps; those unlit at the start left out, :func:`unlit_out_py` by each frame's ``dark`` level):
    the poses (``r``, ``t``; ``r_other``, ``t_other``), ``gain_step`` (the gain, the step) and the partner's move so
    far (``other_moved``) updated in place; the step model and its slope (``*_model``, rows) of the fine and the coarse
    steps; the settings in ``sparse._settings_arrays``' order. Returns the outcome (:data:`DONE` or why it stopped),
    the last iteration's number, the largest move of its step, the samples read (indices into the chosen), which were
    kept, their RMS residuals, the normal matrix and their rows."""
    border_px, min_inliers, outlier_factor, converged_px = reals[0], reals[1], reals[2], reals[3]
    converged_rms_px, settled_px, give_up_px = reals[4], reals[5], reals[6]
    other_sigma_px, flow_sigma_px, coarse_smooth_px = reals[7], reals[8], reals[9]
    radius, lines, iterations, give_up_steps = counts[0], counts[1], counts[2], counts[3]
    give_up_from, damp_from, width, coarse_steps, coarse_reach = counts[4], counts[5], counts[6], counts[7], counts[8]
    damp_swings, own_steps, esm_partner, fit_gain = flags[0], flags[1], flags[2], flags[3]
    n = len(obj)
    moved, large, noise2, it = np.inf, 0, -1.0, 0
    kept, last_push, order = np.ones(n, np.bool_), np.full(n, np.nan), np.arange(n)  # (order: places among the chosen)
    weights, normal = np.full((n, 2), -1.0 if own_steps else 0.0), np.eye(16)
    idx, keep, rms, a_rows = np.zeros(0, np.int64), np.zeros(0, np.bool_), np.zeros(0), np.eye(0, 14)
    for it in range(iterations):
        coarse = it < coarse_steps
        reach = coarse_reach if coarse else radius
        idx, pk, pj, a_rows = profiles(obj, nrm, r, t, r_other, t_other, k, dist, image, other, reach, border_px, lines)
        if it == 0:  # (the unlit left out while their kept marks, weights and pushes are still the first ones)
            order, obj, nrm, steps, idx, pk, pj, a_rows = unlit_out(dark, order, obj, nrm, steps, idx, pk, pj, a_rows)
            kept, last_push, weights = kept[: len(obj)], last_push[: len(obj)], weights[: len(obj)]
        if len(idx) < min_inliers:
            return FEW_IN_VIEW, it, moved, order[idx], keep, rms, normal, a_rows
        gain_step[0] = pair_gain(pk, pj) if it == 0 else gain_step[0]
        pk, pj = (smoothed(pk, coarse_smooth_px), smoothed(pj, coarse_smooth_px)) if coarse else (pk, pj)
        noise2 = pixel_noise(pk) if noise2 < 0 else noise2
        frame_weights = weights[idx]
        keep = kept[idx]
        model = coarse_model if coarse else fine_model
        gram, uy, yy = moments(
            pk, pj, steps[idx], gain_step[0], gain_step[1], model[0], model[1], noise2, frame_weights, esm_partner
        )
        weights[idx] = frame_weights
        sol = np.zeros(16)
        for _ in range(2 if it == 0 else 1):  # robust: drop profiles far worse than the typical one
            if keep.sum() < min_inliers:
                return FEW_KEPT, it, moved, order[idx], keep, rms, normal, a_rows
            sol, rss, normal, _ok = solve_step(
                gram, uy, yy, a_rows, keep, other_moved, other_sigma_px, flow_sigma_px, fit_gain, width
            )
            rms = np.sqrt(rss / width)
            keep = rms < outlier_factor * max(median_of(rms[keep]), 0.5)
        kept[idx] = keep
        push, moved, push_rms = pushed(a_rows, sol, keep)
        if damp_swings:
            sol = damped(sol, push, last_push, idx, keep, it >= damp_from)
        stepped(sol, r, t, r_other, t_other, other_moved, gain_step)
        by_rms = converged_rms_px > 0.0 and moved <= settled_px and push_rms < converged_rms_px
        if (moved < converged_px or by_rms) and not coarse:  # settled
            break
        large = large + 1 if give_up_px > 0.0 and moved > give_up_px else 0
        if large >= give_up_steps and it + 1 >= give_up_from and it + 1 < iterations:
            return GAVE_UP, it, moved, order[idx], keep, rms, normal, a_rows
    return DONE, it, moved, order[idx], keep, rms, normal, a_rows
