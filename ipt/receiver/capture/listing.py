"""``ipt-receiver --list-cameras``: which cameras this computer has."""

from __future__ import annotations

import re
from pathlib import Path

from ipt.receiver.capture.picamera import picamera2_cameras
from ipt.receiver.capture.v4l2 import probe_v4l2


def list_cameras(
    dev_dir: Path = Path("/dev"), sysfs_dir: Path = Path("/sys/class/video4linux"), *, probe: bool = True
) -> list[str]:
    """Lines saying which cameras are there: each V4L2 node (``/dev/videoN``, its name, and what OpenCV
    opens it at) and the picamera2 cameras. Never raises; what cannot be looked at is said."""
    lines = []
    nodes = sorted(
        (p for p in dev_dir.glob("video*") if re.fullmatch(r"video[0-9]+", p.name)), key=lambda p: int(p.name[5:])
    )
    for node in nodes:
        n = int(node.name[5:])
        try:
            label = (sysfs_dir / node.name / "name").read_text(encoding="utf-8", errors="replace").strip()
        except OSError:
            label = "?"
        what = probe_v4l2(n) if probe else "not opened"
        lines.append(f"device:{n}  {node}  {label or '?'}: {what}")
    if not nodes:
        lines.append(f"V4L2: no cameras ({dev_dir}/video* absent)")
    else:
        usable = sum("frames" in line for line in lines)
        lines.append(f"V4L2: {len(nodes)} node(s), {usable} giving frames (a USB camera also has metadata nodes)")
    lines.append(picamera2_cameras())
    return lines
