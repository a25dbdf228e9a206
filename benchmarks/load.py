"""Load held: the sender keeps its frame deadlines under a full arena's packets and a flood of junk; the
receiver keeps its capture→send latency bounded with a CPU hog on every core.

**Sender.** A real ``ipt-sender`` subprocess (null sink, paced at the projector rate, listening on
127.0.0.1) at ``--width``×``--height`` (default 960×1080, where it meets its deadlines on a quiet
2-core machine), with ``--auth-key-file`` and ``--vehicles 1..16`` (the recommended deployment: every
datagram costs an HMAC) and ``--source-rate-limit 0``: all the traffic comes from 127.0.0.1 here, and
this benchmark measures what the filter does with every datagram (``benchmarks/flood.py`` measures the
limits). Three phases of ``--seconds`` each, in one process:

- ``baseline``: no packets;
- ``spread``: ``--vehicles`` vehicles each sending ``--rate`` authenticated poses per second, plus
  ``--invalid`` invalid datagrams spread evenly over the phase;
- ``burst``: the same vehicles, plus the ``--invalid`` datagrams sent as fast as one thread can.

The invalid datagrams are a mix: random bytes, truncated or padded packets, bad CRC, wrong version,
unauthenticated (no tag), forged (right CRC, wrong tag), replays of packets already accepted, and
well-formed packets of a vehicle that is not allowed. For each phase: frames shown and the frame rate,
missed deadlines and late frames (the sender's own counters, see ``ipt/sender/server.py``), packets
sent, accepted and rejected by reason, and datagrams the kernel dropped before the sender read them
(``/proc/net/udp``). Counts per phase are differences of the sender's periodic statistics lines, so
they include up to a second of quiet time on either side.

**Receiver.** ``ipt-receiver run`` on a recording paced to 120 FPS (``--realtime``, a live source: the
newest frame wins and drops are counted), sending to a UDP socket here, for ``--seconds``: once on a
quiet machine, once with ``--hogs`` processes (default: one per core) spinning at the same priority.
The recording is a simulated flight (``--video DIR`` from ``ipt sim``, or 0.5 s rendered on the spot)
repeated to the length needed. Reported from the daemon's final statistics line: frames captured and
processed, drops, poses, latency p50/p99 (capture to send, queueing included); and packets received.

Prints one JSON object; ``loadavg`` fields say how busy the machine was (the figures are only as quiet
as the machine).

    ./dev run python benchmarks/load.py                       # both parts, 15 s phases
    ./dev run python benchmarks/load.py --part sender --seconds 30
    ./dev run python benchmarks/load.py --part receiver --video results/flight
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml

from ipt.config.models import MIN_TAG_SIZE_PX, ArenaConfig, load_arena_config, shipped_config_path
from ipt.protocol import CRC_OFFSET, PosePacket, encode_pose

KEY = b"ipt-load-benchmark-key-0123456789"
FIRST_SEQ = 1000
"""Sequence number the vehicles start from; the replayed junk uses 1..50, always behind it."""
START_TIMEOUT_S = 120.0


def _loadavg() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def arena_for(width: int, height: int) -> dict[str, Any]:
    """The shipped arena at another projector size, tags scaled by the same factor (as benchmarks/sender.py)."""
    data: dict[str, Any] = load_arena_config(shipped_config_path("arena.yaml")).model_dump(mode="json")
    scale = min(width / data["projector"]["width_px"], height / data["projector"]["height_px"])
    data["projector"].update(width_px=width, height_px=height)
    tm = data["tag_map"]
    tm["tag_size_px"] = max(MIN_TAG_SIZE_PX, int(tm["tag_size_px"] * scale) // 8 * 8)
    # Tags keep 8 projector px per bit: on a small projector fewer of them fit, and a pad's small tags none.
    quiet_size = tm["tag_size_px"] * 10 // 8
    tm.update(cols=min(tm["cols"], width // quiet_size), rows=min(tm["rows"], height // quiet_size))
    if scale < 1:
        tm["pads"] = []
    ArenaConfig.model_validate(data)
    return data


# --- processes ------------------------------------------------------------------------------------------


@contextmanager
def process(cmd: list[str], log: Path) -> Iterator[subprocess.Popen[bytes]]:
    """``cmd`` running with stderr to ``log``; SIGTERM (then SIGKILL) on the way out."""
    with log.open("wb") as err:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def wait_for(log: Path, pattern: str, proc: subprocess.Popen[bytes], timeout_s: float) -> re.Match[str]:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if m := re.search(pattern, log.read_text(encoding="utf-8", errors="replace")):
            return m
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    raise RuntimeError(f"{pattern!r} not seen in {log}:\n{log.read_text(errors='replace')[-3000:]}")


def udp_drops(pid: int) -> int:
    """Datagrams the kernel dropped on the UDP sockets of ``pid`` (receive buffer full)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            if m := re.fullmatch(r"socket:\[(\d+)\]", os.readlink(fd)):
                inodes.add(m.group(1))
        except OSError:
            continue
    drops = 0
    for table in ("udp", "udp6"):
        for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            f = line.split()
            if f[9] in inodes:
                drops += int(f[-1])
    return drops


# --- the sender under packets ---------------------------------------------------------------------------


def _pose(vehicle: int, seq: int, t: float) -> PosePacket:
    angle = 0.5 * t + vehicle
    return PosePacket(
        vehicle_id=vehicle,
        seq=seq,
        capture_time_us=int(t * 1e6),
        position_m=(0.6 * math.cos(angle), 0.6 * math.sin(angle), 1.0),
        quat_wxyz=(0.0, 1.0, 0.0, 0.0),
        num_tags=6,
    )


def invalid_pool(rng: random.Random, vehicles: int, size: int = 600) -> tuple[list[bytes], list[str]]:
    """``size`` invalid datagrams of assorted kinds (and the kind of each)."""
    kinds = ["random", "truncated", "padded", "bad_crc", "version", "unauthenticated", "forged", "replayed",
             "unknown_vehicle"]  # fmt: skip
    pool, labels = [], []
    for i in range(size):
        kind = kinds[i % len(kinds)]
        valid = encode_pose(_pose(1 + i % vehicles, 1 + i % 50, 0.0), KEY)
        if kind == "random":
            data = bytes(rng.randrange(256) for _ in range(rng.randrange(200)))
        elif kind == "truncated":
            data = valid[: rng.randrange(len(valid))]
        elif kind == "padded":
            data = valid + bytes(rng.randrange(1, 64))
        elif kind == "bad_crc":
            buf = bytearray(valid)
            buf[rng.randrange(8, CRC_OFFSET)] ^= 0xFF
            data = bytes(buf)
        elif kind == "version":
            buf = bytearray(valid[:CRC_OFFSET])
            buf[4] = rng.randrange(2, 256)
            data = bytes(buf) + struct.pack("<I", zlib.crc32(bytes(buf))) + valid[CRC_OFFSET + 4 :]
        elif kind == "unauthenticated":
            data = encode_pose(_pose(1 + i % vehicles, 10**6 + i, 0.0))
        elif kind == "forged":
            data = encode_pose(_pose(1 + i % vehicles, 10**6 + i, 0.0), b"not-the-key-" + bytes(16))
        elif kind == "replayed":  # sequence numbers far behind those the vehicles are sending
            data = valid
        else:
            data = encode_pose(_pose(1000 + i, 1, 0.0), KEY)
        pool.append(data)
        labels.append(kind)
    return pool, labels


class Traffic:
    """Valid poses of ``vehicles`` at ``rate`` Hz on one thread; ``invalid`` junk datagrams on another."""

    def __init__(self, port: int, vehicles: int, rate: float, invalid: int, seconds: float, burst: bool) -> None:
        self.target = ("127.0.0.1", port)
        self.vehicles, self.rate, self.invalid, self.seconds, self.burst = vehicles, rate, invalid, seconds, burst
        self.pool, self.labels = invalid_pool(random.Random(1), vehicles)
        self.valid_sent = 0
        self.invalid_sent: Counter[str] = Counter()
        self.behind_s = 0.0
        self.flood_s = 0.0

    def run(self, seq0: int) -> int:
        """Send for ``seconds``; returns the next sequence number to use."""
        flood = threading.Thread(target=self._flood, name="flood")
        flood.start()
        seq = self._vehicles(seq0)
        flood.join()
        return seq

    def _vehicles(self, seq: int) -> int:
        ticks = round(self.seconds * self.rate)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            t0 = time.monotonic()
            for k in range(ticks):
                due = t0 + k / self.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                else:
                    self.behind_s = max(self.behind_s, -delay)
                t = time.monotonic() - t0
                seq += 1
                for v in range(1, self.vehicles + 1):
                    sock.sendto(encode_pose(_pose(v, seq, t), KEY), self.target)
                    self.valid_sent += 1
        return seq

    def _flood(self) -> None:
        time.sleep(0.1)  # the vehicles speak first: a replay must never find a vehicle without a baseline
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            t0 = time.monotonic()
            for i in range(self.invalid):
                if not self.burst:
                    delay = t0 + i * self.seconds / self.invalid - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                j = i % len(self.pool)
                try:
                    sock.sendto(self.pool[j], self.target)
                except OSError:  # ENOBUFS on a saturated loopback: counted as not sent
                    continue
                self.invalid_sent[self.labels[j]] += 1
            self.flood_s = time.monotonic() - t0


_LINE = re.compile(r"frames=(\d+) fps=\S+ work_p50=(\S+)ms work_p99=(\S+)ms missed=(\d+) late=(\d+)")


def parse_stats(line: str) -> dict[str, Any]:
    """The counters of one sender statistics line (periodic or final)."""
    m = _LINE.search(line)
    if m is None:
        raise RuntimeError(f"not a statistics line: {line!r}")
    packets = dict(re.findall(r"\b([a-z_]+)=(\d+)", line.split(" packets ", 1)[1]))
    return {
        "frames": int(m[1]),
        "work_p99_ms": float(m[3]),
        "missed": int(m[4]),
        "late": int(m[5]),
        "packets": {k: int(v) for k, v in packets.items() if k != "rejected"},
    }


def _stats_lines(log: Path) -> list[str]:
    return [ln for ln in log.read_text(encoding="utf-8", errors="replace").splitlines() if _LINE.search(ln)]


def _diff(after: dict[str, Any], before: dict[str, Any], seconds: float, rate_hz: float) -> dict[str, Any]:
    packets = Counter(after["packets"])
    packets.subtract(before["packets"])
    accepted = packets.pop("accepted", 0)
    frames = after["frames"] - before["frames"]
    return {
        "seconds": round(seconds, 2),
        "frames": frames,
        "frames_per_s": round(frames / seconds, 2) if seconds > 0 else None,
        "rate_hz": rate_hz,
        "missed_deadlines": after["missed"] - before["missed"],
        "late_frames": after["late"] - before["late"],
        "accepted": accepted,
        "rejected": {k: v for k, v in sorted(packets.items()) if v},
    }


def sender_load(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    arena = arena_for(args.width, args.height)
    arena_path = work / "arena.yaml"
    arena_path.write_text(yaml.safe_dump(arena), encoding="utf-8")
    key_file = work / "key"
    key_file.write_bytes(KEY)
    key_file.chmod(0o600)  # a key file others can read is refused
    log = work / "sender.log"
    vehicles = [str(v) for v in range(1, args.vehicles + 1)]
    cmd = [sys.executable, "-m", "ipt.sender.cli", "--config", str(arena_path), "--sink", "null", "--listen",
           "127.0.0.1:0", "--stats-every", "1", "--auth-key-file", str(key_file), "--vehicles", *vehicles,
           "--source-rate-limit", "0"]  # fmt: skip
    rate_hz = float(arena["projector"]["rate_hz"])
    phases: dict[str, Any] = {}
    with process(cmd, log) as proc:
        port = int(wait_for(log, r"listening for pose packets on udp 127\.0\.0\.1:(\d+)", proc, START_TIMEOUT_S)[1])
        wait_for(log, r"t=\S+s frames=", proc, START_TIMEOUT_S)  # running: content made, first frames out
        seq = FIRST_SEQ
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:  # every vehicle gets its baseline
            for v in range(1, args.vehicles + 1):
                sock.sendto(encode_pose(_pose(v, seq, 0.0), KEY), ("127.0.0.1", port))
        wait_for(log, rf"t=\S+s frames=.* accepted={args.vehicles} ", proc, 30)  # counted before phase one
        time.sleep(args.settle)
        for name in args.phases.split(","):
            before_line = _stats_lines(log)[-1]
            drops_before = udp_drops(proc.pid)
            t0 = time.monotonic()
            traffic = None
            if name == "baseline":
                time.sleep(args.seconds)
            else:
                traffic = Traffic(port, args.vehicles, args.rate, args.invalid, args.seconds, burst=name == "burst")
                seq = traffic.run(seq)
            time.sleep(args.settle)  # the sender reads what is queued and prints a line
            n = len(_stats_lines(log))
            end = time.monotonic() + 10
            while len(_stats_lines(log)) == n and time.monotonic() < end:
                time.sleep(0.05)
            after_line = _stats_lines(log)[-1]
            result = _diff(parse_stats(after_line), parse_stats(before_line), time.monotonic() - t0, rate_hz)
            result["kernel_drops"] = udp_drops(proc.pid) - drops_before
            result["work_p99_ms_last_interval"] = parse_stats(after_line)["work_p99_ms"]
            if traffic is not None:
                sent_invalid = sum(traffic.invalid_sent.values())
                received = result["accepted"] + sum(result["rejected"].values())
                result.update(
                    valid_sent=traffic.valid_sent,
                    invalid_sent=sent_invalid,
                    invalid_sent_by_kind=dict(sorted(traffic.invalid_sent.items())),
                    invalid_send_seconds=round(traffic.flood_s, 3),
                    received=received,
                    not_counted=traffic.valid_sent + sent_invalid - received,
                    generator_max_behind_ms=round(traffic.behind_s * 1e3, 1),
                )
            result["loadavg"] = _loadavg()
            phases[name] = result
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=15)
    final = _stats_lines(log)[-1]
    return {
        "command": " ".join(cmd[1:]).replace(str(work), "<tmp>"),
        "resolution": f"{args.width}x{args.height}",
        "vehicles": args.vehicles,
        "pose_rate_hz": args.rate,
        "invalid_per_phase": args.invalid,
        "phases": phases,
        "final_line": final.split("done: ", 1)[-1],
        "exit_code": rc,
    }


# --- the receiver with CPU hogs -------------------------------------------------------------------------


def looped_video(args: argparse.Namespace, work: Path) -> tuple[Path, Path]:
    """A recording of at least ``seconds`` + 2 s at 120 FPS: a short simulated flight repeated."""
    from ipt.sender.content import GeneratedScene
    from ipt.sim.config import SimConfig
    from ipt.sim.run import CAMERA_NAME, VIDEO_NAME, simulate_to_folder
    from ipt.videoio import FfvWriter, open_frames

    flight = Path(args.video) if args.video else work / "flight"
    if not args.video:
        arena = load_arena_config(shipped_config_path("arena.yaml"))
        scene = GeneratedScene(arena.projector.width_px, arena.projector.height_px, seed=0)
        simulate_to_folder(arena, SimConfig(), scene, flight, 0.5, progress=None)
    with open_frames(flight / VIDEO_NAME) as source:
        fps = source.fps or 120.0
        frames = list(source)
    frames = frames[: len(frames) // 4 * 4]  # whole phase cycles (120 FPS camera, 60 Hz projector)
    needed = math.ceil((args.seconds + 2) * fps)
    looped = work / "looped.mkv"
    h, w = frames[0].shape[:2]
    with FfvWriter(looped, w, h, fps) as writer:
        for k in range(needed):
            writer.write(frames[k % len(frames)])
    return looped, flight / CAMERA_NAME


_FINAL = re.compile(
    r"final: (\d+) frames \((\d+) captured\), (\d+) poses, (\d+) packets in (\S+) s: .*latency p50 (\S+)(?: ms)? "
    r"p99 (\S+)(?: ms)?, drops (\d+), send errors (\d+)"
)


def receiver_run(video: Path, camera: Path, seconds: float, hogs: int, work: Path) -> dict[str, Any]:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sink:
        sink.bind(("127.0.0.1", 0))
        sink.settimeout(0.2)
        port = sink.getsockname()[1]
        received = 0
        stop = threading.Event()

        def collect() -> None:
            nonlocal received
            while not stop.is_set():
                try:
                    sink.recv(2048)
                    received += 1
                except TimeoutError:
                    continue

        collector = threading.Thread(target=collect)
        collector.start()
        hog_cmd = [sys.executable, "-c", f"import time\nend = time.monotonic() + {seconds + 60}\n"
                   "while time.monotonic() < end:\n    pass\n"]  # fmt: skip
        spinners = [subprocess.Popen(hog_cmd) for _ in range(hogs)]
        log = work / f"receiver-{hogs}.log"
        cmd = [sys.executable, "-m", "ipt.receiver.cli", "run", "--source", f"video:{video}", "--camera", str(camera),
               "--realtime", "--fps", "120", "--max-frames", str(round(seconds * 120)), "--send",
               f"127.0.0.1:{port}"]  # fmt: skip
        t0 = time.monotonic()
        try:
            with process(cmd, log) as proc:
                rc = proc.wait(timeout=seconds + START_TIMEOUT_S)
        finally:
            for s in spinners:
                s.kill()
                s.wait()
            time.sleep(0.3)
            stop.set()
            collector.join()
        wall = time.monotonic() - t0
    text = log.read_text(encoding="utf-8", errors="replace")
    m = _FINAL.search(text)
    if m is None:
        raise RuntimeError(f"no final statistics line in {log}:\n{text[-3000:]}")

    def ms(v: str) -> float | None:
        return None if v == "-" else float(v)

    return {
        "hogs": hogs,
        "command": " ".join(cmd[1:]).replace(str(work), "<tmp>"),
        "exit_code": rc,
        "wall_seconds": round(wall, 1),
        "frames_captured": int(m[2]),
        "frames_processed": int(m[1]),
        "drops": int(m[2]) - int(m[1]),
        "drops_reported": int(m[8]),
        "poses": int(m[3]),
        "packets_sent": int(m[4]),
        "packets_received": received,
        "send_errors": int(m[9]),
        "latency_p50_ms": ms(m[6]),
        "latency_p99_ms": ms(m[7]),
        "processed_per_s": round(int(m[1]) / float(m[5]), 1),
        "final_line": m[0],
        "loadavg_after": _loadavg(),
    }


def receiver_load(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    video, camera = looped_video(args, work)
    hogs = args.hogs if args.hogs is not None else (os.cpu_count() or 1)
    return {
        "source": "a simulated flight repeated, paced to 120 FPS (--realtime: live, newest frame wins)",
        "quiet": receiver_run(video, camera, args.seconds, 0, work),
        "with_hogs": receiver_run(video, camera, args.seconds, hogs, work),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--part", choices=("sender", "receiver", "all"), default="all")
    p.add_argument("--seconds", type=float, default=15.0, help="length of each phase (default 15)")
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--vehicles", type=int, default=16)
    p.add_argument("--rate", type=float, default=120.0, help="poses per second per vehicle (default 120)")
    p.add_argument("--invalid", type=int, default=50_000, help="invalid datagrams per loaded phase (default 50000)")
    p.add_argument("--settle", type=float, default=1.5, help="quiet seconds around each phase (default 1.5)")
    p.add_argument("--phases", default="baseline,spread,burst", help="sender phases to run, in order")
    p.add_argument("--hogs", type=int, help="CPU hog processes for the receiver (default: one per core)")
    p.add_argument("--video", help="an `ipt sim` output folder to loop (default: render 0.5 s)")
    args = p.parse_args(argv)
    out: dict[str, Any] = {"benchmark": "load", "cpu_count": os.cpu_count(), "loadavg_before": _loadavg()}
    with tempfile.TemporaryDirectory(prefix="ipt-load-") as tmp:
        work = Path(tmp)
        if args.part in ("sender", "all"):
            out["sender"] = sender_load(args, work)
        if args.part in ("receiver", "all"):
            out["receiver"] = receiver_load(args, work)
    out["loadavg_after"] = _loadavg()
    json.dump(out, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
