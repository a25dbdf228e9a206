"""The sparse tracker prototype (ipt/receiver/core/sparse.py) on pairs rendered from known poses: two raw frames of
opposite phase, the partner's pose known, this frame's guessed some pixels off."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from floorview import render_view

from ipt.config.models import ArenaConfig
from ipt.geometry import R_BODY_CAM_DOWNWARD, rot_x, rot_y, rot_z, rotation_angle_rad
from ipt.receiver.core import kernels, phaseclock, sparse, sparsechain
from ipt.receiver.core.demodulator import lightness
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.pose import pose_of, rt_of
from ipt.receiver.core.sparse import (
    SparseCamera,
    SparseResult,
    SparseSettings,
    _step_model,
    extrapolate,
    fit_sparse,
)
from ipt.sender.modulator import PaperModulator
from ipt.tagmap import grid_tag_map

ROOT = Path(__file__).resolve().parents[1]

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]

ARENA = ArenaConfig()
TAG_MAP = grid_tag_map(ARENA)
SIZE = (640, 360)
K = np.array([[450.0, 0.0, 319.5], [0.0, 450.0, 179.5], [0.0, 0.0, 1.0]])
#: A lens like the realcam flight's (barrel, some tangential): 9 px at the corners of a 640x360 image.
LENS = np.array([-0.14, 0.06, 0.0005, -0.0004, -0.008])
POSITION_M = np.array([0.07, -0.12, 0.8])
R_ARENA_CAM = rot_z(np.deg2rad(11.0)) @ rot_x(np.deg2rad(2.0)) @ R_BODY_CAM_DOWNWARD
#: The partner frame's own pose: the camera moved 6 mm and turned a little between the two frames.
OTHER_POSITION_M = POSITION_M + np.array([0.004, -0.003, 0.003])
R_OTHER = rot_y(np.deg2rad(0.3)) @ R_ARENA_CAM


@dataclass(frozen=True)
class Pair:
    image: U8
    other: U8
    camera: SparseCamera


def _distorted_view(img: U8, position_m: F64, r_arena_cam: F64, lens: F64) -> U8:
    """The view through a camera with ``lens``: each sensor pixel takes the undistorted view at the pinhole
    pixel its ray hits (rendered larger than the sensor, as the barrel lens sees more)."""
    margin = 64
    k_big = K.copy()
    k_big[:2, 2] += margin
    big = render_view(img, ARENA, k_big, position_m, r_arena_cam, (SIZE[0] + 2 * margin, SIZE[1] + 2 * margin))
    if not np.any(lens):
        return np.ascontiguousarray(big[margin:-margin, margin:-margin])
    u, v = np.meshgrid(np.arange(SIZE[0], dtype=np.float64), np.arange(SIZE[1], dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1)[:, None, :]
    ideal = cv2.undistortPoints(pts, K, lens, P=k_big).reshape(SIZE[1], SIZE[0], 2).astype(np.float32)
    return np.asarray(cv2.remap(big, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR), np.uint8)


def _pair(lens: F64, position_m: F64 = POSITION_M) -> Pair:
    """The pair seen through ``lens`` from ``position_m`` (the partner from it moved as OTHER_POSITION_M is)."""
    rng = np.random.default_rng(3)
    coarse = rng.integers(40, 216, (ARENA.projector.height_px // 8, ARENA.projector.width_px // 8, 3), np.uint8)
    content = np.asarray(
        cv2.resize(coarse, (ARENA.projector.width_px, ARENA.projector.height_px), interpolation=cv2.INTER_CUBIC),
        np.uint8,
    )
    plus, minus = PaperModulator(TAG_MAP.render_mask(), ARENA.modulation.delta_l).modulate(content, 0, 2)
    image = lightness(_distorted_view(plus, position_m, R_ARENA_CAM, lens))
    other = lightness(_distorted_view(minus, position_m + (OTHER_POSITION_M - POSITION_M), R_OTHER, lens))
    return Pair(image, other, SparseCamera.of(K, lens, SIZE))


@pytest.fixture(scope="module")
def pinhole_pair() -> Pair:
    return _pair(np.zeros(5))


@pytest.fixture(scope="module")
def lens_pair() -> Pair:
    return _pair(LENS)


@pytest.fixture(scope="module")
def edges() -> MapEdges:
    return MapEdges.from_tag_map(TAG_MAP)


def _errors(rvec: F64, tvec: F64) -> tuple[float, float]:
    """(position error mm, rotation error deg) against the frame's true pose."""
    position, r_arena_cam = pose_of(rvec, tvec)
    return (
        1000 * float(np.linalg.norm(position - POSITION_M)),
        float(np.rad2deg(rotation_angle_rad(r_arena_cam.T @ R_ARENA_CAM))),
    )


def _image_error_px(rvec: F64, tvec: F64) -> float:
    """The largest distance (pixels, pinhole) between where the pose and the true pose put the floor under a
    grid over the image."""
    true_r, true_t = rt_of(POSITION_M, R_ARENA_CAM)
    grid = np.stack(np.meshgrid(np.linspace(40, 600, 8), np.linspace(40, 320, 5)), axis=-1).reshape(-1, 2)
    r_true, _ = cv2.Rodrigues(true_r)
    rays = (np.linalg.inv(K) @ np.column_stack([grid, np.ones(len(grid))]).T).T @ r_true  # arena directions
    centre = -r_true.T @ true_t
    floor = centre + (-centre[2] / rays[:, 2])[:, None] * rays
    seen, _ = cv2.projectPoints(floor, rvec, tvec, K, None)
    return float(np.linalg.norm(seen.reshape(-1, 2) - grid, axis=1).max())


def _guess_off_by(pixels: float) -> tuple[F64, F64]:
    """The true pose moved sideways so that the image moves by ``pixels``, and turned a little."""
    shift_m = pixels * POSITION_M[2] / K[0, 0]
    r = rot_z(np.deg2rad(0.15)) @ R_ARENA_CAM
    return rt_of(POSITION_M + np.array([shift_m * 0.8, shift_m * 0.6, 0.002]), r)


DEFAULT = SparseSettings()
EVERY_SAMPLE = SparseSettings(lit_only=False)
"""For the tests of other rules than ``lit_only``, on every sample: the pair's content is random video of 40-216
levels, whose darkest parts the rule takes for unlit (a real shadow: ``test_sparseloop.py``)."""


def _fit(
    pair: Pair, edges: MapEdges, start: tuple[F64, F64], settings: SparseSettings = DEFAULT
) -> tuple[SparseResult | None, str]:
    return fit_sparse(pair.image, pair.other, pair.camera, edges, rt_of(OTHER_POSITION_M, R_OTHER), start, settings)


def test_a_guess_3px_off_converges_to_a_fraction_of_a_pixel(pinhole_pair: Pair, edges: MapEdges) -> None:
    start = _guess_off_by(3.0)
    assert _image_error_px(*start) > 2.9
    result, why = _fit(pinhole_pair, edges, start)
    assert result is not None, why
    assert _image_error_px(result.rvec, result.tvec) < 0.2
    mm, deg = _errors(result.rvec, result.tvec)
    assert mm < 1.0
    assert deg < 0.05
    assert result.sign == 1  # this frame showed the + phase
    assert result.inliers > 0.6 * result.tried


def test_an_error_of_the_partners_pose_is_not_inherited(pinhole_pair: Pair, edges: MapEdges) -> None:
    """The partner's pose given 1 px off: registering the content alone would carry that error over to this
    frame; the map's steps in both frames place both poses on the map."""
    shift_m = 1.0 * OTHER_POSITION_M[2] / K[0, 0]
    partner = rt_of(OTHER_POSITION_M + np.array([-0.6 * shift_m, 0.8 * shift_m, 0.0]), R_OTHER)
    result, why = fit_sparse(
        pinhole_pair.image, pinhole_pair.other, pinhole_pair.camera, edges, partner, _guess_off_by(2.0), EVERY_SAMPLE
    )
    assert result is not None, why
    assert _image_error_px(result.rvec, result.tvec) < 0.25


def test_a_distorted_camera_is_fitted_through_its_lens(lens_pair: Pair, edges: MapEdges) -> None:
    start = _guess_off_by(3.0)
    result, why = _fit(lens_pair, edges, start)
    assert result is not None, why
    assert _image_error_px(result.rvec, result.tvec) < 0.25
    assert _errors(result.rvec, result.tvec)[0] < 1.0
    # The same frames taken for a pinhole's: the lens's 9 px at the corners pull the fit off, or it fails.
    naive = SparseCamera.of(K, np.zeros(5), SIZE)
    wrong, _ = fit_sparse(
        lens_pair.image, lens_pair.other, naive, edges, rt_of(OTHER_POSITION_M, R_OTHER), start, SparseSettings()
    )
    assert wrong is None or _image_error_px(wrong.rvec, wrong.tvec) > 0.5


def test_the_other_phase_is_found_from_the_pair(lens_pair: Pair, edges: MapEdges) -> None:
    """The partner as this frame and this as the partner: the phase comes out the other way round."""
    start = rt_of(OTHER_POSITION_M + np.array([0.002, 0.001, 0.0]), R_OTHER)
    result, why = fit_sparse(
        lens_pair.other, lens_pair.image, lens_pair.camera, edges, rt_of(POSITION_M, R_ARENA_CAM), start
    )
    assert result is not None, why
    assert result.sign == -1
    position, _ = pose_of(result.rvec, result.tvec)
    assert 1000 * np.linalg.norm(position - OTHER_POSITION_M) < 1.0


def test_extrapolation_continues_a_steady_motion() -> None:
    a = rt_of(np.array([0.0, 0.0, 1.0]), R_ARENA_CAM)
    b = rt_of(np.array([0.01, 0.0, 1.0]), rot_z(np.deg2rad(1.0)) @ R_ARENA_CAM)
    rvec, tvec = extrapolate(a, 0, b, 1000, 2000)
    position, r_arena_cam = pose_of(rvec, tvec)
    assert np.allclose(position, [0.02, 0.0, 1.0], atol=1e-9)
    assert rotation_angle_rad(r_arena_cam.T @ rot_z(np.deg2rad(2.0)) @ R_ARENA_CAM) < 1e-9


def test_the_benchmark_names_a_folder_that_is_not_a_rendering(tmp_path: Path) -> None:
    (tmp_path / "bmp").mkdir()
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "sparse_track.py"), str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 2
    assert done.stderr.strip() == f"sparse_track: {tmp_path}: no camera.yaml"


#: The frame before the pair, of the partner's phase, showing the previous video frame: the photograph panned
#: by this many projector pixels (moving-content's pans are 3-10 a video frame).
PAN_PX = 8
PREVIOUS_POSITION_M = POSITION_M - np.array([0.004, -0.003, 0.003])


def _photo(pan_px: int) -> tuple[U8, U8]:
    """The two phases of one video frame whose content (busy, seeded) is panned by ``pan_px``."""
    rng = np.random.default_rng(5)
    coarse = rng.integers(40, 216, (ARENA.projector.height_px // 8, ARENA.projector.width_px // 8, 3), np.uint8)
    size = (ARENA.projector.width_px, ARENA.projector.height_px)
    content = np.asarray(cv2.resize(coarse, size, interpolation=cv2.INTER_CUBIC), np.uint8)
    modulator = PaperModulator(TAG_MAP.render_mask(), ARENA.modulation.delta_l)
    plus, minus = modulator.modulate(np.ascontiguousarray(np.roll(content, pan_px, axis=1)), 0, 2)
    return plus, minus


@pytest.fixture(scope="module")
def panned() -> tuple[Pair, U8]:
    """The pair of one video frame (this frame in its first phase, the later partner in the second) and a
    frame of the previous video frame in the second phase, its content panned."""
    plus, minus = _photo(0)
    pair = Pair(
        lightness(_distorted_view(plus, POSITION_M, R_ARENA_CAM, LENS)),
        lightness(_distorted_view(minus, OTHER_POSITION_M, R_OTHER, LENS)),
        SparseCamera.of(K, LENS, SIZE),
    )
    return pair, lightness(_distorted_view(_photo(PAN_PX)[1], PREVIOUS_POSITION_M, R_ARENA_CAM, LENS))


def test_a_first_phase_frame_is_fitted_with_its_later_same_content_partner(
    panned: tuple[Pair, U8], edges: MapEdges
) -> None:
    """With its past partner (the previous video frame, panned) the fit is pulled along the pan or refused;
    with the later partner of the same video frame, both frames' poses only predicted (each 2 px off), the
    joint fit gives this frame's pose."""
    pair, before = panned
    start = _guess_off_by(2.0)
    past, _ = fit_sparse(pair.image, before, pair.camera, edges, rt_of(PREVIOUS_POSITION_M, R_ARENA_CAM), start)
    assert past is None or _image_error_px(past.rvec, past.tvec) > 2.0  # 5 px here, accepted by its checks
    shift_m = 2.0 * OTHER_POSITION_M[2] / K[0, 0]
    predicted_partner = rt_of(OTHER_POSITION_M + np.array([-0.8 * shift_m, 0.6 * shift_m, 0.0]), R_OTHER)
    loose = SparseSettings(other_sigma_px=3.0, max_partner_px=9.0, iterations=6)
    # The later frame is the one fitted; this frame is its partner, whose pose the fit solves too.
    later, why = fit_sparse(pair.other, pair.image, pair.camera, edges, start, predicted_partner, loose)
    assert later is not None, why
    this = later.partner()
    assert this.sign == 1
    assert _image_error_px(this.rvec, this.tvec) < 0.3
    assert _errors(this.rvec, this.tvec)[0] < 1.0
    position, _ = pose_of(later.rvec, later.tvec)
    assert 1000 * np.linalg.norm(position - OTHER_POSITION_M) < 1.0


def test_the_phase_order_pairs_each_frame_within_its_video_frame() -> None:
    """Four camera frames a video frame, [+, +, -, -] (IPT's sender shows each input frame's + phase first): a
    + frame waits for a later partner, a - frame pairs with the + frames before it, the nearest first, never
    with the previous video frame's."""
    phase = {k: (1 if k % 4 in (0, 1) else -1) for k in range(12)}
    pairing = sparsechain.order_pairing(phase)
    assert [pairing.waits(k) for k in range(4, 8)] == [True, True, False, False]
    assert pairing.partners(6) == [5, 4]
    assert pairing.partners(7) == [5, 4]
    assert pairing.partners(4) == []


def test_the_phase_by_the_clock_at_twice_the_projectors_rate() -> None:
    """A camera at exactly 120 FPS against a 60 Hz projector: every frame is half a period after the last, its
    time rounded to the microsecond. From eight frames' phases ([+, +, -, -] a video frame) the phases of the
    next three frames are predicted (the + frames wait for partners, so the chain may know none of them yet),
    wherever the camera's clock starts against the projector's: the rounding never leaves one undecided.
    (Offsets of 0 and half a period put every frame on a flip, where a microsecond decides its side: 7 % of
    these were undecided, and the chain then waited on a wrong phase: moving-content and realcam posed a third
    of their frames the dense way.)"""
    pattern = [1, 1, -1, -1] * 6
    undecided = []
    for start_us in range(0, 16_667, 37):
        times = [round(start_us + k * 1e6 / 120) for k in range(24)]
        for k in range(10, 24):
            for gap in (1, 2, 3):
                known = slice(k - gap - 7, k - gap + 1)
                said = phaseclock.clock_phase(times[known], pattern[known], times[k], 60.0)
                assert said in (pattern[k], None), (start_us, k, gap)
                if said is None:
                    undecided.append((start_us, k, gap))
    assert undecided == []


def _clock_phase_numpy(times_us: list[int], signs: list[int], at_us: int, projector_hz: float) -> int | None:
    """:func:`~ipt.receiver.core.phaseclock.clock_phase` as it was written with numpy (stop 56)."""
    if len(signs) < 2:
        return None
    ref = times_us[-1]
    t = (np.asarray(times_us, np.float64) - ref) * 1e-6 * projector_hz
    offsets = (np.arange(20) + 0.5) / 20.0
    pattern = 1.0 - 2.0 * (np.floor(t[None, :] + offsets[:, None]) % 2)
    agree = pattern @ np.asarray(signs, np.float64)
    best = float(np.abs(agree).max())
    if best < len(signs) - 2 or best == 0.0:
        return None
    ok = np.abs(agree) == best
    at = (at_us - ref) * 1e-6 * projector_hz
    predicted = np.sign(agree[ok]) * (1.0 - 2.0 * (np.floor(at + offsets[ok]) % 2))
    return int(predicted[0]) if np.all(predicted == predicted[0]) else None


def test_the_clock_in_plain_python_says_what_numpys_said() -> None:
    """The clock's phase, written in plain Python for speed, against its numpy form on 20 000 random cases: camera
    clocks at 100-240 FPS with jitter, 59.94-60 Hz projectors, 2-8 phases of which some are wrong, times rounded
    to the microsecond, asked 1-3 frames on (undecided answers included)."""
    rng = np.random.default_rng(7)
    undecided = 0
    for _ in range(20_000):
        fps, hz = float(rng.uniform(100.0, 240.0)), float(rng.choice([60.0, 59.94]))
        n = int(rng.integers(2, 9))
        start = int(rng.integers(0, 10**9))
        times = [start + round(k * 1e6 / fps + rng.normal(0.0, 30.0)) for k in range(n + 3)]
        truth = [1 if math.floor(t * 1e-6 * hz + 0.37) % 2 == 0 else -1 for t in times]
        signs = [-s if rng.random() < 0.1 else s for s in truth[:n]]
        at = times[n + int(rng.integers(0, 3))]
        said = phaseclock.clock_phase(times[:n], signs, at, hz)
        assert said == _clock_phase_numpy(times[:n], signs, at, hz)
        undecided += said is None
    assert 0 < undecided < 20_000


def test_two_phases_that_contradict_each_other_tell_no_phase() -> None:
    """Two known phases that every clock offset finds one right and one wrong (here: the same phase a whole
    projector period apart, where the projector has flipped) give no phase, not 0 (the chain stored 0 as a
    frame's phase: dark-scene once, rolling twice, low-fast-big-shadow once in a replay)."""
    times = [0, 16_667]
    assert phaseclock.clock_phase(times, [1, 1], 33_333, 60.0) is None
    assert phaseclock.clock_phase(times, [1, -1], 33_333, 60.0) == 1  # agreeing ones still tell
    assert phaseclock.clock_phase(times, [-1, 1], 33_333, 60.0) == -1


def test_both_frames_moved_together_see_the_maps_step_alone() -> None:
    """With ``esm_partner`` the model's columns for this frame's displacement and the partner's add up to the
    map's step's slope, whatever the two profiles' content slopes: where the pair sits on the map is then
    measured by the step, not by the content's slopes' difference (over photographs that difference swamped
    the step, and a pair fitted from a partner's pose 3 mm off kept 2.9 of the 3 mm)."""
    rng = np.random.default_rng(9)
    width, gain, step = 9, 0.9, 3.0
    cdf, pdf = _step_model(width, 1.0)
    content = np.cumsum(rng.normal(0.0, 20.0, (5, width + 1)), axis=1)  # busy: tens of levels a pixel
    pj = np.asarray(100 + content[:, :-1], np.float32)
    pk = np.asarray(gain * (100 + content[:, 1:]) + step * cdf + rng.normal(0.0, 3.0, (5, width)), np.float32)
    sv = np.ones(5)
    pure = (step * pdf) - np.mean(step * pdf)  # the step's slope, centred as the model centres each profile
    for esm, close in ((True, True), (False, False)):
        gram, _, _ = kernels.sparse_moments(pk, pj, sv, gain, step, cdf, pdf, 1.0, np.zeros((5, 2)), esm)
        together = gram[:, 2, 2] + 2 * gram[:, 2, 3] + gram[:, 3, 3]  # Σ (u_δ + u_ε)² per profile
        assert np.allclose(together, np.sum(pure * pure), rtol=1e-6) == close


def test_content_that_held_still_is_told_from_content_that_panned(panned: tuple[Pair, U8], edges: MapEdges) -> None:
    """The ``auto`` chain's judge: a second-phase frame against one of the same phase of the video frame before
    (the map cancels between them), each read at its pose, the camera moved 6 mm between them. The same content:
    still; panned 8 px: moved."""
    pair, before = panned
    fitted, why = _fit(pair, edges, _guess_off_by(1.0))  # a pair fit's residual, the judge's yardstick
    assert fitted is not None, why
    held = lightness(_distorted_view(_photo(0)[1], PREVIOUS_POSITION_M, R_ARENA_CAM, LENS))
    for earlier, still in ((held, True), (before, False)):
        chain = sparsechain.Chain()
        chain.rt = {0: rt_of(PREVIOUS_POSITION_M, R_ARENA_CAM), 4: rt_of(OTHER_POSITION_M, R_OTHER)}
        chain.fitted = {4: fitted}
        lum = dict(enumerate([earlier, earlier, earlier, earlier, pair.other]))
        phase = {0: -1, 4: -1}
        assert sparsechain.content_still(chain, 4, lum, phase, pair.camera, edges) == still


def test_content_that_held_still_under_a_moving_shadow_is_still(panned: tuple[Pair, U8], edges: MapEdges) -> None:
    """The drone's shadow moves with it over the floor: where it lies in one frame and not in the other the two
    frames differ, but not the content. The judge leaves the unlit profiles out, as the fits whose residual is its
    yardstick do: the content that held still, with three fifths of the earlier view in shadow, is still."""
    pair, _ = panned
    fitted, why = _fit(pair, edges, _guess_off_by(1.0))
    assert fitted is not None, why
    held = lightness(_distorted_view(_photo(0)[1], PREVIOUS_POSITION_M, R_ARENA_CAM, LENS))
    shadowed = held.copy()
    cut = int(0.6 * held.shape[1])
    shadowed[:, :cut] = (shadowed[:, :cut] * 0.08).astype(np.uint8)
    chain = sparsechain.Chain()
    chain.rt = {0: rt_of(PREVIOUS_POSITION_M, R_ARENA_CAM), 4: rt_of(OTHER_POSITION_M, R_OTHER)}
    chain.fitted = {4: fitted}
    lum, phase = {0: shadowed, 4: pair.other}, {0: -1, 4: -1}
    assert sparsechain.content_still(chain, 4, lum, phase, pair.camera, edges) is True


def test_a_judge_of_the_content_left_waiting_judges_the_frames_as_they_were(
    panned: tuple[Pair, U8], edges: MapEdges
) -> None:
    """The live chain leaves each second-phase frame's verdict waiting (the next one's replaces it unread, a frame
    of the first phase asks for it): a judge made over panned content says "moved" even after the chain's frames
    and poses were replaced by those of content that held still, which the judge made then calls still."""
    pair, before = panned
    fitted, why = _fit(pair, edges, _guess_off_by(1.0))
    assert fitted is not None, why
    held = lightness(_distorted_view(_photo(0)[1], PREVIOUS_POSITION_M, R_ARENA_CAM, LENS))
    chain = sparsechain.Chain()
    chain.rt = {0: rt_of(PREVIOUS_POSITION_M, R_ARENA_CAM), 4: rt_of(OTHER_POSITION_M, R_OTHER)}
    chain.fitted = {4: fitted}
    lum, phase = {0: before, 4: pair.other}, {0: -1, 4: -1}
    judge = sparsechain.still_judge(chain, 4, lum, phase, pair.camera, edges)
    assert judge is not None
    lum[0] = held
    assert judge() is False
    assert sparsechain.content_still(chain, 4, lum, phase, pair.camera, edges) is True
    assert sparsechain.still_judge(chain, 4, lum, {4: -1}, pair.camera, edges) is None  # no frame to judge against


def test_a_fit_that_reads_half_the_samples_while_far_off_ends_on_all_of_them(
    pinhole_pair: Pair, edges: MapEdges
) -> None:
    """Every second sample steers the first steps (``half_until_px``); the fit settles, and is judged, on all."""
    start = _guess_off_by(3.0)
    full, why = _fit(pinhole_pair, edges, start, EVERY_SAMPLE)  # (lit_only judges at the first full read: later here)
    assert full is not None, why
    halved, why = _fit(pinhole_pair, edges, start, replace(EVERY_SAMPLE, half_until_px=1.0, iterations=5))
    assert halved is not None, why
    assert halved.tried == full.tried
    assert _image_error_px(halved.rvec, halved.tvec) < 0.2


#: A joint fit's settings (the chain's: 12 iterations, the first coarse, the partner only predicted).
JOINT = SparseSettings(iterations=12, coarse_iterations=1, other_sigma_px=10.0, max_partner_px=30.0, esm_partner=True)


def _iterations_of(
    monkeypatch: pytest.MonkeyPatch, pair: Pair, edges: MapEdges, start: tuple[F64, F64], settings: SparseSettings
) -> tuple[SparseResult | None, str, int]:
    """The fit, and how many Gauss-Newton steps it took: its pose updates, counted in ``fit_sparse``'s Python loop
    (the compiled one, which the chain's fits take, gives the same outcome: checked here, and the same poses to 1e-7
    in tests/test_sparseloop.py)."""
    count = [0]
    update = sparse._update

    def counted(st: object, sol: F64) -> None:
        count[0] += 1
        update(st, sol)  # type: ignore[arg-type]

    with monkeypatch.context() as patch:
        patch.setattr(sparse, "_update", counted)
        patch.setattr(kernels, "sparse_iterate_compiled", lambda: False)
        result, why = _fit(pair, edges, start, settings)
    compiled, compiled_why = _fit(pair, edges, start, settings)
    assert compiled_why == why
    assert (compiled is None) == (result is None)
    return result, why, count[0]


def test_a_joint_fit_whose_steps_stay_large_gives_up_early(
    pinhole_pair: Pair, edges: MapEdges, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Started 12 px off, a joint fit's steps grow (4–6 px a sample from its 7th on): it gives up after its 9th
    instead of running all 12 to be refused unsettled."""
    start = _guess_off_by(12.0)
    joint = replace(JOINT, lit_only=False)
    result, why, steps = _iterations_of(monkeypatch, pinhole_pair, edges, start, replace(joint, give_up_px=0.0))
    assert (result, why, steps) == (None, "not_converged", 12)
    result, why, steps = _iterations_of(monkeypatch, pinhole_pair, edges, start, joint)
    assert (result, why) == (None, "gave_up")
    assert steps == JOINT.give_up_from == 9


def test_a_good_start_is_fitted_as_without_giving_up(
    pinhole_pair: Pair, edges: MapEdges, monkeypatch: pytest.MonkeyPatch
) -> None:
    start = _guess_off_by(3.0)
    never, why, steps_never = _iterations_of(monkeypatch, pinhole_pair, edges, start, replace(JOINT, give_up_px=0.0))
    assert never is not None, why
    given, why, steps = _iterations_of(monkeypatch, pinhole_pair, edges, start, JOINT)
    assert given is not None, why
    assert steps == steps_never
    assert given.rvec.tobytes() == never.rvec.tobytes()
    assert given.tvec.tobytes() == never.tvec.tobytes()
    assert _image_error_px(given.rvec, given.tvec) < 0.2


def test_a_step_that_swings_back_is_shortened_to_the_swings_limit() -> None:
    """Steps that swing about the answer (each turning back a share q of the last) are scaled to where the
    swinging sequence ends, 1 / (1 + q) of the way; a step along the last one, or the first, is kept."""
    idx = np.arange(4)
    keep = np.ones(4, np.bool_)
    last = np.full(4, np.nan)
    sol = np.arange(16, dtype=np.float64)
    push = np.array([1.0, -2.0, 0.5, 1.5])
    assert np.array_equal(sparse.damped(sol, push, last, idx, keep), sol)  # the first step
    assert np.array_equal(last, push)
    swung = sparse.damped(sol, -0.6 * push, last, idx, keep)
    assert np.allclose(swung, sol / 1.6)
    assert np.allclose(last, -0.6 * push)
    assert np.array_equal(sparse.damped(sol, -0.3 * push, last, idx, keep), sol)  # along the last one
    far = sparse.damped(sol, 2.0 * push, last, idx, keep)  # takes back more than the whole last step
    assert np.allclose(far, sol / 2.0)
    unread = np.full(4, np.nan)
    unread[2] = 1.0  # the only sample read last time is not kept now
    keep2 = np.array([True, True, False, True])
    assert np.array_equal(sparse.damped(sol, -push, unread, idx, keep2), sol)


def test_damping_the_swings_settles_a_guess_sooner(pinhole_pair: Pair, edges: MapEdges) -> None:
    """The known-partner fit as the chain runs it (steps that swing back damped) against the same fit undamped,
    from guesses 2-4 px off: fewer iterations in all, each as close to the true pose."""
    known, _ = sparsechain.chain_settings(SIZE[0])
    assert known.damp_swings
    iterations = {}
    for damp in (False, True):
        total = 0
        for px in (2.0, 3.0, 4.0):
            # (the damping alone: without the RMS rule, which ends both at once on these noiseless frames)
            settings = replace(known, damp_swings=damp, converged_rms_px=0.0)
            result, why = _fit(pinhole_pair, edges, _guess_off_by(px), settings)
            assert result is not None, why
            assert _image_error_px(result.rvec, result.tvec) < 0.15
            total += result.iterations
        iterations[damp] = total
    assert iterations[True] < iterations[False]


def test_a_joint_fit_damps_its_swings_from_its_third_step(
    pinhole_pair: Pair, edges: MapEdges, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The chain's joint fits damp steps that swing back from their third step on (the first two, the coarse step and
    the first fine one at another reach, are the long way from the prediction): from starts 2-5 px off, the same first
    two steps as undamped, to the bit, then fewer steps in all, each fit as close to the true pose."""
    _, joint = sparsechain.chain_settings(SIZE[0])
    assert joint.damp_swings
    assert joint.damp_from == 2
    totals, first_two = {}, {}
    update = sparse._update
    for damp in (False, True):
        settings = replace(joint, damp_swings=damp)
        total = 0
        for px in (2.0, 3.0, 5.0):
            steps: list[bytes] = []

            def recorded(st: object, sol: F64, steps: list[bytes] = steps) -> None:
                steps.append(np.asarray(sol).tobytes())
                update(st, sol)  # type: ignore[arg-type]

            with monkeypatch.context() as patch:
                patch.setattr(sparse, "_update", recorded)
                patch.setattr(kernels, "sparse_iterate_compiled", lambda: False)  # (the Python loop: its steps seen)
                result, why = _fit(pinhole_pair, edges, _guess_off_by(px), settings)
            assert result is not None, why
            assert _image_error_px(result.rvec, result.tvec) < 0.2
            if damp:
                assert steps[:2] == first_two[px]
            else:
                first_two[px] = steps[:2]
            total += len(steps)
        totals[damp] = total
    assert totals[True] < totals[False]  # (16 steps undamped, 12 damped)


def test_a_fit_whose_step_is_small_on_average_stops_there(
    pinhole_pair: Pair, edges: MapEdges, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The known-partner fit as the chain runs it stops once a step moved the samples by less than
    ``converged_rms_px`` RMS, before its largest move falls below ``converged_px`` (on a camera's noise, 2 levels,
    the largest of a few hundred samples' moves is several times their RMS): fewer steps from guesses 2-4 px off,
    each pose as close to the true one; without the RMS rule it runs on."""
    rng = np.random.default_rng(7)

    def noisy(img: U8) -> U8:
        return np.clip(img + rng.normal(0.0, 2.0, img.shape), 0, 255).round().astype(np.uint8)

    pinhole_pair = Pair(noisy(pinhole_pair.image), noisy(pinhole_pair.other), pinhole_pair.camera)
    known, joint = sparsechain.chain_settings(SIZE[0])
    assert known.converged_rms_px > 0.0
    assert joint.converged_rms_px == 0.0
    steps = {}
    for rms_px in (0.0, known.converged_rms_px):
        total = 0
        for px in (2.0, 3.0, 4.0):
            result, why, n = _iterations_of(
                monkeypatch,
                pinhole_pair,
                edges,
                _guess_off_by(px),
                replace(known, converged_rms_px=rms_px, lit_only=False),
            )
            assert result is not None, why
            assert _image_error_px(result.rvec, result.tvec) < 0.15
            mm, _ = _errors(result.rvec, result.tvec)
            assert mm < 1.0
            total += n
        steps[rms_px] = total
    assert steps[known.converged_rms_px] < steps[0.0]


def test_the_rms_rule_never_ends_a_fit_whose_largest_move_is_unsettled() -> None:
    s = SparseSettings(converged_rms_px=0.1, settled_px=0.6)
    small = np.full(100, 0.01)
    assert sparse.converged_by_rms(small, 0.01, s)
    spike = small.copy()
    spike[0] = 0.7  # RMS 0.07 px, but one sample moved beyond the settled mark
    assert not sparse.converged_by_rms(spike, 0.7, s)
    assert not sparse.converged_by_rms(np.full(100, 0.2), 0.2, s)
    assert not sparse.converged_by_rms(small, 0.01, SparseSettings())  # off by default


def test_a_fit_that_sees_fewer_tags_carries_a_larger_covariance(pinhole_pair: Pair, edges: MapEdges) -> None:
    """The same pair fitted on every tag in view and on the three nearest the view's middle alone: fewer edge
    samples constrain the pose less, and the pose's standard deviation says so (both fits still near the truth)."""
    known, _ = sparsechain.chain_settings(SIZE[0])
    nearest = np.argsort(np.linalg.norm(edges.tag_centres_m[:, :2] - POSITION_M[:2], axis=1))[:3]
    mask = np.isin(edges.tag, nearest)
    few = replace(
        edges,
        points_m=edges.points_m[mask],
        normals_m=edges.normals_m[mask],
        step=edges.step[mask],
        tag=edges.tag[mask],
    )
    stds = []
    for which in (edges, few):
        result, why = _fit(pinhole_pair, which, _guess_off_by(1.0), known)
        assert result is not None, why
        assert _image_error_px(result.rvec, result.tvec) < 0.3
        stds.append(float(np.linalg.norm(result.estimate().position_std_m)))
        tags = len(result.tags)
    assert tags == 3
    assert stds[1] > 1.5 * stds[0]


def _pair_at(height_m: float) -> tuple[Pair, tuple[F64, F64], tuple[F64, F64]]:
    """The pinhole pair seen from ``height_m``, with the two frames' true poses."""
    position = np.array([POSITION_M[0], POSITION_M[1], height_m])
    other_position = position + (OTHER_POSITION_M - POSITION_M)
    return _pair(np.zeros(5), position), rt_of(position, R_ARENA_CAM), rt_of(other_position, R_OTHER)


def test_a_joint_fit_over_cells_a_few_pixels_wide_fails_even_from_the_truth(edges: MapEdges) -> None:
    # The chain's joint fits reach ±6 px (at 640 across) and smooth their first iteration: over the map's 23 mm
    # cells seen from 2.5 m (4.1 px) a profile crosses three edges where the fit models one. From 2.0 m (5.2 px)
    # the same fit finds the pose. This is what the chain's rule (sparsechain.JOINT_MIN_CELL_RADII) skips. (Undamped:
    # with its swings damped from the third step, as the chain's joint fits are since stop 56, the fit from the truth
    # holds at 2.5 m too, but on hover-2.5m without the rule 188 of 299 joint fits still gave up: the rule stays.)
    _known, joint = sparsechain.chain_settings(SIZE[0])
    undamped = replace(joint, damp_swings=False)
    for height_m, fits in ((2.5, False), (2.0, True)):
        pair, truth, other_truth = _pair_at(height_m)
        result, why = fit_sparse(pair.image, pair.other, pair.camera, edges, other_truth, truth, undamped, 0.0)
        assert (result is not None) == fits, (height_m, why)
        cells = sparsechain.cell_px(pair.camera, edges.largest_cell_m, truth)
        assert (cells >= sparsechain.JOINT_MIN_CELL_RADII * joint.radius_px) == fits, cells


def test_the_chain_tries_no_joint_fit_where_the_maps_cells_are_too_small(
    edges: MapEdges, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[bool] = []
    real = sparsechain.fit_sparse

    def counted(*args: object) -> tuple[SparseResult | None, str]:
        calls.append(True)
        return real(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(sparsechain, "fit_sparse", counted)
    fit = sparsechain.fitter(SparseCamera.of(K, np.zeros(5), SIZE), edges, *sparsechain.chain_settings(SIZE[0]))
    high, high_other = rt_of(np.array([0.07, -0.12, 2.5]), R_ARENA_CAM), rt_of(np.array([0.07, -0.12, 2.5]), R_OTHER)
    blank = np.full((SIZE[1], SIZE[0]), 128, np.uint8)
    assert fit(blank, blank, high_other, high, 0.0, True) == (None, "small_cells")
    assert calls == []  # refused before any profile was read
    fit(blank, blank, high_other, high, 0.0, False)  # a known partner's fit reaches ±4 px: it is tried
    assert calls == [True]
    low, low_other = rt_of(POSITION_M, R_ARENA_CAM), rt_of(OTHER_POSITION_M, R_OTHER)
    _result, why = fit(blank, blank, low_other, low, 0.0, True)
    assert calls == [True, True]
    assert why != "small_cells"


def test_the_samples_of_the_tags_in_view_are_picked_by_their_ranges_as_by_a_look_at_each(edges: MapEdges) -> None:
    """:func:`~ipt.receiver.core.sparse.select` joins the ranges of the near tags' samples (they lie tag by tag): the
    same indices as its look at every sample's tag (taken where the samples are not in tag order), over many views."""
    assert edges.tag_ranges is not None
    looking = replace(edges)
    looking.__dict__["tag_ranges"] = None  # (the cached ranges set aside: select looks at every sample)
    camera = SparseCamera.of(K, np.zeros(5), SIZE)
    rng = np.random.default_rng(29)
    sizes = set()
    for _ in range(300):
        position = np.array([rng.uniform(-0.5, 2.5), rng.uniform(-0.5, 1.5), rng.uniform(0.3, 2.5)])
        turn = rot_z(rng.uniform(-np.pi, np.pi)) @ rot_x(rng.uniform(-0.3, 0.3)) @ R_BODY_CAM_DOWNWARD
        rvec, t = rt_of(position, turn)
        r = np.asarray(cv2.Rodrigues(rvec.reshape(3, 1))[0], np.float64)
        for most in (700, 10**6):
            joined, looked = sparse.select(edges, camera, r, t, most), sparse.select(looking, camera, r, t, most)
            assert joined.dtype == looked.dtype
            assert np.array_equal(joined, looked)
            sizes.add(len(joined))
    assert 0 in sizes
    assert 700 in sizes
    assert len(sizes) > 20  # (views of no tag, of many, and between)
    assert replace(edges, tag=edges.tag[::-1].copy()).tag_ranges is None
