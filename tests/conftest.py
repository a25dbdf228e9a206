"""Shared fixtures: one short simulated flight for every test module that needs real camera frames, and
the cache folder of the sender's colour table."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from ipt.config.models import ArenaConfig, load_arena_config, shipped_config_path
from ipt.sender.content import GeneratedScene
from ipt.sim.config import SimConfig
from ipt.sim.run import simulate_to_folder


@pytest.fixture(scope="session")
def short_flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """0.5 s (60 frames) of the smooth simulated flight: frames.mkv, camera.yaml, groundtruth.tum.

    No shadow, vibration or moving content: the tests that use it check the receiver's mechanics (files,
    sockets, timing), not its robustness, which the realistic flights of benchmarks/flights/ measure."""
    out = tmp_path_factory.mktemp("flight")
    # The shipped arena (its landing pad included), which the daemon and the CLIs use by default.
    arena = load_arena_config(shipped_config_path("arena.yaml"))
    simulate_to_folder(arena, SimConfig.smooth(), GeneratedScene(1920, 2160), out, 0.5, progress=None)
    return out


XDG_CACHE = Path(__file__).resolve().parent.parent / ".pytest_cache" / "xdg"
"""$XDG_CACHE_HOME of the tests (and of the programs they start): kept between runs like numba's cache, so
that the sender's colour table for the shipped arena is computed once per checkout, not in every run, and
nothing is written into the user's own ~/.cache."""


@pytest.fixture(scope="session", autouse=True)
def xdg_cache_home() -> Iterator[Path]:
    """Point $XDG_CACHE_HOME at :data:`XDG_CACHE`, with the shipped arena's colour table in it (computed
    here the first time, a quarter of a minute on 2 cores), so that a paced sender starts at once."""
    from ipt.sender.pairtable import default_cache_dir, pair_table

    before = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(XDG_CACHE)
    mod = ArenaConfig().modulation
    pair_table(mod.delta_l, mod.clip_allowance_l8).complete_with_cache(default_cache_dir(), lambda _: None)
    yield XDG_CACHE
    if before is None:
        os.environ.pop("XDG_CACHE_HOME", None)
    else:
        os.environ["XDG_CACHE_HOME"] = before
