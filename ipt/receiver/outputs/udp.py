"""Where the receiver daemon's poses go: UDP pose packets to every configured target.

One connected datagram endpoint per target, so that the kernel reports an unreachable target (ICMP
port unreachable comes back as ``ECONNREFUSED`` through ``error_received``). Send problems are counted,
never fatal: a listener that is not up yet, or goes away, must not stop the drone's localisation.

Each run of the daemon is one stream (``docs/protocol.md``): :func:`new_stream_id` at its start, sent in
every version-2 packet, so that a listener takes a restarted daemon at its first packet and still refuses
the packets of an earlier run.
"""

from __future__ import annotations

import asyncio
import functools
import time
from collections import Counter
from collections.abc import Sequence

from ipt.errors import IptError
from ipt.protocol import PosePacket, encode_pose
from ipt.receiver.core.pose import PoseEstimate

SEQ_MODULUS = 1 << 32
MAX_BUFFERED_BYTES = 64 * 1024
"""A target whose transport holds more unsent bytes than this gets no more packets until it drains."""
CLOSE_TIMEOUT_S = 0.2


class OutputError(IptError):
    """A pose output cannot be set up (e.g. a send target's host name does not resolve)."""


_last_stream_id = 0


def new_stream_id() -> int:
    """A stream identity for a run starting now: the wall clock in µs since the UNIX epoch, and larger than
    any given before in this process. Newer than an earlier run's as long as the clock has not gone back."""
    global _last_stream_id
    _last_stream_id = max(time.time_ns() // 1000, _last_stream_id + 1)
    return _last_stream_id


class PacketMaker:
    """Turns poses into encoded pose packets of one vehicle, numbering them 0, 1, ... (wrapping at 2**32).

    With a ``stream_id`` (the daemon passes :func:`new_stream_id`) the packets are version 2 and carry it;
    without, version 1 (what receivers before version 2 sent).
    """

    def __init__(
        self, vehicle_id: int, key: bytes | None = None, first_seq: int = 0, stream_id: int | None = None
    ) -> None:
        self.vehicle_id, self.key, self.stream_id = vehicle_id, key, stream_id
        self.seq = first_seq % SEQ_MODULUS
        """The sequence number of the next packet."""

    def packet(self, pose: PoseEstimate, capture_time_us: int) -> PosePacket:
        """The packet for ``pose`` (takes the next sequence number)."""
        p, q = pose.position_m, pose.quat_wxyz
        packet = PosePacket(
            vehicle_id=self.vehicle_id,
            seq=self.seq,
            capture_time_us=capture_time_us,
            position_m=(float(p[0]), float(p[1]), float(p[2])),
            quat_wxyz=(float(q[0]), float(q[1]), float(q[2]), float(q[3])),
            num_tags=len(pose.tag_ids),
            reprojection_rms_px=pose.reprojection_rms_px,
            stream_id=self.stream_id,
        )
        self.seq = (self.seq + 1) % SEQ_MODULUS
        return packet

    def encode(self, pose: PoseEstimate, capture_time_us: int) -> bytes:
        """The wire bytes for ``pose`` (authenticated when a key is set)."""
        return encode_pose(self.packet(pose, capture_time_us), self.key)


def _buffered(transport: asyncio.BaseTransport) -> int:
    """Bytes waiting in ``transport`` (asyncio's and uvloop's datagram transports both tell)."""
    size = getattr(transport, "get_write_buffer_size", None)
    return int(size()) if callable(size) else 0


class _TargetProtocol(asyncio.DatagramProtocol):
    def __init__(self, sender: UdpPoseSender, target: str) -> None:
        self.sender, self.target = sender, target
        self.closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        pass  # the receiver sends only

    def error_received(self, exc: Exception) -> None:
        self.sender._count_error(self.target, exc)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)


class UdpPoseSender:
    """Sends each datagram to every ``(host, port)`` target; use ``async with`` or :meth:`open`/:meth:`close`.

    Counts: :attr:`sent` (datagrams handed to the kernel), :attr:`errors` (failed or refused sends, all
    targets) and :attr:`errors_by_target`; :attr:`last_error` is the text of the latest one.
    """

    def __init__(self, targets: Sequence[tuple[str, int]]) -> None:
        self.targets = list(targets)
        self.sent = 0
        self.errors = 0
        self.errors_by_target: Counter[str] = Counter()
        self.last_error: str | None = None
        self._endpoints: list[tuple[str, asyncio.DatagramTransport, _TargetProtocol]] = []

    @staticmethod
    def _name(host: str, port: int) -> str:
        return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"

    async def open(self) -> None:
        """Create one connected UDP endpoint per target."""
        loop = asyncio.get_running_loop()
        try:
            for host, port in self.targets:
                name = self._name(host, port)
                try:
                    transport, protocol = await loop.create_datagram_endpoint(
                        functools.partial(_TargetProtocol, self, name),
                        remote_addr=(host, port),
                    )
                except OSError as exc:
                    raise OutputError(f"send target {name}: {exc.strerror or exc}") from None
                self._endpoints.append((name, transport, protocol))
        except BaseException:
            await self.close()
            raise

    def send(self, data: bytes) -> int:
        """Send ``data`` to every target; how many took it (the rest are counted as errors)."""
        ok = 0
        for name, transport, _ in self._endpoints:
            if transport.is_closing():
                self._count_error(name, ConnectionError("the endpoint is closed"))
                continue
            if _buffered(transport) > MAX_BUFFERED_BYTES:
                self._count_error(name, BlockingIOError("the send buffer is full"))
                continue
            try:
                transport.sendto(data)
            except OSError as exc:  # asyncio reports through error_received, but be safe
                self._count_error(name, exc)
                continue
            ok += 1
        self.sent += ok
        return ok

    def _count_error(self, target: str, exc: BaseException) -> None:
        self.errors += 1
        self.errors_by_target[target] += 1
        self.last_error = f"{target}: {exc}"

    async def close(self) -> None:
        """Close every endpoint (waits briefly for the sockets to be released)."""
        endpoints, self._endpoints = self._endpoints, []
        for _, transport, _ in endpoints:
            transport.close()
        waits = [protocol.closed for _, _, protocol in endpoints]
        if waits:
            await asyncio.wait(waits, timeout=CLOSE_TIMEOUT_S)

    async def __aenter__(self) -> UdpPoseSender:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
