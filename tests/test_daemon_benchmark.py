"""benchmarks/daemon.py's split of the live latency at one second after the first pose (issue 29, target 3): the
start-up's poses (acquisition, the chain's first restarts while a one-core pipeline catches up) apart from the rest."""

from __future__ import annotations

from types import ModuleType

from benchmodule import load_benchmark


def _bench() -> ModuleType:
    return load_benchmark("daemon")


def test_the_latency_is_split_one_second_after_the_first_pose() -> None:
    period_us = 8_333
    first = [(1_000_000 + k * period_us, 100.0 - k) for k in range(60)]  # late: the pipeline catching up
    rest = [(1_000_000 + k * period_us, 4.0 + (k % 3)) for k in range(121, 481)]
    split = _bench()._latency_split(first + rest)
    assert split["latency_first_second"]["poses"] == 60
    assert split["latency_first_second"]["over_30ms"] == 60
    after = split["latency_after_first_second"]
    assert after["poses"] == 360
    assert after["p50_ms"] == 5.0
    assert after["max_ms"] == 6.0
    assert after["over_30ms"] == 0
    assert split["poses_over_30ms"] == 60


def test_no_pose_sent_gives_no_split() -> None:
    assert _bench()._latency_split([]) == {}
