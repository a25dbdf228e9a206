"""The allocator keeps what a frame frees (ipt/receiver/allocator.py): measured as page faults in fresh processes."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from ipt.receiver import allocator

# Frames' arrays come and go: five blocks of 3 MB made and freed, twenty times over, after one round to warm up.
# Without the thresholds glibc gives the freed heap top back to the kernel, and each round faults it in again.
PROGRAM = """
import resource, sys
import numpy as np
from ipt.receiver.allocator import keep_freed_memory
print(keep_freed_memory())
def one_round():
    blocks = [np.ones(3 * 2**20 // 8) for _ in range(5)]
    del blocks
one_round()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(20):
    one_round()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(env: dict[str, str]) -> tuple[str, int]:
    out = subprocess.run(
        [sys.executable, "-c", PROGRAM], env=env, capture_output=True, text=True, timeout=120, check=True
    ).stdout.split()
    return out[0], int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_the_freed_frames_memory_is_kept_and_not_faulted_in_again() -> None:
    env = {k: v for k, v in os.environ.items() if k not in allocator.USER_SETTINGS}
    set_here, kept = _faults(env)
    if set_here != "True":
        pytest.skip("this C library has no mallopt (not glibc)")
    # The user's own setting wins: the same thresholds as glibc's defaults, then no call of ours.
    told, default = _faults({**env, "MALLOC_TRIM_THRESHOLD_": str(128 * 1024), "MALLOC_MMAP_THRESHOLD_": "131072"})
    assert told == "False"
    assert kept < 500  # 25 blocks of 3 MB made again after the first round: nothing faulted in afresh
    assert default > 20 * 3 * 2**20 // 4096  # glibc's defaults: at least one 3 MB block faulted in every round
