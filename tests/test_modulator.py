"""Algorithm 1 (PaperModulator): phase signs, the lightness step on the tags, clipping, rates, resize, regions."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from ipt.config.models import ArenaConfig
from ipt.sender.modulator import ModulationError, PaperModulator, frames_per_input, phase_sign
from ipt.tagmap import grid_tag_map

U8 = npt.NDArray[np.uint8]

SMALL = ArenaConfig.model_validate(
    {
        "projector": {"width_px": 640, "height_px": 480},
        "screen": {"width_m": 1.0, "height_m": 0.75},
        "tag_map": {"rows": 3, "cols": 4, "tag_size_px": 64},
    }
)
DELTA_L = 4.0


@pytest.fixture(scope="module")
def mask() -> npt.NDArray[np.int8]:
    m = grid_tag_map(SMALL).render_mask()
    assert {-1, 0, 1} == set(np.unique(m).tolist())
    return m


def _random_frame(shape: tuple[int, int], lo: int = 40, hi: int = 215, seed: int = 0) -> U8:
    """Random RGB, kept away from the ends of the range so that ±ΔL stays inside the RGB gamut."""
    rng = np.random.default_rng(seed)
    return rng.integers(lo, hi + 1, (*shape, 3), dtype=np.uint8)


def _l(frame_rgb: U8) -> npt.NDArray[np.int16]:
    return cv2.cvtColor(frame_rgb, cv2.COLOR_RGB2Lab)[:, :, 0].astype(np.int16)


def test_phase_sign() -> None:
    assert [phase_sign(i) for i in range(6)] == [1, -1, 1, -1, 1, -1]
    assert phase_sign(1001) == -1
    assert phase_sign(1000) == 1


def test_frames_alternate_sign(mask: npt.NDArray[np.int8]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    frame = _random_frame(mask.shape)
    lab = mod.prepare(frame)
    plus, minus = mod.phase_frame(lab, +1), mod.phase_frame(lab, -1)
    out = mod.modulate(frame, 0, 4)
    assert len(out) == 4
    for i, f in enumerate(out):
        assert f.shape == (*mask.shape, 3)
        assert f.dtype == np.uint8
        assert np.array_equal(f, plus if i % 2 == 0 else minus), i
    odd_start = mod.modulate(frame, 3, 2)
    assert np.array_equal(odd_start[0], minus)
    assert np.array_equal(odd_start[1], plus)
    # Even index: brighter on white tag cells, darker on black ones.
    white, black = mask == 1, mask == -1
    l_plus, l_minus = _l(plus), _l(minus)
    assert l_plus[white].mean() > l_minus[white].mean() + 6
    assert l_plus[black].mean() < l_minus[black].mean() - 6


def test_lightness_step_per_mask_class(mask: npt.NDArray[np.int8]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    frame = _random_frame(mask.shape, seed=3)
    plus, minus = mod.modulate(frame, 0, 2)
    l_in, l_plus, l_minus = _l(frame), _l(plus), _l(minus)
    diff = l_plus - l_minus
    white, black, untouched = mask == 1, mask == -1, mask == 0
    two_dl = 2 * round(DELTA_L)
    assert abs(diff[white].mean() - two_dl) < 0.5
    assert abs(diff[black].mean() + two_dl) < 0.5
    # Most pixels within the 8-bit round-trip error of the exact step.
    assert np.mean(np.abs(diff[white] - two_dl) <= 2) > 0.99
    assert np.mean(np.abs(diff[black] + two_dl) <= 2) > 0.99
    # Untouched pixels are bit-identical in both phases, and within the Lab round trip of the input.
    assert np.array_equal(plus[untouched], minus[untouched])
    assert abs((l_plus - l_in)[untouched].mean()) < 0.5
    # Each phase moves L by ±ΔL relative to the input.
    assert abs((l_plus - l_in)[white].mean() - DELTA_L) < 0.5
    assert abs((l_minus - l_in)[white].mean() + DELTA_L) < 0.5
    assert abs((l_plus - l_in)[black].mean() + DELTA_L) < 0.5


@pytest.mark.parametrize("delta_l", [1.0, 2.6, 7.0])
def test_lightness_step_rounds_delta(mask: npt.NDArray[np.int8], delta_l: float) -> None:
    mod = PaperModulator(mask, delta_l)
    frame = _random_frame(mask.shape, lo=70, hi=180, seed=5)
    plus, minus = mod.modulate(frame, 0, 2)
    diff = _l(plus) - _l(minus)
    assert abs(diff[mask == 1].mean() - 2 * round(delta_l)) < 0.5


def test_prepared_lab_offsets_are_exact(mask: npt.NDArray[np.int8]) -> None:
    # phase_frame's own Lab result, seen through a Lab input whose RGB round trip is exact: a grey frame.
    mod = PaperModulator(mask, DELTA_L)
    grey = np.full((*mask.shape, 3), 128, np.uint8)
    lab = mod.prepare(grey)
    base_l = int(lab[0, 0, 0])
    plus = mod.phase_frame(lab, +1)
    l_plus = _l(plus)
    assert np.all(l_plus[mask == 0] == base_l)
    assert abs(float(np.median(l_plus[mask == 1])) - (base_l + 4)) <= 1
    assert abs(float(np.median(l_plus[mask == -1])) - (base_l - 4)) <= 1
    # Neutral stays neutral: only lightness changes.
    assert np.all(np.ptp(plus.astype(int), axis=2) <= 2)


def test_clipping_at_white(mask: npt.NDArray[np.int8]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    white_frame = np.full((*mask.shape, 3), 255, np.uint8)
    plus, minus = mod.modulate(white_frame, 0, 2)
    white, black = mask == 1, mask == -1
    # + phase cannot brighten white tag cells beyond 255: they stay exactly white.
    assert np.all(plus[white] == 255)
    assert np.all(plus[mask == 0] == 255)
    assert _l(plus)[black].max() < 255
    # - phase: white cells darker, black cells clipped at white.
    assert np.all(minus[black] == 255)
    assert _l(minus)[white].max() < 255
    assert abs(float(np.median(255 - _l(minus)[white])) - DELTA_L) <= 1


def test_clipping_at_black(mask: npt.NDArray[np.int8]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    black_frame = np.zeros((*mask.shape, 3), np.uint8)
    plus, minus = mod.modulate(black_frame, 0, 2)
    assert np.all(plus[mask == -1] == 0)
    assert np.all(minus[mask == 1] == 0)
    assert _l(plus)[mask == 1].min() > 0
    assert np.all(plus[mask == 0] == 0)


def test_frames_per_input() -> None:
    assert frames_per_input(30, 60) == 2
    assert frames_per_input(60, 60) == 1
    assert frames_per_input(15, 60) == 4
    assert frames_per_input(29.97, 59.94) == 2
    for fi, fo in [(24, 60), (60, 30), (25, 60), (40, 60)]:
        with pytest.raises(ModulationError, match="whole multiple"):
            frames_per_input(fi, fo)


def test_frames_per_input_ntsc_rates() -> None:
    assert frames_per_input(30000 / 1001, 60000 / 1001) == 2


def test_resize_of_different_size_input(mask: npt.NDArray[np.int8]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    small = _random_frame((120, 160), seed=9)
    lab = mod.prepare(small)
    assert lab.shape == (*mask.shape, 3)
    assert lab.dtype == np.uint8
    expected = cv2.cvtColor(cv2.resize(small, (640, 480), interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2Lab)
    assert np.array_equal(lab, expected)
    out = mod.modulate(small, 0, 2)
    assert all(f.shape == (480, 640, 3) for f in out)
    # A uniform input of another size and aspect stays uniform where the mask is 0.
    uniform = np.full((37, 91, 3), (90, 140, 60), np.uint8)
    plus = mod.modulate(uniform, 0, 1)[0]
    rest = plus[mask == 0]
    assert np.all(rest == rest[0])


def test_region_equals_crop(mask: npt.NDArray[np.int8]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    lab = mod.prepare(_random_frame(mask.shape, 0, 255, seed=11))
    for region in [(0, 0, 640, 480), (37, 51, 300, 222), (400, 300, 640, 480), (10, 10, 11, 12)]:
        x0, y0, x1, y1 = region
        for sign in (1, -1):
            full = mod.phase_frame(lab, sign)
            part = mod.phase_frame(lab[y0:y1, x0:x1], sign, region)
            assert part.shape == (y1 - y0, x1 - x0, 3)
            assert np.array_equal(part, full[y0:y1, x0:x1]), (region, sign)


def test_region_mismatch_raises(mask: npt.NDArray[np.int8]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    lab = mod.prepare(_random_frame(mask.shape))
    with pytest.raises(ModulationError, match="does not match"):
        mod.phase_frame(lab[:100, :100], 1, (0, 0, 100, 101))
    with pytest.raises(ModulationError, match="does not match"):
        mod.phase_frame(lab[:10, :10], 1)


@pytest.mark.parametrize("delta_l", [0.0, -1.0, 128.0])
def test_bad_delta_l(mask: npt.NDArray[np.int8], delta_l: float) -> None:
    with pytest.raises(ModulationError, match="ΔL"):
        PaperModulator(mask, delta_l)


@pytest.mark.parametrize(
    "frame",
    [
        np.zeros((480, 640), np.uint8),
        np.zeros((480, 640, 4), np.uint8),
        np.zeros((480, 640, 3), np.float32),
    ],
)
def test_bad_frames(mask: npt.NDArray[np.int8], frame: npt.NDArray[np.generic]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    with pytest.raises(ModulationError, match="uint8 RGB"):
        mod.modulate(frame, 0, 2)  # type: ignore[arg-type]


def test_input_frame_not_modified(mask: npt.NDArray[np.int8]) -> None:
    mod = PaperModulator(mask, DELTA_L)
    frame = _random_frame(mask.shape)
    copy = frame.copy()
    lab = mod.prepare(frame)
    lab_copy = lab.copy()
    mod.modulate(frame, 0, 2)
    mod.phase_frame(lab, 1)
    assert np.array_equal(frame, copy)
    assert np.array_equal(lab, lab_copy)


def test_paper_arena_modulates() -> None:
    # The full-size paper mask with its configured ΔL: the step is visible in the difference of phases.
    arena = ArenaConfig()
    m = grid_tag_map(arena).render_mask()
    mod = PaperModulator(m, arena.modulation.delta_l)
    frame = np.full((1080, 960, 3), 120, np.uint8)
    n = frames_per_input(arena.modulation.input_rate_hz, arena.projector.rate_hz)
    out = mod.modulate(frame, 0, n)
    assert len(out) == 2
    diff = _l(out[0]) - _l(out[1])
    assert abs(diff[m == 1].mean() - 8) < 0.5
    assert abs(diff[m == -1].mean() + 8) < 0.5
    assert np.all(diff[m == 0] == 0)
