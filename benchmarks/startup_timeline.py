"""When each step of the receiver daemon's start-up happens: wall-clock and processor time of the process.

    python benchmarks/startup_timeline.py run --camera DIR/camera.yaml --source video:DIR/frames.mkv \\
        --fps 120 --realtime --max-frames 40 --send 127.0.0.1:9

Runs ``ipt-receiver`` with the given arguments in this process and prints a line to stderr at each step:
the CLI and the daemon imported, the pipeline made, numba's kernels made (``kernels.ensure``) and loaded
from the cache (``kernels.warm``), the first frame processed and the first pose computed. ``cpu`` is the
processor time of the whole process (every thread; the AprilTag helper process is not counted). The
start-up is bound by the interpreter lock, so on a quiet machine the processor time is close to the
wall-clock one; on a busy one it is the figure to compare.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import Any

T0 = time.monotonic()


def mark(what: str) -> None:
    wall, cpu = time.monotonic() - T0, time.process_time()
    sys.stderr.write(f"startup: wall {wall:6.3f} s  cpu {cpu:6.3f} s  [{threading.current_thread().name}] {what}\n")


def _wrap(owner: Any, name: str, label: str) -> None:
    original: Callable[..., Any] = getattr(owner, name)

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        mark(f"{label} start")
        result = original(*args, **kwargs)
        mark(f"{label} done")
        return result

    setattr(owner, name, wrapped)


def main() -> int:
    mark("python up")
    from ipt.receiver import cli
    from ipt.receiver.core import kernels

    mark("cli imported")
    _wrap(kernels, "ensure", "kernels.ensure")
    _wrap(kernels, "warm", "kernels.warm")
    from ipt.receiver.core.pipeline import Pipeline

    mark("daemon's pipeline imported")
    _wrap(Pipeline, "__init__", "Pipeline made")
    process = Pipeline.process
    state = {"first": True, "posed": False}

    def process_marked(self: Pipeline, *args: Any) -> Any:
        if state["first"]:
            mark("first frame")
            state["first"] = False
        results = process(self, *args)
        if not state["posed"] and any(r.pose is not None for r in results):
            mark("first pose computed")
            state["posed"] = True
        return results

    Pipeline.process = process_marked  # type: ignore[method-assign]
    return cli.main(sys.argv[1:])


if __name__ == "__main__":
    sys.exit(main())
