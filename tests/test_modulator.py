"""Modulation: the paper's Algorithm 1 (PaperModulator) and the ipt profile (IptModulator): phase signs, the
lightness step on the tags, clipping and balance, colour, rates and re-timing, resize, regions, detection."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from ipt.config.models import ArenaConfig
from ipt.sender.colour import (
    CODE_TO_LINEAR,
    L8_PER_LSTAR,
    LUMINANCE_WEIGHTS,
    code_to_lab,
    code_to_linear,
    linear_to_lab,
    lstar,
)
from ipt.sender.modulator import (
    FrameTiming,
    IptModulator,
    ModulationError,
    PaperModulator,
    amplitude_grid,
    delta_l_warning,
    frames_per_input,
    make_modulator,
    phase_sign,
)
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


# --- the ipt profile ---------------------------------------------------------------------------------------


def _lstar8(rgb: npt.NDArray[np.uint8]) -> npt.NDArray[np.float64]:
    """Exact L* of 8-bit sRGB, in 8-bit L units."""
    return lstar(code_to_linear(rgb) @ LUMINANCE_WEIGHTS) * L8_PER_LSTAR


def _half_step(codes: npt.NDArray[np.uint8]) -> npt.NDArray[np.float64]:
    """Half the larger linear-light step next to each code: what 8-bit quantisation of that code allows."""
    k = codes.astype(np.int64)
    up = CODE_TO_LINEAR[np.minimum(k + 1, 255)] - CODE_TO_LINEAR[k]
    down = CODE_TO_LINEAR[k] - CODE_TO_LINEAR[np.maximum(k - 1, 0)]
    out: npt.NDArray[np.float64] = np.maximum(up, down) / 2
    return out


def _all_kinds_of_colours(n: int = 60_000, seed: int = 0) -> U8:
    """Uniform random colours plus greys, primaries, and colours at or next to the ends of the range."""
    rng = np.random.default_rng(seed)
    random = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    grey = np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, axis=1)
    ends = rng.choice(np.array([0, 1, 2, 253, 254, 255], np.uint8), (2000, 3))
    mixed = ends.copy()
    mixed[:, 1] = rng.integers(0, 256, 2000)
    return np.concatenate([random, grey, ends, mixed])


@pytest.fixture(scope="module")
def ipt(mask: npt.NDArray[np.int8]) -> IptModulator:
    return IptModulator(mask, DELTA_L)


def test_ipt_is_the_default_profile() -> None:
    assert ArenaConfig().modulation.profile == "ipt"
    m = np.zeros((4, 4), np.int8)
    assert isinstance(make_modulator("ipt", m, 4.0), IptModulator)
    assert isinstance(make_modulator("paper", m, 4.0), PaperModulator)
    with pytest.raises(ModulationError, match="unknown modulation profile 'fancy'"):
        make_modulator("fancy", m, 4.0)


def test_ipt_leaves_non_tag_pixels_bit_identical(ipt: IptModulator, mask: npt.NDArray[np.int8]) -> None:
    frame = _random_frame(mask.shape, 0, 255, seed=21)
    plus, minus = ipt.phases(frame)
    off = mask == 0
    assert np.array_equal(plus[off], frame[off])
    assert np.array_equal(minus[off], frame[off])
    # ...and the tags do change.
    assert np.mean(np.any(plus[~off] != minus[~off], axis=1)) > 0.95


def test_ipt_phases_average_to_the_input_in_linear_light(ipt: IptModulator) -> None:
    codes = _all_kinds_of_colours()
    up, down = ipt.pair_codes(codes)
    fused = (code_to_linear(up) + code_to_linear(down)) / 2
    error = np.abs(fused - code_to_linear(codes))
    # Per channel within half a code step of the input: the input code's own quantisation.
    assert np.all(error <= _half_step(codes) + 1e-12)
    # As a colour difference of what the eye fuses, far below what can be seen.
    de = np.linalg.norm(linear_to_lab(fused) - code_to_lab(codes), axis=1)
    assert float(np.percentile(de, 99)) < 0.5
    # The + phase is the brighter one, channel by channel.
    assert np.all(up >= codes)
    assert np.all(down <= codes)


def test_ipt_step_is_two_delta_l_in_lightness(ipt: IptModulator) -> None:
    rng = np.random.default_rng(3)
    codes = rng.integers(30, 226, (20_000, 3), dtype=np.uint8)  # room for the step in every channel
    up, down = ipt.pair_codes(codes)
    diff = _lstar8(up) - _lstar8(down)
    assert abs(float(diff.mean()) - 2 * DELTA_L) < 0.2
    assert float(np.percentile(np.abs(diff - 2 * DELTA_L), 99)) < 1.0
    # Greys step evenly over the whole middle range.
    grey = np.repeat(np.arange(40, 230, dtype=np.uint8)[:, None], 3, axis=1)
    g_up, g_down = ipt.pair_codes(grey)
    assert np.all(np.abs(_lstar8(g_up) - _lstar8(g_down) - 2 * DELTA_L) < 1.0)


def test_ipt_holds_the_chromaticity_where_nothing_clips(ipt: IptModulator) -> None:
    rng = np.random.default_rng(4)
    codes = rng.integers(60, 200, (5000, 3), dtype=np.uint8)
    up, down = ipt.pair_codes(codes)
    lab_in, lab_up, lab_down = code_to_lab(codes), code_to_lab(up), code_to_lab(down)

    # a*, b* move with lightness only by what 8-bit codes and the lightness change itself imply: compare the
    # chromaticity (x, y) of linear RGB instead, which scaling RGB leaves unchanged.
    def xy(c: npt.NDArray[np.uint8]) -> npt.NDArray[np.float64]:
        lin = code_to_linear(c)
        return lin / lin.sum(axis=1, keepdims=True)

    assert float(np.abs(xy(up) - xy(codes)).max()) < 0.01
    assert float(np.abs(xy(down) - xy(codes)).max()) < 0.01
    assert float(np.abs(lab_up[:, 0] - lab_in[:, 0]).min()) > 0.5  # while lightness does change
    assert float(np.abs(lab_down[:, 0] - lab_in[:, 0]).min()) > 0.5


def test_ipt_clipping_rebalances_or_shrinks_the_pair(ipt: IptModulator) -> None:
    colours = np.array(
        [(255, 255, 255), (0, 0, 0), (255, 0, 0), (254, 254, 254), (1, 1, 1), (255, 216, 96), (38, 130, 255)],
        np.uint8,
    )
    up, down = ipt.pair_codes(colours)
    # Pure white, black and a pure primary cannot flicker around themselves: both phases are the input.
    for k in range(3):
        assert np.array_equal(up[k], colours[k])
        assert np.array_equal(down[k], colours[k])
    # Next to white and black the pair shrinks but stays balanced (checked above for all colours).
    assert 0 < _lstar8(up[3:4])[0] - _lstar8(down[3:4])[0] < 2 * DELTA_L
    assert 0 < _lstar8(up[4:5])[0] - _lstar8(down[4:5])[0] < 2 * DELTA_L
    # A channel at 255 stays there; the others make up the step.
    assert up[5, 0] == down[5, 0] == 255
    assert abs(_lstar8(up[5:6])[0] - _lstar8(down[5:6])[0] - 2 * DELTA_L) < 1.0
    assert up[6, 2] == down[6, 2] == 255
    assert abs(_lstar8(up[6:7])[0] - _lstar8(down[6:7])[0] - 2 * DELTA_L) < 1.0


def test_ipt_frames_follow_the_mask_and_phase(ipt: IptModulator, mask: npt.NDArray[np.int8]) -> None:
    frame = _random_frame(mask.shape, seed=5)
    plus, minus = ipt.phases(frame)
    white, black = mask == 1, mask == -1
    up, down = ipt.pair_codes(frame.reshape(-1, 3))
    up, down = up.reshape(frame.shape), down.reshape(frame.shape)
    assert np.array_equal(plus[white], up[white])
    assert np.array_equal(minus[white], down[white])
    assert np.array_equal(plus[black], down[black])
    assert np.array_equal(minus[black], up[black])
    out = ipt.modulate(frame, 1, 3)
    assert [np.array_equal(f, minus if i % 2 == 0 else plus) for i, f in enumerate(out)] == [True] * 3
    assert np.array_equal(ipt.phase_frame(frame, 1), plus)
    assert np.array_equal(ipt.phase_frame(frame, -1), minus)


def test_ipt_region_equals_crop(ipt: IptModulator, mask: npt.NDArray[np.int8]) -> None:
    frame = _random_frame(mask.shape, 0, 255, seed=11)
    plus, minus = ipt.phases(frame)
    for region in [(0, 0, 640, 480), (37, 51, 300, 222), (400, 300, 640, 480), (10, 10, 11, 12)]:
        x0, y0, x1, y1 = region
        crop = frame[y0:y1, x0:x1]
        assert np.array_equal(ipt.phase_region(crop, 1, region), plus[y0:y1, x0:x1])
        assert np.array_equal(ipt.phase_region(crop, -1, region), minus[y0:y1, x0:x1])
    with pytest.raises(ModulationError, match="does not match"):
        ipt.phase_region(frame[:10, :10], 1, (0, 0, 10, 11))
    with pytest.raises(ModulationError, match="not inside"):
        ipt.phase_region(frame[:10, :10], 1, (635, 0, 645, 10))


def test_ipt_buffers_threads_and_resize(mask: npt.NDArray[np.int8]) -> None:
    frame = _random_frame(mask.shape, 0, 255, seed=12)
    one = IptModulator(mask, DELTA_L)
    two = IptModulator(mask, DELTA_L, threads=2)
    try:
        expected = one.phases(frame)
        buffers = (np.zeros_like(frame), np.zeros_like(frame))
        got = two.phases(frame, buffers)
        assert got[0] is buffers[0]
        assert got[1] is buffers[1]
        assert np.array_equal(got[0], expected[0])
        assert np.array_equal(got[1], expected[1])
    finally:
        two.close()
    with pytest.raises(ModulationError, match="output buffers"):
        one.phases(frame, (np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10, 3), np.uint8)))
    small = _random_frame((120, 160), seed=9)
    resized = cv2.resize(small, (640, 480), interpolation=cv2.INTER_AREA)
    assert np.array_equal(one.phases(small)[0], one.phases(resized)[0])
    copy = frame.copy()
    one.phases(frame)
    assert np.array_equal(frame, copy)


@pytest.mark.parametrize("frame", [np.zeros((480, 640), np.uint8), np.zeros((480, 640, 3), np.float32)])
def test_ipt_bad_frames(ipt: IptModulator, frame: npt.NDArray[np.generic]) -> None:
    with pytest.raises(ModulationError, match="uint8 RGB"):
        ipt.phases(frame)  # type: ignore[arg-type]


@pytest.mark.parametrize("delta_l", [0.0, -1.0, 128.0, float("nan")])
def test_ipt_bad_delta_l(mask: npt.NDArray[np.int8], delta_l: float) -> None:
    with pytest.raises(ModulationError, match="ΔL"):
        IptModulator(mask, delta_l)


def test_delta_l_warnings() -> None:
    assert delta_l_warning(4.0) is None
    assert delta_l_warning(1.0) is None
    assert delta_l_warning(20.0) is None
    low = delta_l_warning(0.5)
    assert low is not None
    assert "8-bit output" in low
    high = delta_l_warning(30.0)
    assert high is not None
    assert "seen" in high


def test_amplitude_grid_solves_the_lightness_step() -> None:
    grid = amplitude_grid(4.0, steps=1024)
    y = np.linspace(0.0, 1.0, 1025)
    inner = (y > 0.02) & (y < 0.98)
    step = lstar(y + grid) - lstar(y - grid)
    assert np.allclose(step[inner], 2 * 4.0 / L8_PER_LSTAR, atol=1e-9)
    assert grid[0] == 0.0
    assert np.all(grid <= y + 1e-15)


def test_frame_timing_whole_and_other_ratios() -> None:
    t = FrameTiming(30, 60)
    assert t.whole
    assert t.note() is None
    assert [t.input_of(j) for j in range(6)] == [0, 0, 1, 1, 2, 2]
    t = FrameTiming(24, 60)
    assert not t.whole
    shown = [t.input_of(j) for j in range(10)]
    assert shown == [0, 0, 0, 1, 1, 2, 2, 2, 3, 3]  # 3, 2, 3, 2 output frames per input frame
    note = t.note()
    assert note is not None
    assert "2 or 3" in note
    assert "alternates" in note
    t = FrameTiming(120, 60)
    assert [t.input_of(j) for j in range(4)] == [0, 2, 4, 6]
    note = t.note()
    assert note is not None
    assert "dropped" in note
    assert [FrameTiming(29.97, 59.94).input_of(j) for j in range(4)] == [0, 0, 1, 1]
    assert [FrameTiming(25, 60).input_of(j) for j in range(12)] == [0, 0, 0, 1, 1, 2, 2, 2, 3, 3, 4, 4]
    with pytest.raises(ModulationError, match="input frame rate"):
        FrameTiming(0, 60)
    with pytest.raises(ModulationError, match="output frame rate"):
        FrameTiming(30, float("inf"))


def _detect_tags(plus: U8, minus: U8, tag_count: int) -> int:
    """Tags pupil-apriltags finds in the lightness difference of two phases (projector space, halved)."""
    from ipt.config.models import DetectorConfig
    from ipt.receiver.detect.detector import TagDetector

    diff = _lstar8(plus) - _lstar8(minus)
    small = cv2.resize(diff, (diff.shape[1] // 2, diff.shape[0] // 2), interpolation=cv2.INTER_AREA)
    binary = np.where(small > 0, 255, 0).astype(np.uint8)
    detector = TagDetector(DetectorConfig())
    found = {d.tag_id for d in detector.detect(binary)}
    assert len(found) <= tag_count
    return len(found)


def test_ipt_tags_are_detected_like_the_papers() -> None:
    # The full paper arena on busy colourful content: every tag is found in the difference of the two
    # phases with either profile.
    arena = ArenaConfig()
    m = grid_tag_map(arena).render_mask()
    rng = np.random.default_rng(8)
    coarse = rng.integers(25, 231, (arena.projector.height_px // 24, arena.projector.width_px // 24, 3), np.uint8)
    content = np.asarray(
        cv2.resize(coarse, (arena.projector.width_px, arena.projector.height_px), interpolation=cv2.INTER_CUBIC),
        dtype=np.uint8,
    )
    n = arena.tag_map.rows * arena.tag_map.cols
    for profile in ("ipt", "paper"):
        plus, minus = make_modulator(profile, m, arena.modulation.delta_l).phases(content)
        assert _detect_tags(plus, minus, n) == n, profile


def test_the_simulator_projects_what_the_sender_makes() -> None:
    from ipt.sender.content import GeneratedScene
    from ipt.sim.arena import SimulatedArena
    from ipt.sim.config import SimConfig

    arena = ArenaConfig()
    scene = GeneratedScene(arena.projector.width_px, arena.projector.height_px)
    world = SimulatedArena(arena, SimConfig(), scene)
    assert world.modulator.profile == "ipt"
    mod = IptModulator(
        grid_tag_map(arena).render_mask(),
        arena.modulation.delta_l,
        clip_allowance_l8=arena.modulation.clip_allowance_l8,
    )
    plus, minus = mod.phases(scene.frame(1, 30))
    region = (700, 900, 1100, 1250)
    x0, y0, x1, y1 = region
    assert np.array_equal(world.projector_crop(2, region), plus[y0:y1, x0:x1])
    assert np.array_equal(world.projector_crop(3, region), minus[y0:y1, x0:x1])
    paper = ArenaConfig.model_validate({"modulation": {"profile": "paper"}})
    assert SimulatedArena(paper, SimConfig(), scene).modulator.profile == "paper"


def test_clip_allowance_buys_signal_near_white_and_black(mask: npt.NDArray[np.int8]) -> None:
    from ipt.invisibility import ciede2000

    exact = IptModulator(mask, DELTA_L)
    allowed = IptModulator(mask, DELTA_L, clip_allowance_l8=2.2)
    assert ArenaConfig().modulation.clip_allowance_l8 == 2.2
    ends = np.array([(255, 255, 255), (0, 0, 0), (254, 254, 253), (2, 2, 2)], np.uint8)
    up, down = allowed.pair_codes(ends)
    step = _lstar8(up) - _lstar8(down)
    assert np.all(step > 4.1)  # the paper gets 4.4 on white, 4.2 on black (0 with the exact default)
    fused = (code_to_linear(up) + code_to_linear(down)) / 2
    de = ciede2000(linear_to_lab(fused), code_to_lab(ends))
    assert np.all(de <= 0.4937)  # what a lightness change of 2.2 costs at white
    assert float(de[0]) > 0.2  # the price: white is no longer exactly white on average
    # Colours with room for the full step are not touched by the allowance.
    rng = np.random.default_rng(6)
    middle = rng.integers(30, 226, (5000, 3), dtype=np.uint8)
    for a, b in zip(exact.pair_codes(middle), allowed.pair_codes(middle), strict=True):
        assert np.array_equal(a, b)
    for bad in (-1.0, 9.0, float("nan")):
        with pytest.raises(ModulationError, match="clip allowance"):
            IptModulator(mask, DELTA_L, clip_allowance_l8=bad)
    arena = ArenaConfig.model_validate({"modulation": {"clip_allowance_l8": 2}})
    from ipt.sender.content import StillImageScene
    from ipt.sim.arena import SimulatedArena
    from ipt.sim.config import SimConfig

    world = SimulatedArena(arena, SimConfig(), StillImageScene(np.zeros((8, 8, 3), np.uint8), 1920, 2160))
    assert isinstance(world.modulator, IptModulator)
    assert world.modulator.clip_allowance_l8 == 2.0
