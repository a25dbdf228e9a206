"""How soon poses resume after ``ipt-receiver run`` is killed and started again, as systemd does it.

A short simulated flight (the shipped arena, the smooth flight, rendered once into a temporary folder) is
fed to ``ipt-receiver run --source images:... --realtime`` (its frames as BMP images, paced as a live 120 FPS
camera) sending poses to a UDP socket on 127.0.0.1. Like a camera's frames, BMP images cost next to nothing to
read, as in issue 29's whole-process replays; ``--source video`` feeds the rendering's FFV1 video instead, as
this benchmark did before: its decoding costs about 10 ms of processor time a frame, 0.1 s or more before the
first pose, which no camera costs. Each round: wait for the first pose, ``kill -9`` the daemon, wait the
unit's ``RestartSec`` (300 ms, deploy/systemd/ipt-receiver.service), start the same command, and time the
first pose of the new process from the kill (``resumed_s``) and from its start (``first_pose_s``). Also a
cold start's first pose, for comparison. Prints one JSON object with every round and the medians;
``loadavg`` says how busy the machine was (these are wall-clock times on a shared machine). Each round also
gives ``first_pose_cpu_s``: the processor time (user + sys) the new daemon and its AprilTag helper had used
when its first pose arrived, which a busy machine changes far less than the wall-clock time (Linux: from
/proc).

Before the rounds it runs ``ipt-receiver warm`` once, as the unit's ExecStartPre does, into a cache folder of
each receiver's own (``NUMBA_CACHE_DIR`` in the temporary folder, as the unit's ``CacheDirectory=``; a minute
the first time: numba compiles every kernel, then they are built ahead of time where a C compiler is): the
kernels and ipt's own bytecode are then in place, as on an installed drone (``pip install`` compiles the
bytecode; an editable checkout under ``PYTHONDONTWRITEBYTECODE`` would otherwise compile every module of
ipt at every start, so the warm runs without that variable).

With ``--baseline DIR`` (another checkout of ipt, e.g. ``git worktree add /tmp/base main``) the rounds
alternate between that checkout's receiver and this one (which starts first swapped every round), on the same
rendering, so that a busy machine weighs on both alike; the JSON then has one entry per build and the ratio of
their medians.

    ./dev run python benchmarks/restart.py              # 5 rounds, about half a minute
    ./dev run python benchmarks/restart.py --rounds 9
    ./dev run python benchmarks/restart.py --baseline /tmp/base --rounds 9
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
from dataclasses import dataclass
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


def _source(folder: Path, kind: str) -> str:
    """The ``--source`` of the rendering in ``folder``: its frames as BMP images (written once), or its video."""
    if kind == "video":
        return f"video:{folder / 'frames.mkv'}"
    from suite import frames_folder  # benchmarks/suite.py, beside this script

    return f"images:{frames_folder(folder)}"


def _command(folder: Path, source: str, port: int) -> list[str]:
    return [
        sys.executable, "-m", "ipt.receiver.cli", "run",
        "--camera", str(folder / "camera.yaml"),
        "--source", source,
        "--fps", "120", "--realtime",
        "--send", f"127.0.0.1:{port}",
    ]  # fmt: skip


@dataclass(frozen=True)
class _Build:
    """A receiver to start: this checkout's, or another's (``--baseline``) through ``PYTHONPATH``."""

    name: str
    env: dict[str, str] | None
    cwd: str | None
    """A folder of its own for a baseline: ``python -m`` puts the working directory first on the path."""


def _builds(baseline: Path | None, tmp: Path) -> list[_Build]:
    """Each receiver with a kernel cache folder of its own (``NUMBA_CACHE_DIR``, as the unit's
    ``CacheDirectory=``), which :func:`_warm` fills."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp / "cache-this"))
    if baseline is None:
        return [_Build("this", env, None)]
    if not (baseline / "ipt" / "receiver" / "cli.py").is_file():
        raise SystemExit(f"restart: --baseline {baseline}: not a checkout of ipt (no ipt/receiver/cli.py)")
    # Both started alike, each from a folder of its own through PYTHONPATH (run from its checkout, "this" had the
    # checkout first on the path where the baseline had an empty folder: not the same start).
    own = tmp / "this-cwd"
    own.mkdir()
    here = _Build("this", dict(env, PYTHONPATH=str(Path(__file__).resolve().parents[1])), str(own))
    cwd = tmp / "baseline-cwd"
    cwd.mkdir()
    base_env = dict(os.environ, PYTHONPATH=str(baseline.resolve()), NUMBA_CACHE_DIR=str(tmp / "cache-baseline"))
    return [_Build("baseline", base_env, str(cwd)), here]


def _warm(build: _Build) -> None:
    """``ipt-receiver warm``: the kernels in numba's cache, ipt's modules compiled (see the module's doc)."""
    env = {k: v for k, v in (build.env or os.environ).items() if k != "PYTHONDONTWRITEBYTECODE"}
    command = [sys.executable, "-m", "ipt.receiver.cli", "warm"]
    subprocess.run(command, env=env, cwd=build.cwd, check=False, stdout=subprocess.DEVNULL, timeout=600)


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


def _start(build: _Build, cmd: list[str]) -> subprocess.Popen[bytes]:
    out = subprocess.DEVNULL
    return subprocess.Popen(cmd, stdout=out, stderr=out, env=build.env, cwd=build.cwd)


def _summary(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    return {
        "rounds": rounds,
        "median_resumed_s": round(statistics.median(r["resumed_s"] for r in rounds), 3),
        "median_first_pose_s": round(statistics.median(r["first_pose_s"] for r in rounds), 3),
        "median_first_pose_cpu_s": _median_or_none([r["first_pose_cpu_s"] for r in rounds]),
    }


def _run_rounds(builds: list[_Build], cmd: list[str], listener: socket.socket, n: int) -> dict[str, Any]:
    """A cold start of the first build, then ``n`` rounds of kill-and-restart of each build in turn, the order
    swapped every round, so that a bias of the place in a round weighs on both alike (stop 71: with the order
    fixed, the build started second was the slower one to its first pose in four runs of five, whichever it was)."""
    rounds: dict[str, list[dict[str, Any]]] = {b.name: [] for b in builds}
    started = time.monotonic()
    proc = _start(builds[0], cmd)
    try:
        listener.settimeout(20.0)
        listener.recv(2048)
        cold_s = time.monotonic() - started
        for k in range(n):
            for build in builds if k % 2 == 0 else builds[::-1]:
                proc.kill()
                killed = time.monotonic()
                proc.wait(5.0)
                time.sleep(RESTART_SEC)
                started = time.monotonic()
                proc = _start(build, cmd)
                _drain(listener)  # what the killed one sent before it died
                listener.settimeout(20.0)
                listener.recv(2048)
                now = time.monotonic()
                cpu_s = _tree_cpu_s(proc.pid)
                rounds[build.name].append(
                    {
                        "resumed_s": round(now - killed, 3),
                        "first_pose_s": round(now - started, 3),
                        "first_pose_cpu_s": None if cpu_s is None else round(cpu_s, 3),
                    }
                )
                print(f"restart: round {k + 1} ({build.name}): poses resumed {now - killed:.2f} s after the kill, "
                      f"{cpu_s} s of processor time", file=sys.stderr)  # fmt: skip
    finally:
        proc.kill()
        proc.wait()
    return {"cold_first_pose_s": round(cold_s, 3), **{name: _summary(r) for name, r in rounds.items()}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="kill-and-restart rounds (default 5)")
    parser.add_argument(
        "--source",
        choices=("images", "video"),
        default="images",
        help="the frames as BMP images (default: as cheap to read as a camera's) or as the FFV1 video",
    )
    parser.add_argument("--baseline", type=Path, metavar="DIR",
                        help="another checkout of ipt: its receiver and this one's, in alternate rounds")  # fmt: skip
    args = parser.parse_args()
    if not 1 <= args.rounds <= 100:
        parser.error(f"--rounds must be 1..100, got {args.rounds}")
    with tempfile.TemporaryDirectory(prefix="ipt-restart-") as tmp:
        folder = Path(tmp)
        builds = _builds(args.baseline, folder)
        print("restart: rendering a 1 s flight", file=sys.stderr)
        _render(folder)
        source = _source(folder, args.source)
        for build in builds:
            print(f"restart: ipt-receiver warm ({build.name}: up to a minute the first time)", file=sys.stderr)
            _warm(build)
        load_before = os.getloadavg()
        listener = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        listener.bind(("127.0.0.1", 0))
        try:
            measured = _run_rounds(builds, _command(folder, source, listener.getsockname()[1]), listener, args.rounds)
        finally:
            listener.close()
    out: dict[str, Any] = {"restart_sec": RESTART_SEC, "source": args.source}
    if args.baseline is None:
        out |= {"cold_first_pose_s": measured["cold_first_pose_s"], **measured["this"]}
    else:
        out |= measured | {"baseline_dir": str(args.baseline)}
        base, this = measured["baseline"]["median_first_pose_cpu_s"], measured["this"]["median_first_pose_cpu_s"]
        if base and this:
            out["cpu_ratio_this_to_baseline"] = round(this / base, 3)
    out |= {"loadavg_before": load_before, "loadavg": os.getloadavg()}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
