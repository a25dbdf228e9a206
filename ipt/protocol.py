"""The UDP pose packet: what the receiver daemon on the drone sends to the projector PC and to anyone else.

This module owns the wire format (layout, CRC, optional authentication tag, versioning) and a replay
guard for the listening side. It is sans-IO: no sockets, no clocks, no files. Bytes and values go in,
values come out; the daemons own the sockets and pass the time in where it is needed.

The normative description, with the byte table and a worked example, is ``docs/protocol.md``. In
short: a fixed-size little-endian packet (magic ``b"IPTL"``, version, message type, flags, the pose and
its uncertainty, then a CRC-32), optionally followed by a 16-byte truncated HMAC-SHA256 tag; the
``AUTHENTICATED`` flag says which of the two it is. Version 1 is :data:`PACKET_SIZE` bytes
(:data:`AUTH_PACKET_SIZE` with the tag); version 2 adds the sending run's *stream identity* (a uint64)
after the capture time, :data:`PACKET_SIZE_V2` bytes (:data:`AUTH_PACKET_SIZE_V2`). A packet with a
``stream_id`` is written as version 2, one without as version 1, and both are read.

Streams. A receiver daemon numbers its packets from 0 at every start; version 2 tells the runs apart:
each run sends a stream identity newer than the last run's (by convention its start time in µs since
the UNIX epoch), and :class:`PacketFilter` lets a newer stream of a vehicle supersede the older one at
once, while the sequence check (replays) is done within a stream. With a key the stream identity is
authenticated with the rest, so a packet recorded from an earlier run stays refused after a restart.

Frames (see :mod:`ipt.geometry`): the position is the camera optical centre in the arena frame (ENU
metres, origin at the tag-map centre, z up); the quaternion rotates camera vectors (OpenCV optical
axes: x right, y down, z forward) into the arena frame.

Public API: :class:`PosePacket`, :func:`encode_pose`, :func:`decode_pose`, :class:`PacketFilter`,
:func:`seq_newer`, :class:`MessageType`, :class:`QualityFlags`, :class:`Rejection`,
:class:`ProtocolError`, :class:`AuthKeyError`, the size and format constants (``*_V2`` for version 2),
:data:`SUPPORTED_VERSIONS`; the per-vehicle state and the conflicts of two sources live in
:mod:`ipt.streams` (:class:`~ipt.streams.Conflict` from :meth:`PacketFilter.take_conflicts`).
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import math
import numbers
import struct
import zlib
from collections import Counter
from collections.abc import Hashable, Iterable
from dataclasses import dataclass

from ipt.errors import IptError
from ipt.ratelimit import SourceRateLimit
from ipt.streams import MAX_WINDOW, Conflict, VehicleRegistry
from ipt.streams import seq_newer as seq_newer  # re-exported: part of this module's API

MAGIC = b"IPTL"
"""The first four bytes of every IPT packet, in every version ("IPT Localisation")."""

VERSION = 2
"""The newest protocol version: written for packets with a stream identity (version 1 otherwise)."""

SUPPORTED_VERSIONS: tuple[int, ...] = (1, 2)
"""The versions :func:`decode_pose` reads unless told otherwise."""

AUTH_TAG_SIZE = 16
"""Bytes of the authentication tag: HMAC-SHA256 truncated to its first 16 bytes."""

MIN_KEY_SIZE = 16
"""Shortest shared key accepted, in bytes (128 bits)."""

QUAT_NORM_TOLERANCE = 1e-3
"""A quaternion is accepted if its Euclidean norm is within this of 1. It is not normalised."""

# The header is the same in every version, so that any decoder can say which version it was sent.
_HEADER = struct.Struct("<4sBB")
# Version 1 pose body up to (not including) the CRC: flags, vehicle id, tags used, sequence number,
# capture time, position, quaternion, position std, attitude std, reprojection RMS.
_POSE_V1 = struct.Struct("<4sBBHHHIQ3d4d3f3ff")
# Version 2: the same, with the stream identity (uint64) after the capture time.
_POSE_V2 = struct.Struct("<4sBBHHHIQQ3d4d3f3ff")
_CRC = struct.Struct("<I")
_F32 = struct.Struct("<f")

CRC_OFFSET = _POSE_V1.size
"""Offset of the CRC-32 in a version-1 pose packet (108)."""

PACKET_SIZE = CRC_OFFSET + _CRC.size
"""Size in bytes of a version-1 pose packet without the authentication tag (112)."""

AUTH_PACKET_SIZE = PACKET_SIZE + AUTH_TAG_SIZE
"""Size in bytes of a version-1 pose packet with the authentication tag (128)."""

CRC_OFFSET_V2 = _POSE_V2.size
"""Offset of the CRC-32 in a version-2 pose packet (116)."""

PACKET_SIZE_V2 = CRC_OFFSET_V2 + _CRC.size
"""Size in bytes of a version-2 pose packet without the authentication tag (120)."""

AUTH_PACKET_SIZE_V2 = PACKET_SIZE_V2 + AUTH_TAG_SIZE
"""Size in bytes of a version-2 pose packet with the authentication tag (136)."""

_LAYOUTS = {1: _POSE_V1, 2: _POSE_V2}

_UINT16_MAX = 0xFFFF
_UINT32_MAX = 0xFFFF_FFFF
_UINT64_MAX = 0xFFFF_FFFF_FFFF_FFFF
_MAX_WINDOW = MAX_WINDOW

ACCEPTED = "accepted"
"""The key of :attr:`PacketFilter.counts` for packets that passed."""


class MessageType(enum.IntEnum):
    """Byte 5 of every packet: what follows the header."""

    POSE = 1
    """A camera pose with its uncertainty (:class:`PosePacket`)."""


class QualityFlags(enum.IntFlag):
    """The uint16 flags of a pose packet. Bits not defined here are reserved: sent as 0, rejected if set."""

    NONE = 0
    AUTHENTICATED = 1 << 0
    """On the wire: a 16-byte authentication tag follows the CRC. In a decoded packet: the tag was
    checked against the key. :func:`encode_pose` sets or clears it according to its ``key``."""
    SMOOTHED = 1 << 1
    """The pose is the output of a filter over several frames rather than a single-frame solution."""
    RESET = 1 << 2
    """The estimator restarted at this packet: do not difference it with earlier poses of this vehicle."""
    LOW_CONFIDENCE = 1 << 3
    """The estimator doubts this pose (few tags, large reprojection error, ...); use with care."""


_RESERVED_FLAG_BITS = _UINT16_MAX & ~int(
    QualityFlags.AUTHENTICATED | QualityFlags.SMOOTHED | QualityFlags.RESET | QualityFlags.LOW_CONFIDENCE
)


class Rejection(enum.StrEnum):
    """Why a packet was refused; :attr:`ProtocolError.reason` and the keys of :attr:`PacketFilter.counts`."""

    MALFORMED = "malformed"
    """Wrong length, wrong magic, reserved flag bits set, or a field value out of range or not finite."""
    UNSUPPORTED = "unsupported"
    """A version or message type this decoder does not speak (usually mismatched software)."""
    BAD_CRC = "bad_crc"
    """The CRC-32 does not match: the packet was damaged."""
    UNAUTHENTICATED = "unauthenticated"
    """A key is configured but the packet carries no authentication tag."""
    BAD_AUTH = "bad_auth"
    """The authentication tag does not match: wrong key or a tampered packet."""
    UNKNOWN_VEHICLE = "unknown_vehicle"
    """A well-formed packet from a vehicle id that :class:`PacketFilter` was not told to accept."""
    REPLAYED = "replayed"
    """A well-formed packet of an older stream than the vehicle's current one, or of the current stream
    with a sequence number not newer than the last one accepted."""
    VEHICLE_LIMIT = "vehicle_limit"
    """A vehicle not yet tracked while :class:`PacketFilter` tracks ``max_vehicles`` others that are not
    silent; when no slot can be free the packet is refused before it is decoded."""
    RATE_LIMITED = "rate_limited"
    """More datagrams from one source address than its rate limit allows; refused before decoding."""


class ProtocolError(IptError):
    """A packet (or a packet's values) violates the protocol. ``reason`` says which way, for counting."""

    def __init__(self, message: str, reason: Rejection = Rejection.MALFORMED) -> None:
        super().__init__(message)
        self.reason = reason


class AuthKeyError(IptError):
    """The shared authentication key is unusable (too short). A configuration problem, not a packet one."""


def _check_key(key: bytes | None) -> None:
    if key is not None and len(key) < MIN_KEY_SIZE:
        raise AuthKeyError(f"authentication key is {len(key)} bytes; at least {MIN_KEY_SIZE} are needed")


def _uint(name: str, value: object, maximum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ProtocolError(f"{name} must be an integer, got {value!r}")
    number = int(value)
    if not 0 <= number <= maximum:
        raise ProtocolError(f"{name} {number} is outside 0..{maximum}")
    return number


def _floats(name: str, value: object, count: int) -> tuple[float, ...]:
    if not isinstance(value, Iterable) or isinstance(value, str | bytes):
        raise ProtocolError(f"{name} must be a sequence of {count} numbers, got {value!r}")
    items = list(value)
    if len(items) != count:
        raise ProtocolError(f"{name} must have {count} values, got {len(items)}")
    return tuple(_finite(f"{name}[{i}]", item) for i, item in enumerate(items))


def _finite(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ProtocolError(f"{name} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ProtocolError(f"{name} is {number}; it must be finite")
    return number


def _float32_non_negative(name: str, value: float) -> float:
    """``value`` rounded to the nearest float32, so that a packet equals its decoded self."""
    if not value >= 0.0:
        raise ProtocolError(f"{name} is {value}; it must be >= 0")
    try:
        return float(_F32.unpack(_F32.pack(value))[0])
    except OverflowError:
        raise ProtocolError(f"{name} is {value}, too large for a float32") from None


@dataclass(frozen=True)
class PosePacket:
    """One pose of one vehicle, as carried by a POSE packet (version 2 with a ``stream_id``, else version 1).

    Construction validates every field and raises :class:`ProtocolError` (reason ``malformed``) on a bad
    value. Sequences of numbers (lists, numpy arrays) are stored as tuples of ``float``; the float32
    fields are rounded to float32 here, so ``decode_pose(encode_pose(p)) == p`` for every valid ``p``.
    The quaternion is checked (norm within :data:`QUAT_NORM_TOLERANCE` of 1) but not normalised: it is
    sent exactly as given.
    """

    vehicle_id: int
    """Which drone, 0..65535 (uint16)."""
    seq: int
    """Sequence number, 0..2**32-1 (uint32), +1 per packet of this vehicle, wrapping to 0."""
    capture_time_us: int
    """Microseconds on the drone's clock at image capture (uint64). The epoch is the drone's: the UNIX
    epoch when its clock is synchronised. Differences between packets of one vehicle are always valid."""
    position_m: tuple[float, float, float]
    """Camera optical centre in the arena frame: ENU metres, origin at the tag-map centre, z up (float64)."""
    quat_wxyz: tuple[float, float, float, float]
    """Unit quaternion (Hamilton, w first) rotating camera-frame vectors (OpenCV optical: x right, y down,
    z forward) into the arena frame (float64)."""
    position_std_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """1-sigma position uncertainty along arena x, y, z in metres (float32, >= 0)."""
    attitude_std_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """1-sigma attitude uncertainty in radians: roll, pitch, yaw about arena x, y, z (float32, >= 0)."""
    num_tags: int = 0
    """Number of tags the pose was solved from, 0..65535 (uint16)."""
    reprojection_rms_px: float = 0.0
    """RMS reprojection error of the tag corners in image pixels (float32, >= 0)."""
    flags: QualityFlags = QualityFlags.NONE
    """Quality flags; see :class:`QualityFlags`."""
    stream_id: int | None = None
    """The sending run's stream identity, 0..2**64-1 (uint64), version 2 only; ``None`` in a version-1
    packet. Each start of a receiver daemon takes one newer than its last (its start time in µs since the
    UNIX epoch); a newer stream of a vehicle supersedes an older one (:class:`PacketFilter`)."""

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "vehicle_id", _uint("vehicle_id", self.vehicle_id, _UINT16_MAX))
        set_(self, "seq", _uint("seq", self.seq, _UINT32_MAX))
        set_(self, "capture_time_us", _uint("capture_time_us", self.capture_time_us, _UINT64_MAX))
        set_(self, "num_tags", _uint("num_tags", self.num_tags, _UINT16_MAX))
        if self.stream_id is not None:
            set_(self, "stream_id", _uint("stream_id", self.stream_id, _UINT64_MAX))
        flags = _uint("flags", self.flags, _UINT16_MAX)
        if flags & _RESERVED_FLAG_BITS:
            raise ProtocolError(f"flags 0x{flags:04x} set reserved bits (mask 0x{_RESERVED_FLAG_BITS:04x})")
        set_(self, "flags", QualityFlags(flags))

        set_(self, "position_m", _floats("position_m", self.position_m, 3))
        quat = _floats("quat_wxyz", self.quat_wxyz, 4)
        norm = math.hypot(*quat)
        if norm == 0.0:
            raise ProtocolError("quat_wxyz is the zero quaternion")
        if abs(norm - 1.0) > QUAT_NORM_TOLERANCE:
            raise ProtocolError(
                f"quat_wxyz has norm {norm:.6g}; it must be within {QUAT_NORM_TOLERANCE} of 1"
            )
        set_(self, "quat_wxyz", quat)

        for name in ("position_std_m", "attitude_std_rad"):
            values = _floats(name, getattr(self, name), 3)
            set_(self, name, tuple(_float32_non_negative(f"{name}[{i}]", v) for i, v in enumerate(values)))
        rms = _finite("reprojection_rms_px", self.reprojection_rms_px)
        set_(self, "reprojection_rms_px", _float32_non_negative("reprojection_rms_px", rms))


def _auth_tag(key: bytes, signed: bytes) -> bytes:
    return hmac.new(key, signed, hashlib.sha256).digest()[:AUTH_TAG_SIZE]


def encode_pose(packet: PosePacket, key: bytes | None = None) -> bytes:
    """The wire bytes of ``packet``: version 2 if it has a ``stream_id`` (:data:`PACKET_SIZE_V2` bytes, or
    :data:`AUTH_PACKET_SIZE_V2` with a ``key``), else version 1 (:data:`PACKET_SIZE`, :data:`AUTH_PACKET_SIZE`).

    The ``AUTHENTICATED`` flag on the wire follows ``key`` (set with a key, cleared without), whatever
    ``packet.flags`` says. Raises :class:`AuthKeyError` for a key shorter than :data:`MIN_KEY_SIZE`.
    """
    _check_key(key)
    flags = int(packet.flags) & ~int(QualityFlags.AUTHENTICATED)
    if key is not None:
        flags |= int(QualityFlags.AUTHENTICATED)
    version = 1 if packet.stream_id is None else 2
    stream = () if packet.stream_id is None else (packet.stream_id,)
    body = _LAYOUTS[version].pack(
        MAGIC,
        version,
        MessageType.POSE,
        flags,
        packet.vehicle_id,
        packet.num_tags,
        packet.seq,
        packet.capture_time_us,
        *stream,
        *packet.position_m,
        *packet.quat_wxyz,
        *packet.position_std_m,
        *packet.attitude_std_rad,
        packet.reprojection_rms_px,
    )
    signed = body + _CRC.pack(zlib.crc32(body))
    return signed if key is None else signed + _auth_tag(key, signed)


def _speaks(versions: Iterable[int]) -> str:
    known = sorted(versions)
    if len(known) == 1:
        return f"version {known[0]}"
    return "versions " + ", ".join(str(v) for v in known[:-1]) + f" and {known[-1]}"


def _check_header(data: bytes, versions: Iterable[int]) -> int:
    """The version of ``data`` after checking its header and length; raises :class:`ProtocolError`."""
    size = len(data)
    if size < _HEADER.size:
        raise ProtocolError(f"packet too short: {size} bytes")
    magic, version, message_type = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if version not in versions or version not in _LAYOUTS:
        raise ProtocolError(
            f"version {version} not supported (this decoder speaks {_speaks(versions)})", Rejection.UNSUPPORTED
        )
    if message_type != MessageType.POSE:
        raise ProtocolError(f"message type {message_type} not supported", Rejection.UNSUPPORTED)
    plain = _LAYOUTS[version].size + _CRC.size
    if size not in (plain, plain + AUTH_TAG_SIZE):
        raise ProtocolError(
            f"bad length {size} bytes: a version-{version} pose packet is {plain} bytes, "
            f"or {plain + AUTH_TAG_SIZE} with an authentication tag"
        )
    return int(version)


def decode_pose(data: bytes, key: bytes | None = None, versions: Iterable[int] = SUPPORTED_VERSIONS) -> PosePacket:
    """The pose in ``data``; raises :class:`ProtocolError` and nothing else if ``data`` is not a valid packet.

    Checks, in this order: length of the header, magic, version (one of ``versions``: by default
    :data:`SUPPORTED_VERSIONS`; ``versions=(1,)`` is a version-1-only decoder), message type, total length
    for that version, CRC, flags, authentication tag, field values. With a ``key``, a packet without a tag
    is rejected (``unauthenticated``) and a tag that does not match is rejected (``bad_auth``); the
    returned packet has ``AUTHENTICATED`` set. Without a key, a tagged packet is accepted after its CRC
    check, its tag is not checked, and the returned packet has ``AUTHENTICATED`` *cleared*: in a decoded
    packet the flag means "verified", never merely "a tag was present". A version-1 packet decodes with
    ``stream_id`` ``None``.

    Raises :class:`AuthKeyError` (not a packet problem) for a key shorter than :data:`MIN_KEY_SIZE`.
    """
    _check_key(key)
    data = bytes(memoryview(data))
    version = _check_header(data, versions)
    layout = _LAYOUTS[version]
    crc_offset = layout.size
    signed_size = crc_offset + _CRC.size
    (crc,) = _CRC.unpack_from(data, crc_offset)
    if crc != zlib.crc32(data[:crc_offset]):
        raise ProtocolError("bad CRC", Rejection.BAD_CRC)

    fields = layout.unpack_from(data)
    flags = fields[3]
    if flags & _RESERVED_FLAG_BITS:
        raise ProtocolError(f"flags 0x{flags:04x} set reserved bits (mask 0x{_RESERVED_FLAG_BITS:04x})")
    tagged = bool(flags & QualityFlags.AUTHENTICATED)
    if tagged != (len(data) > signed_size):
        state = "set" if tagged else "clear"
        raise ProtocolError(f"AUTHENTICATED flag is {state} but the packet is {len(data)} bytes")
    if key is not None:
        if not tagged:
            raise ProtocolError("packet is not authenticated but a key is set", Rejection.UNAUTHENTICATED)
        if not hmac.compare_digest(data[signed_size:], _auth_tag(key, data[:signed_size])):
            raise ProtocolError(
                "authentication tag does not match (wrong key or tampered)", Rejection.BAD_AUTH
            )
    else:
        flags &= ~int(QualityFlags.AUTHENTICATED)

    vehicle_id, num_tags, seq, capture_time_us = fields[4:8]
    stream_id, pose = (None, fields[8:]) if version == 1 else (fields[8], fields[9:])
    return PosePacket(
        vehicle_id=vehicle_id,
        seq=seq,
        capture_time_us=capture_time_us,
        position_m=pose[0:3],
        quat_wxyz=pose[3:7],
        position_std_m=pose[7:10],
        attitude_std_rad=pose[10:13],
        num_tags=num_tags,
        reprojection_rms_px=pose[13],
        flags=QualityFlags(flags),
        stream_id=stream_id,
    )


_VEHICLE_OFFSET = 8  # magic (4), version, type, flags (2): the vehicle id follows, a little-endian uint16


def peek_vehicle_id(data: bytes) -> int | None:
    """The vehicle id a datagram claims, read without decoding it (``None`` if it is not an IPT packet).

    Nothing is checked but the magic and the length: use it only to refuse cheaply, never to accept.
    """
    if len(data) < _VEHICLE_OFFSET + 2 or data[:4] != MAGIC:
        return None
    return int.from_bytes(data[_VEHICLE_OFFSET : _VEHICLE_OFFSET + 2], "little")


class PacketFilter:
    """The listening side's gate: decode, authenticate, check the vehicle, and reject replays.

    Sans-IO: feed it datagrams with :meth:`accept`; it keeps per-vehicle stream and sequence state and
    counts outcomes. A packet is accepted if it decodes (with ``key``, when set: then unauthenticated
    packets are refused), its vehicle is allowed, and it is newer than the last one accepted from that
    vehicle: of a newer stream (version 2's ``stream_id``; a version-1 packet has none and ranks below
    every stream), or of the same stream with a newer sequence number (:func:`seq_newer` with ``window``).
    The first packet of a vehicle, and the first of each newer stream, sets the baseline. Packets of an
    older stream are refused as ``replayed``.

    So a version-2 daemon that restarts (a new, newer stream) is accepted at its first packet, and a
    packet recorded from its earlier run is refused; with a key the stream identity is authenticated.
    A version-1 daemon that restarts starts again from a low sequence number, which looks like a replay.
    Call :meth:`forget` for that vehicle, or set ``resync_after_s``: a vehicle that has had nothing
    accepted for longer than that is re-baselined by its next valid packet, whatever its stream (pass
    ``now`` to :meth:`accept`). The price: after that much silence an attacker could replay an old,
    validly authenticated packet once.

    Conflicts: with ``now`` given, two sources (address and stream) heard alternately for one vehicle
    within :data:`~ipt.streams.CONFLICT_WINDOW_S` are recorded once per pair (:meth:`take_conflicts`),
    see :mod:`ipt.streams`; nothing else changes: the newer stream is kept as always.

    Protection against floods, both counted like any other refusal:

    - ``max_vehicles``: at most this many vehicles are tracked. A new vehicle gets a slot only if one is
      free; a vehicle silent for longer than ``resync_after_s`` gives its slot up (its baseline is worth
      nothing any more). While every slot is taken and none can free up, a packet of another vehicle is
      refused (``vehicle_limit``), without a ``vehicle_ids`` list before it is even decoded, so a flood of
      made-up vehicle ids costs little.
      Without a key the first vehicles heard take the slots: authenticate, or list ``vehicle_ids``, to
      keep them for your own drones.
    - ``source_rate_hz``: datagrams from one source address (the ``source`` given to :meth:`accept`)
      beyond this rate (``source_burst`` at once) are refused (``rate_limited``) before anything else.

    Args:
        key: shared authentication key; when set, only correctly tagged packets are accepted.
        vehicle_ids: vehicle ids to accept; ``None`` accepts any.
        window: how far ahead of the last accepted sequence number a new one may be, 1..2**31-1.
        resync_after_s: silence after which a vehicle's sequence baseline is dropped; ``None`` (the
            default) never drops it.
        max_vehicles: most vehicles tracked at once; ``None`` (the default) is no limit.
        source_rate_hz: datagrams per second allowed from one source; ``None`` (the default) is no limit.
        source_burst: datagrams one source may send at once (default: one second's worth).
    """

    def __init__(
        self,
        key: bytes | None = None,
        vehicle_ids: Iterable[int] | None = None,
        window: int = _MAX_WINDOW,
        resync_after_s: float | None = None,
        *,
        max_vehicles: int | None = None,
        source_rate_hz: float | None = None,
        source_burst: float | None = None,
    ) -> None:
        _check_key(key)
        if not 1 <= window <= _MAX_WINDOW:
            raise ValueError(f"window {window} is outside 1..2**31-1")
        if resync_after_s is not None and not resync_after_s > 0.0:
            raise ValueError(f"resync_after_s {resync_after_s} must be > 0")
        if max_vehicles is not None and not 1 <= max_vehicles <= _UINT16_MAX + 1:
            raise ValueError(f"max_vehicles {max_vehicles} is outside 1..65536")
        self.key = key
        self.vehicle_ids = None if vehicle_ids is None else frozenset(vehicle_ids)
        self.window = window
        self.resync_after_s = resync_after_s
        self.max_vehicles = max_vehicles
        self.rate_limit = None if source_rate_hz is None else SourceRateLimit(source_rate_hz, source_burst)
        self.counts: Counter[str] = Counter({ACCEPTED: 0, **{reason.value: 0 for reason in Rejection}})
        """Outcomes so far: ``"accepted"`` and each :class:`Rejection` value, one increment per call."""
        self._registry = VehicleRegistry(window, resync_after_s, max_vehicles)

    def accept(
        self, data: bytes, now: float | None = None, source: Hashable | None = None, peer: Hashable | None = None
    ) -> PosePacket | None:
        """The packet in ``data`` if it passes every check, else ``None`` (the reason is counted).

        ``now`` is the caller's clock in seconds (any monotonic clock); it is required when
        ``resync_after_s``, ``max_vehicles`` or ``source_rate_hz`` is set, and conflicts are only looked for
        with it. ``source`` is where the datagram came from (e.g. the sender's IP address), for the rate
        limit; ``peer`` names it in conflicts (e.g. ``"HOST:PORT"``; default ``source``).
        """
        if now is None and (self.resync_after_s is not None or self.rate_limit is not None):
            raise ValueError("accept() needs `now` when resync_after_s or source_rate_hz is set")
        if self.rate_limit is not None and source is not None and not self.rate_limit.allow(source, now or 0.0):
            self.counts[Rejection.RATE_LIMITED.value] += 1
            return None
        registry = self._registry
        if self.vehicle_ids is None and registry.full():
            # (With a list of vehicles, a stranger is refused as unknown_vehicle after decoding instead, so
            # that a forged packet is always counted as unauthenticated or bad_auth.)
            claimed = peek_vehicle_id(data)
            if claimed is not None and not registry.knows(claimed) and not registry.slot_may_free(now):
                self.counts[Rejection.VEHICLE_LIMIT.value] += 1
                return None
        try:
            packet = decode_pose(data, self.key)
        except ProtocolError as error:
            self.counts[error.reason.value] += 1
            return None
        if self.vehicle_ids is not None and packet.vehicle_id not in self.vehicle_ids:
            self.counts[Rejection.UNKNOWN_VEHICLE.value] += 1
            return None
        if not registry.knows(packet.vehicle_id) and not registry.take_slot(now):
            self.counts[Rejection.VEHICLE_LIMIT.value] += 1
            return None
        if not registry.judge(packet.vehicle_id, packet.stream_id, packet.seq, now, source if peer is None else peer):
            self.counts[Rejection.REPLAYED.value] += 1
            return None
        self.counts[ACCEPTED] += 1
        return packet

    @property
    def resyncs(self) -> int:
        """Packets accepted by re-baselining after ``resync_after_s`` (also counted as accepted)."""
        return self._registry.resyncs

    @property
    def new_streams(self) -> int:
        """Packets accepted because they start a newer stream of a vehicle already heard (also accepted)."""
        return self._registry.new_streams

    def take_conflicts(self) -> list[Conflict]:
        """The conflicts found since the last call (each pair of sources of a vehicle once), oldest first."""
        return self._registry.take_conflicts()

    def tracked(self) -> int:
        """How many vehicles have a sequence baseline (a slot, with ``max_vehicles``)."""
        return self._registry.tracked()

    def forget(self, vehicle_id: int) -> None:
        """Drop the baseline of ``vehicle_id``: its next valid packet is accepted whatever its stream or number."""
        self._registry.forget(vehicle_id)

    def last_seq(self, vehicle_id: int) -> int | None:
        """The sequence number last accepted from ``vehicle_id``, or ``None`` if there is no baseline."""
        return self._registry.last_seq(vehicle_id)
