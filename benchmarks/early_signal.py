"""SIGINT to a tool 0-100 ms (``--max-ms``) after it is started: how the runs end (issue 33, item 16).

    ./dev run python benchmarks/early_signal.py                     # ipt --version, 4 runs per delay
    ./dev run python benchmarks/early_signal.py --runs 10 -- ipt-sender --version

Each run is a real process and a real signal. A traceback is counted as the script's or IPT's when it has a
frame of the console script or of the ``ipt`` package, else as Python's own start-up (before any IPT code).
"""

from __future__ import annotations

import argparse
import collections
import os
import shutil
import signal
import subprocess
import sys
import time


def outcome(returncode: int, stdout: bytes, stderr: bytes, script: str) -> str:
    if b"Traceback" in stderr:
        ours = script.encode() in stderr or f"{os.sep}ipt{os.sep}".encode() in stderr
        return "traceback in the script or IPT" if ours else "traceback in Python's start-up"
    if returncode == 128 + signal.SIGINT:
        return "130 and one line"
    if returncode == -signal.SIGINT:
        return "ended by SIGINT, no output"
    return f"finished (status {returncode})" if stdout else f"status {returncode}"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=4, help="runs per delay (default 4)")
    p.add_argument("--step-ms", type=float, default=5.0, help="delay step (default 5 ms)")
    p.add_argument("--max-ms", type=float, default=100.0, help="longest delay (default 100 ms; more on a busy machine)")
    p.add_argument("command", nargs="*", default=["ipt", "--version"], help="the tool and its arguments")
    args = p.parse_args()
    script = shutil.which(args.command[0]) or args.command[0]
    counts: collections.Counter[str] = collections.Counter()
    steps = int(args.max_ms / args.step_ms) + 1
    for i in range(steps):
        for _ in range(args.runs):
            proc = subprocess.Popen([script, *args.command[1:]], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            time.sleep(i * args.step_ms / 1000)
            proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=120)
            counts[outcome(proc.returncode, out, err, script)] += 1
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"{' '.join(args.command)}: {sum(counts.values())} runs, load average {load}")
    for kind, n in counts.most_common():
        print(f"  {n:4d}  {kind}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
