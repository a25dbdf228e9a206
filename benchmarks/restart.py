"""How soon poses resume after ``ipt-receiver run`` is killed and started again, as systemd does it.

A short simulated flight (the shipped arena, the smooth flight, rendered once into a temporary folder) is
fed to ``ipt-receiver run --source video:... --realtime`` (paced as a live 120 FPS camera) sending poses to
a UDP socket on 127.0.0.1. Each round: wait for the first pose, ``kill -9`` the daemon, wait the unit's
``RestartSec`` (300 ms, deploy/systemd/ipt-receiver.service), start the same command, and time the first
pose of the new process from the kill (``resumed_s``) and from its start (``first_pose_s``). Also a cold
start's first pose, for comparison. Prints one JSON object with every round and the medians; ``loadavg``
says how busy the machine was (these are wall-clock times on a shared machine).

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


def _drain(listener: socket.socket) -> None:
    listener.settimeout(0.05)
    while True:
        try:
            listener.recv(2048)
        except TimeoutError:
            return


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
        rounds = []
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
                rounds.append({"resumed_s": round(now - killed, 3), "first_pose_s": round(now - started, 3)})
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
        "loadavg_before": load_before,
        "loadavg": os.getloadavg(),
    }
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
