"""The search of the whole map (``Acquisition.search_map``) is not run on a view mostly in the drone's shadow (lit below
``SHADOWED_SHARE``): it cannot lay the map there, and it costs 50-60 ms a search. Such a frame does not use up the
search's turn either: the next lit frame is searched at once. A placement whose track fits little of the map is not
taken. From a live camera a fallback pair (half a projector period apart) is not searched; a replay searches it."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from flightpipeline import flight_pipeline

from ipt.config.models import PipelineConfig
from ipt.receiver.core.acquire import ACQUIRE_LIT_SHARE, FALLBACK_PHASE_ERROR, MIN_SEARCH_FIT
from ipt.receiver.core.demodulator import PairDifference
from ipt.receiver.core.history import Frame
from ipt.receiver.core.mapsearch import MapSearch
from ipt.receiver.core.pipeline import Pipeline
from ipt.receiver.core.reasons import SHADOWED_SHARE
from ipt.receiver.core.track import TrackResult
from ipt.videoio import open_frames


@pytest.fixture(scope="module")
def pipeline(short_flight: Path) -> Iterator[Pipeline]:
    p = flight_pipeline(short_flight, PipelineConfig())
    yield p
    p.close()


def _frame(p: Pipeline, index: int, lit_share: float) -> Frame:
    h, w = p.camera.height_px, p.camera.width_px
    f = Frame(index, index * 8_333, np.zeros((h, w), np.uint8), signal=np.full((h, w), 255, np.uint8))
    f.lit_share = lit_share
    return f


def test_a_shadowed_view_is_not_searched_and_keeps_the_turn(pipeline: Pipeline) -> None:
    acq = pipeline.acquisition
    h, w = pipeline.camera.height_px, pipeline.camera.width_px
    noise = np.random.default_rng(0).normal(0.0, 1.0, (h, w)).astype(np.float32)
    diff = PairDifference(noise, np.full((h, w), 255, np.uint8), 1.0, 0.0)
    acq.searched_at = -100
    assert acq.search_map(_frame(pipeline, 10, SHADOWED_SHARE / 2), _frame(pipeline, 9, 1.0), diff) is None
    assert acq.searched_at == -100
    assert acq.map_search is None
    # The next frame, lit, is searched at once (on noise: whatever it finds, it searched).
    acq.search_map(_frame(pipeline, 11, 0.9), _frame(pipeline, 10, 1.0), diff)
    assert acq.searched_at == 11
    assert acq.map_search is not None


def test_a_dim_view_is_not_searched_but_takes_its_turn(pipeline: Pipeline) -> None:
    """Lit between ``SHADOWED_SHARE`` and ``ACQUIRE_LIT_SHARE``: no search either (none found a pose there on the
    suite's and held-out flights), but the turn goes by as if searched, so the searches after fall on the frames they
    would have."""
    acq = pipeline.acquisition
    h, w = pipeline.camera.height_px, pipeline.camera.width_px
    noise = np.random.default_rng(2).normal(0.0, 1.0, (h, w)).astype(np.float32)
    diff = PairDifference(noise, np.full((h, w), 255, np.uint8), 1.0, 0.0)
    acq.searched_at, acq.map_search = -100, None
    dim = (SHADOWED_SHARE + ACQUIRE_LIT_SHARE) / 2
    assert acq.search_map(_frame(pipeline, 40, dim), _frame(pipeline, 38, 1.0), diff) is None
    assert acq.searched_at == 40
    assert acq.map_search is None
    assert acq.search_map(_frame(pipeline, 41, 0.9), _frame(pipeline, 39, 1.0), diff) is None  # not its turn yet
    assert acq.map_search is None
    acq.search_map(_frame(pipeline, 43, 0.9), _frame(pipeline, 41, 1.0), diff)
    assert acq.searched_at == 43
    assert acq.map_search is not None


def test_a_live_cameras_fallback_pair_is_not_searched_and_keeps_the_turn(pipeline: Pipeline) -> None:
    acq = pipeline.acquisition
    h, w = pipeline.camera.height_px, pipeline.camera.width_px
    noise = np.random.default_rng(1).normal(0.0, 1.0, (h, w)).astype(np.float32)
    diff = PairDifference(noise, np.full((h, w), 255, np.uint8), 1.0, 0.0)
    # One camera frame apart at 120 FPS: half a period of the 60 Hz projector; two: a whole one.
    assert pipeline.history.phase_error(8_333) > FALLBACK_PHASE_ERROR > pipeline.history.phase_error(2 * 8_333)
    acq.live, acq.searched_at = True, -100
    try:
        assert acq.search_map(_frame(pipeline, 21, 1.0), _frame(pipeline, 20, 1.0), diff) is None
        assert acq.searched_at == -100
        # The same frame with its partner a whole period before is searched (on noise: whatever it finds).
        acq.search_map(_frame(pipeline, 21, 1.0), _frame(pipeline, 19, 1.0), diff)
        assert acq.searched_at == 21
    finally:
        acq.live = False
    # A replay searches the fallback pair.
    acq.searched_at = -100
    acq.search_map(_frame(pipeline, 31, 1.0), _frame(pipeline, 30, 1.0), diff)
    assert acq.searched_at == 31


def _placed(inliers: int, tried: int) -> TrackResult:
    """The track from a placement of the search, fitting ``inliers`` of ``tried`` of the map's visible edges."""
    rvec, tvec = np.array([np.pi, 0.0, 0.0]), np.array([-1.0, 1.0, 0.8])
    return TrackResult(rvec, tvec, inliers, tried, 0.5, (1, 2, 3), np.eye(6) * 1e-8, sign=1)


@pytest.mark.parametrize(("inliers", "taken"), [(300, False), (700, True)])
def test_a_placement_whose_track_fits_little_of_the_map_is_not_taken(
    short_flight: Path, monkeypatch: pytest.MonkeyPatch, inliers: int, taken: bool
) -> None:
    """A placement a tag or more off can fit part of the periodic map (the wrong ones seen fitted 0.34-0.49 of the
    edges, every right one 0.66 or more): below ``MIN_SEARCH_FIT`` the search does not take it, and tries the next.
    On a real pair of the short flight (frames 0 and 2, a projector period apart), the track from each placement
    replaced by one that fits ``inliers`` of 1000 edge samples."""
    p = flight_pipeline(short_flight, PipelineConfig())
    try:
        with open_frames(short_flight / "frames.mkv") as src:
            for k, frame in zip(range(3), src, strict=False):
                p.process(k, frame, round(k * 1e6 / 120))
        first, _, third = list(p.history)[:3]
        pair = p.pair(first, third)
        assert pair is not None
        diff = p.difference_in(pair, True)
        placements = len(list(MapSearch.of(p.tag_map).search(diff.diff, diff.valid, p.pinhole.camera_matrix)))
        assert placements > 0
        tried: list[int] = []

        def track_from(*args: object, **kwargs: object) -> TrackResult:
            tried.append(1)
            return _placed(inliers, 1000)

        monkeypatch.setattr(p, "track_from", track_from)
        assert (inliers / 1000 >= MIN_SEARCH_FIT) == taken
        p.acquisition.searched_at = -100
        got = p.acquisition.search_map(third, first, diff)
    finally:
        p.close()
    if taken:
        assert got is not None
        assert got.quality == pytest.approx(inliers / 1000)
        assert len(tried) == 1  # the first placement is taken
    else:
        assert got is None
        assert len(tried) == placements  # every placement was tried, none taken
