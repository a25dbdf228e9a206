"""The processor time of a replay as the systemd unit runs the receiver, against an unrestricted one.

"As the unit runs it": the unit's Environment= (``NUMBA_CACHE_DIR`` pointing into its ``CacheDirectory=``,
here a temporary folder standing for /var/cache/ipt-receiver), no home (``HOME=/nonexistent``, no
``XDG_*``), the cache filled by the unit's ``ExecStartPre=ipt-receiver warm``, and W^X (the kernel's
``prctl(PR_SET_MDWE)``, as tests/test_systemd.py applies it) if and only if the unit sets
``MemoryDenyWriteExecute=yes``. "Unrestricted": the developer's environment, numba's default cache, warmed
first. Each replay runs pinned to one core, ``taskset -c 0 /usr/bin/time -f '%U %S' ipt-receiver replay``,
rounds alternating so that a change in the machine's load hits both. ``--wx`` adds the same replay under
W^X whatever the unit says (what the old unit cost). ``--read-only`` (root, Linux) runs the unit's
commands in a mount namespace of their own where the whole file system is read-only but the cache folder,
as ``ProtectSystem=strict`` with ``CacheDirectory=`` leaves it (numba cannot then fall back to a cache
next to the sources). ``--live DIR`` (a folder as ``ipt sim`` writes it: frames.mkv, camera.yaml,
groundtruth.tum) adds issue 29's live figure under the same settings: ``benchmarks/daemon.py --video DIR
--modes camera`` (the daemon fed the recording at the camera's rate, capture -> send latency) pinned to one core,
as the unit runs the receiver and unrestricted, alternating for ``--live-rounds``; with ``--wx`` under W^X too.
Prints one JSON object.

    ./dev run python benchmarks/unit_kernels.py --video DIR/bmp --camera DIR/camera.yaml --config DIR/arena.yaml
    ./dev run python benchmarks/unit_kernels.py ... --rounds 0 --live DIR --live-rounds 3 --wx --read-only
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
UNIT = ROOT / "deploy" / "systemd" / "ipt-receiver.service"
MDWE_EXEC = """
import ctypes, os, sys
if ctypes.CDLL(None, use_errno=True).prctl(65, 1, 0, 0, 0) != 0:
    sys.exit(77)
os.execv(sys.argv[1], sys.argv[1:])
"""


def _unit_settings() -> tuple[dict[str, str], bool]:
    """The unit's Environment= variables and whether it sets MemoryDenyWriteExecute=yes."""
    env: dict[str, str] = {}
    wx = False
    for line in UNIT.read_text(encoding="utf-8").splitlines():
        if line.startswith("Environment="):
            for item in shlex.split(line.partition("=")[2]):
                name, _, value = item.partition("=")
                env[name] = value
        elif line.startswith("MemoryDenyWriteExecute="):
            wx = line.partition("=")[2].strip() == "yes"
    return env, wx


READ_ONLY = 'mount --make-rprivate / && mount --bind "$0" "$0" && mount -o remount,bind,ro / && exec "$@"'
"""sh: bind the cache folder ($0) onto itself, then make the root mount read-only, then run the command."""


def _restricted(command: list[str], wx: bool, writable: str | None) -> list[str]:
    """``command`` pinned to core 0 and timed, under W^X (``wx``), the file system read-only but ``writable``."""
    if wx:
        command = [sys.executable, "-c", MDWE_EXEC, *command]
    if writable is not None:
        command = ["unshare", "-m", "sh", "-c", READ_ONLY, writable, *command]
    return ["taskset", "-c", "0", "/usr/bin/time", "-f", "%U %S", *command]


FPS = 120.0
"""The camera's frame rate, for the replays and the live runs alike (the simulated flights' 120 FPS)."""

LIVE_FIGURES = ("poses", "frames_per_second", "latency_p50_ms", "latency_p99_ms", "drops", "poses_over_30ms")
"""What each live run reports of ``benchmarks/daemon.py``'s camera mode (its packets' errors are checked too)."""


def _live(folder: str, env: dict[str, str], wx: bool, writable: str | None) -> dict[str, object]:
    """``benchmarks/daemon.py --video folder --modes camera`` under these settings: its camera mode's figures."""
    env = dict(env, TMPDIR=writable) if writable is not None else env  # (its temporary folder, as PrivateTmp= gives)
    daemon = [sys.executable, str(ROOT / "benchmarks" / "daemon.py"), "--video", folder, "--modes", "camera",
              "--fps", str(FPS)]  # fmt: skip
    result = subprocess.run(_restricted(daemon, wx, writable), capture_output=True, text=True, env=env, check=False,
                            timeout=1800)  # fmt: skip
    if result.returncode != 0:
        return {"exit": result.returncode, "error": result.stderr.strip().splitlines()[-1:]}
    camera = json.loads(result.stdout)["camera"]
    out: dict[str, object] = {name: camera.get(name) for name in LIVE_FIGURES}
    seconds = camera["frames_captured"] / FPS  # (the flight's length)
    out["poses_per_second"] = round(camera["poses"] / seconds, 1) if seconds else None
    out["packets_over_30mm"] = camera.get("packet_error_mm", {}).get("over_30mm")
    out["loadavg_1min"] = os.getloadavg()[0]
    return out


def _timed(command: list[str], env: dict[str, str], wx: bool, writable: str | None = None) -> dict[str, object]:
    full = _restricted(command, wx, writable)
    result = subprocess.run(full, capture_output=True, text=True, env=env, check=False, timeout=1800)
    lines = result.stderr.strip().splitlines()
    user, sys_s = (float(x) for x in lines[-1].split())
    kernels = next((ln for ln in result.stdout.splitlines() + lines if "kernels:" in ln), "")
    return {"cpu_s": round(user + sys_s, 2), "user_s": user, "sys_s": sys_s, "exit": result.returncode,
            "kernels": kernels.partition("kernels: ")[2]}  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--video", required=True, help="the recording (an image folder: BMP costs no decoding)")
    parser.add_argument("--camera", required=True)
    parser.add_argument("--config", required=True, help="the arena YAML")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--wx", action="store_true", help="also one replay under W^X (the old unit's setting)")
    parser.add_argument("--read-only", action="store_true", help="as the unit: all read-only but the cache (root)")
    parser.add_argument("--live", metavar="DIR", help="also the live daemon on this flight folder (frames.mkv, ...)")
    parser.add_argument("--live-rounds", type=int, default=3, help="live runs of each setting, alternating")
    args = parser.parse_args()
    if args.live is not None and not (Path(args.live) / "frames.mkv").is_file():
        parser.error(f"--live {args.live}: no frames.mkv there (a folder as ipt sim writes it)")
    unit_env, unit_wx = _unit_settings()
    with tempfile.TemporaryDirectory(prefix="ipt-unit-") as tmp:
        cli = [sys.executable, "-m", "ipt.receiver.cli"]
        replay = [*cli, "replay", "--config", args.config, "--camera", args.camera, "--video", args.video,
                  "--fps", str(FPS), "--output", str(Path(tmp) / "poses.tum")]  # fmt: skip
        free = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
        as_unit = {k: v for k, v in free.items() if not k.startswith(("NUMBA_", "XDG_"))}
        as_unit.update(unit_env, HOME="/nonexistent")
        if "NUMBA_CACHE_DIR" in unit_env:
            as_unit["NUMBA_CACHE_DIR"] = str(Path(tmp) / "var-cache" / Path(unit_env["NUMBA_CACHE_DIR"]).name)
        warm_free = subprocess.run([*cli, "warm"], capture_output=True, text=True, env=free, check=False)
        writable = None
        if args.read_only:
            writable = as_unit.get("NUMBA_CACHE_DIR", tmp)
            Path(writable).mkdir(parents=True, exist_ok=True)
            replay[-1] = str(Path(writable) / "poses.tum")  # the only place it may write
        warm_unit = _timed([*cli, "warm"], as_unit, unit_wx, writable)
        rounds = []
        for _ in range(args.rounds):
            unit_run = _timed(replay, as_unit, unit_wx, writable)
            rounds.append({"unrestricted": _timed(replay, free, False), "unit": unit_run})
        free_s = statistics.median(float(r["unrestricted"]["cpu_s"]) for r in rounds) if rounds else None  # type: ignore[arg-type]
        unit_s = statistics.median(float(r["unit"]["cpu_s"]) for r in rounds) if rounds else None  # type: ignore[arg-type]
        out: dict[str, object] = {
            "unit_environment": unit_env,
            "unit_wx": unit_wx,
            "read_only_but_the_cache": args.read_only,
            "warm_unrestricted": warm_free.stdout.strip(),
            "warm_as_unit": warm_unit,
            "rounds": rounds,
            "median_cpu_s": {"unrestricted": free_s, "unit": unit_s},
            "ratio_unit_to_unrestricted": round(unit_s / free_s, 3) if unit_s and free_s else None,
            "loadavg_1min": os.getloadavg()[0],
        }
        if args.wx and rounds:
            out["under_wx"] = _timed(replay, as_unit, True)
        if args.live is not None:
            live = []
            for _ in range(args.live_rounds):
                one = {
                    "unit": _live(args.live, as_unit, unit_wx, writable),
                    "unrestricted": _live(args.live, free, False, None),
                }
                if args.wx:
                    one["unit_under_wx"] = _live(args.live, as_unit, True, writable)
                live.append(one)
            out["live"] = live
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
