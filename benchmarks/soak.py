"""Soak: the sender and the receiver daemon running together for a long time keep their memory and their
file descriptors flat.

Runs two real processes, as deployed but on one machine:

- ``ipt-sender`` (null sink, paced at the projector rate, ``--width``×``--height``, default 960×1080),
  listening on 127.0.0.1 for authenticated packets of vehicle 1, drawing it on the overlay;
- ``ipt-receiver run`` on the simulated arena (``--source sim --realtime``: the simulator renders what
  a camera flying over the projected floor sees, forever), sending authenticated pose packets to it.

Every ``--interval`` seconds it samples each process's resident memory (``VmRSS`` in
``/proc/PID/status``, and its two parts: ``RssAnon``, the process's own memory, where a leak would
show, and ``RssFile``, mapped library pages), open file descriptors (entries of ``/proc/PID/fd``) and
threads, each summed over the process and its descendants: the receiver runs AprilTag in a helper
process (``ipt.receiver.detect.tagworker``) that it replaces once the helper's memory grew by
``detector.recycle_mb``, so its memory is counted with the daemon's. The first ``--warmup`` seconds
are left out (imports, caches, histograms and pools filling up).
After that, growth is reported four ways: last minus first sample, median of the last five samples
minus that of the first five, median of the last sixth of the run minus that of the first sixth, and
the least-squares slope scaled to 30 minutes.

The receiver's RSS is a saw-tooth: the helper's memory climbs by up to ``recycle_mb`` (AprilTag's
leak) and drops when a fresh helper takes over, the daemon's own heap wanders by a few megabytes, and
for the second a replacement takes to start there are two helpers. A slope or an end-minus-start then
depends on where the first and the last sample fall in a tooth. So the verdicts use the windowed
medians (the level at the start against the level at the end). Targets: RSS growth below 5 MB over
30 minutes, no growth in file descriptors. At the end both get SIGTERM and their final statistics
lines are kept (poses sent and accepted prove the loop was alive throughout; the receiver's line says
how many helpers were replaced).

Prints one JSON object; ``--samples FILE`` also writes every sample as JSON lines.

    ./dev run python benchmarks/soak.py --minutes 30
    ./dev run python benchmarks/soak.py --minutes 3 --warmup 30 --interval 2
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml
from load import arena_for, wait_for  # benchmarks/ is on sys.path when a script here runs

from ipt.config.models import shipped_config_path

KEY = b"ipt-soak-benchmark-key-0123456789"
TARGET_RSS_GROWTH_MB_PER_30MIN = 5.0


def _children() -> dict[int, list[int]]:
    """Parent pid -> child pids, for every process on the machine."""
    tree: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            tree.setdefault(int(stat.rsplit(")", 1)[1].split()[1]), []).append(int(entry))
    return tree


def _one(pid: int) -> dict[str, int] | None:
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (FileNotFoundError, ProcessLookupError):
        return None

    def field(name: str) -> int:
        m = re.search(rf"^{name}:\s+(\d+)", status, re.M)
        return int(m[1]) if m else 0

    return {
        "rss_kb": field("VmRSS"),
        "rss_anon_kb": field("RssAnon"),  # the process's own memory: where a leak would show
        "rss_file_kb": field("RssFile"),  # mapped files (libraries): the kernel may drop and re-read them
        "fds": fds,
        "threads": field("Threads"),
    }


def sample(pid: int) -> dict[str, int] | None:
    """RSS (kB), open fds and threads of ``pid`` and all its descendants (the receiver's detector helper
    process among them), summed; None once ``pid`` has gone. ``processes`` counts them, and
    ``main_rss_anon_kb`` is ``pid``'s own share."""
    main = _one(pid)
    if main is None:
        return None
    total = dict(main)
    total["processes"] = 1
    total["main_rss_anon_kb"] = main["rss_anon_kb"]
    tree = _children()
    todo = list(tree.get(pid, []))
    while todo:
        child = todo.pop()
        todo.extend(tree.get(child, []))
        one = _one(child)
        if one is None:
            continue
        for key, value in one.items():
            total[key] += value
        total["processes"] += 1
    return total


def slope_per_s(ts: list[float], ys: list[float]) -> float:
    """Least-squares slope of ``ys`` over ``ts``."""
    n = len(ts)
    if n < 2:
        return 0.0
    mt, my = sum(ts) / n, sum(ys) / n
    den = sum((t - mt) ** 2 for t in ts)
    return sum((t - mt) * (y - my) for t, y in zip(ts, ys, strict=True)) / den if den > 0 else 0.0


def _memory(steady: list[tuple[float, dict[str, int]]], key: str) -> dict[str, float]:
    ts = [t for t, _ in steady]
    mb = [s[key] / 1024 for _, s in steady]
    return {
        "start": round(mb[0], 1),
        "end": round(mb[-1], 1),
        "min": round(min(mb), 1),
        "max": round(max(mb), 1),
        "growth": round(mb[-1] - mb[0], 2),
        # Median of the last five samples less that of the first five: one frame buffer more or less
        # in flight (3 MB at 960x1080) does not move it.
        "growth_median5": round(statistics.median(mb[-5:]) - statistics.median(mb[:5]), 2),
        # The same over the first and the last sixth of the run (5 minutes of a 30-minute run): the level,
        # wherever in its saw-tooth (see the module doc) the first and the last sample fell.
        "growth_window_median": round(_window_median(ts, mb, last=True) - _window_median(ts, mb, last=False), 2),
        "slope_mb_per_30min": round(slope_per_s(ts, mb) * 1800, 2),
    }


def _window_median(ts: list[float], ys: list[float], last: bool) -> float:
    """Median of ``ys`` over the first (or the last) sixth of the time span."""
    span = (ts[-1] - ts[0]) / 6
    picked = [y for t, y in zip(ts, ys, strict=True) if (t >= ts[-1] - span if last else t <= ts[0] + span)]
    return statistics.median(picked)


def summarise(samples: list[tuple[float, dict[str, int]]], warmup_s: float) -> dict[str, Any]:
    steady = [(t, s) for t, s in samples if t >= warmup_s] or samples
    fds = [s["fds"] for _, s in steady]
    threads = [s["threads"] for _, s in steady]
    procs = [s["processes"] for _, s in steady]
    ts = [t for t, _ in steady]
    return {
        "samples": len(samples),
        "rss_mb": {"first": round(samples[0][1]["rss_kb"] / 1024, 1), **_memory(steady, "rss_kb")},
        # RSS = the process's anonymous memory (heap, arrays: where a leak shows) + the pages of mapped
        # files (shared libraries) the kernel holds in memory for it, which it may drop and read again.
        "rss_anon_mb": _memory(steady, "rss_anon_kb"),
        "rss_file_mb": _memory(steady, "rss_file_kb"),
        "main_rss_anon_mb": _memory(steady, "main_rss_anon_kb"),
        "fds": {
            "start": fds[0],
            "end": fds[-1],
            "min": min(fds),
            "max": max(fds),
            "growth": fds[-1] - fds[0],
            # While a replacement detector helper starts, the tree holds its pipes too (a second or so).
            "growth_window_median": _window_median(ts, [float(f) for f in fds], last=True)
            - _window_median(ts, [float(f) for f in fds], last=False),
        },
        "threads": {"start": threads[0], "end": threads[-1], "max": max(threads)},
        "processes": {"start": procs[0], "end": procs[-1], "max": max(procs)},
    }


def _stop(proc: subprocess.Popen[bytes]) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            return proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait()


def _last(log: Path, marker: str) -> str | None:
    lines = [ln for ln in log.read_text(encoding="utf-8", errors="replace").splitlines() if marker in ln]
    return lines[-1] if lines else None


def soak(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    arena_path = work / "arena.yaml"
    arena_path.write_text(yaml.safe_dump(arena_for(args.width, args.height)), encoding="utf-8")
    key_file = work / "key"
    key_file.write_bytes(KEY)
    key_file.chmod(0o600)  # a key file others can read is refused
    sender_log, receiver_log = work / "sender.log", work / "receiver.log"
    sender_cmd = [sys.executable, "-m", "ipt.sender.cli", "--config", str(arena_path), "--sink", "null",
                  "--listen", "127.0.0.1:0", "--auth-key-file", str(key_file), "--vehicles", "1",
                  "--stats-every", "30"]  # fmt: skip
    with sender_log.open("wb") as err:
        sender = subprocess.Popen(sender_cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    receiver: subprocess.Popen[bytes] | None = None
    samples: dict[str, list[tuple[float, dict[str, int]]]] = {"sender": [], "receiver": []}
    died: dict[str, float] = {}
    # Line-buffered: the samples can be watched while the run goes on.
    out_file = open(args.samples, "w", encoding="utf-8", buffering=1) if args.samples else None  # noqa: SIM115
    try:
        port = int(wait_for(sender_log, r"listening for pose packets on udp 127\.0\.0\.1:(\d+)", sender, 120)[1])
        receiver_cfg = {
            "arena": str(arena_path),
            "camera": str(shipped_config_path("camera.yaml")),
            "source": "sim",
            "realtime": True,
            "vehicle_id": 1,
            "send": [f"127.0.0.1:{port}"],
            "auth_key_file": str(key_file),
            "stats_interval_s": 30,
        }
        cfg_path = work / "receiver.yaml"
        cfg_path.write_text(yaml.safe_dump(receiver_cfg), encoding="utf-8")
        receiver_cmd = [sys.executable, "-m", "ipt.receiver.cli", "run", "--config", str(cfg_path)]
        with receiver_log.open("wb") as err:
            receiver = subprocess.Popen(receiver_cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
        wait_for(receiver_log, r"ipt-receiver: running: ", receiver, 120)
        procs = {"sender": sender, "receiver": receiver}
        t0 = time.monotonic()
        end = t0 + args.minutes * 60
        next_at = t0
        while True:
            now = time.monotonic()
            for name, proc in procs.items():
                s = sample(proc.pid) if proc.poll() is None else None
                if s is None:
                    died.setdefault(name, round(now - t0, 1))
                    continue
                samples[name].append((now - t0, s))
                if out_file is not None:
                    out_file.write(json.dumps({"t": round(now - t0, 1), "process": name, **s}) + "\n")
            if died or now >= end:
                break
            next_at += args.interval
            time.sleep(max(0.0, min(next_at, end) - time.monotonic()))
        wall = time.monotonic() - t0
    finally:
        rc_receiver = _stop(receiver) if receiver is not None else None
        rc_sender = _stop(sender)
        if out_file is not None:
            out_file.close()
    result: dict[str, Any] = {
        "minutes": round(wall / 60, 2),
        "interval_s": args.interval,
        "warmup_s": args.warmup,
        "resolution": f"{args.width}x{args.height}",
    }
    for name, rc, log, marker in (
        ("sender", rc_sender, sender_log, "done:"),
        ("receiver", rc_receiver, receiver_log, "final:"),
    ):
        result[name] = summarise(samples[name], args.warmup) if samples[name] else {"samples": 0}
        result[name]["exit_code"] = rc
        result[name]["final_line"] = _last(log, marker)
        if name in died:
            result[name]["died_at_s"] = died[name]
            result[name]["log_tail"] = log.read_text(errors="replace")[-2000:]
    verdicts = {}
    for name in ("sender", "receiver"):
        r = result[name]
        if r.get("samples"):
            verdicts[name] = {
                # The level, not last minus first: RSS wanders by megabytes between samples (module doc).
                "rss_growth_below_5mb": r["rss_mb"]["growth_window_median"] < TARGET_RSS_GROWTH_MB_PER_30MIN,
                "no_fd_growth": r["fds"]["growth_window_median"] <= 0,
                "ran_throughout": name not in died and r["exit_code"] == 0,
            }
    result["verdicts"] = verdicts
    result["ok"] = bool(verdicts) and all(all(v.values()) for v in verdicts.values())
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=30.0, help="how long to run after both have started")
    p.add_argument("--interval", type=float, default=5.0, help="seconds between samples (default 5)")
    p.add_argument("--warmup", type=float, default=60.0, help="seconds left out of the growth (default 60)")
    p.add_argument("--width", type=int, default=960)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--samples", metavar="FILE", help="also write every sample to FILE (JSON lines)")
    args = p.parse_args(argv)
    if not args.minutes > 0 or not args.interval > 0 or args.warmup < 0:
        p.error("--minutes and --interval must be positive, --warmup not negative")
    load_before = [round(v, 2) for v in os.getloadavg()]
    with tempfile.TemporaryDirectory(prefix="ipt-soak-") as tmp:
        result = soak(args, Path(tmp))
    out = {"benchmark": "soak", "cpu_count": os.cpu_count(), "loadavg_before": load_before, **result}
    out["loadavg_after"] = [round(v, 2) for v in os.getloadavg()]
    json.dump(out, sys.stdout, indent=1)
    print()
    return 0 if result["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
