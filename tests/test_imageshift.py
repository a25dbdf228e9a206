"""The image's shift between frames of one projector field and the chain's predictions turned by it
(ipt/receiver/core/imageshift.py), on views of a modulated floor rendered from known poses."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from floorview import render_view

from ipt.config.models import ArenaConfig
from ipt.geometry import R_BODY_CAM_DOWNWARD, rot_x, rot_y, rot_z
from ipt.receiver.core import imageshift, sparsechain
from ipt.receiver.core.demodulator import lightness
from ipt.receiver.core.imageshift import ImageShifts
from ipt.receiver.core.pose import rt_of
from ipt.sender.modulator import PaperModulator
from ipt.tagmap import grid_tag_map

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]

ARENA = ArenaConfig()
SIZE = (640, 360)
K = np.array([[450.0, 0.0, 319.5], [0.0, 450.0, 179.5], [0.0, 0.0, 1.0]])
POSITION_M = np.array([0.07, -0.12, 0.8])
R_ARENA_CAM = rot_z(np.deg2rad(11.0)) @ rot_x(np.deg2rad(2.0)) @ R_BODY_CAM_DOWNWARD


@pytest.fixture(scope="module")
def phases() -> tuple[U8, U8]:
    """One video frame (a photograph-like texture) in its + and − phase, projector pixels."""
    rng = np.random.default_rng(5)
    coarse = rng.integers(40, 216, (ARENA.projector.height_px // 8, ARENA.projector.width_px // 8, 3), np.uint8)
    size = (ARENA.projector.width_px, ARENA.projector.height_px)
    content = np.asarray(cv2.resize(coarse, size, interpolation=cv2.INTER_CUBIC), np.uint8)
    modulator = PaperModulator(grid_tag_map(ARENA).render_mask(), ARENA.modulation.delta_l)
    plus, minus = modulator.modulate(content, 0, 2)
    return plus, minus


def _view(img: U8, position_m: F64, r_arena_cam: F64) -> U8:
    return lightness(render_view(img, ARENA, K, position_m, r_arena_cam, SIZE))


def _centre_moves_px(position_a: F64, r_a: F64, position_b: F64, r_b: F64, k: F64 = K) -> F64:
    """Where the floor point on camera a's optical axis is seen by camera b (``k``), less the principal point."""
    axis = r_a[:, 2]
    floor = position_a + axis * (-position_a[2] / axis[2])
    seen, _ = cv2.projectPoints(floor.reshape(1, 3), *rt_of(position_b, r_b), k, None)
    return np.asarray(seen.reshape(2) - k[:2, 2], np.float64)


def test_the_shift_between_two_frames_of_one_phase_is_the_cameras_move(phases: tuple[U8, U8]) -> None:
    plus, minus = phases
    turned = rot_y(np.deg2rad(0.4)) @ rot_x(np.deg2rad(-0.25)) @ R_ARENA_CAM
    moved = POSITION_M + np.array([0.003, -0.002, 0.001])
    shifts = ImageShifts(K)
    shifts.add(10, _view(plus, POSITION_M, R_ARENA_CAM), 1)
    shifts.add(11, _view(plus, moved, turned), 1)
    truth = _centre_moves_px(POSITION_M, R_ARENA_CAM, moved, turned)
    assert float(np.linalg.norm(truth)) > 3.0  # (a move worth measuring)
    assert float(np.linalg.norm(shifts.shift_px[10] - truth)) < 0.3, (shifts.shift_px[10], truth)
    # Across a phase change (the floor's lightness flips along the map's edges) nothing is measured.
    shifts.add(12, _view(minus, moved, turned), -1)
    assert 11 not in shifts.shift_px
    # A frame whose phase is not known, or one after a skipped frame, is not measured either.
    shifts.add(13, _view(minus, moved, turned), None)
    shifts.add(15, _view(minus, moved, turned), -1)
    shifts.add(16, _view(minus, moved, turned), -1)
    assert set(shifts.shift_px) == {10, 15}
    assert float(np.linalg.norm(shifts.shift_px[15])) < 0.05  # the same view twice
    shifts.forget(12)
    assert set(shifts.shift_px) == {15}
    shifts.clear()
    assert not shifts.shift_px


def test_a_narrow_cameras_frames_are_measured_as_they_are_even_read_bottom_up(phases: tuple[U8, U8]) -> None:
    plus, _ = phases
    half_k = K.copy()
    half_k[:2] /= 2
    size = (SIZE[0] // 2, SIZE[1] // 2)
    turned = rot_y(np.deg2rad(0.5)) @ R_ARENA_CAM
    first = lightness(render_view(plus, ARENA, half_k, POSITION_M, R_ARENA_CAM, size))
    second = lightness(render_view(plus, ARENA, half_k, POSITION_M, turned, size))
    shifts = ImageShifts(half_k)
    backwards = [np.flipud(np.ascontiguousarray(np.flipud(view))) for view in (first, second)]
    assert backwards[0].strides[0] < 0  # (views whose rows run backwards in memory, the frames they show)
    shifts.add(0, backwards[0], 1)
    shifts.add(1, backwards[1], 1)
    truth = _centre_moves_px(POSITION_M, R_ARENA_CAM, POSITION_M, turned, half_k)
    assert float(np.linalg.norm(truth)) > 1.5
    assert float(np.linalg.norm(shifts.shift_px[0] - truth)) < 0.3, (shifts.shift_px[0], truth)


def test_an_unmeasured_shift_takes_the_mean_of_its_measured_neighbours() -> None:
    shifts = ImageShifts(K)
    shifts.shift_px.update({3: np.array([1.0, 2.0]), 5: np.array([3.0, -2.0])})
    assert np.allclose(_shift(shifts, 3, 6), [1.0 + 2.0 + 3.0, 2.0 + 0.0 - 2.0])  # interval 4 bridged
    assert np.allclose(_shift(shifts, 4, 5), [1.0, 2.0])  # only 3 measured by then: 5 is past the predicted frame
    assert shifts.between(10, 12) is None
    assert np.allclose(_shift(shifts, 5, 5), [0.0, 0.0])


def _shift(shifts: ImageShifts, b: int, k: int) -> F64:
    found = shifts.between(b, k)
    assert found is not None
    return found


def test_a_prediction_turned_puts_the_floor_where_the_image_moved() -> None:
    shifts = ImageShifts(K)
    newest = rt_of(POSITION_M, R_ARENA_CAM)
    predicted = rt_of(POSITION_M + np.array([0.004, 0.001, 0.0]), rot_x(np.deg2rad(0.2)) @ R_ARENA_CAM)
    wanted = np.array([2.5, -4.0])
    rvec, tvec = shifts.turned(predicted, newest, wanted)
    axis = R_ARENA_CAM[:, 2]
    floor = POSITION_M + axis * (-POSITION_M[2] / axis[2])
    seen, _ = cv2.projectPoints(floor.reshape(1, 3), rvec, tvec, K, None)
    assert np.allclose(seen.reshape(2) - K[:2, 2], wanted, atol=1e-6)
    # The camera stays where the prediction put it; only its attitude turns.
    r_turned, _ = cv2.Rodrigues(rvec)
    r_pred, _ = cv2.Rodrigues(predicted[0])
    assert np.allclose(-r_turned.T @ tvec, -r_pred.T @ predicted[1], atol=1e-12)
    # A turn beyond MAX_TURN_RAD (a shift measured wrongly) leaves the prediction as it was.
    far = np.array([K[0, 0] * imageshift.MAX_TURN_RAD * 1.5, 0.0])
    same = shifts.turned(predicted, newest, far)
    assert same[0] is predicted[0]
    assert same[1] is predicted[1]


def test_the_chains_prediction_is_turned_by_the_shifts_since_its_newest_pose() -> None:
    shifts = ImageShifts(K)
    chain = sparsechain.Chain(shifts=shifts)
    times_us = {k: 8333 * k for k in range(6)}
    chain.rt[2] = rt_of(POSITION_M, R_ARENA_CAM)
    chain.rt[3] = rt_of(POSITION_M + np.array([0.001, 0.0, 0.0]), R_ARENA_CAM)
    plain = sparsechain.predict(sparsechain.Chain(rt=dict(chain.rt)), 5, times_us)
    assert plain is not None
    unturned = sparsechain.predict(chain, 5, times_us)  # no shift measured: as the poses carry on
    assert unturned is not None
    assert all(np.array_equal(a, b) for a, b in zip(unturned, plain, strict=True))
    shifts.shift_px[3] = np.array([1.5, 0.5])
    shifts.shift_px[4] = np.array([1.5, 0.5])
    turned = sparsechain.predict(chain, 5, times_us)
    assert turned is not None
    expected = shifts.turned(plain, chain.rt[3], np.array([3.0, 1.0]))
    assert np.allclose(turned[0], expected[0])
    assert np.allclose(turned[1], expected[1])
    assert not np.allclose(turned[0], plain[0])
