"""The pose from the whole visible map (ipt/receiver/core/track.py) on frames warped from a known camera pose."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from floorview import render_view

from ipt.config.camera_info import CameraInfo
from ipt.config.models import ArenaConfig
from ipt.geometry import R_BODY_CAM_DOWNWARD, rot_x, rot_y, rot_z, rotation_angle_rad
from ipt.receiver.core.demodulator import PairDifference, lightness, pair_difference
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.pose import rt_of
from ipt.receiver.core.track import (
    MaskRenderer,
    TrackSettings,
    coarse_shift,
    shifted_pose,
    track_pose,
)
from ipt.sender.modulator import PaperModulator
from ipt.tagmap import arena_to_pixel_matrix, grid_tag_map, pixel_to_arena

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]

ARENA = ArenaConfig()
TAG_MAP = grid_tag_map(ARENA)
CAMERA = CameraInfo(width_px=640, height_px=360, fx_px=450.0, fy_px=450.0, cx_px=319.5, cy_px=179.5, name="test")
K = CAMERA.camera_matrix
POSITION_M = np.array([0.07, -0.12, 0.8])
R_ARENA_CAM = rot_z(np.deg2rad(11.0)) @ rot_x(np.deg2rad(2.0)) @ R_BODY_CAM_DOWNWARD


@dataclass(frozen=True)
class Pair:
    diff: PairDifference
    rvec: F64
    tvec: F64


def _render(img: U8, position_m: F64, r_arena_cam: F64) -> U8:
    return render_view(img, ARENA, K, position_m, r_arena_cam)


@pytest.fixture(scope="module")
def pair() -> Pair:
    """A pair of opposite phases seen from one pose, over busy content (the + phase is the later frame)."""
    rng = np.random.default_rng(3)
    coarse = rng.integers(40, 216, (ARENA.projector.height_px // 8, ARENA.projector.width_px // 8, 3), np.uint8)
    content = np.asarray(
        cv2.resize(coarse, (ARENA.projector.width_px, ARENA.projector.height_px), interpolation=cv2.INTER_CUBIC),
        np.uint8,
    )
    plus, minus = PaperModulator(TAG_MAP.render_mask(), ARENA.modulation.delta_l).modulate(content, 0, 2)
    later, earlier = (lightness(_render(p, POSITION_M, R_ARENA_CAM)) for p in (plus, minus))
    lit = np.full(later.shape, 255, np.uint8)
    diff = pair_difference(earlier, later, np.eye(3), lit, lit)
    return Pair(diff, *rt_of(POSITION_M, R_ARENA_CAM))


@pytest.fixture(scope="module")
def edges() -> MapEdges:
    return MapEdges.from_tag_map(TAG_MAP)


def _errors(rvec: F64, tvec: F64) -> tuple[float, float]:
    """(position error mm, rotation error deg) of OpenCV's (rvec, tvec) against the pair's pose."""
    r_cam, _ = cv2.Rodrigues(rvec.reshape(3, 1))
    position = -r_cam.T @ tvec
    return (
        1000 * float(np.linalg.norm(position - POSITION_M)),
        float(np.rad2deg(rotation_angle_rad(r_cam.T.T @ R_ARENA_CAM))),
    )


def _perturbed(pose_mm: float, tilt_deg: float, seed: int = 0) -> tuple[F64, F64]:
    direction = np.random.default_rng(seed).normal(size=3)
    r = rot_x(np.deg2rad(tilt_deg)) @ rot_y(np.deg2rad(-tilt_deg / 2)) @ R_ARENA_CAM
    return rt_of(POSITION_M + pose_mm / 1000 * direction / np.linalg.norm(direction), r)


def test_the_map_edges_are_where_the_mask_changes(edges: MapEdges) -> None:
    assert set(np.unique(np.abs(edges.step))) == {1.0, 2.0}
    assert np.allclose(np.linalg.norm(edges.normals_m, axis=1), 1.0)
    assert np.allclose(edges.points_m[:, 2], 0.0)
    # Every sample sits on a boundary: the mask differs on its two sides, by its step.
    to_px = arena_to_pixel_matrix(ARENA)
    mask = TAG_MAP.render_mask().astype(int)
    for i in np.random.default_rng(1).choice(len(edges.step), 300, replace=False):
        p, n = edges.points_m[i, :2], edges.normals_m[i, :2]
        a, b = (to_px @ np.array([*(p + s * 0.25 * edges.cell_m * n), 1.0]) for s in (-1, 1))
        before, after = mask[int(a[1]), int(a[0])], mask[int(b[1]), int(b[0])]
        assert after - before == edges.step[i]
    # Data cells only in the agreement check: 36 per tag.
    assert len(edges.cell_value) == 36 * len(TAG_MAP.tags)


def test_the_track_refines_a_close_guess_to_a_fraction_of_a_millimetre(pair: Pair, edges: MapEdges) -> None:
    start = _perturbed(4.0, 0.3)
    assert _errors(*start)[0] > 3.9
    result = track_pose(pair.diff.diff, K, edges, *start, TrackSettings(), None, pair.diff.valid)
    assert result is not None
    mm, deg = _errors(result.rvec, result.tvec)
    assert mm < 0.5
    assert deg < 0.05
    assert result.sign == 1  # the later frame was the + phase
    assert result.inlier_fraction > 0.6
    assert result.cell_agreement > 0.95
    assert len(result.tags) >= 6
    assert result.flipped_rows is None


def test_a_far_guess_is_brought_in_by_the_coarse_search(pair: Pair, edges: MapEdges) -> None:
    start = _perturbed(20.0, 1.5, seed=2)
    masks = MaskRenderer(TAG_MAP.render_mask(), pixel_to_arena(TAG_MAP))
    dx, dy, score = coarse_shift(pair.diff.diff, masks.render(K, *start, (640, 360)), pair.diff.valid)
    assert score > 0.2
    assert np.hypot(dx, dy) > 5
    moved = shifted_pose(K, *start, dx, dy, (640, 360))
    assert moved is not None
    result = track_pose(pair.diff.diff, K, edges, *moved, TrackSettings(), None, pair.diff.valid)
    assert result is not None
    mm, deg = _errors(result.rvec, result.tvec)
    assert mm < 0.5
    assert deg < 0.05


def test_a_pose_a_cell_off_does_not_pass_for_the_right_one(pair: Pair, edges: MapEdges) -> None:
    # Start exactly one cell sideways: the edges of the neighbouring cells are there to be found, but
    # the data cells then disagree with the map.
    cell = edges.cell_m
    r_cam, _ = cv2.Rodrigues(pair.rvec)
    off = rt_of(POSITION_M + r_cam.T @ np.array([cell, 0.0, 0.0]), R_ARENA_CAM)
    result = track_pose(pair.diff.diff, K, edges, *off, TrackSettings(search_px=2.0), None, pair.diff.valid)
    assert result is None or _errors(result.rvec, result.tvec)[0] < 1.0 or result.cell_agreement < 0.7


def test_half_the_view_in_shadow_still_gives_the_pose(pair: Pair, edges: MapEdges) -> None:
    diff = pair.diff.diff.copy()
    valid = pair.diff.valid.copy()
    yy, xx = np.mgrid[0:360, 0:640]
    shadow = (xx - 380) ** 2 + (yy - 200) ** 2 < 150**2  # a drone's shadow over the middle of the view
    diff[shadow] = np.random.default_rng(0).normal(0, 0.5, shadow.sum())  # noise only: no projector light
    valid[shadow] = 0
    result = track_pose(diff, K, edges, *_perturbed(4.0, 0.3), TrackSettings(), None, valid)
    assert result is not None
    mm, deg = _errors(result.rvec, result.tvec)
    assert mm < 1.0
    assert deg < 0.1


def test_a_rolling_shutter_flip_inside_the_frame_is_found_per_band(pair: Pair, edges: MapEdges) -> None:
    diff = pair.diff.diff.copy()
    diff[200:] *= -1  # the projector flipped while row 200 was being read
    result = track_pose(diff, K, edges, *_perturbed(4.0, 0.3), TrackSettings(), None, pair.diff.valid)
    assert result is not None
    assert result.flipped_rows is not None
    first, last = result.flipped_rows
    assert 150 <= first <= 260
    assert last == 359
    assert _errors(result.rvec, result.tvec)[0] < 1.0


def test_the_covariance_follows_the_fit(pair: Pair, edges: MapEdges) -> None:
    result = track_pose(pair.diff.diff, K, edges, *_perturbed(4.0, 0.3), TrackSettings(), None, pair.diff.valid)
    assert result is not None
    pose = result.estimate()
    assert np.allclose(pose.position_m, POSITION_M, atol=5e-4)
    assert np.all(np.linalg.eigvalsh(pose.position_cov_m2) > 0)
    assert np.all(np.linalg.eigvalsh(pose.attitude_cov_rad2) > 0)
    # Carry samples of the fit's (δ, Δt) through the pose by brute force: the same spread.
    rng = np.random.default_rng(5)
    r_cam, _ = cv2.Rodrigues(result.rvec)
    samples = rng.multivariate_normal(np.zeros(6), result.cov_rt, 4000)
    positions = []
    for s in samples:
        dr, _ = cv2.Rodrigues(s[:3].reshape(3, 1))
        r = dr @ r_cam
        positions.append(-r.T @ (result.tvec + s[3:]))
    empirical = np.cov(np.array(positions).T)
    assert np.allclose(np.diag(empirical), np.diag(pose.position_cov_m2), rtol=0.15)
    # A pose from the fit's edges is a few tenths of a millimetre certain, not a few centimetres.
    assert np.linalg.norm(pose.position_std_m) < 0.002


def test_no_map_in_view_gives_no_pose(pair: Pair, edges: MapEdges) -> None:
    flat = np.zeros_like(pair.diff.diff)
    assert track_pose(flat, K, edges, pair.rvec, pair.tvec, TrackSettings(), None, pair.diff.valid) is None
    away = rt_of(np.array([30.0, 30.0, 0.8]), R_ARENA_CAM)  # far off the arena: no tag near the view
    assert track_pose(pair.diff.diff, K, edges, *away, TrackSettings(), None, pair.diff.valid) is None


def test_compiled_kernels_agree_with_their_python_source() -> None:
    # The kernels run as plain Python where numba cannot compile: both must measure the same steps.
    from ipt.receiver.core import kernels as tk

    tk.ensure()
    if not tk.COMPILED:
        pytest.skip("numba cannot compile here: only the Python source runs")
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.normal(0, 4, (90, 160)).astype(np.float32), (0, 0), 2.0)
    valid = np.where(rng.random((90, 160)) < 0.9, 255, 0).astype(np.uint8)
    obj = np.column_stack([rng.uniform(-0.3, 0.3, 300), rng.uniform(-0.2, 0.2, 300), np.zeros(300)])
    angle = rng.uniform(0, np.pi, 300)
    nrm = np.column_stack([np.cos(angle), np.sin(angle), np.zeros(300)])
    sign = np.where(rng.random(300) < 0.5, -1.0, 1.0)
    r, _ = cv2.Rodrigues(np.array([0.05, -0.03, 0.4]))
    t = np.array([0.01, -0.02, 0.8])
    k = np.array([[105.0, 0.0, 80.0], [0.0, 105.0, 45.0], [0.0, 0.0, 1.0]])
    sweep = np.array([0.004, -0.006, 0.002, 0.003, -0.002, 0.001])  # a rolling shutter's pose change
    fast = tk.measure(obj, nrm, sign, r, t, k, image, valid, 4, 3.0, 6, sweep)
    slow = tk.measure.py_func(obj, nrm, sign, r, t, k, image, valid, 4, 3.0, 6, sweep)
    assert len(fast[0]) > 100  # most samples are measurable: the comparison means something
    for a, b in zip(fast, slow, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
    idx, raw, band, _, _ = fast
    signs = tk.band_signs(raw, band, 6)
    np.testing.assert_array_equal(signs, tk.band_signs.py_func(raw, band, 6))
    threshold = np.full(len(idx), 0.5)
    for a, b in zip(tk.peaks(raw, band, signs, threshold), tk.peaks.py_func(raw, band, signs, threshold), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    cells, tags = obj[:200], np.arange(200) % 4
    value = np.where(rng.random(200) < 0.5, -1.0, 1.0)
    on = np.array([True, False, True, True])
    args = (image, k, r, t, cells, tags, value, on, signs, valid)
    assert tk.cell_agreement(*args) == pytest.approx(tk.cell_agreement.py_func(*args))


def test_slope_noise_is_the_median_of_the_sampled_slopes() -> None:
    # The compiled kernel and its Python source give numpy's median of |diff[y, x+2] − diff[y, x]| (every
    # fourth row, every second column) where valid, or of all of them when nothing is valid.
    from ipt.receiver.core import kernels as tk
    from ipt.receiver.core.track import slope_noise

    rng = np.random.default_rng(5)
    for h, w in ((90, 160), (91, 161), (360, 640)):
        diff = rng.normal(0, 2, (h, w)).astype(np.float32)
        valid = np.where(rng.random((h, w)) < 0.6, 255, 0).astype(np.uint8)
        slopes = np.abs(np.diff(diff[::4, ::2], axis=1))
        inside = valid[::4, ::2][:, 1:] > 0
        assert slope_noise(diff, valid) == max(float(np.median(slopes[inside].astype(np.float64))), 1e-3)
        assert slope_noise(diff, None) == max(float(np.median(slopes.astype(np.float64))), 1e-3)
        assert slope_noise(diff, np.zeros((h, w), np.uint8)) == slope_noise(diff, None)
        np.testing.assert_array_equal(tk.slopes_sampled.py_func(diff, valid), tk.slopes_sampled(diff, valid))
    assert slope_noise(np.zeros((8, 8), np.float32), None) == 1e-3
