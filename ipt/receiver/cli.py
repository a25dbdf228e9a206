"""``ipt-receiver``: the drone side — replay a recorded flight (the daemon comes with the services)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from ipt import __version__
from ipt.cliutil import Parser, run_main
from ipt.config.models import PipelineConfig, load_arena_config, shipped_config_path


def _cmd_replay(args: argparse.Namespace) -> int:
    from ipt.receiver.replay import ReplayError, replay
    from ipt.tagmap import grid_tag_map

    arena = load_arena_config(args.config or shipped_config_path("arena.yaml"))
    if args.fps is not None and args.fps <= 0:
        raise ReplayError(f"--fps must be positive, got {args.fps}")
    summary = replay(
        arena, grid_tag_map(arena), Path(args.camera), Path(args.video), Path(args.output), args.fps, PipelineConfig()
    )
    print(f"ipt-receiver replay: {summary.poses} poses from {summary.frames} frames -> {args.output}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``ipt-receiver`` argument parser."""
    p = Parser(
        prog="ipt-receiver",
        description="The IPT receiver: demodulate the hidden tags from a 120 FPS camera, detect them with "
        "AprilTag 3 and estimate the camera's pose in the arena.",
    )
    p.add_argument("--version", action="version", version=f"ipt-receiver {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    r = sub.add_parser(
        "replay",
        help="localise every frame of a recording and write a TUM trajectory",
        description="Run a recorded flight (a video file, or a folder of images in name order) through the "
        "receiver. Frame k has time k/fps. Writes one TUM line 't x y z qx qy qz qw' per pose: the camera's "
        "optical centre in arena metres and its rotation camera->arena (OpenCV optical axes).",
    )
    r.add_argument("--config", metavar="ARENA.yaml", help="arena YAML (default: the shipped paper arena)")
    r.add_argument("--camera", required=True, metavar="CAMERA.yaml", help="ROS camera_info YAML of the camera")
    r.add_argument("--video", required=True, metavar="VIDEO|DIR", help="recording: video file or image folder")
    r.add_argument("--fps", type=float, help="camera frame rate (default: from the video file)")
    r.add_argument("--output", required=True, metavar="POSES.tum", help="where to write the poses")
    r.set_defaults(func=_cmd_replay)
    return p


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    rc: int = args.func(args)
    return rc


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ipt-receiver``."""
    return run_main("ipt-receiver", _main, argv)


if __name__ == "__main__":
    sys.exit(main())
