"""The A/B benchmark of two checkouts' whole-process replays (benchmarks/replay_ab.py): its summary of the pairs,
its flight names, and its one-line refusals of a wrong checkout or flight (the script run as a user runs it)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from benchmodule import BENCHMARKS

sys.path.insert(0, str(BENCHMARKS))
import replay_ab


def _run(side: str, fps: float, digest: str = "a") -> dict[str, object]:
    return {"checkout": side, "frames_per_cpu_s": fps, "poses_sha256": digest}


def test_the_summary_pairs_each_base_run_with_its_new_run_whatever_their_order() -> None:
    runs = [_run("base", 200.0), _run("new", 220.0), _run("new", 250.0), _run("base", 200.0), _run("base", 100.0),
            _run("new", 300.0)]  # fmt: skip
    s = replay_ab.summary(runs)
    assert s["base_median"] == 200.0
    assert s["new_median"] == 250.0
    assert s["ratio_median"] == 1.25
    assert s["ratio_range"] == [1.1, 3.0]
    assert s["same_poses"] is True


def test_one_run_that_wrote_other_poses_is_told() -> None:
    assert replay_ab.summary([_run("base", 1.0), _run("new", 1.0, "b")])["same_poses"] is False


def test_flights_are_found_in_the_suite_and_the_held_out_folder() -> None:
    assert replay_ab.flight_file("fast").parent.name == "flights"
    assert replay_ab.flight_file("hover-1.9m-cuts").parent.name == "heldout"


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--base", "NOWHERE"], "holds no ipt package"),
        (["--base", ".", "--flights", "no-such-flight"], "no flight 'no-such-flight'"),
        (["--base", ".", "--pairs", "0"], "--pairs must be 1 to 50"),
    ],
)
def test_bad_arguments_get_one_line_and_no_traceback(tmp_path: Path, args: list[str], says: str) -> None:
    root = BENCHMARKS.parent
    done = subprocess.run(
        [sys.executable, str(BENCHMARKS / "replay_ab.py"), *[str(root) if a == "." else a for a in args],
         "--cache", str(tmp_path)], capture_output=True, text=True, timeout=120, check=False, cwd=tmp_path,
    )  # fmt: skip
    assert done.returncode != 0
    assert says in done.stderr
    assert "Traceback" not in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
