"""Peak memory of the tools given an image bomb: a 20000x20000 PNG of about 0.4 MB (issue 33 item 2).

Makes the bomb (a valid PNG, written row by row through zlib, so that making it takes no memory), then runs
each tool in a subprocess under ``/usr/bin/time -v`` and reports its exit status, wall time, maximum resident
set size and last line:

- ``replay``: ``ipt-receiver replay`` over a folder of three 64x48 frames with the bomb first (target: at
  most 700 MB);
- ``sender-image``: ``ipt-sender --image bomb.png --sink file --frames 30`` (target: refused with one line, at
  most 2 GB);
- ``sender-video``: ``ipt-sender --video FOLDER --sink file --frames 30`` over the same folder (target: the
  bomb skipped and said, at most 2 GB).

Prints one JSON object. The code measured is the one ``python -m ipt...`` imports: set ``PYTHONPATH`` to
another checkout to measure it (``PYTHONPATH=/path/to/old/checkout python benchmarks/image_bomb.py``).

    ./dev run python benchmarks/image_bomb.py
"""

from __future__ import annotations

import json
import os
import re
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ipt.config.camera_info import CameraInfo, save_camera_info
from ipt.imageio import write_image

SIDE_PX = 20000
ARENA = {
    "projector": {"width_px": 320, "height_px": 288, "rate_hz": 60},
    "screen": {"width_m": 1.0, "height_m": 0.9},
    "tag_map": {"rows": 2, "cols": 2, "tag_size_px": 64},
    "modulation": {"delta_l": 8, "input_rate_hz": 30},
}
CAMERA = CameraInfo(width_px=64, height_px=48, fx_px=60.0, fy_px=60.0, cx_px=31.5, cy_px=23.5, name="bomb")
TARGETS_MB = {"replay": 700, "sender-image": 2048, "sender-video": 2048}


def write_bomb(path: Path, side_px: int = SIDE_PX) -> None:
    """A valid grey PNG of ``side_px`` x ``side_px`` black pixels, compressed row by row."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    packer = zlib.compressobj(9)
    row = bytes(side_px + 1)  # filter byte 0, then the row
    parts = [packer.compress(row) for _ in range(side_px)]
    parts.append(packer.flush())
    ihdr = struct.pack(">IIBBBBB", side_px, side_px, 8, 0, 0, 0, 0)
    idat = chunk(b"IDAT", b"".join(parts))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + idat + chunk(b"IEND", b""))


def timed(args: list[str], cwd: Path) -> dict[str, Any]:
    """``args`` run under /usr/bin/time -v: status, seconds, max RSS (MB), the tool's last stderr line."""
    t0 = time.monotonic()
    proc = subprocess.run(
        ["/usr/bin/time", "-v", sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, check=False,
        timeout=300, stdin=subprocess.DEVNULL,
    )  # fmt: skip
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    tool_lines = [line for line in proc.stderr.splitlines() if not line.startswith("\t") and "Command " not in line]
    return {
        "exit_status": proc.returncode,
        "seconds": round(time.monotonic() - t0, 2),
        "max_rss_mb": round(int(rss.group(1)) / 1024, 1) if rss else None,
        "lines": [line for line in tool_lines if "20000" in line or "error" in line or "done" in line][-3:],
    }


def main() -> int:
    with tempfile.TemporaryDirectory(prefix="ipt-bomb-") as tmp:
        z = Path(tmp)
        (z / "arena.yaml").write_text(yaml.safe_dump(ARENA), encoding="utf-8")
        save_camera_info(CAMERA, z / "camera.yaml")
        write_bomb(z / "bomb.png")
        folder = z / "frames"
        folder.mkdir()
        os.link(z / "bomb.png", folder / "frame_000.png")
        for k in range(1, 4):
            write_image(folder / f"frame_{k:03d}.png", np.full((48, 64, 3), 60 * k, np.uint8))
        runs = {
            "replay": ["ipt.receiver.cli", "replay", "--config", "arena.yaml", "--camera", "camera.yaml", "--video",
                       "frames", "--fps", "120", "--output", "poses.tum"],
            "sender-image": ["ipt.sender.cli", "--config", "arena.yaml", "--image", "bomb.png", "--sink", "file",
                             "--frames", "30", "--output", "image.mkv"],
            "sender-video": ["ipt.sender.cli", "--config", "arena.yaml", "--video", "frames", "--sink", "file",
                             "--frames", "30", "--output", "out.mkv"],
        }  # fmt: skip
        result: dict[str, Any] = {
            "benchmark": "image_bomb",
            "bomb": f"{SIDE_PX}x{SIDE_PX} grey PNG, {(z / 'bomb.png').stat().st_size / 1e6:.2f} MB",
            "pythonpath": os.environ.get("PYTHONPATH"),
            "load_avg_1min_before": round(os.getloadavg()[0], 2),
        }
        for name, args in runs.items():
            out = timed(args, z)
            out["within_target"] = out["max_rss_mb"] is not None and out["max_rss_mb"] <= TARGETS_MB[name]
            result[name] = out
        result["load_avg_1min_after"] = round(os.getloadavg()[0], 2)
    json.dump(result, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
