"""The sparse chain's fit settings (ipt/receiver/core/sparsechain.py ``chain_settings``) on a pair rendered from known
poses (tests/test_sparse.py's): a partner whose pose, itself a fit, is off does not pass its error on."""

from __future__ import annotations

import numpy as np
import pytest
from test_sparse import OTHER_POSITION_M, R_OTHER, TAG_MAP, K, Pair, _guess_off_by, _image_error_px, _pair

from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.pose import rt_of
from ipt.receiver.core.sparse import fit_sparse
from ipt.receiver.core.sparsechain import chain_settings


@pytest.fixture(scope="module")
def noisy_pair() -> Pair:
    """The pinhole pair with camera noise (σ 4 levels: a dark scene's, against a map step of a few levels)."""
    pair = _pair(np.zeros(5))
    rng = np.random.default_rng(1)

    def noisy(img: np.ndarray) -> np.ndarray:  # type: ignore[type-arg]
        return np.clip(img + rng.normal(0.0, 4.0, img.shape), 0, 255).astype(np.uint8)

    return Pair(noisy(pair.image), noisy(pair.other), pair.camera)


@pytest.mark.parametrize("off_px", [2.0, 3.0])
def test_a_known_partner_s_pose_off_by_pixels_is_not_passed_on(noisy_pair: Pair, off_px: float) -> None:
    """The partner's pose given ``off_px`` off (the chain's previous fit, off by as much): this frame's pose within
    0.45 px (0.33, 0.39). (Held at 1 px as in the prototype: 0.79 px and 1.87 px off, the chain carried each
    fit's error on.)"""
    known, _ = chain_settings(640)
    shift_m = off_px * OTHER_POSITION_M[2] / K[0, 0]
    partner = rt_of(OTHER_POSITION_M + np.array([-0.6 * shift_m, 0.8 * shift_m, 0.0]), R_OTHER)
    edges = MapEdges.from_tag_map(TAG_MAP)
    result, why = fit_sparse(
        noisy_pair.image, noisy_pair.other, noisy_pair.camera, edges, partner, _guess_off_by(1.0), known
    )
    assert result is not None, why
    assert _image_error_px(result.rvec, result.tvec) < 0.45


@pytest.mark.parametrize("changed_share", [0.25, 0.4])
def test_a_pair_whose_content_changed_over_a_quarter_of_the_view_is_refused(changed_share: float) -> None:
    """The partner's content changed over the left ``changed_share`` of its view (a cut, a shadow's edge): the
    fit leaves those profiles out and is refused for keeping too few of its samples, so the frame takes the dense
    way. (With the prototype's 0.5 it was taken; on dark-scene such fits were 4.7 mm off at the median and passed
    it on along the chain.)"""
    pair = _pair(np.zeros(5))
    rng = np.random.default_rng(2)
    other = pair.other.copy()
    w = int(pair.other.shape[1] * changed_share)
    blocks = rng.integers(-60, 60, (pair.other.shape[0] // 8 + 1, w // 8 + 1)).repeat(8, 0).repeat(8, 1)
    other[:, :w] = np.clip(other[:, :w].astype(np.int64) + blocks[: other.shape[0], :w], 0, 255)
    known, _ = chain_settings(640)
    edges = MapEdges.from_tag_map(TAG_MAP)
    result, why = fit_sparse(
        pair.image, other, pair.camera, edges, rt_of(OTHER_POSITION_M, R_OTHER), _guess_off_by(1.0), known
    )
    assert result is None
    assert why == "inlier_fraction"


def test_with_a_rolling_shutter_a_pair_keeping_three_quarters_of_its_samples_is_taken() -> None:
    """The fit has no model of a rolling shutter's sweep, so a right fit keeps fewer of its samples: the rolling
    flight lost 2.6 points of yield at 0.8. With ``rolling_shutter`` the prototype's 0.5 stays, and the pair of
    the test above (a quarter of the partner's content changed) is fitted."""
    pair = _pair(np.zeros(5))
    rng = np.random.default_rng(2)
    other = pair.other.copy()
    w = pair.other.shape[1] // 4
    blocks = rng.integers(-60, 60, (pair.other.shape[0] // 8 + 1, w // 8 + 1)).repeat(8, 0).repeat(8, 1)
    other[:, :w] = np.clip(other[:, :w].astype(np.int64) + blocks[: other.shape[0], :w], 0, 255)
    known, _ = chain_settings(640, rolling_shutter=True)
    edges = MapEdges.from_tag_map(TAG_MAP)
    result, why = fit_sparse(
        pair.image, other, pair.camera, edges, rt_of(OTHER_POSITION_M, R_OTHER), _guess_off_by(1.0), known
    )
    assert result is not None, why
    assert _image_error_px(result.rvec, result.tvec) < 0.3
