"""The landing pads' geometry lives in the tag map; the arena config only describes (issue 32, target 5).

The map must stay exactly what it was when the geometry moved: the digests below were taken at 5def445
(``ArenaConfig.pad_grid``) and again after the move (``ipt.tagmap.pad_grid``), and were the same."""

from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from ipt.config.models import ArenaConfig, load_arena_config, shipped_config_path
from ipt.tagmap import TagMap, TagMapError, grid_tag_map, pad_grid, pad_tags, pads_problem

SHIPPED = load_arena_config(shipped_config_path("arena.yaml"))

THREE_PADS = [
    {"name": "a", "centre_m": [-0.7, -0.5], "size_m": 0.5, "tag_size_px": 64, "gap_px": 8},
    {"name": "b", "centre_m": [0.7, 0.9], "size_m": 0.37, "tag_size_px": 80, "gap_px": 3},
    {"name": "c", "centre_m": [0.55, -0.7], "size_m": 0.9, "tag_size_px": 72, "gap_px": 0},
]


def _arena(**tag_map: object) -> ArenaConfig:
    data = SHIPPED.model_dump(mode="json")
    data["tag_map"].update(tag_map)
    return ArenaConfig.model_validate(data)


def _digests(tag_map: TagMap) -> tuple[int, str, str]:
    image = hashlib.sha256(tag_map.render_image().tobytes()).hexdigest()
    tags = [(t.tag_id, t.corners_px, np.round(np.asarray(t.corners_m), 9).tolist()) for t in tag_map.tags]
    return len(tag_map.tags), image, hashlib.sha256(repr(tags).encode()).hexdigest()


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        (
            "shipped",
            (
                107,
                "85fe6fc72b6005c57718d4b8f08d039642edc5bb3df20890f1e57b207f8e472c",
                "22b92d6da41bf64c5f3afa340b9fad1d5bd633f20b46c52c1192da027c301c8f",
            ),
        ),
        (
            "three pads",
            (
                236,
                "63f8a8e8b2d988848be3ed3650133327185c820ab29c12b987b72ed5a719c591",
                "5e14d6f296202751d963cd90e48c1cc7da4842ef5e965bfdd238003b2c6a8e5d",
            ),
        ),
    ],
)
def test_the_map_is_the_one_drawn_before_the_geometry_moved(name: str, expected: tuple[int, str, str]) -> None:
    arena = SHIPPED if name == "shipped" else _arena(pads=THREE_PADS)
    assert _digests(grid_tag_map(arena)) == expected


def test_the_config_describes_and_the_tag_map_lays_out() -> None:
    assert not hasattr(ArenaConfig, "pad_grid"), "the pads' grid is the tag map's geometry (ipt.tagmap.pad_grid)"
    (pad,) = SHIPPED.tag_map.pads
    grid = pad_grid(SHIPPED, pad)
    (col0, col1, row0, row1), (cols, rows, left_px, top_px) = grid
    assert (grid.cells, grid.block) == ((col0, col1, row0, row1), (cols, rows, left_px, top_px))
    (small,) = pad_tags(SHIPPED)
    assert len(small) == cols * rows
    # The block's top-left quiet zone starts at (left_px, top_px): the first tag of its top row sits one
    # quiet cell (tag_size_px / 8) inside it.
    top_left = min(small, key=lambda t: (np.asarray(t.corners_px)[:, 1].min(), np.asarray(t.corners_px)[:, 0].min()))
    corners = np.asarray(top_left.corners_px)
    quiet = pad.tag_size_px // 8
    assert (corners[:, 0].min(), corners[:, 1].min()) == (left_px + quiet, top_px + quiet)


def test_pads_that_cannot_be_laid_out_are_named_by_the_map() -> None:
    too_many = _arena(pads=[{"name": "a", "centre_m": [0.0, 0.0], "size_m": 2.1, "gap_px": 0}])
    assert pads_problem(too_many) == "tag36h11 has 587 ids: the grid and the landing pads' 648 small tags need more"
    with pytest.raises(TagMapError, match="587 ids"):
        grid_tag_map(too_many)
    too_big = _arena(pads=[{"name": "tiny", "centre_m": [0.0, 0.0], "size_m": 0.01, "tag_size_px": 200}])
    assert pads_problem(too_big) == "landing pad 'tiny': not one of its tags fits in the grid cells it covers"
    assert pads_problem(SHIPPED) is None


def test_map_export_refuses_pads_that_cannot_be_laid_out_in_one_line(tmp_path: Path) -> None:
    data = SHIPPED.model_dump(mode="json")
    data["tag_map"]["pads"] = [{"name": "a", "centre_m": [0.0, 0.0], "size_m": 2.1, "gap_px": 0}]
    config = tmp_path / "arena.yaml"
    config.write_text(yaml.safe_dump(data), encoding="utf-8")
    image, layout = tmp_path / "map.png", tmp_path / "map.json"
    cli = Path(sys.executable).with_name("ipt")
    done = subprocess.run(
        [str(cli), "map", "export", "--config", str(config), "--image", str(image), "--layout", str(layout)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1
    assert "587 ids" in done.stderr
    assert "Traceback" not in done.stderr
    assert not image.exists()
    assert not layout.exists()
