"""The sparse chain's pair step (ipt/receiver/core/sparsechain.py ``pair_frame``) when its fits land far from the
prediction: refused alone, taken when a second partner's fit lands with the first (the prediction was off, not the
fits: ``corroborates``). The fits are stood in for by a function that lands each partner's fit where the test says,
so what is judged is the chain's rule, not the fit."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ipt.receiver.core.pose import pose_of, rt_of
from ipt.receiver.core.sparse import SparseResult
from ipt.receiver.core.sparsechain import (
    AGREE_M,
    MAX_CORROBORATED_M,
    MAX_JUMP_M,
    RT,
    Chain,
    FitResult,
    order_pairing,
    pair_frame,
)

DOWN = np.diag([1.0, -1.0, -1.0])
"""A camera looking straight down."""
HOVER_M = np.array([0.2, 0.1, 1.5])
PHASE = {4: -1, 5: -1, 6: 1, 7: 1, 8: -1}
"""Frames 4 and 5 posed (− phase), 6 and 7 (+) waiting for 8 (−): 8 is fitted jointly with 7, then with 6."""
TIMES_US = {k: k * 8333 for k in PHASE}
LUM = {k: np.full((4, 4), k, np.uint8) for k in PHASE}
"""Each frame's image carries its index, so the stand-in fit knows its partner."""


def _result(position_m: np.ndarray, partner_position_m: np.ndarray, sign: int) -> SparseResult:
    rvec, tvec = rt_of(position_m, DOWN)
    other_rvec, other_tvec = rt_of(partner_position_m, DOWN)
    return SparseResult(
        rvec, tvec, 500, 500, 1.0, sign, 4.0, 1.0, 5, (0,), other_rvec, other_tvec, np.eye(6), np.eye(6)
    )


def _run(
    landings_m: dict[int, np.ndarray], refine: bool = False, partner_apart_m: np.ndarray | None = None
) -> tuple[dict[int, SparseResult], Chain, list[int]]:
    """Frame 8's pair step from a hovering chain, each partner's fit landing ``landings_m[partner]`` from the hover
    (both frames of the pair moved alike, or the partner ``partner_apart_m`` further); the poses found, the chain and
    the partners fitted, in order."""
    chain = Chain()
    for k in (4, 5):
        chain.rt[k], chain.sign[k] = rt_of(HOVER_M, DOWN), PHASE[k]
    tried: list[int] = []

    def fit(image: np.ndarray, other: np.ndarray, other_rt: RT, guess: RT, hint: float, predicted: bool) -> FitResult:
        partner = int(other[0, 0])
        tried.append(partner)
        moved = landings_m[partner]
        apart = partner_apart_m if partner_apart_m is not None else np.zeros(3)
        return _result(HOVER_M + moved, HOVER_M + moved + apart, PHASE[int(image[0, 0])]), ""

    pairing = replace(order_pairing(PHASE), known_first=True, refine=refine)
    found = pair_frame(chain, 8, LUM, PHASE, TIMES_US, fit, pairing)
    return found, chain, tried


def _position(result: SparseResult) -> np.ndarray:
    position, _ = pose_of(result.rvec, result.tvec)
    return np.asarray(position)


def test_a_fit_near_the_prediction_is_taken_at_once() -> None:
    found, chain, tried = _run({7: np.array([0.005, 0.0, 0.0]), 6: np.array([0.0, 0.0, 0.0])})
    assert tried == [7]
    assert set(found) == {8, 7}
    assert chain.corroborated == 0


def test_far_fits_that_do_not_land_together_are_refused() -> None:
    """Two partners' fits both far from the prediction, 30 mm apart: neither is taken."""
    far = np.array([1.5 * MAX_JUMP_M, 0.0, 0.0])
    found, chain, tried = _run({7: far, 6: far + np.array([0.0, 3 * AGREE_M, 0.0])})
    assert tried == [7, 6]
    assert found == {}
    assert chain.refused["far_from_prediction"] == 2
    assert chain.corroborated == 0


@pytest.mark.parametrize("off_m", [1.2 * MAX_JUMP_M, 0.95 * MAX_CORROBORATED_M])
def test_two_partners_fits_landing_together_far_from_the_prediction_are_taken(off_m: float) -> None:
    """Takeoff's case: both joint fits of a frame 35-75 mm from a prediction the chain's last noisy pose threw
    off, within a few millimetres of each other (and of the truth)."""
    first = np.array([off_m, 0.0, -0.01])
    second = first + np.array([0.0, 0.6 * AGREE_M, 0.0])
    found, chain, tried = _run({7: first, 6: second})
    assert tried == [7, 6]
    assert set(found) == {8, 6}
    assert np.allclose(_position(found[8]), HOVER_M + second)
    assert np.allclose(_position(found[6]), HOVER_M + second)
    assert chain.corroborated == 1
    assert chain.refused["far_from_prediction"] == 2


def test_a_waiting_frame_refitted_after_a_corroborated_fit_starts_where_the_chain_s_error_puts_it() -> None:
    """Frame 7, still waiting once 8 and 6 are posed together, is refitted against 8 from its own prediction moved
    as far as 8's fit landed from 8's: its fit (landing with the others) is then near its start and taken. (Started
    from the prediction alone, it was refused as far: realcam's frame 176, whose three frames then went the dense
    way.)"""
    off = np.array([1.5 * MAX_JUMP_M, 0.0, -0.01])
    found, chain, tried = _run({7: off, 6: off, 8: off}, refine=True)
    assert tried == [7, 6, 8, 8]  # (both waiting frames refitted against 8: 6 from its joint pose, 7 moved)
    assert set(found) == {8, 7, 6}
    assert np.allclose(_position(found[7]), HOVER_M + off)
    assert chain.refused["far_from_prediction"] == 2


def test_two_far_fits_that_agree_too_far_from_the_prediction_are_refused() -> None:
    first = np.array([1.2 * MAX_CORROBORATED_M, 0.0, 0.0])
    found, chain, _ = _run({7: first, 6: first + np.array([0.0, 0.002, 0.0])})
    assert found == {}
    assert chain.corroborated == 0


def test_a_corroborated_fit_whose_partner_moved_otherwise_is_refused() -> None:
    """The partner's pose, predicted by the same chain, is judged net of the prediction's error: moved by as much
    as this frame, it passes (above); moved apart from it by more than the chain allows, it does not."""
    first = np.array([1.5 * MAX_JUMP_M, 0.0, 0.0])
    found, chain, _ = _run({7: first, 6: first}, partner_apart_m=np.array([0.0, 1.5 * MAX_JUMP_M, 0.0]))
    assert found == {}
    assert chain.refused["partner_far_from_prediction"] == 1
