"""The scenario suite's ``--tracker`` (benchmarks/suite.py): the ipt profile's receiver with the tracker chosen, the
paper profile untouched, and a bad value refused in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import suite

SUITE = Path(__file__).resolve().parents[1] / "benchmarks" / "suite.py"


def test_the_ipt_profile_takes_the_tracker_chosen_and_keeps_its_own_without() -> None:
    assert suite.receiver_config("ipt", False, "sparse").tracker == "sparse"
    assert suite.receiver_config("ipt", True, "sparse").pose.track.rolling_shutter
    assert suite.receiver_config("ipt", False).tracker == suite.PipelineConfig.profile("ipt").tracker
    assert suite.receiver_config("paper", False, "sparse") == suite.PipelineConfig.profile("paper")


def test_an_unknown_tracker_is_refused_in_one_line(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, str(SUITE), "--tracker", "fast", "--cache", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 2
    assert "--tracker" in done.stderr
    assert "Traceback" not in done.stderr
    assert list(tmp_path.iterdir()) == []
