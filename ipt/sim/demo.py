"""``ipt demo``: the closed loop: sender, simulated drone camera and receiver daemon in one process.

What runs, on one asyncio event loop (uvloop when installed):

- the **sender**, :func:`ipt.sender.server.run_sender`, with the built-in generated content, the AR
  overlay and the paper's modulator. Its sink is a :class:`LockstepProjector`: the "projector", an
  in-memory sink keeping the newest :data:`KEEP_FRAMES` output frames by index.
- the **drone's camera**, :class:`ClosedLoopArena`: the simulator of ``ipt sim`` with one change, its
  floor is lit by exactly what the sender output. ``projector_crop(j, region)`` is that region of the
  sender's output frame ``j`` (modulated, drone overlay included), not a re-modulation of the content.
- the **receiver daemon**, :func:`ipt.receiver.daemon.run_daemon`, whose capture source is that camera
  (:class:`ClosedLoopCapture`). It sends each pose over real UDP to the sender's listener on 127.0.0.1
  (a free port); the sender's packet filter accepts it and the overlay draws the drone at that position
  in the next input frame, so the drone's own marker is in the picture the camera then sees.

Clock. Simulated time drives everything; nothing waits for the wall clock. Camera frame ``k`` is
exposed around ``t_k = k / fps``; projector output frame ``j`` lies on the floor for one period from the
simulator's projector offset on (:meth:`SimulatedArena.projector_index`). Before it renders frame ``k``
the capture source waits until the receiver has finished frame ``k - 1`` and the sender's listener has
taken in its packet; then it sets the simulated clock to ``t_k`` and renders. Rendering asks the
projector for the output frames its exposure covers: the projector opens the gate on the sender's
content for their input frame ``i = j // N`` (:class:`_GatedScene`: the sender's render thread may take
input frame ``i`` only once it is asked for) and waits until the sender has shown frame ``j``. So the
sender makes each frame on demand, in order; the overlay of input frame ``i`` shows every pose up to the
camera frame before the first one that needed it (as if a pose reached the projector within one camera
frame), with the simulated time as the overlay's clock (fading, trails); and a run is deterministic for
a seed. The price: the stages run one after the other, so the loop is slower than real time. The
status line on stderr says by how much. (The sender's work times in ``sender.log`` include its waits
for the camera at the gate.)
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final, TextIO

import numpy as np
import numpy.typing as npt
import yaml

from ipt import signals
from ipt.config.camera_info import save_camera_info
from ipt.config.models import ArenaConfig, load_arena_config
from ipt.config.receiver import ReceiverConfig
from ipt.fileio import write_text_atomic
from ipt.geometry import quat_wxyz_from_matrix
from ipt.receiver.capture import CapturedFrame
from ipt.receiver.core.pipeline import FrameResult
from ipt.receiver.daemon import DaemonStats, load_setup, run_daemon
from ipt.runtime import line_writer, run_loop
from ipt.sender.modulator import frames_per_input
from ipt.sender.overlay import ArOverlay
from ipt.sender.server import SenderStats, run_sender
from ipt.sim.arena import scene_for
from ipt.sim.config import SimCameraConfig, SimConfig, apply_arena_changes, describe_flight
from ipt.sim.lockstep import (
    ClosedLoopArena,
    ClosedLoopCapture,
    DemoError,
    Lockstep,
    LockstepProjector,
    SimClock,
    _CountingFilter,
)
from ipt.sim.render import camera_info_of
from ipt.tagmap import TagMap, grid_tag_map
from ipt.tum import Trajectory, write_tum

U8 = npt.NDArray[np.uint8]

STATUS_EVERY_S: Final = 1.0
"""Wall-clock interval of the status line."""
LISTEN_HOST: Final = "127.0.0.1"
RESULT_NAMES: Final = ("summary.txt", "errors.png", "report.json", "poses.tum", "groundtruth.tum")
"""What a run writes in its results folder (besides camera.yaml and the two logs)."""


@dataclass
class FlightLog:
    """Every camera frame the receiver finished: the truth, the pose sent, the error, the latency.

    :meth:`on_result` is the daemon's result hook (on the event loop); :meth:`on_processed` tells the
    lockstep that a frame went through.
    """

    source: ClosedLoopCapture
    lockstep: Lockstep
    truth_rows: list[tuple[float, npt.NDArray[np.float64], npt.NDArray[np.float64]]] = field(default_factory=list)
    pose_rows: list[tuple[float, npt.NDArray[np.float64], npt.NDArray[np.float64]]] = field(default_factory=list)
    packets_sent: int = 0
    errors_m: list[float] = field(default_factory=list)
    latencies_s: list[float] = field(default_factory=list)
    failed_frames: int = 0

    @property
    def frames(self) -> int:
        return len(self.truth_rows)

    def on_result(self, frame: CapturedFrame, result: FrameResult | None, sent: int) -> None:
        latency = time.monotonic() - frame.grabbed_s
        truth = self.source.truth.pop(frame.index)
        t = frame.capture_time_us * 1e-6
        self.truth_rows.append((t, truth.position_m, quat_wxyz_from_matrix(truth.r_arena_cam)))
        if result is None:
            self.failed_frames += 1
        elif result.pose is not None and sent > 0:
            p = np.asarray(result.pose.position_m, dtype=np.float64)
            self.pose_rows.append((t, p, np.asarray(result.pose.quat_wxyz, dtype=np.float64)))
            self.errors_m.append(float(np.linalg.norm(p - truth.position_m)))
            self.latencies_s.append(latency)
        self.packets_sent += sent

    def on_processed(self, frame: CapturedFrame, sent: int) -> None:
        """The daemon's hook for every frame processed: the camera may render the next one once the
        packets of the results that came out with it are in."""
        self.lockstep.frame_done(frame.index, sent)

    def truth(self) -> Trajectory | None:
        return _trajectory(self.truth_rows)

    def poses(self) -> Trajectory | None:
        return _trajectory(self.pose_rows)


def _trajectory(rows: list[tuple[float, npt.NDArray[np.float64], npt.NDArray[np.float64]]]) -> Trajectory | None:
    if not rows:
        return None
    return Trajectory.from_arrays(
        np.array([r[0] for r in rows]), np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    )


@dataclass
class DemoRun:
    """The outcome of one closed-loop run."""

    seconds_asked: float
    fps: float
    flight: FlightLog
    projector_frames_used: int
    """Output frames up to the newest one the camera asked for."""
    daemon: DaemonStats | None
    sender: SenderStats | None
    lockstep: Lockstep
    listen: tuple[str, int] | None
    loop_wall_s: float
    """Wall time of the loop itself, from the first camera frame to the receiver's end."""
    total_wall_s: float
    """Wall time of the whole run, set-up included."""
    interrupted: bool
    seed: int

    @property
    def simulated_s(self) -> float:
        """Simulated seconds the receiver finished."""
        return self.flight.frames / self.fps

    @property
    def real_time_factor(self) -> float:
        return self.simulated_s / self.loop_wall_s if self.loop_wall_s > 0 else math.nan


def real_time_text(factor: float) -> str:
    """``0.12x real time (slower than real time)`` and the like."""
    if not math.isfinite(factor):
        return "-"
    if factor < 1.0:
        return f"{factor:.2f}x real time (this machine is slower than real time)"
    return f"{factor:.2f}x real time"


# --- the run ---------------------------------------------------------------------------------------------


class _Status:
    """The status line on stderr, about once a second: rewritten in place on a terminal."""

    def __init__(self, out: TextIO, run_total_s: float, fps: float) -> None:
        self.out, self.total_s, self.fps = out, run_total_s, fps
        self.tty = bool(getattr(out, "isatty", lambda: False)())
        self._latency_mark = 0
        self._pending_newline = False

    def line(self, flight: FlightLog, wall_s: float) -> str:
        sim_s = flight.frames / self.fps
        poses = len(flight.pose_rows)
        rate = f"{poses / sim_s:.0f} poses/s" if sim_s > 0 else "- poses/s"
        err = f"{1e3 * float(np.mean(flight.errors_m)):.1f} mm" if flight.errors_m else "-"
        recent = flight.latencies_s[self._latency_mark :] or flight.latencies_s[-1:]
        self._latency_mark = len(flight.latencies_s)
        lat = f"{1e3 * float(np.mean(recent)):.1f} ms" if recent else "-"
        factor = sim_s / wall_s if wall_s > 0 else math.nan
        return (
            f"ipt demo: {sim_s:.2f}/{self.total_s:.2f} s simulated, {rate}, position error {err} (mean), "
            f"capture->send {lat}, {real_time_text(factor)}"
        )

    def show(self, text: str) -> None:
        try:
            if self.tty:
                self.out.write("\r\x1b[K" + text)
                self._pending_newline = True
            else:
                self.out.write(text + "\n")
            self.out.flush()
        except (OSError, ValueError):
            pass

    def end(self) -> None:
        if self._pending_newline:
            with contextlib.suppress(OSError, ValueError):
                self.out.write("\n")
                self.out.flush()
            self._pending_newline = False


async def closed_loop(
    arena_path: Path,
    seconds: float,
    out: Path,
    seed: int = 0,
    *,
    sim: SimConfig | None = None,
    status: TextIO | None = None,
    interrupt: asyncio.Event | None = None,
) -> DemoRun:
    """Fly ``seconds`` of ``sim`` (default: the realistic default flight, :class:`SimConfig`) in the closed
    loop (see the module doc); ``seed`` replaces the flight's seed.

    The status line goes to ``status`` (none without it). Setting ``interrupt`` stops the run early
    (what was flown is kept); SIGINT sets it when this runs on the main thread. Writes
    ``out/camera.yaml``, ``out/arena.yaml`` (the arena flown, with the flight's changes),
    ``out/sender.log`` and ``out/receiver.log``.
    """
    if not seconds > 0 or not math.isfinite(seconds):
        raise DemoError(f"--seconds must be a positive number, got {seconds:g}")
    wall_start = time.monotonic()
    sim = (sim if sim is not None else SimConfig()).model_copy(update={"seed": seed})
    try:
        arena = apply_arena_changes(load_arena_config(arena_path), sim.arena)
    except ValueError as exc:
        raise DemoError(f"the flight's arena changes do not fit {arena_path}: {exc}") from None
    cam = sim.camera
    count = max(1, round(seconds * cam.fps))
    tag_map = grid_tag_map(arena)
    per_input = frames_per_input(arena.modulation.input_rate_hz, arena.projector.rate_hz)
    camera_path, flown_arena = _results_folder(out, arena, cam)
    run = _ClosedLoop(arena, sim, count, tag_map, per_input, status, interrupt)
    await run.fly(out, flown_arena, camera_path)
    return run.result(seconds, cam.fps, wall_start, seed)


def _results_folder(out: Path, arena: ArenaConfig, cam: SimCameraConfig) -> tuple[Path, Path]:
    """Make ``out`` with the camera and the arena flown in it (their paths), without a previous run's results."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DemoError(f"{out}: cannot create the results folder ({exc.strerror or exc})") from None
    for name in RESULT_NAMES:  # a previous run's results would look like this run's if it stops early
        (out / name).unlink(missing_ok=True)
    camera_path = out / "camera.yaml"
    save_camera_info(camera_info_of(cam), camera_path)
    flown_arena = out / "arena.yaml"
    write_text_atomic(flown_arena, yaml.safe_dump(arena.model_dump(mode="json"), sort_keys=False))
    return camera_path, flown_arena


class _ClosedLoop:
    """The parts of one closed-loop run and what they gave: :meth:`fly` runs the sender and the receiver
    daemon until the flight ends or is interrupted, :meth:`result` says what happened."""

    def __init__(
        self,
        arena: ArenaConfig,
        sim: SimConfig,
        count: int,
        tag_map: TagMap,
        per_input: int,
        status: TextIO | None,
        interrupt: asyncio.Event | None,
    ) -> None:
        loop = asyncio.get_running_loop()
        cam = sim.camera
        self.arena = arena
        self.projector = projector = LockstepProjector(per_input)
        self.lockstep = lockstep = Lockstep()
        self.clock = clock = SimClock()
        self.source = source = ClosedLoopCapture(arena, sim, projector, lockstep, clock, count, tag_map)
        self.flight = FlightLog(source, lockstep)
        self.scene = projector.gated(scene_for(sim, arena))
        self.interrupt = interrupt if interrupt is not None else asyncio.Event()
        self.sender_stop, self.daemon_stop = asyncio.Event(), asyncio.Event()
        self.listening: asyncio.Future[tuple[str, int]] = loop.create_future()
        self.shower = _Status(status, count / cam.fps, cam.fps) if status is not None else None
        self.daemon_stats: DaemonStats | None = None
        self.sender_stats: SenderStats | None = None
        self.loop_start = self.loop_end = time.monotonic()
        self.failure: BaseException | None = None
        self.tasks: list[asyncio.Task[Any]] = []

    def on_stop_signal(self, signum: int) -> None:
        self.interrupt.set()  # Ctrl-C, SIGTERM or SIGHUP: stop flying and score what was flown (a second one waits)

    def on_listening(self, address: tuple[str, int]) -> None:
        if not self.listening.done():
            self.listening.set_result(address)

    async def fly(self, out: Path, flown_arena: Path, camera_path: Path) -> None:
        """Run the sender, then the receiver daemon on the simulated camera, until the flight ends, the
        run is interrupted or a part fails; then stop both in order. The logs go into ``out``."""
        loop = asyncio.get_running_loop()
        with (
            (out / "sender.log").open("w", encoding="utf-8") as sender_log,
            (out / "receiver.log").open("w", encoding="utf-8") as receiver_log,
        ):
            sender_task = loop.create_task(
                run_sender(
                    self.arena,
                    self.projector,
                    self.scene,
                    paced=False,
                    listen=(LISTEN_HOST, 0),
                    packet_filter=_CountingFilter(self.lockstep),
                    overlay=ArOverlay(self.arena),
                    log=line_writer(sender_log),
                    install_signal_handlers=False,
                    stop=self.sender_stop,
                    overlay_clock=self.clock.now,
                    on_listening=self.on_listening,
                ),
                name="ipt-demo-sender",
            )
            unroute = signals.route_to_loop(loop, self.on_stop_signal)
            try:
                await self._receive(sender_task, receiver_log, flown_arena, camera_path)
            except BaseException as exc:
                self.failure = exc
                raise
            finally:
                await self._stop(sender_task, unroute)

    async def _receive(
        self, sender_task: asyncio.Task[SenderStats], receiver_log: TextIO, flown_arena: Path, camera_path: Path
    ) -> None:
        """Once the sender listens, run the receiver daemon until the flight ends or is interrupted."""
        loop = asyncio.get_running_loop()
        first: set[asyncio.Future[Any]] = {self.listening, sender_task}
        await asyncio.wait(first, return_when=asyncio.FIRST_COMPLETED)
        if not self.listening.done():
            await sender_task  # raises what stopped it
            raise DemoError("the sender stopped before it listened for pose packets")
        host, port = self.listening.result()
        cfg = ReceiverConfig(arena=flown_arena, camera=camera_path, send=[f"{host}:{port}"], stats_interval_s=5.0)
        self.loop_start = time.monotonic()
        daemon_task = loop.create_task(
            run_daemon(
                load_setup(cfg),
                stop=self.daemon_stop,
                stats_out=receiver_log,
                install_signal_handlers=False,
                source=self.source,
                on_result=self.flight.on_result,
                on_processed=self.flight.on_processed,
            ),
            name="ipt-demo-receiver",
        )
        interrupted_task = loop.create_task(self.interrupt.wait())
        self.tasks.append(interrupted_task)
        if self.shower is not None:

            def start() -> float:
                return self.source.started_s or self.loop_start

            self.tasks.append(loop.create_task(_report(self.shower, self.flight, start)))
        await asyncio.wait({daemon_task, sender_task, interrupted_task}, return_when=asyncio.FIRST_COMPLETED)
        if not daemon_task.done():  # interrupted, or the sender failed: stop the camera and the receiver
            self.lockstep.stop()
            self.projector.stop()
            self.daemon_stop.set()
        try:
            self.daemon_stats = await daemon_task
        finally:
            self.loop_end = time.monotonic()
            self.loop_start = self.source.started_s or self.loop_start

    async def _stop(self, sender_task: asyncio.Task[SenderStats], unroute: Callable[[], None]) -> None:
        """Stop the status line, the camera and the sender, and take the sender's totals."""
        for task in self.tasks:
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        self.lockstep.stop()
        self.sender_stop.set()
        self.projector.stop()
        try:
            self.sender_stats = await sender_task
        except Exception as exc:
            if self.failure is None:
                raise DemoError(f"the sender failed: {type(exc).__name__}: {exc}") from exc
        finally:
            unroute()
            if self.shower is not None:
                self.shower.show(self.shower.line(self.flight, max(self.loop_end - self.loop_start, 1e-9)))
                self.shower.end()

    def result(self, seconds: float, fps: float, wall_start: float, seed: int) -> DemoRun:
        """What the run gave (:class:`DemoError` if the simulated camera failed)."""
        if self.source.failure is not None:
            raise DemoError(self.source.failure)
        listening = self.listening
        return DemoRun(
            seconds_asked=seconds,
            fps=fps,
            flight=self.flight,
            projector_frames_used=self.projector.asked + 1,
            daemon=self.daemon_stats,
            sender=self.sender_stats,
            lockstep=self.lockstep,
            listen=listening.result() if listening.done() and not listening.cancelled() else None,
            loop_wall_s=self.loop_end - self.loop_start,
            total_wall_s=time.monotonic() - wall_start,
            interrupted=self.interrupt.is_set(),
            seed=seed,
        )


async def _report(shower: _Status, flight: FlightLog, start: Callable[[], float]) -> None:
    while True:
        await asyncio.sleep(STATUS_EVERY_S)
        shower.show(shower.line(flight, time.monotonic() - start()))


# --- results ------------------------------------------------------------------------------------------------


def summary_dict(run: DemoRun) -> dict[str, Any]:
    """The run's totals as plain JSON-able values (also written as summary.txt)."""
    flight, d, s = run.flight, run.daemon, run.sender
    errors = np.asarray(flight.errors_m)
    lat_ms = 1e3 * np.asarray(flight.latencies_s)
    accepted = s.accepted if s is not None else 0
    rejected = s.rejected if s is not None else 0
    return {
        "simulated_s": round(run.simulated_s, 6),
        "simulated_s_asked": run.seconds_asked,
        "interrupted": run.interrupted,
        "seed": run.seed,
        "camera_frames": flight.frames,
        "camera_fps": run.fps,
        "projector_frames": run.projector_frames_used,
        "projector_frames_made": s.frames if s is not None else 0,
        "poses": len(flight.pose_rows),
        "yield": len(flight.pose_rows) / flight.frames if flight.frames else 0.0,
        "packets_sent": flight.packets_sent,
        "packets_accepted": accepted,
        "packets_rejected": rejected,
        "packets_lost": run.lockstep.lost,
        "listen": f"{run.listen[0]}:{run.listen[1]}" if run.listen is not None else None,
        "position_error_mean_m": float(errors.mean()) if errors.size else None,
        "position_error_median_m": float(np.median(errors)) if errors.size else None,
        "latency_p50_ms": float(np.percentile(lat_ms, 50)) if lat_ms.size else None,
        "latency_p99_ms": float(np.percentile(lat_ms, 99)) if lat_ms.size else None,
        "loop_wall_s": round(run.loop_wall_s, 3),
        "total_wall_s": round(run.total_wall_s, 3),
        "real_time_factor": round(run.real_time_factor, 4) if math.isfinite(run.real_time_factor) else None,
        "sender_vehicles": s.vehicles if s is not None else 0,
        "receiver_frames_processed": d.frames_processed if d is not None else flight.frames,
    }


def summary_text(run: DemoRun) -> str:
    """summary.txt: one ``key: value`` line per total, with a short explanation at the top."""
    d = summary_dict(run)

    def mm(v: float | None) -> str:
        return "-" if v is None else f"{1e3 * v:.1f} mm"

    def ms(v: float | None) -> str:
        return "-" if v is None else f"{v:.1f} ms"

    lines = [
        "ipt demo: the closed loop (sender, simulated drone camera and receiver daemon in one process;",
        "poses over UDP on loopback to the sender, which draws the drone into the projected video).",
        "",
        f"simulated flight: {d['simulated_s']:.3f} s of {d['simulated_s_asked']:g} s asked"
        + (" (interrupted)" if d["interrupted"] else ""),
        f"seed: {d['seed']}",
        f"camera frames: {d['camera_frames']} at {d['camera_fps']:g} Hz",
        f"projector frames: {d['projector_frames']} filmed by the camera "
        f"({d['projector_frames_made']} made by the sender)",
        f"poses: {d['poses']}",
        f"yield: {100 * d['yield']:.1f} %",
        f"packets sent: {d['packets_sent']} (receiver daemon -> udp {d['listen']})",
        f"packets accepted: {d['packets_accepted']} (by the sender's packet filter)",
        f"packets rejected: {d['packets_rejected']}",
        f"packets lost: {d['packets_lost']}",
        f"position error: mean {mm(d['position_error_mean_m'])}, median {mm(d['position_error_median_m'])}",
        f"capture->send latency: p50 {ms(d['latency_p50_ms'])}, p99 {ms(d['latency_p99_ms'])} (wall clock)",
        f"wall time: {d['loop_wall_s']:.1f} s for the loop, {d['total_wall_s']:.1f} s in all",
        f"real-time factor: {real_time_text(run.real_time_factor)}",
    ]
    return "\n".join(lines) + "\n"


def write_results(run: DemoRun, out: Path) -> str | None:
    """Write the results folder; the paper's table as text, or None when there is no pose to score."""
    from ipt.eval import evaluate, format_table, plot_report

    truth, est = run.flight.truth(), run.flight.poses()
    write_text_atomic(out / "summary.txt", summary_text(run))
    if truth is not None:
        write_tum(out / "groundtruth.tum", truth)
    if est is not None:
        write_tum(out / "poses.tum", est)
    if truth is None or est is None:
        return None
    report = evaluate(truth, est)
    plot_report(truth, est, report, out / "errors.png")
    data = report.to_dict()
    data["closed_loop"] = summary_dict(run)
    write_text_atomic(out / "report.json", json.dumps(data, indent=1) + "\n")
    return format_table(report)


def _remove_run_files(out: Path, made: list[Path]) -> None:
    """Remove what a failed run wrote in ``out``, and the folders it created if they are empty then."""
    for name in (*RESULT_NAMES, "camera.yaml", "arena.yaml", "sender.log", "receiver.log"):
        with contextlib.suppress(OSError):
            (out / name).unlink(missing_ok=True)
    for folder in made:  # innermost first
        try:
            folder.rmdir()
        except OSError:
            return


def run_demo(arena_path: Path, seconds: float, out: Path, seed: int = 0, sim: SimConfig | None = None) -> int:
    """``ipt demo``: the closed loop, then the paper's table on stdout and the results in ``out``.

    Exit status: 0, or 128 + the signal's number when interrupted (130 for Ctrl-C, 143 for SIGTERM), or 1
    when the flight gave no pose at all.
    """
    if not seconds > 0 or not math.isfinite(seconds):
        raise DemoError(f"--seconds must be a positive number, got {seconds:g}")
    flight = sim if sim is not None else SimConfig()
    print(
        f"ipt demo: {seconds:g} s in the closed loop: sender -> simulated camera -> receiver -> udp -> sender "
        f"(results -> {out})\nipt demo: the flight: {describe_flight(flight)}",
        flush=True,
    )
    made = [p for p in (out, *out.parents) if not p.exists()]  # the folders this run creates
    try:
        run = run_loop(closed_loop(arena_path, seconds, out, seed, sim=flight, status=sys.stderr))
        table = write_results(run, out)
    except Exception:  # a failed run leaves nothing behind (an interrupted one is scored: no exception)
        _remove_run_files(out, made)
        raise
    s = summary_dict(run)
    print(
        f"ipt demo: {s['camera_frames']} camera frames, {s['projector_frames']} projector frames, "
        f"{s['poses']} poses ({100 * s['yield']:.1f} %), packets sent {s['packets_sent']}, "
        f"accepted by the sender {s['packets_accepted']}; {run.loop_wall_s:.1f} s wall, "
        f"{real_time_text(run.real_time_factor)}"
    )
    if table is not None:
        print()
        print(table)
        print()
    else:
        print("ipt demo: no pose: nothing to score")
    names = (*RESULT_NAMES, "sender.log", "receiver.log")
    print(f"ipt demo: results in {out}/ ({', '.join(n for n in names if (out / n).is_file())})")
    if run.interrupted:
        return 128 + (signals.received() or 2)  # SIGINT unless a signal was noted
    return 0 if table is not None else 1


__all__ = [
    "ClosedLoopArena",
    "ClosedLoopCapture",
    "DemoError",
    "DemoRun",
    "FlightLog",
    "Lockstep",
    "LockstepProjector",
    "SimClock",
    "closed_loop",
    "run_demo",
    "summary_dict",
    "summary_text",
    "write_results",
]
