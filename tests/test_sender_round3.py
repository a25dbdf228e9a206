"""Issue 33 (round three), the sender's items: a stop signal while the colour table is built (10), image
bombs (2), content that stalls the sender (3) and the loop seam of a video (5)."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from waiting import wait_until

TINY_ARENA = """\
projector: {width_px: 320, height_px: 288, rate_hz: 60}
screen: {width_m: 1.0, height_m: 0.9}
tag_map: {rows: 2, cols: 2, tag_size_px: 64}
modulation: {delta_l: 8, input_rate_hz: 30, profile: ipt}
"""


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "ipt.sender.cli", *args]


def _wait_for(log: Path, pattern: str, timeout_s: float) -> re.Match[str]:
    def found() -> re.Match[str] | None:
        return re.search(pattern, log.read_text(encoding="utf-8", errors="replace"))

    with contextlib.suppress(AssertionError):  # said below, with the log
        wait_until(found, timeout_s)
    if (m := found()) is None:
        raise AssertionError(f"{pattern!r} not seen in {timeout_s} s:\n{log.read_text(errors='replace')}")
    return m


# --- item 10: a stop signal while the colour table is computed -------------------------------------


def _stop_while_building(tmp_path: Path, sig: signal.Signals) -> tuple[int, float, str]:
    arena = tmp_path / "arena.yaml"
    arena.write_text(TINY_ARENA, encoding="utf-8")
    log = tmp_path / "stderr.txt"
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}  # an empty cache: the table is computed
    with log.open("w") as err:
        proc = subprocess.Popen(
            _cli("--config", str(arena), "--sink", "null"), stdout=subprocess.DEVNULL, stderr=err, env=env
        )
    try:
        _wait_for(log, r"colour table: computing", 60)  # said once the build began (several seconds on two cores)
        t0 = time.monotonic()
        proc.send_signal(sig)
        rc = proc.wait(timeout=30)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return rc, took, log.read_text(encoding="utf-8")


def test_sigterm_while_the_colour_table_is_built_stops_promptly(tmp_path: Path) -> None:
    rc, took, text = _stop_while_building(tmp_path, signal.SIGTERM)
    assert took < 1.5, f"took {took:.2f} s to stop:\n{text}"
    assert rc == 0, text
    assert "Traceback" not in text, text
    assert "done:" in text.strip().splitlines()[-1], text
    assert not list((tmp_path / "cache").glob("**/pairs-*.bin")), "an incomplete table was cached"


def test_sigint_while_the_colour_table_is_built_stops_promptly(tmp_path: Path) -> None:
    rc, took, text = _stop_while_building(tmp_path, signal.SIGINT)
    assert took < 1.5, f"took {took:.2f} s to stop:\n{text}"
    assert rc == 0, text
    assert "Traceback" not in text, text
