"""How one run of the sender is set up, in one object: :class:`SenderOptions`.

The CLI builds one, :func:`~ipt.sender.server.run_sender` takes one (or the same fields as keywords) and
the :class:`~ipt.sender.server.Sender` reads it; a field left at its default is filled in by the sender
(the generated content, the sink's own pacing, the default packet filter, a new overlay, stderr).
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, Literal

if TYPE_CHECKING:
    from ipt.protocol import PacketFilter
    from ipt.sender.modulator import Modulator
    from ipt.sender.overlay import ArOverlay

DEFAULT_LISTEN: Final = ("127.0.0.1", 9870)
"""Where the sender listens for pose packets unless told otherwise."""


@dataclass(frozen=True)
class SenderOptions:
    """Everything about a sender run but the arena, the sink and the content."""

    frames: int | None = None
    """How many output frames to show; ``None`` runs until stopped."""
    paced: bool | None = None
    """Hand frame j to the sink at its due time; ``None``: the sink's own ``paced``."""
    listen: tuple[str, int] | None = DEFAULT_LISTEN
    """``(host, port)`` of the UDP pose listener, or ``None`` for none."""
    packet_filter: PacketFilter | None = None
    """The gate for datagrams (``None``: :func:`~ipt.sender.server.default_packet_filter`, any vehicle, no
    key, at most 16 vehicles, re-baselined after 10 s of silence so that a restarted drone is seen again)."""
    overlay: ArOverlay | None = None
    """The AR overlay (``None``: a new :class:`~ipt.sender.overlay.ArOverlay`); it may also be updated by the
    caller's own code (it is thread-safe)."""
    stats_every_s: float = 5.0
    """Interval of the statistics lines."""
    log: Callable[[str], None] | None = None
    """Where lines go (``None``: stderr)."""
    lookahead: int = 2
    """Frames the render thread may work ahead of the clock."""
    install_signal_handlers: bool = True
    """SIGTERM, SIGINT and SIGHUP stop the run (main thread only)."""
    stop: asyncio.Event | None = None
    """Set it to stop the run from elsewhere."""
    shutdown_timeout_s: float = 0.5
    """Bound on waiting for the render thread when stopping."""
    overlay_clock: Callable[[], float] | None = None
    """The time (seconds) the overlay runs on: given to :meth:`ArOverlay.update` for each accepted pose and to
    :meth:`ArOverlay.draw` for each input frame, so it sets fading and trails (``None``: ``time.monotonic``;
    the closed-loop demo passes the simulation's clock)."""
    on_listening: Callable[[tuple[str, int]], None] | None = None
    """Called with the bound ``(host, port)`` once the pose listener is up (useful with port 0)."""
    input_rate_hz: float | None = None
    """The content's frame rate (``None``: the arena's ``modulation.input_rate_hz``); any ratio to the
    projector rate works (:class:`~ipt.sender.modulator.FrameTiming`)."""
    modulator: Modulator | None = None
    """The modulator (``None``: the arena's ``modulation.profile`` for its tag map and ΔL)."""
    pair_cache: os.PathLike[str] | Literal["default"] | None = "default"
    """Folder of the ``ipt`` profile's colour table cache (``"default"``:
    :func:`~ipt.sender.pairtable.default_cache_dir`; ``None``: none, the table is computed at every start). A
    paced run completes the table before its first frame."""
