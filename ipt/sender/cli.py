"""``ipt-sender``: project the video with the hidden tags, and draw the drones it hears about on it."""

from __future__ import annotations

import argparse
import asyncio
import gc
import math
import sys
from collections.abc import Callable, Coroutine, Sequence
from pathlib import Path
from typing import Any, TypeVar

from ipt import __version__
from ipt.cliutil import Parser, run_main
from ipt.config.models import ArenaConfig, load_arena_config, shipped_config_path
from ipt.errors import IptError

DEFAULT_ARENA = shipped_config_path("arena.yaml")
T = TypeVar("T")


class SenderCliError(IptError):
    """A file named on the command line cannot be used."""


def _vehicle_id(text: str) -> int:
    """An argparse ``type``: a vehicle id as the packets carry it (0..65535)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: '{text}'") from None
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"vehicle ids are 0..65535 (a uint16 in the packets), got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The ``ipt-sender`` argument parser."""
    p = Parser(
        prog="ipt-sender",
        description="The IPT sender: hide the arena's AprilTag map in a video as a lightness flicker at the "
        "projector rate and show it (full screen, to a file, or nowhere for a benchmark). It listens for the "
        "drones' pose packets and draws each drone, its heading and its trail on the video.",
        epilog="Without --video or --image the built-in map-app animation is shown. Statistics go to stderr "
        "every few seconds and when it stops (SIGINT or SIGTERM); the last line holds missed=<deadlines>.",
    )
    p.add_argument("--version", action="version", version=f"ipt-sender {__version__}")
    p.add_argument("--config", metavar="ARENA.yaml", help=f"arena YAML (default: the shipped {DEFAULT_ARENA.name})")
    content = p.add_mutually_exclusive_group()
    content.add_argument("--video", metavar="IN", help="input video file or image folder, played in a loop")
    content.add_argument("--image", metavar="IN", help="a still image to show")
    p.add_argument(
        "--sink",
        choices=("window", "file", "null"),
        default="window",
        help="window: full screen with vsync (needs pygame-ce); file: lossless FFV1 to --output, as fast as "
        "possible; null: discard (benchmarks). Default: window",
    )
    p.add_argument("--output", metavar="OUT.mkv", help="the video file of --sink file")
    p.add_argument(
        "--modulation",
        choices=("ipt", "paper"),
        help="modulation profile (default: the arena's modulation.profile): ipt is colour-exact and balanced, "
        "paper is the published Algorithm 1",
    )
    p.add_argument("--frames", type=int, metavar="N", help="stop after N output frames (default: run until stopped)")
    p.add_argument(
        "--threads",
        type=int,
        default=1,
        metavar="N",
        help="threads sharing each modulation pass of the ipt profile (default 1; 2 shortens each frame's work "
        "on an otherwise idle 2-core machine)",
    )
    p.add_argument(
        "--listen",
        metavar="HOST:PORT",
        help="UDP address for pose packets (default 127.0.0.1:9870; with --sink file only when given)",
    )
    p.add_argument("--auth-key-file", metavar="F", help="accept only packets authenticated with this key")
    p.add_argument(
        "--vehicles", type=_vehicle_id, nargs="+", metavar="ID", help="accept packets from these vehicle ids only"
    )
    p.add_argument(
        "--gpu",
        action="store_true",
        help="--sink window, ipt profile: make the phases on the GPU (OpenGL 3.3; needs moderngl: pip install "
        "'ipt[gpu]'), leaving the CPU only the content and the overlay. If the GPU path cannot start, one line "
        "says why and the CPU makes the phases",
    )
    p.add_argument("--display", type=int, default=0, metavar="N", help="display index of --sink window (default 0)")
    p.add_argument("--windowed", action="store_true", help="--sink window in a window rather than full screen")
    p.add_argument("--stats-every", type=float, default=5.0, metavar="S", help="statistics interval (default 5 s)")
    return p


def _read_key(path: str) -> bytes:
    """The key file's bytes, without one trailing line break (keys are often written with ``echo``)."""
    try:
        key = Path(path).read_bytes()
    except OSError as exc:
        raise SenderCliError(f"{path}: cannot read the key file ({exc.strerror or exc})") from None
    for ending in (b"\r\n", b"\n"):
        if key.endswith(ending):
            return key[: -len(ending)]
    return key


def _image_size(path: Path) -> tuple[int, int]:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SenderCliError(f"{path}: not an image OpenCV can read")
    return int(img.shape[1]), int(img.shape[0])


def _scene(args: argparse.Namespace, arena: ArenaConfig) -> tuple[Any, float]:
    """The content and its frame rate; notes on stderr where it is resized or re-timed."""
    from ipt.sender.content import GeneratedScene, StillImageScene, VideoScene
    from ipt.videoio import open_frames

    w, h = arena.projector.width_px, arena.projector.height_px
    rate_hz = arena.modulation.input_rate_hz
    if args.video is not None:
        with open_frames(args.video) as source:
            size, fps = (source.width, source.height), source.fps
        if size != (w, h):
            _note(f"input video is {size[0]}x{size[1]}; frames are resized to {w}x{h}")
        if fps is not None and math.isfinite(fps) and fps > 0:
            if abs(fps - rate_hz) > 1e-3:
                _note(f"input video is {fps:g} fps, not the arena's input_rate_hz {rate_hz:g}: played at its own rate")
            rate_hz = fps
        # No cache of the first pass: each cached frame (12 MB at 1920x2160) is fresh memory, and faulting it
        # in cost the content thread 40 ms a frame here, more than a frame's time; re-decoding each lap
        # costs 6 ms a frame and a re-open at the loop.
        return VideoScene(args.video, w, h, cache_bytes=0), rate_hz
    if args.image is not None:
        size = _image_size(Path(args.image))
        if size != (w, h):
            _note(f"input image is {size[0]}x{size[1]}; it is resized to {w}x{h}")
        return StillImageScene.from_file(args.image, w, h), rate_hz
    return GeneratedScene(w, h), rate_hz


def _note(text: str) -> None:
    print(f"ipt-sender: {text}", file=sys.stderr)


def _gpu_path(args: argparse.Namespace, arena: ArenaConfig, mask: Any) -> tuple[Any, Any]:
    """The GPU window and its modulator, ready (colour table complete, textures up); or, when the GPU path
    cannot start, one line saying why and (None, None): the CPU makes the phases instead."""
    from ipt.sender.gpu import GlWindowSink, GpuError, GpuModulator
    from ipt.sender.pairs import default_cache_dir

    mod = arena.modulation
    gpu = GpuModulator(mask, mod.delta_l, mod.clip_allowance_l8)
    _note(gpu.complete_table(default_cache_dir(), _note))  # the shader needs every colour's pair up front
    sink = GlWindowSink(gpu, args.display, not args.windowed, rate_hz=arena.projector.rate_hz)
    try:
        renderer = sink.open()
    except GpuError as exc:
        sink.close()
        _note(f"the GPU path cannot start ({exc}); the CPU makes the phases")
        return None, None
    _note(f"the GPU makes the phases ({renderer})")
    return sink, gpu


def _run(make: Callable[[], Coroutine[Any, Any, T]]) -> T:
    """Run a coroutine on uvloop where it is available, else on asyncio's own loop."""
    try:
        import uvloop
    except ImportError:
        return asyncio.run(make())
    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        return runner.run(make())


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.sink == "file" and args.output is None:
        parser.error("--sink file needs --output OUT.mkv")
    if args.sink != "file" and args.output is not None:
        parser.error("--output is only for --sink file")
    if args.frames is not None and args.frames < 1:
        parser.error(f"--frames must be at least 1, got {args.frames}")
    if not args.stats_every > 0:
        parser.error(f"--stats-every must be positive, got {args.stats_every}")
    if not 1 <= args.threads <= 64:
        parser.error(f"--threads must be 1..64, got {args.threads}")
    if args.gpu and args.sink != "window":
        parser.error("--gpu is for --sink window (the GPU draws straight into the window)")

    from ipt.protocol import PacketFilter
    from ipt.sender.display import Sink, make_sink
    from ipt.sender.modulator import FrameTiming, Modulator, delta_l_warning, make_modulator
    from ipt.sender.scene import ArScene
    from ipt.sender.server import DEFAULT_LISTEN, parse_listen, run_sender
    from ipt.tagmap import grid_tag_map

    arena = load_arena_config(args.config if args.config is not None else DEFAULT_ARENA)
    if args.modulation is not None:
        modulation = arena.modulation.model_copy(update={"profile": args.modulation})
        arena = arena.model_copy(update={"modulation": modulation})
    pr, mod = arena.projector, arena.modulation
    if (warning := delta_l_warning(mod.delta_l)) is not None:
        _note(f"warning: {warning}")
    if args.listen is not None:
        listen: tuple[str, int] | None = parse_listen(args.listen)
    else:
        listen = None if args.sink == "file" else DEFAULT_LISTEN
    key = _read_key(args.auth_key_file) if args.auth_key_file is not None else None
    packet_filter = PacketFilter(key=key, vehicle_ids=args.vehicles, resync_after_s=10.0)
    if args.gpu and mod.profile != "ipt":
        parser.error(f"--gpu makes the ipt profile's phases; the arena's modulation.profile is {mod.profile!r}")
    mask = grid_tag_map(arena).render_mask()
    modulator: Modulator = make_modulator(mod.profile, mask, mod.delta_l, args.threads, mod.clip_allowance_l8)
    scene, input_rate_hz = _scene(args, arena)
    timing = FrameTiming(input_rate_hz, pr.rate_hz)
    if (note := timing.note()) is not None:
        _note(note)
    sink: Sink | None = None
    on_gpu = False
    if args.gpu:
        sink, gpu_modulator = _gpu_path(args, arena, mask)
        if gpu_modulator is not None:
            modulator, on_gpu = gpu_modulator, True
    if sink is None:
        sink = make_sink(
            args.sink,
            output=args.output,
            fps=pr.rate_hz,
            width=pr.width_px,
            height=pr.height_px,
            display_index=args.display,
            fullscreen=not args.windowed,
        )
    ratio = float(timing.ratio)
    per_input = f"N={int(timing.ratio)}" if timing.whole else f"{ratio:.3g} output frames per input frame"
    print(
        f"ipt-sender: {pr.width_px}x{pr.height_px} at {pr.rate_hz:g} Hz, input {input_rate_hz:g} Hz "
        f"({per_input}), modulation {mod.profile}"
        + (f" (clip allowance {mod.clip_allowance_l8:g})" if mod.profile == "ipt" else "")
        + f", ΔL {mod.delta_l:g}, sink {args.sink}{' (phases on the GPU)' if on_gpu else ''} "
        f"({'paced' if sink.paced else 'as fast as possible'})"
        + ("" if key is None else ", authenticated packets only"),
        file=sys.stderr,
    )
    try:
        stats = _run(
            lambda: run_sender(
                arena,
                sink,
                scene,
                frames=args.frames,
                listen=listen,
                packet_filter=packet_filter,
                ar_scene=ArScene(arena),
                stats_every_s=args.stats_every,
                input_rate_hz=input_rate_hz,
                modulator=modulator,
            )
        )
    finally:
        for thing in (scene, modulator):
            close = getattr(thing, "close", None)
            if close is not None:
                close()
    if args.sink == "file":
        print(f"ipt-sender: wrote {stats.frames} frames -> {args.output}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ipt-sender``."""
    rc = run_main("ipt-sender", _main, argv)
    # Everything is closed and reported. The interpreter's last garbage collection would walk numba's many
    # compiler objects (about a second on a busy machine, after SIGTERM); leave them to the process exit.
    gc.freeze()
    return rc


if __name__ == "__main__":
    sys.exit(main())
