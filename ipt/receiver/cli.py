"""``ipt-receiver``: the drone side — replay a recorded flight, or run the receiver daemon.

Only the standard library and :mod:`ipt.cliutil` load with this module; the rest loads when a command
runs, after the stop signals are handled (:mod:`ipt.signals`): ``run`` stopped by SIGTERM, SIGINT or
SIGHUP at any moment, also while starting, prints its final statistics line and exits with status 0.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ipt import __version__
from ipt.cliutil import Parser, positive_float, run_main
from ipt.memory import keep_freed_memory
from ipt.signals import Interrupted, interruption

if TYPE_CHECKING:
    from ipt.config.models import PipelineConfig
    from ipt.config.receiver import ReceiverConfig
    from ipt.receiver.capture import CaptureSource
    from ipt.receiver.capture.framelog import FrameLogWriter
    from ipt.receiver.core.frameresult import FrameResult

PROFILES = ("ipt", "paper")
"""The processing profiles of ``replay --profile`` (:meth:`ipt.config.models.PipelineConfig.profile`)."""
MIN_FPS, MAX_FPS = 1.0, 1000.0  # ipt.config.models.MIN_CAMERA_RATE_HZ and MAX_RATE_HZ, without importing it


def _camera_rate(text: str) -> float:
    """An argparse ``type``: a camera frame rate, 1 to 1000 Hz (``nan``, ``inf``, ``1e-300`` are refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: '{text}'") from None
    if not (math.isfinite(value) and MIN_FPS <= value <= MAX_FPS):
        raise argparse.ArgumentTypeError(f"must be a frame rate of {MIN_FPS:g} to {MAX_FPS:g} Hz, got '{text}'")
    return value


def _cmd_replay(args: argparse.Namespace) -> int:
    # As the daemon does: AprilTag's helper forked first, while this process is lean and runs one thread (a
    # fork costs a few hundredths of a second of processor time where a new interpreter costs a tenth or more);
    # the garbage collector held off until the first pose (a replay's collections: 0.058 -> 0.002 s on
    # moving-content's 960 frames).
    hold = GcHeldForStartUp()
    from ipt.receiver.detect import tagworker

    tagworker.prestart()
    try:
        return _replay(args, hold)
    finally:
        hold.release()
        tagworker.drop_prestarted()  # not adopted: AprilTag ran inline, or the replay failed before it began


def _replay(args: argparse.Namespace, hold: GcHeldForStartUp) -> int:
    from ipt.config.models import PipelineConfig, load_arena_config, shipped_config_path
    from ipt.receiver.detect.tagworker import drop_prestarted
    from ipt.receiver.replay import ReplayError, replay, replay_frame_log
    from ipt.tagmap import grid_tag_map

    if (args.video is None) == (args.frames is None):
        raise ReplayError("replay: give either --video (with --camera) or --frames")
    if args.frames is not None and (args.camera or args.config or args.fps or args.rolling_shutter):
        raise ReplayError("replay --frames: the recording holds its arena, camera and settings; drop the other flags")
    if args.rolling_shutter and args.profile != "ipt":
        raise ReplayError("replay --rolling-shutter: only the ipt profile models a rolling shutter")
    if args.frames is None and args.camera is None:
        raise ReplayError("replay --video: --camera CAMERA.yaml is needed")
    if args.frames is not None:
        hold.release()  # (a recording's replay takes no hook: the collector runs throughout, as it may be long)
        summary = replay_frame_log(Path(args.frames), Path(args.output))
        print(f"ipt-receiver replay: {summary.poses} poses from {summary.frames} frames -> {args.output}")
        _say_kernels()
        return 0
    arena = load_arena_config(args.config or shipped_config_path("arena.yaml"))
    cfg = _replay_config(PipelineConfig.profile(args.profile), args.tracker, args.rolling_shutter)
    if cfg.detector.isolation != "process":
        drop_prestarted()  # AprilTag runs in this process: the forked helper has nothing to do
    tag_map = grid_tag_map(arena)
    camera, video, output = Path(args.camera), Path(args.video), Path(args.output)
    summary = replay(arena, tag_map, camera, video, output, args.fps, cfg, on_result=hold.on_result)
    print(f"ipt-receiver replay: {summary.poses} poses from {summary.frames} frames -> {args.output}")
    _say_kernels()
    return 0


def _replay_config(cfg: PipelineConfig, tracker: str | None, rolling_shutter: bool) -> PipelineConfig:
    """``cfg`` with ``replay --tracker`` if given (the profile's own otherwise), told of a rolling shutter
    (``pose.track.rolling_shutter``, as a daemon's receiver.yaml tells it) with ``--rolling-shutter``."""
    if tracker is not None:
        cfg = cfg.model_copy(update={"tracker": tracker})
    return cfg.with_rolling_shutter() if rolling_shutter else cfg


def _say_kernels() -> None:
    """The kernels' line (compiled? from the cache? compiled in this process?) on stdout: stderr's last line
    stays the run's final statistics (or the replay's summary)."""
    from ipt.receiver.core.kernelcache import status

    print(f"ipt-receiver: {status().line()}", flush=True)


def _cmd_warm(args: argparse.Namespace) -> int:
    """``ipt-receiver warm``: exit 0 when every kernel is compiled and in numba's disk cache, else 1."""
    from ipt.receiver.core.kernelcache import STAMP_NAME, already_warm, cache_env_hint, compile_bytecode, warm

    compile_bytecode()  # ipt's own modules too: a start that compiles none of them saves a tenth of a second
    if not args.force and already_warm():
        print(f"ipt-receiver warm: kernels already cached for this installation ({STAMP_NAME} matches); "
              "--force loads them all")  # fmt: skip
        return 0
    kernel_status = warm(lambda step: print(f"ipt-receiver warm: {step}", file=sys.stderr, flush=True))
    print(f"ipt-receiver warm: {kernel_status.line()}")
    wanted = os.environ.get("NUMBA_CACHE_DIR")
    cached = kernel_status.cache_dir
    if kernel_status.compiled and cached and (not wanted or Path(cached).is_relative_to(Path(wanted).resolve())):
        return 0
    print(f"ipt-receiver warm: the kernels are not cached ({cache_env_hint()}): they will compile or fall back "
          "in every start; see docs/raspberry-pi.md", file=sys.stderr)  # fmt: skip
    return 1


def _positive_int(text: str) -> int:
    value = int(text)
    if value <= 0:
        raise ValueError(text)
    return value


_positive_int.__name__ = "positive integer"


EMPTY_FINAL_LINE = (
    "ipt-receiver: final: 0 frames (0 captured), 0 poses, 0 packets in 0.00 s: 0.0 frames/s, 0.0 poses/s, "
    "yield 0.0 %, latency p50 - p99 -, drops 0, send errors 0, capture failures 0, detector helpers replaced 0 "
    "for memory and 0 after failures ()"
)
"""The final statistics line of a run that never captured a frame (``DaemonStats.line()`` of nothing, spelt
out: a stop signal may have cut an import short, so nothing more is imported to print it)."""


def _stopped_while_starting(exc: Interrupted) -> int:
    """A stop signal before the daemon's loop ran: a note, the final statistics line, and exit status 0."""
    print(f"ipt-receiver: stopped by {exc.name} while starting", file=sys.stderr)
    print(EMPTY_FINAL_LINE, file=sys.stderr)
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    try:
        return _run_daemon(args)
    except (Interrupted, Exception) as exc:  # or a library's error that wraps one (signals.interruption)
        stop = interruption(exc)
        if stop is None:
            raise
        return _stopped_while_starting(stop)


def _run_daemon(args: argparse.Namespace) -> int:
    # Before anything else, while this process is lean and runs one thread: fork the AprilTag helper. Then the
    # kernels, which the daemon's first pose waits for above all (the paper profile, a research setting whose
    # pipeline does not use them, pays for their load on that thread).
    hold = GcHeldForStartUp()
    from ipt.receiver.detect import tagworker

    tagworker.prestart()
    hold.release_after(START_UP_SECONDS)  # (a thread: only once the helper is forked)
    try:
        return _run_daemon_started(args, hold)
    finally:
        tagworker.drop_prestarted()  # not adopted: AprilTag runs inline, or the start failed


START_UP_RESULTS = 240
"""Frames' results (2 s of a 120 FPS camera) after which :class:`GcHeldForStartUp` lets go without a pose."""
START_UP_SECONDS = 10.0
"""... and the seconds after which it lets go without any result (a camera that delivers nothing yet)."""


class GcHeldForStartUp:
    """Python's cyclic garbage collector, held off from the daemon's (or a replay's) start to its first pose.

    The start-up makes a few hundred thousand objects that live as long as the process (the modules of numba,
    pydantic, OpenCV and ipt, the configuration, the pipeline), and the collector's passes over them, two of
    them full, cost 0.05-0.1 s of processor time before the first pose here. At the first pose (or after
    :data:`START_UP_RESULTS` results without one, or :data:`START_UP_SECONDS` without any) everything alive
    is frozen (``gc.freeze``: left out of every later pass, as Python's documentation advises after a
    start-up) and collection resumes for what is made from then on. What cyclic garbage the start-up left
    stays frozen with it."""

    def __init__(self) -> None:
        self.held = gc.isenabled()
        self.results = 0
        self._lock = threading.Lock()
        self._timer: Any = None
        if self.held:
            gc.disable()

    def release_after(self, seconds: float, timer: Callable[..., Any] = threading.Timer) -> None:
        """Let go after ``seconds`` whatever comes (``timer``: :class:`threading.Timer` or a test's stand-in)."""
        if self.held:
            self._timer = timer(seconds, self.release)
            self._timer.daemon = True
            self._timer.start()

    def on_result(self, frame: object, result: FrameResult | None, sent: int) -> None:
        """The daemon's ``on_result`` hook (:class:`~ipt.receiver.options.ReceiverOptions`)."""
        if not self.held:
            return
        self.results += 1
        if (result is not None and result.pose is not None) or self.results >= START_UP_RESULTS:
            self.release()

    def release(self) -> None:
        with self._lock:  # (the timer's thread or the daemon's)
            if not self.held:
                return
            self.held = False
            if self._timer is not None:
                self._timer.cancel()
            gc.freeze()
            gc.enable()


def _run_daemon_started(args: argparse.Namespace, hold: GcHeldForStartUp) -> int:
    _warm_kernels_in_background()
    from ipt.config.models import shipped_config_path
    from ipt.config.receiver import load_receiver_config, with_overrides
    from ipt.receiver.daemon import ReceiverOptions, load_setup, run
    from ipt.receiver.outputs.udp import OutputError

    config = Path(args.config) if args.config else shipped_config_path("receiver.yaml")
    cfg = load_receiver_config(config)
    flags = {
        "arena": None if args.arena is None else Path(args.arena),
        "camera": None if args.camera is None else Path(args.camera),
        "source": args.source,
        "fps": args.fps,
        "send": args.send,
        "vehicle_id": args.vehicle_id,
        "realtime": True if args.realtime else None,
        "auth_key_file": None if args.auth_key_file is None else Path(args.auth_key_file),
    }
    updates: dict[str, object] = {k: v for k, v in flags.items() if v is not None}
    if args.mavlink is not None:
        updates["mavlink"] = {**cfg.mavlink.model_dump(), "link": None if args.mavlink == "off" else args.mavlink}
    if args.ros2:
        updates["ros2"] = {**cfg.ros2.model_dump(), "enabled": True}
    if args.record is not None:
        updates["record"] = {**cfg.record.model_dump(), "path": Path(args.record)}
    if updates:
        cfg = with_overrides(cfg, **updates)
    setup = load_setup(cfg)
    if cfg.pipeline.detector.isolation != "process":
        from ipt.receiver.detect.tagworker import drop_prestarted

        drop_prestarted()  # AprilTag runs in this process: the forked helper has nothing to do
    capture_stop = threading.Event()
    source = _simulated_camera(cfg, capture_stop) if cfg.source_spec.kind == "sim" else None
    frame_log = _frame_log(cfg, args)
    options = ReceiverOptions(
        max_frames=args.max_frames,
        source=source,
        capture_stop=capture_stop,
        frame_log=frame_log,
        on_result=hold.on_result,
    )
    try:
        stats = run(setup, options)
    except OutputError as exc:
        # Say where the target came from, so that the fix is one look away.
        where = "--send" if args.send else f"{config} (send:)"
        raise OutputError(f"{where}: {exc}") from None
    finally:
        if frame_log is not None:
            frame_log.close()
    _say_kernels()
    if stats.capture_running:
        # A read still inside native code (camera driver, renderer) must neither hold up the exit nor
        # see the C++ runtime torn down under it: leave now, everything worth keeping is written.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


def _warm_kernels_in_background() -> None:
    """Start loading the compiled kernels now, on a thread of their own: numba's import and its cache's load
    (a third of a second of processor time here) then overlap the rest of the start-up (the imports, the
    pipeline's set-up, the AprilTag helper, the camera) instead of following it. The pipeline starts the same
    once made (:func:`ipt.receiver.core.kernels.warm_in_background` runs once per process)."""
    from ipt.receiver.core import kernels

    kernels.warm_in_background()


def _frame_log(cfg: ReceiverConfig, args: argparse.Namespace) -> FrameLogWriter | None:
    """The flight recorder of ``--record-frames`` (:mod:`ipt.receiver.capture.framelog`), if asked for."""
    if args.record_frames is None:
        return None
    from ipt.receiver.capture.framelog import start_frame_log

    def say(line: str) -> None:
        print(f"ipt-receiver: {line}", file=sys.stderr, flush=True)

    folder = Path(args.record_frames)
    return start_frame_log(cfg, folder, say, max_mb=args.record_frames_max_mb, max_s=args.record_frames_max_s)


SOURCE_PLUGINS = "ipt.capture_sources"
"""The entry-point group of capture sources the receiver does not make itself (pyproject.toml): ``sim``, the
simulator's camera (:func:`ipt.sim.capture.receiver_sim_source`). The receiver's code imports nothing of the
simulator; an installation without it says so in one line."""


def _simulated_camera(cfg: ReceiverConfig, capture_stop: threading.Event) -> CaptureSource:
    """The ``sim`` source: the simulator's camera, found as a plug-in and handed to the daemon."""
    from importlib.metadata import entry_points

    from ipt.receiver.capture import CaptureError

    found = list(entry_points(group=SOURCE_PLUGINS, name="sim"))
    if not found:
        raise CaptureError(f"--source sim: no simulator in this installation ('{SOURCE_PLUGINS}' has no 'sim')")
    factory: Callable[[ReceiverConfig, threading.Event], CaptureSource] = found[0].load()
    return factory(cfg, capture_stop)


class _ListCameras(argparse.Action):
    """``--list-cameras``: print what was found and exit (like ``--version``, no command needed)."""

    def __init__(self, option_strings: Sequence[str], dest: str, help: str | None = None) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, help=help)

    def __call__(self, parser: argparse.ArgumentParser, *_: object) -> None:
        from ipt.receiver.capture import list_cameras

        print("\n".join(list_cameras()))
        parser.exit(0)


def build_parser() -> argparse.ArgumentParser:
    """The ``ipt-receiver`` argument parser."""
    p = Parser(
        prog="ipt-receiver",
        description="The IPT receiver: demodulate the hidden tags from a 120 FPS camera, detect them with "
        "AprilTag 3 and estimate the camera's pose in the arena.",
    )
    p.add_argument("--version", action="version", version=f"ipt-receiver {__version__}")
    p.add_argument(
        "--list-cameras",
        action=_ListCameras,
        help="list the cameras this computer has (V4L2 devices, picamera2 cameras) and exit",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    sub.required = True
    _add_replay(sub)
    _add_run(sub)
    _add_doctor(sub)
    w = sub.add_parser(
        "warm",
        help="compile the receiver's kernels into numba's disk cache and build them ahead of time, so that "
        "nothing compiles in flight",
        description="Compile every compiled kernel of the receiver (numba) and store it in numba's disk cache "
        "($NUMBA_CACHE_DIR; the systemd unit runs this with /var/cache/ipt-receiver before the daemon), so that "
        "`run` loads them in a fraction of a second instead of compiling for seconds. Then, where a C compiler "
        "is (Debian: apt install gcc), build them once more ahead of time into a module in $NUMBA_CACHE_DIR "
        "(numba.pycc; seconds here, a minute or so on a Pi), which later processes load without numba: a "
        "faster start and faster calls, the same poses to the bit. Says what it does on stderr and the outcome "
        "in one line; exit status 0 when every kernel is compiled and cached (built ahead or not), 1 when they "
        "cannot compile (numba missing, executable memory forbidden) or no cache folder is writable.",
    )
    w.add_argument(
        "--force",
        action="store_true",
        help="load (or compile) every kernel even when the cache's stamp says it is complete for this installation",
    )
    w.set_defaults(func=_cmd_warm)
    return p


def _cmd_doctor(args: argparse.Namespace) -> int:
    from ipt.config.models import shipped_config_path
    from ipt.receiver.doctor import main_lines

    config = Path(args.config) if args.config else shipped_config_path("receiver.yaml")

    def say(line: str) -> None:
        try:
            print(line, flush=True)
        except BrokenPipeError:  # `doctor | head`: the reader left; the checks (and the exit status) go on
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())

    return main_lines(config, say)


def _add_doctor(sub: argparse._SubParsersAction[Parser]) -> None:
    """``ipt-receiver doctor``."""
    d = sub.add_parser(
        "doctor",
        help="check this computer for the receiver: cameras, calibration, arena, key, targets, kernels, MAVLink",
        description="One line per check, with what to do when it fails (docs/doctor.md): the cameras and the modes "
        "their drivers advertise at the configured rate, the rate measured over 2 s, camera.yaml against the "
        "frames, the arena and its map hash, the key file, every send target, the compiled kernels, the MAVLink "
        "HEARTBEAT and the clock's synchronisation. Exit status 0 when every check passed, 1 otherwise.",
    )
    d.add_argument("--config", metavar="RECEIVER.yaml", help="receiver YAML (default: the shipped receiver.yaml)")
    d.set_defaults(func=_cmd_doctor)


def _add_replay(sub: argparse._SubParsersAction[Parser]) -> None:
    """``ipt-receiver replay``."""
    r = sub.add_parser(
        "replay",
        help="localise every frame of a recording and write a TUM trajectory",
        description="Run a recorded flight (a video file, or a folder of images in name order) through the "
        "receiver. Frame k has time k/fps. With --frames, a flight recorder's folder (run --record-frames) is played "
        "with its own frame numbers and capture times and the settings it was recorded with, to the poses the live "
        "run sent, bit for bit (exact TUM numbers). Writes one TUM line 't x y z qx qy qz qw' per pose: the camera's "
        "optical centre in arena metres and its rotation camera->arena (OpenCV optical axes).",
    )
    r.add_argument("--config", metavar="ARENA.yaml", help="arena YAML (default: the shipped paper arena)")
    r.add_argument("--camera", metavar="CAMERA.yaml", help="ROS camera_info YAML of the camera (with --video)")
    r.add_argument("--video", metavar="VIDEO|DIR", help="recording: video file or image folder")
    r.add_argument("--frames", metavar="DIR", help="a flight recorder's folder (ipt-receiver run --record-frames DIR)")
    r.add_argument("--fps", type=_camera_rate, help="camera frame rate, 1-1000 Hz (default: from the video file)")
    r.add_argument("--output", required=True, metavar="POSES.tum", help="where to write the poses")
    r.add_argument(
        "--profile",
        choices=PROFILES,
        default="ipt",
        help="processing profile: 'ipt' (default: opposite-phase pairing, sub-pixel alignment, refined and "
        "gated poses) or 'paper' (the published pipeline: lag-1 pairs, integer shift, IPPE alone)",
    )
    r.add_argument(
        "--tracker",
        choices=("dense", "sparse"),
        help="with the ipt profile: 'dense' (every frame undistorted, aligned and differenced) or 'sparse' (the "
        "sparse chain first, the dense way for the frames it does not pose; docs/receiver-cores.md); default: "
        "the profile's",
    )
    r.add_argument(
        "--rolling-shutter",
        action="store_true",
        help="the camera reads its rows out over time (most Pi and USB cameras): with the ipt profile, fit how the "
        "pose moves from the top row to the bottom one, as the daemon does with pose.track.rolling_shutter in its "
        "receiver.yaml",
    )
    r.set_defaults(func=_cmd_replay)


def _add_run(sub: argparse._SubParsersAction[Parser]) -> None:
    """``ipt-receiver run``."""
    d = sub.add_parser(
        "run",
        help="the receiver daemon: localise every camera frame and send UDP pose packets",
        description="Read frames from the simulator, a recording or a camera (V4L2 or picamera2), localise each "
        "and send one UDP pose packet per pose to every target, and with --mavlink (or mavlink.link) ODOMETRY to "
        "the flight controller (docs/flight-controllers.md). Statistics go to stderr every stats_interval_s "
        "seconds and at exit. With --ros2 (or ros2.enabled) also /ipt/pose, /ipt/odom and /tf as ROS 2 topics over "
        'DDS, and with --record an MCAP flight log (README "ROS 2 and flight logs"). Stops on SIGTERM, SIGINT or '
        "SIGHUP at any moment, also while starting (exit code 0, with the final statistics line), at the end of a "
        "recording, or after --max-frames. A recording is read to its end once: a frame that cannot be decoded is "
        "skipped and counted, and a file shorter than its header says is reported.",
    )
    d.add_argument("--config", metavar="RECEIVER.yaml", help="receiver YAML (default: the shipped receiver.yaml)")
    d.add_argument("--arena", metavar="ARENA.yaml", help="arena YAML (overrides the config)")
    d.add_argument("--camera", metavar="CAMERA.yaml", help="ROS camera_info YAML (overrides the config)")
    d.add_argument(
        "--source",
        metavar="SOURCE",
        help="sim, video:PATH, images:DIR, device:N or picamera2[:N] (overrides the config)",
    )
    d.add_argument(
        "--fps", type=_camera_rate, metavar="F", help="camera frame rate in Hz, 1-1000 (overrides the config)"
    )
    d.add_argument(
        "--send",
        action="append",
        metavar="HOST:PORT",
        help="UDP destination of the pose packets; repeat for several (replaces the config's list)",
    )
    d.add_argument("--vehicle-id", type=int, metavar="N", help="vehicle id in the packets, 0..65535")
    d.add_argument(
        "--auth-key-file",
        metavar="F",
        help="authenticate the pose packets with the key in this file (overrides the config's auth_key_file)",
    )
    d.add_argument(
        "--mavlink",
        metavar="LINK",
        help="MAVLink to the flight controller: udpout:HOST:PORT or serial:DEVICE:BAUD (e.g. "
        "serial:/dev/ttyAMA0:921600); 'off' for none (overrides the config's mavlink.link)",
    )
    d.add_argument(
        "--ros2",
        action="store_true",
        help="publish /ipt/pose, /ipt/odom and /tf as ROS 2 topics over DDS (CycloneDDS, no ROS needed: pip install "
        "'ipt[ros2]'); domain, QoS and names in the config's ros2: section, the network in $CYCLONEDDS_URI",
    )
    d.add_argument(
        "--record",
        metavar="FILE.mcap",
        help="write every frame's pose, odometry, transforms and diagnostics to an MCAP flight log with ROS 2 "
        "schemas, for Foxglove, ros2 bag and ipt eval (overrides the config's record.path)",
    )
    d.add_argument(
        "--record-frames",
        metavar="DIR",
        help="flight recorder: keep every frame the pipeline gets, losslessly, with its number and capture time, "
        "in DIR (new or empty), for 'ipt-receiver replay --frames DIR' (docs/doctor.md)",
    )
    d.add_argument(
        "--record-frames-max-mb",
        type=positive_float,
        default=4000.0,
        metavar="MB",
        help="stop recording frames at this size (default 4000 MB; localisation goes on)",
    )
    d.add_argument(
        "--record-frames-max-s",
        type=positive_float,
        default=600.0,
        metavar="S",
        help="stop recording frames after this many seconds of capture time (default 600)",
    )
    d.add_argument("--realtime", action="store_true", help="pace sim/video to the frame rate (a live source)")
    d.add_argument("--max-frames", type=_positive_int, metavar="N", help="stop after N captured frames")
    d.set_defaults(func=_cmd_run)


def _main(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    rc: int = args.func(args)
    return rc


SERIAL_LIBRARIES = {"OPENBLAS_NUM_THREADS": "1", "OPENCV_FOR_THREADS_NUM": "1"}
"""Set (unless already set) before numpy and OpenCV load (:func:`serial_libraries`). The receiver's matrix products
are small (3x3 up to a few thousand rows by 3), and OpenBLAS's worker threads, one per core, started with numpy in
this process and in the AprilTag helper, only spin: a tenth of a second of processor time at every start, taken from
the other core while the daemon starts. OpenCV's pool splits each remap, warp and blur of a 640-pixel frame over the
cores and its idle workers wait by spinning (``sched_yield``, 240 000-280 000 calls a replay): on this 2-core machine an
unpinned moving-content replay took 5.8-6.2 s of processor time against 4.5-5.3 with one thread, and no less wall
time (4.7-5.0 s against 4.2-4.9), the same poses; on a Pi's four cores the spin takes what the capture thread and the
AprilTag helper would use. Under ``taskset -c 0`` both run one thread anyway."""


def serial_libraries() -> None:
    """:data:`SERIAL_LIBRARIES` into the environment where the user has not set them (before numpy or OpenCV loads:
    each reads its variable then)."""
    for name, value in SERIAL_LIBRARIES.items():
        os.environ.setdefault(name, value)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ipt-receiver``."""
    serial_libraries()
    keep_freed_memory()  # (before the frames' arrays: ipt/memory.py)
    words = list(sys.argv[1:] if argv is None else argv)

    def on_interrupt(exc: Interrupted) -> int:
        """A stop signal before a command took over (while the arguments were read)."""
        if words[:1] == ["run"]:
            return _stopped_while_starting(exc)
        print(f"ipt-receiver: interrupted by {exc.name}; nothing was left half-written", file=sys.stderr)
        return exc.exit_status

    return run_main("ipt-receiver", _main, argv, on_interrupt=on_interrupt)


if __name__ == "__main__":
    sys.exit(main())
