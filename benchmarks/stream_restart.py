"""How long a restarted receiver goes unheard: the sender's packet filter against real receiver restarts.

Runs ``ipt-receiver run --source sim --realtime --vehicle-id 5`` sending to a loopback socket of this
script, which passes the datagrams through the sender's own filter (``default_packet_filter``; with
``--key`` the receiver and the filter share a key). For each restart it says, for the new run: how long
after the old run's last packet its first packet reached the filter, how long after its first packet the
first one was accepted, and how many of its packets were refused before that.

A receiver takes 10 s or more to start on a loaded shared machine, longer than the silence after which
the filter takes any packet of a vehicle (``resync_after_s``, 10 s), which would hide the problem. So by
default the new run is started while the old one still runs; its packets are dropped until its first one
arrives, then the old run is stopped (``--signal``) and the new one's packets go to the filter from then
on: the filter hears the new run a moment after the old one, as it would a receiver that restarts in a
second or two. ``--plain`` stops the old run first and then starts the new one.

Only the command line and ``default_packet_filter`` are used, so it runs against older versions too
(``cd /tmp && PYTHONPATH=<old checkout> python <this file>``).

    python benchmarks/stream_restart.py --signal term [--key] [--restarts 2] [--plain]
"""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ipt.protocol import PacketFilter
from ipt.sender.server import default_packet_filter

KEY = b"ipt-restart-bench-key-0123456789"
Address = tuple[str, int]


def _receiver(port: int, key_file: Path | None, log: Path) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "ipt.receiver.cli", "run", "--source", "sim", "--realtime", "--vehicle-id", "5",
           "--send", f"127.0.0.1:{port}"]  # fmt: skip
    if key_file is not None:
        cmd += ["--auth-key-file", str(key_file)]
    with log.open("wb") as err:
        return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)


class Bench:
    def __init__(self, args: argparse.Namespace, folder: Path) -> None:
        self.args = args
        self.folder = folder
        self.key_file: Path | None = None
        if args.key:
            self.key_file = folder / "key"
            self.key_file.write_bytes(KEY)
            self.key_file.chmod(0o600)
        self.gate: PacketFilter = default_packet_filter(KEY if args.key else None)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port: int = self.sock.getsockname()[1]
        self.last_fed = 0.0

    def recv(self, until: float) -> tuple[bytes, Address, float] | None:
        while time.monotonic() < until:
            try:
                data, addr = self.sock.recvfrom(4096)
            except TimeoutError:
                continue
            return data, addr, time.monotonic()
        return None

    def feed(self, data: bytes, addr: Address, now: float) -> bool:
        self.last_fed = now
        return self.gate.accept(data, now, addr[0]) is not None

    def start(self, run: int) -> subprocess.Popen[bytes]:
        return _receiver(self.port, self.key_file, self.folder / f"run{run}.log")

    def first_run(self, proc: subprocess.Popen[bytes]) -> Address:
        """Feed the first run until it has had ``--packets`` accepted; its address."""
        accepted, addr = 0, None
        while accepted < self.args.packets:
            got = self.recv(time.monotonic() + 300.0)
            if got is None:
                raise SystemExit("stream_restart: the first run sent nothing within 300 s")
            addr = got[1]
            accepted += self.feed(*got)
        assert addr is not None
        return addr

    def switch(self, old: subprocess.Popen[bytes], old_addr: Address, new: subprocess.Popen[bytes]) -> None:
        """Until the new run's first packet: feed the old run's, drop the new run's; then stop the old run."""
        while True:
            got = self.recv(time.monotonic() + 300.0)
            if got is None:
                raise SystemExit("stream_restart: the new run sent nothing within 300 s")
            if got[1] == old_addr:
                self.feed(*got)
            else:
                break
        self.stop(old)
        while (got := self.recv(time.monotonic() + 0.3)) is not None:  # what the old run still had in flight
            if got[1] == old_addr:
                self.feed(*got)

    def stop(self, proc: subprocess.Popen[bytes]) -> None:
        proc.send_signal(signal.SIGTERM if self.args.signal == "term" else signal.SIGKILL)
        proc.wait(timeout=30)

    def new_run(self, old_addr: Address) -> tuple[str, Address]:
        """Feed the new run's packets; what happened to it, and its address."""
        before = self.last_fed
        first = accepted_at = None
        refused = accepted = 0
        addr: Address | None = None
        until = time.monotonic() + 300.0
        while accepted < self.args.packets and (got := self.recv(until)) is not None:
            if got[1] == old_addr:
                continue
            addr, now = got[1], got[2]
            if first is None:
                first, until = now, now + self.args.give_up_s
            if self.feed(*got):
                accepted += 1
                accepted_at = now if accepted_at is None else accepted_at
            elif accepted_at is None:
                refused += 1
        if first is None or addr is None:
            raise SystemExit("stream_restart: the new run sent nothing within 300 s")
        heard = (f"first accepted {1e3 * (accepted_at - first):.1f} ms after its first packet"
                 if accepted_at is not None else f"nothing accepted within {self.args.give_up_s:g} s")  # fmt: skip
        return (f"first packet {first - before:.2f} s after the old run's last; {heard}; "
                f"{refused} refused before that"), addr  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--signal", choices=["term", "kill"], default="term", help="how a run is stopped")
    ap.add_argument("--key", action="store_true", help="authenticate (the receiver and the filter share a key)")
    ap.add_argument("--restarts", type=int, default=1)
    ap.add_argument("--packets", type=int, default=5, help="accepted packets of a run before the next one")
    ap.add_argument("--give-up-s", type=float, default=30.0, help="after a run's first packet, wait this long")
    ap.add_argument("--plain", action="store_true", help="stop the old run before starting the new one")
    args = ap.parse_args()
    bench = Bench(args, Path(tempfile.mkdtemp(prefix="ipt-restart-")))
    proc = bench.start(0)
    try:
        addr = bench.first_run(proc)
        for run in range(1, args.restarts + 1):
            if args.plain:
                bench.stop(proc)
                proc = bench.start(run)
            else:
                new = bench.start(run)
                bench.switch(proc, addr, new)
                proc = new
            said, addr = bench.new_run(addr)
            mode = "plain restart" if args.plain else "started before the old run was stopped"
            print(f"restart {run} (SIG{args.signal.upper()}, {'key' if args.key else 'no key'}, {mode}): {said}")
        counts = {k: v for k, v in bench.gate.counts.items() if v}
        print(f"filter counts: {counts}")
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
    return 0


if __name__ == "__main__":
    sys.exit(main())
