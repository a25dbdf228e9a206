"""The search of the whole map (``Acquisition.search_map``) is not run on a view mostly in the drone's shadow (lit below
``SHADOWED_SHARE``): it cannot lay the map there, and it costs 50-60 ms a search. Such a frame does not use up the
search's turn either: the next lit frame is searched at once."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from flightpipeline import flight_pipeline

from ipt.config.models import PipelineConfig
from ipt.receiver.core.demodulator import PairDifference
from ipt.receiver.core.history import Frame
from ipt.receiver.core.pipeline import Pipeline
from ipt.receiver.core.reasons import SHADOWED_SHARE


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
