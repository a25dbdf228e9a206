"""The whole-map search: a view with no whole tag (tags cut by the border and a drone's shadow) gives the
pose; a view without the map's signal gives nothing."""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from floorview import render_view

from ipt.config.camera_info import CameraInfo
from ipt.config.models import ArenaConfig, DetectorConfig
from ipt.geometry import R_BODY_CAM_DOWNWARD, rot_x, rot_y, rot_z
from ipt.receiver.core.demodulator import PairDifference, binarise_difference, lightness, pair_difference
from ipt.receiver.core.mapedges import MapEdges
from ipt.receiver.core.mapsearch import MapSearch, MapSearchError, level_pose, yaw_mod_90
from ipt.receiver.core.track import TrackSettings, track_pose
from ipt.receiver.detect.detector import InlineBackend, c_settings
from ipt.sender.modulator import PaperModulator
from ipt.tagmap import grid_tag_map, pixel_to_arena

U8 = npt.NDArray[np.uint8]
F64 = npt.NDArray[np.float64]

ARENA = ArenaConfig()
TAG_MAP = grid_tag_map(ARENA)
CAMERA = CameraInfo(width_px=640, height_px=360, fx_px=460.0, fy_px=460.0, cx_px=319.5, cy_px=179.5, name="test")
K = CAMERA.camera_matrix
#: Low over the floor, yawed, tilted a little (a vibrating drone); its view cut by its shadow.
POSITION_M = np.array([0.31, -0.22, 0.5])
R_ARENA_CAM = rot_z(np.deg2rad(127.0)) @ rot_x(np.deg2rad(1.5)) @ rot_y(np.deg2rad(-1.0)) @ R_BODY_CAM_DOWNWARD
#: The camera's x axis from the arena's, counter-clockwise (the search's yaw).
YAW_DEG = float(np.rad2deg(np.arctan2(R_ARENA_CAM[1, 0], R_ARENA_CAM[0, 0])))


def _render(img: U8) -> U8:
    return render_view(img, ARENA, K, POSITION_M, R_ARENA_CAM)


@pytest.fixture(scope="module")
def shadowed() -> PairDifference:
    """A pair of opposite phases over busy content, a dark disc (the drone's shadow) over the right centre."""
    rng = np.random.default_rng(5)
    w, h = ARENA.projector.width_px, ARENA.projector.height_px
    coarse = rng.integers(40, 216, (h // 8, w // 8, 3), np.uint8)
    content = np.asarray(cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC), np.uint8)
    plus, minus = PaperModulator(TAG_MAP.render_mask(), ARENA.modulation.delta_l).modulate(content, 0, 2)
    later, earlier = (lightness(_render(p)) for p in (plus, minus))
    yy, xx = np.mgrid[0:360, 0:640]
    disc = (xx - 420) ** 2 + (yy - 140) ** 2 < 170**2
    lit = np.where(disc, 0, 255).astype(np.uint8)
    for frame in (later, earlier):
        frame[disc] = rng.integers(10, 20, int(disc.sum()))
    return pair_difference(earlier, later, np.eye(3), lit, lit)


@pytest.fixture(scope="module")
def search() -> MapSearch:
    return MapSearch.of(TAG_MAP)


def test_the_search_works_at_the_grid_s_code_cell(search: MapSearch) -> None:
    edges = MapEdges.from_tag_map(TAG_MAP)
    assert edges.tag_cell_m is not None
    assert search.cell_m == pytest.approx(float(np.median(edges.tag_cell_m)), rel=1e-3)


def test_the_view_shows_no_whole_tag(shadowed: PairDifference) -> None:
    """The premise: AprilTag finds nothing on this difference, in either phase."""
    backend = InlineBackend(c_settings(DetectorConfig()))
    try:
        for sign in (1, -1):
            assert backend.detect_raw(binarise_difference(shadowed, sign, 3)) == []
    finally:
        backend.close()


def test_the_yaw_mod_90_comes_from_the_edges(shadowed: PairDifference) -> None:
    yaw, _ = yaw_mod_90(shadowed.diff, shadowed.valid)
    error = (np.rad2deg(yaw) - YAW_DEG + 45.0) % 90.0 - 45.0
    assert abs(error) < 1.5


def test_a_view_without_a_whole_tag_gives_the_pose(shadowed: PairDifference, search: MapSearch) -> None:
    """Among the few placements is the right one (within a few cm and degrees), and the first the track
    accepts (as the pipeline checks it: inliers and cell agreement) is the pose to the millimetre."""
    found = search.search(shadowed.diff, shadowed.valid, K)
    assert 0 < len(found) <= search.settings.hypotheses
    assert any(
        np.linalg.norm(h.position_m - POSITION_M) < 0.03
        and abs((np.rad2deg(h.yaw_rad) - YAW_DEG + 180.0) % 360.0 - 180.0) < 2.0
        for h in found
    )
    edges = MapEdges.from_tag_map(TAG_MAP)
    accepted = None
    for h in found:
        try:
            tracked = track_pose(
                shadowed.diff, K, edges, h.rvec, h.tvec, TrackSettings(), None, shadowed.valid, coarse_px=h.search_px
            )
        except np.linalg.LinAlgError:
            continue
        if tracked is not None and tracked.inlier_fraction >= 0.35 and tracked.cell_agreement >= 0.75:
            accepted = tracked
            break
    assert accepted is not None
    assert np.linalg.norm(accepted.estimate().position_m - POSITION_M) < 0.003


def test_a_view_without_the_map_gives_nothing(search: MapSearch) -> None:
    rng = np.random.default_rng(1)
    noise = np.asarray(cv2.GaussianBlur(rng.normal(0, 2.0, (360, 640)).astype(np.float32), (0, 0), 1.0), np.float32)
    assert search.search(noise, np.full((360, 640), 255, np.uint8), K) == []
    assert search.search(np.zeros((360, 640), np.float32), np.zeros((360, 640), np.uint8), K) == []


def test_a_level_pose_looks_down_at_its_yaw() -> None:
    rvec, tvec = level_pose(np.array([0.1, 0.2, 0.7]), np.deg2rad(30.0))
    r_cam, _ = cv2.Rodrigues(rvec)
    assert np.allclose(-r_cam.T @ tvec, [0.1, 0.2, 0.7])
    assert np.allclose(r_cam.T[:, 2], [0.0, 0.0, -1.0])  # the optical axis points down
    assert np.allclose(r_cam.T[:, 0], [np.cos(np.pi / 6), np.sin(np.pi / 6), 0.0])


def test_a_map_without_tags_cannot_be_searched() -> None:
    with pytest.raises(MapSearchError, match="no tags"):
        MapSearch(np.zeros((100, 100), np.int8), np.eye(3), 0.02)


@pytest.mark.parametrize("shape", [(36, 50), (35, 49)])
def test_the_packed_correlation_is_the_circular_one(shape: tuple[int, int]) -> None:
    """The search correlates in OpenCV's packed half spectrum of a real image (even and odd sizes pack differently):
    corr(t) = sum over q of patch(q) * map(q + t), circularly, as numpy's complex transforms give it."""
    from ipt.receiver.core.mapsearch import _correlate

    rng = np.random.default_rng(3)
    flat_map = rng.normal(size=shape).astype(np.float32)
    patch = np.zeros(shape, np.float32)
    patch[:7, :9] = rng.normal(size=(7, 9))
    got = _correlate(patch, cv2.dft(flat_map))
    want = np.real(np.fft.ifft2(np.fft.fft2(flat_map) * np.conj(np.fft.fft2(patch))))
    assert got.shape == shape
    assert np.abs(got - want).max() < 1e-4 * np.abs(want).max()
    t = (3, 11)  # one shift by hand
    rolled = np.roll(flat_map, (-t[0], -t[1]), axis=(0, 1))
    assert got[t] == pytest.approx(float((patch * rolled).sum()), rel=1e-4, abs=1e-3)


def test_the_pipeline_renders_the_map_s_mask_once_for_both_of_its_searches(monkeypatch: pytest.MonkeyPatch) -> None:
    """The coarse search's mask renderer and the whole map's search share one rendering of the mask (20 ms at the
    shipped 1920x2160, before a restarted daemon's first pose), and the map search made from it is the one a
    rendering of its own gives."""
    from ipt.config.models import PipelineConfig
    from ipt.receiver.core.pipeline import Pipeline
    from ipt.receiver.detect.detector import pipeline_detector
    from ipt.tagmap import TagMap

    real = TagMap.render_mask
    rendered: list[TagMap] = []

    def counted(self: TagMap) -> npt.NDArray[np.int8]:
        rendered.append(self)
        return real(self)

    monkeypatch.setattr(TagMap, "render_mask", counted)
    cfg = PipelineConfig()
    pipeline = Pipeline(TAG_MAP, CAMERA, cfg, 60.0, pipeline_detector(cfg.detector, TAG_MAP.by_id))
    assert pipeline.masks is not None
    assert len(rendered) == 1
    shared = pipeline.acquisition.searcher()
    assert len(rendered) == 1
    assert pipeline.acquisition.searcher() is shared
    own = MapSearch.of(TAG_MAP)
    assert len(rendered) == 2
    assert shared.map.tobytes() == own.map.tobytes()
    assert (shared.origin_m == own.origin_m).all()
    assert shared.mean_energy == own.mean_energy


def test_the_coarse_map_is_the_whole_mask_blurred_at_full_resolution(search: MapSearch) -> None:
    """The map is built from the mask's 4 x 4 means and a smaller Gaussian (a tenth of the time): it matches the
    whole-resolution Gaussian warped the same way, place for place (a misplaced square's offset would show as a
    shift of the tags' edges, errors of order 1 at every edge)."""
    mask = TAG_MAP.render_mask()
    index_to_arena = np.array(
        [[search.res_m, 0.0, search.origin_m[0]], [0.0, search.res_m, search.origin_m[1]], [0.0, 0.0, 1.0]]
    )
    edge_to_index = np.array([[1.0, 0.0, -0.5], [0.0, 1.0, -0.5], [0.0, 0.0, 1.0]])
    to_mask = edge_to_index @ np.linalg.inv(pixel_to_arena(TAG_MAP)) @ index_to_arena
    px_per_index = float(np.sqrt(abs(np.linalg.det(to_mask[:2, :2]))))
    assert px_per_index > 8  # (the shipped arena: the 4 x 4 means are used)
    whole = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 0.4 * px_per_index)
    h, w = search.map.shape
    reference = cv2.warpPerspective(whole, to_mask, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    error = np.abs(search.map - reference)
    assert float(error.max()) < 0.1
    assert float(np.sqrt(np.mean(error**2))) < 0.02
    assert float(np.sqrt(np.mean(reference**2))) > 0.3  # (a map with tags on it)
