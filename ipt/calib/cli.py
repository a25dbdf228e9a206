"""``ipt calibrate camera`` and ``ipt calibrate arena``: the argument parsers and the commands.

Only argparse is imported here; OpenCV and the calibration code load when a command runs.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from ipt.cliutil import Parser

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from ipt.calib.floor import FloorFit

    U8 = npt.NDArray[np.uint8]

LIVE_TIMEOUT_S = 120.0
"""How long ``--device`` waits for enough views of the board."""
LIVE_MIN_GAP_S = 0.7
"""Live views are taken at least this far apart, so that the board can be moved between them."""


def _image_files(paths: list[str]) -> list[Path]:
    from ipt.calib.camera import CalibrationError
    from ipt.imageio import IMAGE_SUFFIXES

    files: list[Path] = []
    for text in paths:
        p = Path(text)
        if p.is_dir():
            found = sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and f.is_file())
            if not found:
                raise CalibrationError(f"{p}: the folder holds no images")
            files += found
        elif p.is_file():
            files.append(p)
        else:
            raise CalibrationError(f"{p}: no such file or folder")
    return files


def _grey_images(files: list[Path]) -> Iterator[tuple[str, U8]]:
    from ipt.calib.camera import CalibrationError
    from ipt.imageio import read_image

    for f in files:
        yield str(f), read_image(f, "grey", CalibrationError)


def _live_views(device: int, size: tuple[int, int], wanted: int, finder_find: object) -> Iterator[tuple[str, U8]]:
    """Grey frames of camera ``device`` in which the board is found, ``LIVE_MIN_GAP_S`` apart."""
    import cv2
    import numpy as np

    from ipt.calib.camera import CalibrationError
    from ipt.receiver.capture import DeviceCapture

    cam = DeviceCapture(device, size[0], size[1], None)
    try:
        cam.open()
    except Exception as exc:
        raise CalibrationError(f"device:{device}: {exc}") from None
    try:
        taken = 0
        last = 0.0
        deadline = time.monotonic() + LIVE_TIMEOUT_S
        print(f"ipt calibrate camera: show the board to device:{device} from many angles; {wanted} views to take")
        while taken < wanted:
            if time.monotonic() > deadline:
                raise CalibrationError(f"device:{device}: only {taken} views of the board in {LIVE_TIMEOUT_S:g} s")
            frame = cam.read()
            if frame is None or time.monotonic() - last < LIVE_MIN_GAP_S:
                continue
            image = frame.image
            gray = image if image.ndim == 2 else np.asarray(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY), dtype=np.uint8)
            if finder_find(gray) is None:  # type: ignore[operator]
                continue
            taken += 1
            last = time.monotonic()
            print(f"ipt calibrate camera: view {taken}/{wanted}")
            yield f"device:{device} view {taken}", gray
    finally:
        cam.close()


def _cmd_camera(args: argparse.Namespace) -> int:
    from ipt.calib.camera import Board, BoardFinder, CalibrationError, calibrate_camera
    from ipt.config.camera_info import save_camera_info

    board = Board(
        args.pattern,
        args.cols,
        args.rows,
        args.square_m,
        marker_m=args.marker_m if args.marker_m is not None else 0.0,
        dictionary=args.dictionary,
    )
    if (args.images is None) == (args.device is None):
        raise CalibrationError("give either --images or --device")
    if args.device is not None:
        size = _size(args.size)
        views = _live_views(args.device, size, args.views, BoardFinder(board).find)
    else:
        views = _grey_images(_image_files(args.images))
    result = calibrate_camera(views, board, name=args.name, fix_k3=not args.k3)
    save_camera_info(result.camera, args.output)
    c = result.camera
    skipped = f" (no board in: {', '.join(Path(s).name for s in result.skipped)})" if result.skipped else ""
    worst = max(range(len(result.views)), key=lambda i: result.view_rms_px[i])
    print(
        f"ipt calibrate camera: board found in {len(result.views)} of {len(result.views) + len(result.skipped)} "
        f"images{skipped}"
    )
    print(
        f"ipt calibrate camera: reprojection RMS {result.rms_px:.3f} px (worst view {Path(result.views[worst]).name}: "
        f"{result.view_rms_px[worst]:.3f} px)"
    )
    print(
        f"ipt calibrate camera: {c.width_px}x{c.height_px}, fx {c.fx_px:.2f} fy {c.fy_px:.2f} cx {c.cx_px:.2f} "
        f"cy {c.cy_px:.2f} px, distortion {' '.join(f'{d:.5f}' for d in c.distortion)} -> {args.output}"
    )
    if result.rms_px > 1.0:
        print("ipt calibrate camera: the RMS is over 1 px: check focus, that the board is flat, and the sizes given")
    return 0


def _size(text: str) -> tuple[int, int]:
    from ipt.calib.camera import CalibrationError

    w, sep, h = text.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit() or int(w) < 16 or int(h) < 16:
        raise CalibrationError(f"--size must be WIDTHxHEIGHT, as in 640x360, got {text!r}")
    return int(w), int(h)


def _point(text: str) -> tuple[float, float]:
    u, _, v = text.partition(",")
    try:
        return float(u), float(v)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a projector pixel is U,V (e.g. 960,1080), got {text!r}") from None


_point.__name__ = "projector pixel U,V"


def _grid(text: str) -> tuple[int, int]:
    c, sep, r = text.lower().partition("x")
    if not sep or not c.isdigit() or not r.isdigit() or not 1 <= int(c) <= 50 or not 1 <= int(r) <= 50:
        raise argparse.ArgumentTypeError(f"a grid is COLSxROWS, each 1 to 50, as in 3x3, got {text!r}")
    return int(c), int(r)


_grid.__name__ = "grid COLSxROWS"


def _cmd_marks(args: argparse.Namespace, config: Path) -> int:
    """``--marks``: the cross-hairs to project and measure, and the points file to fill in."""
    from ipt.calib.floor import FloorCalibrationError, grid_pixels, marks_image, read_points, template_csv
    from ipt.config.models import load_arena_config
    from ipt.fileio import output_group, write_text_atomic
    from ipt.imageio import write_image

    arena = load_arena_config(config)
    pr = arena.projector
    points = Path(args.points)
    if points.exists():
        pixels = [(p.u_px, p.v_px) for p in read_points(points, arena, measured=False)]
        template = None
    else:
        # A grid over the image, or over each projector's part of the canvas (each is fitted on its own).
        rects = [(t.x_px, t.y_px, t.width_px, t.height_px) for t in arena.projectors or ()]
        pixels = [
            (float(x0 + u), float(y0 + v))
            for x0, y0, w, h in rects or [(0, 0, pr.width_px, pr.height_px)]
            for u, v in grid_pixels(w, h, *args.grid)
        ]
        template = template_csv(pixels)
    with output_group():
        write_image(args.marks, marks_image(pr.width_px, pr.height_px, pixels), FloorCalibrationError, suffix=".png")
        if template is not None:
            write_text_atomic(points, template)
    print(f"ipt calibrate arena: {len(pixels)} numbered cross-hairs at {pr.width_px}x{pr.height_px} -> {args.marks}")
    if template is not None:
        print(f"ipt calibrate arena: their pixels -> {points}: project the image, measure where each crossing lands "
              f"on the floor, fill in x_m and y_m, then run again without --marks")  # fmt: skip
    return 0


def _report_fit(fit: FloorFit, points: Path, label: str) -> None:
    """Print a fit's table of points, its RMS and the points that are off."""
    print(f"ipt calibrate arena: {label}{len(fit.points)} points from {points}; distance of each from the fit, "
          "and from where the other points put it")  # fmt: skip
    print(f"  {'point':>5} {'row':>4} {'u_px':>8} {'v_px':>8} {'x_m':>9} {'y_m':>9} {'residual':>9} {'left out':>9}")
    for i, p in enumerate(fit.points):
        out = "—" if fit.left_out_m is None else f"{1e3 * fit.left_out_m[i]:.1f} mm"
        print(
            f"  {i + 1:>5} {p.row:>4} {p.u_px:>8g} {p.v_px:>8g} {p.x_m:>9.4f} {p.y_m:>9.4f} "
            f"{1e3 * fit.residual_m[i]:>6.1f} mm {out:>9}"
        )
    print(f"ipt calibrate arena: {label}RMS {1e3 * fit.rms_m:.2f} mm over {len(fit.points)} points")
    if len(fit.points) == 4:
        print(f"ipt calibrate arena: {label}4 points fit exactly, so nothing checks them: measure 6 or more")
    for i in fit.far:
        p = fit.points[i]
        d = fit.left_out_m[i] if fit.left_out_m is not None else fit.residual_m[i]
        print(
            f"ipt calibrate arena: point {i + 1} (row {p.row} of {points}) is {1e2 * d:.1f} cm from where the other "
            "points put it: remeasure it, or leave it out"
        )


def _cmd_points(args: argparse.Namespace, config: Path) -> int:
    """``--points``: the floor homography (of each projector tile) from measured points, written into the
    arena config."""
    import numpy as np

    from ipt.calib.arena import write_arena_text
    from ipt.calib.floor import (
        FloorCalibrationError,
        fit_floor,
        read_points,
        update_floor_yaml,
        update_tiles_yaml,
    )
    from ipt.config.models import load_arena_config
    from ipt.fileio import read_text_file
    from ipt.tagmap import pixel_to_floor_matrix, tile_of

    arena = load_arena_config(config)
    pr = arena.projector
    points = Path(args.points)
    measured = read_points(points, arena)
    tiles = arena.projectors
    if tiles is None:
        groups = [("", measured, (0, 0, pr.width_px, pr.height_px))]
    else:
        groups = []
        for n, t in enumerate(tiles):
            rect = (t.x_px, t.y_px, t.width_px, t.height_px)
            mine = [p for p in measured if tile_of(arena, p.u_px, p.v_px) == n]
            groups.append((f"projector {n + 1} (x {t.x_px}-{t.x_px + t.width_px}, y {t.y_px}-{t.y_px + t.height_px}): ",
                           mine, rect))  # fmt: skip
    fits = []
    for label, mine, (x0, y0, w, h) in groups:
        where = f" in {label[:-2]}" if label else ""
        fits.append(fit_floor(points, mine, w, h, origin_px=(x0, y0), where=where))
    uniform = arena.model_copy(update={"floor": None, "projectors": None})
    worst = 0.0
    for (label, _, (x0, y0, w, h)), fit in zip(groups, fits, strict=True):
        _report_fit(fit, points, label)
        # How far the uniform layout was from what was measured, over the image's corners and centre.
        corners = [(x0, y0), (x0 + w, y0), (x0 + w, y0 + h), (x0, y0 + h), (x0 + w / 2, y0 + h / 2)]
        probe = np.array([[u, v, 1.0] for u, v in corners]).T
        a, b = pixel_to_floor_matrix(uniform) @ probe, fit.pixel_to_floor @ probe
        worst = max(worst, float(np.linalg.norm(a[:2] / a[2] - b[:2] / b[2], axis=0).max()))
    print(
        f"ipt calibrate arena: the measured floor differs from the uniform {arena.screen.width_m:g} x "
        f"{arena.screen.height_m:g} m layout by up to {1e2 * worst:.1f} cm (image corners and centre)"
    )
    if args.dry_run:
        print("ipt calibrate arena: --dry-run: nothing written")
        return 0
    text = read_text_file(config, FloorCalibrationError, "an arena YAML file")
    if tiles is None:
        new_text = update_floor_yaml(text, fits[0].config())
    else:
        new_text = update_tiles_yaml(
            text,
            tuple(
                t.model_copy(
                    update={
                        "pixel_to_floor": f.config().pixel_to_floor,
                        "points": len(f.points),
                        "rms_m": round(f.rms_m, 7),
                    }
                )
                for t, f in zip(tiles, fits, strict=True)
            ),
        )
    written, backup = write_arena_text(config, new_text, output=Path(args.output) if args.output else None)
    kept = f" (the previous file is {backup})" if backup is not None else ""
    what = "the floor homography" if tiles is None else f"the floor homographies of the {len(tiles)} projectors"
    print(f"ipt calibrate arena: wrote {what} to {written}{kept}")
    return 0


def _cmd_arena(args: argparse.Namespace) -> int:
    from ipt.calib.arena import (
        ArenaCalibrationError,
        factor_from_height,
        factor_from_points,
        scaled_arena,
        tag_centre_px,
        write_screen,
    )
    from ipt.config.camera_info import load_camera_info
    from ipt.config.models import load_arena_config
    from ipt.tagmap import grid_tag_map

    config = Path(args.config)
    methods = sum(x is not None for x in (args.height_m, args.tags, args.pixels, args.points))
    if methods != 1:
        raise ArenaCalibrationError(
            "give one measurement: --points (with or without --marks), --height-m (with --camera and --image), "
            "--tags or --pixels"
        )
    if args.marks is not None and args.points is None:
        raise ArenaCalibrationError("--marks needs --points POINTS.csv (the pixels to mark, or where to list them)")
    if args.marks is not None:
        return _cmd_marks(args, config)
    if args.points is not None:
        return _cmd_points(args, config)
    arena = load_arena_config(config)
    if arena.floor is not None or any(t.pixel_to_floor is not None for t in arena.projectors or ()):
        raise ArenaCalibrationError(
            f"{config}: the arena has a measured floor homography (floor: or projectors:), which a scale does not "
            "change: measure again with --points, or delete the measured homographies first"
        )
    if args.height_m is not None:
        if args.camera is None or not args.image:
            raise ArenaCalibrationError("--height-m needs --camera CAMERA.yaml and at least one --image")
        camera = load_camera_info(args.camera)
        factor, used, skipped = factor_from_height(arena, camera, _grey_images(_image_files(args.image)), args.height_m)
        for v in used:
            print(
                f"ipt calibrate arena: {Path(v.name).name}: {v.tags} tags, height {v.solved_height_m:.4f} m under the "
                f"current config (reprojection {v.reprojection_rms_px:.2f} px)"
            )
        if skipped:
            print(f"ipt calibrate arena: fewer than two tags in: {', '.join(Path(s).name for s in skipped)}")
        how = f"camera {args.height_m:g} m above the floor, {len(used)} image(s)"
    else:
        if args.distance_m is None:
            raise ArenaCalibrationError("--tags and --pixels need --distance-m (the distance measured on the floor)")
        if args.tags is not None:
            tm = grid_tag_map(arena)
            a, b = (tag_centre_px(tm, t) for t in args.tags)
            how = f"tags {args.tags[0]} and {args.tags[1]} {args.distance_m:g} m apart"
        else:
            a, b = args.pixels
            how = f"pixels ({a[0]:g}, {a[1]:g}) and ({b[0]:g}, {b[1]:g}) {args.distance_m:g} m apart"
        factor = factor_from_points(arena, a, b, args.distance_m)
    new = scaled_arena(arena, factor)
    pr, old_s, new_s = arena.projector, arena.screen, new.screen
    print(
        f"ipt calibrate arena: {how}: scale x{factor:.5f}; screen {old_s.width_m:g} x {old_s.height_m:g} m -> "
        f"{new_s.width_m:.4f} x {new_s.height_m:.4f} m ({new_s.width_m / pr.width_px * 1e3:.4f} x "
        f"{new_s.height_m / pr.height_px * 1e3:.4f} mm per projector pixel)"
    )
    if args.dry_run:
        print("ipt calibrate arena: --dry-run: nothing written")
        return 0
    written, backup = write_screen(
        config, new_s.width_m, new_s.height_m, output=Path(args.output) if args.output else None
    )
    kept = f" (the previous file is {backup})" if backup is not None else ""
    print(f"ipt calibrate arena: wrote screen.width_m and screen.height_m to {written}{kept}")
    return 0


def add_calibrate_parser(sub: argparse._SubParsersAction[Parser]) -> None:
    """Add ``calibrate camera`` and ``calibrate arena`` to the ``ipt`` command's subparsers."""
    c = sub.add_parser("calibrate", help="calibrate the drone's camera or the arena's projector scale")
    csub = c.add_subparsers(dest="calibrate_command", metavar="WHAT", parser_class=Parser)
    csub.required = True
    cam = csub.add_parser(
        "camera",
        help="camera intrinsics from chessboard or ChArUco views -> ROS camera_info YAML",
        description="Calibrate a camera from views of a flat chessboard or ChArUco board: image files (or folders of "
        "them) or a live V4L2 camera. Writes ROS camera_info YAML (what ipt-receiver --camera reads) and reports "
        "the reprojection RMS. Take 10-20 views with the board filling much of the image, tilted in different "
        "directions, at the resolution the receiver will use.",
    )
    cam.add_argument("--images", nargs="+", metavar="IMAGE|DIR", help="calibration images, or folders of them")
    cam.add_argument("--device", type=int, metavar="N", help="take the views live from /dev/videoN instead")
    cam.add_argument("--size", default="640x360", help="live camera resolution WIDTHxHEIGHT (default 640x360)")
    cam.add_argument("--views", type=int, default=15, help="live views to take (default 15)")
    cam.add_argument("--pattern", choices=("chessboard", "charuco"), default="chessboard", help="the board")
    cam.add_argument(
        "--cols", type=int, required=True, help="chessboard: inner corners per row; ChArUco: squares (3 to 100)"
    )
    cam.add_argument(
        "--rows", type=int, required=True, help="chessboard: inner corners per column; ChArUco: squares (3 to 100)"
    )
    cam.add_argument(
        "--square-m", type=float, required=True, help="side of one square in metres, 0.001 to 1, e.g. 0.025"
    )
    cam.add_argument("--marker-m", type=float, help="ChArUco: side of one marker in metres (0.1 to 1 of the square)")
    cam.add_argument("--dictionary", default="DICT_5X5_100", help="ChArUco: ArUco dictionary (default DICT_5X5_100)")
    cam.add_argument("--k3", action="store_true", help="also fit the sixth-order radial term k3 (wide-angle lenses)")
    cam.add_argument("--name", default="camera", help="camera_name in the YAML (default camera)")
    cam.add_argument("--output", required=True, metavar="CAMERA.yaml", help="where to write the calibration")
    cam.set_defaults(func=_cmd_camera)

    ar = csub.add_parser(
        "arena",
        help="measure where projector pixels land on the floor and write it into the arena config",
        description="Measure where the projector's pixels land on the floor, and write it into the arena config. "
        "A keystoned projector (mounted off-axis) needs --points: list four or more projector pixels and the "
        "floor positions you measured for them (tape, laser, total station; in your own floor frame, metres) in a "
        "CSV file with the header u_px,v_px,x_m,y_m. They give the projector-to-floor homography (least squares); "
        "each point's distance from the fit and from where the other points put it is printed, a point more than "
        "1 cm off is named, and the 'floor:' section of the config is written (every part uses it: tag corners, "
        "simulator, AR overlay); for an arena of several projectors (projectors: tiles of the canvas) each tile "
        "is fitted from the points in its part and gets its own homography. To get the points: '--points P.csv "
        "--marks M.png' writes M.png, numbered cross-hairs at a --grid of pixels (default 3x3, in each "
        "projector's part), and P.csv listing their pixels with x_m, y_m empty; project M.png, measure each "
        "crossing, fill in P.csv, run again without --marks. (With an existing P.csv, --marks draws its "
        "pixels.) "
        "Without a floor section the layout is a uniform scale, which the other methods measure: how large the "
        "projected image is on the floor, written as screen.width_m and "
        "screen.height_m into the arena config (the aspect of a projector pixel is kept). Either project the plain "
        "map ('ipt map export') and give a calibrated camera's images taken looking down from a measured height "
        "(--height-m, --camera, --image: measure to the lens, from 1 m or more, as 1 cm is 1 % at 1 m), or tape-"
        "measure the distance between two tag centres (--tags A B) or two projector pixels (--pixels U,V U,V). "
        "The config is updated in place, only what was measured (the floor section, or those two numbers), after "
        "a copy to CONFIG.bak; or written to --output.",
    )
    ar.add_argument("--config", required=True, metavar="ARENA.yaml", help="the arena config to measure and update")
    ar.add_argument("--height-m", type=float, help="the camera's height above the floor, metres")
    ar.add_argument("--camera", metavar="CAMERA.yaml", help="ROS camera_info of the camera (with --height-m)")
    ar.add_argument("--image", action="append", metavar="IMAGE|DIR", help="image(s) of the projected map; repeat")
    ar.add_argument("--tags", type=int, nargs=2, metavar=("A", "B"), help="two tag ids whose centres were measured")
    ar.add_argument("--pixels", type=_point, nargs=2, metavar=("U,V", "U,V"), help="two projector pixels measured")
    ar.add_argument("--distance-m", type=float, help="the floor distance between the two points, metres")
    ar.add_argument("--points", metavar="POINTS.csv", help="measured points: u_px,v_px,x_m,y_m (4 or more)")
    ar.add_argument("--marks", metavar="MARKS.png", help="write numbered cross-hairs to project and measure")
    ar.add_argument("--grid", type=_grid, default=(3, 3), metavar="COLSxROWS", help="marks' grid (default 3x3)")
    ar.add_argument("--output", metavar="ARENA.yaml", help="write the updated config here; leave --config as it is")
    ar.add_argument("--dry-run", action="store_true", help="only print the measurement")
    ar.set_defaults(func=_cmd_arena)
