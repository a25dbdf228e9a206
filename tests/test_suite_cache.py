"""The scenario suite's render cache (benchmarks/suite.py): a flight renders again when its key changes, and
that replaces only its own older renderings, not those of a flight whose name starts with its name."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from ipt.config.models import load_arena_config, shipped_config_path
from ipt.sim.config import SimConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import suite


def test_a_new_rendering_replaces_only_its_own_flight_s_old_ones(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in ("dark-scene-0123456789abcdef", "dark-scene-ipt-fedcba9876543210", "takeoff-open-floor-00aa"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "frames.mkv").write_bytes(b"x")
        (tmp_path / name / "groundtruth.tum").write_text("# t\n")
    made: list[Path] = []

    def fake_simulate(arena: Any, sim: Any, scene: Any, folder: Path, seconds: float) -> None:
        folder.mkdir()
        (folder / "frames.mkv").write_bytes(b"y")
        (folder / "groundtruth.tum").write_text("# t\n")
        made.append(folder)

    monkeypatch.setattr(suite, "simulate_to_folder", fake_simulate)
    monkeypatch.setattr(suite, "scene_for", lambda sim, arena: None)
    arena = load_arena_config(shipped_config_path("arena.yaml"))
    for name in ("dark-scene", "takeoff"):
        folder = suite.render(name, SimConfig(), arena, 1.0, tmp_path, "digest")
        assert folder in made
    left = sorted(p.name for p in tmp_path.iterdir())
    assert "dark-scene-0123456789abcdef" not in left  # its own older rendering went
    assert "dark-scene-ipt-fedcba9876543210" in left  # another flight's stayed
    assert "takeoff-open-floor-00aa" in left
