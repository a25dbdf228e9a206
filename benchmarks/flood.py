"""The projection holds under a flood of vehicle ids: 60 Hz while strangers send poses of made-up vehicles.

A real ``ipt-sender`` subprocess (null sink, paced at the projector rate, ``--width``×``--height``,
default 960×1080), listening on 127.0.0.1 as the shipped service listened before it authenticated: no
key, no list of vehicles, so every well-formed packet of any vehicle id could be drawn. Only its
defaults protect it: at most 16 vehicles tracked, 1000 datagrams a second from one source address.
``--sender-args`` adds flags (e.g. ``--source-rate-limit 0`` to see the vehicle limit alone).

Phases of ``--seconds`` each, in one sender process, every datagram a well-formed, unauthenticated pose
packet with a correct CRC (what an unprotected sender would draw):

- ``baseline``: no packets;
- ``ids300``: 300 vehicle ids, each at 30 Hz (9,000 datagrams a second);
- ``ids65536``: all 65,536 vehicle ids, each at 1 Hz (65,536 datagrams a second).

The datagrams go out evenly spread, in 1 ms batches, from one thread of this process, from ``--sources``
loopback addresses (127.0.0.1, 127.0.0.2, ...: an attacker with several addresses). For each phase:
frames shown, frames per second, missed deadlines and late frames (the sender's own counters,
differences of its statistics lines, so up to a second of quiet time either side is included), the
vehicles it drew, datagrams sent, counted by the sender (accepted, refused by reason) and dropped by the
kernel (``/proc/net/udp``). ``criteria`` checks the targets: >= 57 frames/s and <= 6 missed deadlines
in every flooded phase. Prints one JSON object; ``loadavg`` fields say how busy the machine was (the
machine is shared: timing figures are only as good as it is quiet).

    ./dev run python benchmarks/flood.py                        # 15 s phases, about 1.5 minutes
    ./dev run python benchmarks/flood.py --seconds 5 --phases ids300
    ./dev run python benchmarks/flood.py --sender-args="--source-rate-limit 0"
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import socket
import struct
import sys
import tempfile
import threading
import time
import zlib
from pathlib import Path
from typing import Any

import yaml
from load import _diff, _stats_lines, arena_for, parse_stats, process, udp_drops, wait_for  # benchmarks/ is on sys.path

from ipt.protocol import CRC_OFFSET, PosePacket, decode_pose, encode_pose

START_TIMEOUT_S = 120.0
VEHICLE_OFFSET, SEQ_OFFSET = 8, 12
"""Byte offsets of the vehicle id (uint16) and the sequence number (uint32) in a pose packet (docs/protocol.md)."""
PHASES = {"ids300": (300, 30.0), "ids65536": (65_536, 1.0)}
"""Phase name -> (distinct vehicle ids, datagrams a second per id)."""
TARGET_FPS, TARGET_MISSED = 57.0, 6


def _loadavg() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


class Flood:
    """``ids`` vehicle ids, each sending ``rate_hz`` unauthenticated poses a second, for ``seconds``."""

    def __init__(self, port: int, ids: int, rate_hz: float, seconds: float, sources: int) -> None:
        self.target = ("127.0.0.1", port)
        self.ids, self.rate_hz, self.seconds, self.sources = ids, rate_hz, seconds, sources
        template = bytearray(encode_pose(PosePacket(0, 0, 1, (0.1, 0.2, 1.0), (0.0, 1.0, 0.0, 0.0), num_tags=4)))
        self._packet = template
        # The layout is the documented one: a packet patched here decodes to the id and number put in.
        check = decode_pose(self._make(1234, 56789))
        assert (check.vehicle_id, check.seq) == (1234, 56789), "pose packet layout changed"
        self.sent = 0
        self.send_errors = 0
        self.behind_s = 0.0
        self.elapsed_s = 0.0

    def _make(self, vehicle: int, seq: int) -> bytes:
        p = self._packet
        struct.pack_into("<H", p, VEHICLE_OFFSET, vehicle)
        struct.pack_into("<I", p, SEQ_OFFSET, seq & 0xFFFF_FFFF)
        struct.pack_into("<I", p, CRC_OFFSET, zlib.crc32(memoryview(p)[:CRC_OFFSET]))
        return bytes(p)

    def run(self) -> None:
        socks = []
        for k in range(self.sources):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind((f"127.0.0.{1 + k}", 0))
            socks.append(s)
        total = round(self.ids * self.rate_hz * self.seconds)
        per_s = self.ids * self.rate_hz
        try:
            t0 = time.monotonic()
            n = 0
            while n < total:
                now = time.monotonic()
                due = min(total, int((now - t0) * per_s) + 1)  # everything due by now, in one batch
                if due <= n:
                    time.sleep(0.001)
                    continue
                self.behind_s = max(self.behind_s, now - t0 - n / per_s)
                for i in range(n, due):
                    vehicle, seq = i % self.ids, 1 + i // self.ids
                    try:
                        socks[i % self.sources].sendto(self._make(vehicle, seq), self.target)
                    except OSError:  # ENOBUFS on a saturated loopback: counted, not sent
                        self.send_errors += 1
                        continue
                    self.sent += 1
                n = due
            self.elapsed_s = time.monotonic() - t0
        finally:
            for s in socks:
                s.close()


_VEHICLES = r"vehicles=(\d+)"


def flood_run(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    arena = arena_for(args.width, args.height)
    arena_path = work / "arena.yaml"
    arena_path.write_text(yaml.safe_dump(arena), encoding="utf-8")
    log = work / "sender.log"
    extra = shlex.split(args.sender_args)
    cmd = [sys.executable, "-m", "ipt.sender.cli", "--config", str(arena_path), "--sink", "null", "--listen",
           "127.0.0.1:0", "--stats-every", "1", *extra]  # fmt: skip
    rate_hz = float(arena["projector"]["rate_hz"])
    phases: dict[str, Any] = {}
    with process(cmd, log) as proc:
        port = int(wait_for(log, r"listening for pose packets on udp 127\.0\.0\.1:(\d+)", proc, START_TIMEOUT_S)[1])
        wait_for(log, r"t=\S+s frames=", proc, START_TIMEOUT_S)  # running: content made, first frames out
        time.sleep(args.settle)
        for name in args.phases.split(","):
            before_line = _stats_lines(log)[-1]
            drops_before = udp_drops(proc.pid)
            t0 = time.monotonic()
            flood = None
            vehicles_seen = 0
            if name == "baseline":
                time.sleep(args.seconds)
            else:
                ids, per_id_hz = PHASES[name]
                flood = Flood(port, ids, per_id_hz, args.seconds, args.sources)
                thread = threading.Thread(target=flood.run, name="flood")
                thread.start()
                while thread.is_alive():  # the most vehicles any statistics line showed meanwhile
                    thread.join(0.5)
                    line = _stats_lines(log)[-1]
                    vehicles_seen = max(vehicles_seen, int(line.split("vehicles=", 1)[1].split()[0]))
            time.sleep(args.settle)  # the sender reads what is queued and prints a line
            n = len(_stats_lines(log))
            end = time.monotonic() + 10
            while len(_stats_lines(log)) == n and time.monotonic() < end:
                time.sleep(0.05)
            after_line = _stats_lines(log)[-1]
            result = _diff(parse_stats(after_line), parse_stats(before_line), time.monotonic() - t0, rate_hz)
            result["kernel_drops"] = udp_drops(proc.pid) - drops_before
            result["work_p99_ms_last_interval"] = parse_stats(after_line)["work_p99_ms"]
            if flood is not None:
                received = result["accepted"] + sum(result["rejected"].values())
                result.update(
                    vehicle_ids=flood.ids,
                    per_id_hz=flood.rate_hz,
                    sources=flood.sources,
                    datagrams_sent=flood.sent,
                    send_errors=flood.send_errors,
                    send_rate_per_s=round(flood.sent / flood.elapsed_s, 1) if flood.elapsed_s else None,
                    generator_max_behind_ms=round(flood.behind_s * 1e3, 1),
                    counted_by_sender=received,
                    not_counted=flood.sent - received,
                    most_vehicles_drawn=vehicles_seen,
                )
            result["loadavg"] = _loadavg()
            phases[name] = result
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=15)
    final = _stats_lines(log)[-1]
    flooded = {k: v for k, v in phases.items() if k != "baseline"}
    criteria = {
        f"{k}: >= {TARGET_FPS:g} frames/s and <= {TARGET_MISSED} missed deadlines": bool(
            v["frames_per_s"] is not None and v["frames_per_s"] >= TARGET_FPS and v["missed_deadlines"] <= TARGET_MISSED
        )
        for k, v in flooded.items()
    }
    return {
        "command": " ".join(cmd[1:]).replace(str(work), "<tmp>"),
        "resolution": f"{args.width}x{args.height}",
        "phases": phases,
        "criteria": criteria,
        "final_line": final.split("done: ", 1)[-1],
        "exit_code": rc,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=15.0, help="length of each phase (default 15, at most 120)")
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--settle", type=float, default=1.5, help="quiet seconds around each phase (default 1.5)")
    p.add_argument("--phases", default="baseline,ids300,ids65536", help="phases to run, in order")
    p.add_argument("--sources", type=int, default=1, help="loopback source addresses to flood from (default 1)")
    p.add_argument("--sender-args", default="", help="more ipt-sender flags, e.g. '--source-rate-limit 0'")
    args = p.parse_args(argv)
    if not 0 < args.seconds <= 120:
        p.error("--seconds must be in (0, 120]: the flood is bounded")
    if not 1 <= args.sources <= 254:
        p.error("--sources must be 1..254 (loopback addresses 127.0.0.1..254)")
    unknown = set(args.phases.split(",")) - {"baseline", *PHASES}
    if unknown:
        p.error(f"unknown phases {sorted(unknown)}; choose from baseline, {', '.join(PHASES)}")
    out: dict[str, Any] = {"benchmark": "flood", "cpu_count": os.cpu_count(), "loadavg_before": _loadavg()}
    with tempfile.TemporaryDirectory(prefix="ipt-flood-") as tmp:
        out["sender"] = flood_run(args, Path(tmp))
    out["loadavg_after"] = _loadavg()
    json.dump(out, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
