"""The measured floor mapping: ``ipt calibrate arena --points`` and every part that maps through it.

A known keystone homography gives the "measured" points (with and without noise); the real CLI must
recover it, print a residual per point, name a point that is off, write the ``floor:`` section without
disturbing the rest of the file, and refuse bad points files with one line naming the file and the row,
leaving the arena file as it was. The tag map, the simulator and the sender's overlay must then all use
that one mapping, and an arena without it must map exactly as before.
"""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import yaml

from ipt.calib.floor import fit_floor, parse_points, update_floor_yaml
from ipt.config.models import ArenaConfig, FloorConfig, load_arena_config
from ipt.receiver.core.mapedges import MapEdges
from ipt.sender.content import GeneratedScene
from ipt.sender.overlay import ArOverlay
from ipt.sim.arena import SimulatedArena, survey_points, true_arena
from ipt.sim.config import KeystoneConfig, SimConfig
from ipt.sim.run import simulate_to_folder
from ipt.tagmap import arena_to_pixel_matrix, grid_tag_map, pixel_to_arena, pixel_to_arena_m, pixel_to_floor_matrix

F64 = npt.NDArray[np.float64]

ROOT = Path(__file__).resolve().parents[1]
PAPER = ArenaConfig()
W, H = PAPER.projector.width_px, PAPER.projector.height_px
# A projector tilted forward and turned a little: the corners land up to 13 cm from the uniform layout.
SHIFT = ((-0.11, 0.07), (0.12, 0.05), (0.035, -0.02), (-0.03, -0.015))
KEYSTONED = true_arena(PAPER, SimConfig(keystone=KeystoneConfig(corner_shift_m=SHIFT)))
TRUE_H = pixel_to_floor_matrix(KEYSTONED)

ARENA_TEXT = """# my arena, measured on 3 May
projector:
  width_px: 1920
  height_px: 2160   # two projectors
screen:
  width_m: 2.17
  height_m: 2.47
modulation:
  delta_l: 4
"""


def _floor(h: F64, u: float, v: float) -> tuple[float, float]:
    q = h @ np.array([u, v, 1.0])
    return float(q[0] / q[2]), float(q[1] / q[2])


def _grid(cols: int = 3, rows: int = 3) -> list[tuple[float, float]]:
    return [(float(u), float(v)) for v in np.linspace(100, H - 100, rows) for u in np.linspace(100, W - 100, cols)]


def _csv(pixels: list[tuple[float, float]], noise_m: float = 0.0, seed: int = 0) -> str:
    rng = np.random.default_rng(seed)
    lines = ["u_px,v_px,x_m,y_m"]
    for u, v in pixels:
        x, y = _floor(TRUE_H, u, v)
        dx, dy = rng.normal(0, noise_m, 2) if noise_m else (0.0, 0.0)
        lines.append(f"{u:g},{v:g},{x + dx:.6f},{y + dy:.6f}")
    return "\n".join(lines) + "\n"


def _ipt(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ipt.cli", *args], capture_output=True, text=True, timeout=120, cwd=cwd, check=False
    )


def _worst_floor_error_m(h: F64, truth: F64) -> float:
    us, vs = np.meshgrid(np.linspace(0, W, 9), np.linspace(0, H, 9))
    pts = np.column_stack([us.ravel(), vs.ravel(), np.ones(us.size)]).T
    a, b = h @ pts, truth @ pts
    return float(np.max(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0)))


# --- the fit ------------------------------------------------------------------------------------------


def test_exact_points_give_the_homography_back() -> None:
    path = Path("p.csv")
    fit = fit_floor(path, parse_points(path, _csv(_grid()), W, H), W, H)
    # The file holds micrometres (6 decimals): the fit is exact to that.
    assert _worst_floor_error_m(fit.pixel_to_floor, TRUE_H) < 3e-6
    assert fit.rms_m < 1e-6
    assert fit.far == ()
    assert fit.left_out_m is not None
    assert float(fit.left_out_m.max()) < 1e-5


def test_nine_points_with_a_millimetre_of_noise_map_the_whole_floor_within_a_few_millimetres() -> None:
    path = Path("p.csv")
    worst = []
    for seed in range(5):
        fit = fit_floor(path, parse_points(path, _csv(_grid(), 0.001, seed), W, H), W, H)
        worst.append(_worst_floor_error_m(fit.pixel_to_floor, TRUE_H))
        assert 0.0003 < fit.rms_m < 0.002
        assert fit.far == ()
    print(f"worst floor error over the image, 9 points with 1 mm noise: {[f'{1e3 * w:.2f} mm' for w in worst]}")
    assert max(worst) < 0.004


def test_a_spreadsheets_csv_reads_as_written() -> None:
    text = "\ufeffx_m,y_m,u_px,v_px\r\n# taped 3 May\r\n0.5,0.25,100,200\r\n\r\n"
    (p,) = parse_points(Path("p.csv"), text, W, H)
    assert (p.row, p.u_px, p.v_px, p.x_m, p.y_m) == (3, 100.0, 200.0, 0.5, 0.25)


def test_a_point_two_centimetres_off_is_the_one_named() -> None:
    path = Path("p.csv")
    points = parse_points(path, _csv(_grid(), 0.001, 3), W, H)
    bad = points[4]
    points[4] = type(bad)(bad.row, bad.u_px, bad.v_px, (bad.x_m or 0) + 0.02, bad.y_m)
    fit = fit_floor(path, points, W, H)
    assert fit.far == (4,)


# --- the CLI ------------------------------------------------------------------------------------------


def test_cli_writes_the_floor_section_and_leaves_the_rest_of_the_file(tmp_path: Path) -> None:
    (tmp_path / "arena.yaml").write_text(ARENA_TEXT, encoding="utf-8")
    (tmp_path / "points.csv").write_text(_csv(_grid(), 0.001, 1), encoding="utf-8")
    out = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "points.csv", "--output", "cal.yaml",
               cwd=tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr
    print(out.stdout)
    assert (tmp_path / "arena.yaml").read_text(encoding="utf-8") == ARENA_TEXT  # --output: untouched
    lines = out.stdout.splitlines()
    table = [ln for ln in lines if ln.strip()[:1].isdigit()]
    assert len(table) == 9
    assert all(" mm" in ln for ln in table)
    assert "RMS" in out.stdout
    assert re.search(r"up to 13\.\d cm", out.stdout)
    text = (tmp_path / "cal.yaml").read_text(encoding="utf-8")
    assert text.startswith(ARENA_TEXT)  # comments, order and values kept; the section appended
    cal = load_arena_config(tmp_path / "cal.yaml")
    assert cal.floor is not None
    assert cal.floor.points == 9
    assert _worst_floor_error_m(pixel_to_floor_matrix(cal), TRUE_H) < 0.004
    # Measuring again replaces the section in place (and keeps a backup of the file as it was).
    (tmp_path / "points.csv").write_text(_csv(_grid(4, 4), 0.0005, 2), encoding="utf-8")
    again = _ipt("calibrate", "arena", "--config", "cal.yaml", "--points", "points.csv", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert (tmp_path / "cal.yaml.bak").read_text(encoding="utf-8") == text
    new = load_arena_config(tmp_path / "cal.yaml")
    assert new.floor is not None
    assert new.floor.points == 16
    assert (tmp_path / "cal.yaml").read_text(encoding="utf-8").count("\nfloor:") == 1


def test_cli_names_a_point_more_than_a_centimetre_off(tmp_path: Path) -> None:
    (tmp_path / "arena.yaml").write_text(ARENA_TEXT, encoding="utf-8")
    rows = _csv(_grid(), 0.001, 4).splitlines()
    u, v, x, y = rows[7].split(",")
    rows[7] = f"{u},{v},{x},{float(y) - 0.025:.6f}"  # point 7, on line 8 of the file: 2.5 cm off
    (tmp_path / "points.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    out = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "points.csv", "--dry-run", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    named = [ln for ln in out.stdout.splitlines() if "remeasure" in ln]
    assert len(named) == 1, out.stdout
    assert "point 7 (row 8 of points.csv)" in named[0], out.stdout
    assert (tmp_path / "arena.yaml").read_text(encoding="utf-8") == ARENA_TEXT


BAD_POINTS = [
    ("three", "u_px,v_px,x_m,y_m\n100,100,0,0\n1800,100,1,0\n1800,2000,1,1\n", "3 points"),
    ("collinear", "u_px,v_px,x_m,y_m\n100,100,0,0\n500,100,0.4,0\n900,100,0.8,0\n1300,100,1.2,0\n1000,900,1,1\n",
     "rows 2, 3, 4, 5: on one line"),
    ("outside", "u_px,v_px,x_m,y_m\n100,100,0,0\n1800,100,1,0\n1800,2200,1,1\n100,2000,0,1\n", "row 4: pixel"),
    ("nan", "u_px,v_px,x_m,y_m\n100,100,0,0\n1800,100,nan,0\n1800,2000,1,1\n100,2000,0,1\n", "row 3: x_m"),
    ("no-header", "100,100,0,0\n1800,100,1,0\n1800,2000,1,1\n100,2000,0,1\n", "row 1: expected the header"),
    ("header-missing-column", "u_px,v_px,x_m\n100,100,0\n", "missing y_m"),
    ("short-row", "u_px,v_px,x_m,y_m\n100,100,0,0\n1800,100,1\n", "row 3: expected 4 values"),
    ("text", "u_px,v_px,x_m,y_m\n100,100,0,0\n1800,abc,1,0\n", "row 3: v_px is not a number"),
    ("duplicate", "u_px,v_px,x_m,y_m\n100,100,0,0\n1800,100,1,0\n100,100,0,0\n100,2000,0,1\n", "row 4: the same"),
    ("mirrored", "u_px,v_px,x_m,y_m\n0,0,0,0\n1920,0,2,0\n1920,2160,2,2\n0,2160,0,2\n", "mirrors"),
]  # fmt: skip


@pytest.mark.parametrize(("name", "text", "expected"), BAD_POINTS, ids=[b[0] for b in BAD_POINTS])
def test_bad_points_are_one_line_naming_the_file_and_row_and_the_arena_is_untouched(
    tmp_path: Path, name: str, text: str, expected: str
) -> None:
    (tmp_path / "arena.yaml").write_text(ARENA_TEXT, encoding="utf-8")
    (tmp_path / "points.csv").write_text(text, encoding="utf-8")
    out = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "points.csv", cwd=tmp_path)
    assert out.returncode == 2, (out.stdout, out.stderr)
    err = out.stderr.strip()
    assert "\n" not in err, err
    assert "Traceback" not in err, err
    assert "points.csv" in err, err
    assert expected in err, err
    assert (tmp_path / "arena.yaml").read_text(encoding="utf-8") == ARENA_TEXT
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arena.yaml", "points.csv"]  # no backup, no output


def test_marks_and_their_template_then_the_same_marks_from_it(tmp_path: Path) -> None:
    (tmp_path / "arena.yaml").write_text(ARENA_TEXT, encoding="utf-8")
    out = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "p.csv", "--marks", "m.png",
               "--grid", "4x3", cwd=tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr
    rows = (tmp_path / "p.csv").read_text(encoding="utf-8").splitlines()
    assert rows[0] == "u_px,v_px,x_m,y_m"
    assert len(rows) == 13
    assert all(r.endswith(",,") for r in rows[1:])
    img = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (H, W)
    for r in rows[1:]:
        u, v = (int(c) for c in r.split(",")[:2])
        # The cross-hair's arms cross at the pixel corner (u, v): lit along both arms, dark in the quadrants.
        assert img[v, u + 20] > 100
        assert img[v - 1, u - 20] > 100
        assert img[v + 20, u - 1] > 100
        assert img[v + 5, u + 5] < 50
    assert (tmp_path / "arena.yaml").read_text(encoding="utf-8") == ARENA_TEXT
    # Without measurements the template is not a calibration: one line naming the row.
    bad = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "p.csv", cwd=tmp_path)
    assert bad.returncode == 2
    assert "p.csv: row 2: x_m is empty" in bad.stderr
    # With the file there, --marks draws its pixels again (the same image).
    (tmp_path / "m.png").rename(tmp_path / "first.png")
    again = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "p.csv", "--marks", "m.png", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert np.array_equal(cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_GRAYSCALE), img)


def test_the_scale_methods_refuse_a_measured_floor(tmp_path: Path) -> None:
    (tmp_path / "arena.yaml").write_text(update_floor_yaml(ARENA_TEXT, KEYSTONED.floor), encoding="utf-8")  # type: ignore[arg-type]
    before = (tmp_path / "arena.yaml").read_bytes()
    out = _ipt("calibrate", "arena", "--config", "arena.yaml", "--pixels", "0,0", "100,0", "--distance-m", "0.1",
               cwd=tmp_path)  # fmt: skip
    assert out.returncode == 2
    assert "floor" in out.stderr
    assert (tmp_path / "arena.yaml").read_bytes() == before


def test_floor_yaml_replaces_a_null_section_and_keeps_comments() -> None:
    text = "# c\nprojector: {width_px: 1920, height_px: 2160}\nfloor: null\nscreen:\n  width_m: 2  # m\n"
    new = update_floor_yaml(text, KEYSTONED.floor)  # type: ignore[arg-type]
    parsed = yaml.safe_load(new)
    assert parsed["screen"] == {"width_m": 2}
    assert "# m" in new
    assert new.startswith("# c\n")
    assert ArenaConfig.model_validate(parsed).floor == KEYSTONED.floor


# --- the configuration --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("h", "expected"),
    [
        (((1e-3, 0, -1), (0, 1e-3, -1), (0, 0, 1)), "mirrors"),  # v down would be y down
        (((1e-3, 0, -1), (0, -1e-3, 1), (-1e-3, 0, 1.5)), "infinity"),  # a horizon through the image
        (((1e-3, 0, -1), (2e-3, 0, -2), (0, 0, 1)), "singular"),
        (((float("nan"), 0, -1), (0, -1e-3, 1), (0, 0, 1)), "finite"),
    ],
)
def test_unusable_floor_homographies_are_refused(h: tuple[tuple[float, ...], ...], expected: str) -> None:
    with pytest.raises(ValueError, match=expected):
        ArenaConfig.model_validate({"floor": {"pixel_to_floor": h}})


def test_without_a_floor_section_the_mapping_is_the_uniform_scale_exactly() -> None:
    sx, sy = PAPER.screen.width_m / W, PAPER.screen.height_m / H
    for u, v in [(0.0, 0.0), (123.0, 456.0), (W, H), (960.5, 1079.25)]:
        # The old formula, bit for bit.
        assert pixel_to_arena_m(PAPER, u, v) == ((u - W / 2) * sx, (H / 2 - v) * sy, 0.0)
        x, y = _floor(pixel_to_floor_matrix(PAPER), u, v)
        assert (x, y) == pytest.approx(((u - W / 2) * sx, (H / 2 - v) * sy), abs=1e-12)
    assert np.array_equal(
        arena_to_pixel_matrix(PAPER), np.array([[1 / sx, 0, W / 2], [0, -1 / sy, H / 2], [0, 0, 1]])
    )


# --- every consumer through the one mapping -----------------------------------------------------------


def test_tag_corners_edges_and_the_receivers_homography_follow_the_measured_floor() -> None:
    tm = grid_tag_map(KEYSTONED)
    assert tm.render_mask().tobytes() == grid_tag_map(PAPER).render_mask().tobytes()  # the projector image: same
    for tag in tm.tags:
        for (u, v), (x, y, z) in zip(tag.corners_px, tag.corners_m, strict=True):
            assert (x, y) == pytest.approx(_floor(TRUE_H, u, v), abs=1e-12)
            assert z == 0.0
    h = pixel_to_arena(tm)
    assert _worst_floor_error_m(h, TRUE_H) < 1e-7  # a tenth of a micrometre
    # The tracker's edge samples lie where the projector draws the cell edges, on the keystoned floor.
    edges = MapEdges.from_tag_map(tm)
    inv = np.linalg.inv(TRUE_H)
    q = inv @ np.column_stack([edges.points_m[:, :2], np.ones(len(edges.points_m))]).T
    px = q[:2] / q[2]
    cell = 160 / 8
    frac = (px - np.array([[tm.tags[0].corners_px[3][0]], [tm.tags[0].corners_px[3][1]]])) / cell
    # Every sample is on a cell boundary along one axis (a whole number of cells from a tag's corner, up
    # to float32 of OpenCV's per-tag transform) — checked on the first tag's samples.
    first = edges.tag == 0
    off = np.minimum(np.abs(frac[:, first] - np.rint(frac[:, first])).min(axis=0), 1)
    assert float(off.max()) < 1e-3


def test_the_overlay_draws_a_vehicle_on_the_pixel_that_lands_where_it_is() -> None:
    ar = ArOverlay(KEYSTONED)
    for u, v in [(100.0, 100.0), (1800.0, 2000.0), (960.0, 1080.0)]:
        x, y = _floor(TRUE_H, u, v)
        assert ar.pixel_of(x, y) == pytest.approx((u, v), abs=1e-6)
    # The heading arrow points along the floor's x axis as the keystoned image shows it there.
    x, y = _floor(TRUE_H, 1800.0, 200.0)
    du, dv = ar.heading_px(0.0, x, y)
    a, b = ar.pixel_of(x, y), ar.pixel_of(x + 1e-4, y)
    d = np.array(b) - np.array(a)
    assert (du, dv) == pytest.approx(tuple(d / np.linalg.norm(d)), abs=1e-5)
    # On (and beyond) the keystoned image's horizon a pose maps nowhere: no division by zero, nothing drawn.
    g, _h, k = np.linalg.inv(TRUE_H)[2]
    assert ar.pixel_of(-k / g, 0.0) == (math.inf, math.inf)
    assert ar.pixel_of(-2 * k / g, 0.0) == (math.inf, math.inf)


def test_the_simulator_lays_the_keystoned_image_and_writes_its_survey(tmp_path: Path) -> None:
    sim = SimConfig.smooth(keystone=KeystoneConfig(corner_shift_m=SHIFT, survey_noise_m=0.001), seed=3)
    world = SimulatedArena(PAPER, sim, GeneratedScene(W, H, seed=3))
    assert np.allclose(world.renderer.arena_to_px, np.linalg.inv(TRUE_H) / np.linalg.inv(TRUE_H)[2, 2] *
                       world.renderer.arena_to_px[2, 2], atol=1e-9)  # fmt: skip
    # Corners: where the flight says, relative to the file's layout.
    for (u, v), (dx, dy) in zip([(0, 0), (W, 0), (W, H), (0, H)], SHIFT, strict=True):
        x0, y0, _ = pixel_to_arena_m(PAPER, u, v)
        assert _floor(TRUE_H, u, v) == pytest.approx((x0 + dx, y0 + dy), abs=1e-12)
    survey = survey_points(PAPER, sim)
    err = np.array([np.subtract((x, y), _floor(TRUE_H, u, v)) for u, v, x, y in survey])
    assert len(survey) == 9
    assert 0.0002 < float(np.std(err)) < 0.003
    n = simulate_to_folder(PAPER, sim, GeneratedScene(W, H, seed=3), tmp_path, 2 / 120, progress=None)
    assert n == 2
    rows = (tmp_path / "survey.csv").read_text(encoding="utf-8").splitlines()
    assert rows[0] == "u_px,v_px,x_m,y_m"
    assert len(rows) == 10
    flown = load_arena_config(tmp_path / "arena.yaml")
    assert flown.floor is None  # the receiver is told the file's layout, not the truth
    fl = FloorConfig.model_validate({"pixel_to_floor": TRUE_H.tolist()})
    assert fl.pixel_to_floor[2][2] == pytest.approx(1.0)


# --- several projectors ---------------------------------------------------------------------------------

TILES = {
    "projectors": [
        {"x_px": 0, "y_px": 0, "width_px": 1920, "height_px": 1080},
        {"x_px": 0, "y_px": 1080, "width_px": 1920, "height_px": 1080},
    ]
}
TWO = ArenaConfig.model_validate(TILES)
ZERO = ((0.0, 0.0), (0.0, 0.0), (0.0, 0.0), (0.0, 0.0))
OFF_1CM = ((0.01, 0.0), (0.01, 0.0), (0.01, 0.0), (0.01, 0.0))
TWO_TRUE = true_arena(TWO, SimConfig(keystone=KeystoneConfig(tile_corner_shift_m=(ZERO, OFF_1CM))))


@pytest.mark.parametrize(
    ("tiles", "expected"),
    [
        ([{"x_px": 0, "y_px": 0, "width_px": 1920, "height_px": 1200}, {"x_px": 0, "y_px": 1080, "width_px": 1920,
          "height_px": 1080}], "overlaps"),
        ([{"x_px": 0, "y_px": 0, "width_px": 1920, "height_px": 1080}], "cover the whole"),
        ([{"x_px": 100, "y_px": 0, "width_px": 1920, "height_px": 2160}], "outside"),
    ],
)  # fmt: skip
def test_tiles_must_partition_the_canvas(tiles: list[dict[str, int]], expected: str) -> None:
    with pytest.raises(ValueError, match=expected):
        ArenaConfig.model_validate({"projectors": tiles})
    with pytest.raises(ValueError, match="not both"):
        ArenaConfig.model_validate({**TILES, "floor": {"pixel_to_floor": TRUE_H.tolist()}})


def test_tags_stay_out_of_the_seam_and_take_their_own_projectors_mapping() -> None:
    tm = grid_tag_map(TWO_TRUE)
    assert sorted(set(range(81)) - set(tm.by_id)) == list(range(36, 45))  # the middle row crosses the seam
    for tag in tm.tags:
        tile = 0 if tag.corners_px[0][1] <= 1080 else 1
        h = pixel_to_floor_matrix(TWO_TRUE, tile)
        for (u, v), (x, y, _) in zip(tag.corners_px, tag.corners_m, strict=True):
            assert (x, y) == pytest.approx(_floor(h, u, v), abs=1e-12)
    lower = tm.by_id[4].corners_m[0][0] - grid_tag_map(TWO).by_id[4].corners_m[0][0]
    upper = tm.by_id[76].corners_m[0][0] - grid_tag_map(TWO).by_id[76].corners_m[0][0]
    assert (lower, upper) == pytest.approx((0.01, 0.0), abs=1e-12)  # the lower projector is 1 cm off
    ar = ArOverlay(TWO_TRUE)
    for u, v in [(500.0, 300.0), (500.0, 1900.0), (1500.0, 1100.0)]:
        x, y, _ = pixel_to_arena_m(TWO_TRUE, u, v)
        assert ar.pixel_of(x, y) == pytest.approx((u, v), abs=1e-6)


def test_tiles_calibrated_each_from_its_own_points(tmp_path: Path) -> None:
    (tmp_path / "arena.yaml").write_text("# two\n" + yaml.safe_dump(TILES, sort_keys=False), encoding="utf-8")
    survey = survey_points(TWO, SimConfig(keystone=KeystoneConfig(tile_corner_shift_m=(ZERO, OFF_1CM)), seed=1))
    rows = ["u_px,v_px,x_m,y_m", *(f"{u:g},{v:g},{x:.6f},{y:.6f}" for u, v, x, y in survey)]
    (tmp_path / "p.csv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    out = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "p.csv", "--output", "cal.yaml",
               cwd=tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "projector 2 (x 0-1920, y 1080-2160): RMS" in out.stdout
    cal = load_arena_config(tmp_path / "cal.yaml")
    assert cal.projectors is not None
    assert [t.points for t in cal.projectors] == [9, 9]
    # Along the seam, both sides land within 4 mm of the truth (1 mm noise on 9 marks each).
    for tile in (0, 1):
        v = 1080.0
        for u in np.linspace(0, W, 9):
            got = _floor(pixel_to_floor_matrix(cal, tile), float(u), v)
            want = _floor(pixel_to_floor_matrix(TWO_TRUE, tile), float(u), v)
            assert math.dist(got, want) < 0.004
    # The marks to measure: a grid in each projector's part of the canvas.
    marks = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "m.csv", "--marks", "m.png", cwd=tmp_path)
    assert marks.returncode == 0, marks.stderr
    pix = [tuple(int(c) for c in r.split(",")[:2]) for r in (tmp_path / "m.csv").read_text().splitlines()[1:]]
    assert len(pix) == 18
    assert sum(v < 1080 for _, v in pix) == 9
    # A projector with fewer than four points: one line naming the file and that projector.
    (tmp_path / "p.csv").write_text("\n".join(rows[:13]) + "\n", encoding="utf-8")
    bad = _ipt("calibrate", "arena", "--config", "arena.yaml", "--points", "p.csv", cwd=tmp_path)
    assert bad.returncode == 2
    assert "p.csv: 3 points in projector 2 (x 0-1920, y 1080-2160)" in bad.stderr
    assert not (tmp_path / "arena.yaml.bak").exists()


def test_two_projectors_that_agree_render_as_one() -> None:
    sim = SimConfig.smooth(seed=2)
    sim = sim.model_copy(update={"flight": sim.flight.model_copy(update={"path": "hover", "centre_m": (0.1, 0.0)})})
    tm = grid_tag_map(TWO)  # the same tags drawn (the two-projector map leaves the seam's row out)
    one = SimulatedArena(PAPER, sim, GeneratedScene(W, H, seed=2), tm).render(3).image_rgb.astype(int)
    two = SimulatedArena(TWO, sim, GeneratedScene(W, H, seed=2), tm).render(3).image_rgb.astype(int)
    # Bilinear sampling is linear in the image: the two crops, each black beyond its seam, add up to the
    # whole exactly (up to the order of float sums), so no seam shows where the projectors agree.
    assert int(np.abs(one - two).max()) <= 1
    shifted = SimConfig(**{**sim.model_dump(), "keystone": {"tile_corner_shift_m": (ZERO, OFF_1CM)}})
    off = SimulatedArena(TWO, shifted, GeneratedScene(W, H, seed=2), tm).render(3).image_rgb.astype(int)
    assert (np.abs(off - two).max(axis=2) > 4).mean() > 0.1  # half the view moved by 1 cm (6 px)
