"""Streams in process: the receiver's packets carry a new stream per run, and the sender's listener names a
shared vehicle id once (a real loopback socket; the end-to-end runs are in test_restart.py)."""

from __future__ import annotations

import asyncio
import socket
import time

import numpy as np
import pytest
from waiting import until

from ipt.protocol import PACKET_SIZE_V2, PosePacket, decode_pose, encode_pose
from ipt.receiver.core.pose import PoseEstimate
from ipt.receiver.outputs.udp import PacketMaker, new_stream_id
from ipt.sender.server import _PoseListener, default_packet_filter


def _pose() -> PoseEstimate:
    return PoseEstimate(np.array([0.1, -0.2, 0.8]), np.diag([1.0, -1.0, -1.0]), (3, 4, 12), 0.42)


def test_each_run_takes_a_newer_stream_near_the_wall_clock() -> None:
    before = time.time_ns() // 1000
    ids = [new_stream_id() for _ in range(1000)]
    after = time.time_ns() // 1000
    assert ids == sorted(set(ids)), "strictly increasing, even within one microsecond"
    assert before <= ids[0]
    assert ids[-1] <= after + 1000


def test_the_packet_maker_sends_version_2_with_its_stream() -> None:
    maker = PacketMaker(5, b"k" * 16, stream_id=1_764_000_000_000_000)
    data = maker.encode(_pose(), 1234)
    assert (len(data), data[4]) == (PACKET_SIZE_V2 + 16, 2)
    packet = decode_pose(data, b"k" * 16)
    assert (packet.vehicle_id, packet.seq, packet.stream_id) == (5, 0, 1_764_000_000_000_000)
    assert PacketMaker(5).packet(_pose(), 1).stream_id is None  # without a stream: version 1, as before


def _packet(seq: int, stream: int) -> bytes:
    return encode_pose(PosePacket(5, seq, 1000 * seq, (0.1, 0.2, 1.0), (0.0, 1.0, 0.0, 0.0), stream_id=stream))


@pytest.mark.asyncio
async def test_the_listener_says_a_shared_vehicle_id_once_naming_both_sockets() -> None:
    lines: list[str] = []
    gate = default_packet_filter()
    listener = _PoseListener(gate, None, log=lines.append)
    loop = asyncio.get_running_loop()
    transport, _ = await loop.create_datagram_endpoint(lambda: listener, local_addr=("127.0.0.1", 0))
    port = transport.get_extra_info("sockname")[1]
    try:
        with (
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as a,
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b,
        ):
            a.bind(("127.0.0.1", 0))
            b.bind(("127.0.0.1", 0))
            for seq in range(20):
                a.sendto(_packet(seq, 1_000), ("127.0.0.1", port))
                b.sendto(_packet(seq, 2_000), ("127.0.0.1", port))
                await until(lambda n=2 * (seq + 1): sum(gate.counts.values()) >= n, 5.0)  # type: ignore[misc]
            a_port, b_port = a.getsockname()[1], b.getsockname()[1]
    finally:
        transport.close()
    assert len(lines) == 1, lines
    assert lines[0].startswith("ipt-sender: vehicle 5 is claimed by two sources within 1 s: ")
    assert f"127.0.0.1:{b_port} (stream 2000)" in lines[0]
    assert f"127.0.0.1:{a_port} (stream 1000)" in lines[0]
    assert f"drawing the newer stream (127.0.0.1:{b_port} (stream 2000))" in lines[0]
    assert gate.counts["accepted"] == 21  # a's first, then b's 20: the newer stream
    assert gate.counts["replayed"] == 19
