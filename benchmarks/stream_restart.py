"""How long a restarted receiver goes unheard: the sender's packet filter against real receiver restarts.

Runs ``ipt-receiver run --source sim --realtime --vehicle-id 5`` sending to a loopback socket of this
script, which passes every datagram through the sender's own filter (``default_packet_filter``, with
``--key`` the same key as the receiver). After a few accepted packets the receiver is stopped (SIGTERM or
SIGKILL) and started again; for the new run this says when its first datagram arrived, when its first one
was accepted, and how many of its datagrams were refused in between. Only the command line and
``default_packet_filter`` are used, so it runs against older versions too (``PYTHONPATH=<old checkout>``).

    python benchmarks/stream_restart.py --signal term [--key] [--restarts 2] [--give-up-s 30]
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

from ipt.sender.server import default_packet_filter

KEY = b"ipt-restart-bench-key-0123456789"


def _receiver(port: int, key_file: Path | None, log: Path) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "ipt.receiver.cli", "run", "--source", "sim", "--realtime", "--vehicle-id", "5",
           "--send", f"127.0.0.1:{port}"]  # fmt: skip
    if key_file is not None:
        cmd += ["--auth-key-file", str(key_file)]
    with log.open("wb") as err:
        return subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--signal", choices=["term", "kill"], default="term")
    ap.add_argument("--key", action="store_true", help="authenticate (the receiver and the filter share a key)")
    ap.add_argument("--restarts", type=int, default=1)
    ap.add_argument("--packets", type=int, default=5, help="accepted packets of a run before stopping it")
    ap.add_argument("--give-up-s", type=float, default=30.0, help="after a run's first packet, wait this long")
    args = ap.parse_args()
    stop_with = signal.SIGTERM if args.signal == "term" else signal.SIGKILL
    folder = Path(tempfile.mkdtemp(prefix="ipt-restart-"))
    key_file = None
    if args.key:
        key_file = folder / "key"
        key_file.write_bytes(KEY)
        key_file.chmod(0o600)
    gate = default_packet_filter(KEY if args.key else None)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.1)
    port = sock.getsockname()[1]
    for run in range(args.restarts + 1):
        proc = _receiver(port, key_file, folder / f"run{run}.log")
        first = accepted_at = None
        refused = accepted = 0
        deadline = time.monotonic() + 300.0
        try:
            while time.monotonic() < deadline and accepted < args.packets:
                try:
                    data, addr = sock.recvfrom(4096)
                except TimeoutError:
                    continue
                now = time.monotonic()
                if first is None:
                    first, deadline = now, now + args.give_up_s
                if gate.accept(data, now, addr[0]) is None:
                    refused += 0 if accepted_at is not None else 1
                else:
                    accepted += 1
                    accepted_at = accepted_at if accepted_at is not None else now
        finally:
            proc.send_signal(stop_with)
            proc.wait(timeout=30)
        if first is None:
            print(f"run {run}: no packet within 300 s", file=sys.stderr)
            return 1
        heard = f"first accepted {1e3 * (accepted_at - first):.1f} ms after its first packet" if accepted_at else (
            f"nothing accepted within {args.give_up_s:g} s of its first packet")  # fmt: skip
        counts = {k: v for k, v in gate.counts.items() if v}
        how = "first run" if run == 0 else f"after SIG{args.signal.upper()}"
        print(f"run {run} ({'key' if args.key else 'no key'}, {how}): "
              f"{heard}; {refused} refused before that; filter counts so far {counts}")  # fmt: skip
        while True:  # drain what the stopped run still had in flight
            try:
                sock.recvfrom(4096)
            except TimeoutError:
                break
    return 0


if __name__ == "__main__":
    sys.exit(main())
