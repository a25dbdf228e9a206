"""The sparse fit's iterations in one compiled call (ipt/receiver/core/sparseloop.py) against fit_sparse's own Python
loop around the three kernels, on tests/test_sparse.py's pair rendered from known poses: the same outcome and the
same pose to far below a micrometre, from starts off by pixels, through a lens, with camera noise, and where the
fit stops early; a fit the compiled loop is not for (smoothed, coarse steps) or a process without numba keeps the
Python loop."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from test_sparse import OTHER_POSITION_M, POSITION_M, R_OTHER, Pair, _guess_off_by, _pair

from ipt.config.models import ArenaConfig
from ipt.receiver.core import kernels, sparseloop
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.pose import rt_of
from ipt.receiver.core.sparse import SparseResult, SparseSettings, fit_sparse
from ipt.receiver.core.sparsechain import chain_settings
from ipt.tagmap import grid_tag_map

KNOWN, JOINT = chain_settings(640)


@pytest.fixture(scope="module", autouse=True)
def compiled_first() -> None:
    """Every kernel compiled (or loaded) before a test stands one in for another."""
    assert kernels.sparse_iterate_compiled()  # (numba is there in the tests)


@pytest.fixture(scope="module")
def edges() -> MapEdges:
    return MapEdges.from_tag_map(grid_tag_map(ArenaConfig()))


@pytest.fixture(scope="module")
def pairs() -> dict[str, Pair]:
    pinhole, lens = _pair(np.zeros(5)), _pair(np.array([-0.14, 0.06, 0.0005, -0.0004, -0.008]))
    rng = np.random.default_rng(5)

    def noisy(img: np.ndarray) -> np.ndarray:  # type: ignore[type-arg]
        return np.clip(img + rng.normal(0.0, 4.0, img.shape), 0, 255).round().astype(np.uint8)

    return {
        "pinhole": pinhole,
        "lens": lens,
        "noisy": Pair(noisy(pinhole.image), noisy(pinhole.other), pinhole.camera),
        "shadowed": Pair(_shadowed(pinhole.image), _shadowed(pinhole.other), pinhole.camera),
    }


def _shadowed(image: np.ndarray) -> np.ndarray:  # type: ignore[type-arg]
    """The left two fifths of the view in the drone's shadow: 8 % of the light (no projector light there)."""
    out = image.copy()
    cut = int(0.4 * image.shape[1])
    out[:, :cut] = (out[:, :cut] * 0.08).astype(np.uint8)
    return out


def _fit(
    pair: Pair, edges: MapEdges, start: tuple[np.ndarray, np.ndarray], settings: SparseSettings, compiled: bool
) -> tuple[SparseResult | None, str]:
    if not compiled:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(kernels, "sparse_iterate_compiled", lambda: False)
            return fit_sparse(
                pair.image, pair.other, pair.camera, edges, rt_of(OTHER_POSITION_M, R_OTHER), start, settings
            )
    return fit_sparse(pair.image, pair.other, pair.camera, edges, rt_of(OTHER_POSITION_M, R_OTHER), start, settings)


def _refused(*args: object) -> None:
    raise AssertionError("the Python loop was asked for, the compiled one ran")


def _same(a: tuple[SparseResult | None, str], b: tuple[SparseResult | None, str]) -> None:
    assert a[1] == b[1]
    if a[0] is None or b[0] is None:
        assert a[0] is None
        assert b[0] is None
        return
    x, y = a[0], b[0]
    assert np.abs(x.tvec - y.tvec).max() < 1e-7  # metres
    assert np.abs(x.rvec - y.rvec).max() < 1e-7  # radians
    assert np.abs(x.other_tvec - y.other_tvec).max() < 1e-7
    assert (x.iterations, x.inliers, x.tried, x.sign, x.tags) == (y.iterations, y.inliers, y.tried, y.sign, y.tags)
    assert x.amplitude == pytest.approx(y.amplitude, rel=1e-6)
    assert x.rms_px == pytest.approx(y.rms_px, rel=2e-5)  # (OpenCV's blur and ours: float32 sums in two orders)
    assert x.gain == pytest.approx(y.gain, rel=1e-6)
    # (an element a million times below the largest, 8e-13, differs by 0.3 %: float32 sums in two orders)
    assert np.allclose(x.cov_rt, y.cov_rt, rtol=1e-4, atol=1e-5 * float(np.abs(y.cov_rt).max()))


@pytest.mark.parametrize("name", ["pinhole", "lens", "noisy", "shadowed"])
@pytest.mark.parametrize(
    ("fit", "off_px"), [("known", 0.5), ("known", 2.0), ("known", 4.0), ("joint", 2.0), ("joint", 5.0)]
)
def test_the_compiled_iterations_fit_as_the_python_loop(
    pairs: dict[str, Pair], edges: MapEdges, name: str, fit: str, off_px: float
) -> None:
    """The chain's known-partner fits, and its joint fits (the partner only predicted; the first step over profiles
    reaching further, smoothed)."""
    settings = KNOWN if fit == "known" else JOINT
    start = _guess_off_by(off_px)
    python = _fit(pairs[name], edges, start, settings, compiled=False)
    compiled = _fit(pairs[name], edges, start, settings, compiled=True)
    assert python[0] is not None, python[1]
    _same(python, compiled)


@pytest.mark.parametrize("compiled", [True, False])
def test_a_fit_leaves_out_the_samples_in_the_shadow(pairs: dict[str, Pair], edges: MapEdges, compiled: bool) -> None:
    """Samples whose profiles are unlit in either frame (``SparseSettings.lit_only``) are left out: fitted, the
    shadowed ones pass as inliers (their residuals are small: no step, no noise), pull the map's step down and the
    pose off; left out, the step is the unshadowed pair's and the pose as near the truth as from the lit tags."""
    start = _guess_off_by(2.0)
    plain, _ = _fit(pairs["pinhole"], edges, start, KNOWN, compiled)
    lit, _ = _fit(pairs["shadowed"], edges, start, KNOWN, compiled)
    every, _ = _fit(pairs["shadowed"], edges, start, replace(KNOWN, lit_only=False), compiled)
    assert plain is not None
    assert lit is not None
    assert every is not None
    assert every.amplitude < 0.7 * plain.amplitude
    assert lit.amplitude == pytest.approx(plain.amplitude, rel=0.05)
    assert len(lit.tags) < len(every.tags)
    assert lit.tried < 0.7 * every.tried

    def error_m(result: SparseResult) -> float:
        r, _ = cv2.Rodrigues(result.rvec)
        return float(np.linalg.norm(-r.T @ result.tvec - POSITION_M))

    assert error_m(lit) < error_m(every)


def test_the_smoothing_is_opencvs() -> None:
    profiles = np.random.default_rng(4).uniform(0, 255, (50, 13)).astype(np.float32)
    for sigma in (0.7, 1.5, 3.0):
        size = 2 * int(np.ceil(2.5 * sigma)) + 1
        expected = cv2.GaussianBlur(profiles, (size, 1), sigma, borderType=cv2.BORDER_REPLICATE)
        assert np.abs(sparseloop.smoothed_py(profiles, sigma) - expected).max() < 1e-3  # (levels, of 0-255)
    assert sparseloop.smoothed_py(profiles, 0.0) is profiles


@pytest.mark.parametrize(
    ("settings", "why"),
    [
        (replace(KNOWN, border_px=170.0), "few_in_view"),  # (a window of 300 x 20 pixels)
        (replace(KNOWN, iterations=1), "not_converged"),  # (settled: the checks after, the same for both)
        (replace(KNOWN, give_up_px=0.01, give_up_steps=1, give_up_from=1), "gave_up"),
        (replace(KNOWN, min_step_sigmas=1e6), "weak_step"),
        (replace(JOINT, give_up_px=0.01, give_up_steps=1, give_up_from=2), "gave_up"),
    ],
)
def test_a_fit_that_stops_early_says_why_as_the_python_loop_does(
    pairs: dict[str, Pair], edges: MapEdges, settings: SparseSettings, why: str
) -> None:
    start = _guess_off_by(4.0)
    python = _fit(pairs["noisy"], edges, start, settings, compiled=False)
    compiled = _fit(pairs["noisy"], edges, start, settings, compiled=True)
    assert python[1] == why
    _same(python, compiled)


def test_the_fits_it_is_not_for_keep_the_python_loop(pairs: dict[str, Pair], edges: MapEdges) -> None:
    """A fit reading half its samples while far off, one smoothing every step, and a process where numba cannot
    compile: the compiled loop is not called."""
    start = _guess_off_by(2.0)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(kernels, "sparse_iterate", _refused)
        for settings in (replace(KNOWN, half_until_px=1.0), replace(KNOWN, smooth_px=0.7)):
            result, why = fit_sparse(
                *(pairs["pinhole"].image, pairs["pinhole"].other, pairs["pinhole"].camera, edges),
                *(rt_of(OTHER_POSITION_M, R_OTHER), start, settings),
            )
            assert result is not None, why
        patch.setattr(kernels, "COMPILED", False)
        patch.setattr(kernels.BY_NAME["sparse_iterate"], "compiled", None)
        patch.setattr(kernels.BY_NAME["sparse_iterate"], "ahead", object())
        result, why = _fit(pairs["pinhole"], edges, start, KNOWN, compiled=True)
        assert result is not None, why


def test_the_median_and_the_rotation_are_numpys_and_opencvs() -> None:
    rng = np.random.default_rng(2)
    for n in (1, 2, 9, 700, 701):
        values = rng.normal(size=n).astype(np.float32)
        assert sparseloop.median_of_py(values) == pytest.approx(float(np.median(values)), abs=1e-7)
    for v in (np.zeros(3), np.array([1e-9, 0.0, 0.0]), np.array([0.01, -0.02, 0.005]), np.array([1.0, 2.0, -0.5])):
        r = np.asarray(cv2.Rodrigues(np.array([0.2, -0.1, 0.3]))[0], np.float64)
        expected = np.asarray(cv2.Rodrigues(v.reshape(3, 1))[0], np.float64) @ r
        sparseloop.rotate_by_py(float(v[0]), float(v[1]), float(v[2]), r)
        assert np.abs(r - expected).max() < 1e-12


def test_the_damping_is_the_python_loops(pairs: dict[str, Pair], edges: MapEdges) -> None:
    """With and without the damping of steps that swing back (the known fits damp), each way as the Python loop."""
    start = _guess_off_by(3.0)
    for damp in (False, True):
        settings = replace(KNOWN, damp_swings=damp, converged_rms_px=0.0)
        _same(_fit(pairs["noisy"], edges, start, settings, False), _fit(pairs["noisy"], edges, start, settings, True))


def test_the_chains_known_fits_take_the_compiled_loop(
    pairs: dict[str, Pair], edges: MapEdges, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The chain's known-partner settings read every sample unsmoothed: one compiled call per fit."""
    calls = []
    compiled = kernels.sparse_iterate

    def counted(*args: object) -> object:
        calls.append(len(args))
        return compiled(*args)

    monkeypatch.setattr(kernels, "sparse_iterate", counted)
    result, why = _fit(pairs["pinhole"], edges, _guess_off_by(2.0), KNOWN, compiled=True)
    assert result is not None, why
    assert len(calls) == 1
