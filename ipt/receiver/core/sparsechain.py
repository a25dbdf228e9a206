"""The sparse tracker as a chain over the frames (issue 29; the fits are :mod:`ipt.receiver.core.sparse`'s).

IPT's sender shows each video frame in its + phase, then its − (it starts each input frame on an even output
index), so at 120 FPS a video frame is [+, +, −, −]. The chain pairs each frame with one of the other phase that
shows the same video frame (``order``): a + frame waits; a − frame is fitted with a + frame before it (k−1, k−2,
k−3, those with a pose first), both poses fitted when that one has none yet (a *joint* fit, the + frame held near
its prediction); then each + frame still waiting is fitted on its own against the − frame's new pose. While the
floor's content holds still (judged on each − frame against the − frame of the video frame before,
:func:`content_still`) a + frame is fitted at once with its past partner instead of waiting. Predictions carry the
chain's last two poses on at constant velocity, turned as the image moved since the newest (:mod:`~ipt.receiver.core.
imageshift`). A fit its checks refuse gives no pose: the caller's dense pipeline poses that frame and re-seeds the
chain with it.

:class:`LiveChain` is that chain fed one frame at a time (the pipeline's); the functions below it are shared with
``benchmarks/sparse_track.py``, which runs other pairings for comparison. Pure: lightness frames and poses in,
poses out.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import numpy.typing as npt

from ipt.receiver.core import kernels, sparse
from ipt.receiver.core.demodulator import median_f32
from ipt.receiver.core.imageshift import ImageShifts
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.phaseclock import PhaseClock
from ipt.receiver.core.pose import pose_of
from ipt.receiver.core.sparse import SparseCamera, SparseResult, SparseSettings, extrapolate, fit_sparse, select

F64 = npt.NDArray[np.float64]
U8 = npt.NDArray[np.uint8]
RT = tuple[F64, F64]
FitResult = tuple[SparseResult | None, str]
Fit = Callable[[U8, U8, RT, RT, float, bool], FitResult]
"""A pair fit: (this frame, partner, partner's pose, start, step hint, partner only predicted) → result, why not."""

#: A fit this far (metres) from the chain's prediction is refused (the dense pipeline's gates do as much).
MAX_JUMP_M = 0.03
#: Two fits of one frame with different partners, both further than :data:`MAX_JUMP_M` from the prediction, within
#: this of each other (metres) are taken (:func:`corroborates`) up to :data:`MAX_CORROBORATED_M` from it: the
#: prediction was off, not the fits (takeoff's refused fits were mostly within 10 mm of the truth, their predictions
#: 30-75 mm off: docs/receiver-cores.md, stop 62).
AGREE_M = 0.01
MAX_CORROBORATED_M = 0.09
#: Two same-phase frames' difference (a video frame apart, lit profiles) spread up to this many times a pair fit's
#: residual: still (p10-p90, stop 73: shadow-vibration 0.78-1.01; fast 1.10-2.53, moving-content 1.59-3.12 moved).
STILL_SPREAD = 1.0
#: A + frame still waiting this many frames after it is given up (the caller poses it densely).
WAIT_FRAMES = 3
#: Frames of chain state kept behind the newest.
KEEP_FRAMES = 16
#: No joint fit where the map's largest code cell, seen straight down from the predicted height, spans fewer pixels
#: than this share of the joint fit's profile half-length (:attr:`~ipt.receiver.core.sparse.SparseSettings.radius_px`:
#: 4.5 px at 640 across): a profile of ±6 px over 4 px cells crosses three of the map's edges where the fit models one.
#: On hover-2.5m all such fits were refused, 26 % of its processor time (docs/receiver-cores.md, stops 53 and 56).
JOINT_MIN_CELL_RADII = 0.75


@dataclass
class Chain:
    """The sparse chain's poses so far."""

    rt: dict[int, RT] = field(default_factory=dict)
    sign: dict[int, int] = field(default_factory=dict)
    step: dict[int, float] = field(default_factory=dict)
    fitted: dict[int, SparseResult] = field(default_factory=dict)
    emitted: dict[int, int] = field(default_factory=dict)
    """The frame on whose arrival each sparse pose came out."""
    last_amplitude: float = 0.0
    same_rms: list[float] = field(default_factory=list)
    """The residuals of the fits with a same-content partner, in order."""
    still: bool = False
    """The floor's content held still over the last video frame (``auto``; a :class:`LiveChain` judges it only when
    asked: read it through the chain, :meth:`LiveChain.content_moved`)."""
    moved: bool = False
    """The floor's content was judged to have moved over the last video frame (``still`` is False also when
    :func:`content_still` could not judge)."""
    reseeds: int = 0
    corroborated: int = 0
    """Fits taken far from their prediction because another partner's fit landed with them (:func:`corroborates`)."""
    refused: Counter[str] = field(default_factory=Counter)
    guesses: dict[int, RT] = field(default_factory=dict)
    """The prediction (rvec, tvec) of each frame started from one in a joint fit (both poses predicted)."""
    joint_ok: dict[int, bool] = field(default_factory=dict)
    """Whether each joint fit of a frame (the last one tried) passed the fit's own checks."""
    partner: dict[int, int] = field(default_factory=dict)
    """The partner frame of each fitted pose."""
    shifts: ImageShifts | None = None
    """The image's shifts between frames, which turn the predictions (:mod:`~ipt.receiver.core.imageshift`)."""


@dataclass(frozen=True)
class Pairing:
    """Which frames show the same video frame: ``waits(k)``: frame k's same-content partner is a later frame
    (k's pose comes out with it); ``partners(k)``: the earlier frames to pair k with, best first; ``baseline``:
    of the predictions' velocity (frames); ``joint_baseline``: the same for joint fits (0: ``baseline``)."""

    waits: Callable[[int], bool]
    partners: Callable[[int], list[int]]
    baseline: int = 1
    joint_baseline: int = 0
    known_first: bool = False
    """Partners with a pose first."""
    refine: bool = False
    """Each frame still waiting among a fitted frame's partners is then fitted on its own against it."""
    past_first: bool = False
    """A waiting frame first tries its past partners and takes the fit at once if the content held still."""
    auto: bool = False
    """A waiting frame is fitted at once with its past partner while the content holds still (measured on each
    second-phase frame against the video frame before), and waits only when that fit fails or it moved."""


def past_pairing(phase: Mapping[int, int]) -> Pairing:
    """Round one's chain: every frame from its nearest past partner of the other phase."""
    return Pairing(lambda k: False, lambda k: [k - b for b in (1, 2, 3) if phase.get(k - b) == -phase.get(k, 0)])


def order_pairing(phase: Mapping[int, int], first: int = 1, order: tuple[int, ...] = (1, 2, 3)) -> Pairing:
    """The rule a live receiver applies (the module's note): a frame of the phase ``first`` waits for a later
    partner, one of the other phase pairs with a past one of the first phase, ``order`` (the nearest first)."""
    return Pairing(
        lambda k: phase.get(k) == first,
        lambda k: [k - b for b in order if phase.get(k) == -first and phase.get(k - b) == first],
    )


def auto_pairing(phase: Mapping[int, int]) -> Pairing:
    """The live chain's pairing: ``order``, partners with a pose first, waiting frames refined, and past partners
    while the content holds still."""
    return replace(order_pairing(phase), known_first=True, refine=True, auto=True)


def moved_m(result: SparseResult, guess: RT) -> float:
    """How far the fitted camera is from the predicted one, metres."""
    return float(np.linalg.norm(shift_m(result, guess)))


def shift_m(result: SparseResult, guess: RT) -> F64:
    """The fitted camera's position less the predicted one's, metres (arena frame)."""
    fitted, _ = pose_of(result.rvec, result.tvec)
    predicted, _ = pose_of(*guess)
    return np.asarray(fitted - predicted, np.float64)


def predict(chain: Chain, k: int, times_us: Mapping[int, int], baseline: int = 1) -> RT | None:
    """The chain's last pose before ``k`` (within five frames) carried on to ``k`` at the velocity since a pose
    at least ``baseline`` frames before it (within eight frames; else the nearest before it), or that last pose
    alone; turned as the image moved since that last pose where the chain's :attr:`Chain.shifts` measured it."""
    recent = [j for j in range(k - 1, max(k - 6, -1), -1) if j in chain.rt]
    if not recent:
        return None
    b = recent[0]
    before = [j for j in range(b - 1, max(b - 9, -1), -1) if j in chain.rt]
    rt = chain.rt[b]
    if before:
        a = next((j for j in before if j <= b - baseline), before[0])
        rt = extrapolate(chain.rt[a], times_us[a], rt, times_us[b], times_us[k])
    if chain.shifts is None or (shift_px := chain.shifts.between(b, k)) is None:
        return rt
    return chain.shifts.turned(rt, chain.rt[b], shift_px)


def accept(chain: Chain, result: SparseResult | None, why: str, guess: RT, want: int) -> bool:
    """Whether a fit is taken: found, within :data:`MAX_JUMP_M` of its start, of the expected phase."""
    if result is not None and moved_m(result, guess) > MAX_JUMP_M:
        chain.refused["far_from_prediction"] += 1
        return False
    if result is not None and result.sign == want:
        return True
    chain.refused[why or "wrong_phase"] += 1
    return False


def corroborates(first: SparseResult, second: SparseResult, guess: RT) -> bool:
    """Whether ``second`` (a fit of the same frame with another partner) lands where ``first`` did, both far from
    their start ``guess``: within :data:`AGREE_M` of each other, of one phase, and no further from the start than
    :data:`MAX_CORROBORATED_M`. Then the prediction was off, not the fits."""
    a, _ = pose_of(first.rvec, first.tvec)
    b, _ = pose_of(second.rvec, second.tvec)
    return (
        first.sign == second.sign
        and float(np.linalg.norm(a - b)) <= AGREE_M
        and moved_m(second, guess) <= MAX_CORROBORATED_M
    )


def moved_by(rt: RT, off_m: F64) -> RT:
    """The pose ``rt`` (rvec, tvec: arena → camera) with the camera moved by ``off_m`` (arena frame), turned alike."""
    r, _ = cv2.Rodrigues(np.asarray(rt[0], np.float64).reshape(3, 1))
    return np.asarray(rt[0], np.float64).reshape(3), np.asarray(rt[1], np.float64).reshape(3) - r @ off_m


def pair_frame(
    chain: Chain,
    k: int,
    lum: Mapping[int, U8],
    phase: Mapping[int, int],
    times_us: Mapping[int, int],
    fit: Fit,
    pairing: Pairing,
) -> dict[int, SparseResult]:
    """Frame ``k``'s fit with its same-content past partner j (``pairing``); when j has no pose yet (it waited
    for k) both poses are unknowns, j's started from its prediction. With ``refine``, each frame still waiting
    among k's partners is then fitted on its own against k, k held at its fitted pose. The poses found, by
    frame."""
    guess = predict(chain, k, times_us, pairing.baseline)
    if guess is None or k not in phase:
        return {}
    candidates = [j for j in pairing.partners(k) if j in lum and (j in chain.rt or pairing.waits(j))]
    if pairing.known_first:
        candidates.sort(key=lambda j: j not in chain.rt)
    joint = pairing.joint_baseline or pairing.baseline
    found: dict[int, SparseResult] = {}
    far: SparseResult | None = None
    """A fit refused only for landing far from the prediction (:data:`MAX_JUMP_M`): a later partner's fit that lands
    where it did (:func:`corroborates`) is taken."""
    corrected_m: F64 | None = None
    """How far (arena frame) such a fit landed from its prediction: the chain's error, which its partner's pose and
    the starts of the waiting frames refitted after it share."""
    for j in candidates:
        known = j in chain.rt
        partner_rt = chain.rt[j] if known else predict(chain, j, times_us, joint)
        start = guess if known else predict(chain, k, times_us, joint)
        if partner_rt is None or start is None:
            continue
        if not known:
            chain.guesses.setdefault(k, start)
            chain.guesses.setdefault(j, partner_rt)
        hint = -chain.sign[j] * chain.step[j] if j in chain.step else 0.0 if known else phase[k] * chain.last_amplitude
        result, why = fit(lum[k], lum[j], partner_rt, start, hint, not known)
        if not known:
            chain.joint_ok[k] = result is not None
        agreed = False
        if not accept(chain, result, why, start, phase[k]):
            if result is None or result.sign != phase[k] or moved_m(result, start) <= MAX_JUMP_M:
                continue
            agreed = far is not None and corroborates(far, result, start)
            if not agreed:
                far = result
                continue
        assert result is not None
        found[k], chain.partner[k] = result, j
        chain.corroborated += agreed
        corrected_m = shift_m(result, start) if agreed else None
        if not known:
            other = result.partner()
            offset = corrected_m if corrected_m is not None else 0.0
            if float(np.linalg.norm(shift_m(other, partner_rt) - offset)) > MAX_JUMP_M:
                chain.refused["partner_far_from_prediction"] += 1
                found.clear()
                continue
            found[j], chain.partner[j] = other, k
        break
    if k in found and pairing.refine:
        _refine(chain, k, found, candidates, lum, phase, times_us, fit, pairing.baseline, corrected_m)
    return found


def _refine(
    chain: Chain,
    k: int,
    found: dict[int, SparseResult],
    candidates: list[int],
    lum: Mapping[int, U8],
    phase: Mapping[int, int],
    times_us: Mapping[int, int],
    fit: Fit,
    baseline: int,
    off_m: F64 | None = None,
) -> None:
    """Each frame still waiting among ``candidates`` fitted on its own against ``k``, held at its fitted pose; one
    not posed yet started from its prediction, moved by ``off_m`` (arena frame, metres: how far ``k``'s corroborated
    fit landed from its own prediction, the same chain's error; None: not moved)."""
    held = (found[k].rvec, found[k].tvec)
    for j in candidates:
        if j in chain.rt or phase.get(j) != -phase[k]:
            continue
        start = (found[j].rvec, found[j].tvec) if j in found else predict(chain, j, times_us, baseline)
        if start is None:
            continue
        if j not in found and off_m is not None:
            start = moved_by(start, off_m)
        result, why = fit(lum[j], lum[k], held, start, -found[k].sign * found[k].amplitude, False)
        if accept(chain, result, why, start, phase[j]):
            assert result is not None
            found[j], chain.partner[j] = result, k


def content_still(
    chain: Chain,
    k: int,
    lum: Mapping[int, U8],
    phase: Mapping[int, int],
    camera: SparseCamera,
    edges: MapEdges,
    spread_ratio: float = STILL_SPREAD,
) -> bool | None:
    """Whether the floor's content held still from the video frame before to ``k``'s: ``k`` and a frame of the
    same phase of the video frame before (k−4, k−3, k−5), both read at their poses along the map's edges (the
    map cancels between frames of one phase): the spread of their difference (robust) against ``k``'s pair fit's
    residual, at most ``spread_ratio`` times it. None: no such frame, or too few of the map's edges in view."""
    judge = still_judge(chain, k, lum, phase, camera, edges, spread_ratio)
    return judge() if judge is not None else None


def still_judge(
    chain: Chain,
    k: int,
    lum: Mapping[int, U8],
    phase: Mapping[int, int],
    camera: SparseCamera,
    edges: MapEdges,
    spread_ratio: float = STILL_SPREAD,
) -> Callable[[], bool | None] | None:
    """:func:`content_still` for ``k`` as it stands now, to be judged later or never (None: no frame to judge it
    against): the chain's poses, the frames and the fit's residual it reads are taken now."""
    m = next((m for m in (k - 4, k - 3, k - 5) if phase.get(m) == phase.get(k) and m in chain.rt and m in lum), None)
    if m is None:
        return None
    rt_k, rt_m, lum_k, lum_m, rms_px = chain.rt[k], chain.rt[m], lum[k], lum[m], chain.fitted[k].rms_px
    return lambda: _held_still(rt_k, rt_m, lum_k, lum_m, rms_px, camera, edges, spread_ratio)


def _held_still(
    rt_k: RT, rt_m: RT, lum_k: U8, lum_m: U8, rms_px: float, camera: SparseCamera, edges: MapEdges, spread_ratio: float
) -> bool | None:
    r_k, _ = cv2.Rodrigues(np.asarray(rt_k[0], np.float64).reshape(3, 1))
    r_m, _ = cv2.Rodrigues(np.asarray(rt_m[0], np.float64).reshape(3, 1))
    t_k, t_m = np.asarray(rt_k[1], np.float64).reshape(3), np.asarray(rt_m[1], np.float64).reshape(3)
    chosen = select(edges, camera, r_k, t_k, 300)
    _, pk, pm, _ = kernels.sparse_profiles(
        edges.points_m[chosen],
        edges.normals_m[chosen],
        r_k,
        t_k,
        r_m,
        t_m,
        camera.camera_matrix,
        camera.dist_coeffs,
        lum_k,
        lum_m,
        4,
        3.0,
        3,
    )
    dark = sparse.dark_levels(lum_k, lum_m)  # (the fits' residual is of lit profiles: so is the spread)
    lit = (pk.mean(axis=1) > dark[0]) & (pm.mean(axis=1) > dark[1])
    pk, pm = pk[lit], pm[lit]
    if len(pk) < 30:
        return None
    gain = median_f32(pk.mean(axis=1) / np.maximum(pm.mean(axis=1), 1.0))  # (float32: np.median's floats)
    d = (pk - gain * pm).ravel()
    spread = 1.4826 * median_f32(np.abs(d - median_f32(d)))
    return spread <= spread_ratio * max(rms_px, 0.1)


def take(chain: Chain, k: int, result: SparseResult, out_at: int) -> None:
    """A fitted pose of ``k`` into the chain (it came out on frame ``out_at``'s arrival)."""
    chain.rt[k], chain.sign[k], chain.step[k] = (result.rvec, result.tvec), result.sign, result.amplitude
    chain.fitted[k], chain.emitted[k], chain.last_amplitude = result, out_at, result.amplitude


def seed(chain: Chain, k: int, rt: RT, sign: int) -> None:
    """A pose of ``k`` found otherwise (the dense pipeline's) into the chain; counted as a re-seed once the chain
    has started."""
    chain.rt[k], chain.sign[k] = rt, sign
    chain.step.pop(k, None)
    chain.reseeds += 1 if chain.fitted or len(chain.rt) > 1 else 0


def chain_settings(
    width_px: int,
    *,
    esm_partner: bool = True,
    partner_sigma_px: float = 10.0,
    base: SparseSettings | None = None,
    joint_iterations: int = 12,
    joint_coarse: int = 1,
    joint_settled_px: float = 0.6,
    joint_radius_px: int = SparseSettings.radius_px,
    joint_smooth_px: float = SparseSettings.coarse_smooth_px,
    joint_half_until_px: float = 0.0,
    known_sigma_px: float = 3.0,
    known_iterations: int = 5,
    known_converged_rms_px: float = 0.15,
    joint_converged_rms_px: float = 0.0,
    joint_damp_from: int | None = 2,
) -> tuple[SparseSettings, SparseSettings]:
    """The fits' settings for a camera ``width_px`` wide (pixel figures are stated at 640 and scale with the width:
    the blur, the profiles' reach, the priors, and the marks of convergence, settling and giving up): with a partner
    whose pose is known (held near it by ``known_sigma_px``, refused if moved by more than 1.5 times that), and for a
    joint fit (the partner only predicted, held near it by ``partner_sigma_px``). The defaults are the
    prototype's best measured chain (docs/receiver-cores.md, rounds two and three), with the known partner
    held looser than the prototype's 1 px and 3 iterations: a partner's pose is a fit too, and held at 1 px
    its error passed on to the next frame along the chain (dark-scene's sparse MAE 2.68 / 2.05 / 0.73 mm
    against the dense tracker's 2.08 / 1.52 / 0.49; 3 px and 5 iterations: 2.16 / 1.75 / 0.62). The known-partner
    fits damp their swinging steps (:attr:`~ipt.receiver.core.sparse.SparseSettings.damp_swings`); the joint fits from
    their third step (``joint_damp_from``; None: never), once the coarse step and the first fine one have come the long
    way from the prediction (damped from their first step, two-projectors uncalibrated once gave a pose 115 mm off and
    keystone uncalibrated seven 100-116 mm off; from the third, stop 56, fast 97.8 -> 99.0 % and 103 -> 116-119 frames
    per processor-second, moving-content's MAE 1.04 / 0.76 / 0.27 -> 1.20 / 0.96 / 0.32 mm, rolling 98.75 -> 97.60 %:
    docs/receiver-cores.md). The known-partner fits also stop once
    a step moved the samples by less than ``known_converged_rms_px`` RMS (stop 44: shadow-vibration's known fits
    4.71 -> 3.43 iterations, the same yield and MAE within 0.03 mm; at 0.1 px, 3.77 iterations, and the keystoned
    flight with the uniform arena file lost its chain where that file is furthest off: four poses 105-111 mm off)."""
    s = base if base is not None else SparseSettings(esm_partner=esm_partner)
    scale = width_px / 640
    known = replace(
        s,
        blur_px=s.blur_px * scale,
        border_px=s.border_px * scale,
        other_sigma_px=known_sigma_px * scale,
        max_partner_px=1.5 * known_sigma_px * scale,
        iterations=known_iterations,
        radius_px=round(s.radius_px * scale),
        fine_radius_px=round(s.fine_radius_px * scale),
        converged_px=s.converged_px * scale,
        converged_rms_px=known_converged_rms_px * scale,
        settled_px=s.settled_px * scale,
        give_up_px=s.give_up_px * scale,
        damp_swings=True,
    )
    ratio = known.blur_px / SparseSettings.blur_px
    joint = replace(
        known,
        other_sigma_px=partner_sigma_px * scale,
        max_partner_px=3.0 * partner_sigma_px * scale,
        iterations=joint_iterations,
        settled_px=joint_settled_px * scale,
        converged_rms_px=joint_converged_rms_px * scale,
        coarse_iterations=joint_coarse,
        radius_px=round(joint_radius_px * ratio),
        half_until_px=joint_half_until_px * ratio,
        coarse_smooth_px=joint_smooth_px * ratio,
        damp_swings=joint_damp_from is not None,
        damp_from=joint_damp_from if joint_damp_from is not None else 0,
    )
    return known, joint


def fitter(camera: SparseCamera, edges: MapEdges, known: SparseSettings, joint: SparseSettings) -> Fit:
    """The pair fit with these settings (``joint`` when the partner's pose is only predicted; none where the map's
    cells are too small in the image for it, :data:`JOINT_MIN_CELL_RADII`: refused as "small_cells")."""
    largest_cell_m, min_cell_px = edges.largest_cell_m, JOINT_MIN_CELL_RADII * joint.radius_px

    def fit(
        image: U8, other: U8, other_rt: RT, guess: RT, hint: float, predicted: bool
    ) -> tuple[SparseResult | None, str]:
        if predicted and cell_px(camera, largest_cell_m, guess) < min_cell_px:
            return None, "small_cells"
        return fit_sparse(image, other, camera, edges, other_rt, guess, joint if predicted else known, hint)

    return fit


def cell_px(camera: SparseCamera, cell_m: float, rt: RT) -> float:
    """How many pixels a floor square of side ``cell_m`` spans, seen straight down from the camera's height at the
    pose ``rt`` (rvec, tvec: arena → camera); infinite at or below the floor."""
    position, _ = pose_of(*rt)
    height = float(position[2])
    return cell_m * float(camera.camera_matrix[0, 0]) / height if height > 0 else math.inf


@dataclass(frozen=True)
class ChainStep:
    """What the chain made of a frame: the sparse poses it found (this frame's and waiting earlier frames'), by
    frame; the earlier frames it gave up on (the caller poses them otherwise); whether this frame waits for a
    later partner (its pose, if any, comes with a later frame's step)."""

    poses: dict[int, SparseResult]
    partners: dict[int, int]
    """The partner frame of each of :attr:`poses`."""
    given_up: list[int]
    waits: bool


class LiveChain:
    """The chain fed one frame at a time: its raw (distorted) lightness, capture time and predicted projector
    phase (+1, −1, or None if not known yet). It starts from a pose given by :meth:`seed` (the dense pipeline's),
    is re-seeded the same way for frames it gives up on, and starts afresh on :meth:`reset` (a restart, a gap in
    time, a bad frame, a pose the caller found it wrong on). ``wait`` False: no frame waits for a later partner
    (each is paired with its past ones: a pipeline without look-ahead)."""

    def __init__(self, camera: SparseCamera, edges: MapEdges, fit: Fit, projector_hz: float, wait: bool = True) -> None:
        self.camera, self.edges, self.fit, self.projector_hz = camera, edges, fit, projector_hz
        self.shifts = ImageShifts(camera.camera_matrix)
        self.chain = Chain(shifts=self.shifts)
        self._lum: dict[int, U8] = {}
        self._times_us: dict[int, int] = {}
        self._phase: dict[int, int] = {}
        self._pending: list[int] = []
        self._judge: Callable[[], bool | None] | None = None
        """:func:`still_judge` of the last frame of the second phase posed, until it is judged or replaced."""
        self.pairing = auto_pairing(self._phase) if wait else replace(past_pairing(self._phase), known_first=True)
        self.posed = 0
        """Frames posed by the chain since it was made."""

    @property
    def started(self) -> bool:
        """Whether the chain has a pose to go on from."""
        return bool(self.chain.rt)

    def reset(self, frames: bool = True) -> None:
        """Forget the chain's poses, and with ``frames`` the frames too (else a frame kept may still be seeded):
        the chain waits for a new seed."""
        self.chain = Chain(reseeds=self.chain.reseeds, refused=self.chain.refused, shifts=self.shifts)
        self._judge = None
        if frames:
            for kept in (self._lum, self._times_us, self._phase, self.shifts):
                kept.clear()
        self._pending.clear()

    def seed(self, k: int, rt: RT, sign: int) -> None:
        """Frame ``k``'s pose found otherwise (``sign``: its projector phase), if the chain has it as a frame."""
        if k in self._lum:
            self._phase[k] = sign
            seed(self.chain, k, rt, sign)
            if k in self._pending:
                self._pending.remove(k)

    def feed(self, k: int, time_us: int, lum: U8, phase: int | None) -> ChainStep:
        """Take frame ``k``; what the chain made of it (:class:`ChainStep`). Its phase is predicted from the phases
        the chain found for the frames before (:func:`clock_phase`), else ``phase`` is taken."""
        clock = self.clock()
        by_clock = clock.at(time_us) if clock is not None else None
        phase = by_clock if by_clock is not None else phase
        self._lum[k], self._times_us[k] = lum, time_us
        if phase is not None:
            self._phase[k] = phase
        self.shifts.add(k, lum, phase)
        self._forget(k - KEEP_FRAMES)
        out: dict[int, SparseResult] = {}
        chain, pairing, started = self.chain, self.pairing, self.started
        waits = phase is not None and pairing.waits(k)
        if started and phase is not None:
            if not waits:
                out = pair_frame(chain, k, self._lum, self._phase, self._times_us, self.fit, pairing)
                if k in out:
                    chain.same_rms = [*chain.same_rms[-15:], out[k].rms_px]
            elif self._still():
                past = past_pairing(self._phase)
                out = pair_frame(chain, k, self._lum, self._phase, self._times_us, self.fit, past)
        for j, result in out.items():
            take(chain, j, result, k)
            if j in self._pending:
                self._pending.remove(j)
        if k in out and not waits:  # judged when asked: the next second-phase frame's verdict replaces it unread
            self._judge = still_judge(chain, k, self._lum, self._phase, self.camera, self.edges)
            chain.still = chain.moved = False
        waiting = started and waits and k not in out
        if waiting:
            self._pending.append(k)
        given_up = [j for j in self._pending if j <= k - WAIT_FRAMES]
        for j in given_up:
            self._pending.remove(j)
        self.posed += len(out)
        return ChainStep(out, {j: chain.partner.get(j, -1) for j in out}, given_up, waiting)

    def _still(self) -> bool:
        """The chain's :attr:`Chain.still`, once the verdict left waiting (:func:`still_judge`) is judged."""
        if self._judge is not None:
            verdict = self._judge()
            self._judge = None
            self.chain.still, self.chain.moved = bool(verdict), verdict is False
        return self.chain.still

    def content_moved(self) -> bool:
        """Whether the floor's content was judged to have moved over the last video frame (:attr:`Chain.moved`)."""
        self._still()
        return self.chain.moved

    def clock(self) -> PhaseClock | None:
        """The projector's phase clock from the phases of the (at most eight) newest frames the chain has posed,
        if it has posed two."""
        known = sorted(self.chain.sign)[-8:]
        if len(known) < 2:
            return None
        signs = tuple(self.chain.sign[j] for j in known)
        return PhaseClock(tuple(self._times_us[j] for j in known), signs, self.projector_hz)

    def _forget(self, before: int) -> None:
        for kept in (self._lum, self._times_us, self._phase):
            for j in [j for j in kept if j < before]:
                del kept[j]
        self.shifts.forget(before)
        c = self.chain
        for kept_rt in (c.rt, c.sign, c.step, c.fitted, c.emitted, c.guesses, c.joint_ok, c.partner):
            for j in [j for j in kept_rt if j < before]:
                del kept_rt[j]


__all__ = ["Chain", "ChainStep", "LiveChain", "Pairing", "PhaseClock", "chain_settings", "fitter"]
