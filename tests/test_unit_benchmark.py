"""benchmarks/unit_kernels.py: how it restricts a command as the systemd unit would (W^X, a read-only file system
but the cache folder, one core), and its one-line refusal of a ``--live`` folder that holds no recording."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from benchmodule import BENCHMARKS, load_benchmark


def test_a_restricted_command_is_pinned_timed_then_read_only_then_wx() -> None:
    bench = load_benchmark("unit_kernels")
    plain = bench._restricted(["prog", "arg"], False, None)
    assert plain == ["taskset", "-c", "0", "/usr/bin/time", "-f", "%U %S", "prog", "arg"]
    both = bench._restricted(["prog"], True, "/cache")
    assert both[:6] == plain[:6]
    # the mount namespace outermost (its shell then runs the W^X wrapper, which execs the command)
    assert both[6:11] == ["unshare", "-m", "sh", "-c", bench.READ_ONLY]
    assert both[11] == "/cache"
    assert both[12:14] == [sys.executable, "-c"]
    assert "prctl(65, 1" in both[14]
    assert both[15:] == ["prog"]


def test_a_live_folder_without_a_recording_is_refused_in_one_line(tmp_path: Path) -> None:
    (tmp_path / "camera.yaml").write_text("{}\n", encoding="utf-8")
    result = subprocess.run(
        [sys.executable, str(BENCHMARKS / "unit_kernels.py"), "--video", str(tmp_path), "--camera",
         str(tmp_path / "camera.yaml"), "--config", str(tmp_path / "arena.yaml"), "--live", str(tmp_path)],
        capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert result.returncode == 2
    assert result.stdout == ""
    assert "Traceback" not in result.stderr
    assert f"--live {tmp_path}: no frames.mkv there" in result.stderr.strip().splitlines()[-1]
