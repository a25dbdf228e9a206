"""Shared fixtures: one short simulated flight for every test module that needs real camera frames."""

from __future__ import annotations

from pathlib import Path

import pytest

from ipt.config.models import ArenaConfig
from ipt.sender.content import GeneratedScene
from ipt.sim.config import SimConfig
from ipt.sim.run import simulate_to_folder


@pytest.fixture(scope="session")
def short_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.5 s (60 frames) of the smooth simulated flight: frames.mkv, camera.yaml, groundtruth.tum.

    No shadow, vibration or moving content: the tests that use it check the receiver's mechanics (files,
    sockets, timing), not its robustness, which the realistic flights of benchmarks/flights/ measure."""
    out = tmp_path_factory.mktemp("flight")
    simulate_to_folder(ArenaConfig(), SimConfig.smooth(), GeneratedScene(1920, 2160), out, 0.5, progress=None)
    return out
