"""The invisibility measure: CIEDE2000 against the published test data, the figures of each profile, the CLI."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

from ipt.config.models import ArenaConfig
from ipt.invisibility import Distribution, ProfileFigures, ciede2000, frame_indices, measure, measure_scene, report
from ipt.sender.colour import CODE_TO_LINEAR, code_to_lab, linear_to_lab, srgb_to_linear
from ipt.sender.content import GeneratedScene
from ipt.sender.modulator import IptModulator, PaperModulator
from ipt.tagmap import grid_tag_map
from ipt.videoio import FfvWriter

U8 = npt.NDArray[np.uint8]

# Sharma, Wu & Dalal (2005), Table 1: the 34 test pairs (L*, a*, b*) and their CIEDE2000 difference.
SHARMA_PAIRS = [
    ((50.0000, 2.6772, -79.7751), (50.0000, 0.0000, -82.7485), 2.0425),
    ((50.0000, 3.1571, -77.2803), (50.0000, 0.0000, -82.7485), 2.8615),
    ((50.0000, 2.8361, -74.0200), (50.0000, 0.0000, -82.7485), 3.4412),
    ((50.0000, -1.3802, -84.2814), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, -1.1848, -84.8006), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, -0.9009, -85.5211), (50.0000, 0.0000, -82.7485), 1.0000),
    ((50.0000, 0.0000, 0.0000), (50.0000, -1.0000, 2.0000), 2.3669),
    ((50.0000, -1.0000, 2.0000), (50.0000, 0.0000, 0.0000), 2.3669),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0009), 7.1792),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0010), 7.1792),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0011), 7.2195),
    ((50.0000, 2.4900, -0.0010), (50.0000, -2.4900, 0.0012), 7.2195),
    ((50.0000, -0.0010, 2.4900), (50.0000, 0.0009, -2.4900), 4.8045),
    ((50.0000, -0.0010, 2.4900), (50.0000, 0.0010, -2.4900), 4.8045),
    ((50.0000, -0.0010, 2.4900), (50.0000, 0.0011, -2.4900), 4.7461),
    ((50.0000, 2.5000, 0.0000), (50.0000, 0.0000, -2.5000), 4.3065),
    ((50.0000, 2.5000, 0.0000), (73.0000, 25.0000, -18.0000), 27.1492),
    ((50.0000, 2.5000, 0.0000), (61.0000, -5.0000, 29.0000), 22.8977),
    ((50.0000, 2.5000, 0.0000), (56.0000, -27.0000, -3.0000), 31.9030),
    ((50.0000, 2.5000, 0.0000), (58.0000, 24.0000, 15.0000), 19.4535),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.1736, 0.5854), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.2972, 0.0000), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 1.8634, 0.5757), 1.0000),
    ((50.0000, 2.5000, 0.0000), (50.0000, 3.2592, 0.3350), 1.0000),
    ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644),
    ((63.0109, -31.0961, -5.8663), (62.8187, -29.7946, -4.0864), 1.2630),
    ((61.2901, 3.7196, -5.3901), (61.4292, 2.2480, -4.9620), 1.8731),
    ((35.0831, -44.1164, 3.7933), (35.0232, -40.0716, 1.5901), 1.8645),
    ((22.7233, 20.0904, -46.6940), (23.0331, 14.9730, -42.5619), 2.0373),
    ((36.4612, 47.8580, 18.3852), (36.2715, 50.5065, 21.2231), 1.4146),
    ((90.8027, -2.0831, 1.4410), (91.1528, -1.6435, 0.0447), 1.4441),
    ((90.9257, -0.5406, -0.9208), (88.6381, -0.8985, -0.7239), 1.5381),
    ((6.7747, -0.2908, -2.4247), (5.8714, -0.0985, -2.2286), 0.6377),
    ((2.0776, 0.0795, -1.1350), (0.9033, -0.0636, -0.5514), 0.9082),
]

SMALL = ArenaConfig.model_validate(
    {
        "projector": {"width_px": 320, "height_px": 288},
        "screen": {"width_m": 1.0, "height_m": 0.9},
        "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
    }
)


def test_ciede2000_matches_the_published_test_data() -> None:
    lab1 = np.array([p[0] for p in SHARMA_PAIRS])
    lab2 = np.array([p[1] for p in SHARMA_PAIRS])
    expected = np.array([p[2] for p in SHARMA_PAIRS])
    assert np.allclose(ciede2000(lab1, lab2), expected, atol=5e-5)
    assert np.allclose(ciede2000(lab2, lab1), expected, atol=5e-5)  # symmetric
    assert np.all(ciede2000(lab1, lab1) == 0)


def test_colour_conversions() -> None:
    assert np.allclose(code_to_lab(np.array([255, 255, 255], np.uint8)), [100.0, 0.0, 0.0], atol=1e-9)
    assert np.allclose(code_to_lab(np.array([0, 0, 0], np.uint8)), [0.0, 0.0, 0.0])
    # sRGB red in CIELAB (D65), as published for the sRGB primaries.
    assert np.allclose(code_to_lab(np.array([255, 0, 0], np.uint8)), [53.24, 80.09, 67.20], atol=0.02)
    assert srgb_to_linear(0.5) == pytest.approx(0.21404, abs=1e-5)
    grey = linear_to_lab(np.array([0.18, 0.18, 0.18]))
    assert grey[0] == pytest.approx(49.496, abs=1e-3)


def test_distribution_percentiles() -> None:
    d = Distribution()
    d.add(np.array([0.1, 0.2, 0.3]), zeros=97)
    assert d.n == 100
    assert d.mean == pytest.approx(0.006)
    assert d.max == pytest.approx(0.3)
    assert d.percentile(50) == 0.0
    assert d.percentile(98) == pytest.approx(0.101, abs=1e-9)  # upper edge of the bin holding it
    assert d.percentile(100) == pytest.approx(0.3)
    empty = Distribution()
    assert np.isnan(empty.percentile(99))


def test_frame_indices() -> None:
    assert frame_indices(3, None, 30) == [0, 30, 60]
    assert frame_indices(4, 100, 1) == [0, 25, 50, 75]
    assert frame_indices(10, 4, 1) == [0, 1, 2, 3]
    with pytest.raises(ValueError, match="at least one"):
        frame_indices(0, 10, 1)


def test_measure_tells_the_profiles_apart() -> None:
    mask = grid_tag_map(SMALL).render_mask()
    scene = GeneratedScene(320, 288)
    rng = np.random.default_rng(0)
    frames = [(0, scene.frame(0, 30.0)), (1, rng.integers(20, 236, (288, 320, 3), dtype=np.uint8))]
    ipt_mod = IptModulator(mask, 4.0, clip_allowance_l8=2.2)
    figures = measure(frames, mask, {"ipt": ipt_mod, "paper": PaperModulator(mask, 4.0)})
    r = report(figures)
    ipt, paper = r["ipt"], r["paper"]
    assert ipt["pairs_measured"] == paper["pairs_measured"] == 2
    # ipt: nothing outside the tags changes; what the eye fuses on the tags is the input.
    assert ipt["non_tag_identical_fraction"] == 1.0
    assert ipt["fused_ciede2000_non_tag"] == {"mean": 0.0, "p99": 0.0, "max": 0.0}
    assert ipt["fused_ciede2000_tag"]["p99"] <= 0.5
    # paper: the 8-bit CIELAB round trip touches every pixel, and clipped phases do not average out.
    assert paper["non_tag_identical_fraction"] < 0.9
    assert paper["fused_ciede2000_non_tag"]["max"] > 0.5
    assert paper["fused_ciede2000_tag"]["max"] > ipt["fused_ciede2000_tag"]["max"]
    # Both aim at 2ΔL = 8: on the random frame (no pure white or black) they get it.
    assert ipt["pairs"][1]["signal_l8"] == pytest.approx(8.0, abs=0.3)
    assert paper["pairs"][1]["signal_l8"] == pytest.approx(8.0, abs=0.3)
    assert r["ipt"]["signal_vs_paper"] == pytest.approx(ipt["signal_l8"] / paper["signal_l8"], abs=1e-3)
    assert ipt["flat_tag_fraction"] == 0  # the allowance gives pure white and black on tags a signal too
    # A moving eye sees the tags' edges (the phases no longer cancel pixel by pixel): well above the fused
    # error, for either profile.
    for prof in (ipt, paper):
        assert prof["saccade_px"] == 4
        assert prof["saccade_ciede2000_tag"]["p99"] > prof["fused_ciede2000_tag"]["p99"]
    json.dumps(r)


def test_measure_scene_uses_the_arena() -> None:
    out = measure_scene(SMALL, GeneratedScene(160, 144), [0], 30.0, ("ipt",), delta_l=6.0)
    assert out["projector"] == "320x288"
    assert out["delta_l"] == 6.0
    assert list(out["profiles"]) == ["ipt"]
    assert 0 < out["tag_pixels_fraction"] < 1


def test_signal_counts_the_mask_sign() -> None:
    fig = ProfileFigures("x", 4.0)
    mask = np.array([[1, -1, 0]], np.int8)
    frame = np.full((1, 3, 3), 100, np.uint8)
    plus = np.array([[[110] * 3, [90] * 3, [100] * 3]], np.uint8)
    minus = np.array([[[90] * 3, [110] * 3, [100] * 3]], np.uint8)
    fig.add_pair(0, frame, plus, minus, mask)
    assert fig.signal_l8 > 10  # both tag pixels count positive: + phase brighter on white, darker on black
    assert fig.non_tag_identical == 1


def test_saccade_of_a_known_pair() -> None:
    # One row: a white tag pixel then a black one, then content. The eye moves one pixel between the
    # phases: at x it sees (+ phase at x, - phase at x + 1).
    fig = ProfileFigures("x", 4.0, saccade_px=1)
    mask = np.array([[1, -1, 0, 0]], np.int8)
    frame = np.full((1, 4, 3), 100, np.uint8)
    plus = np.array([[[110] * 3, [90] * 3, [100] * 3, [100] * 3]], np.uint8)
    minus = np.array([[[90] * 3, [110] * 3, [100] * 3, [100] * 3]], np.uint8)
    fig.add_pair(0, frame, plus, minus, mask)
    # Points 0, 1 (tag at x) and 2 (nothing at x, nor at x + 1 = 3) ... only 0 and 1 touch a tag.
    assert fig.saccade.n == 2
    lin = CODE_TO_LINEAR
    seen0 = (lin[110] + lin[110]) / 2  # + at 0 (white: up), - at 1 (black: up)
    seen1 = (lin[90] + lin[100]) / 2  # + at 1 (black: down), - at 2 (untouched)
    ref = linear_to_lab(np.full(3, lin[100]))
    want = ciede2000(np.stack([ref, ref]), linear_to_lab(np.array([[seen0] * 3, [seen1] * 3])))
    assert fig.saccade.max == pytest.approx(float(want.max()))
    assert fig.saccade.mean == pytest.approx(float(want.mean()))
    assert fig.to_dict()["saccade_ciede2000_tag"]["max"] == pytest.approx(float(want.max()), abs=1e-4)
    # No eye movement, no saccade figure.
    still = ProfileFigures("x", 4.0, saccade_px=0)
    still.add_pair(0, frame, plus, minus, mask)
    assert still.saccade.n == 0


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ipt.cli", *args], capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_invisibility_cli_on_a_video_of_another_size(tmp_path: Path) -> None:
    arena = tmp_path / "arena.yaml"
    arena.write_text(
        "projector: {width_px: 320, height_px: 288, rate_hz: 60}\nscreen: {width_m: 1.0, height_m: 0.9}\n"
        "tag_map: {rows: 2, cols: 2, tag_size_px: 64}\nmodulation: {delta_l: 4, input_rate_hz: 30}\n",
        encoding="utf-8",
    )
    video = tmp_path / "content.mkv"
    rng = np.random.default_rng(1)
    with FfvWriter(video, 200, 150, 25) as writer:
        for _ in range(6):
            writer.write(rng.integers(0, 256, (150, 200, 3), dtype=np.uint8))
    run = _cli(
        "invisibility", "--config", str(arena), "--content", "photos", str(video), "--pairs", "3", "--saccade-px", "6"
    )
    assert run.returncode == 0, run.stderr
    assert "resized to 320x288" in run.stderr
    out = json.loads(run.stdout)
    photos, clip = out["contents"]
    assert photos["content"] == "photos"
    assert photos["input_frames"] == [0, 150, 300]  # spread over one round of its six 2.5 s shots at 30 fps
    assert clip["content"] == str(video)
    assert clip["input_frames"] == [0, 2, 4]
    for block in (photos, clip):
        assert set(block["profiles"]) == {"ipt", "paper"}
        ipt = block["profiles"]["ipt"]
        assert ipt["non_tag_identical_fraction"] == 1.0
        assert ipt["fused_ciede2000_tag"]["p99"] <= 0.5
        assert ipt["saccade_px"] == 6
        assert ipt["saccade_ciede2000_tag"]["max"] > 0
        assert 0.5 < ipt["signal_vs_paper"] < 1.5


def test_invisibility_cli_bad_input(tmp_path: Path) -> None:
    missing = _cli("invisibility", "--video", str(tmp_path / "nope.mkv"))
    assert missing.returncode == 2
    assert missing.stderr.count("\n") == 1
    assert "nope.mkv" in missing.stderr
    bad = _cli("invisibility", "--profiles", "ipt,fancy")
    assert bad.returncode == 2
    assert "--profiles" in bad.stderr
    assert "Traceback" not in bad.stderr
    dl = _cli("invisibility", "--delta-l", "99")
    assert dl.returncode == 2
    assert "--delta-l" in dl.stderr
