"""A pose stream that survives restarts, with real processes on loopback (issue 34).

A real sender (``ipt-sender --sink null``) listens; real receiver daemons (``ipt-receiver run --source
sim``) send to it and to a tap socket of the test, which sees every datagram the sender is sent. The
sender's final statistics line says what it accepted and refused; its stderr says what it noticed.

- a receiver stopped (SIGTERM or SIGKILL) and started again is accepted from its first packet, with and
  without a key: the sender refuses nothing;
- with a key, packets recorded from the earlier run and sent again after the restart are refused;
- two receivers with one vehicle id: one stderr line naming the vehicle and both;
- version-1 packets (an old receiver) are still accepted next to a version-2 receiver.

These only use what the sender and the receiver did before version 2 (command lines, ``encode_pose`` of a
packet without a stream), so they can be run against the code before the change, where they fail.
"""

from __future__ import annotations

import contextlib
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from waiting import wait_until

from ipt.protocol import PosePacket, encode_pose

pytestmark = pytest.mark.slow

KEY = b"ipt-restart-test-key-0123456789ab"
VEHICLE = 5
TINY_ARENA = """\
projector: {width_px: 320, height_px: 288, rate_hz: 60}
screen: {width_m: 1.0, height_m: 0.9}
tag_map: {rows: 2, cols: 2, tag_size_px: 64}
modulation: {delta_l: 8, input_rate_hz: 30}
"""
START_TIMEOUT_S = 180.0  # a receiver's first pose on a loaded two-core machine (numba, the simulated camera)
CONFLICT_LINE = re.compile(r"ipt-sender: vehicle (\d+) is claimed by two sources within 1 s: (.*)")


class Tap:
    """A loopback UDP socket that records every datagram with its source address and arrival time."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port: int = self.sock.getsockname()[1]
        self.datagrams: list[tuple[float, tuple[str, int], bytes]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(4096)
            except TimeoutError:
                continue
            with self._lock:
                self.datagrams.append((time.monotonic(), addr, data))

    def since(self, t0: float) -> list[tuple[float, tuple[str, int], bytes]]:
        with self._lock:
            return [d for d in self.datagrams if d[0] >= t0]

    def wait_for(self, count: int, t0: float, proc: subprocess.Popen[bytes], log: Path, sources: int = 1) -> None:
        """Until ``count`` datagrams arrived since ``t0`` from each of ``sources`` addresses."""

        def arrived() -> bool:
            by_source: dict[tuple[str, int], int] = {}
            for _, addr, _ in self.since(t0):
                by_source[addr] = by_source.get(addr, 0) + 1
            return len(by_source) >= sources and sorted(by_source.values())[-sources] >= count

        with contextlib.suppress(AssertionError):  # said below, with the log
            wait_until(lambda: arrived() or proc.poll() is not None, START_TIMEOUT_S)
        if not arrived():
            raise AssertionError(f"{count} packets not seen (exit {proc.poll()}):\n{log.read_text(errors='replace')}")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


class Relay(Tap):
    """A tap that forwards to the sender what comes from ``current`` (the first source heard, until changed),
    each source through a socket of its own (so the sender still tells them apart); the rest is dropped."""

    def __init__(self, sender_port: int) -> None:
        self.sender_port = sender_port
        self.current: tuple[str, int] | None = None
        self.forwarded: list[tuple[float, tuple[str, int], bytes]] = []
        self._out: dict[tuple[str, int], socket.socket] = {}
        super().__init__()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(4096)
            except TimeoutError:
                continue
            now = time.monotonic()
            with self._lock:
                self.datagrams.append((now, addr, data))
                if self.current is None:
                    self.current = addr
                if addr != self.current:
                    continue
                out = self._out.get(addr)
                if out is None:
                    out = self._out[addr] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                    out.bind(("127.0.0.1", 0))
                out.sendto(data, ("127.0.0.1", self.sender_port))
                self.forwarded.append((now, addr, data))

    def wait_forwarded(self, count: int, t0: float, proc: subprocess.Popen[bytes], log: Path) -> float:
        """Until ``count`` datagrams were forwarded after ``t0``; when the first one was."""

        def times() -> list[float]:
            with self._lock:
                return [t for t, _, _ in self.forwarded if t > t0]

        with contextlib.suppress(AssertionError):  # said below, with the log
            wait_until(lambda: len(times()) >= count or proc.poll() is not None, START_TIMEOUT_S)
        if len(got := times()) >= count:
            return got[0]
        raise AssertionError(f"{count} packets not forwarded (exit {proc.poll()}):\n{log.read_text(errors='replace')}")

    def wait_for_another(self, t0: float, proc: subprocess.Popen[bytes], log: Path) -> tuple[str, int]:
        """Until a source other than ``current`` is heard after ``t0``; its address."""

        def others() -> list[tuple[str, int]]:
            with self._lock:
                return [addr for t, addr, _ in self.datagrams if t > t0 and addr != self.current]

        with contextlib.suppress(AssertionError):  # said below, with the log
            wait_until(lambda: others() or proc.poll() is not None, START_TIMEOUT_S)
        if got := others():
            return got[0]
        raise AssertionError(f"no packet (exit {proc.poll()}):\n{log.read_text(errors='replace')}")

    def close(self) -> None:
        super().close()
        for out in self._out.values():
            out.close()


@contextmanager
def _relay(sender_port: int) -> Iterator[Relay]:
    relay = Relay(sender_port)
    try:
        yield relay
    finally:
        relay.close()


@contextmanager
def _tap() -> Iterator[Tap]:
    tap = Tap()
    try:
        yield tap
    finally:
        tap.close()


def _start(cmd: list[str], log: Path, cwd: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as err:
        return subprocess.Popen(cmd, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)


def _stop(proc: subprocess.Popen[bytes], sig: int = signal.SIGTERM) -> int:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            return proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait()


@contextmanager
def _processes() -> Iterator[list[subprocess.Popen[bytes]]]:
    """Every process put in the list is stopped on the way out (SIGTERM, then SIGKILL if it lingers)."""
    procs: list[subprocess.Popen[bytes]] = []
    try:
        yield procs
    finally:
        for proc in procs:
            _stop(proc)


def _wait_for_line(log: Path, pattern: str, proc: subprocess.Popen[bytes]) -> re.Match[str]:
    def found() -> re.Match[str] | None:
        return re.search(pattern, log.read_text(encoding="utf-8", errors="replace"))

    with contextlib.suppress(AssertionError):  # said below, with the log
        wait_until(lambda: found() or proc.poll() is not None, START_TIMEOUT_S)
    if (m := found()) is None:
        raise AssertionError(f"{pattern!r} not seen (exit {proc.poll()}):\n{log.read_text(errors='replace')}")
    return m


def _sender_heard(log: Path, count: int) -> None:
    """Until one of the sender's periodic lines counts ``count`` datagrams (accepted and rejected) or more."""

    def heard() -> int:
        text = log.read_text(encoding="utf-8", errors="replace")
        return max((int(a) + int(r) for a, r in re.findall(r"t=\S+ .*accepted=(\d+) rejected=(\d+)", text)), default=0)

    with contextlib.suppress(AssertionError):  # the final counts are checked by the test
        wait_until(lambda: heard() >= count, 10.0)


def _sent_by(log: Path) -> int:
    """The datagrams a stopped receiver sent (its final line's packets; 0 if it has none)."""
    found = re.findall(r"final: .* (\d+) packets in", log.read_text(encoding="utf-8", errors="replace"))
    return int(found[-1]) if found else 0


def _sender(tmp_path: Path, procs: list[subprocess.Popen[bytes]], key_file: Path | None) -> tuple[int, Path]:
    """Start the sender (null sink, tiny arena) on a free loopback port; (port, its stderr log)."""
    arena = tmp_path / "arena.yaml"
    arena.write_text(TINY_ARENA, encoding="utf-8")
    cmd = [sys.executable, "-m", "ipt.sender.cli", "--config", str(arena), "--sink", "null", "--frames", "1000000",
           "--listen", "127.0.0.1:0", "--stats-every", "0.1"]  # fmt: skip
    if key_file is not None:
        cmd += ["--auth-key-file", str(key_file)]
    log = tmp_path / "sender.log"
    procs.append(proc := _start(cmd, log, tmp_path))
    m = _wait_for_line(log, r"listening for pose packets on udp 127\.0\.0\.1:(\d+)", proc)
    return int(m.group(1)), log


def _receiver(
    tmp_path: Path, name: str, targets: list[int], key_file: Path | None, vehicle: int = VEHICLE
) -> tuple[subprocess.Popen[bytes], Path]:
    cmd = [sys.executable, "-m", "ipt.receiver.cli", "run", "--source", "sim", "--realtime",
           "--vehicle-id", str(vehicle), *(a for p in targets for a in ("--send", f"127.0.0.1:{p}"))]  # fmt: skip
    if key_file is not None:
        cmd += ["--auth-key-file", str(key_file)]
    log = tmp_path / f"{name}.log"
    return _start(cmd, log, tmp_path), log


def _sender_final(proc: subprocess.Popen[bytes], log: Path) -> tuple[dict[str, int], str]:
    """Stop the sender; the packet counts of its final line (accepted, rejected, each reason) and its stderr."""
    _stop(proc)
    text = log.read_text(encoding="utf-8", errors="replace")
    finals = [line for line in text.splitlines() if line.startswith("ipt-sender: done:")]
    assert len(finals) == 1, text
    m = re.search(r"packets accepted=(\d+) rejected=(\d+)(?: \(([^)]*)\))?", finals[0])
    assert m is not None, finals[0]
    counts = {"accepted": int(m.group(1)), "rejected": int(m.group(2))}
    for item in (m.group(3) or "").split(", "):
        if "=" in item:
            k, v = item.split("=")
            counts[k] = int(v)
    return counts, text


def _key_file(tmp_path: Path) -> Path:
    path = tmp_path / "key"
    path.write_bytes(KEY)
    path.chmod(0o600)
    return path


def _replay(packets: list[bytes], port: int) -> int:
    """Send ``packets`` to the sender from a socket of the test's own; its port."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as attacker:
        attacker.bind(("127.0.0.1", 0))
        for data in packets:
            attacker.sendto(data, ("127.0.0.1", port))
        attacker_port: int = attacker.getsockname()[1]
    return attacker_port


@pytest.mark.parametrize("keyed", [False, True], ids=["no-key", "key"])
def test_a_restarted_receiver_is_accepted_from_its_first_packet(tmp_path: Path, keyed: bool) -> None:
    """Three runs of one receiver: stopped with SIGTERM, started again, killed with SIGKILL, started again.

    A receiver takes longer to start on this shared machine than the 10 s of silence after which the sender
    used to take any packet of a vehicle, which would hide the problem. So each new run is started while
    the old one still runs, its packets dropped by the relay in front of the sender until the old run has
    been stopped: the sender then hears the new run a moment after the old one, as it would a receiver
    that restarts in a second or two.
    """
    key_file = _key_file(tmp_path) if keyed else None
    with _processes() as procs:
        port, sender_log = _sender(tmp_path, procs, key_file)
        sender = procs[0]
        with _relay(port) as relay:
            receiver, log = _receiver(tmp_path, "run0", [relay.port], key_file)
            procs.append(receiver)
            relay.wait_for(3, 0.0, receiver, log)
            gaps: list[float] = []
            earlier: list[bytes] = []
            started_old = 0.0
            for run, stop in enumerate((signal.SIGTERM, signal.SIGKILL), start=1):
                started = time.monotonic()
                new, log = _receiver(tmp_path, f"run{run}", [relay.port], key_file)
                procs.append(new)
                new_addr = relay.wait_for_another(started, new, log)  # the new run is up; its packets dropped so far
                _stop(receiver, stop)
                with relay._lock:
                    earlier += [d for t, a, d in relay.forwarded if a == relay.current and t > started_old]
                    last_old = relay.forwarded[-1][0]
                    relay.current = new_addr  # from now on the new run reaches the sender
                receiver, started_old = new, started
                gaps.append(relay.wait_forwarded(3, last_old, receiver, log) - last_old)
            # With a key: packets recorded from the earlier runs, sent again after the restarts: refused.
            replays = [earlier[0], earlier[-1]] if keyed else []
            attacker_port = _replay(replays, port)
            _stop(receiver)
            sent = _sent_by(log)  # all of them reached the relay, then the sender heard all it was given
            with contextlib.suppress(AssertionError):  # the counts are checked below
                wait_until(lambda: sum(1 for _, a, _ in relay.since(0.0) if a == relay.current) >= sent, 10.0)
            genuine = len(relay.forwarded)
            _sender_heard(sender_log, genuine + len(replays))
        counts, text = _sender_final(sender, sender_log)
    assert max(gaps) < 8.0, gaps  # the sender heard each new run well within the old 10 s
    # Every genuine packet of the three runs accepted, the first of each restarted run included; nothing
    # refused but the replayed ones.
    assert counts["accepted"] == genuine, (counts, genuine, gaps, text)
    assert counts["rejected"] == len(replays), (counts, text)
    assert counts.get("replayed", 0) == len(replays), (counts, text)
    # A restart is no conflict: a line, if any, names the replaying socket.
    for m in CONFLICT_LINE.finditer(text):
        assert f"127.0.0.1:{attacker_port} " in m.group(2), text


def test_two_receivers_with_one_vehicle_id_are_named_once(tmp_path: Path) -> None:
    with _tap() as tap, _processes() as procs:
        port, sender_log = _sender(tmp_path, procs, None)
        sender = procs[0]
        a, a_log = _receiver(tmp_path, "a", [port, tap.port], None)
        b, b_log = _receiver(tmp_path, "b", [port, tap.port], None)
        procs += [a, b]
        # Both sending, several packets each: enough for them to alternate at the sender.
        tap.wait_for(6, 0.0, a, a_log, sources=2)
        tap.wait_for(6, 0.0, b, b_log, sources=2)
        ports = {_sender_facing_port(p.pid, port) for p in (a, b)}
        _stop(a)
        _stop(b)
        counts, text = _sender_final(sender, sender_log)
    lines = [line for line in text.splitlines() if CONFLICT_LINE.match(line)]
    assert len(lines) == 1, text
    m = CONFLICT_LINE.match(lines[0])
    assert m is not None
    assert int(m.group(1)) == VEHICLE
    for p in ports:
        assert f"127.0.0.1:{p} " in lines[0], (ports, lines[0])
    assert "drawing the newer stream" in lines[0]
    assert counts["accepted"] > 0


def _sender_facing_port(pid: int, sender_port: int) -> int:
    """The local port of ``pid``'s UDP socket connected to ``sender_port`` (from /proc, as the kernel says)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = fd.readlink()
        except OSError:
            continue
        if m := re.fullmatch(r"socket:\[(\d+)\]", str(target)):
            inodes.add(m.group(1))
    for line in Path(f"/proc/{pid}/net/udp").read_text().splitlines()[1:]:
        f = line.split()
        local_port, remote_port = int(f[1].split(":")[1], 16), int(f[2].split(":")[1], 16)
        if f[9] in inodes and remote_port == sender_port:
            return local_port
    raise AssertionError(f"process {pid} has no socket connected to port {sender_port}")


def test_version_1_packets_are_accepted_next_to_a_version_2_receiver(tmp_path: Path) -> None:
    with _tap() as tap, _processes() as procs:
        port, sender_log = _sender(tmp_path, procs, None)
        sender = procs[0]
        receiver, receiver_log = _receiver(tmp_path, "receiver", [port, tap.port], None)
        procs.append(receiver)
        tap.wait_for(3, 0.0, receiver, receiver_log)
        # This receiver sends version 2 ...
        assert {(len(d), d[4]) for _, _, d in tap.since(0.0)} == {(120, 2)}
        # ... and an old receiver (vehicle 6) sends version-1 packets: numbered on, then from 0 again (a restart of a
        # version-1 daemon, refused as replayed for 10 s as it always was).
        old = [PosePacket(6, seq, 1_000 * seq, (0.1, 0.2, 1.0), (0.0, 1.0, 0.0, 0.0), num_tags=4) for seq in range(10)]
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as old_receiver:
            for packet in [*old, old[0]]:
                data = encode_pose(packet)
                assert (len(data), data[4]) == (112, 1)
                old_receiver.sendto(data, ("127.0.0.1", port))  # in order: loopback keeps it
        _stop(receiver)
        sent = _sent_by(receiver_log) // 2  # to the sender and to the tap
        with contextlib.suppress(AssertionError):  # the counts are checked below
            wait_until(lambda: len(tap.since(0.0)) >= sent, 10.0)
        genuine = len(tap.since(0.0))
        _sender_heard(sender_log, genuine + len(old) + 1)
        counts, text = _sender_final(sender, sender_log)
    assert genuine + 10 <= counts["accepted"] <= genuine + 11, (counts, genuine, text)
    assert counts["rejected"] == 1, (counts, text)
    assert counts.get("replayed") == 1, (counts, text)
