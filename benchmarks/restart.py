"""How soon poses resume after ``ipt-receiver run`` is killed and started again, as systemd does it.

A short simulated flight (the shipped arena, the smooth flight, rendered once into a temporary folder) is
fed to ``ipt-receiver run --source video:... --realtime`` (paced as a live 120 FPS camera) sending poses to
a UDP socket on 127.0.0.1. Each round: wait for the first pose, ``kill -9`` the daemon, wait the unit's
``RestartSec`` (300 ms, deploy/systemd/ipt-receiver.service), start the same command, and time the first
pose of the new process from the kill (``resumed_s``) and from its start (``first_pose_s``). Also a cold
start's first pose, for comparison. Prints one JSON object with every round and the medians; ``loadavg``
says how busy the machine was (these are wall-clock times on a shared machine). Each round also gives
``first_pose_cpu_s``: the processor time (user + sys) the new daemon and its AprilTag helper had used when
its first pose arrived, which a busy machine changes far less than the wall-clock time (Linux: from /proc).

Before the rounds it runs ``ipt-receiver warm`` once, as the unit's ExecStartPre does: numba's cache of the
kernels and ipt's own bytecode are then in place, as on an installed drone (``pip install`` compiles the
bytecode; an editable checkout under ``PYTHONDONTWRITEBYTECODE`` would otherwise compile every module of
ipt at every start, so the warm runs without that variable).

    ./dev run python benchmarks/restart.py              # 5 rounds, about half a minute
    ./dev run python benchmarks/restart.py --rounds 9
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

RESTART_SEC = 0.3
"""deploy/systemd/ipt-receiver.service's RestartSec."""


def _render(folder: Path) -> None:
    from ipt.config.models import load_arena_config, shipped_config_path
    from ipt.sender.content import GeneratedScene
    from ipt.sim.config import SimConfig
    from ipt.sim.run import simulate_to_folder

    arena = load_arena_config(shipped_config_path("arena.yaml"))
    simulate_to_folder(arena, SimConfig.smooth(), GeneratedScene(1920, 2160), folder, 1.0, progress=None)


def _command(folder: Path, port: int) -> list[str]:
    return [
        sys.executable, "-m", "ipt.receiver.cli", "run",
        "--camera", str(folder / "camera.yaml"),
        "--source", f"video:{folder / 'frames.mkv'}",
        "--fps", "120", "--realtime",
        "--send", f"127.0.0.1:{port}",
    ]  # fmt: skip


def _warm() -> None:
    """``ipt-receiver warm``: the kernels in numba's cache, ipt's modules compiled (see the module's doc)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    command = [sys.executable, "-m", "ipt.receiver.cli", "warm"]
    subprocess.run(command, env=env, check=False, stdout=subprocess.DEVNULL, timeout=600)


def _cpu_s(pid: int) -> float:
    """Processor time (user + sys) process ``pid`` has used so far, seconds (0 if it is gone)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _tree_cpu_s(pid: int) -> float | None:
    """Processor time of ``pid`` and its children (the AprilTag helper), or None without /proc."""
    if not os.path.isdir(f"/proc/{pid}/task"):
        return None
    children: list[int] = []
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/children", encoding="ascii") as f:
                children += [int(c) for c in f.read().split()]
        except OSError:
            continue
    return _cpu_s(pid) + sum(_cpu_s(c) for c in children)


def _drain(listener: socket.socket) -> None:
    listener.settimeout(0.05)
    while True:
        try:
            listener.recv(2048)
        except TimeoutError:
            return


def _median_or_none(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return round(statistics.median(known), 3) if known else None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="kill-and-restart rounds (default 5)")
    args = parser.parse_args()
    if not 1 <= args.rounds <= 100:
        parser.error(f"--rounds must be 1..100, got {args.rounds}")
    with tempfile.TemporaryDirectory(prefix="ipt-restart-") as tmp:
        folder = Path(tmp)
        print("restart: rendering a 1 s flight", file=sys.stderr)
        _render(folder)
        _warm()
        load_before = os.getloadavg()
        listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        listener.bind(("127.0.0.1", 0))
        cmd = _command(folder, listener.getsockname()[1])
        rounds: list[dict[str, Any]] = []
        try:
            started = time.monotonic()
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            listener.settimeout(20.0)
            listener.recv(2048)
            cold_s = time.monotonic() - started
            for k in range(args.rounds):
                proc.kill()
                killed = time.monotonic()
                proc.wait(5.0)
                time.sleep(RESTART_SEC)
                started = time.monotonic()
                proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                _drain(listener)  # what the killed one sent before it died
                listener.settimeout(20.0)
                listener.recv(2048)
                now = time.monotonic()
                cpu_s = _tree_cpu_s(proc.pid)
                rounds.append(
                    {
                        "resumed_s": round(now - killed, 3),
                        "first_pose_s": round(now - started, 3),
                        "first_pose_cpu_s": None if cpu_s is None else round(cpu_s, 3),
                    }
                )
                print(f"restart: round {k + 1}: poses resumed {now - killed:.2f} s after the kill", file=sys.stderr)
        finally:
            proc.kill()
            proc.wait()
            listener.close()
    out = {
        "restart_sec": RESTART_SEC,
        "cold_first_pose_s": round(cold_s, 3),
        "rounds": rounds,
        "median_resumed_s": round(statistics.median(r["resumed_s"] for r in rounds), 3),
        "median_first_pose_s": round(statistics.median(r["first_pose_s"] for r in rounds), 3),
        "median_first_pose_cpu_s": _median_or_none([r["first_pose_cpu_s"] for r in rounds]),
        "loadavg_before": load_before,
        "loadavg": os.getloadavg(),
    }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
