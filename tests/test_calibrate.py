"""``ipt calibrate camera`` and ``ipt calibrate arena`` on images rendered from a known camera.

Camera: a chessboard (and a ChArUco board) rendered exactly through a known pinhole + plumb_bob camera, at
varied poses; the real CLI must recover fx, fy within 1 % and the principal point within 2 px. Arena: the
plain tag map rendered by the simulator's camera from a known height, measured with a wrongly scaled arena
config; the CLI must find the true size and write it back without disturbing the user's file.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import yaml

from ipt.calib.arena import (
    ArenaCalibrationError,
    factor_from_points,
    scaled_arena,
    tag_centre_px,
    update_screen_yaml,
)
from ipt.calib.camera import Board, CalibrationError, calibrate_camera
from ipt.config.camera_info import CameraInfo, load_camera_info, save_camera_info
from ipt.config.models import ArenaConfig, load_arena_config
from ipt.geometry import matrix_from_ypr, rot_x, rot_y, rot_z
from ipt.sim.config import SimCameraConfig
from ipt.sim.flight import FlightState
from ipt.sim.render import CameraRenderer, Exposure, camera_info_of
from ipt.tagmap import arena_to_pixel_matrix, grid_tag_map

U8 = npt.NDArray[np.uint8]

TRUE_CAMERA = CameraInfo(640, 480, 600.0, 612.0, 326.3, 233.8, (-0.12, 0.06, 0.0008, -0.0005, 0.0), "truth")
SUPERSAMPLE = 3


def _rays(cam: CameraInfo) -> npt.NDArray[np.float64]:
    """Normalised ray (x/z, y/z) of every supersampled pixel, through the true distortion."""
    ss = SUPERSAMPLE
    xs = (np.arange(cam.width_px * ss) + 0.5) / ss - 0.5
    ys = (np.arange(cam.height_px * ss) + 0.5) / ss - 0.5
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    und = cv2.undistortPoints(grid, cam.camera_matrix, cam.dist_coeffs, criteria=crit)
    return np.asarray(und, np.float64).reshape(cam.height_px * ss, cam.width_px * ss, 2)


def _render_plane(
    rays: npt.NDArray[np.float64],
    cam: CameraInfo,
    texture: U8,
    texels_per_m: float,
    r_cam_board: npt.NDArray[np.float64],
    t_cam_board: npt.NDArray[np.float64],
    rng: np.random.Generator,
) -> U8:
    """What the camera sees of a flat textured board (texture's top-left corner at the board origin, x right,
    y down, z = 0), surrounded by white."""
    d = np.concatenate([rays, np.ones((*rays.shape[:2], 1))], axis=-1)  # ray directions, camera frame
    rt = r_cam_board.T
    d_b = d @ rt.T  # directions in board axes
    o_b = -rt @ t_cam_board  # camera centre in board frame
    s = -o_b[2] / d_b[..., 2]
    x = o_b[0] + s * d_b[..., 0]
    y = o_b[1] + s * d_b[..., 1]
    map_x = (x * texels_per_m - 0.5).astype(np.float32)
    map_y = (y * texels_per_m - 0.5).astype(np.float32)
    fine = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=235)
    img = cv2.resize(fine.astype(np.float32), (cam.width_px, cam.height_px), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 0.5) + rng.normal(0.0, 1.5, img.shape)
    return np.asarray(np.clip(np.rint(img), 0, 255), dtype=np.uint8)


def _chessboard_texture(cols: int, rows: int, texels_per_square: int) -> U8:
    """(cols + 1) x (rows + 1) squares, dark in the top-left, so (cols x rows) inner corners."""
    i, j = np.meshgrid(np.arange((cols + 1) * texels_per_square), np.arange((rows + 1) * texels_per_square))
    dark = ((i // texels_per_square) + (j // texels_per_square)) % 2 == 0
    return np.where(dark, 20, 235).astype(np.uint8)


def _views(texture: U8, texels_per_m: float, size_m: tuple[float, float], n: int, seed: int) -> list[U8]:
    rng = np.random.default_rng(seed)
    rays = _rays(TRUE_CAMERA)
    centre = np.array([size_m[0] / 2, size_m[1] / 2, 0.0])
    out = []
    for k in range(n):
        tilt_x = math.radians(rng.uniform(-35, 35))
        tilt_y = math.radians(rng.uniform(-35, 35))
        spin = math.radians(rng.uniform(-25, 25) + (90 if k % 4 == 3 else 0))
        r = rot_x(tilt_x) @ rot_y(tilt_y) @ rot_z(spin)
        dist = rng.uniform(0.42, 0.6)
        shift = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04), dist])
        t = -r @ centre + shift
        out.append(_render_plane(rays, TRUE_CAMERA, texture, texels_per_m, r, t, rng))
    return out


def _ipt(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ipt.cli", *args], capture_output=True, text=True, timeout=300, cwd=cwd, check=False
    )


def _check_recovered(cam: CameraInfo) -> tuple[float, float, float, float]:
    fx_err = abs(cam.fx_px / TRUE_CAMERA.fx_px - 1)
    fy_err = abs(cam.fy_px / TRUE_CAMERA.fy_px - 1)
    cx_err = abs(cam.cx_px - TRUE_CAMERA.cx_px)
    cy_err = abs(cam.cy_px - TRUE_CAMERA.cy_px)
    assert fx_err < 0.01, cam.fx_px
    assert fy_err < 0.01, cam.fy_px
    assert cx_err < 2.0, cam.cx_px
    assert cy_err < 2.0, cam.cy_px
    return fx_err, fy_err, cx_err, cy_err


@pytest.mark.slow
def test_calibrate_camera_cli_recovers_a_known_camera_from_chessboard_images(tmp_path: Path) -> None:
    cols, rows, square_m = 9, 6, 0.03
    texels = 60
    texture = _chessboard_texture(cols, rows, texels)
    views = _views(texture, texels / square_m, ((cols + 1) * square_m, (rows + 1) * square_m), 14, seed=3)
    folder = tmp_path / "views"
    folder.mkdir()
    for k, img in enumerate(views):
        cv2.imwrite(str(folder / f"view{k:02d}.png"), img)
    cv2.imwrite(str(folder / "blank.png"), np.full((480, 640), 128, np.uint8))  # no board in this one
    out = _ipt(
        "calibrate", "camera", "--images", str(folder), "--cols", str(cols), "--rows", str(rows),
        "--square-m", str(square_m), "--output", "camera.yaml", cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    cam = load_camera_info(tmp_path / "camera.yaml")
    fx_err, fy_err, cx_err, cy_err = _check_recovered(cam)
    assert "board found in 14 of 15 images (no board in: blank.png)" in out.stdout
    rms = float(out.stdout.split("reprojection RMS ")[1].split(" px")[0])
    assert rms < 0.5
    assert (cam.width_px, cam.height_px) == (640, 480)
    print(
        f"chessboard: fx {cam.fx_px:.2f} ({100 * fx_err:.3f} %), fy {cam.fy_px:.2f} ({100 * fy_err:.3f} %), "
        f"cx {cam.cx_px:.2f} ({cx_err:.2f} px), cy {cam.cy_px:.2f} ({cy_err:.2f} px), RMS {rms:.3f} px"
    )


def test_calibrate_camera_recovers_a_known_camera_from_charuco_views() -> None:
    board = Board("charuco", 7, 5, 0.04, marker_m=0.03, dictionary="DICT_5X5_100")
    texels = 80
    texture = np.asarray(board.charuco().generateImage((7 * texels, 5 * texels), marginSize=0), np.uint8)
    views = _views(texture, texels / 0.04, (0.28, 0.20), 10, seed=5)
    result = calibrate_camera(((f"v{k}", v) for k, v in enumerate(views)), board)
    fx_err, fy_err, cx_err, cy_err = _check_recovered(result.camera)
    assert len(result.views) >= 8
    print(f"charuco: fx {100 * fx_err:.3f} %, fy {100 * fy_err:.3f} %, cx {cx_err:.2f} px, cy {cy_err:.2f} px")


def test_images_without_a_board_are_one_clear_line(tmp_path: Path) -> None:
    blank = np.full((120, 160), 128, np.uint8)
    with pytest.raises(CalibrationError, match=r"found in 0 of 2 images; at least 3 .*inner corners"):
        calibrate_camera([("a.png", blank), ("b.png", blank)], Board("chessboard", 9, 6, 0.025))
    with pytest.raises(CalibrationError, match="one camera mode at a time"):
        calibrate_camera([("a.png", blank), ("b.png", blank[:100])], Board("chessboard", 9, 6, 0.025))
    with pytest.raises(CalibrationError, match="marker size"):
        Board("charuco", 7, 5, 0.04, marker_m=0.05)
    folder = tmp_path / "none"
    folder.mkdir()
    for name in ("a.png", "b.png", "c.png"):
        cv2.imwrite(str(folder / name), blank)
    (tmp_path / "notes.txt").write_text("not an image")
    for args in (
        ["--images", str(folder)],
        ["--images", str(tmp_path / "missing")],
        ["--images", str(tmp_path / "notes.txt")],
    ):
        out = _ipt(
            "calibrate", "camera", *args, "--cols", "9", "--rows", "6", "--square-m", "0.025", "--output",
            "c.yaml", cwd=tmp_path,
        )  # fmt: skip
        assert out.returncode == 2, out.stderr
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr
        assert out.stderr.startswith("ipt: error: ")
    assert not (tmp_path / "c.yaml").exists()


# --- the arena -----------------------------------------------------------------------------------

ARENA_FILE = """\
# Our lab's arena: comments and the order of keys must survive calibration.
projector:
  width_px: 1920        # output width
  height_px: 2160
  rate_hz: 60
screen:
  width_m: {w}          # measured with a tape in 2024
  height_m: {h}   # ditto
tag_map:
  rows: 9
  cols: 9
"""


def _map_photo(arena: ArenaConfig, height_m: float, seed: int) -> tuple[U8, CameraInfo]:
    """The plain tag map projected with ``arena``'s true size, seen by the simulator's camera from above."""
    cfg = SimCameraConfig()
    renderer = CameraRenderer(cfg, arena_to_pixel_matrix(arena), (arena.projector.width_px, arena.projector.height_px))
    image = grid_tag_map(arena).render_image()
    rgb = np.repeat(image[:, :, None], 3, axis=2)
    r_arena_flu = matrix_from_ypr(0.3, 0.02, -0.03)
    r_arena_cam = r_arena_flu @ np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    state = FlightState(np.array([0.07, -0.12, height_m]), r_arena_cam, np.zeros(3))

    def crop(_: int, region: tuple[int, int, int, int]) -> U8:
        x0, y0, x1, y1 = region
        return np.ascontiguousarray(rgb[y0:y1, x0:x1])

    photo = renderer.render([Exposure(state, 0)], crop, np.random.default_rng(seed))
    gray = np.asarray(cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY), np.uint8)
    return gray, camera_info_of(cfg)


@pytest.mark.slow
def test_calibrate_arena_from_a_camera_at_a_measured_height_writes_the_config_back(tmp_path: Path) -> None:
    truth = ArenaConfig()  # 2.17 x 2.47 m
    config = tmp_path / "arena.yaml"
    original = ARENA_FILE.format(w="2.0", h="2.27")  # the lab's first, wrong guess
    config.write_text(original)
    height_m = 1.3
    for k, seed in enumerate((1, 2)):
        photo, camera = _map_photo(truth, height_m, seed)
        cv2.imwrite(str(tmp_path / f"map{k}.png"), photo)
    save_camera_info(camera, tmp_path / "camera.yaml")
    out = _ipt(
        "calibrate", "arena", "--config", str(config), "--camera", "camera.yaml", "--image", "map0.png",
        "--image", "map1.png", "--height-m", str(height_m), cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    new = load_arena_config(config)
    w_err = abs(new.screen.width_m / truth.screen.width_m - 1)
    assert w_err < 0.005, new.screen
    # the pixel aspect of the first guess is kept (2.0 x 2.27), so the height lands within the same bound
    assert new.screen.height_m / new.screen.width_m == pytest.approx(2.27 / 2.0, rel=1e-4)
    text = config.read_text()
    assert text.splitlines()[0] == original.splitlines()[0]
    assert "width_m: " in text
    assert "# measured with a tape in 2024" in text
    assert "# ditto" in text
    assert [line for line in text.splitlines() if "_m:" not in line] == [
        line for line in original.splitlines() if "_m:" not in line
    ]
    assert (tmp_path / "arena.yaml.bak").read_text() == original
    print(f"arena from height: width {new.screen.width_m:.4f} m vs 2.17 m ({100 * w_err:.3f} %); {out.stdout}")


def test_calibrate_arena_from_two_measured_tags_and_output_elsewhere(tmp_path: Path) -> None:
    truth = ArenaConfig()
    wrong = scaled_arena(truth, 0.9)
    tm = grid_tag_map(truth)
    a, b = tag_centre_px(tm, 0), tag_centre_px(tm, 80)
    sx = truth.screen.width_m / truth.projector.width_px
    sy = truth.screen.height_m / truth.projector.height_px
    measured = math.hypot((a[0] - b[0]) * sx, (a[1] - b[1]) * sy)
    assert factor_from_points(wrong, a, b, measured) == pytest.approx(1 / 0.9, rel=1e-12)

    config = tmp_path / "arena.yaml"
    original = ARENA_FILE.format(w=f"{wrong.screen.width_m:.6g}", h=f"{wrong.screen.height_m:.6g}")
    config.write_text(original)
    out = _ipt(
        "calibrate", "arena", "--config", str(config), "--tags", "0", "80", "--distance-m", f"{measured:.6f}",
        "--output", "measured.yaml", cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert config.read_text() == original  # --output leaves the user's file alone
    assert not (tmp_path / "arena.yaml.bak").exists()
    new = load_arena_config(tmp_path / "measured.yaml")
    assert new.screen.width_m == pytest.approx(2.17, abs=1e-4)
    assert new.screen.height_m == pytest.approx(2.47, abs=1e-4)


def test_screen_update_keeps_the_file_and_refuses_what_it_cannot_do() -> None:
    appended = update_screen_yaml("projector:\n  width_px: 1920\n", 2.5, 2.8)
    assert yaml.safe_load(appended) == {"projector": {"width_px": 1920}, "screen": {"width_m": 2.5, "height_m": 2.8}}
    flow = update_screen_yaml("screen: {width_m: 1, height_m: 2}\ntag_map: {rows: 3}\n", 2.5, 2.8)
    assert yaml.safe_load(flow) == {"screen": {"width_m": 2.5, "height_m": 2.8}, "tag_map": {"rows": 3}}
    partial = update_screen_yaml("screen:\n  height_m: 2  # h\n", 2.5, 2.8)
    assert yaml.safe_load(partial) == {"screen": {"width_m": 2.5, "height_m": 2.8}}
    assert "# h" in partial
    with pytest.raises(ArenaCalibrationError, match="in place"):
        update_screen_yaml("screen:\n  width_m: &w 2\n  height_m: *w\n", 2.5, 2.8)
    with pytest.raises(ArenaCalibrationError, match="positive"):
        factor_from_points(ArenaConfig(), (0, 0), (10, 0), -1.0)


def test_calibrate_arena_mistakes_are_one_line(tmp_path: Path) -> None:
    config = tmp_path / "arena.yaml"
    config.write_text(ARENA_FILE.format(w="2.0", h="2.27"))
    cases = [
        ["--tags", "0", "999", "--distance-m", "1"],
        ["--tags", "0", "1"],
        ["--height-m", "1.2"],
        ["--height-m", "1.2", "--camera", "camera.yaml", "--image", str(tmp_path / "none.png")],
    ]
    for args in cases:
        out = _ipt("calibrate", "arena", "--config", str(config), *args, cwd=tmp_path)
        assert out.returncode == 2, (args, out.stderr)
        assert len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert config.read_text() == ARENA_FILE.format(w="2.0", h="2.27")
