"""The bridge across a content change (ipt.receiver.core.bridge): a frame exposed while the video changed has its
tags back from the frames before and after it, where either pair alone shows only the content."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from ipt.receiver.core.bridge import bridge_difference
from ipt.receiver.core.demodulator import pair_difference

H, W = 180, 320
F32 = npt.NDArray[np.float32]


def _texture(seed: int) -> F32:
    """Grass-like content: fine random texture, 8-bit range, a few pixels of grain."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, 1.0, (H + 40, W + 40)).astype(np.float32)
    grain = cv2.GaussianBlur(noise, (0, 0), 1.5)
    return np.asarray(110 + 40 * grain / grain.std(), np.float32)


def _tags() -> F32:
    """A blocky ±1 pattern in cells of 12 px: the hidden map's cells."""
    rng = np.random.default_rng(7)
    cells = rng.choice([-1.0, 1.0], size=(H // 12 + 1, W // 12 + 1)).astype(np.float32)
    return np.asarray(np.kron(cells, np.ones((12, 12), np.float32))[:H, :W], np.float32)


def _shift(img: F32, dx: float, dy: float) -> F32:
    """``img`` seen by a camera moved by (dx, dy) pixels, cropped to the frame."""
    m = np.array([[1.0, 0.0, -dx - 20], [0.0, 1.0, -dy - 20]])
    return np.asarray(cv2.warpAffine(img, m, (W, H), flags=cv2.INTER_LINEAR), np.float32)


def _u8(img: F32) -> npt.NDArray[np.uint8]:
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _linear(l8: F32) -> F32:
    """Linear light (relative luminance, 0..1) of 8-bit CIELAB L, by the CIE's formula."""
    lstar = np.clip(l8, 0, 255) * 100 / 255
    return np.asarray(np.where(lstar > 8, ((lstar + 16) / 116) ** 3, lstar / (24389 / 27)), np.float32)


def _exposed(*parts: tuple[float, F32]) -> npt.NDArray[np.uint8]:
    """What the camera records (8-bit L) when its exposure is split between pictures (share, 8-bit L): it adds
    their light."""
    y = sum(share * _linear(img) for share, img in parts)
    lstar = np.where(y > 216 / 24389, 116 * np.cbrt(y) - 16, y * 24389 / 27)
    return _u8(np.asarray(lstar * 2.55, np.float32))


def _translation(dx: float, dy: float) -> npt.NDArray[np.float64]:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])


def test_a_frame_across_a_content_change_gets_its_tags_from_the_frames_around_it() -> None:
    old, new = _texture(1), _texture(2)
    tags = 3.0 * np.pad(_tags(), 20)  # the ±ΔL pattern on the floor, in floor pixels
    # The camera drifts 1.5 px a frame to the right; the frame between was exposed 65 % on the old video
    # in the − phase and 35 % on the new in the + phase; the frames around it one phase each.
    before = _shift(old + tags, -3.0, 0.0)
    target = _exposed((0.65, _shift(old - tags, 0.0, 0.0)), (0.35, _shift(new + tags, 0.0, 0.0)))
    after = _shift(new - tags, 3.0, 0.0)
    truth_tags = _shift(tags, 0.0, 0.0)
    lit = np.full((H, W), 255, np.uint8)
    # The warps a prediction gives, 2 px off the truth in opposite directions (a vibrating camera).
    warps = (_translation(-3.0 + 2.0, 0.0), _translation(3.0, 2.0))
    bridged = bridge_difference(_u8(before), target, _u8(after), warps, (lit, lit, lit))
    assert bridged is not None
    plain = pair_difference(_u8(before), target, _translation(-3.0, 0.0), lit, lit)

    def agreement(diff: F32) -> float:
        inner = (slice(20, H - 20), slice(20, W - 20))
        return float(abs(np.corrcoef(diff[inner].ravel(), truth_tags[inner].ravel())[0, 1]))

    # The tags, whatever their sign (each weighted by the slope of lightness where it lies: the camera adds
    # light). A mix of the frames' lightness instead of their light leaves the content's edges: 0.33.
    assert agreement(bridged.diff) > 0.6
    assert agreement(plain.diff) < 0.3  # a pair alone: the content's change drowns them


def test_a_frame_no_mix_of_its_neighbours_explains_is_refused() -> None:
    lit = np.full((H, W), 255, np.uint8)
    before, after = _u8(_shift(_texture(1), 0, 0)), _u8(_shift(_texture(2), 0, 0))
    unrelated = _u8(_shift(_texture(3), 0, 0))
    assert bridge_difference(before, unrelated, after, (np.eye(3), np.eye(3)), (lit, lit, lit)) is None
    dark = np.zeros((H, W), np.uint8)
    assert bridge_difference(before, unrelated, after, (np.eye(3), np.eye(3)), (lit, dark, lit)) is None


def test_which_neighbours_keep_the_tags_of_a_frame_across_a_content_change() -> None:
    # 32.5 % of the frame's exposure before the flip (old video, - phase), the rest after (new video, +).
    # Its neighbours one frame away lie inside those projector frames; two frames away they straddle the
    # flips before and after it with the same shares (see ipt.receiver.core.bridge).
    alpha, old, new = 0.325, _texture(1), _texture(2)
    tags = 3.0 * np.pad(_tags(), 20)
    still = (0.0, 0.0)

    def seen(content: F32, before_flip: float, after_flip: float) -> npt.NDArray[np.uint8]:
        """A frame of ``content`` whose exposure spans a flip of the phase from ``before_flip`` to
        ``after_flip`` (the same on both sides: inside one projector frame)."""
        first, second = _shift(content + before_flip * tags, *still), _shift(content + after_flip * tags, *still)
        return _exposed((alpha, first), (1 - alpha, second))

    target = _exposed((alpha, _shift(old - tags, *still)), (1 - alpha, _shift(new + tags, *still)))
    two_before, one_before = seen(old, 1.0, -1.0), seen(old, -1.0, -1.0)
    one_after, two_after, three_after = seen(new, 1.0, 1.0), seen(new, 1.0, -1.0), seen(new, -1.0, -1.0)
    truth_tags = _shift(tags, *still)
    lit = np.full((H, W), 255, np.uint8)
    flat = (np.eye(3), np.eye(3))

    def tags_left(before: npt.NDArray[np.uint8], after: npt.NDArray[np.uint8]) -> float:
        """The amplitude of the tags in the bridged difference, in units of one phase's ±ΔL."""
        bridged = bridge_difference(before, target, after, flat, (lit, lit, lit))
        assert bridged is not None
        inner = (slice(20, H - 20), slice(20, W - 20))
        d, t = bridged.diff[inner].ravel(), truth_tags[inner].ravel()
        return abs(float(np.cov(d, t)[0, 1] / np.var(t)))

    # (A pair of opposite phases has 2.) The shares are those of the frames' lightness; the camera adds their
    # light, so a tag counts by the slope of lightness where it lies: on this texture about nine tenths.
    assert tags_left(one_before, one_after) < 0.05  # 0: any mix that explains the content cancels them
    assert tags_left(two_before, one_after) == pytest.approx(2 * alpha**2, rel=0.15)  # 0.21
    assert tags_left(two_before, two_after) == pytest.approx(abs(2 - 4 * alpha), rel=0.15)  # 0.70
    assert tags_left(one_before, three_after) == pytest.approx(2 - 2 * alpha, rel=0.15)  # 1.35: the same phase
