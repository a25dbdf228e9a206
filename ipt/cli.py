"""``ipt``: the arena tools — tag map export, simulator, evaluation and the end-to-end demo.

Only the standard library and :mod:`ipt.cliutil` load with this module; everything else loads when a
command runs, so that the stop signals are handled from the first moment (:mod:`ipt.signals`).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from ipt import __version__
from ipt.calib.cli import add_calibrate_parser
from ipt.cliutil import Parser, bounded_float, run_main, same_file, seed_int
from ipt.errors import IptError

if TYPE_CHECKING:  # loaded only by the commands that use them
    from ipt.config.models import ArenaConfig
    from ipt.sender.content import ContentSource

MAX_FLIGHT_S = 3600.0
"""The longest flight ``ipt sim`` and ``ipt demo`` take (``--seconds``): an hour of 120 FPS frames."""

DEFAULT_ARENA_NAME = "arena.yaml"
"""The arena shipped in ``ipt/config``, used when ``--config`` is not given."""


def _default_arena() -> Path:
    from ipt.config.models import shipped_config_path

    return shipped_config_path(DEFAULT_ARENA_NAME)


def _arena(path: str | None) -> ArenaConfig:
    from ipt.config.models import load_arena_config

    return load_arena_config(path if path is not None else _default_arena())


def _scene(spec: str, arena: ArenaConfig, seed: int) -> ContentSource:
    from ipt.imageio import IMAGE_SUFFIXES
    from ipt.sender.content import GeneratedScene, StillImageScene, VideoScene
    from ipt.sender.photos import PanningPhotoScene

    w, h = arena.projector.width_px, arena.projector.height_px
    if spec in ("generated", "map"):
        return GeneratedScene(w, h, seed=seed)
    if spec == "photos":
        return PanningPhotoScene(w, h, seed=seed)
    p = Path(spec)
    if p.suffix.lower() in IMAGE_SUFFIXES:
        return StillImageScene.from_file(p, w, h)
    return VideoScene(p, w, h)


def _cmd_map_export(args: argparse.Namespace) -> int:
    from ipt.maphash import map_hash
    from ipt.tagmap import TagMapError, export_map, grid_tag_map

    if same_file(args.image, args.layout):
        raise TagMapError(f"--image and --layout name the same file ({args.layout}): the layout would replace the map")
    tm = grid_tag_map(_arena(args.config))
    export_map(tm, args.image, args.layout)
    print(f"ipt map export: {len(tm.tags)} tags -> {args.image} ({tm.width_px}x{tm.height_px}), {args.layout}")
    print(f"ipt map export: map hash sha256:{map_hash(tm)} (the SHA-256 of {args.layout})")
    return 0


def _cmd_map_check(args: argparse.Namespace) -> int:
    import numpy as np

    from ipt.imageio import read_image
    from ipt.tagmap import TagMapError, load_layout

    tm = load_layout(args.layout)
    print(f"ipt map check: {args.layout}: {len(tm.tags)} tags, ids unique, projector {tm.width_px}x{tm.height_px}")
    if args.image is None:
        return 0
    img = read_image(args.image, "grey", TagMapError)
    from ipt.config.models import DetectorConfig
    from ipt.receiver.detect.detector import APRILTAG_TO_OPENCV_PX, TagDetector

    # The layout uses AprilTag's own pixel convention, so undo the wrapper's shift to OpenCV's.
    detector = TagDetector(DetectorConfig(max_hamming=0))
    found = {d.tag_id: d.corners_px - APRILTAG_TO_OPENCV_PX for d in detector.detect(img)}
    wanted = set(tm.by_id)
    hit = wanted & set(found)
    worst = max((float(np.abs(found[i] - np.asarray(tm.by_id[i].corners_px)).max()) for i in hit), default=float("nan"))
    print(
        f"ipt map check: {args.image}: AprilTag found {len(hit)}/{len(wanted)} ids of the layout, "
        f"largest corner difference {worst:.3f} px"
    )
    return 0 if hit == wanted else 1


def _cmd_sim(args: argparse.Namespace) -> int:
    from ipt.config.models import load_yaml_model
    from ipt.sim.arena import scene_for
    from ipt.sim.config import SimConfig, apply_arena_changes
    from ipt.sim.limits import check_flight
    from ipt.sim.run import simulate_to_folder

    sim = load_yaml_model(args.sim_config, SimConfig) if args.sim_config else SimConfig()
    check_flight(sim, args.sim_config)
    if args.seed is not None:
        sim = sim.model_copy(update={"seed": args.seed})
    arena = apply_arena_changes(_arena(args.config), sim.arena)
    scene = scene_for(sim, arena) if args.content is None else _scene(args.content, arena, sim.seed)
    n = simulate_to_folder(arena, sim, scene, Path(args.out), args.seconds)
    survey = ", survey.csv" if sim.keystone is not None else ""
    print(f"ipt sim: {n} frames -> {args.out}/frames.mkv, camera.yaml, groundtruth.tum, arena.yaml{survey}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from ipt.config.models import load_yaml_model
    from ipt.sim.config import SimConfig
    from ipt.sim.demo import run_demo
    from ipt.sim.limits import check_flight

    arena_path = Path(args.config) if args.config is not None else _default_arena()
    _arena(str(arena_path))  # a bad arena file is one line before anything starts
    sim = check_flight(load_yaml_model(args.sim_config, SimConfig), args.sim_config) if args.sim_config else None
    out = Path(args.out) if args.out else Path("results") / time.strftime("demo-%Y%m%d-%H%M%S")
    return run_demo(arena_path, args.seconds, out, args.seed, sim)


def _cmd_invisibility(args: argparse.Namespace) -> int:
    import json

    from ipt.invisibility import frame_indices, measure_scene
    from ipt.sender.modulator import PROFILES, ModulationError, delta_l_warning
    from ipt.sender.photos import SHOTS, PanningPhotoScene

    arena = _arena(args.config)
    if args.pairs < 1:
        raise ModulationError(f"--pairs must be at least 1, got {args.pairs}")
    profiles = [p.strip() for p in args.profiles.split(",") if p.strip()]
    unknown = [p for p in profiles if p not in PROFILES]
    if not profiles or unknown:
        raise ModulationError(f"--profiles must name some of {', '.join(PROFILES)}, got {args.profiles!r}")
    if any(not 0 <= a <= 8 for a in args.clip_allowance):
        raise ModulationError(f"--clip-allowance values must be in [0, 8] 8-bit L units, got {args.clip_allowance}")
    if args.delta_l is not None and not 0 < args.delta_l <= 50:
        raise ModulationError(f"--delta-l must be in (0, 50] 8-bit L units, got {args.delta_l:g}")
    if not 0 <= args.saccade_px < arena.projector.width_px:
        raise ModulationError(f"--saccade-px must be 0..{arena.projector.width_px - 1}, got {args.saccade_px}")
    delta_l = arena.modulation.delta_l if args.delta_l is None else args.delta_l
    if (warning := delta_l_warning(delta_l)) is not None:
        print(f"ipt invisibility: warning: {warning}", file=sys.stderr)
    w, h = arena.projector.width_px, arena.projector.height_px
    contents = [*args.content, *([] if args.video is None else [args.video])] or ["map"]
    results = []
    for content in contents:
        rate_hz, length = arena.modulation.input_rate_hz, None
        if content not in ("map", "generated", "photos"):
            from ipt.videoio import open_frames

            with open_frames(content) as source:
                size, fps, length = (source.width, source.height), source.fps, getattr(source, "frame_count", None)
                if length is None:  # not in the container: count the frames
                    length = sum(1 for _ in source)
            if size != (w, h):
                print(f"ipt invisibility: {content} is {size[0]}x{size[1]}; resized to {w}x{h}", file=sys.stderr)
            rate_hz = fps if fps is not None and fps > 0 else rate_hz
        scene = _scene(content, arena, args.seed)
        if isinstance(scene, PanningPhotoScene):  # spread over one round of its shots: every kind is measured
            length = round(len(SHOTS) * scene.cut_every_s * rate_hz)
        try:
            indices = frame_indices(args.pairs, length, max(1, round(rate_hz)))
            print(f"ipt invisibility: {content}: {len(indices)} input frames", file=sys.stderr)
            result = measure_scene(
                arena, scene, indices, rate_hz, profiles, delta_l, args.clip_allowance, args.saccade_px
            )
        finally:
            close = getattr(scene, "close", None)
            if close is not None:
                close()
        label = "generated" if content in ("map", "generated") else content
        results.append({"content": label, "input_frames": indices, **result})
    print(json.dumps({"command": "ipt invisibility", "contents": results}, indent=1))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``ipt`` argument parser."""
    p = Parser(
        prog="ipt",
        description="IPT arena tools: export the hidden tag map, simulate a flight over the projected arena, "
        "evaluate poses against ground truth, or run the whole chain with 'ipt demo'.",
        epilog="Start with: ipt demo   (simulate, localise and score a 15 s flight; no hardware needed)",
    )
    p.add_argument("--version", action="version", version=f"ipt {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True

    cfg_help = f"arena YAML (default: the shipped paper arena, {DEFAULT_ARENA_NAME})"

    _add_map_parser(sub, cfg_help)
    _add_sim_parser(sub, cfg_help)
    # 'ipt eval' is dispatched to ipt.eval.eval_main before parsing; listed here for the help text.
    sub.add_parser("eval", help="the paper's error table for poses against ground truth (see ipt eval --help)")

    _add_demo_parser(sub, cfg_help)
    _add_invisibility_parser(sub, cfg_help)
    add_calibrate_parser(sub)
    return p


def _add_map_parser(sub: argparse._SubParsersAction[Parser], cfg_help: str) -> None:
    """``ipt map export`` and ``ipt map check``."""
    m = sub.add_parser("map", help="export or check the tag map")
    msub = m.add_subparsers(dest="map_command", metavar="ACTION", parser_class=Parser)
    msub.required = True
    e = msub.add_parser(
        "export",
        help="write the map image and its layout JSON",
        description="Write the tag map at projector resolution (8-bit grey: 255 white tag cells, 0 black, "
        "127 elsewhere) and a JSON layout with every tag's corners in projector pixels and arena metres.",
    )
    e.add_argument("--config", metavar="ARENA.yaml", help=cfg_help)
    e.add_argument("--image", required=True, metavar="MAP.png", help="where to write the map image")
    e.add_argument("--layout", required=True, metavar="LAYOUT.json", help="where to write the layout")
    e.set_defaults(func=_cmd_map_export)
    c = msub.add_parser(
        "check",
        help="validate a layout JSON (and detect its tags in a map image)",
        description="Check a layout file; with --image, detect the tags with AprilTag 3 (dt-apriltags) and compare "
        "their corners with the layout. Exit 1 if any tag of the layout is not found.",
    )
    c.add_argument("--layout", required=True, metavar="LAYOUT.json")
    c.add_argument("--image", metavar="MAP.png")
    c.set_defaults(func=_cmd_map_check)


def _add_sim_parser(sub: argparse._SubParsersAction[Parser], cfg_help: str) -> None:
    """``ipt sim``."""
    s = sub.add_parser(
        "sim",
        help="render a simulated flight (video, camera.yaml, ground truth)",
        description="Render what a drone's downward 120 FPS camera sees over the projected, modulated floor. "
        "By default the flight is a realistic one: the paper's rectangle at 0.8 m flown by a pilot, the "
        "airframe vibrating (1-2° at 5-7 Hz), its shadow under a ceiling projector (3 m up) crossing the "
        "view, over photographic video that pans and cuts. --sim-config changes any of it (camera: mono, "
        "JPEG, rolling shutter, gain drift, vignetting; flight: rectangle, takeoff or hover; shadow; content; "
        "arena changes such as ΔL): see benchmarks/flights/*.yaml. Writes OUT/frames.mkv (lossless FFV1; "
        "grey for a mono camera), OUT/camera.yaml (ROS camera_info), OUT/groundtruth.tum (camera pose at "
        "each frame time), OUT/arena.yaml (the arena flown, with the flight's changes) and OUT/sim.json; for a "
        "keystoned projector (keystone: in --sim-config) also OUT/survey.csv, its marks as a tape would measure "
        "them, for 'ipt calibrate arena --points'.",
    )
    s.add_argument("--config", metavar="ARENA.yaml", help=cfg_help)
    s.add_argument("--out", required=True, metavar="DIR", help="output folder (created if needed)")
    s.add_argument(
        "--seconds",
        type=bounded_float(0, MAX_FLIGHT_S, " s"),
        default=15.0,
        help="flight length, at most 3600 (default 15, as in the paper)",
    )
    s.add_argument(
        "--sim-config",
        metavar="SIM.yaml",
        help="the flight: camera, timing, noise, path, vibration, shadow, content (default: the realistic flight)",
    )
    s.add_argument(
        "--seed", type=seed_int, help="random seed, 0 to 2^32-1 (noise, pilot, vibration and generated content)"
    )
    s.add_argument(
        "--content",
        metavar="photos|map|FILE",
        help="the projected content: panning photographs, the paper's map app, or a video file / image folder "
        "(default: the flight's content.kind, photos unless set)",
    )
    s.set_defaults(func=_cmd_sim)


def _add_demo_parser(sub: argparse._SubParsersAction[Parser], cfg_help: str) -> None:
    """``ipt demo``."""
    d = sub.add_parser(
        "demo",
        help="the closed loop: sender, simulated drone and receiver together; prints the paper's error table",
        description="The whole system in one process on the built-in simulated arena: the sender modulates "
        "the content (by default photographs that pan and cut) and keeps its output frames in memory (the "
        "projector); a simulated drone camera, on a hand-flown, vibrating drone casting its own shadow, "
        "films exactly those frames; the receiver daemon localises each camera frame and sends the pose over "
        "UDP (127.0.0.1) back to the sender, which draws the drone into the next frames. Simulated time drives "
        "everything, frame by frame, so the run is deterministic for a seed but slower than real time "
        "(about 0.1x on a 2-core machine: the default 15 s takes about 2.5 minutes). A status line on stderr "
        "shows progress; at the end the paper's error table goes to stdout and the results (summary.txt, "
        "errors.png, report.json, poses.tum, groundtruth.tum, logs) to a folder. Ctrl-C (or SIGTERM) stops "
        "early and still scores what was flown (exit status 130, or 143 for SIGTERM).",
    )
    d.add_argument("--config", metavar="ARENA.yaml", help=cfg_help)
    d.add_argument(
        "--seconds",
        type=bounded_float(0, MAX_FLIGHT_S, " s"),
        default=15.0,
        help="simulated flight length, at most 3600 (default 15, the paper's test unit; about 10 s of wall time "
        "per simulated second here)",
    )
    d.add_argument(
        "--seed", type=seed_int, default=0, help="random seed, 0 to 2^32-1 (content and camera noise; default 0)"
    )
    d.add_argument(
        "--sim-config",
        metavar="SIM.yaml",
        help="another flight (e.g. benchmarks/flights/realcam.yaml); default: the realistic default flight",
    )
    d.add_argument("--out", metavar="DIR", help="results folder (default results/demo-<time>)")
    d.set_defaults(func=_cmd_demo)


def _add_invisibility_parser(sub: argparse._SubParsersAction[Parser], cfg_help: str) -> None:
    """``ipt invisibility``."""
    v = sub.add_parser(
        "invisibility",
        help="how visible the hidden tags are, and how much signal a camera gets, for each modulation profile",
        description="For input frames of the content, make the two output frames of opposite phase with each "
        "modulation profile and print JSON: the CIEDE2000 difference between the input and the linear-light "
        "mean of the two phases (what the eye fuses at 60 Hz) over tag pixels and over the other pixels (mean, "
        "p99, max), the share of non-tag pixels left bit-identical, and the camera-side signal: the mean L* "
        "difference of the phases times the tag mask, in 8-bit L units, also as a fraction of the paper "
        "profile's; and the saccade figure: the two phases seen --saccade-px apart, as a moving eye sees them, "
        "against the input seen the same way. One block of figures per content.",
    )
    v.add_argument("--config", metavar="ARENA.yaml", help=cfg_help)
    v.add_argument(
        "--content",
        nargs="+",
        default=[],
        metavar="CONTENT",
        help="what to measure on, each on its own: map (the generated map app), photos (photographs that pan and "
        "cut, colour bars and grey ramps), or a video file / image folder (default: map)",
    )
    v.add_argument("--video", metavar="CONTENT", help="a video file or image folder (the same as --content CONTENT)")
    v.add_argument("--pairs", type=int, default=10, help="input frames to measure, spread over the video (default 10)")
    v.add_argument("--profiles", default="ipt,paper", help="comma-separated profiles (default ipt,paper)")
    v.add_argument("--delta-l", type=float, metavar="DL", help="ΔL in 8-bit L units (default: the arena's)")
    v.add_argument(
        "--clip-allowance",
        type=float,
        nargs="+",
        default=[],
        metavar="A",
        help="also measure the ipt profile with these clip allowances (8-bit L units; reported as ipt@A)",
    )
    v.add_argument(
        "--saccade-px",
        type=int,
        default=4,
        metavar="D",
        help="how far apart (projector pixels) a moving eye sees the two phases for the saccade figure (default 4; "
        "0: none)",
    )
    v.add_argument(
        "--seed",
        type=seed_int,
        default=0,
        help="seed of the generated and the photographic content, 0 to 2^32-1 (default 0)",
    )
    v.set_defaults(func=_cmd_invisibility)


def _main(argv: Sequence[str] | None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["eval"]:  # its own parser, with its own --help
        from ipt.eval import eval_main

        return eval_main(argv[1:])
    args = build_parser().parse_args(argv)
    rc: int = args.func(args)
    return rc


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ipt``."""
    return run_main("ipt", _main, argv)


if __name__ == "__main__":
    sys.exit(main())

__all__ = ["IptError", "build_parser", "main"]
