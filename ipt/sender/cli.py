"""``ipt-sender``: project the video with the hidden tags, and draw the drones it hears about on it.

Only the standard library and :mod:`ipt.cliutil` load with this module; the rest loads in ``main``, after
the stop signals are handled (:mod:`ipt.signals`), so that SIGTERM at any moment of the start-up gives
the final statistics line and exit status 0.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import sys
from collections.abc import Callable, Coroutine, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

from ipt import __version__
from ipt.cliutil import Parser, run_main
from ipt.errors import IptError
from ipt.signals import Interrupted, interruption

if TYPE_CHECKING:
    from ipt.config.models import ArenaConfig
    from ipt.protocol import PacketFilter
    from ipt.sender.display import Sink
    from ipt.sender.modulator import FrameTiming

DEFAULT_ARENA_NAME = "arena.yaml"
"""The arena shipped in ``ipt/config``, used when ``--config`` is not given."""
MIN_STATS_EVERY_S = 0.1
"""Shortest --stats-every: ten lines a second is already more than anyone reads (1e-300 gave one a frame)."""
MAX_STATS_EVERY_S = 86400.0
"""Longest --stats-every (a day)."""

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


def _vehicle_count(text: str) -> int:
    """An argparse ``type``: how many vehicles may be tracked (1..65536)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: '{text}'") from None
    if not 1 <= value <= 65536:
        raise argparse.ArgumentTypeError(f"must be 1..65536, got {value}")
    return value


def _rate_limit(text: str) -> float:
    """An argparse ``type``: datagrams per second, 0 for no limit."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: '{text}'") from None
    if not (math.isfinite(value) and (value == 0 or 1 <= value <= 1e7)):
        raise argparse.ArgumentTypeError(f"must be 0 (no limit) or 1..1e7 datagrams a second, got '{text}'")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The ``ipt-sender`` argument parser."""
    p = Parser(
        prog="ipt-sender",
        description="The IPT sender: hide the arena's AprilTag map in a video as a lightness flicker at the "
        "projector rate and show it (full screen, to a file, or nowhere for a benchmark). It listens for the "
        "drones' pose packets and draws each drone, its heading and its trail on the video.",
        epilog="Without --video or --image the built-in map-app animation is shown. Statistics go to stderr "
        "every few seconds and when it stops (SIGINT, SIGTERM or SIGHUP, at any moment, also while starting: "
        "exit status 0); the last line holds missed=<deadlines>. With --sink file and --frames N, a run stopped "
        "short of N frames keeps no file and exits with 128 + the signal's number. Pose packets: without a key "
        "anyone on the network can place vehicles on the projection, so give --auth-key-file (the shipped "
        "service does) or --vehicles; at most --max-vehicles are drawn whatever arrives.",
    )
    p.add_argument("--version", action="version", version=f"ipt-sender {__version__}")
    p.add_argument("--config", metavar="ARENA.yaml", help=f"arena YAML (default: the shipped {DEFAULT_ARENA_NAME})")
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
    _add_network_options(p)
    p.add_argument(
        "--gpu",
        action="store_true",
        help="--sink window, ipt profile: make the phases on the GPU (OpenGL 3.3; needs moderngl: pip install "
        "'ipt[gpu]'), leaving the CPU only the content and the overlay. If the GPU path cannot start, one line "
        "says why and the CPU makes the phases",
    )
    p.add_argument("--display", type=int, default=0, metavar="N", help="display index of --sink window (default 0)")
    p.add_argument("--windowed", action="store_true", help="--sink window in a window rather than full screen")
    p.add_argument(
        "--stats-every",
        type=float,
        default=5.0,
        metavar="S",
        help=f"statistics interval ({MIN_STATS_EVERY_S:g} to {MAX_STATS_EVERY_S:g} s; default 5 s)",
    )
    return p


def _add_network_options(p: argparse.ArgumentParser) -> None:
    """Where the pose packets come from and which are taken."""
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
        "--max-vehicles",
        type=_vehicle_count,
        metavar="N",
        help="most vehicles tracked and drawn at once (default 16); packets of further vehicles are refused and "
        "counted (vehicle_limit) until one has been silent for 10 s",
    )
    p.add_argument(
        "--source-rate-limit",
        type=_rate_limit,
        metavar="HZ",
        help="datagrams a second taken from one source address (default 1000; 0: no limit); the rest are "
        "refused and counted (rate_limited) before they are decoded",
    )


def _read_key(path: str) -> bytes:
    """The key file's bytes, without one trailing line break (keys are often written with ``echo``); the key
    file must be private and the key at least 16 bytes."""
    from ipt.keyfile import read_key_file

    return read_key_file(path)  # one line naming the file: missing, not private, too short (ipt.keyfile)


def _scene(args: argparse.Namespace, arena: ArenaConfig) -> tuple[Any, float]:
    """The content and its frame rate; notes on stderr where it is resized or re-timed."""
    from ipt.config.models import MAX_RATE_HZ, MIN_CONTENT_RATE_HZ
    from ipt.imageio import read_image
    from ipt.sender.content import GeneratedScene, StillImageScene
    from ipt.sender.prefetch import PrefetchedVideo
    from ipt.videoio import open_frames

    w, h = arena.projector.width_px, arena.projector.height_px
    rate_hz = arena.modulation.input_rate_hz
    if args.video is not None:
        with open_frames(args.video) as source:
            size, fps = (source.width, source.height), source.fps
        if size != (w, h):
            _note(f"input video is {size[0]}x{size[1]}; frames are resized to {w}x{h}")
        if fps is not None and math.isfinite(fps) and fps > 0:
            if not MIN_CONTENT_RATE_HZ <= fps <= MAX_RATE_HZ:
                raise SenderCliError(
                    f"{args.video}: its frame rate is {fps:.3g} fps; content is played at "
                    f"{MIN_CONTENT_RATE_HZ:g} to {MAX_RATE_HZ:g} frames a second"
                )
            if abs(fps - rate_hz) > 1e-3:
                _note(f"input video is {fps:g} fps, not the arena's input_rate_hz {rate_hz:g}: played at its own rate")
            rate_hz = fps
        # Decoded and resized ahead in a thread of its own (the next loop opened before it is due; a short
        # loop, such as a few photos, kept in memory): see ipt.sender.prefetch.
        return PrefetchedVideo(args.video, w, h), rate_hz
    if args.image is not None:
        image = read_image(args.image, "rgb", SenderCliError)
        if image.shape[:2] != (h, w):
            _note(f"input image is {image.shape[1]}x{image.shape[0]}; it is resized to {w}x{h}")
        return StillImageScene(image, w, h), rate_hz
    return GeneratedScene(w, h), rate_hz


def _note(text: str) -> None:
    print(f"ipt-sender: {text}", file=sys.stderr)


def _gpu_path(args: argparse.Namespace, arena: ArenaConfig, mask: Any) -> tuple[Any, Any]:
    """The GPU window and its modulator, ready (colour table complete, textures up); or, when the GPU path
    cannot start, one line saying why and (None, None): the CPU makes the phases instead."""
    from ipt.sender.gpu import GlWindowSink, GpuError, GpuModulator
    from ipt.sender.pairtable import default_cache_dir

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
    # Imported here, not at the top: asyncio alone takes longer to import than everything else up to main().
    from ipt.runtime import run_loop

    return run_loop(make())


def _check_flags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.sink == "file" and args.output is None:
        parser.error("--sink file needs --output OUT.mkv")
    if args.sink != "file" and args.output is not None:
        parser.error("--output is only for --sink file")
    if args.frames is not None and args.frames < 1:
        parser.error(f"--frames must be at least 1, got {args.frames}")
    if not (MIN_STATS_EVERY_S <= args.stats_every <= MAX_STATS_EVERY_S):  # also false for nan
        parser.error(
            f"--stats-every must be {MIN_STATS_EVERY_S:g} to {MAX_STATS_EVERY_S:g} seconds, got {args.stats_every}"
        )
    if not 1 <= args.threads <= 64:
        parser.error(f"--threads must be 1..64, got {args.threads}")
    if args.gpu and args.sink != "window":
        parser.error("--gpu is for --sink window (the GPU draws straight into the window)")


EMPTY_STATS_LINE = (
    "ipt-sender: done: frames=0 fps=nan work_p50=nanms work_p99=nanms missed=0 late=0 vehicles=0 packets "
    "accepted=0 rejected=0"
)
"""The final statistics line of a run that never showed a frame (``SenderStats.line()`` of nothing, spelt
out: a stop signal may have cut an import short, so nothing more is imported to print it)."""


def _stopped_while_starting(exc: Interrupted, args: argparse.Namespace | None) -> int:
    """What a stop signal during the start-up leaves: a note, the final line and the documented status."""
    _note(f"stopped by {exc.name} while starting")
    print(EMPTY_STATS_LINE, file=sys.stderr)
    if args is not None and args.sink == "file" and args.frames is not None:
        _note(f"{args.output} was not written (0 of the {args.frames} frames asked for)")
        return exc.exit_status
    return 0


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _check_flags(parser, args)
    try:
        return _serve(args)
    except (Interrupted, Exception) as exc:  # or a library's error that wraps one (signals.interruption)
        stop = interruption(exc)
        if stop is None:
            raise
        return _stopped_while_starting(stop, args)


def _serve(args: argparse.Namespace) -> int:
    from ipt.maphash import map_hash_line
    from ipt.sender.modulator import FrameTiming, Modulator, delta_l_warning, make_modulator
    from ipt.sender.options import SenderOptions
    from ipt.sender.overlay import ArOverlay
    from ipt.sender.server import run_sender
    from ipt.tagmap import grid_tag_map

    arena = _arena(args)
    pr, mod = arena.projector, arena.modulation
    if (warning := delta_l_warning(mod.delta_l)) is not None:
        _note(f"warning: {warning}")
    listen = _listen(args)
    packet_filter, max_vehicles = _packet_filter(args)
    if args.gpu and mod.profile != "ipt":
        raise SenderCliError(f"--gpu makes the ipt profile's phases; the arena's modulation.profile is {mod.profile!r}")
    with contextlib.ExitStack() as stack:
        mask = (tag_map := grid_tag_map(arena)).render_mask()
        modulator: Modulator = make_modulator(mod.profile, mask, mod.delta_l, args.threads, mod.clip_allowance_l8)
        stack.callback(_close, modulator)
        scene, input_rate_hz = _scene(args, arena)
        stack.callback(_close, scene)
        timing = FrameTiming(input_rate_hz, pr.rate_hz)
        if (note := timing.note()) is not None:
            _note(note)
        sink, gpu_modulator = _gpu_path(args, arena, mask) if args.gpu else (None, None)
        if gpu_modulator is not None:
            modulator = gpu_modulator
            stack.callback(_close, gpu_modulator)
        if sink is None:
            sink = _make_sink(args, arena)
        print(map_hash_line("ipt-sender", tag_map), file=sys.stderr)
        _say_what_runs(args, arena, timing, sink, gpu_modulator is not None, max_vehicles)
        options = SenderOptions(
            frames=args.frames,
            listen=listen,
            packet_filter=packet_filter,
            overlay=ArOverlay(arena, max_vehicles=max_vehicles),
            stats_every_s=args.stats_every,
            input_rate_hz=input_rate_hz,
            modulator=modulator,
        )
        try:
            stats = _run(lambda: run_sender(arena, sink, scene, options))
        except BaseException:
            sink.abort()  # a file begun before the run (or in it) is not left behind; aborting twice is harmless
            raise
    if stats.stopped_by is not None and not stats.output_kept:
        from ipt.signals import signal_name

        _note(
            f"stopped by {signal_name(stats.stopped_by)} after {stats.frames} of the {args.frames} frames asked "
            f"for: {args.output} was not written"
        )
        return 128 + stats.stopped_by
    if args.sink == "file":
        print(f"ipt-sender: wrote {stats.frames} frames -> {args.output}")
    return 0


def _arena(args: argparse.Namespace) -> ArenaConfig:
    """The arena of ``--config`` (default: the shipped one), with ``--modulation`` applied."""
    from ipt.config.models import load_arena_config, shipped_config_path

    arena = load_arena_config(args.config if args.config is not None else shipped_config_path(DEFAULT_ARENA_NAME))
    if args.modulation is not None:
        modulation = arena.modulation.model_copy(update={"profile": args.modulation})
        arena = arena.model_copy(update={"modulation": modulation})
    return arena


def _listen(args: argparse.Namespace) -> tuple[str, int] | None:
    """Where to listen for pose packets: ``--listen``, else the default (no listener for a file by default)."""
    from ipt.sender.server import DEFAULT_LISTEN, parse_listen

    if args.listen is not None:
        return parse_listen(args.listen)
    return None if args.sink == "file" else DEFAULT_LISTEN


def _packet_filter(args: argparse.Namespace) -> tuple[PacketFilter, int]:
    """The pose packets' gate of ``--auth-key-file``, ``--vehicles``, ``--max-vehicles`` and
    ``--source-rate-limit``, and the most vehicles tracked."""
    from ipt.protocol import PacketFilter
    from ipt.sender.overlay import DEFAULT_MAX_VEHICLES
    from ipt.sender.server import DEFAULT_SOURCE_RATE_HZ

    key = _read_key(args.auth_key_file) if args.auth_key_file is not None else None
    max_vehicles = args.max_vehicles if args.max_vehicles is not None else DEFAULT_MAX_VEHICLES
    rate = args.source_rate_limit if args.source_rate_limit is not None else DEFAULT_SOURCE_RATE_HZ
    packet_filter = PacketFilter(
        key=key,
        vehicle_ids=args.vehicles,
        resync_after_s=10.0,
        max_vehicles=max_vehicles,
        source_rate_hz=rate or None,
    )
    return packet_filter, max_vehicles


def _make_sink(args: argparse.Namespace, arena: ArenaConfig) -> Sink:
    """The sink of ``--sink`` (window, file or null)."""
    from ipt.sender.display import make_sink

    pr = arena.projector
    return make_sink(
        args.sink,
        output=args.output,
        fps=pr.rate_hz,
        width=pr.width_px,
        height=pr.height_px,
        display_index=args.display,
        fullscreen=not args.windowed,
    )


def _say_what_runs(
    args: argparse.Namespace, arena: ArenaConfig, timing: FrameTiming, sink: Sink, on_gpu: bool, max_vehicles: int
) -> None:
    """The one line on stderr that says what this run does, before it starts."""
    pr, mod = arena.projector, arena.modulation
    ratio = float(timing.ratio)
    per_input = f"N={int(timing.ratio)}" if timing.whole else f"{ratio:.3g} output frames per input frame"
    guard = "authenticated packets only" if args.auth_key_file is not None else "packets not authenticated"
    if args.vehicles is not None:
        guard += f", vehicles {' '.join(map(str, args.vehicles))}"
    print(
        f"ipt-sender: {pr.width_px}x{pr.height_px} at {pr.rate_hz:g} Hz, input {timing.input_rate_hz:g} Hz "
        f"({per_input}), modulation {mod.profile}"
        + (f" (clip allowance {mod.clip_allowance_l8:g})" if mod.profile == "ipt" else "")
        + f", ΔL {mod.delta_l:g}, sink {args.sink}{' (phases on the GPU)' if on_gpu else ''} "
        f"({'paced' if sink.paced else 'as fast as possible'}), {guard}, at most {max_vehicles} vehicles",
        file=sys.stderr,
    )


def _close(thing: object) -> None:
    close = getattr(thing, "close", None)
    if close is not None:
        close()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ipt-sender``."""
    rc = run_main("ipt-sender", _main, argv, on_interrupt=lambda exc: _stopped_while_starting(exc, None))
    # Everything is closed and reported. The interpreter's last garbage collection would walk numba's many
    # compiler objects (about a second on a busy machine, after SIGTERM); leave them to the process exit.
    gc.freeze()
    return rc


if __name__ == "__main__":
    sys.exit(main())
