"""Who claims a vehicle: telling a restarted receiver from two receivers sharing one vehicle id (sans-IO).

A *source* of a vehicle's packets is where they come from (``peer``, e.g. ``"127.0.0.1:40001"``) and,
for version 2, the stream identity of the run that sent them (``None`` for version 1). A receiver
daemon that restarts becomes a new source (a new stream, usually a new port too) and its old source
falls silent. Two daemons that claim one vehicle id are two sources that both keep speaking.

:class:`SourceLog` tells the two apart by alternation: a source heard again after another source of
the same vehicle was heard in between, within :data:`CONFLICT_WINDOW_S` of one of the two packets around
it, is a conflict, and each pair of sources is reported once. A restart never alternates (the old run
is gone before the new one speaks), so it is never reported.

:class:`VehicleRegistry` is the per-vehicle state of the listening side (:class:`ipt.protocol.PacketFilter`):
which stream and sequence number a vehicle is at, whether a packet is newer, the vehicles' slots, and the
conflicts found. No clock is read here: the caller passes its own monotonic ``now``.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass, field
from typing import Final

CONFLICT_WINDOW_S: Final = 1.0
"""Two sources of one vehicle heard within this many seconds of each other, alternately, are a conflict."""

FORGET_SOURCE_S: Final = 10.0
"""A source not heard for this long is forgotten (it can no longer be half of a conflict)."""

MAX_SOURCES: Final = 8
"""Sources of one vehicle remembered at once (those heard within the window); the oldest goes first."""

MAX_REPORTED: Final = 256
"""Pairs of sources of one vehicle remembered as reported; beyond this the memory starts again."""


@dataclass(frozen=True)
class Source:
    """Where a vehicle's packets come from: the peer address and the stream (``None``: version 1)."""

    peer: Hashable | None
    stream_id: int | None

    def __str__(self) -> str:
        where = "an unnamed address" if self.peer is None else str(self.peer)
        if self.stream_id is None:
            return f"{where} (version 1, no stream)"
        return f"{where} (stream {self.stream_id})"


def stream_order(stream_id: int | None) -> int:
    """The rank of a stream: a larger one is newer; a version-1 packet (no stream) ranks below every stream."""
    return -1 if stream_id is None else stream_id


@dataclass(frozen=True)
class Conflict:
    """Two sources claiming one vehicle within :data:`CONFLICT_WINDOW_S`, and which one is kept."""

    vehicle_id: int
    kept: Source
    """The source whose packets are drawn: the newer stream. When both send one stream (or both are
    version 1) the one heard first; each packet is then still judged by its sequence number alone."""
    other: Source

    @property
    def same_stream(self) -> bool:
        """Both sources send the same stream (or are both version 1): packets are taken by sequence number."""
        return stream_order(self.kept.stream_id) == stream_order(self.other.stream_id)

    def __str__(self) -> str:
        head = (
            f"vehicle {self.vehicle_id} is claimed by two sources within {CONFLICT_WINDOW_S:g} s: "
            f"{self.kept} and {self.other}; "
        )
        if self.same_stream:
            return head + (
                "they send one stream, so each packet is taken only if its sequence number is newer and the "
                "vehicle may jump between them: give each receiver its own vehicle id"
            )
        return head + (
            f"drawing the newer stream ({self.kept}), refusing the older one's packets (counted as replayed): "
            "give each receiver its own vehicle id"
        )


class SourceLog:
    """The sources of one vehicle heard lately, and the conflicts among them already reported."""

    def __init__(self) -> None:
        self._heard: dict[Source, float] = {}
        self._reported: set[frozenset[Source]] = set()

    def heard(self, source: Source, now: float) -> Source | None:
        """Note a packet from ``source`` at ``now``; the other source it newly conflicts with, if any.

        A conflict: ``source`` was heard before (at ``before``), and another source was heard since, at a
        time ``t`` within :data:`CONFLICT_WINDOW_S` of ``before`` or of ``now``: the two packets of one
        source have one of the other between them, and close to one of them. Each pair is returned once.
        """
        before = self._heard.pop(source, None)
        for stale in [s for s, t in self._heard.items() if now - t > FORGET_SOURCE_S]:
            del self._heard[stale]
        rival = None
        if before is not None:
            for other, t in self._heard.items():
                pair = frozenset((source, other))
                near = t - before <= CONFLICT_WINDOW_S or now - t <= CONFLICT_WINDOW_S
                if t >= before and near and pair not in self._reported:
                    if len(self._reported) >= MAX_REPORTED:
                        self._reported.clear()
                    self._reported.add(pair)
                    rival = other
                    break
        self._heard[source] = now
        while len(self._heard) > MAX_SOURCES:
            del self._heard[next(iter(self._heard))]
        return rival


SEQ_MODULUS: Final = 1 << 32
MAX_WINDOW: Final = (1 << 31) - 1


def seq_newer(seq: int, last: int, window: int = MAX_WINDOW) -> bool:
    """Whether ``seq`` comes after ``last`` in uint32 serial-number arithmetic (RFC 1982 style).

    ``seq`` is newer if it is 1..``window`` steps ahead of ``last``, counting modulo 2**32, so 0 is newer
    than 2**32 - 1. Equal, behind, or further ahead than ``window`` is not newer.
    """
    return 1 <= (seq - last) % SEQ_MODULUS <= window


@dataclass
class VehicleState:
    """What the registry keeps of one vehicle: its current stream, its last sequence number, its sources."""

    last_seq: int
    last_accept_time: float | None
    stream: int = -1
    """:func:`stream_order` of the stream last accepted."""
    sources: SourceLog = field(default_factory=SourceLog)


_MAX_PENDING_CONFLICTS: Final = 64  # conflicts kept until take_conflicts(); older ones beyond this are dropped


class VehicleRegistry:
    """The listening side's per-vehicle state, behind :class:`ipt.protocol.PacketFilter` (sans-IO).

    :meth:`judge` says whether a well-formed, authenticated packet of a vehicle is newer than the last one
    accepted (a newer stream, or the same stream with a newer sequence number, or anything after
    ``resync_after_s`` of silence) and notes its source for conflicts. ``max_vehicles`` bounds the vehicles
    tracked: :meth:`take_slot` before a vehicle's first packet.
    """

    def __init__(self, window: int, resync_after_s: float | None, max_vehicles: int | None) -> None:
        self.window, self.resync_after_s, self.max_vehicles = window, resync_after_s, max_vehicles
        self.resyncs = 0
        self.new_streams = 0
        self._vehicles: dict[int, VehicleState] = {}
        self._no_slot_until = -math.inf  # while every slot is taken: no slot can free up before this time
        self._conflicts: list[Conflict] = []

    def judge(self, vehicle_id: int, stream_id: int | None, seq: int, now: float | None, peer: Hashable | None) -> bool:
        """Whether to accept this packet (then it becomes the baseline); with ``now``, conflicts are noted."""
        state = self._vehicles.get(vehicle_id)
        accepted = state is None or self._newer(state, stream_order(stream_id), seq, now)
        if state is None:
            state = self._vehicles[vehicle_id] = VehicleState(seq, now)
        if accepted:
            state.last_seq, state.last_accept_time, state.stream = seq, now, stream_order(stream_id)
        if now is not None:
            source = Source(peer, stream_id)
            rival = state.sources.heard(source, now)
            if rival is not None:
                # The newer stream is kept; for one stream from both, the one heard first is named first.
                newer_first = stream_order(rival.stream_id) > stream_order(stream_id)
                kept, other = (rival, source) if newer_first else (source, rival)
                self._conflicts.append(Conflict(vehicle_id, kept, other))
                del self._conflicts[:-_MAX_PENDING_CONFLICTS]
        return accepted

    def _newer(self, state: VehicleState, stream: int, seq: int, now: float | None) -> bool:
        if stream > state.stream:
            self.new_streams += 1
            return True
        if stream == state.stream and seq_newer(seq, state.last_seq, self.window):
            return True
        if self._silent_too_long(state, now):
            self.resyncs += 1
            return True
        return False

    def take_conflicts(self) -> list[Conflict]:
        """The conflicts found since the last call (each pair of sources of a vehicle once), oldest first."""
        conflicts, self._conflicts = self._conflicts, []
        return conflicts

    def knows(self, vehicle_id: int) -> bool:
        """Whether ``vehicle_id`` has a baseline (a slot)."""
        return vehicle_id in self._vehicles

    def tracked(self) -> int:
        """How many vehicles have a baseline (a slot, with ``max_vehicles``)."""
        return len(self._vehicles)

    def full(self) -> bool:
        """Whether every slot is taken (never, without ``max_vehicles``)."""
        return self.max_vehicles is not None and len(self._vehicles) >= self.max_vehicles

    def slot_may_free(self, now: float | None) -> bool:
        """Whether a slot is free, or a silent vehicle's could be given up at ``now``."""
        if not self.full():
            return True
        return self.resync_after_s is not None and now is not None and now >= self._no_slot_until

    def take_slot(self, now: float | None) -> bool:
        """Make room for a new vehicle if ``max_vehicles`` asks for it; whether there is room."""
        if not self.full():
            return True
        if not self.slot_may_free(now):
            return False
        assert self.resync_after_s is not None
        assert now is not None
        silent = [v for v, s in self._vehicles.items() if self._silent_too_long(s, now)]
        for v in silent:
            del self._vehicles[v]
        if not self.full():
            return True
        # Every slot is held by a vehicle heard within resync_after_s: none frees up before the one heard
        # longest ago falls silent for that long.
        heard = [s.last_accept_time for s in self._vehicles.values() if s.last_accept_time is not None]
        self._no_slot_until = (min(heard) if heard else now) + self.resync_after_s
        return False

    def forget(self, vehicle_id: int) -> None:
        """Drop the baseline of ``vehicle_id``: its next valid packet is accepted whatever its stream or number."""
        self._vehicles.pop(vehicle_id, None)

    def last_seq(self, vehicle_id: int) -> int | None:
        """The sequence number last accepted from ``vehicle_id``, or ``None`` if there is no baseline."""
        state = self._vehicles.get(vehicle_id)
        return None if state is None else state.last_seq

    def _silent_too_long(self, state: VehicleState, now: float | None) -> bool:
        if self.resync_after_s is None or now is None or state.last_accept_time is None:
            return False
        return now - state.last_accept_time > self.resync_after_s
