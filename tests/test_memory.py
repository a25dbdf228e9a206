"""ipt.memory: with the thresholds fixed, a freed frame buffer is reused without faulting its pages again.

Run in a subprocess: mallopt changes the whole process, and the page-fault counts must not see pytest's
own allocations.
"""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

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
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], capture_output=True, text=True, timeout=60, check=True)
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
