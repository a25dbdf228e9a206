"""Two checkouts' receivers on the same flights, whole process, one core: frames per processor-second measured in
alternating pairs, and whether both wrote the same poses to the byte (issue 29: the A/B of a speed-up).

    python benchmarks/replay_ab.py --base CHECKOUT [--new CHECKOUT] [--flights shadow-vibration,fast] [--pairs 3]

``CHECKOUT``: a folder holding another version's ``ipt`` package, e.g. ``git worktree add /tmp/base 0e34c44``
(``--new`` defaults to this checkout). Each flight is a name from ``benchmarks/flights`` or ``benchmarks/heldout``,
rendered as the suite renders it (into ``--cache``, kept for the next run) and written once as BMP frames; each
checkout's kernels are warmed into a folder of ``--cache`` of its own first, as the systemd unit's
``ipt-receiver warm`` does. Then, pair after pair, ``ipt-receiver replay`` of the frames runs as a process of its own
pinned to core 0 and timed by ``/usr/bin/time`` (user + sys, its AprilTag helper included: the suite's whole-process
column, ``suite.whole_process``), base and new in turn, the order swapped from one pair to the next so that a change
in the machine's load hits both alike. This machine's time is noisy (a shared host): quote the medians and the pairs'
ratios of one run, with its load.

JSON on stdout: for each flight every run (which checkout, frames per processor-second, user and sys seconds, the
load average when it started, the SHA-256 of the poses file, how the kernels were loaded), the median of each
checkout's runs, the median and the range of the pairs' ratios new / base, and ``same_poses``: whether every run of
both wrote the same bytes (a speed-up that claims to leave the poses alone must show true). Progress goes to stderr.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

import suite

from ipt.config.models import load_arena_config, load_yaml_model, shipped_config_path
from ipt.sim.config import SimConfig, apply_arena_changes

HELDOUT = suite.ROOT / "benchmarks" / "heldout"
DEFAULT_FLIGHTS = ("shadow-vibration", "moving-content", "realcam", "fast", "takeoff", "independent")
"""Issue 29 target 1's flights."""


def flight_file(name: str) -> Path:
    """The flight file called ``name`` in the suite's folder or the held-out one; one line if there is none."""
    for folder in (suite.FLIGHTS, HELDOUT):
        if (folder / f"{name}.yaml").is_file():
            return folder / f"{name}.yaml"
    have = sorted(p.stem for folder in (suite.FLIGHTS, HELDOUT) for p in folder.glob("*.yaml"))
    raise SystemExit(f"replay_ab: no flight {name!r} (have {', '.join(have)})")


def checkout(path: Path, option: str) -> Path:
    """``path`` if it holds an ``ipt`` package, else one line that says what is wrong."""
    if not (path / "ipt" / "receiver" / "cli.py").is_file():
        raise SystemExit(f"replay_ab: {option} {path} holds no ipt package (ipt/receiver/cli.py)")
    return path.resolve()


def summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Each checkout's median, the pairs' ratios new / base (the runs come in pairs, base and new in either order)
    and whether every run wrote the same poses."""
    fps = {side: [r["frames_per_cpu_s"] for r in runs if r["checkout"] == side] for side in ("base", "new")}
    ratios = [round(n / b, 3) for b, n in zip(fps["base"], fps["new"], strict=True)]
    return {
        "base_median": statistics.median(fps["base"]),
        "new_median": statistics.median(fps["new"]),
        "ratio_median": statistics.median(ratios),
        "ratio_range": [min(ratios), max(ratios)],
        "same_poses": len({r["poses_sha256"] for r in runs}) == 1,
    }


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", type=Path, required=True, help="checkout of the version to compare against")
    p.add_argument("--new", type=Path, help="checkout of the version measured (default: this one)")
    p.add_argument("--flights", default=",".join(DEFAULT_FLIGHTS), help="comma-separated flight names")
    p.add_argument("--pairs", type=int, default=3, help="pairs of runs per flight (default 3)")
    p.add_argument("--seconds", type=float, default=8.0, help="length of each flight (default 8, as the suite)")
    p.add_argument("--cache", type=Path, default=suite.DEFAULT_CACHE, help="where renderings and kernels are kept")
    args = p.parse_args()
    if not 1 <= args.pairs <= 50:
        raise SystemExit(f"replay_ab: --pairs must be 1 to 50, got {args.pairs}")
    base = checkout(args.base, "--base")
    new = checkout(args.new, "--new") if args.new is not None else None
    files = [flight_file(n) for n in args.flights.split(",") if n]
    if not files:
        raise SystemExit("replay_ab: --flights names no flight")
    shipped = load_arena_config(shipped_config_path("arena.yaml"))
    args.cache.mkdir(parents=True, exist_ok=True)
    digest = suite._source_digest()
    for tree in (base, new):  # both kernels' folders filled before the first timed run
        suite.kernel_env(args.cache, tree, suite.receiver_command(tree))
    out: dict[str, Any] = {"base": str(base), "new": str(new or suite.ROOT), "pairs": args.pairs, "flights": {}}
    for path in files:
        sim = load_yaml_model(path, SimConfig)
        folder = suite.render(path.stem, sim, apply_arena_changes(shipped, sim.arena), args.seconds, args.cache, digest)
        runs: list[dict[str, Any]] = []
        for pair in range(args.pairs):
            order = (("base", base), ("new", new)) if pair % 2 == 0 else (("new", new), ("base", base))
            for side, tree in order:
                r = suite.whole_process(folder, folder / "arena.yaml", "ipt", tree, args.cache)
                runs.append({"checkout": side, **{k: r[k] for k in ("frames_per_cpu_s", "user_s", "sys_s")},
                             "load_average": r["load_average"], "poses_sha256": r["poses_sha256"],
                             "kernels": r["kernels"]})  # fmt: skip
                print(f"replay_ab: {path.stem} pair {pair + 1}/{args.pairs} {side}: {r['frames_per_cpu_s']} frames "
                      f"per processor-second (load {r['load_average']})", file=sys.stderr, flush=True)  # fmt: skip
        out["flights"][path.stem] = {"runs": runs, **summary(runs)}
        s = out["flights"][path.stem]
        print(f"replay_ab: {path.stem}: {s['base_median']} -> {s['new_median']}, x{s['ratio_median']} "
              f"({s['ratio_range'][0]}-{s['ratio_range'][1]}), same poses: {s['same_poses']}",
              file=sys.stderr, flush=True)  # fmt: skip
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
