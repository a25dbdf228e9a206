"""The sender's statistics: what a run did (:class:`SenderStats`) and the duration histograms it keeps.

Plain counters and numbers, no clocks and no threads: the sender (:mod:`ipt.sender.server`) fills them
in, :meth:`SenderStats.line` is the line it prints and :meth:`SenderStats.to_dict` what the benchmarks
write.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from ipt.protocol import ACCEPTED
from ipt.runtime import Histogram


@dataclass
class SenderStats:
    """What the sender did; :meth:`line` is the statistics line it prints."""

    width_px: int
    height_px: int
    rate_hz: float
    paced: bool
    frames: int = 0
    """Output frames handed to the sink."""
    missed: int = 0
    """Frames whose rendering finished after their due time (paced sinks only)."""
    late: int = 0
    """Frames rendered in time but reached more than half a period after their due time, because the sink
    or the loop was behind (paced sinks only)."""
    elapsed_s: float = 0.0
    """From showing the first frame to showing the last."""
    work_ms: Histogram = field(default_factory=Histogram)
    """Render-thread time per output frame: at the first output frame of an input frame, waiting for its
    content (made ahead in the content thread), the overlay and both phases; the others reuse them."""
    overlay_ms: Histogram = field(default_factory=Histogram)
    """Time of the AR overlay per input frame."""
    work_cpu_ms: Histogram = field(default_factory=Histogram)
    """CPU time of the render thread per output frame: the part of ``work_ms`` that is not waiting for a core
    (on a busy machine ``work_ms`` grows, this does not)."""
    content_ms: Histogram = field(default_factory=Histogram)
    """Content-thread time per input frame (scene frame, resize to projector size), made ahead in parallel."""
    content_cpu_ms: Histogram = field(default_factory=Histogram)
    """CPU time of the content thread per input frame."""
    overlay_errors: int = 0
    content_errors: int = 0
    """Input frames the scene failed to make; the last good one was shown instead (phases alternating)."""
    display_errors: int = 0
    """Output frames the sink failed to show; the loop went on (phases alternating) and tried the next."""
    packets: Counter[str] = field(default_factory=Counter)
    """Datagram outcomes: ``accepted`` and each rejection reason (and ``error``)."""
    vehicles: int = 0
    """Vehicles on the overlay when the statistics were taken."""
    pacing: dict[str, Any] | None = None
    """What the sink saw of its frames reaching the screen, for a sink that times them (the window:
    :meth:`~ipt.sender.display.WindowSink.pacing`): refreshes that repeated a frame, frames never shown."""
    startup_s: float = math.nan
    """From the start of the run to the first frame shown: the colour table, warming memory, the first
    frame's work (the modulator was made before)."""
    stopped_by: int | None = None
    """The signal that stopped the run, if one did."""
    output_kept: bool = True
    """Whether the sink's output (a file) was kept: not when the run stopped short of the frames asked for."""

    @property
    def frames_per_s(self) -> float:
        """Output rate between the first frame shown and the last."""
        return (self.frames - 1) / self.elapsed_s if self.frames > 1 and self.elapsed_s > 0 else math.nan

    @property
    def accepted(self) -> int:
        return self.packets[ACCEPTED]

    @property
    def rejected(self) -> int:
        return sum(v for k, v in self.packets.items() if k != ACCEPTED)

    def line(self, frames: int | None = None, seconds: float | None = None, work: Histogram | None = None) -> str:
        """One line of statistics; ``frames``/``seconds``/``work`` override the totals (for an interval)."""
        work = self.work_ms if work is None else work
        if frames is None or seconds is None:
            fps = self.frames_per_s
        else:
            fps = frames / seconds if seconds > 0 else math.nan
        reasons = ", ".join(f"{k}={v}" for k, v in sorted(self.packets.items()) if k != ACCEPTED and v)
        text = (
            f"frames={self.frames} fps={fps:.2f} work_p50={work.percentile(50):.2f}ms "
            f"work_p99={work.percentile(99):.2f}ms missed={self.missed} late={self.late} "
            f"vehicles={self.vehicles} packets accepted={self.accepted} rejected={self.rejected}"
        )
        if reasons:
            text += f" ({reasons})"
        if self.overlay_errors:
            text += f" overlay_errors={self.overlay_errors}"
        if self.content_errors:
            text += f" content_errors={self.content_errors}"
        if self.display_errors:
            text += f" display_errors={self.display_errors}"
        if self.pacing is not None:
            p = self.pacing
            text += (
                f" repeated_vsyncs={p['repeated_vsyncs']} dropped_frames={p['dropped_frames']} "
                f"present_p99={p['present_interval_p99_ms']:.2f}ms"
            )
        return text

    def to_dict(self) -> dict[str, Any]:
        """The totals as plain JSON-able values."""
        return {
            "width_px": self.width_px,
            "height_px": self.height_px,
            "rate_hz": self.rate_hz,
            "paced": self.paced,
            "output_frames": self.frames,
            "seconds": round(self.elapsed_s, 3),
            "frames_per_s": round(self.frames_per_s, 3),
            "work_p50_ms": round(self.work_ms.percentile(50), 3),
            "work_p99_ms": round(self.work_ms.percentile(99), 3),
            "work_mean_ms": round(self.work_ms.mean_ms, 3),
            "work_max_ms": round(self.work_ms.max_ms, 3),
            "overlay_p50_ms": round(self.overlay_ms.percentile(50), 3),
            "overlay_p99_ms": round(self.overlay_ms.percentile(99), 3),
            "work_cpu_p50_ms": round(self.work_cpu_ms.percentile(50), 3),
            "work_cpu_p99_ms": round(self.work_cpu_ms.percentile(99), 3),
            "work_cpu_mean_ms": round(self.work_cpu_ms.mean_ms, 3),
            "content_p50_ms": round(self.content_ms.percentile(50), 3),
            "content_p99_ms": round(self.content_ms.percentile(99), 3),
            "content_cpu_p50_ms": round(self.content_cpu_ms.percentile(50), 3),
            "content_cpu_p99_ms": round(self.content_cpu_ms.percentile(99), 3),
            "content_cpu_mean_ms": round(self.content_cpu_ms.mean_ms, 3),
            "startup_s": round(self.startup_s, 3),
            "missed_deadlines": self.missed,
            "late_frames": self.late,
            "repeated_phases": self.missed + self.late,
            "overlay_errors": self.overlay_errors,
            "content_errors": self.content_errors,
            "display_errors": self.display_errors,
            "packets": dict(sorted(self.packets.items())),
            "pacing": self.pacing,
        }

