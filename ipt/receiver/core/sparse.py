"""A sparse tracker (a prototype for issue 29): a frame's pose from two raw frames read only along the map's edges.

:mod:`ipt.receiver.core.track` fits the pose to the steps of a difference image that the dense stages make
(undistortion of both frames, their content homography, their brightness-matched difference). Once the
partner frame's pose is known roughly, none of that is needed: the floor points on both sides of each edge
sample of the hidden map are projected into this frame ``k`` (at its current estimate) and into its partner
``j`` (at its estimate), through the camera's own lens model, and the two raw frames are read there.

Two traps shape the fit. The floor's content does not cancel in I_k − g·I_j unless the two readings are
registered: a pixel of misregistration leaves the content's slope (tens of levels a pixel) against a map step
of a few levels. And ``j`` carries the map too, with the other sign: read at ``j``'s pose its step sits at
o = 0 of each profile while ``k``'s sits at its error δ, so a peak finder on the difference finds about their
midpoint (or o = 0). So the fit is direct, on the profiles' values: this frame's profile is modelled as the
partner's with its step turned over, I_k ≈ g·I_j + c·M (M the map's blurred step, c = 2ΔL signed by the
phase), each shifted by its frame's pose change (Gauss-Newton in both poses, the gain and c; the content
ties the two poses together, the map's step places them on the map; the partner's pose is held near its own
by a prior, so a flat floor still fits). Profiles whose residual is far above the typical one (content that
changed between the frames, the shadow's edge) are left out. The first iterations smooth the profiles, for
a guess a few pixels off.

Pure: two 8-bit lightness frames, the camera model, the partner's pose and a guess in; a pose out, or why not.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from ipt.receiver.core import kernels, sparseloop
from ipt.receiver.core.demodulator import dark_level
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.pose import PoseEstimate, estimate_from_step
from ipt.receiver.core.track import MIN_CELL_PX, fast_median

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
U8 = npt.NDArray[np.uint8]

#: A profile whose mean lies below this share of the way from its frame's darkest tenth to the median is taken for
#: unlit (:attr:`SparseSettings.lit_only`). The dense signal mask's 0.35 takes more dark video for unlit too; 0.2
#: measured best (every suite and held-out row in process at 0.1 / 0.2 / 0.3 / 0.35: docs/receiver-cores.md, stop 73).
LIT_FRACTION = 0.2


@dataclass(frozen=True)
class SparseSettings:
    """How the profiles are read and the pose fitted (pixels at the camera's own resolution)."""

    radius_px: int = 6
    """Profile half-length of the coarse iterations."""
    fine_radius_px: int = 4
    """Profile half-length of the later iterations."""
    coarse_iterations: int = 0
    """The first iterations smooth the profiles (a wider reach for a guess a few pixels off)."""
    coarse_smooth_px: float = 1.5
    smooth_px: float = 0.0
    """The later iterations' smoothing of the profiles (σ, pixels): the camera's noise is several times the
    map's step, and the fit's slopes come from the partner's profile."""
    iterations: int = 3
    converged_px: float = 0.1
    """The fit stops when its last step moved no kept sample by more than this (pixels)."""
    converged_rms_px: float = 0.0
    """... or when it moved the kept samples by less than this, RMS (pixels), and none by more than
    ``settled_px`` (0: only ``converged_px``). The largest of ~700 samples' moves is several times their RMS:
    traced on shadow-vibration's known-partner fits (median of the fits, stop 43's code), the steps' RMS went
    1.03, 0.44, 0.11, 0.057, 0.034 px from the first iteration to the fifth while the largest move was 2.05, 1.18,
    0.33, 0.17, 0.11 px, so three fits in four ran all five iterations for changes of a few hundredths of a
    pixel."""
    settled_px: float = 0.6
    """... and is refused if, after the last iteration, that step was larger than this."""
    half_until_px: float = 0.0
    """While the last step moved a sample by more than this (pixels), only every second sample is read (0:
    all, always): far from the answer half of them steer as well; a fit is only taken from all of them."""
    max_samples: int = 700
    min_inliers: int = 60
    min_tags: int = 2
    min_inlier_fraction: float = 0.5
    """Fewer of the samples in view kept than this: refused (content changed, or the pose is lost)."""
    blur_px: float = 1.0
    """The Gaussian blur (σ) of a step in the camera's image: the model of the map's step."""
    border_px: float = 3.0
    lines: int = 3
    """Each profile is the mean of this many parallel lines a pixel apart along the edge."""
    own_steps: bool = True
    """Fit each frame's own step beside the pair's, where the floor is flat (False: the pair's alone)."""
    outlier_factor: float = 2.5
    """A profile whose RMS residual exceeds this many times the median one is left out."""
    other_sigma_px: float = 1.0
    """How far the partner's known pose may be off (pixels): its prior."""
    flow_sigma_px: float = 0.0
    """How far the floor's content may move between the two frames (pixels): its prior (panning video); 0:
    not fitted. (Fitted, it cost shadow-vibration 7 points of yield and did not take out moving-content's
    bias: a pan of several pixels a frame is beyond a profile's reach.)"""
    max_partner_px: float = 1.5
    """A fit that moves the partner's pose by more than this (pixels, at any sample) is refused."""
    min_step_sigmas: float = 8.0
    """The map's step must stand this many standard errors clear of zero."""
    fit_gain: bool = False
    """Fit the pair's brightness ratio too (False: keep the ratio of the profiles' means). Over a flat floor
    the partner's centred profile is its (turned over) step, and the gain and the step are one unknown."""
    min_amplitude: float = 0.5
    """... and be at least this many lightness levels per unit of the map's step."""
    lit_only: bool = True
    """Leave out the samples whose profiles (their means) are not lit in both frames at the start
    (:func:`dark_levels`; too few left: "few_in_view"): the drone's shadow and the floor beyond the projection carry
    no step, yet fitted they pass as inliers (no step, and no more noise than the lit floor) and pull the map's step
    down and the pose towards them."""
    esm_partner: bool = False
    """The partner's displacement's slope averaged, as this frame's is, with the slope where it will be
    (this frame's profile less the step's): then a move of both frames together (where the pair sits on the
    map) sees the map's step alone, not the two frames' content slopes' difference."""
    give_up_px: float = 2.5
    """A fit gives up ("gave_up") once each of its last ``give_up_steps`` steps moved a sample by more than
    this (pixels), from its ``give_up_from``-th iteration on (0: never). Traced on the joint fits (12
    iterations, settled at 0.6 px) of moving-content, fast, realcam, shadow-vibration and takeoff-open-floor:
    of 708 that were taken none had three steps running above 2.5 px from the 9th on, of 750 refused unsettled
    340 did before their last (a refused fit's steps do shrink, to just above the settled mark: a rule that
    cut them sooner, at any threshold tried, also cut fits that would have been taken). Not lossless: in
    whole-process replays of the BMP frames it cut some fit that would have been taken on moving-content,
    realcam and takeoff-open-floor (their poses then differ from those without it; yield −0.1 / 0 / −0.2
    points, MAE within 0.07 mm on every axis); fast, shadow-vibration and dark-scene stayed identical."""
    give_up_from: int = 9
    give_up_steps: int = 3
    damp_swings: bool = False
    """A step that turns back against the last one (the samples' displacements, compared on the samples both
    kept) is scaled by 1 / (1 + q), q (at most 1) the share of the last step it takes back: where the steps
    swing, the limit of the swinging sequence (:func:`damped`). Traced on shadow-vibration's known-partner
    fits: successive steps point back against each other (median cosine −0.5 at the second step, −0.9 by the
    fifth) while shrinking by only 0.6–0.9 each, so most fits ran all their iterations and a third were refused
    unsettled."""
    damp_from: int = 0
    """The first step (counted from 0) that :attr:`damp_swings` scales; the steps before it only set the last step
    that the next is compared with."""


@dataclass(frozen=True)
class SparseResult:
    """The frame's pose fitted from its pair."""

    rvec: F64
    """Rotation arena → camera (Rodrigues)."""
    tvec: F64
    inliers: int
    tried: int
    rms_px: float
    sign: int
    """The frame's projector phase: +1 if the map's white cells are brighter in it than in its partner."""
    amplitude: float
    """The pair's step, lightness levels per unit of the map's step (ΔL seen by the camera, both phases)."""
    gain: float
    iterations: int
    tags: tuple[int, ...]
    other_rvec: F64
    """The partner's pose as the fit left it (its prior held it near the one given): a pose of its own when
    the partner's given pose was only a prediction (a pair of which neither frame had a pose)."""
    other_tvec: F64
    cov_rt: F64
    """6x6 covariance of the fit's last step of this frame's pose (δ, Δt: as
    :attr:`~ipt.receiver.core.track.TrackResult.cov_rt`): the residual's variance times the inverse normal matrix,
    the partner's pose free within its prior."""
    other_cov_rt: F64
    """The same for the partner's pose."""

    def estimate(self) -> PoseEstimate:
        return estimate_from_step(self.rvec, self.tvec, self.cov_rt, self.tags, self.rms_px)

    def partner(self) -> SparseResult:
        """The partner frame's pose from the same fit, as a result of its own (its phase the other)."""
        return dataclasses.replace(
            self,
            rvec=self.other_rvec,
            tvec=self.other_tvec,
            sign=-self.sign,
            other_rvec=self.rvec,
            other_tvec=self.tvec,
            cov_rt=self.other_cov_rt,
            other_cov_rt=self.cov_rt,
        )


@dataclass(frozen=True)
class SparseCamera:
    """The camera as the sparse tracker projects through it."""

    camera_matrix: F64
    dist_coeffs: F64
    """k1, k2, p1, p2, k3 (OpenCV's order)."""
    size: tuple[int, int]
    """(width, height) pixels."""

    @classmethod
    def of(cls, camera_matrix: F64, dist_coeffs: F64, size: tuple[int, int]) -> SparseCamera:
        dist = np.zeros(5)
        given = np.asarray(dist_coeffs, np.float64).ravel()[:5]
        dist[: len(given)] = given
        return cls(np.asarray(camera_matrix, np.float64), dist, size)


def select(edges: MapEdges, camera: SparseCamera, r: F64, t: F64, most: int) -> I64:
    """Indices of the edge samples of the tags that may be in view at (r, t), at most ``most``, spread evenly
    (the tags' centres through the pinhole: the lens moves them by less than the margin of a tag's reach)."""
    w, h = camera.size
    k = camera.camera_matrix
    centres = edges.tag_centres_m @ r.T + t
    depth = np.maximum(centres[:, 2], 0.05)
    uv = (k[:2, :2] @ (centres[:, :2] / depth[:, None]).T).T + k[:2, 2]
    reach = k[0, 0] * edges.tag_radius_m / depth
    near = (centres[:, 2] > 0.05) & (uv[:, 0] > -reach) & (uv[:, 0] < w + reach)
    near &= (uv[:, 1] > -reach) & (uv[:, 1] < h + reach)
    cell = edges.tag_cell_m if edges.tag_cell_m is not None else np.full(len(depth), edges.cell_m)
    near &= k[0, 0] * cell / depth >= MIN_CELL_PX
    ranges = edges.tag_ranges
    if ranges is None:
        chosen = np.flatnonzero(near[edges.tag])
    else:  # the near tags' ranges of samples, joined (the same indices, without a look at every sample)
        start, count = ranges
        tags = np.flatnonzero(near)
        lengths = count[tags]
        ends = np.cumsum(lengths)
        chosen = np.arange(int(ends[-1]) if len(ends) else 0) + np.repeat(start[tags] - (ends - lengths), lengths)
    if len(chosen) > most:
        chosen = chosen[_spread(len(chosen), most)]
    return chosen


@functools.lru_cache(maxsize=64)
def _spread(n: int, most: int) -> I64:
    """``most`` indices spread evenly over ``n`` (a chain asks for the same few counts again and again)."""
    picks = np.linspace(0, n - 1, most).astype(np.int64)
    picks.flags.writeable = False
    return picks


#: Unknowns of the fit: the pair's brightness ratio's change, the map's step in the difference, this frame's
#: pose change (δ rotation, Δt), the partner's, and the motion of the floor's content between the two (x, y).
_GAIN, _STEP, _THIS, _OTHER, _FLOW = 0, 1, slice(2, 8), slice(8, 14), slice(14, 16)


@dataclass
class _State:
    """The fit's running estimate."""

    r: F64
    t: F64
    r_other: F64
    t_other: F64
    gain: float
    step: float
    """The map's step in the difference I_k − gain·I_j, lightness levels per unit of the map's step: 2ΔL
    seen by the camera, signed by this frame's phase."""
    other_moved: F64
    """The partner's pose change so far (δ rotation, Δt), which its prior holds near zero."""


def _smooth(profiles: F32, sigma_px: float) -> F32:
    if sigma_px <= 0:
        return profiles
    size = 2 * math.ceil(2.5 * sigma_px) + 1
    return np.asarray(cv2.GaussianBlur(profiles, (size, 1), sigma_px, borderType=cv2.BORDER_REPLICATE), np.float32)


@dataclass
class _Moments:
    """One iteration's profiles, reduced to what the fit needs (:func:`~ipt.receiver.core.sparsekernels.moments`)."""

    gram: F64
    uy: F64
    yy: F64
    a_rows: F64
    """(n, 14): the rows of this frame's displacement, the partner's, the content's."""


@functools.lru_cache(maxsize=16)
def _step_model(width: int, blur_px: float) -> tuple[F64, F64]:
    """The map's unit step at the profile's middle, blurred by ``blur_px`` (σ), and its slope, per profile sample."""
    o = (np.arange(width, dtype=np.float64) - width // 2) / blur_px
    cdf = 0.5 * (1.0 + np.array([math.erf(x / math.sqrt(2.0)) for x in o]))
    pdf = np.exp(-0.5 * o * o) / (math.sqrt(2.0 * math.pi) * blur_px)
    return cdf, pdf


def _moments(
    pk: F32, pj: F32, a_rows: F64, sv: F64, st: _State, blur_px: float, weights: F64, noise2: float, esm: bool
) -> _Moments:
    """The linearised model of this frame's profiles from the partner's and the map's (per profile, centred:
    each sample's own brightness level drops out): I_k − g·I_j − c·M = Δg·I_j + Δc·M − F′·δ + g·I_j′·ε, with
    F = g·I_j + c·M the partner's profile with its step turned over (what this frame shows when registered),
    δ and ε the displacements (profile steps) that this frame's and the partner's pose changes make."""
    cdf, pdf = _step_model(pk.shape[1], blur_px)
    gram, uy, yy = kernels.sparse_moments(pk, pj, sv, st.gain, st.step, cdf, pdf, noise2, weights, esm)
    return _Moments(gram, uy, yy, a_rows)


def _solve(m: _Moments, keep: npt.NDArray[np.bool_], st: _State, s: SparseSettings) -> tuple[F64, F64, F64]:
    """The least-squares change of the 14 unknowns from the kept profiles, the partner's pose held near its
    own by its prior (:func:`~ipt.receiver.core.sparsekernels.solve_step`); also each profile's RMS residual
    (per profile sample) and the normal matrix."""
    width = 2 * s.fine_radius_px + 1
    sol, rss, normal, _ok = kernels.sparse_solve_step(
        m.gram, m.uy, m.yy, m.a_rows, keep, st.other_moved, s.other_sigma_px, s.flow_sigma_px, s.fit_gain, width
    )
    return sol, np.sqrt(rss / width), normal


def _update(st: _State, sol: F64) -> None:
    rot, _ = cv2.Rodrigues(sol[2:5].reshape(3, 1))
    st.r, st.t = np.asarray(rot, np.float64) @ st.r, st.t + sol[5:8]
    rot, _ = cv2.Rodrigues(sol[8:11].reshape(3, 1))
    st.r_other, st.t_other = np.asarray(rot, np.float64) @ st.r_other, st.t_other + sol[11:14]
    st.other_moved = st.other_moved + sol[_OTHER]
    st.gain += float(sol[_GAIN])
    st.step += float(sol[_STEP])


def _initial(image: U8, other: U8, other_rt: tuple[F64, F64], guess_rt: tuple[F64, F64], step: float) -> _State:
    rot, _ = cv2.Rodrigues(np.asarray(guess_rt[0], np.float64).reshape(3, 1))
    rot_o, _ = cv2.Rodrigues(np.asarray(other_rt[0], np.float64).reshape(3, 1))
    return _State(
        np.asarray(rot, np.float64),
        np.asarray(guess_rt[1], np.float64).reshape(3).copy(),
        np.asarray(rot_o, np.float64),
        np.asarray(other_rt[1], np.float64).reshape(3).copy(),
        1.0,
        step,
        np.zeros(6),
    )


def fit_sparse(
    image: U8,
    other: U8,
    camera: SparseCamera,
    edges: MapEdges,
    other_rt: tuple[F64, F64],
    guess_rt: tuple[F64, F64],
    settings: SparseSettings = SparseSettings(),
    step_hint: float = 0.0,
) -> tuple[SparseResult | None, str]:
    """The pose of the frame ``image`` (raw 8-bit lightness, as the camera sees it: not undistorted) from its
    pair with ``other`` (opposite projector phase) whose pose ``other_rt`` (rvec, tvec: arena → camera) is
    known, starting from ``guess_rt``; ``step_hint``: the pair's step if known (the last pair's, signed for
    this frame). The result, or None and why ("few_samples", "few_in_view", "few_kept", "few_tags",
    "not_converged", "gave_up", "weak_step", "partner_moved")."""
    s = settings
    st = _initial(image, other, other_rt, guess_rt, step_hint)
    chosen = select(edges, camera, st.r, st.t, s.max_samples)
    if len(chosen) < s.min_inliers:
        return None, "few_samples"
    obj, nrm, steps = edges.points_m[chosen], edges.normals_m[chosen], edges.step[chosen]
    k, dist = camera.camera_matrix, camera.dist_coeffs
    dark = dark_levels(image, other) if s.lit_only else np.zeros(2)
    if s.smooth_px == 0.0 and s.half_until_px <= 0 and kernels.sparse_iterate_compiled():
        return _fit_compiled(st, image, other, k, dist, edges, chosen, obj, nrm, steps, dark, s)
    return _fit_python(st, image, other, camera, edges, chosen, dark, s)


def _fit_python(
    st: _State, image: U8, other: U8, camera: SparseCamera, edges: MapEdges, chosen: I64, dark: F64, s: SparseSettings
) -> tuple[SparseResult | None, str]:
    """:func:`fit_sparse`'s iterations as a Python loop around the three compiled kernels (a fit that smooths every
    step or reads half its samples first, or a process without numba), then its checks."""
    obj, nrm, steps = edges.points_m[chosen], edges.normals_m[chosen], edges.step[chosen]
    k, dist = camera.camera_matrix, camera.dist_coeffs
    moved, it, gain_set, large = np.inf, 0, False, 0  # (large: steps running that moved a sample over give_up_px)
    kept = np.ones(len(chosen), np.bool_)  # per chosen sample: its profile is not an outlier
    # per chosen sample: the weights of its frames' own steps (-1: not yet known)
    weights = np.full((len(chosen), 2), -1.0 if s.own_steps else 0.0)
    noise2 = -1.0
    every = np.arange(len(chosen))
    half = every[::2] if s.half_until_px > 0 else every
    last_push = np.full(len(chosen), np.nan)  # per chosen sample: the last step's displacement (pixels)
    judged = not dark.any()  # the unlit samples left out (on the first step that reads every sample)
    for it in range(s.iterations):
        coarse = it < s.coarse_iterations
        radius = s.radius_px if coarse else s.fine_radius_px
        active = half if moved > s.half_until_px else every
        reading_all = len(active) == len(every)
        idx, pk, pj, a_rows = kernels.sparse_profiles(
            obj if reading_all else obj[active],
            nrm if reading_all else nrm[active],
            *(st.r, st.t, st.r_other, st.t_other, k, dist, image, other, radius, s.border_px, s.lines),
        )
        idx = idx if reading_all else active[idx]
        if len(idx) < s.min_inliers * len(active) / len(every):
            return None, "few_in_view"
        if not judged and reading_all:  # (as the compiled loop does: the unlit samples left out from here on)
            judged = True
            shown = sparseloop.lit_py(pk, pj, dark)
            if int(shown.sum()) < s.min_inliers:
                return None, "few_in_view"
            if not shown.all():
                stays = np.ones(len(chosen), np.bool_)
                stays[idx[~shown]] = False
                place = np.cumsum(stays) - 1  # each staying sample's new index
                chosen, obj, nrm, steps = chosen[stays], obj[stays], nrm[stays], steps[stays]
                kept, weights, last_push = kept[stays], weights[stays], last_push[stays]
                every = np.arange(len(chosen))
                half = every[::2] if s.half_until_px > 0 else every
                idx, pk, pj, a_rows = place[idx[shown]], pk[shown], pj[shown], a_rows[shown]
        if not gain_set:
            st.gain, gain_set = fast_median(pk.mean(axis=1) / np.maximum(pj.mean(axis=1), 1.0)), True
        smooth = s.coarse_smooth_px if coarse else s.smooth_px
        pk, pj = _smooth(pk, smooth), _smooth(pj, smooth)
        blur = math.hypot(s.blur_px, smooth)
        if noise2 < 0:  # a frame's pixel noise (variance): second differences (white noise: 6σ²), robustly
            curvature = np.abs(pk[:, 2:] - 2 * pk[:, 1:-1] + pk[:, :-2])
            noise2 = max((1.4826 * fast_median(curvature)) ** 2 / 6.0, 0.01)
        frame_weights = weights[idx]
        m = _moments(pk, pj, a_rows, steps[idx], st, blur, frame_weights, noise2, s.esm_partner)
        weights[idx] = frame_weights
        keep = kept[idx]
        for _ in range(2 if it == 0 else 1):  # robust: drop profiles far worse than the typical one
            if keep.sum() < s.min_inliers * len(active) / len(every):
                return None, "few_kept"
            sol, rms, normal = _solve(m, keep, st, s)
            keep = rms < s.outlier_factor * max(fast_median(rms[keep]), 0.5)
        kept[idx] = keep
        push = a_rows[:, :6] @ sol[_THIS]
        kept_push = push[keep]
        moved = float(np.abs(kept_push).max())
        if s.damp_swings:
            damped_sol = damped(sol, push, last_push, idx, keep)
            if it >= s.damp_from:
                sol = damped_sol
        _update(st, sol)
        may_end = not coarse and len(active) == len(every)
        if may_end and (moved < s.converged_px or converged_by_rms(kept_push, moved, s)):
            break
        large = large + 1 if moved > s.give_up_px > 0 else 0
        if large >= s.give_up_steps and it + 1 >= s.give_up_from and it + 1 < s.iterations:
            return None, "gave_up"
    if len(active) < len(every):  # still reading half the samples at the last iteration: far from settled
        return None, "not_converged"
    return _finish(st, edges, chosen, idx, keep, rms, normal, moved, it, a_rows[:, 6:12], s)


def _fit_compiled(
    st: _State,
    image: U8,
    other: U8,
    k: F64,
    dist: F64,
    edges: MapEdges,
    chosen: I64,
    obj: F64,
    nrm: F64,
    steps: F64,
    dark: F64,
    s: SparseSettings,
) -> tuple[SparseResult | None, str]:
    """:func:`fit_sparse`'s iterations in one compiled call (:func:`~ipt.receiver.core.sparseloop.iterate`: every
    sample; the coarse steps smoothed at their reach, the others unsmoothed at the fine reach), then its checks."""
    fine, coarse, reals, counts, flags = _settings_arrays(s)
    gain_step = np.array([st.gain, st.step])
    outcome, it, moved, idx, keep, rms, normal, a_rows = kernels.sparse_iterate(
        *(obj, nrm, steps, st.r, st.t, st.r_other, st.t_other, k, dist, image, other, gain_step, st.other_moved, dark),
        *(fine, coarse, reals, counts, flags),
    )
    if outcome != sparseloop.DONE:
        return None, sparseloop.WHY[outcome]
    st.gain, st.step = float(gain_step[0]), float(gain_step[1])
    return _finish(st, edges, chosen, idx, keep, rms, normal, float(moved), int(it), a_rows[:, 6:12], s)


@functools.lru_cache(maxsize=16)
def _settings_arrays(s: SparseSettings) -> tuple[F64, F64, F64, I64, npt.NDArray[np.bool_]]:
    """What :func:`~ipt.receiver.core.sparseloop.iterate` takes of a fit's settings (which it only reads): the
    step model of the fine and of the coarse steps (:func:`_step_model`: the map's blurred step and its slope),
    and the rest as three arrays. Made once per settings (a chain has two): ~0.1 ms of every fit when made
    for each."""
    fine = np.array(_step_model(2 * s.fine_radius_px + 1, math.hypot(s.blur_px, 0.0)))
    coarse = np.array(_step_model(2 * s.radius_px + 1, math.hypot(s.blur_px, s.coarse_smooth_px)))
    reals = [s.border_px, s.min_inliers, s.outlier_factor, s.converged_px, s.converged_rms_px, s.settled_px]
    reals += [s.give_up_px, s.other_sigma_px, s.flow_sigma_px, s.coarse_smooth_px]
    counts = [s.fine_radius_px, s.lines, s.iterations, s.give_up_steps, s.give_up_from, s.damp_from]
    counts += [2 * s.fine_radius_px + 1, s.coarse_iterations, s.radius_px]
    flags = [s.damp_swings, s.own_steps, s.esm_partner, s.fit_gain]
    return fine, coarse, np.array(reals, np.float64), np.array(counts, np.int64), np.array(flags, np.bool_)


def dark_levels(image: U8, other: U8) -> F64:
    """Each frame's dark level (this one's, the partner's) for :attr:`SparseSettings.lit_only`:
    :data:`LIT_FRACTION` of the way from the darkest tenth of every 8th pixel of every 8th row to their median."""
    return np.array([dark_level(image[::8, ::8], LIT_FRACTION), dark_level(other[::8, ::8], LIT_FRACTION)])


def converged_by_rms(push: F64, moved: float, s: SparseSettings) -> bool:
    """Whether a step that moved the kept samples by ``push`` (pixels; ``moved`` the largest) ends the fit by its
    RMS (:attr:`SparseSettings.converged_rms_px`)."""
    if s.converged_rms_px <= 0.0 or moved > s.settled_px:
        return False
    return float(np.sqrt(np.mean(push * push))) < s.converged_rms_px


def damped(sol: F64, push: F64, last_push: F64, idx: I64, keep: npt.NDArray[np.bool_]) -> F64:
    """The step ``sol`` (displacing the samples ``idx`` by ``push``, pixels) scaled by 1 / (1 + q) if it takes
    back the share q > 0 of the last step (``last_push``, per chosen sample, NaN where not read; updated here)
    along it: for steps that swing about the answer, each q times the last turned over, the swinging sequence's
    limit lies 1 / (1 + q) of the way along this step (q taken at most 1)."""
    before = last_push[idx]
    last_push[:] = np.nan
    last_push[idx] = push
    both = keep & np.isfinite(before)
    if not both.any():
        return sol
    p, b = push[both], before[both]
    back = -float(p @ b) / max(float(b @ b), 1e-12)
    return sol / (1.0 + min(back, 1.0)) if back > 0.0 else sol


def _finish(
    st: _State,
    edges: MapEdges,
    chosen: I64,
    idx: I64,
    keep: npt.NDArray[np.bool_],
    rms: F64,
    normal: F64,
    moved: float,
    it: int,
    other_rows: F64,
    s: SparseSettings,
) -> tuple[SparseResult | None, str]:
    """The checks on the last iteration's fit, and the result."""
    present = np.flatnonzero(np.bincount(edges.tag[chosen[idx[keep]]]))
    if len(present) < s.min_tags:
        return None, "few_tags"
    if moved > s.settled_px:
        return None, "not_converged"
    sigma = float(np.sqrt(np.mean(rms[keep] ** 2)))
    try:
        inverse = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        return None, "weak_step"
    step_var = float(inverse[_STEP, _STEP])
    cov = sigma * sigma * inverse
    if abs(st.step) < s.min_step_sigmas * sigma * math.sqrt(step_var) or abs(st.step) < s.min_amplitude:
        return None, "weak_step"
    if float(np.abs(other_rows[keep] @ st.other_moved).max()) > s.max_partner_px:
        return None, "partner_moved"
    inliers = int(keep.sum())
    if inliers < s.min_inlier_fraction * len(idx):
        return None, "inlier_fraction"
    rvec, _ = cv2.Rodrigues(st.r)
    other_rvec, _ = cv2.Rodrigues(st.r_other)
    tags = tuple(sorted(edges.tag_ids[i] for i in present))
    sign = 1 if st.step > 0 else -1
    return SparseResult(
        np.asarray(rvec, np.float64).reshape(3),
        st.t.copy(),
        inliers,
        len(idx),
        sigma,
        sign,
        abs(st.step),
        st.gain,
        it + 1,
        tags,
        np.asarray(other_rvec, np.float64).reshape(3),
        st.t_other.copy(),
        np.asarray(cov[_THIS, _THIS], np.float64),
        np.asarray(cov[_OTHER, _OTHER], np.float64),
    ), ""


def extrapolate(
    older: tuple[F64, F64], older_us: int, newer: tuple[F64, F64], newer_us: int, at_us: int
) -> tuple[F64, F64]:
    """The pose (rvec, tvec) at ``at_us`` moving on from ``newer`` as it moved from ``older``: constant linear and
    angular velocity of the camera."""
    if newer_us == older_us:
        return newer
    f = (at_us - newer_us) / (newer_us - older_us)
    ra, _ = cv2.Rodrigues(np.asarray(older[0], np.float64).reshape(3, 1))
    rb, _ = cv2.Rodrigues(np.asarray(newer[0], np.float64).reshape(3, 1))
    pa = -ra.T @ np.asarray(older[1], np.float64).reshape(3)
    pb = -rb.T @ np.asarray(newer[1], np.float64).reshape(3)
    turn, _ = cv2.Rodrigues(rb @ ra.T)  # arena → camera side: R_b = turn · R_a
    step, _ = cv2.Rodrigues(np.asarray(turn, np.float64) * f)
    r = np.asarray(step, np.float64) @ rb
    p = pb + f * (pb - pa)
    rvec, _ = cv2.Rodrigues(r)
    return np.asarray(rvec, np.float64).reshape(3), -r @ p
