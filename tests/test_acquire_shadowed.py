"""Without a track, AprilTag rests on views mostly in the drone's shadow (lit below ``ACQUIRE_LIT_SHARE``, which is
above ``SHADOWED_SHARE``): it is tried on one such frame in ``REST_EVERY`` (with each of that frame's earlier partners:
its pairs with later ones rest too), and the pairs of the frames between are not made. Once the view is lit again,
AprilTag is tried on every frame and the pose is found at once."""

from __future__ import annotations

import itertools
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
from flightpipeline import flight_frames, flight_pipeline

from ipt.config.models import PipelineConfig
from ipt.receiver.core.acquire import ACQUIRE_LIT_SHARE, REST_EVERY, SEARCH_EVERY, SEARCH_EVERY_MAX, SEARCH_TRIES
from ipt.receiver.core.demodulator import PairDifference
from ipt.receiver.core.history import Frame
from ipt.receiver.core.reasons import SHADOWED_SHARE

SHADOWED = 24
"""The first frames of the flight, each with all but a strip on its right in deep shadow."""


def _shadowed(frame: Any) -> Any:
    out = np.array(frame, copy=True)
    w = out.shape[1]
    out[:, : int(0.82 * w)] //= 25  # (below the signal mask's darkest lit level: no projector light there)
    return out


def test_apriltag_rests_on_shadowed_views_and_acquires_once_lit(short_flight: Path) -> None:
    frames = flight_frames(short_flight)
    p = flight_pipeline(short_flight, PipelineConfig())
    tried: list[tuple[int, float]] = []
    acquire = p.acquisition.acquire

    def spy(target: Frame, other: Frame, diff: Any) -> Any:
        tried.append((target.index, target.lit_share))
        return acquire(target, other, diff)

    p.acquisition.acquire = spy  # type: ignore[method-assign]
    results = []
    try:
        for i, frame in enumerate(frames[:40]):
            results += p.process(i, _shadowed(frame) if i < SHADOWED else frame, i * 8_333)
        results += p.flush()
    finally:
        p.close()
    shadowed = [(i, lit) for i, lit in tried if i < SHADOWED]
    assert shadowed
    assert all(lit < SHADOWED_SHARE for _, lit in shadowed)
    tried_frames = sorted({i for i, _ in shadowed})
    assert all(b - a >= REST_EVERY for a, b in itertools.pairwise(tried_frames))
    assert len(tried_frames) <= SHADOWED // REST_EVERY + 1
    by_index = {r.index: r for r in results}
    assert all(by_index[i].pose is None and by_index[i].reason == "shadowed" for i in range(2, SHADOWED))
    lit_tries = sorted({i for i, _ in tried if i >= SHADOWED})
    assert lit_tries[:1] == [SHADOWED]  # the first lit frame is tried at once
    assert any(by_index[i].pose is not None for i in range(SHADOWED, SHADOWED + 6))


def test_a_lit_view_never_rests_and_a_shadowed_one_every_eighth(short_flight: Path) -> None:
    p = flight_pipeline(short_flight, PipelineConfig())
    p.close()
    acq = p.acquisition
    lit = Frame(5, 5 * 8_333, np.zeros((2, 2), np.uint8))
    lit.lit_share = ACQUIRE_LIT_SHARE
    assert not acq.rests(lit)
    dark = [Frame(i, i * 8_333, np.zeros((2, 2), np.uint8)) for i in range(18)]
    for f in dark:
        f.lit_share = SHADOWED_SHARE / 2
    rested = [acq.rests(f) for f in dark]
    assert REST_EVERY == 8
    assert [i for i, r in enumerate(rested) if not r] == [0, 8, 16]
    assert not acq.rests(dark[16])  # the frame tried is tried with each of its earlier partners ...
    assert acq.rests(dark[16], later=True)  # ... and rests with its later ones


def test_a_dim_view_rests_too_and_its_turns_of_the_search_go_by(short_flight: Path) -> None:
    """A view lit between ``SHADOWED_SHARE`` and ``ACQUIRE_LIT_SHARE`` (no acquisition on the suite's and held-out
    flights ever found a pose there) rests as a shadowed one does; each rested frame on whose turn the whole-map search
    would have run takes that turn as if searched, so the lit frames after are searched when they would have been."""
    p = flight_pipeline(short_flight, PipelineConfig())
    p.close()
    acq = p.acquisition
    assert SHADOWED_SHARE < ACQUIRE_LIT_SHARE
    dim = [Frame(i, i * 8_333, np.zeros((2, 2), np.uint8)) for i in range(18)]
    for f in dim:
        f.lit_share = (SHADOWED_SHARE + ACQUIRE_LIT_SHARE) / 2
    acq.searched_at = -100
    turns = []
    rested = []
    for f in dim:
        rested.append(acq.rests(f))
        turns.append(acq.searched_at)
    assert [i for i, r in enumerate(rested) if not r] == [0, 8, 16]
    assert turns == [i - i % SEARCH_EVERY for i in range(18)]  # (each frame a search's turn falls on took it)
    assert acq.map_search is None


def test_a_frame_at_rest_is_prepared_for_its_lit_share_only(short_flight: Path) -> None:
    """A shadowed frame whose pairs rest needs its lit share (its undistorted lightness and signal mask), not the
    alignment's features: those are made for the frames of a pair only."""
    frames = flight_frames(short_flight)
    p = flight_pipeline(short_flight, PipelineConfig())
    featured: dict[int, bool] = {}
    paired: set[int] = set()
    dense, pair = p._dense, p.pair

    def dense_spy(f: Frame, features: bool = False) -> None:
        dense(f, features)
        featured[f.index] = featured.get(f.index, False) or f.features is not None

    def pair_spy(a: Frame, b: Frame) -> Any:
        paired.update((a.index, b.index))
        return pair(a, b)

    p._dense = dense_spy  # type: ignore[method-assign]
    p.pair = pair_spy  # type: ignore[method-assign]
    try:
        for i, frame in enumerate(frames[:40]):
            p.process(i, _shadowed(frame) if i < SHADOWED else frame, i * 8_333)
        p.flush()
    finally:
        p.close()
    assert {i for i, has in featured.items() if has} <= paired
    at_rest = [i for i, has in featured.items() if i < SHADOWED and not has]
    assert len(at_rest) >= SHADOWED // 2


def test_the_map_search_waits_longer_after_each_search_that_found_nothing(short_flight: Path) -> None:
    """Searches that find nothing (the real search, on a difference showing no map) come 3, 3, 6, 12, 24, 24 ... frames
    apart; a search that finds the pose (here a placement the track is made to take), or a new stretch asked for after
    more than ``SEARCH_EVERY_MAX`` frames without asking, starts the gaps again at ``SEARCH_EVERY``."""
    p = flight_pipeline(short_flight, PipelineConfig())
    p.close()
    acq = p.acquisition
    h, w = flight_frames(short_flight)[0].shape[:2]
    rng = np.random.default_rng(7)
    blank = PairDifference(rng.normal(0, 1, (h, w)).astype(np.float32), np.full((h, w), 255, np.uint8), 1.0, 0.0)
    searched: list[int] = []
    search = acq.searcher().search

    def spy(diff: Any, valid: Any, k: Any) -> Any:
        searched.append(current[0])
        found = search(diff, valid, k)
        return [SimpleNamespace(rvec=None, tvec=None, search_px=0.0)] if current[0] == 119 else found

    acq.searcher().search = spy  # type: ignore[method-assign]
    current = [0]

    def ask(i: int) -> Any:
        current[0] = i
        f = Frame(i, i * 8_333, np.zeros((2, 2), np.uint8))
        other = Frame(i - 1, (i - 1) * 8_333, np.zeros((2, 2), np.uint8))
        f.lit_share = other.lit_share = 0.9
        return acq.search_map(f, other, blank)

    assert all(ask(i) is None for i in range(70))
    assert SEARCH_EVERY == 3
    assert SEARCH_EVERY_MAX == 24
    assert SEARCH_TRIES == 3
    assert searched == [0, 3, 6, 12, 24, 48]
    searched.clear()
    for i in range(70 + SEARCH_EVERY_MAX + 1, 110):  # a new stretch: the track held in between
        ask(i)
    assert searched == [95, 98, 101, 107]
    searched.clear()
    placed = acq._placed
    acq._placed = lambda *a, **k: "found"  # type: ignore[method-assign,assignment]  # (a placement the track took)
    try:
        found = [i for i in range(110, 150) if ask(i) is not None]
    finally:
        acq._placed = placed  # type: ignore[method-assign]
    assert found == [119]
    assert searched == [119, 122, 125, 128, 134, 146]  # (12 frames after 107; the find at 119 starts again)
