"""Every altitude: the landing pad's small tags in the shipped map, and detection sized to the tags in view.

The map is checked by real AprilTag detection on its rendered image; the scales by running the receiver on
frames the simulator renders from 2.5 m, where the paper's filter sizes find no tag at all.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from ipt.config.models import (
    ArenaConfig,
    ConfigError,
    PipelineConfig,
    load_arena_config,
    shipped_config_path,
)
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.pipeline import Pipeline
from ipt.receiver.core.scales import (
    DetectScale,
    ScaleChooser,
    gate_growth,
    honoured_decimation,
    scale_at_height,
    scale_for_cell,
    tag_cells_m,
)
from ipt.receiver.detect.detector import APRILTAG_TO_OPENCV_PX, TagDetector, pipeline_detector
from ipt.sim.arena import SimulatedArena, scene_for
from ipt.sim.config import SimConfig
from ipt.sim.render import camera_info_of
from ipt.tagmap import TagMap, export_map, grid_tag_map, layout_problem, load_layout, pad_grid, pad_tags

SHIPPED = load_arena_config(shipped_config_path("arena.yaml"))
BASE = DetectScale(5, 3.0)
PAD = {"name": "a", "centre_m": [0.0, 0.0], "size_m": 0.3}


@pytest.fixture(scope="module")
def shipped_map() -> TagMap:
    return grid_tag_map(SHIPPED)


def test_shipped_map_has_a_pad_of_small_tags_after_the_grid(shipped_map: TagMap) -> None:
    (pad,) = SHIPPED.tag_map.pads
    (cells, (cols, rows, _, _)), (small,) = pad_grid(SHIPPED, pad), pad_tags(SHIPPED)
    col0, col1, row0, row1 = cells
    gone = {row * 9 + col for row in range(row0, row1) for col in range(col0, col1)}
    assert gone, "the pad replaces some big tags"
    assert len(small) == cols * rows >= 16
    assert [t.tag_id for t in small] == list(range(81, 81 + len(small)))
    assert {t.tag_id for t in shipped_map.tags} == (set(range(81)) - gone) | {t.tag_id for t in small}
    assert layout_problem(shipped_map) is None
    sides = {round(float(np.linalg.norm(np.subtract(t.corners_px[1], t.corners_px[0])))) for t in shipped_map.tags}
    assert sides == {64, 160}
    # The pad's square is inside the block of small tags' cells, around its centre.
    centre = np.mean([np.asarray(t.corners_m)[:, :2].mean(axis=0) for t in small], axis=0)
    assert np.allclose(centre, pad.centre_m, atol=0.06)
    assert tag_cells_m(shipped_map) == (0.023, 0.009)


def test_paper_map_stays_selectable() -> None:
    assert len(grid_tag_map(ArenaConfig()).tags) == 81
    assert ArenaConfig().tag_map.pads == ()


def test_every_tag_of_the_shipped_map_decodes_at_its_corners(shipped_map: TagMap, tmp_path: Path) -> None:
    export_map(shipped_map, tmp_path / "map.png", tmp_path / "map.json")
    loaded = load_layout(tmp_path / "map.json")
    assert loaded == shipped_map
    detector = TagDetector(PipelineConfig().detector.model_copy(update={"quad_decimate": 1.0, "isolation": "inline"}))
    try:
        found = {d.tag_id: d.corners_px - APRILTAG_TO_OPENCV_PX for d in detector.detect(shipped_map.render_image())}
    finally:
        detector.close()
    assert set(found) == set(shipped_map.by_id)
    for tag_id, corners in found.items():
        assert np.abs(corners - np.asarray(shipped_map.by_id[tag_id].corners_px)).max() < 1.0


def _arena_with(**tag_map: object) -> dict[str, object]:
    data = SHIPPED.model_dump(mode="json")
    data["tag_map"].update(tag_map)
    return data


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"pads": [{"name": "a", "centre_m": [1.0, 0.0], "size_m": 0.3}]}, "landing pad 'a'"),
        (
            {
                "pads": [
                    {"name": "a", "centre_m": [0, 0], "size_m": 0.3},
                    {"name": "b", "centre_m": [0.2, 0], "size_m": 0.3},
                ]
            },
            "landing pads 'a' and 'b' overlap",
        ),
        (
            {
                "pads": [
                    {"name": "a", "centre_m": [0, 0], "size_m": 0.3},
                    {"name": "a", "centre_m": [0.6, 0], "size_m": 0.3},
                ]
            },
            "same name",
        ),
        ({"pads": [{"name": "a", "centre_m": [0, 0], "size_m": 0.3, "tag_size_px": 56}]}, "7 projector px per bit"),
        ({"pads": [{"name": "a", "centre_m": [0, 0], "size_m": 0.3, "tag_size_px": 60}]}, "multiple of 8"),
        # (too many small tags for tag36h11: the tag map says so, tests/test_tagmap_geometry.py)
        ({"pads": [{"name": "a", "centre_m": [0, 0], "size_m": 0.3, "shape": "round"}]}, "unknown key"),
    ],
)
def test_bad_pads_are_named(tmp_path: Path, changes: dict[str, object], fragment: str) -> None:
    import yaml

    path = tmp_path / "arena.yaml"
    path.write_text(yaml.safe_dump(_arena_with(**changes)), encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_arena_config(path)
    message = str(err.value)
    assert message.startswith(str(path))
    assert "\n" not in message
    assert fragment in message


def test_scales_follow_the_cell_size_in_the_image() -> None:
    assert scale_for_cell(13.0, BASE) == BASE  # the paper's tags from 0.8 m: the defaults
    assert scale_for_cell(4.2, BASE) == DetectScale(1, 1.5)  # from 2.5 m
    assert scale_for_cell(40.0, BASE) == BASE  # never coarser than configured
    cells = (0.0226, 0.009)
    # At 0.25 m a big tag does not fit in the image: the pad's small ones set the scale.
    assert scale_at_height(0.25, cells, 460.0, 360, BASE) == scale_for_cell(0.009 * 460 / 0.25, BASE)
    assert scale_at_height(2.5, cells, 460.0, 360, BASE) == scale_for_cell(0.0226 * 460 / 2.5, BASE)
    ksizes = [scale_at_height(h, cells, 460.0, 360, BASE).ksize for h in (0.8, 1.6, 2.5)]
    assert ksizes == sorted(ksizes, reverse=True)
    assert ksizes[0] > ksizes[-1]


def test_every_scale_decimates_as_apriltag_does(shipped_map: TagMap) -> None:
    # AprilTag shrinks the image by 1.5 or by a whole factor only, and scales the quads back by the factor asked.
    assert [honoured_decimation(d) for d in (1.0, 1.25, 1.5, 1.75, 2.0, 2.25, 2.5, 2.75, 3.0)] == [
        1.0, 1.0, 1.5, 1.5, 2.0, 2.0, 2.0, 2.0, 3.0,
    ]  # fmt: skip
    for focal_px, short_px in ((460.0, 360), (420.0, 400), (520.0, 600), (980.0, 720)):
        chooser = ScaleChooser(shipped_map, focal_px, short_px, BASE)
        for height_m in np.arange(0.1, 3.6, 0.05):
            for scale in (chooser.at(float(height_m)), *chooser.sizes_at(float(height_m))):
                assert scale.decimate == 1.5 or scale.decimate == int(scale.decimate), (focal_px, height_m, scale)


def test_the_pads_scale_at_0_8_m_finds_its_tags(shipped_map: TagMap) -> None:
    """The pad's small tags from 0.8 m (5.2 px cells): the chosen scale decodes them with real AprilTag, where the
    decimation the cell size asks for (1.75) decodes none (the library looks at the full image and misplaces each
    quad by 75 %). If a newer AprilTag carries out 1.75, the second assertion says so."""
    cell_px = 0.009 * 460.0 / 0.8
    scale = ScaleChooser(shipped_map, 460.0, 360, BASE).sizes_at(0.8)[1]
    assert scale == scale_for_cell(cell_px, BASE) == DetectScale(3, 1.5)
    image = shipped_map.render_image()
    side = float(np.linalg.norm(np.subtract(shipped_map.tags[-1].corners_px[1], shipped_map.tags[-1].corners_px[0])))
    factor = cell_px / (side / 8.0)  # the pad's tags are the map's last; 8 cells across the border
    small = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
    detector = TagDetector(PipelineConfig().detector.model_copy(update={"isolation": "inline"}))
    try:
        pad_ids = {t.tag_id for t in pad_tags(SHIPPED)[0]}
        found = {d.tag_id for d in detector.detect(small, scale.decimate)} & pad_ids
        asked = {d.tag_id for d in detector.detect(small, 1.75)} & pad_ids
    finally:
        detector.close()
    assert len(found) >= len(pad_ids) // 2, (len(found), len(pad_ids))
    assert not asked


def test_chooser_tries_both_tag_sizes_and_cycles_the_rest(shipped_map: TagMap) -> None:
    chooser = ScaleChooser(shipped_map, 460.0, 360, BASE)
    both = chooser.sizes_at(0.8)  # over the pad's edge at 0.8 m: the big tags' scale and the small ones'
    assert len(both) == 2
    assert both[0] == BASE
    assert both[1].ksize < BASE.ksize
    tries = [chooser.to_try(frame) for frame in range(8)]
    assert all(len(t) == 1 for t in tries), "one detector scale a frame: a lost frame stays cheap"
    assert [t[0] for t in tries[:2]] == both, "before any pose: the scales of 0.8 m first"
    assert len({t[0] for t in tries}) >= 3, "lost without a height: other scales in turn"
    assert chooser.to_try(7) == tries[7], "every attempt on one frame (another partner) gets its scale"
    chooser.seen_at(2.5)  # the small tags' 1.7 px cells are not worth a run
    tries = [chooser.to_try(frame)[0] for frame in range(8, 11)]
    assert tries[0] == chooser.at(2.5), "after a pose, the next frame starts from its height"
    assert tries[1] != tries[0]
    chooser.forget()
    assert chooser.to_try(11)[0] == both[0], "a gap forgets the height: 0.8 m again"
    chooser.to_try(12)
    chooser.seen_at(2.5)  # a pose found while frame 12 is being solved: its next attempt starts the cycle
    assert chooser.to_try(12)[0] == chooser.at(2.5)


def test_track_leaves_out_tags_too_small_to_see(shipped_map: TagMap) -> None:
    edges = MapEdges.from_tag_map(shipped_map)
    assert edges.tag_cell_m is not None
    assert sorted({round(c, 4) for c in edges.tag_cell_m}) == [0.009, 0.0226]


def _pipeline_yield(arena: ArenaConfig, sim: SimConfig, frames: int, cfg: PipelineConfig) -> tuple[int, float]:
    world = SimulatedArena(arena, sim, scene_for(sim, arena))
    camera = camera_info_of(sim.camera)
    pipeline = Pipeline(
        world.tag_map, camera, cfg, arena.projector.rate_hz, pipeline_detector(cfg.detector, world.tag_map.by_id)
    )
    results = []
    truth = {}
    try:
        for f in world.frames(frames):
            truth[f.index] = np.asarray(f.truth.position_m)
            results += pipeline.process(f.index, f.image_rgb, round(f.time_s * 1e6))
        results += pipeline.flush()
    finally:
        pipeline.close()
    errors = [float(np.linalg.norm(r.pose.position_m - truth[r.index])) for r in results if r.pose is not None]
    return len(errors), max(errors, default=0.0)


@pytest.mark.slow
def test_receiver_finds_poses_from_2_5_m() -> None:
    """A hover at 2.5 m over the paper's map (tags 33 px across in the image, cells of 4 px): the
    detection sized to them acquires, and the track follows."""
    sim = SimConfig.model_validate(
        {"flight": {"path": "hover", "centre_m": [0.1, 0.2], "altitude_m": 2.5}, "content": {"kind": "map"}, "seed": 6}
    )
    cfg = PipelineConfig().model_copy(
        update={"detector": PipelineConfig().detector.model_copy(update={"isolation": "inline"})}
    )
    poses, worst_m = _pipeline_yield(ArenaConfig(), sim, 24, cfg)
    assert poses >= 12
    assert worst_m < 0.05


def test_consistency_gate_grows_with_height_above_0_8_m() -> None:
    assert gate_growth(0.25) == 1.0
    assert gate_growth(0.8) == 1.0
    assert gate_growth(1.6) == pytest.approx(2.0)
    assert gate_growth(5.0) == 3.0
    assert gate_growth(float("nan")) == 1.0
