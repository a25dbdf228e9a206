"""Replay a recorded flight through the receiver pipeline and write the poses as a TUM file.

Frame ``k`` of the recording has time ``k / fps``. Progress goes to stderr about once a second; the
output appears only when the run completes (it is written beside the target and renamed). A recording
is read to its end: a frame that cannot be decoded (or an image that cannot be read, or is of another
size) is skipped and counted, keeping the others' times, and a file that ends before the frames its
header announces is reported as truncated.

A ``--record-frames`` recording (:mod:`ipt.receiver.capture.framelog`) is replayed by
:func:`replay_frame_log` instead: with its own frame numbers and capture times, not ``k / fps``.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
import numpy.typing as npt

from ipt.config.camera_info import load_camera_info
from ipt.config.models import MAX_RATE_HZ, MIN_CAMERA_RATE_HZ, ArenaConfig, PipelineConfig
from ipt.errors import IptError
from ipt.fileio import atomic_path
from ipt.maphash import map_hash
from ipt.ratelimit import LogThrottle
from ipt.receiver.core.history import Prepared
from ipt.receiver.core.pipeline import FrameResult, Pipeline
from ipt.receiver.detect.detector import pipeline_detector
from ipt.tagmap import TagMap, grid_tag_map
from ipt.tum import TUM_HEADER, format_tum_line
from ipt.videoio import FrameSource, open_frames


class ReplayError(IptError):
    """The recording and the settings do not fit together."""


@dataclass(frozen=True)
class ReplaySummary:
    """Totals of a replay."""

    frames: int
    poses: int
    seconds: float
    reasons: dict[str, int]
    skipped: int = 0
    """Frames of the recording that could not be decoded or read, or were of another size (not processed)."""
    shortfall: str | None = None
    """Why the recording ended before the frames its header announced (a truncated file), if it did."""

    @property
    def yield_fraction(self) -> float:
        """Poses per camera frame."""
        return self.poses / self.frames if self.frames else 0.0

    def line(self) -> str:
        """The one-line summary printed at the end."""
        fps = self.frames / self.seconds if self.seconds > 0 else float("inf")
        why = ", ".join(f"{k}={v}" for k, v in sorted(self.reasons.items()))
        skipped = f", {self.skipped} unreadable frames skipped" if self.skipped else ""
        return (
            f"replay: {self.frames} frames, {self.poses} poses, yield {100 * self.yield_fraction:.1f} %, "
            f"{fps:.1f} frames/s{skipped} ({why})"
        )


def _read_ahead(source: FrameSource, pipeline: Pipeline) -> Iterator[tuple[int, npt.NDArray[np.uint8] | Prepared]]:
    """The source's frames with their numbers (skipped frames keep theirs: every frame keeps its time). With
    more than one core to run on, each is read and prepared (:meth:`Pipeline.prepare`) on a second thread
    while the one before it is processed: the same results, the pipeline's thread freed of that share."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    if cores < 2:
        for frame in source:
            yield source.index, frame
        return

    def read() -> tuple[int, Prepared] | None:
        frame = next(source, None)
        return None if frame is None else (source.index, pipeline.prepare(frame))

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="ipt-prepare") as ahead:
        coming = ahead.submit(read)
        while (item := coming.result()) is not None:
            coming = ahead.submit(read)
            yield item


def _camera_rate(video_path: Path, rate: float | None) -> float:
    """``rate`` (``--fps``, else the video's own), if it is a camera's; else one :class:`ReplayError` line."""
    if rate is None or rate <= 0:
        raise ReplayError(f"{video_path}: the frame rate is unknown; give it with --fps")
    if not MIN_CAMERA_RATE_HZ <= rate <= MAX_RATE_HZ:
        raise ReplayError(
            f"{video_path}: its frame rate {rate:.3g} fps is not a camera's ({MIN_CAMERA_RATE_HZ:g} to "
            f"{MAX_RATE_HZ:g}); give the rate with --fps"
        )
    return rate


def _no_hook(frame: object, result: FrameResult | None, sent: int) -> None:
    """:func:`replay`'s ``on_result`` when none is given (the daemon's hook takes each result as ``(None, result,
    0)``: no frame object, nothing sent)."""


def replay(
    arena: ArenaConfig,
    tag_map: TagMap,
    camera_path: Path,
    video_path: Path,
    output_path: Path,
    fps: float | None,
    pipeline_cfg: PipelineConfig,
    progress: TextIO | None = sys.stderr,
    on_result: Callable[[object, FrameResult | None, int], None] = _no_hook,
) -> ReplaySummary:
    """Run the recording at ``video_path`` through the pipeline; one TUM line per pose; ``on_result``: the hook."""
    camera = load_camera_info(camera_path)
    with open_frames(video_path, skip_bad=True, grey=pipeline_cfg.luminance_only) as source:
        if (source.width, source.height) != (camera.width_px, camera.height_px):
            raise ReplayError(
                f"{camera_path}: the camera is {camera.width_px}x{camera.height_px} but {video_path} has "
                f"{source.width}x{source.height} frames"
            )
        rate = _camera_rate(video_path, fps if fps is not None else source.fps)
        pipeline = Pipeline(
            tag_map,
            camera,
            pipeline_cfg,
            arena.projector.rate_hz,
            pipeline_detector(pipeline_cfg.detector, tag_map.by_id),
        )
        total = source.frame_count
        frames = poses = 0
        start = last_report = time.monotonic()
        throttle = LogThrottle()
        said_skipped = 0

        def say_skipped() -> None:
            """A line for the newest skipped frame (a few, then a count: :class:`LogThrottle`)."""
            nonlocal said_skipped
            if progress is not None and source.skipped > said_skipped:
                said_skipped = source.skipped
                if line := throttle.line("skip", f"replay: {source.last_skipped}; skipped", time.monotonic()):
                    progress.write(line + "\n")

        with atomic_path(output_path) as tmp, tmp.open("w", encoding="utf-8") as out:
            out.write(TUM_HEADER + "\n")

            def write(results: list[FrameResult]) -> int:
                for result in results:
                    on_result(None, result, 0)
                    if result.pose is not None:
                        t_s = result.capture_time_us * 1e-6
                        out.write(format_tum_line(t_s, result.pose.position_m, result.pose.quat_wxyz))
                return sum(r.pose is not None for r in results)

            for k, frame in _read_ahead(source, pipeline):
                say_skipped()
                poses += write(pipeline.process(k, frame, round(k / rate * 1e6)))
                frames += 1
                now = time.monotonic()
                if progress is not None and now - last_report >= 1.0:
                    last_report = now
                    of = f"/{total}" if total else ""
                    progress.write(
                        f"replay: frame {frames}{of}, {poses} poses ({100 * poses / frames:.0f} %), "
                        f"{frames / (now - start):.0f} frames/s\n"
                    )
                    progress.flush()
            poses += write(pipeline.flush())
            say_skipped()
        summary = ReplaySummary(
            frames,
            poses,
            time.monotonic() - start,
            dict(pipeline.reasons),
            skipped=source.skipped,
            shortfall=source.shortfall(),
        )
    if progress is not None:
        progress.write(summary.line() + "\n")
        if summary.shortfall is not None:
            progress.write(f"replay: {summary.shortfall}\n")
    return summary


def exact_tum_line(capture_time_us: int, position_m: Iterable[float], quat_wxyz: Iterable[float]) -> str:
    """A TUM line that keeps every bit: the time from its integer microseconds, the numbers in Python's
    shortest round-trip form (``float(text)`` gives the same float64 back)."""
    w, x, y, z = (float(v) for v in quat_wxyz)
    t = f"{capture_time_us // 1_000_000}.{capture_time_us % 1_000_000:06d}"
    return " ".join([t, *(repr(float(v)) for v in position_m), repr(x), repr(y), repr(z), repr(w)]) + "\n"


def replay_frame_log(folder: Path, output_path: Path, progress: TextIO | None = sys.stderr) -> ReplaySummary:
    """Play a ``--record-frames`` recording back through the pipeline the live run had (its arena, camera and
    pipeline settings are in the recording) with the recorded frame numbers and capture times, and the
    live run's finishing points where it dropped frames and each frame's wait (its live rules read it): the poses
    it sent, bit for bit, as exact TUM lines (:func:`exact_tum_line`)."""
    # Here, not at the top: the capture package (cameras, PyAV, asyncio) is not for a replay of a recording.
    from ipt.receiver.capture.framelog import KIND_FINISH, KIND_LOST, FrameLog

    log = FrameLog(folder)
    try:
        arena = ArenaConfig.model_validate(log.meta["arena"])
        pipeline_cfg = PipelineConfig.model_validate(log.meta["pipeline"])
    except (KeyError, ValueError) as exc:
        raise ReplayError(f"{folder}: the recording's settings cannot be read ({exc})") from None
    tag_map = grid_tag_map(arena)
    if map_hash(tag_map) != log.meta.get("map_hash"):
        raise ReplayError(f"{folder}: the arena's map hash is not the recorded one (another version of ipt?)")
    detector = pipeline_detector(pipeline_cfg.detector, tag_map.by_id)
    pipeline = Pipeline(tag_map, load_camera_info(log.camera_file), pipeline_cfg, arena.projector.rate_hz, detector)
    frames = poses = 0
    notes: list[str] = []
    start = time.monotonic()
    with atomic_path(output_path) as tmp, tmp.open("w", encoding="utf-8") as out:
        out.write(TUM_HEADER + "\n")

        def write(results: list[FrameResult]) -> int:
            kept = [r for r in results if r.pose is not None]
            for r in kept:
                assert r.pose is not None
                out.write(exact_tum_line(r.capture_time_us, r.pose.position_m, r.pose.quat_wxyz))
            return len(kept)

        for event in log.events():
            if event.kind == KIND_FINISH:
                poses += write(pipeline.finish_before(event.capture_time_us))
            elif event.kind == KIND_LOST:
                notes.append(f"frames were not recorded before frame {event.index}: poses from there on may differ")
            elif event.image is not None:
                poses += write(pipeline.process(event.index, event.image, event.capture_time_us, event.waited_us))
                frames += 1
        poses += write(pipeline.flush())
    summary = ReplaySummary(frames, poses, time.monotonic() - start, dict(pipeline.reasons), shortfall=log.problem)
    if progress is not None:
        progress.write(summary.line() + "\n")
        for note in [*notes, *([log.problem] if log.problem else [])]:
            progress.write(f"replay: {note}\n")
    return summary
