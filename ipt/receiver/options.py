"""How one run of the receiver daemon is set up, in two objects, as the sender's :mod:`ipt.sender.options`.

- :class:`ReceiverSetup`: what the configuration names, already loaded (:func:`load_setup`): the arena, the
  camera, the key, the tag map and its hash. A mistake in those files is an :class:`~ipt.errors.IptError`
  there, before the daemon starts.
- :class:`ReceiverOptions`: everything about a run but that: how it stops (the stop event, the signals, a
  number of frames), the hooks that see each result, the clock, and where the lines go.

:func:`~ipt.receiver.daemon.run_daemon` takes both (or the options' fields as keywords).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TextIO

from ipt.config.camera_info import CameraInfo, load_camera_info
from ipt.config.models import ArenaConfig, load_arena_config
from ipt.config.receiver import ReceiverConfig, read_auth_key
from ipt.maphash import map_hash
from ipt.receiver.capture import CapturedFrame, CaptureSource
from ipt.receiver.core.pipeline import FrameResult
from ipt.runtime import MONOTONIC, Clock
from ipt.tagmap import TagMap, grid_tag_map

if TYPE_CHECKING:
    from ipt.receiver.capture.framelog import FrameLogWriter

ResultHook = Callable[[CapturedFrame, FrameResult | None, int], None]
"""``on_result(frame, result, datagrams_sent)`` of :class:`ReceiverOptions`."""
ProcessedHook = Callable[[CapturedFrame, int], None]
"""``on_processed(frame, datagrams_sent)`` of :class:`ReceiverOptions`."""


@dataclass(frozen=True)
class ReceiverSetup:
    """The files a :class:`~ipt.config.receiver.ReceiverConfig` names, loaded (:func:`load_setup`)."""

    cfg: ReceiverConfig
    arena: ArenaConfig
    camera: CameraInfo
    key: bytes | None
    """The shared key of ``cfg.auth_key_file`` (``None``: packets are not authenticated)."""
    tag_map: TagMap
    map_hash: str
    """The tag map's hash (the sender prints it too: a mismatch is seen)."""


def load_setup(cfg: ReceiverConfig) -> ReceiverSetup:
    """Load the arena, the camera and the key ``cfg`` names (:class:`~ipt.errors.IptError` on a problem)."""
    arena = load_arena_config(cfg.arena)
    camera = load_camera_info(cfg.camera)
    key = read_auth_key(cfg.auth_key_file) if cfg.auth_key_file is not None else None
    tag_map = grid_tag_map(arena)
    return ReceiverSetup(cfg, arena, camera, key, tag_map, map_hash(tag_map))


@dataclass(frozen=True)
class ReceiverOptions:
    """Everything about a receiver run but its setup."""

    stop: asyncio.Event | None = None
    """Set it to stop the run from elsewhere."""
    install_signal_handlers: bool = True
    """SIGTERM, SIGINT and SIGHUP stop the run (main thread only)."""
    max_frames: int | None = None
    """Stop once the source delivered this many frames (``--max-frames``); ``None``: until stopped."""
    source: CaptureSource | None = None
    """The frame source, instead of the one ``cfg.source`` describes (the closed-loop demo feeds its simulation
    in this way); ``cfg.camera`` must still describe its frames."""
    capture_stop: threading.Event | None = None
    """The event that stops the capture thread (``None``: a new one). A source handed in paces its sleeps on it
    (as :func:`~ipt.receiver.daemon.make_source` does), so that they end at once at shutdown."""
    on_result: ResultHook | None = None
    """``on_result(frame, result, datagrams_sent)``, on the event loop for every frame's result, in capture order,
    once its packet (if any) was handed to the kernel (``result`` is ``None`` if processing raised). A result may
    come a few frames after its frame was processed (the pipeline's ``lookahead_frames``)."""
    on_processed: ProcessedHook | None = None
    """``on_processed(frame, datagrams_sent)``, once each frame was processed and the results that became final
    with it were delivered, with the datagrams sent for them."""
    frame_log: FrameLogWriter | None = None
    """Keeps every frame handed to the pipeline (``--record-frames``; :mod:`ipt.receiver.capture.framelog`); the
    caller closes it."""
    stats_out: TextIO | None = None
    """Where the statistics lines go (``None``: stderr)."""
    clock: Clock = MONOTONIC
    """The time the daemon runs on: its statistics (interval lines, seconds, latency against each frame's
    ``grabbed_s``, so a source handed in stamps its frames on the same clock) and the wait between interval
    lines. Tests pass a :class:`~ipt.runtime.SteppedClock` and step it instead of sleeping."""
