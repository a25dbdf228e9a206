"""ipt.memory: with the thresholds fixed, a freed frame buffer is reused without faulting its pages again: the
sender's 12 MB frames, and the receiver's (its defaults) 3 MB arrays made and freed frame after frame; the user's own
``MALLOC_*`` settings win.

Run in a subprocess: mallopt changes the whole process, and the page-fault counts must not see pytest's
own allocations.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from ipt.memory import USER_SETTINGS

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc", reason="mallopt is glibc's"
)

_PROBE = r"""
import json, resource, sys
import numpy as np
from ipt.memory import keep_freed_memory, warm

shape = (2160, 1920, 3)  # 12.4 MB, a 1920x2160 projector frame
keep = sys.argv[1] == "keep"
took = keep_freed_memory(int(np.prod(shape)), 16 * int(np.prod(shape))) if keep else None
warm(shape, 1)  # one frame made and freed, as before the sender's clock starts

def faults_of_next_frames(n):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(n):
        a = np.empty(shape, np.uint8)
        a.fill(1)
        del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

print(json.dumps({"took": took, "faults": faults_of_next_frames(5)}))
"""


def _run(mode: str) -> dict[str, int]:
    env = {k: v for k, v in os.environ.items() if k not in USER_SETTINGS}
    out = subprocess.run(
        [sys.executable, "-c", _PROBE, mode], env=env, capture_output=True, text=True, timeout=60, check=True
    )
    result: dict[str, int] = json.loads(out.stdout)
    return result


def test_kept_memory_is_reused_without_page_faults() -> None:
    kept, default = _run("keep"), _run("default")
    assert kept["took"] is True
    pages_per_frame = 2160 * 1920 * 3 // 4096
    # Five frames written after the warm-up reuse its memory: far fewer faults than one frame's pages (a
    # fresh 12 MB frame faults about 3,000 pages in).
    assert kept["faults"] < pages_per_frame // 10, kept
    # glibc's default, for reference, hands part of it back and faults it in again (483 pages here).
    assert default["faults"] > kept["faults"], (default, kept)


# The receiver's frames' arrays come and go: five blocks of 3 MB made and freed, twenty times over, after one round to
# warm up. Without the thresholds glibc gives the freed heap top back to the kernel, and each round faults it in again.
_RECEIVER_PROBE = """
import resource, sys
import numpy as np
from ipt.memory import keep_freed_memory
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


def _receiver_faults(env: dict[str, str]) -> tuple[str, int]:
    out = subprocess.run(
        [sys.executable, "-c", _RECEIVER_PROBE], env=env, capture_output=True, text=True, timeout=120, check=True
    ).stdout.split()
    return out[0], int(out[1])


def test_the_receivers_freed_arrays_are_kept_unless_the_user_set_the_thresholds() -> None:
    env = {k: v for k, v in os.environ.items() if k not in USER_SETTINGS}
    set_here, kept = _receiver_faults(env)
    assert set_here == "True"
    # The user's own setting wins: the same thresholds as glibc's defaults, then no call of ours.
    told, default = _receiver_faults(
        {**env, "MALLOC_TRIM_THRESHOLD_": str(128 * 1024), "MALLOC_MMAP_THRESHOLD_": "131072"}
    )
    assert told == "False"
    assert kept < 500  # 25 blocks of 3 MB made again after the first round: nothing faulted in afresh
    assert default > 20 * 3 * 2**20 // 4096  # glibc's defaults: at least one 3 MB block faulted in every round
